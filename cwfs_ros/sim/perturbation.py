"""Random telescope perturbations for the simulator, and the closed loop's figure of merit.

No ROS. The figure of merit (the closed-loop issue's definition): the wavefront error of a
state is the true wavefront minus the design (intrinsic) wavefront, as sqrt(sum over Z4..Z22
of the squared coefficients) per corner, averaged over the four corners, in nm.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cwfs_ros.layout import CORNERS, N_DOF, N_ZK

__all__ = [
    "BENDING_FRACTION",
    "DECENTRE_STROKE_UM",
    "PERTURBATIONS",
    "PISTON_STROKE_UM",
    "RIGID_SCALE",
    "TILT_STROKE_ARCSEC",
    "random_perturbation",
    "rigid_perturbation",
    "scale_to_error",
    "stroke_perturbation",
    "stroke_usage",
    "true_error_of_state_nm",
    "wavefront_error_nm",
]



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
    from cwfs_ros.sim.render import load_corner_geometry, true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope
    from cwfs_ros.wfs.instrument import load_instrument

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
        from cwfs_ros.ofc.control import load_dof_spec

        dof[10:] = rng.normal(0.0, 1.0, 40) * 0.3 * load_dof_spec().range[10:]
    return dof if target_nm is None else scale_to_error(dof, target_nm, band)


def scale_to_error(dof: np.ndarray, target_nm: float, band: str = "r") -> np.ndarray:
    """``dof`` scaled so that its corner wavefront error (:func:`true_error_of_state_nm`) is
    ``target_nm``: linear, corrected once for the (small) nonlinearity, so within a few per
    cent."""
    if not target_nm > 0:
        raise ValueError(f"target wavefront error must be > 0 nm, got {target_nm}")
    dof = np.array(dof, dtype=np.float64)
    for _ in range(2):
        dof *= target_nm / true_error_of_state_nm(dof, band)
    return dof


# Strokes of the perturbation classes of the closed-loop issue.
DECENTRE_STROKE_UM = 1000.0   # hexapod x-y decentre, each of M2 and camera [um]
TILT_STROKE_ARCSEC = 30.0     # hexapod tilt, each of M2 and camera [arcsec]
PISTON_STROKE_UM = 25.0       # hexapod piston (dz) [um]: defocus of a few hundred nm
BENDING_FRACTION = 0.3        # bending modes: up to this fraction of each mode's range


def _disk_draw(rng: np.random.Generator, stroke: float) -> np.ndarray:
    """A 2-vector in a random direction with a size uniform in [0, stroke]."""
    phi = rng.uniform(0.0, 2.0 * np.pi)
    return rng.uniform(0.0, stroke) * np.array([np.cos(phi), np.sin(phi)])


def stroke_perturbation(kind: str, seed: int, target_nm: float | None = None,
                        band: str = "r") -> np.ndarray:
    """A random telescope state of a class of the closed-loop issue, within given strokes.

    * rigid: both hexapods (M2, camera), each a decentre (dx, dy) in a random direction of a
      size uniform in [0, :data:`DECENTRE_STROKE_UM`], a tilt (rx, ry) likewise up to
      :data:`TILT_STROKE_ARCSEC`, and a piston dz uniform in +-:data:`PISTON_STROKE_UM`;
    * bending: each of the 40 bending modes uniform in +-:data:`BENDING_FRACTION` x its range
      (``config/ofc/dof.yaml``);
    * mixed: both together.

    With ``target_nm`` the state is then scaled (:func:`scale_to_error`) to that corner
    wavefront error; the strokes bound the unscaled draw, so a target above the draw's own
    error can push a DoF past them by the scale factor.
    """
    if kind not in PERTURBATIONS:
        raise ValueError(f"perturbation must be one of {PERTURBATIONS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    dof = np.zeros(N_DOF)
    if kind in ("rigid", "mixed"):
        tilt_deg = TILT_STROKE_ARCSEC / 3600.0
        for base in (0, 5):  # M2, camera: dz, dx, dy, rx, ry
            dof[base] = rng.uniform(-PISTON_STROKE_UM, PISTON_STROKE_UM)
            dof[base + 1:base + 3] = _disk_draw(rng, DECENTRE_STROKE_UM)
            dof[base + 3:base + 5] = _disk_draw(rng, tilt_deg)
    if kind in ("bending", "mixed"):
        from cwfs_ros.ofc.control import load_dof_spec

        dof[10:] = (rng.uniform(-1.0, 1.0, 40) * BENDING_FRACTION
                    * load_dof_spec().range[10:])
    return dof if target_nm is None else scale_to_error(dof, target_nm, band)


def stroke_usage(dof: np.ndarray) -> dict[str, float]:
    """The largest fraction of each class stroke that ``dof`` uses (1 = at the stroke).

    Keys: ``decentre``, ``tilt``, ``piston`` (worst of the two hexapods) and ``bending``
    (worst mode, as a fraction of :data:`BENDING_FRACTION` x range).
    """
    from cwfs_ros.ofc.control import load_dof_spec

    d = np.asarray(dof, dtype=np.float64)
    hexapods = (d[0:5], d[5:10])
    return {
        "decentre": max(np.hypot(h[1], h[2]) for h in hexapods) / DECENTRE_STROKE_UM,
        "tilt": max(np.hypot(h[3], h[4]) for h in hexapods) * 3600.0 / TILT_STROKE_ARCSEC,
        "piston": max(abs(h[0]) for h in hexapods) / PISTON_STROKE_UM,
        "bending": float(np.max(np.abs(d[10:]) / load_dof_spec().range[10:])
                         / BENDING_FRACTION),
    }
