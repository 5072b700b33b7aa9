"""Kalman-filter controller: uncertainty-weighted state estimation and a field-aware correction.

State and model
---------------
The state ``x`` is the telescope's optical state error in the 50 DoF (actuator convention,
:mod:`cwfs_ros.ofc.model`), restricted to the DoF of ``dof_mask``. Each visit measures, in the
telescope frame, ``r = zrot @ y_cam - intrinsic = H x + n`` with ``n ~ N(0, R)``: ``R`` from
the corners' reported ``uncertainty_nm`` plus a model floor (:func:`.measurement_covariance`).

Between visits ``x`` moves by the correction applied (known) and by a random walk: a drift
of ``drift_fraction`` of the prior per visit, and an error of ``correction_error`` times each
applied step (the sensitivity model is not the telescope: ts_ofc's bending columns differ from
batoid's by up to 40 %). After a start or ``reset`` the state is ``0 ± σ0``, with ``σ0``
= ``prior_fraction`` x the DoF's stroke (``config/ofc/dof.yaml``).

Update: the standard Kalman update, Joseph form, with the gain projected onto the directions
a visit observes (:func:`.observability`: whitened SNR >= ``min_snr``); the others keep their
prior and are reported as dropped. When the innovation is larger than the filter expects
(normalised innovation squared per term beyond ``nis_limit``: the telescope moved, a slew or
a thermal step) the predicted covariance is inflated by that ratio, so that the filter
re-converges at once instead of averaging the new state in slowly.

Correction
----------
Certainty equivalence: minimise the expected wavefront variance over the science field,
``E |F (x + u)|²_W = |F (x̂ + u)|²_W + tr(F P Fᵀ)_W``, with ``F`` the sensitivity at the 31
Gaussian-quadrature points and ``W`` their weights, within the per-visit step limits and the
strokes. Without active limits the minimum is ``u = -x̂``; with them, the bounded least-squares
solve picks the correction that is best for the field, not for the four corners. A small
``field_regularization_nm`` term pulls ties (directions that do not change the field) towards
the nominal telescope instead of letting them wander. ``gain`` (default 1) scales the
correction: the filter already weighs the noise, so the gain only buys robustness against a
wrong sensitivity model.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.optimize import lsq_linear

from cwfs_ros import layout
from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.estimation import Observability, measurement_covariance, observability
from cwfs_ros.ofc.model import ModelAtAngle, OpticalModel

__all__ = ["KALMAN_PARAM_RANGES", "KalmanOFC", "KalmanSettings"]

# Ranges of the Kalman settings, shared by ofc_node's parameter descriptors and the checks.
KALMAN_PARAM_RANGES: dict[str, tuple[float, float]] = {
    "prior_fraction": (1e-4, 1.0),
    "drift_fraction": (0.0, 1.0),
    "correction_error": (0.0, 2.0),
    "min_snr": (0.0, 1e3),
    "gain": (0.01, 1.0),
    "default_uncertainty_nm": (0.1, 1e4),
    "model_floor_nm": (0.5, 1e4),
    "nis_limit": (1.0, 1e6),
    "field_regularization_nm": (0.0, 1e3),
    "max_inconsistency": (1.0, 1e6),
}


@dataclass(frozen=True)
class KalmanSettings:
    """Tuning of :class:`KalmanOFC` (see the module docstring for each term's role).

    prior_fraction : prior 1-sigma of each DoF after start or reset, x its stroke.
    drift_fraction : 1-sigma drift per visit, x the prior sigma.
    correction_error : 1-sigma error of an applied step, x the step.
    min_snr : directions seen below this SNR in one visit are dropped.
    gain : fraction of the field-optimal correction applied.
    default_uncertainty_nm : per-term 1-sigma of a corner that reports none.
    model_floor_nm : added in quadrature to every term's uncertainty.
    nis_limit : normalised innovation squared per term above which the covariance is inflated.
    field_regularization_nm : weight of the pull towards the nominal state, nm of field RMS
        per prior sigma.
    max_inconsistency : chi-square per term, against every state the strokes allow, above
        which a measurement is refused as inconsistent.
    """

    prior_fraction: float = 0.2
    drift_fraction: float = 0.01
    correction_error: float = 0.2
    min_snr: float = 1.0
    gain: float = 1.0
    default_uncertainty_nm: float = 15.0
    model_floor_nm: float = 5.0
    nis_limit: float = 4.0
    field_regularization_nm: float = 1.0
    max_inconsistency: float = 25.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            lo, hi = KALMAN_PARAM_RANGES[f.name]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise ConfigError(f"{f.name} must be a number in [{lo:g}, {hi:g}], got {v!r}")


@dataclass(frozen=True)
class _Update:
    """One visit's filter update (masked DoF)."""

    x: np.ndarray  # posterior mean
    P: np.ndarray  # posterior covariance
    obs: Observability
    nis: float  # normalised innovation squared per term, before any inflation
    inflated: float  # factor the predicted covariance was multiplied by


def _uncertainty_problem(uncertainty_nm: np.ndarray | Sequence[float] | None,
                         rows: np.ndarray) -> Problem | None:
    """A reported uncertainty of a used corner that is not a 1-sigma: NaN, inf or negative
    (0 means "not reported" and takes the default)."""
    if uncertainty_nm is None:
        return None
    u = np.asarray(uncertainty_nm, dtype=np.float64).reshape(-1)
    if u.size != rows.size:
        return Problem("bad_uncertainty",
                       f"{u.size} uncertainties for {rows.size} Zernike terms")
    bad = rows & ~(np.isfinite(u) & (u >= 0))
    if bad.any():
        names = sorted({layout.CORNERS[i // layout.N_ZK] for i in np.flatnonzero(bad)})
        return Problem("bad_uncertainty", f"uncertainty_nm of {', '.join(names)} holds NaN, "
                       f"inf or negative values ({int(bad.sum())} terms); 0 means not reported")
    return None


class KalmanOFC(C.OFCSolver):
    """The Kalman-filter controller, with the input and stamp checks of :class:`OFCSolver`.

    Parameters
    ----------
    model : the optical model (sensitivity source, band); default ``OpticalModel()``.
    settings : :class:`KalmanSettings`.
    dof_mask, clip_range, max_step, allow_partial, max_abs_zernike_nm, max_future_s,
    dof_spec : as for :class:`OFCSolver` (its PI parameters are not used).
    """

    def __init__(self, model: OpticalModel | None = None, settings: KalmanSettings | None = None,
                 **kwargs) -> None:
        self.model = model if model is not None else OpticalModel()
        super().__init__(C.sensitivity_for_source(self.model.source), band=self.model.band,
                         **kwargs)
        self.settings = settings if settings is not None else KalmanSettings()
        self.prior_sigma = self.settings.prior_fraction * self.spec.range
        self.reset()

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        """Back to the prior: ``x = 0 ± σ0``, nothing accumulated, no stamp."""
        super().reset()
        self.x = np.zeros(layout.N_DOF)
        self.P = np.diag(self.prior_sigma**2)

    def state(self) -> dict:
        """The controller state (to persist, or to carry into a rebuilt controller)."""
        return {"dof_total": self.dof_total.copy(), "x": self.x.copy(), "P": self.P.copy(),
                "n_steps": self.n_steps, "last_stamp_ns": self.last_stamp_ns}

    def restore(self, state: dict) -> None:  # type: ignore[override]
        """Put back a :meth:`state`; DoF outside this controller's mask restart at the prior."""
        self.dof_total = np.asarray(state["dof_total"], dtype=np.float64).copy()
        self.n_steps = int(state["n_steps"])
        self.last_stamp_ns = state["last_stamp_ns"]
        x = np.asarray(state["x"], dtype=np.float64).copy()
        P = np.asarray(state["P"], dtype=np.float64).copy()
        off = ~self.dof_mask
        x[off] = 0.0
        P[off, :] = 0.0
        P[:, off] = 0.0
        P[off, off] = self.prior_sigma[off] ** 2
        self.x, self.P = x, P

    def warm(self, angle_deg: float = 0.0) -> None:
        """Build the model of ``angle_deg`` now, so that the first visit is fast."""
        self.model.at(angle_deg)

    # ---------------------------------------------------------------- filter
    def _update(self, at: ModelAtAngle, r: np.ndarray, rows: np.ndarray,
                cov: np.ndarray) -> _Update:
        m = self.dof_mask
        H = at.H[np.ix_(rows, m)]
        x, P = self.x[m], self.P[np.ix_(m, m)]
        obs = observability(H, cov, self.prior_sigma[m], self.settings.min_snr)
        nu = r - H @ x
        S = H @ P @ H.T + cov
        nis = float(nu @ np.linalg.solve(S, nu)) / nu.size
        inflated = 1.0
        if nis > self.settings.nis_limit:
            # Only the observed directions: the dropped ones learn nothing from this visit, so
            # inflating them would let their variance grow without bound.
            inflated = nis / self.settings.nis_limit
            Pk = obs.projector @ P @ obs.projector.T
            P = P + (inflated - 1.0) * 0.5 * (Pk + Pk.T)
            S = H @ P @ H.T + cov
        K = obs.projector @ np.linalg.solve(S, H @ P).T
        ikh = np.eye(P.shape[0]) - K @ H
        P_post = ikh @ P @ ikh.T + K @ cov @ K.T
        return _Update(x + K @ nu, 0.5 * (P_post + P_post.T), obs, nis, inflated)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per masked DoF, the correction's bounds from the step limit and the stroke."""
        m = self.dof_mask
        lo = np.full(int(m.sum()), -np.inf)
        hi = np.full(int(m.sum()), np.inf)
        if self.max_step is not None:
            lo, hi = -self.max_step[m], self.max_step[m].copy()
        if self.clip_range is not None:
            total = self.dof_total[m]
            lo = np.maximum(lo, np.minimum(-self.clip_range[m] - total, 0.0))
            hi = np.minimum(hi, np.maximum(self.clip_range[m] - total, 0.0))
        return lo, hi

    def _correction(self, at: ModelAtAngle, x: np.ndarray) -> np.ndarray:
        """The field-optimal correction of the masked DoF within the limits (module doc)."""
        target = self.settings.gain * x
        lo, hi = self._bounds()
        u = -target
        if np.all(u >= lo) and np.all(u <= hi):
            return u
        m = self.dof_mask
        wf = np.repeat(np.sqrt(at.field_weights), layout.N_ZK)[:, None] * at.F[:, m]
        reg = np.diag(self.settings.field_regularization_nm / self.prior_sigma[m])
        A = np.vstack([wf, reg])
        b = -A @ target
        # bvls: exact on this small (50-variable) problem; lo == hi pins a DoF at a stroke.
        hi = np.maximum(hi, lo)
        return lsq_linear(A, b, bounds=(lo, hi + 1e-300), method="bvls").x

    def _field_rms(self, F: np.ndarray, weights: np.ndarray, x: np.ndarray) -> float:
        w = F[:, self.dof_mask] @ x
        return float(np.sqrt(np.sum(weights * np.sum(w.reshape(-1, layout.N_ZK) ** 2, axis=1))))

    # ---------------------------------------------------------------- step
    def step(self, measured_nm: np.ndarray | Sequence[float],  # type: ignore[override]
             corner_valid: np.ndarray | Sequence[bool] | None = None, *,
             uncertainty_nm: np.ndarray | Sequence[float] | None = None,
             rotator_angle_deg: float = 0.0, stamp_ns: int | None = None,
             now_ns: int | None = None, dry_run: bool = False) -> C.OFCResult:
        """One visit: checks, filter update, field-optimal correction, accumulate.

        ``measured_nm`` and ``uncertainty_nm`` are the camera-frame corner Zernikes and their
        1-sigma (76 each, nm); ``rotator_angle_deg`` the camera rotator's angle at the visit.
        Stamps as :meth:`OFCSolver.step`. ``dry_run`` leaves the state as it was. When not
        valid, ``dof`` is zero and the state is unchanged.
        """
        t0 = time.perf_counter()
        problem = self.visit_stamp_problem(stamp_ns, now_ns)
        if problem is None and not np.isfinite(rotator_angle_deg):
            problem = Problem("bad_rotator_angle", f"{rotator_angle_deg!r}")
        if problem is not None:
            return self._refused(problem, (), t0, rotator_angle_deg)
        # The input checks first, against the unrotated design (only its non-zero corners
        # matter there): refused input never builds a rotator bin's model.
        checked = self.check_visit(measured_nm, corner_valid)
        if isinstance(checked, C.Refusal):
            return self._refused(checked, checked.corners, t0, rotator_angle_deg)
        corners = tuple(bool(c) for c in checked.corner_valid)
        bad_unc = _uncertainty_problem(uncertainty_nm, checked.rows)
        if bad_unc is not None:
            return self._refused(bad_unc, corners, t0, rotator_angle_deg)
        at = self.model.at(rotator_angle_deg)
        rows = checked.rows
        r = (at.to_telescope(checked.y) - at.intrinsic_nm)[rows]
        cov = measurement_covariance(uncertainty_nm, rows, at.zrot,
                                     default_nm=self.settings.default_uncertainty_nm,
                                     floor_nm=self.settings.model_floor_nm)
        try:
            problem = self._inconsistency(at, r, rows, cov)
            upd = None if problem else self._update(at, r, rows, cov)
        except np.linalg.LinAlgError as exc:
            problem = Problem("ill_conditioned", f"the measurement covariance cannot be "
                              f"factorised ({exc}); check the corners' uncertainty_nm")
        if problem is not None:
            return self._refused(problem, corners, t0, rotator_angle_deg)
        if upd.obs.n_kept == 0:
            return self._refused(self._unobservable(upd.obs), corners, t0,
                                 rotator_angle_deg)
        u_m = self._correction(at, upd.x)
        if not self._finite_outcome(upd, u_m):
            return self._refused(Problem("non_finite_result", "the filter gave NaN/inf or a "
                                         "state beyond any stroke; state unchanged"),
                                 corners, t0, rotator_angle_deg)
        return self._finish(at, r, rows, upd, u_m, corners, stamp_ns, dry_run, t0)

    def _inconsistency(self, at: ModelAtAngle, r: np.ndarray, rows: np.ndarray,
                       cov: np.ndarray) -> Problem | None:
        """Why no telescope state within the strokes explains this measurement, or None.

        A chi-square test of ``r`` against every state the DoF strokes allow (covariance
        ``H diag(range²) Hᵀ + R``): a corner far off while the others are nominal, or
        wavefronts beyond any DoF's reach, is data no telescope could give, and is refused
        rather than solved (it would drive the actuators to their strokes).
        """
        m = self.dof_mask
        H = at.H[np.ix_(rows, m)]
        S = (H * self.spec.range[m] ** 2) @ H.T + cov
        with np.errstate(over="ignore", invalid="ignore"):
            nis = float(r @ np.linalg.solve(S, r)) / r.size
        if not np.isfinite(nis) or nis > self.settings.max_inconsistency:
            return Problem("inconsistent_measurement", f"no telescope state within the DoF "
                           f"strokes explains this wavefront (chi2 per term {nis:.3g} > "
                           f"max_inconsistency {self.settings.max_inconsistency:g}); a corner "
                           "is wrong or its uncertainty too small")
        return None

    def _finite_outcome(self, upd: _Update, u_m: np.ndarray) -> bool:
        """The posterior, the correction and the next prediction are finite and within
        ten strokes (a filter state beyond that is an arithmetic accident, never physics)."""
        m = self.dof_mask
        lim = 10.0 * self.spec.range[m]
        q = (self.settings.correction_error * u_m) ** 2
        with np.errstate(over="ignore", invalid="ignore"):
            ok = (np.all(np.isfinite(u_m)) and np.all(np.isfinite(upd.x))
                  and np.all(np.isfinite(upd.P)) and np.all(np.isfinite(q))
                  and np.all(np.abs(upd.x) <= lim)
                  and np.all(np.abs(self.dof_total[m] + u_m) <= lim))
        return bool(ok)

    def _finish(self, at: ModelAtAngle, r: np.ndarray, rows: np.ndarray, upd: _Update,
                u_m: np.ndarray, corners: tuple[bool, ...], stamp_ns: int | None,
                dry_run: bool, t0: float) -> C.OFCResult:
        m = self.dof_mask
        u = np.zeros(layout.N_DOF)
        u[m] = u_m
        lo, hi = self._bounds()
        clipped = np.zeros(layout.N_DOF, dtype=bool)
        clipped[m] = (np.abs(u_m - lo) < 1e-12 * (1 + np.abs(lo))) | \
            (np.abs(u_m - hi) < 1e-12 * (1 + np.abs(hi)))
        sigma = np.zeros(layout.N_DOF)
        sigma[m] = np.sqrt(np.clip(np.diag(upd.P), 0.0, None))
        n_used = sum(corners)
        H = at.H[np.ix_(rows, m)]
        status = "ok" if upd.inflated == 1.0 else (
            f"ok: innovation {upd.nis:.3g} per term > nis_limit "
            f"{self.settings.nis_limit:g}, covariance inflated x{upd.inflated:.3g}")
        F = at.F
        dropped_cost = self._dropped_field_cost(F, at.field_weights, upd.obs)
        total = self.dof_total + u
        if not dry_run:
            self._advance(upd, u_m, total, stamp_ns)
        return C.OFCResult(
            u, total, True, status, C._rms(r, n_used), C._rms(r + H @ u_m, n_used),  # noqa: SLF001
            upd.obs.n_kept, self._full(upd.x),
            clipped, float(upd.obs.snr[0] / max(upd.obs.snr[upd.obs.n_kept - 1], 1e-300)),
            corners, time.perf_counter() - t0, sigma,
            self._field_rms(F, at.field_weights, upd.x),
            self._field_rms(F, at.field_weights, upd.x + u_m), at.angle_deg,
            upd.obs.describe_dropped([self.spec.names[i] for i in np.flatnonzero(m)],
                                     dropped_cost),
            int(upd.obs.dropped_dirs.shape[0]))

    def _advance(self, upd: _Update, u_m: np.ndarray, total: np.ndarray,
                 stamp_ns: int | None) -> None:
        """Predict the next visit's state: the applied step, plus drift and step error."""
        m = self.dof_mask
        s = self.settings
        q = (s.drift_fraction * self.prior_sigma[m]) ** 2 + (s.correction_error * u_m) ** 2
        self.x = self._full(upd.x + u_m)
        P = self.P.copy()
        P[np.ix_(m, m)] = upd.P + np.diag(q)
        self.P = P
        self.dof_total = total
        self.n_steps += 1
        if stamp_ns is not None:
            self.last_stamp_ns = int(stamp_ns)

    def _full(self, x_m: np.ndarray) -> np.ndarray:
        out = np.zeros(layout.N_DOF)
        out[self.dof_mask] = x_m
        return out

    def _dropped_field_cost(self, F: np.ndarray, weights: np.ndarray,
                            obs: Observability) -> np.ndarray:
        """Field RMS [nm] of a one-prior-sigma excursion along each dropped direction."""
        if obs.dropped_dirs.shape[0] == 0:
            return np.zeros(0)
        dirs = obs.dropped_dirs * self.prior_sigma[self.dof_mask][None, :]
        return np.array([self._field_rms(F, weights, d) for d in dirs])

    def _unobservable(self, obs: Observability) -> Problem:
        names = [self.spec.names[i] for i in np.flatnonzero(self.dof_mask)]
        return Problem("unobservable", f"the valid corners see no combination of the DoF in "
                       f"dof_mask above min_snr {self.settings.min_snr:g} (best "
                       f"{obs.snr[0]:.2g}); drop {', '.join(names[:6])}"
                       f"{' ...' if len(names) > 6 else ''} from dof_mask or add DoF the "
                       "corners see")

    def _refused(self, problem: Problem, corners: tuple[bool, ...], t0: float,
                 angle_deg: float) -> C.OFCResult:
        sigma = np.sqrt(np.clip(np.diag(self.P), 0.0, None)) * self.dof_mask
        return C.OFCResult(np.zeros(layout.N_DOF), self.dof_total.copy(), False, problem.status,
                           float("nan"), float("nan"), 0, np.zeros(layout.N_DOF),
                           np.zeros(layout.N_DOF, dtype=bool), float("nan"), corners,
                           time.perf_counter() - t0, sigma,
                           rotator_angle_deg=float(angle_deg) if np.isfinite(angle_deg)
                           else float("nan"), reason=problem.reason)

    def observability_report(self, angle_deg: float = 0.0,
                             corner_valid: Sequence[bool] | None = None) -> Observability:
        """Which directions the default measurement noise lets one visit see (no state change)."""
        at = self.model.at(angle_deg)
        cv = np.ones(layout.N_CORNERS, bool) if corner_valid is None else np.asarray(corner_valid)
        rows = self.sensitivity.rows_for(cv)
        cov = measurement_covariance(None, rows, at.zrot,
                                     default_nm=self.settings.default_uncertainty_nm,
                                     floor_nm=self.settings.model_floor_nm)
        return observability(at.H[np.ix_(rows, self.dof_mask)], cov,
                             self.prior_sigma[self.dof_mask], self.settings.min_snr)

    def with_settings(self, **changes) -> KalmanSettings:
        """These settings with ``changes`` (checked)."""
        return replace(self.settings, **changes)
