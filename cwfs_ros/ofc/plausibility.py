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
(``no_uncertainty``), or claims what no estimate has (:class:`Claims`: a per-term one-sigma
outside the estimator's noise model, more pairs than a corner combines:
``implausible_uncertainty``), and two valid corners that are one estimate (:class:`CopyRule`:
closer than photon noise allows; ``copied_corner``).

What the physics cannot refuse: a corner whose terms are all below a nanometre, a corner
copied into another with a nanometre of noise added, shuffled terms or swapped corner blocks
are, near the nominal telescope, within the spread that the Kalman filter's consistency test
(``inconsistent_measurement``) must allow genuine measurements of large aberrations
(``bench/bench_vector_checks.py tampering``; docs/reliability.md).

The bounds are linear in the matrix: with the bundled matrix (r band) they run from about
277 um (Z4: M2 and camera piston move focus by microns per micron) down to ~80 nm for
Z20-Z22 before the margin; a vector of +-19999 nm in every term is beyond them in Z9-Z22.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cwfs_ros import layout
from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import CORNERS, N_ZK
from cwfs_ros.ofc import control as C

__all__ = ["Claims", "CopyRule", "PlausibilityBounds", "Verdict", "VisitGuard", "check_vector",
           "copied_corners", "physical_bounds"]



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
                    bound: np.ndarray, min_rms_nm: float, reports: bool,
                    claims: Claims) -> Verdict | None:
    """The first rule corner ``k`` breaks: a measurement at all, its uncertainty and what it
    claims, then the physical bound (which the claimed uncertainty widens)."""
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
    claimed = claims.problem(name, None if unc is None else unc[sl], n_pairs)
    if claimed is not None:
        return claimed
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
                 min_corner_rms_nm: float = 0.01, claims: Claims | None = None,
                 copies: CopyRule | None = None) -> Verdict:
    """Judge the valid corners of a 76-vector (corner-major, Noll 4..22, nm).

    A producer *reports* uncertainties when any of ``uncertainty_nm`` is non-zero or any
    ``n_pairs`` is non-zero (the message's zeros mean "not reported"); then each valid corner
    must carry both, within ``claims``. Two valid corners that are copies of one another
    (``copies``) are refused as ``copied_corner``. Invalid corners are not judged (the solver
    leaves them out or refuses the visit).
    """
    claims = claims if claims is not None else Claims()
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
                            min_corner_rms_nm, reports, claims)
        if v is not None:
            return v
    v = copied_corners(z, valid, copies if copies is not None else CopyRule(), unc)
    return Verdict(True) if v is None else v


@dataclass(frozen=True)
class Claims:
    """What one corner measurement may claim about itself.

    An estimate's per-term one-sigma comes from the noise model of the frame combination
    (``config/selection.yaml``, ``combination``) at its donuts' S/N: at the faintest donut the
    selection takes (S/N 40) one pair gives at most ~620 nm (``exp``, Z6), a combination whose
    pairs scatter as much as it accepts (reduced chi-square 4) twice that; at the brightest
    donut below the full well (~8e8 e-) the smallest term of ``lsq`` is ~0.04 nm. Beyond
    ``max_uncertainty_nm`` a term carries no measurement (and would widen its plausibility
    bound by ``n_sigma`` times as much); below ``min_uncertainty_nm`` no estimate knows it. A
    corner combines at most ``max_pairs`` donut pairs (``max_pairs`` of the selection).
    """

    min_uncertainty_nm: float = 1e-3
    max_uncertainty_nm: float = 2000.0
    max_pairs: int = 4

    def __post_init__(self) -> None:
        if not self.min_uncertainty_nm < self.max_uncertainty_nm:
            raise ConfigError(f"min_uncertainty_nm ({self.min_uncertainty_nm:g}) must be below "
                              f"max_uncertainty_nm ({self.max_uncertainty_nm:g}): else every "
                              "reported one-sigma is refused")

    def problem(self, name: str, uc: np.ndarray | None, n_pairs: int | None) -> Verdict | None:
        """Why corner ``name``'s uncertainty (19 terms, 0 = not reported) or pair count is
        no estimate's, or None."""
        if n_pairs is not None and n_pairs > self.max_pairs:
            return Verdict(False, "implausible_uncertainty", f"corner {name} claims {n_pairs} "
                           f"donut pairs; a corner combines at most {self.max_pairs}")
        if uc is None:
            return None
        given = np.isfinite(uc) & (uc > 0)
        for bad, what, limit in ((given & (uc > self.max_uncertainty_nm), "above",
                                  self.max_uncertainty_nm),
                                 (given & (uc < self.min_uncertainty_nm), "below",
                                  self.min_uncertainty_nm)):
            if np.any(bad):
                i = int(np.flatnonzero(bad)[0])
                return Verdict(False, "implausible_uncertainty", f"corner {name} claims a "
                               f"one-sigma of {uc[i]:.3g} nm on Z{i + 4} ({int(bad.sum())} "
                               f"terms {what} {limit:g} nm): no estimate has it (the noise "
                               "model of the estimator at the faintest and brightest donuts)")
        return None


@dataclass(frozen=True)
class CopyRule:
    """How close two independent estimates of one corner wavefront can be.

    Two estimates (two visits of one telescope state, or two corners of one visit) differ by
    their photon noise: per term at least ``c_j q`` of the noise model, ~0.1-0.2 nm rms at the
    brightest donut below the full well, and several nm at 1e6 photons, while the reported
    one-sigma, which holds the per-pair floor as well, is 1-25 nm per term. Two corner
    vectors whose rms difference is below ``fraction`` x the reported one-sigma (rms over the
    19 terms, the smaller of the two; ``default_uncertainty_nm`` when not reported), and
    never below ``floor_nm``, are one measurement sent twice.
    """

    fraction: float = 0.002
    floor_nm: float = 0.01
    default_uncertainty_nm: float = 15.0

    def sigma_nm(self, uc: np.ndarray | None) -> float:
        """rms of a corner's reported one-sigma; terms not reported take the default."""
        if uc is None:
            return float(self.default_uncertainty_nm)
        u = np.where(np.isfinite(uc) & (uc > 0), uc, self.default_uncertainty_nm)
        return float(np.sqrt(np.mean(u * u)))

    def copy(self, za: np.ndarray, ua: np.ndarray | None, zb: np.ndarray,
             ub: np.ndarray | None) -> tuple[float, float] | None:
        """(rms difference, threshold) [nm] when ``za`` is a copy of ``zb``, else None."""
        with np.errstate(over="ignore", invalid="ignore"):
            d = float(np.sqrt(np.mean((za - zb) ** 2)))
        thr = max(self.floor_nm, self.fraction * min(self.sigma_nm(ua), self.sigma_nm(ub)))
        return (d, thr) if d < thr else None

    def describe(self, d: float, thr: float) -> str:
        return (f"{d:.3g} nm rms apart, less than {thr:.3g} nm ({self.fraction:g} x the "
                f"reported one-sigma, at least {self.floor_nm:g} nm); two genuine estimates "
                "differ by their photon noise")


def copied_corners(z_nm: np.ndarray, corner_valid: np.ndarray, rule: CopyRule,
                   uncertainty_nm: np.ndarray | None = None) -> Verdict | None:
    """Two valid corners of one visit that are one estimate: the corners are four sensors,
    each with its own photon noise (and, at their four fields, their own design wavefront)."""
    blocks = _blocks(z_nm, uncertainty_nm)
    valid = [k for k in range(len(CORNERS)) if corner_valid[k]]
    for i, a in enumerate(valid):
        for b in valid[i + 1:]:
            hit = rule.copy(blocks[a][0], blocks[a][1], blocks[b][0], blocks[b][1])
            if hit is not None:
                return Verdict(False, "copied_corner", f"corners {CORNERS[a]} and "
                               f"{CORNERS[b]} are {rule.describe(*hit)}: one corner's "
                               "estimate copied into another")
    return None


def _blocks(z_nm: np.ndarray, uncertainty_nm: np.ndarray | None
            ) -> list[tuple[np.ndarray, np.ndarray | None]]:
    z = np.asarray(z_nm, dtype=np.float64).reshape(len(CORNERS), N_ZK)
    u = None if uncertainty_nm is None else \
        np.asarray(uncertainty_nm, dtype=np.float64).reshape(len(CORNERS), N_ZK)
    return [(z[k], None if u is None else u[k]) for k in range(len(CORNERS))]


def _finite(values: object, n: int) -> np.ndarray:
    a = np.array(values, dtype=np.float64).reshape(n)
    if not np.all(np.isfinite(a)):
        raise ValueError("non-finite values")
    return a


@dataclass(frozen=True)
class _Integrated:
    stamp_ns: int
    z_nm: np.ndarray
    corner_valid: np.ndarray
    uncertainty_nm: np.ndarray | None

    @classmethod
    def of(cls, stamp_ns: int, z_nm: np.ndarray, corner_valid: np.ndarray,
           uncertainty_nm: np.ndarray | None) -> _Integrated:
        """A visit as remembered: flat copies, independent of the caller's arrays."""
        return cls(int(stamp_ns), np.array(z_nm, dtype=np.float64).reshape(-1),
                   np.array(corner_valid, dtype=bool).reshape(-1),
                   None if uncertainty_nm is None
                   else np.array(uncertainty_nm, dtype=np.float64).reshape(-1))


class VisitGuard:
    """One measurement, one correction: refuse a visit already integrated, or too soon.

    * ``repeated_measurement``: a valid corner of the vector is a copy (:class:`CopyRule`:
      closer than photon noise allows) of the same corner of one of the last ``history``
      visits integrated, under whatever stamp: a re-sent measurement, bit for bit or with a
      jitter far below the noise. Two genuine visits differ by their photon noise.
    * ``too_soon``: stamped less than ``min_period_s`` after the last visit integrated. No two
      exposures of the survey are closer than a 15 s snap plus the 2 s readout (visits are
      ~34-40 s apart); a burst of vectors closer than that is a flood, not visits.

    Older or equal stamps are the solver's business (``stale_visit``).
    """

    def __init__(self, min_period_s: float = 15.0, history: int = 64,
                 copies: CopyRule | None = None) -> None:
        self.min_period_s = float(min_period_s)
        self.copies = copies if copies is not None else CopyRule()
        self._history = max(1, int(history))
        self._seen: list[_Integrated] = []
        self.last_stamp_ns: int | None = None
        self.refuse_repeats = True

    def check(self, stamp_ns: int, z_nm: np.ndarray, corner_valid: np.ndarray,
              uncertainty_nm: np.ndarray | None = None) -> Verdict:
        if self.refuse_repeats:
            v = self._repeat(z_nm, corner_valid, uncertainty_nm)
            if v is not None:
                return v
        last = self.last_stamp_ns
        if last is not None and self.min_period_s > 0 and \
                0 < stamp_ns - last < self.min_period_s * 1e9:
            return Verdict(False, "too_soon", f"stamped {(stamp_ns - last) / 1e9:.4g} s after "
                           f"the last visit integrated ({last} ns); min_visit_period_s is "
                           f"{self.min_period_s:g} s")
        return Verdict(True)

    def _repeat(self, z_nm: np.ndarray, corner_valid: np.ndarray,
                uncertainty_nm: np.ndarray | None) -> Verdict | None:
        new = _blocks(z_nm, uncertainty_nm)
        valid = np.asarray(corner_valid, dtype=bool).reshape(-1)
        for seen in reversed(self._seen):
            old = _blocks(seen.z_nm, seen.uncertainty_nm)
            for k in np.flatnonzero(valid & seen.corner_valid):
                hit = self.copies.copy(new[k][0], new[k][1], old[k][0], old[k][1])
                if hit is not None:
                    return Verdict(False, "repeated_measurement", f"corner {CORNERS[k]} and "
                                   f"its estimate in visit {seen.stamp_ns} ns, already "
                                   f"integrated, are {self.copies.describe(*hit)}: one "
                                   "measurement gives one correction")
        return None

    def integrated(self, stamp_ns: int, z_nm: np.ndarray, corner_valid: np.ndarray,
                   uncertainty_nm: np.ndarray | None = None) -> None:
        """Remember a visit whose correction was applied (valid, not a dry run)."""
        self._seen.append(_Integrated.of(stamp_ns, z_nm, corner_valid, uncertainty_nm))
        del self._seen[:-self._history]
        self.last_stamp_ns = int(stamp_ns)

    def record(self, pending: tuple[int, np.ndarray, np.ndarray, np.ndarray | None] | None
               = None) -> dict:
        """The integrated visits as plain lists for the state file, with ``pending``
        ``(stamp_ns, z_nm, corner_valid, uncertainty_nm)`` (a visit being applied) last:
        a restarted node keeps refusing what it integrated (:meth:`restore`)."""
        seen = list(self._seen)
        if pending is not None:
            seen.append(_Integrated.of(*pending))
        return {"seen": [{"stamp_ns": v.stamp_ns, "z_nm": v.z_nm.tolist(),
                          "corner_valid": v.corner_valid.tolist(),
                          "uncertainty_nm": None if v.uncertainty_nm is None
                          else v.uncertainty_nm.tolist()} for v in seen[-self._history:]]}

    def restore(self, rec: object) -> int:
        """Put a :meth:`record` back; returns the visits restored. ConfigError for a record
        that is not one (the node then refuses visits until ~/reset, as for the controller
        state)."""
        if rec is None:
            return 0
        try:
            seen = [_Integrated(int(v["stamp_ns"]), _finite(v["z_nm"], layout.N_MEAS),
                                np.array(v["corner_valid"], dtype=bool).reshape(len(CORNERS)),
                                None if v["uncertainty_nm"] is None
                                else _finite(v["uncertainty_nm"], layout.N_MEAS))
                    for v in rec["seen"]]  # type: ignore[index]
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"controller state: the integrated visits are not a record "
                              f"of them ({type(exc).__name__}: {exc})") from exc
        self._seen = seen[-self._history:]
        if seen:
            self.last_stamp_ns = max(v.stamp_ns for v in seen)
        return len(self._seen)

    def carry_over(self, other: VisitGuard) -> None:
        """Take ``other``'s integrated visits (a node reconfigured through its lifecycle
        keeps what it integrated: a cycle must not open the door to a repeat)."""
        self._seen = list(other._seen)[-self._history:]
        self.last_stamp_ns = other.last_stamp_ns

    def reset(self) -> None:
        self._seen.clear()
        self.last_stamp_ns = None
