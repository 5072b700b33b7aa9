"""Perturbed Rubin/LSST telescope models built on batoid's shipped optics.

Degrees of freedom (DoF)
------------------------
A perturbation state is a length-50 float vector in the ts_ofc order and units:

======  ==========================================  =========
index   meaning                                     unit
======  ==========================================  =========
0-2     M2 hexapod dz, dx, dy                       µm
3-4     M2 hexapod rx, ry                           **degrees**
5-7     camera hexapod dz, dx, dy                   µm
8-9     camera hexapod rx, ry                       **degrees**
10-29   M1M3 bending modes 1-20                     µm
30-49   M2 bending modes 1-20                       µm
======  ==========================================  =========

The DoF are given in the observatory coordinate system (OCS), which batoid_rubin's
``LSSTBuilder`` maps into batoid's global frame as x -> -x, y -> y, z -> -z. That frame
change is a 180° rotation about y. The signs applied here follow that builder:

* translation of M2 / camera: ``withGloballyShiftedOptic(name, [-dx, +dy, -dz] * 1e-6 m)``;
* tilt of M2 / camera: ``withLocallyRotatedOptic(name, RotX(-rx) @ RotY(+ry))`` about the
  item's own (already shifted) vertex, applied after the translation;
* bending: the sag perturbation ``sum_k dof_k * Z_k(x, y)`` is added to M1 and M3 (M1M3
  modes, the same polynomial on both surfaces) or to M2 (M2 modes).

One difference from batoid_rubin: there, ``rx, ry`` are in **arcsec**. Here they are in
**degrees**, as in ts_ofc and this project's control code.

Sign convention vs ts_ofc
-------------------------
By default (``convention="batoid_rubin"``) the signs above are used unchanged. The ts_ofc
sensitivity matrix, evaluated at the four corner sensors, disagrees with them. Compared with
this model's own finite-difference sensitivity (``bench/bench_sim.py --ofc-senm``), it is
``-W`` (correction convention) for M2/camera dy and ry and for the bending modes. But it is
``+W`` for dz, dx and rx of both hexapods (|corr| = 1.000 and norm ratio 1.00 for all ten
rigid-body columns). Public Rubin AOS analysis code does the same thing: it negates DoF
``[0, 1, 3, 5, 6, 8]`` when it feeds a ts_ofc state to batoid_rubin. With
``convention="ts_ofc"`` those six components are negated before the mapping above, so the
ts_ofc matrix is exactly ``-W`` for every rigid-body DoF. The two conventions agree on the
bending modes. M2 modes 1-20 and M1M3 modes 1-14 agree with ts_ofc to a correlation of
0.84-1.00 and a norm ratio of 0.6-1.2. M1M3 modes 15-20 agree poorly (correlation
-0.7 to 0.8). ts_ofc was evidently computed from a different or fuller bending-mode set.

Approximation
-------------
batoid_rubin builds each bending mode from its Zernike decomposition (Noll j <= 28) plus a
high-order residual on a bicubic grid. Only the Zernike part ships with this package
(``data/bending/``, see its ``PROVENANCE.md``). The residual grids are downloaded from Zenodo
at run time and are unavailable here. The modelled bending is therefore the j <= 28 part of
each mode. That is accurate for the low-order wavefront (Noll 4-22) that curvature sensing
measures, but it misses the small high-spatial-frequency residue of each mode.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import batoid
import numpy as np
from astropy.io import fits

from cwfs_ros.config import load_yaml
from cwfs_ros.layout import DOF_NAMES, DOF_UNITS, N_DOF
from cwfs_ros.sim._paths import sim_data_dir

__all__ = [
    "BANDS",
    "CONVENTIONS",
    "DOF_NAMES",
    "DOF_UNITS",
    "N_DOF",
    "TS_OFC_FLIPPED_DOF",
    "bending_zernikes",
    "defocused",
    "load_lsst",
    "perturbed_telescope",
]

BANDS = ("u", "g", "r", "i", "z", "y")


# DoF whose sign differs between ts_ofc and batoid_rubin's LSSTBuilder (dz, dx, rx of M2 and
# of the camera); see "Sign convention vs ts_ofc" above.
TS_OFC_FLIPPED_DOF: tuple[int, ...] = (0, 1, 3, 5, 6, 8)
CONVENTIONS = ("batoid_rubin", "ts_ofc")

_CAMERA = "LSSTCamera"
_BEND_SLICES = {"M1M3": slice(10, 30), "M2": slice(30, 50)}
# Which mode set deforms which batoid surface (M1 and M3 are one glass casting).
_SURFACE_MODES = {"M1": "M1M3", "M3": "M1M3", "M2": "M2"}


@lru_cache(maxsize=len(BANDS))
def load_lsst(band: str = "r") -> batoid.Optic:
    """Return batoid's shipped nominal LSST model ``LSST_{band}.yaml`` (cached).

    Parameters
    ----------
    band : one of ``u g r i z y``.

    Returns
    -------
    batoid.Optic
        Immutable nominal telescope. Lengths are in metres. The light reaches the
        detector travelling along +z in batoid's global frame.
    """
    if band not in BANDS:
        raise ValueError(f"unknown band {band!r}; expected one of {BANDS}")
    return batoid.Optic.fromYaml(f"LSST_{band}.yaml")


@lru_cache(maxsize=1)
def _bending_data() -> dict[str, tuple[np.ndarray, float]]:
    """Load the bending-mode Zernike tables.

    Returns
    -------
    dict
        Maps a surface name (``M1``, ``M2``, ``M3``) to ``(zk, R_outer)``. ``zk`` is a
        read-only array of shape (20, 29): metres of sag per µm of mode amplitude for Noll
        j = 0..28, index 0 unused. ``R_outer`` is the Zernike outer radius in metres.
    """
    bend_dir = sim_data_dir() / "bending"
    cfg = load_yaml(bend_dir / "bend.yaml", "bending-mode table", copy_=False)
    out: dict[str, tuple[np.ndarray, float]] = {}
    for surface, modes in _SURFACE_MODES.items():
        zk_cfg = cfg[surface]["zk"]
        zk = np.asarray(fits.getdata(bend_dir / zk_cfg["file"]), dtype=np.float64)
        order = cfg["use_m1m3_modes" if modes == "M1M3" else "use_m2_modes"]
        zk = np.ascontiguousarray(zk[np.asarray(order)])
        zk.flags.writeable = False
        out[surface] = (zk, float(zk_cfg["R_outer"]))
    return out


def _as_dof(dof: Sequence[float] | np.ndarray | None) -> np.ndarray:
    """Validate a DoF vector and return it as a contiguous float64 (50,) array."""
    if dof is None:
        return np.zeros(N_DOF)
    arr = np.ascontiguousarray(dof, dtype=np.float64).reshape(-1)
    if arr.shape != (N_DOF,):
        raise ValueError(f"dof must have {N_DOF} elements, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("dof contains non-finite values")
    return arr + 0.0  # a private copy, with -0.0 normalised to +0.0 (stable cache keys)


def bending_zernikes(dof: Sequence[float] | np.ndarray) -> dict[str, tuple[np.ndarray, float]]:
    """Return the surface-sag Zernike perturbation of each mirror for a DoF vector.

    Parameters
    ----------
    dof : (50,) DoF vector, as described in the module docstring. Only indices 10-49 are used.

    Returns
    -------
    dict
        ``{"M1": (coef, R_outer), "M2": ..., "M3": ...}``. ``coef`` has shape (29,): Noll
        j = 0..28 coefficients of the sag change in metres (index 0 unused). ``R_outer`` is in
        metres. These are plain (non-annular) Zernikes on the mirror's local x/y.
    """
    d = _as_dof(dof)
    out = {}
    for surface, (zk, r_outer) in _bending_data().items():
        amp = d[_BEND_SLICES[_SURFACE_MODES[surface]]]
        out[surface] = (amp @ zk, r_outer)
    return out


def _apply_rigid(optic: batoid.Optic, name: str, block: np.ndarray) -> batoid.Optic:
    """Apply one hexapod's (dz, dx, dy [µm], rx, ry [deg]) to the item ``name``."""
    dz, dx, dy, rx, ry = block
    if dz or dx or dy:
        optic = optic.withGloballyShiftedOptic(name, np.array([-dx, dy, -dz]) * 1e-6)
    if rx or ry:
        rot = batoid.RotX(np.deg2rad(-rx)) @ batoid.RotY(np.deg2rad(ry))
        optic = optic.withLocallyRotatedOptic(name, rot)
    return optic


@lru_cache(maxsize=16)
def _perturbed_cached(band: str, dof_bytes: bytes, rotator_angle_deg: float = 0.0
                      ) -> batoid.Optic:
    dof = np.frombuffer(dof_bytes, dtype=np.float64)
    optic = load_lsst(band)
    if rotator_angle_deg:
        # batoid_rubin's LSSTBuilder._apply_rtp, before the rigid-body DoF: the camera shifts
        # stay global (telescope frame), its tilts turn about the rotated camera's axes.
        optic = optic.withLocallyRotatedOptic(_CAMERA,
                                              batoid.RotZ(np.deg2rad(rotator_angle_deg)))
    optic = _apply_rigid(optic, "M2", dof[0:5])
    optic = _apply_rigid(optic, _CAMERA, dof[5:10])
    if np.any(dof[10:]):
        for surface, (coef, r_outer) in bending_zernikes(dof).items():
            if not np.any(coef):
                continue
            base = optic[surface].surface
            pert = batoid.Zernike(coef, R_outer=r_outer)
            optic = optic.withSurface(surface, batoid.Sum([base, pert]))
    return optic


def perturbed_telescope(
    dof: Sequence[float] | np.ndarray | None = None,
    band: str = "r",
    *,
    convention: str = "batoid_rubin",
    rotator_angle_deg: float = 0.0,
) -> batoid.Optic:
    """Return the LSST model perturbed by a ts_ofc-ordered DoF vector (in focus).

    Parameters
    ----------
    dof : (50,) DoF vector: µm for translations and bending amplitudes, **degrees** for
        rotations (see module docstring). ``None`` means all zeros.
    band : filter band of the batoid model (``u g r i z y``).
    convention : ``"batoid_rubin"`` (default) applies the rigid-body signs of batoid_rubin's
        ``LSSTBuilder``. ``"ts_ofc"`` first negates DoF ``TS_OFC_FLIPPED_DOF`` (dz, dx, rx
        of M2 and camera), so that the model matches ts_ofc's sensitivity matrix (see the
        module docstring).
    rotator_angle_deg : camera rotator angle [deg]. As batoid_rubin's
        ``LSSTBuilder.with_rtp``, the camera becomes ``withLocallyRotatedOptic("LSSTCamera",
        batoid.RotZ(angle))`` *before* the DoF are applied: the camera's dz, dx, dy stay in
        the telescope frame, its rx, ry act about the rotated camera's axes, and rays traced
        to the detector come out in the rotated camera's own frame. See
        :mod:`cwfs_ros.ofc.rotation`.

    Returns
    -------
    batoid.Optic
        The perturbed telescope with its detector at the nominal focal plane. Results are
        cached in a small LRU keyed by ``(band, dof.tobytes(), rotator_angle_deg)``. Optics
        are immutable, so sharing them is safe.
    """
    d = _as_dof(dof)
    if band not in BANDS:
        raise ValueError(f"unknown band {band!r}; expected one of {BANDS}")
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; expected one of {CONVENTIONS}")
    if convention == "ts_ofc":
        d = d.copy()
        d[list(TS_OFC_FLIPPED_DOF)] *= -1.0
        d += 0.0  # -0.0 -> +0.0, so equal states share a cache entry
    angle = float(rotator_angle_deg)
    if not np.isfinite(angle):
        raise ValueError(f"rotator_angle_deg must be finite, got {rotator_angle_deg}")
    return _perturbed_cached(band, d.tobytes(), angle + 0.0)


def defocused(telescope: batoid.Optic, detector_offset_mm: float) -> batoid.Optic:
    """Return ``telescope`` with only its detector displaced along its own normal.

    Parameters
    ----------
    telescope : batoid.Optic
        An (in-focus) LSST model, e.g. from :func:`perturbed_telescope`.
    detector_offset_mm : float
        Displacement of the detector in mm, along the detector's local +z axis. That axis
        equals batoid's global +z for an untilted camera.

    Returns
    -------
    batoid.Optic

    Notes
    -----
    **Sign convention (verified, see ``test/test_sim.py::test_defocus_sign_is_intra_negative``).**
    In batoid's LSST model the light leaves L3 and reaches the detector travelling along +z
    (L3 exit at z = 4.401 m, detector at z = 4.429 m). A **negative** offset moves the
    detector towards L3, so it meets the converging beam **before focus**: that is
    **intra-focal**. A positive offset puts it beyond focus: **extra-focal**. So the project's
    convention (intra = -1.5 mm, extra = +1.5 mm) matches batoid's sign with no flip. Only
    the detector moves; the lenses stay put. This mimics the physically displaced corner
    wavefront sensors, not a camera-hexapod piston.
    """
    if not detector_offset_mm:
        return telescope
    det = telescope["Detector"]
    shift = det.coordSys.rot @ np.array([0.0, 0.0, detector_offset_mm * 1e-3])
    return telescope.withGloballyShiftedOptic("Detector", shift)
