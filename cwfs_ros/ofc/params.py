"""A controller from ofc_node's parameters, and its state as a record (node and replay alike)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cwfs_ros.core import control as C
from cwfs_ros.core.errors import ConfigError

from .kalman import KALMAN_PARAM_RANGES, KalmanOFC, KalmanSettings
from .model import OpticalModel

__all__ = ["CONTROLLERS", "controller_from_params", "restore_record", "state_record"]

#: ``kalman``: this package's filter and field-optimal correction (default);
#: ``pid``: ts_ofc's scheme (range-fwhm weights, truncated SVD, PI gains), for comparison.
CONTROLLERS: tuple[str, ...] = ("kalman", "pid")


def controller_from_params(get: Callable[[str], Any]) -> C.OFCSolver:
    """The controller of ofc_node's parameter values ``get(name) -> value``.

    ``controller: pid`` is :func:`cwfs_ros.core.control.solver_from_params`. ``kalman`` takes
    the same checks, masks and limits plus the :class:`KalmanSettings` parameters and
    ``angle_bin_deg``. Raises ConfigError naming the problem.
    """
    kind = str(get("controller"))
    if kind not in CONTROLLERS:
        raise ConfigError(f"controller must be one of {CONTROLLERS}, got {kind!r}")
    base = C.solver_from_params(get)  # every shared parameter checked in one place
    if kind == "pid":
        return base
    values = {}
    for name in KALMAN_PARAM_RANGES:
        v = get(name)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float)):
            raise ConfigError(f"{name} must be a number, got {v!r}")
        values[name] = float(v)
    settings = KalmanSettings(**values)
    model = OpticalModel(str(get("matrix_source")), base.band or "r",
                         angle_bin_deg=float(get("angle_bin_deg")))
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


def _array(rec: dict[str, Any], key: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(rec[key], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"controller state: {key} missing or not numbers ({exc})") from exc
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ConfigError(f"controller state: {key} must be {shape} finite numbers")
    return a


def restore_record(ctl: C.OFCSolver, rec: dict[str, Any]) -> str:
    """Put a :func:`state_record` back into ``ctl``; returns what was restored.

    A record of the other controller kind restores the accumulated DoF, the step count and
    the last stamp only (the filter or the integral restarts).
    """
    dof_total = _array(rec, "dof_total", (C.N_DOF,))
    last = rec.get("last_stamp_ns")
    if last is not None and (isinstance(last, bool) or not isinstance(last, int) or last < 0):
        raise ConfigError(f"controller state: last_stamp_ns must be an integer, got {last!r}")
    n_steps = int(rec.get("n_steps", 0))
    kind = rec.get("controller")
    if isinstance(ctl, KalmanOFC) and kind == "kalman":
        ctl.restore({"dof_total": dof_total, "x": _array(rec, "x", (C.N_DOF,)),
                     "P": _array(rec, "P", (C.N_DOF, C.N_DOF)), "n_steps": n_steps,
                     "last_stamp_ns": last})
        return f"kalman state of {n_steps} visit(s)"
    if not isinstance(ctl, KalmanOFC) and kind == "pid":
        ctl.restore((dof_total, _array(rec, "integral", (C.N_DOF,)), n_steps, last,
                     float(rec.get("ki", ctl.ki))))
        return f"pid state of {n_steps} visit(s)"
    ctl.reset()
    ctl.dof_total, ctl.n_steps, ctl.last_stamp_ns = dof_total.copy(), n_steps, last
    return f"accumulated DoF and last stamp of a {kind} state ({n_steps} visit(s))"
