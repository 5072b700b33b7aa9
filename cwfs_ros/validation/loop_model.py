"""The closed loop without images: batoid's truth, the estimator's noise model, a controller.

For long runs (50 visits and more) rendering donuts is too slow, so each visit's measurement
is the simulator's true corner wavefront (batoid, :func:`cwfs_ros.sim.render.true_zernikes_nm`)
plus Gaussian noise of the per-term 1-sigma that the wavefront node reports for a corner
(``noise_nm``). The controller never sees the simulator's model: it works from its own
sensitivity data (bundled or ts_ofc). The figures are the true wavefront error at the corners
and over the science field (31 Gaussian-quadrature points), design removed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cwfs_ros import layout
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.field import field_rms_nm, gq_field_points_deg
from cwfs_ros.sim.render import camera_zernikes_nm, true_zernikes_nm
from cwfs_ros.sim.telescope import perturbed_telescope

__all__ = ["LoopTrace", "TruthModel", "run_model_loop"]


class TruthModel:
    """The simulator's true wavefront (batoid), at the corners and over the field.

    ``nx`` is batoid's pupil sampling for the Zernike fit (64 is within 0.5 nm of 128 for
    Z4..Z22 and four times faster).
    """

    def __init__(self, band: str = "r", wavelength_nm: float = 622.0, nx: int = 64) -> None:
        self.band = band
        self.wavelength_nm = wavelength_nm
        self.nx = nx
        self.corners_deg = C.corner_mid_field_points_deg()
        self.gq_deg = gq_field_points_deg()
        nominal = perturbed_telescope(np.zeros(layout.N_DOF), band)
        self._design_field = self._zk(nominal, self.gq_deg)

    def _zk(self, tel, fields: np.ndarray) -> np.ndarray:
        return np.array([true_zernikes_nm(tel, (float(f[0]), float(f[1])),
                                          wavelength_nm=self.wavelength_nm, nx=self.nx)
                         for f in fields])

    def corners_nm(self, dof: np.ndarray, angle_deg: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(76,) camera-frame corner wavefront and (76,) its departure from the design [nm].

        The camera is rotated in batoid itself (``perturbed_telescope(...,
        rotator_angle_deg=)``, before the DoF as batoid_rubin's ``with_rtp``) and each corner
        reads its camera-frame Zernikes (:func:`cwfs_ros.sim.render.camera_zernikes_nm`).
        """
        tel = perturbed_telescope(dof, self.band, rotator_angle_deg=angle_deg)
        nominal = perturbed_telescope(np.zeros(layout.N_DOF), self.band,
                                      rotator_angle_deg=angle_deg)
        z, z0 = (np.array([camera_zernikes_nm(t, (float(f[0]), float(f[1])), angle_deg,
                                              wavelength_nm=self.wavelength_nm, nx=self.nx)
                           for f in self.corners_deg]) for t in (tel, nominal))
        return z.reshape(-1), (z - z0).reshape(-1)

    def field_error_nm(self, dof: np.ndarray, angle_deg: float = 0.0) -> float:
        """True field-averaged wavefront error of a state [nm] (telescope frame; the design
        is rotationally symmetric, so the unrotated design serves every angle)."""
        tel = perturbed_telescope(dof, self.band, rotator_angle_deg=angle_deg)
        return field_rms_nm(self._zk(tel, self.gq_deg) - self._design_field)


@dataclass
class LoopTrace:
    """Per visit (before that visit's correction): true errors and the controller's result."""

    corner_nm: list[float] = field(default_factory=list)
    field_nm: list[float] = field(default_factory=list)
    valid: list[bool] = field(default_factory=list)
    states: list[np.ndarray] = field(default_factory=list)
    results: list[C.OFCResult] = field(default_factory=list)

    def reduction(self, within: int) -> float:
        """Field error at visit 1 over the best of visits 2..within."""
        return self.field_nm[0] / min(self.field_nm[1:within])


def run_model_loop(controller: C.OFCSolver, initial_dof: np.ndarray, visits: int, *,
                   truth: TruthModel, noise_nm: float = 15.0, seed: int = 0,
                   angle_deg: float = 0.0,
                   step: Callable[..., C.OFCResult] | None = None) -> LoopTrace:
    """Run ``visits`` visits: measure (truth + noise), step the controller, apply.

    ``step(controller, measured_nm, uncertainty_nm, stamp_ns)`` adapts a controller's call
    (default: ``controller.step(measured, uncertainty_nm=..., stamp_ns=...)`` for the Kalman
    controller, ``controller.step(measured, stamp_ns=...)`` for the PI one).
    """
    rng = np.random.default_rng(seed)
    dof = np.asarray(initial_dof, dtype=np.float64).copy()
    trace = LoopTrace()
    unc = np.full(layout.N_MEAS, noise_nm)
    for k in range(visits):
        total, departure = truth.corners_nm(dof, angle_deg)
        trace.corner_nm.append(float(np.mean(np.linalg.norm(
            departure.reshape(layout.N_CORNERS, layout.N_ZK), axis=1))))
        trace.field_nm.append(truth.field_error_nm(dof, angle_deg))
        trace.states.append(dof.copy())
        measured = total + rng.normal(0.0, noise_nm, total.size)
        stamp = (k + 1) * 40_000_000_000
        if step is not None:
            res = step(controller, measured, unc, stamp)
        elif hasattr(controller, "settings"):
            res = controller.step(measured, uncertainty_nm=unc, stamp_ns=stamp,
                                  rotator_angle_deg=angle_deg)
        else:
            res = controller.step(measured, stamp_ns=stamp)
        trace.valid.append(res.valid)
        trace.results.append(res)
        if res.valid:
            dof = dof + res.dof
    return trace
