"""Pupil-to-image mappings: where a ray from reduced pupil point (x, y) lands on a defocused image.

The outer loop of the paper (§2.1) compensates images by remapping flux through

    x'(x, y) = x'_0(x, y) + C dW/dx,     y'(x, y) = y'_0(x, y) + C dW/dy          (eqs. 9-10)

with Jacobian ``J = det(d(x', y')/d(x, y))`` (eq. 12).  ``x'_0`` is the mapping of the
unperturbed system and is what differs between models:

* ``paraxial``: ``x'_0 = +/- r_d x`` (eqs. 9-10 as written; r_d = l R / f in pixels).
* ``fastbeam``: ``x'_0 = +/- r_d F(x, y) x`` with ``F = f / sqrt(f^2 - r^2 R^2)``, the paper's
  §3.2 correction for an f/1.23 beam (eq. 13 with the aplanatic mask scale ``m``).
* ``batoid``: ``x'_0`` from rays traced through the defocused design telescope at the star's
  field angle (§3.3): includes fast-beam projection, off-axis distortion and the design
  aberrations of that field point.  A smooth polynomial fitted to the ray hits supplies the
  Jacobian.  Vignetting comes from the same trace.
* ``poly10``: the paper's own §3.3 model: ``x'_0`` from its tables of 10th-order 2-D
  polynomials fitted to ZEMAX ray hits at field points on the +45° diagonal, interpolated
  linearly in field radius and rotated to the star's azimuth (the telescope is rotationally
  symmetric), and linearly in the detector offset between the tabulated intra and extra
  planes (straight rays).  Vignetting from the paper's two circles per field
  (``mask_migrate.txt``: a pass circle and a block circle centred on the field direction).
  No design wavefront is added back: the estimate is whatever wavefront the tables' ray
  hits do not already hold.  For the FAM tables (``lsstfam``) that is the total wavefront
  (their hits hold no design aberration: the FAM estimates match the ZEMAX truth of the
  nominal design, docs/accuracy.md), as it is for the reference code's output on the 1-mm pair.

All positions are in pixels, in the focal-plane frame of the field angles (``[row=y, col=x]``
images), relative to a reference point (the chief ray for batoid, the pupil centre's image
otherwise); the estimator aligns images by centroid, so the reference point drops out.

Intra-focal images are upright (``x'_0 ~ +r_d x``), extra-focal images inverted
(``x'_0 ~ -r_d x``); no image is ever rotated: the mapping carries the inversion.

Sign of the wavefront term: ``C`` is the ray displacement per unit wavefront slope.  A ray
leaving the pupil with OPD slope ``dW/dU`` is deflected by ``-dW/dU`` radians toward the focus
(wavefront ahead of the reference sphere at the edge = positive OPD = focus pushed beyond),
and travels ``f -/+ l`` to the intra/extra plane: ``C = -(f -/+ l) / R`` (m per unit slope per
unit reduced pupil coordinate), the same sign on both sides of focus.  The sign agrees with
batoid's OPD convention; ``test_estimator`` pins it with ray-traced perturbations.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.config import config_dir
from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import SIDES
from cwfs_ros.wfs.instrument import Instrument
from cwfs_ros.wfs.tile_store import TileStore, active_tile_store, use_tile_store
from cwfs_ros.wfs.zernike import zernike_basis

__all__ = ["ImageMapping", "nominal_mapping", "design_zernikes_nm", "design_zernikes_tiled",
           "Poly10Tables", "poly10_tables", "defocused_telescope", "TileCacheStats",
           "field_tile_stats", "size_field_tile_caches", "warm_field_tiles", "tile_of",
           "tile_centre", "use_field_tile_store", "reset_field_tiles"]


# Radial order of the polynomial fitted to ray hits.  The paper uses 10th order (§3.3); with
# LSST at 1.5 mm that left Z4 and Z7 biased by up to 13 nm on noise-free ray-traced pairs,
# while 12 and above converge (14 and 16 agree to 0.01 nm).
_FIT_ORDER = 14


@dataclass(frozen=True)
class ImageMapping:
    """The unperturbed pupil-to-image mapping of one defocused image, at fixed pupil points.

    Attributes:
        x_px, y_px: image position of each pupil point, pixels from the reference point.
        jxx, jxy, jyx, jyy: Jacobian entries ``dx'/dx, dx'/dy, dy'/dx, dy'/dy`` in pixels per
            unit reduced pupil coordinate.
        transmitted: True where the pupil point lies in the unvignetted annulus.
        c_px_per_nm: displacement (pixels) per nm of wavefront per unit reduced pupil
            coordinate of slope: the paper's C (eq. 11) in these units.
        fit_rms_px: rms residual of the ray-hit fit (0 for analytic models).
    """

    side: str
    x_px: np.ndarray
    y_px: np.ndarray
    jxx: np.ndarray
    jxy: np.ndarray
    jyx: np.ndarray
    jyy: np.ndarray
    transmitted: np.ndarray
    c_px_per_nm: float
    fit_rms_px: float = 0.0

    @property
    def det(self) -> np.ndarray:
        return self.jxx * self.jyy - self.jxy * self.jyx

    @cached_property
    def transmitted_index(self) -> np.ndarray:
        """Indices of the transmitted points (cached: the caustic check runs every iteration)."""
        return np.flatnonzero(self.transmitted)

    @cached_property
    def inv_det_transmitted(self) -> np.ndarray:
        """``1 / J_0`` on the transmitted points."""
        return 1.0 / self.det[self.transmitted_index]


def _side_sign(side: str) -> float:
    if side not in SIDES:
        raise ValueError(f"side must be 'intra' or 'extra', got {side!r}")
    return 1.0 if side == "intra" else -1.0


def _c_px_per_nm(inst: Instrument, side: str, defocus_mm: float) -> float:
    """The paper's C (eq. 11): ray displacement per unit wavefront slope, in px per nm."""
    l_m = defocus_mm * 1e-3
    f = inst.focal_length_m
    dist = f - l_m if side == "intra" else f + l_m
    return -dist / inst.pupil_radius_m / (inst.pixel_size_um * 1e-6) * 1e-9


def _annulus(inst: Instrument, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return _in_annulus(x * x + y * y, inst.obscuration)


def _in_annulus(r2: np.ndarray, obscuration: float) -> np.ndarray:
    """The points of squared pupil radius ``r2`` in the annulus (obscuration to 1)."""
    return (r2 <= 1.0) & (r2 >= obscuration**2)


def _paraxial(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray):
    s = _side_sign(side) * inst.donut_radius_px(defocus_mm)
    one = np.full_like(x, s)
    zero = np.zeros_like(x)
    return s * x, s * y, one, zero, zero, one.copy()


def _fastbeam(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray):
    """Paper §3.2: x' = F(x, y) x with F = m sqrt(f^2-R^2)/sqrt(f^2-r^2 R^2), m = f/sqrt(f^2-R^2).

    (For an aplanatic beam the unaberrated image radius is R' = l R / sqrt(f^2 - R^2), so the
    mask scale m = R' f / (l R) = f / sqrt(f^2 - R^2) and F reduces to f / sqrt(f^2 - r^2 R^2).)
    """
    s = _side_sign(side) * inst.donut_radius_px(defocus_mm)
    f, big_r = inst.focal_length_m, inst.pupil_radius_m
    r2 = x * x + y * y
    den = f * f - r2 * big_r * big_r
    if np.any(den <= 0):
        raise ConfigError("fast-beam mapping undefined: pupil point beyond the f-number limit")
    fxy = f / np.sqrt(den)
    g = big_r * big_r / den  # the R^2 / (f^2 - r^2 R^2) factor of the Jacobian terms
    jxx = s * fxy * (1 + x * x * g)
    jyy = s * fxy * (1 + y * y * g)
    jxy = s * fxy * x * y * g
    return s * fxy * x, s * fxy * y, jxx, jxy, jxy.copy(), jyy


@lru_cache(maxsize=8)
def _batoid_telescope(template: str, band: str):
    import batoid  # imported lazily: only the batoid mapping needs it

    try:
        return batoid.Optic.fromYaml(template.format(band=band))
    except Exception as exc:  # batoid raises several types for a missing file
        raise ConfigError(
            f"cannot load batoid optic {template.format(band=band)!r}: {exc}"
        ) from exc


@lru_cache(maxsize=16)
def defocused_telescope(template: str, band: str, detector_dz_m: float):
    """The design with its detector moved by ``detector_dz_m`` along the detector's own axis
    (intra negative; cached).  Shared with :mod:`.field_position`, whose pixel -> field
    model must see the same defocused optic as the mapping."""
    tel = _batoid_telescope(template, band)
    shift = tel["Detector"].coordSys.rot @ np.array([0.0, 0.0, detector_dz_m])
    return tel.withGloballyShiftedOptic("Detector", shift)


def _stop_rays(inst: Instrument, band: str, wavelength_nm: float,
               field_deg: tuple[float, float], side: str, defocus_mm: float,
               x: np.ndarray, y: np.ndarray):
    """``(telescope, rays)``: the defocused design of one side, and rays from the reduced
    pupil points (x, y) at ``field_deg``, not yet traced."""
    import batoid

    dz = (-1.0 if side == "intra" else 1.0) * defocus_mm * 1e-3  # intra: detector before focus
    tel = defocused_telescope(inst.batoid_optic, band, dz)
    big_r = tel.pupilSize / 2.0
    rv = batoid.RayVector.fromStop(np.asarray(x) * big_r, np.asarray(y) * big_r, optic=tel,
                                   wavelength=wavelength_nm * 1e-9,
                                   theta_x=np.deg2rad(field_deg[0]),
                                   theta_y=np.deg2rad(field_deg[1]))
    return tel, rv


def _trace_defocused(inst: Instrument, band: str, wavelength_nm: float,
                     field_deg: tuple[float, float], side: str, defocus_mm: float,
                     x: np.ndarray, y: np.ndarray):
    """Trace rays from reduced pupil points to the shifted detector. Returns hits in pixels."""
    tel, rv = _stop_rays(inst, band, wavelength_nm, field_deg, side, defocus_mm,
                         np.concatenate([[0.0], x]), np.concatenate([[0.0], y]))
    out = tel.trace(rv)
    pix = inst.pixel_size_um * 1e-6
    hx = (out.x[1:] - out.x[0]) / pix  # relative to the chief ray
    hy = (out.y[1:] - out.y[0]) / pix
    ok = ~out.failed[1:]
    transmitted = ok & ~out.vignetted[1:]
    return hx, hy, ok, transmitted


class _FitOperator:
    """Field-independent parts of the ray-hit fit at one set of pupil points.

    The fit basis (circle Zernikes to ``_FIT_ORDER`` over the points' bounding radius), its
    derivatives, and the least-squares operator of the regular fit subset depend only on the
    pupil points, not on the field: a new field then costs one ray trace and a few small
    matrix products (docs/performance.md).  The operator assumes every traced ray succeeded; a
    trace with failed rays falls back to a direct least-squares solve on its own subset.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray):
        self.rmax = float(np.sqrt((x * x + y * y).max())) * 1.0001
        jfit = (_FIT_ORDER + 1) * (_FIT_ORDER + 2) // 2
        basis = zernike_basis(x / self.rmax, y / self.rmax, jmax=jfit, eps=0.0)
        self.z = basis.z
        self.dx = basis.dx / self.rmax
        self.dy = basis.dy / self.rmax
        # 120 smooth terms need far fewer than the ~15k traced points: fit on a regular
        # subset (both coordinates in one solve), then evaluate everywhere.
        self.fit_idx = np.arange(x.size)[::3]
        q, r = np.linalg.qr(self.z[:, self.fit_idx].T.astype(float))
        self.pinv = np.linalg.solve(r, q.T)  # (jfit, n_fit): coefficients = pinv @ hits
        for a in (self.z, self.dx, self.dy, self.fit_idx, self.pinv):
            a.setflags(write=False)
        self.lattice = _lattice(x, y)
        self._r2 = x * x + y * y
        self._annuli: dict[float, np.ndarray] = {}

    def annulus(self, obscuration: float) -> np.ndarray:
        """The points in the annulus of this obscuration (:func:`_annulus`; kept, read-only:
        every pair geometry asks for it on the same pupil grid)."""
        a = self._annuli.get(obscuration)
        if a is None:
            a = _in_annulus(self._r2, obscuration)
            a.setflags(write=False)
            self._annuli[obscuration] = a
        return a

    def infer_transmitted(self, known: np.ndarray, transmitted: np.ndarray,
                          annulus: np.ndarray) -> np.ndarray:
        """Annulus points whose vignetting follows from the traced points around them.

        ``known`` marks the traced points and ``transmitted`` their outcome.  A point is
        decided when at least _VIG_MIN_NEIGHBOURS traced points lie in the
        (2 _VIG_HALF + 1)^2 lattice window around it and all agree; vignetting edges are
        arcs of pupil radius and more, so a point on the other side of an edge from all of
        its window's traced points cannot occur (checked against full traces at 160 random
        LSST fields, corners and the whole field: no point differs).  Returns -1
        (undecided), 0 or 1 per point.
        """
        from scipy.ndimage import uniform_filter

        shape, flat = self.lattice
        size = 2 * _VIG_HALF + 1
        area = float(size * size)
        img_k = np.zeros(shape[0] * shape[1])
        img_t = np.zeros_like(img_k)
        # Every traced point counts, also those beyond the annulus: a thin vignetted crescent
        # inside an annulus edge (an obscuration off the stop, shifted with field) then
        # disagrees with the points across that edge and is traced.
        img_k[flat] = known
        img_t[flat] = known & transmitted
        n_k = np.rint(uniform_filter(img_k.reshape(shape), size, mode="constant") * area)
        n_t = np.rint(uniform_filter(img_t.reshape(shape), size, mode="constant") * area)
        n_k, n_t = n_k.ravel()[flat], n_t.ravel()[flat]
        out = np.full(flat.size, -1, dtype=np.int8)
        enough = n_k >= _VIG_MIN_NEIGHBOURS
        out[enough & (n_t == 0)] = 0
        out[enough & (n_t == n_k)] = 1
        out[~annulus] = 0  # masked by the annulus anyway
        out[known] = transmitted[known]
        return out

    def coefficients(self, hx: np.ndarray, hy: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """(jfit, 2) coefficients of the x' and y' fits to the hits of the successful rays."""
        hits = np.stack([hx, hy], axis=1)
        if ok.all():
            return self.pinv @ hits[self.fit_idx]
        fit_idx = np.flatnonzero(ok)[::3]
        coef, *_ = np.linalg.lstsq(self.z[:, fit_idx].T.astype(float), hits[fit_idx],
                                   rcond=None)
        return coef


# Vignetting inference from a subset of traced rays (see _FitOperator.infer_transmitted).
_VIG_HALF = 2
_VIG_MIN_NEIGHBOURS = 4


def _lattice(x: np.ndarray, y: np.ndarray) -> tuple[tuple[int, int], np.ndarray] | None:
    """(shape, flat index) of the points on their square lattice, or None if not one."""
    ux = np.unique(x)
    uy = np.unique(y)
    if ux.size < 2 or uy.size < 2:
        return None
    step = float(np.min(np.diff(ux)))
    ix = np.rint((x - ux[0]) / step)
    iy = np.rint((y - uy[0]) / step)
    if (np.abs(ux[0] + ix * step - x).max() > 1e-9 * step
            or np.abs(uy[0] + iy * step - y).max() > 1e-9 * step):
        return None
    shape = (int(iy.max()) + 1, int(ix.max()) + 1)
    if shape[0] * shape[1] > 16 * x.size:  # sparse points: no useful neighbourhoods
        return None
    flat = (iy * shape[1] + ix).astype(np.int64)
    if np.unique(flat).size != flat.size:
        return None
    return shape, flat


_FIT_CACHE: dict[tuple[int, bytes], _FitOperator] = {}
# Each operator holds ~45 MB (three 120 x 13.6k float64 arrays) for the LSST 1.5 mm grid.
_FIT_CACHE_SIZE = 4
# Number of fit operators built (the cache is reused while this stays put; tests read it).
fit_operator_builds = 0


def _same_points(a: np.ndarray, ref: np.ndarray) -> bool:
    """``a`` is (a view of) the read-only array ``ref``, whose memory ``ref`` keeps alive:
    then it holds the same values, without hashing them."""
    return (not a.flags.writeable and not ref.flags.writeable and a.dtype == ref.dtype
            and a.shape == ref.shape and a.strides == ref.strides
            and a.__array_interface__["data"][0] == ref.__array_interface__["data"][0])


# The last few point sets asked for and their operators, held by reference: the estimator
# passes the same read-only pupil-grid arrays for every pair, whose values then need no
# hashing (0.5 ms a side on the LSST grid).
_FIT_RECENT: list[tuple[np.ndarray, np.ndarray, _FitOperator]] = []


def _fit_operator(x: np.ndarray, y: np.ndarray) -> _FitOperator:
    """The cached :class:`_FitOperator` of the pupil points (x, y), keyed by their values."""
    global fit_operator_builds
    import hashlib

    for xr, yr, op in _FIT_RECENT:
        if _same_points(x, xr) and _same_points(y, yr):
            return op
    key = (x.size, hashlib.blake2b(np.ascontiguousarray(x).tobytes()
                                   + np.ascontiguousarray(y).tobytes(),
                                   digest_size=16).digest())
    op = _FIT_CACHE.get(key)
    if op is None:
        op = _FitOperator(x, y)
        fit_operator_builds += 1
        if len(_FIT_CACHE) >= _FIT_CACHE_SIZE:
            gone = _FIT_CACHE.pop(next(iter(_FIT_CACHE)))
            _FIT_RECENT[:] = [e for e in _FIT_RECENT if e[2] is not gone]
        _FIT_CACHE[key] = op
    if not x.flags.writeable and not y.flags.writeable:
        _FIT_RECENT.insert(0, (x, y, op))
        del _FIT_RECENT[_FIT_CACHE_SIZE:]
    return op


def _batoid(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray,
            band: str, wavelength_nm: float, field_deg: tuple[float, float],
            tile_deg: float = 0.0):
    # Smooth fit over every traced point (the computation region extends a little beyond the
    # pupil; rays there are traced through the same surfaces, so the fit interpolates).
    op = _fit_operator(x, y)
    annulus = op.annulus(inst.obscuration)
    if tile_deg > 0 and op.lattice is not None:
        tiled = _batoid_tiled(inst, side, defocus_mm, x, y, band, wavelength_nm, field_deg,
                              tile_deg, op, annulus)
        if tiled is not None:
            return tiled
    fit = op.fit_idx
    hx_f, hy_f, ok_f, tr_f = _trace_defocused(inst, band, wavelength_nm, field_deg, side,
                                              defocus_mm, x[fit], y[fit])
    if op.lattice is not None and ok_f.all():
        # Only the fit subset is needed for the mapping; the vignetting of the other annulus
        # points follows from their traced neighbours, except near a vignetting edge, where
        # they are traced too.
        known = np.zeros(x.size, bool)
        known[fit] = True
        transmitted = np.zeros(x.size, bool)
        transmitted[fit] = tr_f
        state = op.infer_transmitted(known, transmitted, annulus)
        todo = np.flatnonzero(state < 0)
        if todo.size:
            *_, tr_e = _trace_defocused(inst, band, wavelength_nm, field_deg, side,
                                        defocus_mm, x[todo], y[todo])
            state[todo] = tr_e  # a failed ray is not transmitted (tr_e is False there)
        transmitted = state > 0
        coef = op.pinv @ np.stack([hx_f, hy_f], axis=1)
        hx, hy, ok = hx_f, hy_f, ok_f
        at = fit
    else:
        hx, hy, ok, transmitted = _trace_defocused(inst, band, wavelength_nm, field_deg, side,
                                                   defocus_mm, x, y)
        coef = op.coefficients(hx, hy, ok)
        at = slice(None)
    # Evaluate the fits and their derivatives w.r.t. the reduced pupil coordinates.
    fx, fy = coef.T @ op.z
    jxx, jyx = coef.T @ op.dx
    jxy, jyy = coef.T @ op.dy
    # Residual over the traced points (the fit subset when only that was traced).
    rms = float(np.sqrt(np.mean((fx[at] - hx)[ok] ** 2 + (fy[at] - hy)[ok] ** 2)))
    return (fx, fy, jxx, jxy, jyx, jyy), transmitted & annulus, rms


# -- the batoid mapping interpolated in field ------------------------------------------------
#
# The fit coefficients of a side's mapping are smooth in field: over a 0.125 deg tile a
# quartic in field reproduces the direct fit to ~1e-7 px (measured at random corner
# fields).  Each tile is fitted once from a 5x5 grid of full traces, which also give the
# vignetting at the nodes: an annulus point transmitted (or vignetted) at every node is
# taken as such over the tile -- the field set in which a vignetting circle (pupil-sized,
# moving linearly with field) covers a pupil point is a disk far larger than the tile.  The
# points whose state changes across the tile (the band the vignetting edges sweep) are
# decided per star from their ray positions on the apertures, interpolated in field like
# the mapping (:class:`_ApertureEdges`).  A tile whose nodes have failed rays or whose
# coefficient fit leaves more than _MAP_TILE_MAX_RESID_PX at its nodes falls back to the
# direct path, as do the tile's first _DESIGN_TILE_AFTER - 1 fields (the tile costs 50
# full traces, ~1.5 s).

_MAP_TILE_NODES = 5
_MAP_TILE_MAX_RESID_PX = 1e-4
_map_tile_requests: dict[tuple, set[tuple[float, float]]] = {}
_MAP_TILE_CACHE: dict[tuple, tuple | None] = {}
# Number of mapping tiles fitted (tests read it to check the cache is reused).
map_tile_builds = 0


def _map_tile(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray,
              band: str, wavelength_nm: float, tile: tuple[int, int], tile_deg: float,
              op: _FitOperator, annulus: np.ndarray) -> tuple | None:
    """The tile's fit from ray traces: (field polynomial of the mapping coefficients,
    always-transmitted, swept points, their aperture edges, node rms) or None
    (:func:`_map_tile_entry` turns it into what a field reads)."""
    global map_tile_builds
    map_tile_builds += 1
    u, v, nodes = _tile_nodes(tile, tile_deg, _MAP_TILE_NODES)
    coefs, masks, rms = [], [], []
    for node in nodes:
        hx, hy, ok, tr = _trace_defocused(inst, band, wavelength_nm, node, side, defocus_mm,
                                          x, y)
        if not ok[op.fit_idx].all():
            return None
        c = op.pinv @ np.stack([hx, hy], axis=1)[op.fit_idx]
        coefs.append(c.ravel())
        masks.append(tr & annulus)
        fx, fy = c.T @ op.z[:, op.fit_idx]
        rms.append(float(np.sqrt(np.mean((fx - hx[op.fit_idx]) ** 2
                                         + (fy - hy[op.fit_idx]) ** 2))))
    coefs = np.array(coefs)
    mono = _tile_monomials(u, v)
    poly, *_ = np.linalg.lstsq(mono, coefs, rcond=None)
    dev = ((mono @ poly - coefs).reshape(len(u), -1, 2).transpose(0, 2, 1) @ op.z)
    if np.abs(dev[:, :, annulus]).max() > _MAP_TILE_MAX_RESID_PX:
        return None
    masks = np.array(masks)
    always, never = masks.all(axis=0), ~masks.any(axis=0)
    sweep = np.flatnonzero(~always & ~never)
    edges = _aperture_edges(inst, side, defocus_mm, x[sweep], y[sweep], band, wavelength_nm,
                            nodes, mono, masks[:, sweep]) if sweep.size else None
    return poly, always, sweep, edges, max(rms)


def _map_tile_entry(fit: tuple | None, op: _FitOperator) -> tuple | None:
    """(coefficient shares, always-transmitted, swept points, their aperture edges, node
    rms) of a tile's fit (:func:`_map_tile`), or None."""
    if fit is None:
        return None
    poly, always, sweep, edges, rms = fit
    # The mapping at a field is linear in the tile's monomials, so each monomial's share of
    # the six mapped quantities at every point is precomputed: a new field then reads
    # (n_mono, 6, n) values (~6 MB) instead of the three (jfit, n) float64 bases (~40 MB),
    # the memory traffic that dominated the per-star cost (8 ms -> 1 ms for two sides).
    # The constant monomial's share (the mapping at the tile centre, up to ~100 px) stays
    # float64; the others carry only the variation across the tile (a few px), so float32
    # leaves them ~1e-7 px of rounding.
    per_mono = poly.reshape(len(poly), -1, 2)
    shares = np.concatenate([np.einsum("kjc,jn->kcn", per_mono, b)
                             for b in (op.z, op.dx, op.dy)], axis=1)
    centre, variation = shares[0], shares[1:].astype(np.float32)
    for a in (centre, variation, always, sweep):
        a.setflags(write=False)
    return (centre, variation), always, sweep, edges, rms


# -- the field-tile caches: sizes, warming and counters --------------------------------------
#
# Three caches hold field tiles: "map" and "pupil" (one tile per side and field tile) and
# "design" (one per field tile of the pairs' mid-points).  A worker serving frames needs every
# tile its half-chips cover (about 9 map tiles per LSST corner at 0.125 deg), so the caches
# are sized from the sensor geometry by :func:`size_field_tile_caches`; 64 is the floor.
_TILE_KINDS = ("map", "pupil", "design")
_TILE_CACHE_SIZE = dict.fromkeys(_TILE_KINDS, 64)
# Per kind: [served from the cache, made on a miss (built, or read from the tile store),
# evicted, traced directly (a tile's first fields), read from the tile store].
_TILE_COUNTS = {k: [0, 0, 0, 0, 0] for k in _TILE_KINDS}
# Tiles warmed at start serve every field in them, from the first (see _tile_wanted).
_WARMED_TILES: set[tuple] = set()
_warming = False


@dataclass(frozen=True)
class TileCacheStats:
    """One field-tile cache of this process: held/size tiles and its request counts."""

    kind: str
    held: int
    size: int
    hits: int
    builds: int  # made on a miss: traced, or read from the tile store (``loaded``)
    evictions: int
    direct: int
    loaded: int = 0

    @property
    def hit_rate(self) -> float:
        """Share of tile requests served from the cache (NaN before any request)."""
        n = self.hits + self.builds
        return self.hits / n if n else float("nan")


def field_tile_stats() -> dict[str, TileCacheStats]:
    """The field-tile caches of this process (``map``, ``pupil``, ``design``)."""
    held = {"map": len(_MAP_TILE_CACHE), "pupil": len(_PUPIL_TILE_CACHE),
            "design": len(_DESIGN_TILE_CACHE)}
    return {k: TileCacheStats(k, held[k], _TILE_CACHE_SIZE[k], *_TILE_COUNTS[k])
            for k in _TILE_KINDS}


def size_field_tile_caches(n_map: int, n_pupil: int, n_design: int) -> None:
    """Hold at least this many tiles of each kind (never fewer than 64, and never fewer than
    asked before): a worker's caches must keep every tile of every half-chip it serves, or
    its corners evict each other's."""
    for kind, n in zip(_TILE_KINDS, (n_map, n_pupil, n_design), strict=True):
        _TILE_CACHE_SIZE[kind] = max(_TILE_CACHE_SIZE[kind], 64, int(n))


def _cached_tile(cache: dict[tuple, Any], kind: str, key: tuple, build: Callable[[], Any],
                 finish: Callable[[Any], Any] | None = None,
                 stored: Callable[[], tuple] | None = None) -> Any:
    """``cache[key]``, made on first use; when the kind's size is held the oldest goes
    (never a warmed tile while an unwarmed one can go).

    ``build()`` fits the tile from ray traces; ``finish`` (default: none) turns the fit into
    what the cache holds. With a tile store in use (:func:`use_field_tile_store`) and
    ``stored()`` giving the tile's key on disk, the fit is read from the store when it holds
    it, and stored when built (:mod:`.tile_store`).
    """
    counts = _TILE_COUNTS[kind]
    if key in cache:
        counts[0] += 1
        return cache[key]
    if len(cache) >= _TILE_CACHE_SIZE[kind]:
        gone = next((k for k in cache if k not in _WARMED_TILES), next(iter(cache)))
        cache.pop(gone)
        counts[2] += 1
    counts[1] += 1
    store = active_tile_store() if stored is not None else None
    fit, missing = None, True
    if store is not None:
        parts = stored()
        arrays = store.load(kind, parts)
        fit, missing = _decode_tile(kind, arrays)
        if missing and arrays is not None:
            store.reject(kind, parts, "its arrays are not a tile of this kind")
        if missing:
            fit = build()
            store.save(kind, parts, _encode_tile(kind, fit))
        else:
            counts[4] += 1
    if missing and store is None:
        fit = build()
    cache[key] = fit if finish is None else finish(fit)
    return cache[key]


def _points_digest(x: np.ndarray, y: np.ndarray) -> str:
    """A digest of the pupil points' values (a tile's key on disk)."""
    import hashlib

    return hashlib.blake2b(np.ascontiguousarray(x, dtype=np.float64).tobytes()
                           + np.ascontiguousarray(y, dtype=np.float64).tobytes(),
                           digest_size=16).hexdigest()


@lru_cache(maxsize=1)
def _store_salt() -> str:
    """Names what builds a stored tile: this module's source and batoid's and numpy's
    versions (:mod:`.tile_store`)."""
    import hashlib

    import batoid

    code = hashlib.blake2b(Path(__file__).read_bytes(), digest_size=16).hexdigest()
    return f"{code} batoid {batoid.__version__} numpy {np.__version__}"


def use_field_tile_store(root: str | Path | None) -> TileStore | None:
    """Keep this process's field tiles in the directory ``root`` across processes (None or
    ``""``: off, the default); the store in use. A tile read from it is the tile this
    process would build (:mod:`.tile_store`)."""
    return use_tile_store(root, _store_salt()) if root else use_tile_store(None)


# Field names of the arrays a stored tile holds (:func:`_encode_tile`): an absent tile (None:
# the direct path) is stored as the single flag ``none``.
_EDGE_FIELDS = ("n_points", "point", "centre", "variation", "aperture")


def _encode_tile(kind: str, fit: Any) -> dict[str, np.ndarray]:
    """A tile's fit as plain arrays (nothing to unpickle)."""
    if fit is None:
        return {"none": np.array(True)}
    if kind == "design":
        return {"coef": fit}
    if kind == "pupil":
        return {"apertures": fit[0], "poly": fit[1]}
    poly, always, sweep, edges, rms = fit
    out = {"poly": poly, "always": always, "sweep": sweep, "rms": np.array(rms)}
    if edges is not None:
        out |= {f"edges_{f}": np.asarray(getattr(edges, f)) for f in _EDGE_FIELDS}
    return out


def _decode_tile(kind: str, arrays: dict[str, np.ndarray] | None) -> tuple[Any, bool]:
    """(fit, missing) from stored arrays; ``missing`` when there are none or they are not a
    tile of ``kind`` (then it is built and stored again)."""
    if arrays is None:
        return None, True
    try:
        if "none" in arrays:
            return None, False
        if kind == "design":
            coef = np.array(arrays["coef"], dtype=np.float64)
            coef.setflags(write=False)
            return _checked(coef, 2), False
        if kind == "pupil":
            return (_checked(arrays["apertures"], 2, apertures=True),
                    _checked(arrays["poly"], 3)), False
        edges = None
        if "edges_point" in arrays:
            e = {f: arrays[f"edges_{f}"] for f in _EDGE_FIELDS}
            edges = _ApertureEdges(int(e["n_points"]), _checked(e["point"], 1),
                                   _checked(e["centre"], 2), _checked(e["variation"], 3),
                                   _checked(e["aperture"], 2, apertures=True))
        fit = (_checked(arrays["poly"], 2), np.asarray(arrays["always"], dtype=bool),
               _checked(arrays["sweep"], 1), edges, float(arrays["rms"]))
        return fit, False
    except (KeyError, ValueError, TypeError):
        return None, True


def _checked(a: np.ndarray, ndim: int, apertures: bool = False) -> np.ndarray:
    """``a`` if it is a numeric array of ``ndim`` dimensions without NaN, and finite unless
    it holds ``apertures`` (a circle's inner radius is -inf), else ValueError."""
    ok = ~np.isnan(a) if apertures else np.isfinite(a)
    if a.ndim != ndim or a.dtype.kind not in "fiu" or not ok.all():
        raise ValueError(f"a stored tile's array has shape {a.shape} and dtype {a.dtype}")
    return a


def _batoid_tiled(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray,
                  y: np.ndarray, band: str, wavelength_nm: float,
                  field_deg: tuple[float, float], tile_deg: float, op: _FitOperator,
                  annulus: np.ndarray):
    """The batoid mapping from its field tile (see above), or None for the direct path."""
    fx, fy = float(field_deg[0]), float(field_deg[1])
    tile = tile_of((fx, fy), tile_deg)
    key = (inst, side, float(defocus_mm), band, float(wavelength_nm), tile, float(tile_deg),
           op)
    if not _tile_wanted(_map_tile_requests, key, (fx, fy), "map"):
        return None
    entry = _cached_tile(
        _MAP_TILE_CACHE, "map", key,
        lambda: _map_tile(inst, side, defocus_mm, x, y, band, wavelength_nm, tile, tile_deg,
                          op, annulus),
        finish=lambda fit: _map_tile_entry(fit, op),
        stored=lambda: (repr(inst), side, float(defocus_mm), band, float(wavelength_nm),
                        tile, float(tile_deg), _points_digest(x, y)))
    if entry is None:
        return None
    (centre, variation), always, sweep, edges, rms = entry
    mono = _tile_monomials(*_tile_local((fx, fy), tile, tile_deg))
    # Rows: x, y, d x/d px, d y/d px, d x/d py, d y/d py (pupil coordinates px, py); the
    # first monomial is the constant 1.
    fxm, fym, jxx, jyx, jxy, jyy = centre + np.tensordot(mono[1:].astype(np.float32),
                                                          variation, axes=1)
    transmitted = _vignetting_in_tile(inst, side, defocus_mm, x, y, band, wavelength_nm,
                                      (fx, fy), mono, always, sweep, edges)
    return (fxm, fym, jxx, jxy, jyx, jyy), transmitted & annulus, rms


# A swept point whose margin to some aperture edge is within this at a star's field is
# traced rather than interpolated: the interpolated ray positions are ~1e-12 m from the
# trace (test_geometry_speed), so this is a million times the error, and about one swept
# point in a thousand is traced.
_EDGE_TRACE_M = 1e-6
# An aperture is kept for a swept point if the point's margin to it comes within this of
# zero anywhere in the tile (the fitted positions on a 17 x 17 field grid); the others
# transmit the point over the whole tile.
_EDGE_KEEP_M = 1e-4


def _aperture(obscuration) -> tuple[float, float, float, float, float] | None:
    """``(x0, y0, inner, outer, sign)`` of a circular or annular aperture (batoid
    obscuration), or None for any other shape.  A ray at distance rho from (x0, y0)
    passes where ``sign * min(outer - rho, rho - inner) > 0``: sign +1 for a clear
    aperture (``ObscNegation`` of a circle or annulus), -1 for a blocking one."""
    import batoid

    sign = -1.0
    if isinstance(obscuration, batoid.ObscNegation):
        obscuration, sign = obscuration.original, 1.0
    if isinstance(obscuration, batoid.ObscCircle):
        return obscuration.x, obscuration.y, -np.inf, obscuration.radius, sign
    if isinstance(obscuration, batoid.ObscAnnulus):
        return obscuration.x, obscuration.y, obscuration.inner, obscuration.outer, sign
    return None


def _edge_margin(x: np.ndarray, y: np.ndarray, aperture: np.ndarray) -> np.ndarray:
    """Signed distance [m] of rays at (x, y) inside the edge of ``aperture``
    (``x0, y0, inner, outer, sign`` along its first axis, see :func:`_aperture`; broadcast
    against x and y): positive where the ray passes."""
    x0, y0, inner, outer, sign = aperture
    rho = np.hypot(x - x0, y - y0)
    return sign * np.minimum(outer - rho, rho - inner)


def _interfaces(optic):
    """The interfaces a trace passes, in order (CompoundOptic.trace's recursion)."""
    import batoid

    for item in optic.items:
        if item.skip:
            continue
        if isinstance(item, batoid.CompoundOptic):
            yield from _interfaces(item)
        else:
            yield item


def _aperture_positions(tel, rv) -> tuple[np.ndarray, np.ndarray] | None:
    """Trace ``rv`` through ``tel`` interface by interface: ``(apertures (5, m), positions
    (m, 2, n) [m])``, each ray's position on each of the m clear apertures in the
    aperture's frame (see :func:`_aperture`).  None if an aperture is not a circle or an
    annulus or a ray fails."""
    stops = [(item, _aperture(item.obscuration)) for item in _interfaces(tel)]
    if any(ap is None for item, ap in stops if item.obscuration is not None):
        return None
    pos = []
    for item, ap in stops:
        item.trace(rv)  # the interaction, then the obscuration, as in tel.trace
        if ap is not None:
            pos.append((rv.x.copy(), rv.y.copy()))
    if rv.failed.any():
        return None
    return np.array([ap for _, ap in stops if ap is not None]).T, np.array(pos)


@dataclass(frozen=True)
class _ApertureEdges:
    """Vignetting of a map tile's swept points from their rays' positions on the apertures.

    A ray is vignetted where it falls outside a clear aperture (mirror annuli, lens and
    filter rims).  Its position on each aperture, in the aperture's frame, is smooth in
    field, so it is fitted per point with the tile's quartic in field like the mapping
    coefficients; at a star's field the positions are evaluated and compared with the
    aperture edges.  Entry ``e`` stands for one (aperture, swept point) pair that comes
    near the edge somewhere in the tile.
    """

    n_points: int
    point: np.ndarray      # (e,) swept point of each entry
    centre: np.ndarray     # (2, e) ray position at the tile centre [m]
    variation: np.ndarray  # (n_mono - 1, 2, e) shares of the other monomials [m]
    aperture: np.ndarray   # (5, e) x0, y0, inner, outer, sign (see _aperture)

    def margins(self, mono: np.ndarray) -> np.ndarray:
        """(e,) signed distance [m] of each entry's ray inside its aperture's edge."""
        pos = self.centre + np.tensordot(mono[1:], self.variation, axes=1)
        return _edge_margin(pos[0], pos[1], self.aperture)

    def transmitted(self, mono: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per swept point at the field of ``mono``: transmitted, and too close to an edge
        to tell (to be traced)."""
        m = self.margins(mono)
        blocked = np.bincount(self.point, weights=m <= 0.0, minlength=self.n_points)
        unsure = np.bincount(self.point, weights=np.abs(m) < _EDGE_TRACE_M,
                             minlength=self.n_points)
        return blocked == 0, unsure > 0


def _aperture_edges(inst: Instrument, side: str, defocus_mm: float, xs: np.ndarray,
                    ys: np.ndarray, band: str, wavelength_nm: float,
                    nodes: list[tuple[float, float]], mono: np.ndarray,
                    node_masks: np.ndarray) -> _ApertureEdges | None:
    """Fit the swept points' aperture positions over a tile (see :class:`_ApertureEdges`).

    None -- the tile's swept points are then traced per star -- if an aperture is not a
    circle or annulus, a ray fails at a node, the fit leaves more than 1e-9 m at the nodes,
    or the edges do not reproduce the traced masks ``node_masks`` (n_nodes, n) exactly.
    """
    pos = []
    for node in nodes:
        traced = _aperture_positions(*_stop_rays(inst, band, wavelength_nm, node, side,
                                                 defocus_mm, xs, ys))
        if traced is None:
            return None
        aps, at = traced
        pos.append(at)
    pos = np.array(pos)  # (n_nodes, n_apertures, 2, n)
    n_nodes, n_ap, _, n = pos.shape
    poly, *_ = np.linalg.lstsq(mono, pos.reshape(n_nodes, -1), rcond=None)
    if np.abs(mono @ poly - pos.reshape(n_nodes, -1)).max() > 1e-9:
        return None
    poly = poly.reshape(len(poly), n_ap, 2, n)

    def margin(p: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Margins of positions p (..., m, 2, n) inside apertures a (5, m): (..., m, n)."""
        return _edge_margin(p[..., 0, :], p[..., 1, :], a[:, :, None])

    if not np.array_equal((margin(pos, aps) > 0).all(axis=1), node_masks):
        return None
    t = np.linspace(-1.0, 1.0, 17)
    fine = _tile_monomials(*(a.ravel() for a in np.meshgrid(t, t)))
    near = np.concatenate([
        margin(np.tensordot(fine, poly[:, k:k + 1], axes=1), aps[:, k:k + 1]).min(axis=0)
        for k in range(n_ap)]) < _EDGE_KEEP_M  # (n_ap, n)
    ap_idx, point = np.nonzero(near)
    kept = poly[:, ap_idx, :, point]  # (e, n_mono, 2)
    return _ApertureEdges(n, point, np.ascontiguousarray(kept[:, 0, :].T),
                          np.ascontiguousarray(kept[:, 1:, :].transpose(1, 2, 0)),
                          np.ascontiguousarray(aps[:, ap_idx]))


def _vignetting_in_tile(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray,
                        y: np.ndarray, band: str, wavelength_nm: float,
                        field_deg: tuple[float, float], mono: np.ndarray,
                        always: np.ndarray, sweep: np.ndarray,
                        edges: _ApertureEdges | None) -> np.ndarray:
    """Transmitted points at ``field_deg`` (tile monomials ``mono``) inside a map tile.

    The tile decides the points transmitted (or vignetted) at all of its nodes; the swept
    points in between are decided by their aperture edges, and only those within
    _EDGE_TRACE_M of an edge are traced (all of them when the tile has no edge model).  The
    masks are those of the direct trace (test_geometry_speed, and 190 random corner fields
    in bench/bench_vignetting_tiles.py); a side costs ~0.3 ms instead of ~5 ms of tracing
    at the LSST corners on the machine of docs/performance.md, Frames.
    """
    transmitted = always.copy()
    if sweep.size == 0:
        return transmitted
    todo = sweep
    if edges is not None:
        tr, unsure = edges.transmitted(mono)
        transmitted[sweep] = tr
        todo = sweep[unsure]
    if todo.size:
        *_, tr = _trace_defocused(inst, band, wavelength_nm, field_deg, side, defocus_mm,
                                  x[todo], y[todo])
        transmitted[todo] = tr
    return transmitted


# -- the paper's poly10 tables (§3.3) ------------------------------------------------------

_POLY10_ORDER = 10


def _poly_exponents(order: int) -> np.ndarray:
    """(a, b) of the terms x^a y^b in the tables' order: by degree d, then x^(d-k) y^k."""
    return np.array([(d - k, k) for d in range(order + 1) for k in range(d + 1)])


@dataclass(frozen=True)
class Poly10Tables:
    """The paper's off-axis mapping and vignetting tables (§3.3), as read from disk.

    Attributes:
        ref_defocus_mm: detector offset of the tabulated intra and extra planes.
        field_radius_deg: field radius of each row (rows lie on the +45° diagonal).
        coef: (4, rows, 66) polynomial coefficients of x'_intra, y'_intra, x'_extra,
            y'_extra in mm over the normalised pupil, in the reference (45°) orientation.
        mask_radius_deg: field radius of each vignetting row.
        mask: (rows, 4) ``ca, ra, cb, rb``: pass circle (centre ca along the field
            direction, radius ra) and block circle (cb, rb), normalised pupil units.
    """

    ref_defocus_mm: float
    field_radius_deg: np.ndarray
    coef: np.ndarray
    mask_radius_deg: np.ndarray
    mask: np.ndarray

    @staticmethod
    def _interp(radius: np.ndarray, rows: np.ndarray, r: float) -> np.ndarray:
        """Linear interpolation in field radius, clamped to the tabulated range."""
        if r <= radius[0]:
            return rows[0]
        if r >= radius[-1]:
            return rows[-1]
        k = int(np.searchsorted(radius, r))
        w = (r - radius[k - 1]) / (radius[k] - radius[k - 1])
        return (1.0 - w) * rows[k - 1] + w * rows[k]

    def coefficients(self, side: str, field_radius_deg: float,
                     defocus_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """x' and y' polynomial coefficients (mm) of one side at a field radius and offset.

        The tabulated planes sit at z = -l_ref (intra) and +l_ref (extra); between them a
        ray is straight, so the coefficients are linear in the detector offset z.
        """
        c = np.stack([self._interp(self.field_radius_deg, self.coef[k], field_radius_deg)
                      for k in range(4)])
        z = -_side_sign(side) * defocus_mm  # intra: detector before focus
        t = (self.ref_defocus_mm - z) / (2.0 * self.ref_defocus_mm)  # 1 at intra, 0 at extra
        return c[2] + t * (c[0] - c[2]), c[3] + t * (c[1] - c[3])

    def vignetting(self, field_radius_deg: float) -> np.ndarray:
        """``ca, ra, cb, rb`` at a field radius (linear interpolation, clamped)."""
        return self._interp(self.mask_radius_deg, self.mask, field_radius_deg)


@lru_cache(maxsize=8)
def poly10_tables(directory: str) -> Poly10Tables:
    """Read the poly10 tables from ``directory`` (relative to ``config/instruments``)."""
    d = Path(directory)
    if not d.is_absolute():
        d = config_dir() / "instruments" / d
    try:
        rows = [np.loadtxt(d / f"offAxis_c{a}{s}_poly{_POLY10_ORDER}.txt", ndmin=2)
                for s in ("in", "ex") for a in ("x", "y")]
        mask = np.loadtxt(d / "mask_migrate.txt", ndmin=2)
    except OSError as exc:
        raise ConfigError(f"cannot read poly10 mapping tables in {d}: {exc}") from exc
    nterm = len(_poly_exponents(_POLY10_ORDER))
    if any(r.shape != rows[0].shape or r.shape[1] != 3 + nterm for r in rows) or \
            mask.shape[1] != 5:
        raise ConfigError(f"poly10 tables in {d} have unexpected shapes")
    radius = np.hypot(rows[0][:, 1], rows[0][:, 2])
    return Poly10Tables(float(rows[0][0, 0]) * 1e3, radius,
                        np.stack([r[:, 3:] for r in rows]), np.sqrt(2.0) * mask[:, 0],
                        mask[:, 1:])


def _poly10(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray,
            field_deg: tuple[float, float]):
    """Paper §3.3 mapping from the poly10 tables, rotated to the field azimuth.

    The tables hold the field on the +45° diagonal; for a field at azimuth phi the pupil is
    rotated by -(phi - 45°) into that reference orientation, mapped, and the image position
    rotated back (and the Jacobian with it: ``J = R J_0 R^T``).  Returns the mapping parts
    in pixels and the transmitted mask.
    """
    tab = poly10_tables(str(inst.mapping_tables))
    fr = float(np.hypot(*field_deg))
    theta = (np.arctan2(field_deg[1], field_deg[0]) if fr > 0 else np.pi / 4) - np.pi / 4
    ct, st = np.cos(theta), np.sin(theta)
    x0 = ct * x + st * y
    y0 = -st * x + ct * y
    # The polynomials were fitted over the annulus only, and a 10th-order polynomial
    # diverges quickly outside it; the computation boundary beyond the pupil edges is
    # mapped by first-order extrapolation from the nearest edge point instead.
    r = np.hypot(x0, y0)
    scale = np.clip(r, inst.obscuration, 1.0) / np.where(r > 0, r, 1.0)
    xc, yc = x0 * scale, y0 * scale
    cx, cy = tab.coefficients(side, fr, defocus_mm)
    exps = _poly_exponents(_POLY10_ORDER)
    a, b = exps[:, 0], exps[:, 1]
    xp = np.vstack([xc**p for p in range(_POLY10_ORDER + 1)])
    yp = np.vstack([yc**p for p in range(_POLY10_ORDER + 1)])
    mono = xp[a] * yp[b]
    # d/dx0 and d/dy0 of each monomial (exponent 0 terms vanish through the factor).
    mdx = a[:, None] * xp[np.maximum(a - 1, 0)] * yp[b]
    mdy = b[:, None] * xp[a] * yp[np.maximum(b - 1, 0)]
    mm_to_px = 1e3 / inst.pixel_size_um
    j0 = np.array([[cx @ mdx, cx @ mdy], [cy @ mdx, cy @ mdy]]) * mm_to_px
    ex, ey = x0 - xc, y0 - yc
    hx0 = cx @ mono * mm_to_px + j0[0, 0] * ex + j0[0, 1] * ey
    hy0 = cy @ mono * mm_to_px + j0[1, 0] * ex + j0[1, 1] * ey
    rot = np.array([[ct, -st], [st, ct]])
    hx = ct * hx0 - st * hy0
    hy = st * hx0 + ct * hy0
    j = np.einsum("ik,klp,jl->ijp", rot, j0, rot)
    # Vignetting: pass inside circle a, block inside circle b, centred on the field direction.
    ca, ra, cb, rb = tab.vignetting(fr)
    ux, uy = np.cos(theta + np.pi / 4), np.sin(theta + np.pi / 4)
    transmitted = (np.hypot(x - ca * ux, y - ca * uy) <= ra) & \
        (np.hypot(x - cb * ux, y - cb * uy) >= rb)
    return (hx, hy, j[0, 0], j[0, 1], j[1, 0], j[1, 1]), transmitted


def nominal_mapping(inst: Instrument, side: str, x: np.ndarray, y: np.ndarray, *,
                    defocus_mm: float, band: str | None = None,
                    wavelength_nm: float | None = None,
                    field_deg: tuple[float, float] = (0.0, 0.0),
                    tile_deg: float = 0.0) -> ImageMapping:
    """The unperturbed mapping of ``inst`` for one image side at pupil points (x, y).

    Args:
        inst: the instrument; its ``mapping`` field selects the model.
        side: ``"intra"`` (detector at -defocus) or ``"extra"`` (+defocus).
        x, y: reduced pupil coordinates (1-D arrays).
        defocus_mm: |detector offset| l.
        band, wavelength_nm: optical band and wavelength (batoid model only).
        field_deg: field angle (x, y) of the star in degrees (batoid and poly10 models).
        tile_deg: batoid only: interpolate the mapping within field tiles of this side
            (:func:`_batoid_tiled`); 0 traces every field directly.
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    rms = 0.0
    if inst.mapping == "paraxial":
        parts = _paraxial(inst, side, defocus_mm, x, y)
        transmitted = _annulus(inst, x, y)
    elif inst.mapping == "fastbeam":
        parts = _fastbeam(inst, side, defocus_mm, x, y)
        transmitted = _annulus(inst, x, y)
    elif inst.mapping == "poly10":
        parts, transmitted = _poly10(inst, side, defocus_mm, x, y,
                                     (float(field_deg[0]), float(field_deg[1])))
        transmitted = transmitted & _annulus(inst, x, y)
    else:
        band = band or inst.default_band
        wl = inst.wavelength_nm(band, wavelength_nm)
        args = (inst, side, defocus_mm, x, y, band, wl,
                (float(field_deg[0]), float(field_deg[1])))
        # (_batoid's transmitted points are already within the annulus.)
        if tile_deg > 0:
            parts, transmitted, rms = _batoid(*args, tile_deg=float(tile_deg))
        else:
            parts, transmitted, rms = _batoid(*args)
    return ImageMapping(side, *parts, transmitted=transmitted,
                        c_px_per_nm=_c_px_per_nm(inst, side, defocus_mm), fit_rms_px=rms)


# The rays' positions on the apertures as polynomials in the reduced pupil coordinates, at
# one field (:class:`_PupilApertures`): total degree, and the side of the square lattice of
# rays traced to fit them.  Degree 10 on 21 x 21 (224 rays in the annulus) leaves ~3e-8 m
# at the LSST corners, degree 8 ~1e-6 m and degree 6 ~1e-5 m (the camera's lenses in the
# fast beam are far from affine in the pupil).
_PUPIL_FIT_DEGREE = 10
_PUPIL_FIT_LATTICE = 21
# The fit is used only if it reproduces its own lattice to this (else every point is traced).
_PUPIL_FIT_MAX_RESID_M = 1e-7


@dataclass(frozen=True)
class _PupilApertures:
    """The positions of the rays from any reduced pupil point on the clear apertures, at
    one field and side: a polynomial fit to a lattice of traced rays."""

    exponents: np.ndarray  # (k, 2) x and y powers of the monomials
    coef: np.ndarray       # (k, 2 m) monomials' coefficients [m] of (x, y) per aperture
    aperture: np.ndarray   # (5, m) see _aperture

    def margins(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(m, n) signed distance [m] of each point's ray inside each aperture's edge."""
        pos = (self.coef.T @ _monomials(x, y, self.exponents)).reshape(
            self.aperture.shape[1], 2, x.size)
        return _edge_margin(pos[:, 0], pos[:, 1], self.aperture[:, :, None])


def _monomials(x: np.ndarray, y: np.ndarray, exponents: np.ndarray) -> np.ndarray:
    """(k, n) x^a y^b for the exponents (a, b), from the powers of x and y (no pow calls;
    one contiguous row per monomial, which is what the product with the coefficients
    wants)."""
    deg = int(exponents.max()) + 1
    px = np.ones((deg, x.size))
    py = np.ones((deg, x.size))
    for d in range(1, deg):
        np.multiply(px[d - 1], x, out=px[d])
        np.multiply(py[d - 1], y, out=py[d])
    out = np.empty((len(exponents), x.size))
    for k, (a, b) in enumerate(exponents):
        np.multiply(px[a], py[b], out=out[k])
    return out


@lru_cache(maxsize=4)
def _pupil_lattice(obscuration: float) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                np.ndarray, np.ndarray, np.ndarray]:
    """The lattice of :func:`_pupil_apertures` (x, y; the annulus and one step beyond),
    the monomials' exponents, their values on it (n, k) and its pseudo-inverse, and each
    lattice point's right and upper neighbour (index, -1 if off the lattice)."""
    t = np.linspace(-1.02, 1.02, _PUPIL_FIT_LATTICE)
    lx, ly = (a.ravel() for a in np.meshgrid(t, t))
    r = np.hypot(lx, ly)
    on = (r <= 1.03) & (r >= obscuration - 0.03)
    index = np.full(on.size, -1)
    index[on] = np.arange(int(on.sum()))
    grid = index.reshape(_PUPIL_FIT_LATTICE, _PUPIL_FIT_LATTICE)
    right = np.full_like(grid, -1)
    up = np.full_like(grid, -1)
    right[:, :-1] = grid[:, 1:]
    up[:-1] = grid[1:]
    exponents = np.array([(a, d - a) for d in range(_PUPIL_FIT_DEGREE + 1)
                          for a in range(d + 1)])
    basis = _monomials(lx[on], ly[on], exponents).T
    return (lx[on], ly[on], exponents, basis, np.linalg.pinv(basis),
            np.stack([right.ravel()[on], up.ravel()[on]]))


def _pupil_fit_at(inst: Instrument, band: str, wavelength_nm: float,
                  field_deg: tuple[float, float], side: str,
                  defocus_mm: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``(apertures (5, m), coefficients (k, 2 m))`` of the rays' aperture positions as
    polynomials in the pupil at one field, from the traced lattice; None when an aperture is
    not a circle or annulus, a ray fails, or the fit misses its lattice by more than
    _PUPIL_FIT_MAX_RESID_M."""
    lx, ly, _, basis, pinv, _ = _pupil_lattice(float(inst.obscuration))
    traced = _aperture_positions(*_stop_rays(inst, band, wavelength_nm, field_deg, side,
                                             defocus_mm, lx, ly))
    if traced is None:
        return None
    aps, pos = traced  # (5, m), (m, 2, n)
    rhs = pos.reshape(-1, lx.size).T  # (n, 2 m)
    coef = pinv @ rhs
    if np.abs(basis @ coef - rhs).max() > _PUPIL_FIT_MAX_RESID_M:
        return None
    return aps, coef


def _pupil_apertures_from(obscuration: float, aps: np.ndarray,
                          coef: np.ndarray) -> _PupilApertures:
    """The :class:`_PupilApertures` of fitted coefficients, with only the apertures that
    some pupil point can come near: an aperture is left out when every lattice ray passes
    it by more than twice the largest step between neighbouring lattice rays on it (every
    pupil point lies within a lattice cell, so its ray passes too)."""
    lx, _, exponents, basis, _, neighbours = _pupil_lattice(obscuration)
    pos = (basis @ coef).T.reshape(aps.shape[1], 2, lx.size)
    margin = _edge_margin(pos[:, 0], pos[:, 1], aps[:, :, None])  # (m, n)
    step = np.zeros(len(pos))
    for nb in neighbours:
        ok = nb >= 0
        d = np.hypot(*(pos[:, :, ok] - pos[:, :, nb[ok]]).transpose(1, 0, 2))
        step = np.maximum(step, d.max(axis=1))
    keep = np.flatnonzero(margin.min(axis=1) < 2.0 * step)
    cols = np.stack([2 * keep, 2 * keep + 1], axis=1).ravel()
    return _PupilApertures(exponents, np.ascontiguousarray(coef[:, cols]), aps[:, keep])


_pupil_tile_requests: dict[tuple, set[tuple[float, float]]] = {}
_PUPIL_TILE_CACHE: dict[tuple, tuple | None] = {}
# Largest difference [m] between a node's traced lattice positions and the tile's field
# polynomial there; the tile is not used beyond it (the fit is ~1e-12 m at the corners).
_PUPIL_TILE_MAX_RESID_M = 1e-9


def _pupil_tile(inst: Instrument, band: str, wavelength_nm: float, side: str,
                defocus_mm: float, tile: tuple[int, int],
                tile_deg: float) -> tuple | None:
    """(apertures, coefficient polynomial (n_mono, k, 2 m)) over a field tile: the pupil
    fits of its 5 x 5 nodes, fitted with the tile's quartic in field; None if a node has no
    pupil fit, the nodes do not share their apertures, or the quartic misses a node."""
    u, v, nodes = _tile_nodes(tile, tile_deg, _MAP_TILE_NODES)
    fits = [_pupil_fit_at(inst, band, wavelength_nm, node, side, defocus_mm)
            for node in nodes]
    if any(f is None for f in fits) or any(not np.array_equal(f[0], fits[0][0])
                                           for f in fits):
        return None
    coefs = np.array([f[1] for f in fits])  # (n_nodes, k, 2 m)
    mono = _tile_monomials(u, v)
    poly, *_ = np.linalg.lstsq(mono, coefs.reshape(len(nodes), -1), rcond=None)
    basis = _pupil_lattice(float(inst.obscuration))[3]
    miss = (mono @ poly).reshape(coefs.shape) - coefs
    if np.abs(np.einsum("lk,nkc->nlc", basis, miss)).max() > _PUPIL_TILE_MAX_RESID_M:
        return None
    return fits[0][0], poly.reshape(len(poly), *coefs.shape[1:])


def _pupil_apertures(inst: Instrument, band: str, wavelength_nm: float,
                     field_deg: tuple[float, float], side: str, defocus_mm: float,
                     tile_deg: float = 0.0) -> _PupilApertures | None:
    """:class:`_PupilApertures` at one field and side: fitted to a traced lattice (~4 ms),
    or with ``tile_deg`` > 0 read from the field tile's polynomial (~0.3 ms; the tile's
    first fields are traced, as for the map tiles).  None: trace every point."""
    if tile_deg > 0:
        tile = tile_of(field_deg, tile_deg)
        key = (inst, side, float(defocus_mm), band, float(wavelength_nm), tile,
               float(tile_deg))
        if _tile_wanted(_pupil_tile_requests, key, field_deg, "pupil"):
            entry = _cached_tile(_PUPIL_TILE_CACHE, "pupil", key,
                                 lambda: _pupil_tile(inst, band, wavelength_nm, side,
                                                     defocus_mm, tile, tile_deg),
                                 stored=lambda: (repr(inst), *key[1:]))
            if entry is not None:
                aps, poly = entry
                mono = _tile_monomials(*_tile_local(field_deg, tile, tile_deg))
                return _pupil_apertures_from(float(inst.obscuration), aps,
                                             np.tensordot(mono, poly, axes=1))
    fit = _pupil_fit_at(inst, band, wavelength_nm, field_deg, side, defocus_mm)
    return None if fit is None else _pupil_apertures_from(float(inst.obscuration), *fit)


def pupil_transmission(inst: Instrument, side: str, x: np.ndarray, y: np.ndarray, *,
                       defocus_mm: float, band: str | None = None,
                       wavelength_nm: float | None = None,
                       field_deg: tuple[float, float] = (0.0, 0.0),
                       tile_deg: float = 0.0) -> np.ndarray:
    """Whether the rays from reduced pupil points (x, y) reach the detector of one side:
    the annulus, and the instrument's vignetting at ``field_deg`` (poly10: its circles).
    For points off the pupil grid, e.g. near a vignetting edge
    (:func:`cwfs_ros.wfs.blur.design_donut`).

    batoid: the rays' positions on the clear apertures come from a polynomial in the pupil
    fitted to 224 traced rays at this field (:class:`_PupilApertures`, ~3e-8 m from the
    trace at the LSST corners), or with ``tile_deg`` > 0 to those of its field tile's nodes
    and interpolated in field (:func:`_pupil_tile`); a point within _EDGE_TRACE_M of an
    edge is traced, and so is every point where the optic's apertures are not circles or
    annuli.  The answer is the trace's (test_blur).  The blur reference's ~3,000 edge
    points a side cost ~8 ms so, ~4 ms from a tile, against ~13 ms of tracing.
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    inside = _annulus(inst, x, y)
    if inst.mapping in ("paraxial", "fastbeam") or not x.size:
        return inside
    fld = (float(field_deg[0]), float(field_deg[1]))
    if inst.mapping == "poly10":
        return inside & _poly10(inst, side, defocus_mm, x, y, fld)[1]
    band = band or inst.default_band
    wl = inst.wavelength_nm(band, wavelength_nm)
    fit = _pupil_apertures(inst, band, wl, fld, side, float(defocus_mm), float(tile_deg))
    if fit is None:
        return inside & _trace_defocused(inst, band, wl, fld, side, defocus_mm, x, y)[3]
    m = fit.margins(x, y)
    out = inside & (m > 0.0).all(axis=0)
    unsure = np.flatnonzero(inside & (np.abs(m) < _EDGE_TRACE_M).any(axis=0))
    if unsure.size:
        out[unsure] = _trace_defocused(inst, band, wl, fld, side, defocus_mm, x[unsure],
                                       y[unsure])[3]
    return out


@lru_cache(maxsize=256)
def design_zernikes_nm(inst: Instrument, band: str, wavelength_nm: float,
                       field_deg: tuple[float, float], jmax: int) -> np.ndarray:
    """Design (intrinsic) wavefront Z1..Z_jmax in nm at a field point; zeros if not ray-traced.

    Uses ``batoid.zernike``: the annular Zernike fit (the instrument's obscuration) of the
    in-focus design telescope's wavefront over the *unvignetted* rays, on a 128x128 pupil
    grid.  The Gaussian-quadrature variant (``zernikeGQ``) integrates over the full annulus
    including vignetted rays; at the FAM edge fields it is 8 nm rms further from the ZEMAX
    truth (1.8 nm with this one), and it disagrees with the simulator's truth by up to 7 nm
    at the corner sensors.
    """
    out = np.zeros(jmax)
    if inst.mapping != "batoid":
        return out
    import batoid

    tel = _batoid_telescope(inst.batoid_optic, band)
    wl = wavelength_nm * 1e-9
    try:
        z = batoid.zernike(tel, np.deg2rad(field_deg[0]), np.deg2rad(field_deg[1]), wl,
                           jmax=jmax, eps=inst.obscuration, nx=128)
    except RuntimeError as exc:  # batoid: too few unvignetted rays to fit every term
        r = float(np.hypot(*field_deg))
        raise ConfigError(
            f"the design wavefront cannot be fitted at field ({field_deg[0]:.4g}, "
            f"{field_deg[1]:.4g}) deg, {r:.3f} deg off axis: the pupil is vignetted there "
            f"beyond what Z1..Z{jmax} can describe (batoid: {exc}). Check the field; a "
            "wavefront is estimated only where the design one can be fitted") from None
    out[:] = z[1:] * wavelength_nm
    out.setflags(write=False)
    return out


# -- design wavefront interpolated in field ----------------------------------------------
#
# ``design_zernikes_nm`` traces a 128x128 in-focus pupil per field (~30 ms), and every pair
# of new star fields has a new mid-point.  The design wavefront is smooth in field: over the
# corners' 0.125 deg tiles a quartic in field leaves ~0.1 nm (near the pixelation of the
# direct fit itself).  The field plane is cut into square tiles; each tile's design
# Zernikes are fitted once by a 2-D quartic to a 5x5 grid of direct evaluations, and a tile
# whose fit leaves more than _DESIGN_TILE_MAX_RESID_NM at its nodes falls back to the
# direct trace.  A tile costs 25 direct traces (~0.7 s), so it is fitted only at the
# _DESIGN_TILE_AFTER-th distinct field asking for it; earlier fields are traced directly
# (the first estimate of a process stays as fast as before).  Whichever is used, a pair's
# departure from design (estimate minus this design wavefront) does not change: the design
# wavefront is only added back at the end.

_DESIGN_TILE_NODES = 5
_DESIGN_TILE_DEGREE = 4
_DESIGN_TILE_MAX_RESID_NM = 0.25
_DESIGN_TILE_AFTER = 3
_design_tile_requests: dict[tuple, set[tuple[float, float]]] = {}
# Number of tiles fitted (tests read it to check the cache is reused).
design_tile_builds = 0


def reset_field_tiles() -> None:
    """Forget every field tile and the fields each tile has seen, as in a fresh process.

    A tile serves a field from its third distinct field on (the first two are traced), and
    it differs from the direct trace by up to ~1e-7 px (mapping) and ~0.2 nm (design), so
    an estimate can move by ~0.1 nm with the history of the process it runs in.
    :func:`cwfs_ros.cli.replay.replay` starts from here, as a freshly started node's workers do.
    """
    _map_tile_requests.clear()
    _MAP_TILE_CACHE.clear()
    _design_tile_requests.clear()
    _DESIGN_TILE_CACHE.clear()
    _pupil_tile_requests.clear()
    _PUPIL_TILE_CACHE.clear()
    _WARMED_TILES.clear()
    for counts in _TILE_COUNTS.values():
        counts[:] = [0, 0, 0, 0, 0]


def tile_of(field_deg: tuple[float, float], tile_deg: float) -> tuple[int, int]:
    """Index (i, j) of the ``tile_deg`` field tile holding ``field_deg`` [deg]."""
    return (int(np.floor(field_deg[0] / tile_deg)), int(np.floor(field_deg[1] / tile_deg)))


def tile_centre(tile: tuple[int, int], tile_deg: float) -> tuple[float, float]:
    """Field [deg] at the centre of field tile ``tile``."""
    return ((tile[0] + 0.5) * tile_deg, (tile[1] + 0.5) * tile_deg)


def warm_field_tiles(inst: Instrument, x: np.ndarray, y: np.ndarray, *,
                     side_tiles: dict[str, Iterable[tuple[int, int]]],
                     mid_tiles: Iterable[tuple[int, int]], defocus_mm: float, band: str,
                     wavelength_nm: float, tile_deg: float, design_tile_deg: float,
                     jmax: int) -> int:
    """Build the map and pupil tiles (``tile_deg``) of each side's field tiles, for the
    pupil points x, y, and the design tiles (``design_tile_deg``) of ``mid_tiles``, and let
    them serve every field in them from now on (without the first-fields rule).

    The caches grow to hold them all, with 16 tiles of each kind to spare for fields beyond
    (:func:`size_field_tile_caches`). Returns the number of tiles built (0 when every one was
    already held, or the instrument is not ray-traced).
    """
    global _warming
    side_tiles = {side: sorted(set(tiles)) for side, tiles in side_tiles.items()}
    mid_tiles = sorted(set(mid_tiles)) if design_tile_deg > 0 else []
    if inst.mapping != "batoid" or tile_deg <= 0:
        return 0
    n_side = sum(len(t) for t in side_tiles.values())
    size_field_tile_caches(len(_MAP_TILE_CACHE) + n_side + 16,
                           len(_PUPIL_TILE_CACHE) + n_side + 16,
                           len(_DESIGN_TILE_CACHE) + len(mid_tiles) + 16)
    before = sum(c[1] for c in _TILE_COUNTS.values())
    _warming = True
    try:
        for side, tiles in side_tiles.items():
            for tile in tiles:
                centre = tile_centre(tile, tile_deg)
                nominal_mapping(inst, side, x, y, defocus_mm=defocus_mm, band=band,
                                wavelength_nm=wavelength_nm, field_deg=centre,
                                tile_deg=tile_deg)
                _pupil_apertures(inst, band, wavelength_nm, centre, side, float(defocus_mm),
                                 float(tile_deg))
        for tile in mid_tiles:
            design_zernikes_tiled(inst, band, wavelength_nm,
                                  tile_centre(tile, design_tile_deg), jmax, design_tile_deg)
    finally:
        _warming = False
    return sum(c[1] for c in _TILE_COUNTS.values()) - before


def _tile_local(field_deg: tuple[float, float], tile: tuple[int, int],
                tile_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates of a field in its tile, -1..1 across the tile."""
    half = 0.5 * tile_deg
    cx, cy = tile_centre(tile, tile_deg)
    return np.array((field_deg[0] - cx) / half), np.array((field_deg[1] - cy) / half)


def _tile_nodes(tile: tuple[int, int], tile_deg: float, n: int
                ) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float]]]:
    """The n x n node grid of a tile: local (u, v) and the node fields [deg]."""
    t = np.linspace(-1.0, 1.0, n)
    u, v = (a.ravel() for a in np.meshgrid(t, t))
    cx, cy = tile_centre(tile, tile_deg)
    half = 0.5 * tile_deg
    return u, v, [(float(cx + half * a), float(cy + half * b))
                  for a, b in zip(u, v, strict=True)]


def _tile_wanted(requests: dict[tuple, set[tuple[float, float]]], key: tuple,
                 field: tuple[float, float], kind: str) -> bool:
    """Whether a tile should serve ``field``: not for the tile's first
    ``_DESIGN_TILE_AFTER - 1`` distinct fields, which keep the direct value, unless the tile
    was warmed (:func:`warm_field_tiles`): then for every field, so that an estimate does not
    depend on what the process estimated before."""
    if key in _WARMED_TILES:
        return True
    if _warming:
        _WARMED_TILES.add(key)
        return True
    seen = requests.setdefault(key, set())
    if field not in seen and len(seen) < _DESIGN_TILE_AFTER - 1:
        seen.add(field)
    wanted = field not in seen
    if not wanted:
        _TILE_COUNTS[kind][3] += 1
    return wanted


def _tile_monomials(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    if np.ndim(u) == 0 and np.ndim(v) == 0:
        # One field (every star): the powers by the same numpy calls as below (to the bit:
        # a square is a product there, and another power pow()), the products in Python
        # floats, without thirty numpy calls on 0-d arrays.
        uv = np.array([float(u), float(v)])
        pu, pv = zip(*((float(p[0]), float(p[1]))
                       for p in (uv ** k for k in range(_DESIGN_TILE_DEGREE + 1))),
                     strict=True)
        return np.array([pu[a] * pv[d - a] for d in range(_DESIGN_TILE_DEGREE + 1)
                         for a in range(d + 1)])
    return np.stack([u**a * v**(d - a) for d in range(_DESIGN_TILE_DEGREE + 1)
                     for a in range(d + 1)], axis=-1)


_DESIGN_TILE_CACHE: dict[tuple, np.ndarray | None] = {}


def _design_tile(inst: Instrument, band: str, wavelength_nm: float, tile: tuple[int, int],
                 tile_deg: float, jmax: int) -> np.ndarray | None:
    """Polynomial coefficients (n_mono, jmax) of one tile's design Zernikes, or None."""
    global design_tile_builds
    design_tile_builds += 1
    u, v, nodes = _tile_nodes(tile, tile_deg, _DESIGN_TILE_NODES)
    z = np.array([design_zernikes_nm(inst, band, wavelength_nm, node, jmax)
                  for node in nodes])
    mono = _tile_monomials(u, v)
    coef, *_ = np.linalg.lstsq(mono, z, rcond=None)
    if np.abs(mono @ coef - z).max() > _DESIGN_TILE_MAX_RESID_NM:
        return None
    coef.setflags(write=False)
    return coef


def design_zernikes_tiled(inst: Instrument, band: str, wavelength_nm: float,
                          field_deg: tuple[float, float], jmax: int,
                          tile_deg: float) -> np.ndarray:
    """:func:`design_zernikes_nm` interpolated within ``tile_deg`` tiles (0: direct)."""
    if inst.mapping != "batoid" or tile_deg <= 0:
        return design_zernikes_nm(inst, band, wavelength_nm, field_deg, jmax)
    fx, fy = float(field_deg[0]), float(field_deg[1])
    tile = tile_of((fx, fy), tile_deg)
    key = (inst, band, float(wavelength_nm), tile, float(tile_deg), int(jmax))
    if not _tile_wanted(_design_tile_requests, key, (fx, fy), "design"):
        return design_zernikes_nm(inst, band, wavelength_nm, (fx, fy), jmax)
    coef = _cached_tile(_DESIGN_TILE_CACHE, "design", key, lambda: _design_tile(*key),
                        stored=lambda: (repr(inst), *key[1:]))
    if coef is None:
        return design_zernikes_nm(inst, band, wavelength_nm, (fx, fy), jmax)
    out = _tile_monomials(*_tile_local((fx, fy), tile, tile_deg)) @ coef
    out.setflags(write=False)
    return out
