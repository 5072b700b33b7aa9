"""Plausibility of a visit's corner wavefronts, from the telescope's physics (no ROS).

A corner sensor measures the total wavefront: the design (intrinsic) wavefront of the band at
the corner, plus what the telescope's 50 degrees of freedom add. Within the DoF strokes
(``config/ofc/dof.yaml`` ``range``), the sensitivity matrix ``A`` (nm per DoF unit at the four
corners, :func:`cwfs_ros.ofc.control.sensitivity_for_source`) bounds what the DoF can add to
term ``i``: the largest of ``|A_i . x|`` over the box ``|x_j| <= range_j`` is
``sum_j |A_ij| range_j`` (a linear function's maximum over a box is at a vertex).  Each term
is then bounded by

    bound_i = |design_i| + sum_j |A_ij| range_j + margin_nm + n_sigma * uncertainty_i

where ``margin_nm`` covers what the 50-DoF model leaves out (the second-order response to
large strokes, mirror figure beyond the modelled bending modes, the estimator's systematic
error) and ``n_sigma * uncertainty_i`` the estimator noise that the measurement reports.  A
term beyond its bound is no telescope state's wavefront: the visit is refused
(``implausible_wavefront``), naming the corner, the term and the figures.

A corner flagged valid whose 19 terms have an rms below ``min_corner_rms_nm`` carries no
measurement (zeros, denormals, 1e-30): every estimate holds the design wavefront and photon
noise of a nanometre or more.  It is refused too (``no_measurement``); so is a valid corner
whose producer reports uncertainties and pair counts but gives none for it
(``no_uncertainty``).

The bounds are linear in the matrix: with the bundled matrix (r band) they run from about
277 um (Z4: M2 and camera piston move focus by microns per micron) down to ~80 nm for
Z20-Z22 before the margin; a vector of +-19999 nm in every term is beyond them in Z9-Z22.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cwfs_ros import layout
from cwfs_ros.layout import CORNERS, N_ZK
from cwfs_ros.ofc import control as C

__all__ = ["PlausibilityBounds", "Verdict", "VisitGuard", "check_vector", "physical_bounds"]



@dataclass(frozen=True)
class PlausibilityBounds:
    """Per-term bounds of the 76-vector, before the noise margin.

    Attributes:
        design_nm: (76,) |intrinsic wavefront| of the band at the matrix's field points.
        reach_nm: (76,) largest |wavefront| the DoF can add within their strokes.
        margin_nm: added to every term (model and estimator systematics).
        band, source: what they were computed for.
    """

    design_nm: np.ndarray
    reach_nm: np.ndarray
    margin_nm: float
    band: str
    source: str

    def bound_nm(self, uncertainty_nm: np.ndarray | None = None,
                 n_sigma: float = 5.0) -> np.ndarray:
        """(76,) per-term bound, with ``n_sigma`` x the reported uncertainty (0 = none)."""
        b = self.design_nm + self.reach_nm + self.margin_nm
        if uncertainty_nm is not None:
            u = np.nan_to_num(np.abs(np.asarray(uncertainty_nm, dtype=np.float64)),
                              nan=0.0, posinf=0.0)
            b = b + n_sigma * u
        return b


def physical_bounds(band: str = "r", source: str = "bundled", margin_nm: float = 300.0,
                    *, dof_range: np.ndarray | None = None) -> PlausibilityBounds:
    """The bounds of :mod:`this module <cwfs_ros.ofc.plausibility>` for a band and matrix.

    Args:
        band: band of the design wavefront (``u g r i z y`` or ``ref``).
        source: sensitivity matrix (``bundled`` or ``ts_ofc``).
        margin_nm: added to every term.
        dof_range: (50,) DoF strokes; default ``config/ofc/dof.yaml``'s ``range``.
    """
    sens = C.sensitivity_for_source(source)
    a = np.asarray(sens.matrix_nm, dtype=np.float64)
    rng = C.load_dof_spec().range if dof_range is None else np.asarray(dof_range, float)
    if rng.shape != (a.shape[1],) or np.any(~np.isfinite(rng)) or np.any(rng < 0):
        raise ValueError(f"dof_range must be {a.shape[1]} finite values >= 0")
    reach = np.abs(a) @ rng
    fields = sens.field_points_deg
    design = np.abs(C.intrinsic_vector_nm(band, fields))
    if design.shape != reach.shape:
        raise ValueError(f"design wavefront {design.shape} and matrix rows {reach.shape} differ")
    return PlausibilityBounds(_rotation_invariant(design), _rotation_invariant(reach),
                              float(margin_nm), str(band), str(source))


def _rotation_invariant(bound: np.ndarray) -> np.ndarray:
    """Each (cos, sin) pair of a corner's terms bounded by the pair's hypotenuse.

    The corners report Zernikes in the camera frame, which the rotator turns: a rotation
    mixes the two terms of an azimuthal pair, so each can reach the pair's norm.
    """
    from cwfs_ros.ofc.rotation import noll_to_nm

    out = np.asarray(bound, dtype=np.float64).reshape(-1, N_ZK).copy()
    js = list(range(layout.NOLL_MIN, layout.NOLL_MAX + 1))
    for i, j in enumerate(js):
        n, m = noll_to_nm(j)
        if m > 0:  # its partner has the same n and -m
            k = next(k for k, jj in enumerate(js) if noll_to_nm(jj) == (n, -m))
            h = np.hypot(out[:, i], out[:, k])
            out[:, i] = out[:, k] = h
    return out.reshape(-1)


@dataclass(frozen=True)
class Verdict:
    """Outcome of :func:`check_vector`: ``ok``, or ``reason`` and a sentence saying why."""

    ok: bool
    reason: str = ""
    message: str = ""

    @property
    def status(self) -> str:
        return "ok" if self.ok else f"{self.reason}: {self.message}"


def _corner_problem(k: int, z: np.ndarray, unc: np.ndarray | None, n_pairs: int | None,
                    bound: np.ndarray, min_rms_nm: float, reports: bool) -> Verdict | None:
    sl = slice(k * N_ZK, (k + 1) * N_ZK)
    zc = z[sl]
    name = CORNERS[k]
    if not np.all(np.isfinite(zc)):
        return None  # the layout and finiteness checks of the solver name that
    with np.errstate(over="ignore"):  # 1e308 squared: inf, which is not small
        rms = float(np.sqrt(np.mean(zc * zc)))
    if rms < min_rms_nm:
        return Verdict(False, "no_measurement", f"corner {name} is flagged valid but its 19 "
                       f"terms have an rms of {rms:.3g} nm (< {min_rms_nm:g} nm): no "
                       "estimate is that small (the design wavefront and photon noise alone "
                       "exceed it)")
    if reports:
        uc = None if unc is None else unc[sl]
        if n_pairs is not None and n_pairs <= 0:
            return Verdict(False, "no_uncertainty", f"corner {name} is flagged valid with 0 "
                           "donut pairs, from a producer that reports pair counts")
        if uc is None or not np.any(np.isfinite(uc) & (uc > 0)):
            return Verdict(False, "no_uncertainty", f"corner {name} is flagged valid without "
                           "an uncertainty, from a producer that reports them")
    over = np.abs(zc) > bound[sl]
    if np.any(over):
        i = int(np.argmax(np.abs(zc) / bound[sl]))
        return Verdict(False, "implausible_wavefront", f"corner {name} Z{i + 4} = "
                       f"{zc[i]:.6g} nm is beyond {bound[sl][i]:.4g} nm, the design "
                       "wavefront plus the most the DoF can add within their strokes plus "
                       "the noise margin: no telescope state gives it "
                       f"({int(over.sum())} of 19 terms over)")
    return None


def check_vector(z_nm: np.ndarray, corner_valid: np.ndarray, bounds: PlausibilityBounds, *,
                 uncertainty_nm: np.ndarray | None = None,
                 n_pairs: np.ndarray | None = None, n_sigma: float = 5.0,
                 min_corner_rms_nm: float = 0.01) -> Verdict:
    """Judge the valid corners of a 76-vector (corner-major, Noll 4..22, nm).

    A producer *reports* uncertainties when any of ``uncertainty_nm`` is non-zero or any
    ``n_pairs`` is non-zero (the message's zeros mean "not reported"); then each valid corner
    must carry both. Invalid corners are not judged (the solver leaves them out or refuses
    the visit).
    """
    z = np.asarray(z_nm, dtype=np.float64).reshape(-1)
    valid = np.asarray(corner_valid, dtype=bool).reshape(-1)
    unc = None if uncertainty_nm is None else np.asarray(uncertainty_nm, float).reshape(-1)
    pairs = None if n_pairs is None else np.asarray(n_pairs, dtype=np.int64).reshape(-1)
    if z.shape != (len(CORNERS) * N_ZK,) or valid.shape != (len(CORNERS),):
        return Verdict(True)  # the layout check of the caller names that
    if unc is not None and unc.shape != z.shape:
        unc = None
    if pairs is not None and pairs.shape != valid.shape:
        pairs = None
    reports = bool((unc is not None and np.any(np.nan_to_num(unc) != 0)) or
                   (pairs is not None and np.any(pairs != 0)))
    bound = bounds.bound_nm(unc, n_sigma)
    for k in range(len(CORNERS)):
        if not valid[k]:
            continue
        v = _corner_problem(k, z, unc, None if pairs is None else int(pairs[k]), bound,
                            min_corner_rms_nm, reports)
        if v is not None:
            return v
    return Verdict(True)


class VisitGuard:
    """One measurement, one correction: refuse a visit already integrated, or too soon.

    * ``repeated_measurement``: the vector (its 76 values and 4 flags, bit for bit) equals
      one integrated before, under whatever stamp: a re-stamped copy. Two genuine estimates
      are never bit-identical (photon noise).
    * ``too_soon``: stamped less than ``min_period_s`` after the last visit integrated. No
      two exposures of the camera can be closer than its 2 s readout, and survey visits are
      ~30-40 s apart; a burst of vectors closer than that is a flood, not visits.

    Older or equal stamps are the solver's business (``stale_visit``). ``history`` bounds
    the identities remembered.
    """

    def __init__(self, min_period_s: float = 2.0, history: int = 64) -> None:
        self.min_period_s = float(min_period_s)
        self._history = max(1, int(history))
        self._seen: dict[bytes, int] = {}
        self.last_stamp_ns: int | None = None
        self.refuse_repeats = True

    @staticmethod
    def identity(z_nm: np.ndarray, corner_valid: np.ndarray) -> bytes:
        import hashlib

        h = hashlib.blake2b(digest_size=16)
        h.update(np.ascontiguousarray(np.asarray(z_nm, dtype=np.float64)).tobytes())
        h.update(np.asarray(corner_valid, dtype=bool).tobytes())
        return h.digest()

    def check(self, stamp_ns: int, z_nm: np.ndarray, corner_valid: np.ndarray) -> Verdict:
        key = self.identity(z_nm, corner_valid)
        first = self._seen.get(key)
        if first is not None and self.refuse_repeats:
            return Verdict(False, "repeated_measurement", f"the vector is bit for bit the one "
                           f"of visit {first} ns, already integrated: one measurement gives "
                           "one correction")
        last = self.last_stamp_ns
        if last is not None and self.min_period_s > 0 and \
                0 < stamp_ns - last < self.min_period_s * 1e9:
            return Verdict(False, "too_soon", f"stamped {(stamp_ns - last) / 1e9:.4g} s after "
                           f"the last visit integrated ({last} ns); min_visit_period_s is "
                           f"{self.min_period_s:g} s")
        return Verdict(True)

    def integrated(self, stamp_ns: int, z_nm: np.ndarray, corner_valid: np.ndarray) -> None:
        """Remember a visit whose correction was applied (valid, not a dry run)."""
        self._seen[self.identity(z_nm, corner_valid)] = int(stamp_ns)
        while len(self._seen) > self._history:
            self._seen.pop(next(iter(self._seen)))
        self.last_stamp_ns = int(stamp_ns)

    def reset(self) -> None:
        self._seen.clear()
        self.last_stamp_ns = None
