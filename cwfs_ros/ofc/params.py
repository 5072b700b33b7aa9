"""A controller from ofc_node's parameters, and its state as a record (node and replay alike)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cwfs_ros import layout
from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.kalman import KALMAN_PARAM_RANGES, KalmanOFC, KalmanSettings
from cwfs_ros.ofc.model import OpticalModel

__all__ = ["CONTROLLERS", "PID_MAX_ANGLE_DEG", "controller_from_params", "refusal",
           "restore_record", "rotator_angle_for", "state_record", "step_controller"]

#: ``kalman``: this package's filter and field-optimal correction (default);
#: ``pid``: ts_ofc's scheme (range-fwhm weights, truncated SVD, PI gains), for comparison.
CONTROLLERS: tuple[str, ...] = ("kalman", "pid")
#: A pid controller has no rotator model: it refuses a camera rotated by more than this [deg].
PID_MAX_ANGLE_DEG = 0.01


def controller_from_params(get: Callable[[str], Any]) -> C.OFCSolver:
    """The controller of ofc_node's parameter values ``get(name) -> value``.

    ``controller: pid`` is :func:`cwfs_ros.ofc.control.solver_from_params`. ``kalman`` takes
    the same checks, masks and limits plus the :class:`KalmanSettings` parameters,
    ``angle_bin_deg`` and ``measurement_model`` (which ``pid`` ignores). Raises ConfigError
    naming the problem.
    """
    kind = str(get("controller"))
    if kind not in CONTROLLERS:
        raise ConfigError(f"controller must be one of {CONTROLLERS}, got {kind!r}")
    base = C.solver_from_params(get)  # every shared parameter checked in one place
    if kind == "pid":
        return base  # ts_ofc's scheme as ts_ofc has it: no measurement model
    values = {}
    for name in KALMAN_PARAM_RANGES:
        v = get(name)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float)):
            raise ConfigError(f"{name} must be a number, got {v!r}")
        values[name] = float(v)
    settings = KalmanSettings(**values)
    model = OpticalModel(str(get("matrix_source")), base.band or "r",
                         angle_bin_deg=float(get("angle_bin_deg")),
                         measurement=str(get("measurement_model")))
    return KalmanOFC(model, settings, dof_mask=base.dof_mask, clip_range=base.clip_range,
                     max_step=base.max_step, allow_partial=base.allow_partial,
                     max_abs_zernike_nm=base.max_abs_zernike_nm,
                     max_future_s=base.max_future_s, dof_spec=base.spec)


def state_record(ctl: C.OFCSolver) -> dict[str, Any]:
    """The controller's state as a plain record (for :mod:`.persistence`)."""
    if isinstance(ctl, KalmanOFC):
        return {"controller": "kalman", **ctl.state()}
    dof_total, integral, n_steps, last, ki = ctl.state()
    return {"controller": "pid", "dof_total": dof_total, "integral": integral,
            "n_steps": n_steps, "last_stamp_ns": last, "ki": ki}


# A state beyond this many strokes is no telescope's: a corrupted or forged file.
_STATE_STROKES = 10.0


def _array(rec: dict[str, Any], key: str, shape: tuple[int, ...],
           limit: np.ndarray | None = None) -> np.ndarray:
    try:
        a = np.asarray(rec[key], dtype=np.float64)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(f"controller state: {key} missing or not numbers ({exc})") from exc
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ConfigError(f"controller state: {key} must be {shape} finite numbers")
    if limit is not None and np.any(np.abs(a) > limit):
        i = int(np.argmax(np.abs(a) / limit))
        raise ConfigError(f"controller state: {key}[{i}] = {a.flat[i]:.4g} is beyond "
                          f"{_STATE_STROKES:g} strokes of that DoF")
    return a


def _covariance(rec: dict[str, Any], rng: np.ndarray) -> np.ndarray:
    """The filter covariance of a record: symmetric, positive semi-definite, each variance
    within (10 strokes)²."""
    P = _array(rec, "P", (layout.N_DOF, layout.N_DOF))
    scale = float(np.max(np.abs(P))) or 1.0
    if np.max(np.abs(P - P.T)) > 1e-9 * scale:
        raise ConfigError("controller state: P is not symmetric")
    if np.any(np.diag(P) > (_STATE_STROKES * rng) ** 2):
        raise ConfigError(f"controller state: a variance of P is beyond {_STATE_STROKES:g} "
                          "strokes")
    w = np.linalg.eigvalsh(P / np.outer(rng, rng))  # in stroke units: comparable entries
    if w.min() < -1e-9 * max(w.max(), 1e-300):
        raise ConfigError("controller state: P is not a covariance (a negative eigenvalue)")
    return P


def _count(rec: dict[str, Any], key: str) -> int:
    v = rec.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ConfigError(f"controller state: {key} must be an integer >= 0, got {v!r}")
    return v


def restore_record(ctl: C.OFCSolver, rec: dict[str, Any]) -> str:
    """Put a :func:`state_record` back into ``ctl``; returns what was restored.

    A record of the other controller kind restores the accumulated DoF, the step count and
    the last stamp only (the filter or the integral restarts).
    """
    rng = ctl.spec.range
    lim = _STATE_STROKES * rng
    kind = rec.get("controller")
    if kind not in CONTROLLERS:
        raise ConfigError(f"controller state: controller must be one of {CONTROLLERS}, "
                          f"got {kind!r}")
    dof_total = _array(rec, "dof_total", (layout.N_DOF,), rng * (1 + 1e-9) if
                       ctl.clip_range is not None else lim)
    last = rec.get("last_stamp_ns")
    if last is not None and (isinstance(last, bool) or not isinstance(last, int) or last < 0):
        raise ConfigError(f"controller state: last_stamp_ns must be an integer, got {last!r}")
    n_steps = _count(rec, "n_steps")
    if isinstance(ctl, KalmanOFC) and kind == "kalman":
        ctl.restore({"dof_total": dof_total, "x": _array(rec, "x", (layout.N_DOF,), lim),
                     "P": _covariance(rec, rng), "n_steps": n_steps, "last_stamp_ns": last})
        return f"kalman state of {n_steps} visit(s)"
    if not isinstance(ctl, KalmanOFC) and kind == "pid":
        ki = rec.get("ki", ctl.ki)
        if isinstance(ki, bool) or not isinstance(ki, (int, float)) or not 0 <= ki <= 1:
            raise ConfigError(f"controller state: ki must be in [0, 1], got {ki!r}")
        ctl.restore((dof_total, _array(rec, "integral", (layout.N_DOF,), lim), n_steps, last,
                     float(ki)))
        return f"pid state of {n_steps} visit(s)"
    ctl.reset()
    ctl.dof_total, ctl.n_steps, ctl.last_stamp_ns = dof_total.copy(), n_steps, last
    return f"accumulated DoF and last stamp of a {kind} state ({n_steps} visit(s))"


def refusal(ctl: C.OFCSolver, problem: Problem) -> C.OFCResult:
    """A refused visit: no correction, the controller's state as it is."""
    return C.OFCResult(np.zeros(layout.N_DOF), ctl.dof_total.copy(), False, problem.status,
                       float("nan"), float("nan"), 0, reason=problem.reason)


def rotator_angle_for(get: Callable[[str], Any], history: Any,
                      stamp_ns: int) -> tuple[float | None, str]:
    """The rotator angle of a visit [deg] by ``rotator_angle_source`` (``fixed``: the
    ``rotator_angle_deg`` parameter; ``topic``: the :class:`~.rotator.RotatorHistory`), or
    None with the reason."""
    if get("rotator_angle_source") == "fixed":
        return float(get("rotator_angle_deg")), "fixed"
    return history.angle_deg(stamp_ns)


def step_controller(ctl: C.OFCSolver, z: np.ndarray, valid: np.ndarray, *,
                    uncertainty_nm: np.ndarray | None, angle_deg: float | None,
                    angle_why: str, stamp_ns: int, now_ns: int | None,
                    dry_run: bool) -> C.OFCResult:
    """One visit through either controller, as ofc_node and the offline replay both run it:
    refused without a rotator angle; the pid controller refuses a rotated camera."""
    if angle_deg is None:
        return refusal(ctl, Problem("no_rotator_angle", angle_why))
    if isinstance(ctl, KalmanOFC):
        return ctl.step(z, valid, uncertainty_nm=uncertainty_nm, rotator_angle_deg=angle_deg,
                        stamp_ns=stamp_ns, now_ns=now_ns, dry_run=dry_run)
    if abs(angle_deg) > PID_MAX_ANGLE_DEG:
        return refusal(ctl, Problem("rotator_unsupported", f"the pid controller has no rotator "
                                    f"model and the camera is at {angle_deg:.3g} deg; use "
                                    "controller kalman"))
    return ctl.step(z, valid, stamp_ns=stamp_ns, now_ns=now_ns, dry_run=dry_run)
