"""Random telescope perturbations for the simulator, and the closed loop's figure of merit.

No ROS. The figure of merit (the closed-loop issue's definition): the wavefront error of a
state is the true wavefront minus the design (intrinsic) wavefront, as sqrt(sum over Z4..Z22
of the squared coefficients) per corner, averaged over the four corners, in nm.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..core.visits import CORNERS, N_ZK

__all__ = [
    "PERTURBATIONS",
    "RIGID_SCALE",
    "random_perturbation",
    "rigid_perturbation",
    "true_error_of_state_nm",
    "wavefront_error_nm",
]

N_DOF = 50


def wavefront_error_nm(zernikes_nm: Sequence[float] | np.ndarray,
                       intrinsic_nm: Sequence[float] | np.ndarray | None = None) -> float:
    """Mean over the 4 corners of sqrt(sum Z4..Z22 squared) [nm] of a 76-vector.

    ``intrinsic_nm`` (same layout) is subtracted first when given. NaN entries (an invalid
    corner of an estimate) drop that corner from the mean; NaN if no corner is left.
    """
    z = np.asarray(zernikes_nm, dtype=np.float64).reshape(len(CORNERS), N_ZK)
    if intrinsic_nm is not None:
        z = z - np.asarray(intrinsic_nm, dtype=np.float64).reshape(len(CORNERS), N_ZK)
    per_corner = np.sqrt(np.sum(z ** 2, axis=1))
    ok = np.isfinite(per_corner)
    return float(np.mean(per_corner[ok])) if ok.any() else float("nan")


# Per-unit-scale sigma of a random rigid-body perturbation of DoF 0..9 (M2 and camera
# hexapods: dz, dx, dy [um], rx, ry [deg]); camera_sim_node's perturbation_seed uses it too.
RIGID_SCALE = np.array([8.0, 150.0, 150.0, 0.005, 0.005, 8.0, 150.0, 150.0, 0.005, 0.005])
PERTURBATIONS = ("rigid", "bending", "mixed")


def rigid_perturbation(seed: int, scale: float = 1.0) -> np.ndarray:
    """A random rigid-body state (50 DoF), as camera_sim_node's ``perturbation_seed`` makes it."""
    dof = np.zeros(N_DOF)
    dof[:10] = np.random.default_rng(seed).normal(0.0, 1.0, 10) * scale * RIGID_SCALE
    return dof


def true_error_of_state_nm(dof: np.ndarray, band: str = "r") -> float:
    """The figure of merit of a telescope state, from the simulator's truth (r-band 622 nm
    unless ``band`` says otherwise)."""
    from ..core.instrument import load_instrument
    from .render import load_corner_geometry, true_zernikes_nm
    from .telescope import perturbed_telescope

    wl = float(load_instrument("lsst").wavelength_nm(band))
    geometry = load_corner_geometry()
    tel = perturbed_telescope(np.asarray(dof, dtype=np.float64), band)
    nominal = perturbed_telescope(np.zeros(N_DOF), band)
    z, z0 = (np.concatenate([true_zernikes_nm(t, geometry[c].mid_field_deg,
                                                  wavelength_nm=wl) for c in CORNERS])
             for t in (tel, nominal))
    return wavefront_error_nm(z, z0)


def random_perturbation(kind: str, seed: int, target_nm: float | None = None,
                        band: str = "r") -> np.ndarray:
    """A random telescope state of ``kind`` (rigid | bending | mixed), optionally scaled so
    that its wavefront error (:func:`wavefront_error_nm`) is ``target_nm``.

    * rigid: both hexapods, normal(0, 1) x :data:`RIGID_SCALE`;
    * bending: the 20 M1M3 and 20 M2 bending modes, normal(0, 1) x 0.3 x each mode's range
      (config/ofc/dof.yaml: the modes' strokes differ by 100x, and a mode pushed past its
      range could not be corrected);
    * mixed: both together.

    The scaling is linear in the DoF and corrected once for the (small) nonlinearity, so the
    result is within a few per cent of ``target_nm``.
    """
    if kind not in PERTURBATIONS:
        raise ValueError(f"perturbation must be one of {PERTURBATIONS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    dof = np.zeros(N_DOF)
    if kind in ("rigid", "mixed"):
        dof[:10] = rng.normal(0.0, 1.0, 10) * RIGID_SCALE
    if kind in ("bending", "mixed"):
        from ..core.control import load_dof_spec

        dof[10:] = rng.normal(0.0, 1.0, 40) * 0.3 * load_dof_spec().range[10:]
    if target_nm is not None:
        if not target_nm > 0:
            raise ValueError(f"target wavefront error must be > 0 nm, got {target_nm}")
        for _ in range(2):
            dof *= target_nm / true_error_of_state_nm(dof, band)
    return dof
