"""From two corner half-chip frames to one corner wavefront: select, pair, estimate, combine.

This is the multi-star strategy the paper leaves open (Xin et al. 2015, Fig. 2 caption):

1. :func:`select_stamps` finds the donuts of one half-chip frame
   (:mod:`.detection`: sky, matched filter, rejection of edge-cut, saturated, blended and
   too-faint donuts), cuts a stamp around each accepted one and computes its star's field
   angle from its pixel position (:mod:`.field_position`).
2. :func:`pair_stars` pairs intra stars with extra stars (different stars on the two halves,
   §3.4): by brightness rank (default: the brightest with the brightest, which keeps the pairs'
   S/N balanced) or by position on the half-chip.
3. Every pair is estimated with each star's own field (``field_intra_deg``,
   ``field_extra_deg``), so the off-axis correction (§3.3) is that of the star, not of the
   half-chip centre.  Caustic and failed pairs are dropped and reported.
4. :func:`cwfs_ros.frames.combination.combine_pairs` combines the pairs' departures from design
   with outlier rejection and adds the design wavefront at the corner's reference field back.

:func:`estimate_corner_frames` runs the four steps; :func:`run_corner_frame_job` is its
never-raising, picklable wrapper for a worker process (like
:func:`cwfs_ros.runtime.corner_pool.run_corner_job` for stamp pairs).  No ROS imports.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cwfs_ros.config import config_dir
from cwfs_ros.errors import ConfigError, CwfsError, FrameSizeError, ImageError
from cwfs_ros.frames.combination import (
    CombinationConfig,
    CombinedEstimate,
    combine_pairs,
    pair_noise_scale,
)
from cwfs_ros.frames.detection import (
    REASONS,
    Background,
    DetectedDonut,
    DetectionConfig,
    cut_stamp,
    detect_donuts,
    expected_donut_radii_px,
)
from cwfs_ros.frames.field_position import HalfChip, half_chip_model, load_half_chips
from cwfs_ros.layout import NOLL as _NOLL
from cwfs_ros.wfs.instrument import load_instrument
from cwfs_ros.wfs.orientation import orient_image
from cwfs_ros.wfs.settings import EstimatorSettings

__all__ = [
    "SelectionConfig",
    "load_selection_config",
    "StarStamp",
    "PairResult",
    "CornerFrameResult",
    "CornerFrameJob",
    "select_stamps",
    "frame_window",
    "pair_stars",
    "estimate_pairs",
    "estimate_corner_frames",
    "run_corner_frame_job",
    "PAIRING_METHODS",
]

PAIRING_METHODS = ("brightness", "position")
_DEFAULT_SETTINGS = EstimatorSettings()
_DONUT_REASONS = frozenset(REASONS)


@dataclass(frozen=True)
class SelectionConfig:
    """Parameters of the frame pipeline (``config/selection.yaml``).

    Attributes:
        detection: detector parameters (:class:`~.detection.DetectionConfig`).
        combination: noise model and clipping (:class:`~.combination.CombinationConfig`).
        max_pairs: at most this many pairs are estimated per corner (each costs an
            estimate, plus a geometry build for a new pair of fields).
        pairing: ``"brightness"`` (rank with rank) or ``"position"`` (each intra star with
            the extra star at the nearest position relative to its own half-chip's centre).
    """

    detection: DetectionConfig = field(default_factory=DetectionConfig)
    combination: CombinationConfig = field(default_factory=CombinationConfig)
    max_pairs: int = 4
    pairing: str = "brightness"

    def __post_init__(self) -> None:
        if not isinstance(self.max_pairs, int) or self.max_pairs < 1:
            raise ConfigError(f"selection: max_pairs must be an integer >= 1, got "
                              f"{self.max_pairs!r}")
        if self.pairing not in PAIRING_METHODS:
            raise ConfigError(f"selection: pairing must be one of {PAIRING_METHODS}, got "
                              f"{self.pairing!r}")


@lru_cache(maxsize=4)
def _selection_yaml(path: str, mtime: float) -> dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read selection file {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"selection file {path} must hold a mapping")
    return data


def load_selection_config(path: str | Path | None = None, *, solver: str | None = None,
                          **overrides: Any) -> SelectionConfig:
    """Read ``config/selection.yaml`` (or ``path``).

    Args:
        path: YAML file; default ``config/selection.yaml``.
        solver: the TIE solver the estimates use; its ``combination.noise_model.<solver>``
            entry (if any) supplies the noise coefficients and floors.
        **overrides: top-level fields (``max_pairs``, ``pairing``).
    """
    p = Path(path) if path is not None else config_dir() / "selection.yaml"
    if not p.is_file():
        # Not the built-in defaults: the file holds the fitted noise model and the
        # detection limits, and a mistyped path must not quietly change them.
        raise ConfigError(f"selection file {p} not found")
    data = _selection_yaml(str(p), p.stat().st_mtime)
    try:
        det = DetectionConfig(**(data.get("detection") or {}))
        comb_data = dict(data.get("combination") or {})
        models = comb_data.pop("noise_model", None) or {}
        if solver is not None and solver in models:
            comb_data.update(models[solver])
        comb = CombinationConfig(**comb_data)
        top = {k: v for k, v in data.items() if k not in ("detection", "combination")}
        top.update({k: v for k, v in overrides.items() if v is not None})
        return SelectionConfig(detection=det, combination=comb, **top)
    except TypeError as exc:
        raise ConfigError(f"selection file {p}: {exc}") from exc


@dataclass(frozen=True)
class StarStamp:
    """An accepted donut, its stamp and its star's field.

    Attributes:
        side: ``"intra"`` or ``"extra"``.
        donut: the detection (centroid, flux, S/N ...).
        stamp: sky-subtracted stamp (float64), focal-plane orientation.
        origin_px: frame pixel (col, row) of ``stamp[0, 0]`` (oriented frame).
        field_deg: the star's field angle (deg).
    """

    side: str
    donut: DetectedDonut
    stamp: np.ndarray = field(repr=False)
    origin_px: tuple[int, int]
    field_deg: tuple[float, float]


def select_stamps(frame: np.ndarray, half: HalfChip, *, instrument: str = "lsst",
                  band: str = "r", config: SelectionConfig | None = None, pad_px: int = 0,
                  full_scale: float | None = None
                  ) -> tuple[list[StarStamp], list[DetectedDonut], Background]:
    """Detect the donuts of one half-chip frame, cut the accepted ones, give their fields.

    Args:
        frame: the frame as read out (``half.orientation`` brings it to the focal plane).
        half: which half-chip (field point, offset, orientation; :func:`load_half_chips`).
        instrument, band: optical model (donut radii, stamp size, plate scale).
        config: selection parameters.
        pad_px: the stamps are cut ``pad_px`` larger on every side than the instrument's
            stamp size (real pixels, rather than :func:`cwfs_ros.wfs.orientation.pad_stamp`'s fill).
        full_scale: the top of the frame's integer range as sent (None: floats): a donut
            with a pixel there is ``saturated`` even when the configured level is higher.

    Returns:
        ``(stamps, detections, background)``: the accepted stars, brightest first; every
        detection with its status; the sky model.
    """
    cfg = config or SelectionConfig()
    inst = load_instrument(instrument)
    img = orient_image(np.asarray(frame), half.orientation)
    r_out, r_in = expected_donut_radii_px(inst, abs(half.detector_offset_mm))
    stamp_px = int(inst.stamp_size_px) + 2 * int(pad_px)
    det_cfg = cfg.detection
    inst_sat = getattr(inst, "saturation_level", None)
    if det_cfg.saturation_level is None and inst_sat is not None:
        # No level of its own: the instrument's (the estimator's stamps, same units).
        det_cfg = det_cfg.with_overrides(saturation_level=float(inst_sat))
    if full_scale is not None and not (det_cfg.saturation_level or np.inf) <= full_scale:
        # The converter clips there: such a pixel's true value is unknown.
        det_cfg = det_cfg.with_overrides(saturation_level=float(full_scale))
    dets, bg = detect_donuts(img, outer_radius_px=r_out, inner_radius_px=r_in,
                             stamp_px=stamp_px, config=det_cfg, name=half.side)
    model = half_chip_model(half, inst, band, shape_px=img.shape)
    stamps = []
    for d in sorted((d for d in dets if d.ok), key=lambda d: -d.snr):
        st, origin = cut_stamp(img, d.x, d.y, stamp_px, bg)
        stamps.append(StarStamp(half.side, d, st, origin, model.field_of_centroid(d.x, d.y)))
    return stamps, dets, bg


def pair_stars(intra: list[StarStamp], extra: list[StarStamp], *, max_pairs: int = 4,
               method: str = "brightness",
               centres_deg: tuple[tuple[float, float], tuple[float, float]] | None = None
               ) -> list[tuple[StarStamp, StarStamp]]:
    """Pair intra stars with extra stars (each star used once).

    Args:
        intra, extra: accepted stars of the two halves.
        max_pairs: at most this many pairs (the brightest, by the fainter star's S/N).
        method: ``"brightness"``: k-th brightest intra with k-th brightest extra.
            ``"position"``: minimise the summed distance between the stars' positions
            relative to their own half-chip's field point (``centres_deg`` = (intra, extra)
            field points), so that each pair's two stars see similar vignetting.
    """
    if method not in PAIRING_METHODS:
        raise ConfigError(f"pairing must be one of {PAIRING_METHODS}, got {method!r}")
    a = sorted(intra, key=lambda s: -s.donut.snr)
    b = sorted(extra, key=lambda s: -s.donut.snr)
    n = min(len(a), len(b))
    if n == 0:
        return []
    if method == "brightness":
        pairs = list(zip(a[:n], b[:n], strict=True))
    else:
        from scipy.optimize import linear_sum_assignment

        ci, ce = centres_deg if centres_deg is not None else ((0.0, 0.0), (0.0, 0.0))
        pa = np.array([[s.field_deg[0] - ci[0], s.field_deg[1] - ci[1]] for s in a])
        pb = np.array([[s.field_deg[0] - ce[0], s.field_deg[1] - ce[1]] for s in b])
        cost = np.hypot(pa[:, None, 0] - pb[None, :, 0], pa[:, None, 1] - pb[None, :, 1])
        ri, rj = linear_sum_assignment(cost)
        pairs = [(a[i], b[j]) for i, j in zip(ri, rj, strict=True)]
    pairs.sort(key=lambda p: -min(p[0].donut.snr, p[1].donut.snr))
    return pairs[:max_pairs]


@dataclass(frozen=True)
class PairResult:
    """One intra/extra pair's estimate and fate.

    Attributes:
        index: rank of the pair (0 = brightest).
        intra_xy, extra_xy: donut centroids (col, row) on the oriented frames.
        field_intra_deg, field_extra_deg, field_mid_deg: the stars' fields and mid-point.
        snr_intra, snr_extra: flux S/N of the two donuts; ``noise_scale`` their q.
        status: ``"ok"``, ``"caustic"``, or the estimator's error tag (``"<tag>"``).
        message: explanation when not ok.
        zernikes_nm: (19,) total wavefront Z4..Z22 at ``field_mid_deg`` (NaN if failed).
        intrinsic_nm: (19,) design wavefront at ``field_mid_deg`` (NaN if failed).
        used: contributed to the combination (False if failed, caustic or an outlier).
        iterations: outer iterations run; ``compute_ms`` wall time of the estimate
            (including a geometry build for a new pair of fields).
        swap_check: the estimator's swapped-pair outcome (``"confirmed"``,
            ``"inconclusive"``, ``"off"``), ``"skipped"`` when an earlier pair had confirmed
            the frames, ``""`` when the estimate failed (a swapped pair fails as such).
        warm_start: the outer loop started from the first good pair's departure.
        converged: the outer loop met its tolerance before its iteration limit.
    """

    index: int
    intra_xy: tuple[float, float]
    extra_xy: tuple[float, float]
    field_intra_deg: tuple[float, float]
    field_extra_deg: tuple[float, float]
    field_mid_deg: tuple[float, float]
    snr_intra: float
    snr_extra: float
    noise_scale: float
    status: str
    message: str
    zernikes_nm: np.ndarray
    intrinsic_nm: np.ndarray
    used: bool = False
    iterations: int = 0
    compute_ms: float = 0.0
    swap_check: str = ""
    warm_start: bool = False
    converged: bool = False

    @property
    def departure_nm(self) -> np.ndarray:
        """Departure from design, ``zernikes_nm - intrinsic_nm`` (nm)."""
        return self.zernikes_nm - self.intrinsic_nm


def estimate_pairs(pairs: list[tuple[StarStamp, StarStamp]],
                   settings: EstimatorSettings = _DEFAULT_SETTINGS, *,
                   warm_start: bool | None = None) -> list[PairResult]:
    """Estimate every pair with each star's own field; never raises for a bad pair.

    With ``warm_start`` (default: the solver's ``warm_start`` in ``config/algorithm.yaml``)
    the pairs after the first good one start their outer loop from its departure from
    design (``estimate_wavefront(initial_nm=...)``): the stars of one corner see nearly the
    same departure, so the loop converges in about half the iterations, to the same fixed
    point as from zero (docs/accuracy.md, Frames).  A warm start that folds into caustic is redone
    from zero.

    Which half is intra-focal is a property of the two frames, not of a star pair: once one
    pair's swapped-pair check (:func:`.checks.check_not_swapped`) has found the images the
    right way round beyond doubt, the corner's further pairs skip it (and the footprints it
    needs, ~4 ms a pair).  Until then every pair is checked, so exchanged frames are refused
    pair by pair, and an inconclusive pair confirms nothing.
    """
    from cwfs_ros.wfs.estimator import load_algorithm

    out = []
    kwargs = settings.estimator_kwargs()
    if warm_start is None:
        warm_start = load_algorithm(settings.solver).warm_start
    confirmed = False
    start = None  # the first good pair's departure: the later pairs' warm start
    for k, (si, se) in enumerate(pairs):
        t0 = time.perf_counter()
        common = _pair_identity(k, si, se)
        try:
            r = _estimate_pair(si, se, start, kwargs, common)
        except Exception as exc:  # noqa: BLE001 - one pair's failure drops that pair only
            out.append(_failed_pair(common, exc, (time.perf_counter() - t0) * 1e3))
            continue
        ms = (time.perf_counter() - t0) * 1e3
        common["swap_check"] = "skipped" if confirmed else r.swap_check
        if r.swap_check == "confirmed":
            confirmed = True
            kwargs = {**kwargs, "swap_check": False}
        out.append(_estimated_pair(common, r, ms))
        if out[-1].status == "ok" and start is None and warm_start:
            start = r.departure_all_nm
    return out


def _pair_identity(k: int, si: StarStamp, se: StarStamp) -> dict[str, Any]:
    """The fields of a :class:`PairResult` that describe the pair itself: rank, donut
    positions, the stars' fields and their mid-point, S/N and noise scale."""
    mid = (0.5 * (si.field_deg[0] + se.field_deg[0]),
           0.5 * (si.field_deg[1] + se.field_deg[1]))
    return dict(index=k, intra_xy=(si.donut.x, si.donut.y),
                extra_xy=(se.donut.x, se.donut.y), field_intra_deg=si.field_deg,
                field_extra_deg=se.field_deg, field_mid_deg=mid,
                snr_intra=si.donut.snr, snr_extra=se.donut.snr,
                noise_scale=pair_noise_scale(si.donut.snr, se.donut.snr))


def _estimate_pair(si: StarStamp, se: StarStamp, start: np.ndarray | None,
                   kwargs: dict[str, Any], common: dict[str, Any]) -> Any:
    """The estimate of one pair, each star at its own field (§3.3-3.4), from ``start`` if
    given.  A warm start that folds the compensation into caustic is redone from zero: the
    paper's cold start decides.  ``common["warm_start"]`` records which start the result
    (or the error of the redo) comes from."""
    from cwfs_ros.wfs.estimator import estimate_wavefront

    fields = dict(field_intra_deg=si.field_deg, field_extra_deg=se.field_deg)
    r = estimate_wavefront(si.stamp, se.stamp, initial_nm=start, **fields, **kwargs)
    common["warm_start"] = start is not None
    if start is not None and r.caustic:
        r = estimate_wavefront(si.stamp, se.stamp, **fields, **kwargs)
        common["warm_start"] = False
    return r


def _failed_pair(common: dict[str, Any], exc: Exception, ms: float) -> PairResult:
    """A pair whose estimate raised: the error's reason as its status (``internal_error``
    for a defect or a library's error, named so that the other pairs still count)."""
    if isinstance(exc, CwfsError):
        tag = str(getattr(exc, "reason", "") or ("config" if isinstance(exc, ConfigError)
                                                 else "bad_image"))
        text = str(exc)
    else:
        tag, text = "internal_error", f"{type(exc).__name__}: {exc}"
    nan = np.full(len(_NOLL), np.nan)
    return PairResult(**common, status=tag, message=text, zernikes_nm=nan,
                      intrinsic_nm=nan, compute_ms=ms)


def _estimated_pair(common: dict[str, Any], r: Any, ms: float) -> PairResult:
    """A pair's result from its estimate: ``ok``, or ``caustic`` (§2.1: the estimator keeps
    its last good iterate, but that is a partial solution that must not pull the
    combination), or ``non_finite_estimate``."""
    z = np.asarray(r.zernikes_nm, dtype=np.float64)
    if r.caustic or r.iterations < 1:
        return PairResult(**common, status="caustic",
                          message=f"the compensation folded into caustic after "
                                  f"{r.iterations} outer iteration(s)",
                          zernikes_nm=z, intrinsic_nm=np.asarray(r.intrinsic_nm),
                          iterations=r.iterations, compute_ms=ms)
    if not np.all(np.isfinite(z)):
        return PairResult(**common, status="non_finite_estimate",
                          message="the estimator returned NaN/Inf Zernikes",
                          zernikes_nm=z, intrinsic_nm=np.asarray(r.intrinsic_nm),
                          iterations=r.iterations, compute_ms=ms)
    return PairResult(**common, status="ok", message="", zernikes_nm=z,
                      intrinsic_nm=np.asarray(r.intrinsic_nm, dtype=np.float64),
                      iterations=r.iterations, compute_ms=ms, converged=bool(r.converged))


@dataclass(frozen=True)
class CornerFrameResult:
    """One corner's result from its two frames (what a ``CornerWavefront`` carries, plus
    the per-pair and per-donut reports).

    Attributes:
        corner: raft name.
        valid: at least one pair contributed, and the pairs kept agree within their noise
            model (``combination.max_reduced_chi2``).
        status: ``"ok"`` or ``"<reason>: <explanation>"``; ``reason`` the tag alone.
        zernikes_nm: (19,) Z4..Z22 (nm) at ``field_deg`` (NaN when not valid).
        uncertainty_nm: (19,) one-sigma per term (nm).
        n_pairs: pairs in the combination.
        field_deg: the corner's reference (mid-point) field.
        pairs: every estimated pair, with its status and whether it was used.
        detections: ``{"intra": (...), "extra": (...)}`` every detected donut and status.
        timing_ms: ``detect``, ``estimate``, ``combine``, ``total`` wall times.
        solver: TIE solver used.
        reduced_chi2: the kept pairs' scatter about their combination in units of their
            noise model (:attr:`.combination.CombinedEstimate.reduced_chi2`; NaN for fewer
            than two pairs).
    """

    corner: str
    stamp_ns: int
    valid: bool
    status: str
    reason: str
    zernikes_nm: np.ndarray
    uncertainty_nm: np.ndarray
    n_pairs: int
    field_deg: tuple[float, float]
    pairs: tuple[PairResult, ...] = ()
    detections: dict[str, tuple[DetectedDonut, ...]] = field(default_factory=dict)
    timing_ms: dict[str, float] = field(default_factory=dict)
    solver: str = ""
    worker_pid: int = 0
    noll: tuple[int, ...] = _NOLL
    reduced_chi2: float = float("nan")
    note: str = ""  # what the status adds: windows, the candidate cap reached

    @property
    def caustic(self) -> bool:
        """Some pair folded into caustic (and was dropped)."""
        return any(p.status == "caustic" for p in self.pairs)

    @property
    def iterations(self) -> int:
        """Most outer iterations run by a combined pair (0 if none)."""
        return max((p.iterations for p in self.pairs if p.used), default=0)

    @property
    def converged(self) -> bool:
        """Every combined pair's outer loop met its tolerance (False if none was used)."""
        used = [p for p in self.pairs if p.used]
        return bool(used) and all(p.converged for p in used)

    def summary(self) -> str:
        """One line for a ``CornerWavefront.status``: the status, then what was dropped,
        e.g. ``"ok: 3 pair(s) (reduced chi2 0.91); dropped 1 caustic; rejected 2 blended,
        1 too_faint"`` (the chi2 of :attr:`reduced_chi2`, with two pairs or more)."""
        dropped = {k: v for k, v in self.rejected_counts().items()
                   if k in ("caustic", "outlier") or k not in _DONUT_REASONS}
        rejected = {k: v for k, v in self.rejected_counts().items() if k in _DONUT_REASONS}
        parts = [f"{self.status}: {self.n_pairs} pair(s)" if self.valid else self.status]
        if self.valid and np.isfinite(self.reduced_chi2):
            parts[0] += f" (reduced chi2 {self.reduced_chi2:.2f})"
        if dropped:
            parts.append("dropped " + ", ".join(f"{v} {k}" for k, v in sorted(dropped.items())))
        if rejected:
            parts.append("rejected " + ", ".join(f"{v} {k}" for k, v in
                                                 sorted(rejected.items())))
        if self.note:
            parts.append(self.note)
        return "; ".join(parts)

    def rejected_counts(self) -> dict[str, int]:
        """Number of rejected donuts and dropped pairs per reason (for diagnostics)."""
        out: dict[str, int] = {}
        for dets in self.detections.values():
            for d in dets:
                if not d.ok:
                    out[d.status] = out.get(d.status, 0) + 1
        for p in self.pairs:
            if p.status != "ok":
                out[p.status] = out.get(p.status, 0) + 1
            elif not p.used:
                out["outlier"] = out.get("outlier", 0) + 1
        return out


def _design_at(instrument: str, band: str, field_deg: tuple[float, float]) -> np.ndarray:
    from cwfs_ros.wfs.mapping import design_zernikes_nm

    inst = load_instrument(instrument)
    wl = inst.wavelength_nm(band, None)
    return np.asarray(design_zernikes_nm(inst, band, wl, tuple(map(float, field_deg)), 22)
                      )[3:22]


def estimate_corner_frames(intra_frame: np.ndarray, extra_frame: np.ndarray, *, corner: str,
                           settings: EstimatorSettings = _DEFAULT_SETTINGS,
                           config: SelectionConfig | None = None,
                           sensors: dict[str, dict[str, HalfChip]] | None = None,
                           stamp_ns: int = 0, full_scale: float | None = None
                           ) -> CornerFrameResult:
    """The whole pipeline for one corner: frames in, combined wavefront out.

    Args:
        intra_frame, extra_frame: the two half-chip frames as read out (``SW1``, ``SW0``).
        corner: raft name (``R00`` ...), selects the geometry.
        settings: instrument, band, solver ... (as for stamp pairs); ``pad_px`` enlarges
            the stamps cut from the frames.
        config: selection parameters (default ``config/selection.yaml`` with the solver's
            noise model).
        sensors: half-chip geometry (default ``config/sensors/lsst_corners.yaml``).
        stamp_ns: visit time stamp, passed through.
        full_scale: the top of the frames' integer range as sent (None: floats); a donut
            with a pixel there is ``saturated`` (:func:`select_stamps`).

    Returns:
        A :class:`CornerFrameResult`.  No usable pair gives ``valid=False`` with a reason:
        ``no_donuts`` (a half has no accepted donut) or ``no_valid_pair``; pairs that
        disagree (:attr:`.combination.CombinedEstimate.consistent`) give
        ``inconsistent_pairs``.  An invalid result's Zernikes and uncertainties are NaN.

    Raises:
        ImageError for a frame that is not a 2-D array, is constant, or has more than
        ``max_nonfinite_fraction`` of its pixels NaN or Inf (fewer are set aside and
        counted in the note); ConfigError for bad settings.
    """
    t0 = time.perf_counter()
    cfg = config or load_selection_config(solver=settings.solver)
    geo = sensors or load_half_chips()
    if corner not in geo:
        raise ConfigError(f"unknown corner {corner!r}; known: {sorted(geo)}")
    hi, he = geo[corner]["intra"], geo[corner]["extra"]
    window = frame_window(intra_frame, extra_frame, hi, he)
    kw = dict(instrument=settings.instrument, band=settings.band, config=cfg,
              pad_px=settings.pad_px, full_scale=full_scale)
    st_in, det_in, bg_in = select_stamps(intra_frame, hi, **kw)
    st_ex, det_ex, bg_ex = select_stamps(extra_frame, he, **kw)
    t1 = time.perf_counter()
    note = "; ".join(n for n in (window, _cap_note(det_in, det_ex, cfg),
                                 _nonfinite_note(bg_in, bg_ex)) if n)
    pairs = pair_stars(st_in, st_ex, max_pairs=cfg.max_pairs, method=cfg.pairing,
                       centres_deg=(hi.field_deg, he.field_deg))
    results = estimate_pairs(pairs, settings)
    t2 = time.perf_counter()
    done = partial(_corner_result, corner=corner, stamp_ns=stamp_ns, field_deg=hi.mid_deg,
                   detections={"intra": tuple(det_in), "extra": tuple(det_ex)},
                   solver=settings.solver, times_s=(t0, t1, t2), note=note)
    if not st_in or not st_ex:
        return done(False, "no_donuts", _no_donuts_message(
            {"intra": (st_in, det_in, bg_in), "extra": (st_ex, det_ex, bg_ex)},
            cfg.detection.gain_e_per_adu), None, results)
    ok = [p for p in results if p.status == "ok"]
    if not ok:
        tags = sorted({p.status for p in results})
        return done(False, "no_valid_pair", f"all {len(results)} pair(s) failed "
                    f"({', '.join(tags)})", None, results)
    design_ref = _design_at(settings.instrument, settings.band, hi.mid_deg)
    comb = combine_pairs(np.array([p.departure_nm for p in ok]),
                         np.array([p.noise_scale for p in ok]), design_ref_nm=design_ref,
                         config=cfg.combination)
    used = iter(comb.used.tolist())
    res = [p if p.status != "ok" else _with_used(p, next(used)) for p in results]
    if comb.n_pairs > 0 and not comb.consistent:
        # Not a correction to act on: the stars of one sensor see nearly the same departure,
        # so pairs that disagree far beyond their noise mean some are bad, and with two bad
        # of four the outlier rejection cannot tell which (docs/accuracy.md, Frames).
        return done(False, "inconsistent_pairs", _inconsistency_message(comb, res, cfg),
                    comb, res)
    return done(comb.n_pairs > 0, "no_valid_pair", "every pair was rejected as an outlier",
                comb, res)


def _corner_result(valid: bool, reason: str, msg: str, comb: CombinedEstimate | None,
                   res: list[PairResult], *, corner: str, stamp_ns: int,
                   field_deg: tuple[float, float],
                   detections: dict[str, tuple[DetectedDonut, ...]], solver: str,
                   times_s: tuple[float, float, float], note: str = ""
                   ) -> CornerFrameResult:
    """The corner's result: the combination's Zernikes and uncertainties when ``valid``
    (NaN otherwise), the status ``"<reason>: <msg>"`` when not, and the stage timings from
    ``times_s`` (start, stamps selected, pairs estimated) to now."""
    t0, t1, t2 = times_s
    t3 = time.perf_counter()
    nan = np.full(len(_NOLL), np.nan)
    status = "ok" if valid else (msg if msg.startswith(reason + ":") else f"{reason}: {msg}")
    return CornerFrameResult(
        corner, int(stamp_ns), valid, status, "" if valid else reason,
        comb.zernikes_nm if comb is not None and valid else nan,
        comb.uncertainty_nm if comb is not None and valid else nan.copy(),
        comb.n_pairs if comb is not None else 0, field_deg, tuple(res), detections,
        {"detect": (t1 - t0) * 1e3, "estimate": (t2 - t1) * 1e3,
         "combine": (t3 - t2) * 1e3, "total": (t3 - t0) * 1e3},
        solver, os.getpid(),
        reduced_chi2=comb.reduced_chi2 if comb is not None else float("nan"), note=note)


def frame_window(intra_frame: np.ndarray, extra_frame: np.ndarray, intra: HalfChip,
                 extra: HalfChip) -> str:
    """Check the two frames' sizes against their half-chips (``shape_px``, focal-plane
    orientation) and say how a smaller one is placed ("" when both are whole).

    A frame may be a window of its half-chip, read out centred on the reference pixel (the
    simulator's frames are), in the half-chip's orientation: its long side, if any, along
    the half-chip's. A larger one, one whose long side lies across the half-chip's, or a
    corner whose two halves differ in size where the sensor file says they are alike,
    cannot be placed: one was transposed, cut or belongs to another sensor file.

    Raises:
        FrameSizeError: a frame larger than its half-chip or crosswise to it, or halves of
            different sizes.
    """
    shapes = {}
    for name, frame, half in (("intra", intra_frame, intra), ("extra", extra_frame, extra)):
        rows, cols = np.shape(frame)[:2]
        if half.orientation.rot90 % 2:
            rows, cols = cols, rows
        shapes[name] = (int(rows), int(cols))
        if rows > half.shape_px[0] or cols > half.shape_px[1]:
            raise FrameSizeError(
                f"the {name} frame is {rows}x{cols} (rows x cols, focal-plane orientation), "
                f"larger than the {half.shape_px[0]}x{half.shape_px[1]} {half.corner} "
                f"{half.sensor} half-chip of the sensor file: "
                + ("a transposed or turned readout, or the wrong sensor file"
                   if rows <= half.shape_px[1] and cols <= half.shape_px[0] else
                   "not a window of it (overscan or prescan pixels left in, or the wrong "
                   "sensor file)"))
        if half.crosswise(shapes[name]):
            raise FrameSizeError(
                f"the {name} frame is {rows}x{cols} (rows x cols, focal-plane orientation): "
                f"its long side lies across that of the {half.shape_px[0]}x"
                f"{half.shape_px[1]} {half.corner} {half.sensor} half-chip. A window keeps "
                f"its half-chip's orientation, so this one is a transposed or turned "
                f"readout (its stars' field positions would be wrong)")
    if intra.shape_px == extra.shape_px and shapes["intra"] != shapes["extra"]:
        raise FrameSizeError(
            f"the intra frame is {shapes['intra'][0]}x{shapes['intra'][1]} and the extra "
            f"{shapes['extra'][0]}x{shapes['extra'][1]}: the two halves of one sensor are read "
            f"out alike, so one was cut (its stars' field positions would be wrong)")
    if shapes["intra"] == intra.shape_px and shapes["extra"] == extra.shape_px:
        return ""
    if intra.reference_px is not None:
        return (f"{shapes['intra'][0]}x{shapes['intra'][1]} windows placed by the sensor "
                f"file's reference_px")
    return (f"{shapes['intra'][0]}x{shapes['intra'][1]} windows of the "
            f"{intra.shape_px[0]}x{intra.shape_px[1]} half-chips, taken as centred on their "
            f"reference pixels")


def _nonfinite_note(bg_in: Background, bg_ex: Background) -> str:
    """How many NaN, Inf or dead pixels each half had ("" when none): the stars whose
    stamps hold one were not used."""
    bad = [f"{what} in the {s} frame" for s, bg in (("intra", bg_in), ("extra", bg_ex))
           for what in (f"{bg.n_nonfinite} non-finite" if bg.n_nonfinite else "",
                        f"{bg.n_dead} dead (blocks of one value)" if bg.n_dead else "")
           if what]
    return (f"unusable pixels: {', '.join(bad)}, set to the frame's median for the search; "
            "stars whose stamps hold one not used") if bad else ""


def _cap_note(det_in: list[DetectedDonut], det_ex: list[DetectedDonut],
              cfg: SelectionConfig) -> str:
    """Which half reached the detection's ``max_candidates`` ("" when neither did): its
    fainter sources, if any, were not measured."""
    cap = cfg.detection.max_candidates
    full = [s for s, d in (("intra", det_in), ("extra", det_ex)) if len(d) >= cap]
    if not full:
        return ""
    return (f"the {' and '.join(full)} frame{'s' if len(full) > 1 else ''} reached "
            f"max_candidates ({cap}): fainter sources, if any, were not measured")


def _no_donuts_message(sides: dict[str, tuple[list[StarStamp], list[DetectedDonut],
                                              Background]], gain: float) -> str:
    """Which half (or both) has no usable donut, and how many it detected and rejected; and
    for a half whose sky was quieter than one electron's shot noise, that its units may not
    be electrons (the S/N limits are in electrons)."""
    empty = [(s, dets, bg) for s, (st, dets, bg) in sides.items() if not st]
    detail = "; ".join(f"{s}: {sum(not d.ok for d in dets)} detected and rejected"
                       for s, dets, _ in empty)
    which = " and ".join(s for s, _, _ in empty)
    quiet = [f"{s} {bg.measured_noise:.3g}" for s, _, bg in empty if bg.quiet_sky]
    units = (f". The sky noise ({', '.join(quiet)} per pixel) is below one electron's shot "
             f"noise at gain_e_per_adu {gain:g}: a frame in other units than electrons needs "
             "detection.gain_e_per_adu (electrons per unit), and saturation_level in its "
             "units, in the selection file"
             if quiet else "")
    return f"no usable donut on the {which} half ({detail}){units}"


def _inconsistency_message(comb: CombinedEstimate, res: list[PairResult],
                           cfg: SelectionConfig) -> str:
    """Why the kept pairs do not make a corner result: two groups and no majority
    (:attr:`.combination.CombinedEstimate.ambiguous`), or a scatter beyond the noise model."""
    kept = ", ".join(str(p.index) for p in res if p.used)
    if comb.ambiguous:
        return (f"the star pairs fall in two groups that each agree and not with each "
                f"other ({comb.n_pairs} kept: {kept}), and no majority to choose")
    return (f"the {comb.n_pairs} star pairs kept ({kept}) disagree: their scatter is "
            f"{np.sqrt(comb.reduced_chi2):.1f}x their noise model (reduced chi^2 "
            f"{comb.reduced_chi2:.1f} > {cfg.combination.max_reduced_chi2:g})")


def _with_used(p: PairResult, used: bool) -> PairResult:
    from dataclasses import replace

    return replace(p, used=bool(used))


@dataclass(frozen=True)
class CornerFrameJob:
    """One corner's two frames for one visit (picklable, for a worker process)."""

    corner: str
    stamp_ns: int
    intra: np.ndarray
    extra: np.ndarray
    settings: EstimatorSettings = EstimatorSettings()
    sensor_config: str = ""  # "" = config/sensors/lsst_corners.yaml
    selection_config: str = ""  # "" = config/selection.yaml
    full_scale: float | None = None  # the frames' integer full scale (None: floats)


def run_corner_frame_job(job: CornerFrameJob) -> CornerFrameResult:
    """:func:`estimate_corner_frames` for a worker: bad input becomes an invalid result
    whose status names the problem; it never raises."""
    t0 = time.perf_counter()
    try:
        sensors = load_half_chips(job.sensor_config or None)
        cfg = load_selection_config(job.selection_config or None, solver=job.settings.solver)
        return estimate_corner_frames(job.intra, job.extra, corner=job.corner,
                                      settings=job.settings, config=cfg, sensors=sensors,
                                      stamp_ns=job.stamp_ns, full_scale=job.full_scale)
    except Exception as exc:  # noqa: BLE001 - a worker must report, not die
        if isinstance(exc, ImageError):
            reason = str(getattr(exc, "reason", "bad_image"))
        elif isinstance(exc, ConfigError):
            reason = "config"
        else:
            reason = "internal_error"
        nan = np.full(len(_NOLL), np.nan)
        msg = str(exc) if isinstance(exc, CwfsError) else f"{type(exc).__name__}: {exc}"
        return CornerFrameResult(job.corner, int(job.stamp_ns), False, f"{reason}: {msg}",
                                 reason, nan, nan.copy(), 0, (float("nan"), float("nan")),
                                 timing_ms={"total": (time.perf_counter() - t0) * 1e3},
                                 solver=job.settings.solver, worker_pid=os.getpid())
