"""The simulator's truth over the science field: wavefront error and optical PSF width (no ROS).

What users care about is the image quality over the whole science field, not at the four
corner sensors. For a simulated telescope this module reports, beside the corner figure
(:func:`cwfs_ros.sim.perturbation.wavefront_error_nm`):

* ``field_wavefront_rms_nm``: the true Zernikes Z4..Z22 minus the design's, at the 31
  Gaussian-quadrature points of the science field (telescope frame, batoid's global field
  angles), combined by :func:`cwfs_ros.ofc.field.field_rms_nm`.
* ``fwhm_arcsec``: the PSF FWHM that those aberrations add, in geometric optics, averaged over
  the field with the same weights (see :func:`fwhm_matrix_arcsec2_per_nm2`).

Cost: 31 ``batoid.zernike`` calls with a 64 x 64 pupil grid, about 1 s per telescope state on
this project's 2-core machine (``bench``: ``python -m cwfs_ros.sim.field_truth``); the design
is computed once per band and wavelength. A 64 grid is within 0.7 nm of a 255 grid per term at
these points (a mixed perturbation of 1470 nm field RMS), a 128 grid within 0.15 nm at 4x the
cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import batoid
import numpy as np

from cwfs_ros.layout import NOLL as _NOLL
from cwfs_ros.ofc.field import field_rms_nm, gq_field_points_deg, gq_weights
from cwfs_ros.sim.telescope import load_lsst

__all__ = [
    "FWHM_PER_SIGMA",
    "FieldTruth",
    "design_field_zernikes_nm",
    "field_truth",
    "field_zernikes_nm",
    "fwhm_arcsec",
    "fwhm_matrix_arcsec2_per_nm2",
]

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))  # 2.3548: Gaussian FWHM / sigma
EPS = 0.61  # the annular obscuration of the project's Zernikes (true_zernikes_nm)
FIELD_NX = 64
_RAD_TO_ARCSEC = 180.0 / np.pi * 3600.0


@dataclass(frozen=True)
class FieldTruth:
    """Truth figures of one telescope state.

    Attributes:
        field_wavefront_rms_nm: GQ-weighted field wavefront error, design removed [nm].
        fwhm_arcsec: GQ-weighted (in quadrature) optical PSF FWHM added by that error
            [arcsec], Gaussian-equivalent (same second moment).
        field_zernikes_nm: (31, 19) Z4..Z22 minus the design at the GQ points [nm].
    """

    field_wavefront_rms_nm: float
    fwhm_arcsec: float
    field_zernikes_nm: np.ndarray


def field_zernikes_nm(telescope: batoid.Optic, *, wavelength_nm: float,
                      nx: int = FIELD_NX) -> np.ndarray:
    """(31, 19) true Z4..Z22 [nm] of ``telescope`` at the GQ points (telescope frame)."""
    wl_m = float(wavelength_nm) * 1e-9
    out = np.empty((gq_field_points_deg().shape[0], len(_NOLL)))
    for i, (x, y) in enumerate(gq_field_points_deg()):
        zk = batoid.zernike(telescope, np.deg2rad(x), np.deg2rad(y), wl_m, jmax=22, eps=EPS,
                            nx=nx)
        out[i] = np.asarray(zk[4:23]) * float(wavelength_nm)
    return out


@lru_cache(maxsize=12)
def design_field_zernikes_nm(band: str, wavelength_nm: float, nx: int = FIELD_NX
                             ) -> np.ndarray:
    """:func:`field_zernikes_nm` of the nominal telescope of ``band`` (cached, read-only).

    A rotated camera does not change it: the camera optics are axisymmetric.
    """
    z = field_zernikes_nm(load_lsst(band), wavelength_nm=wavelength_nm, nx=nx)
    z.setflags(write=False)
    return z


@lru_cache(maxsize=4)
def fwhm_matrix_arcsec2_per_nm2(pupil_radius_m: float = 4.18, eps: float = EPS,
                                n_grid: int = 400) -> np.ndarray:
    """(19, 19) ``G`` with ``sigma**2 = z @ G @ z`` [arcsec^2] for Z4..Z22 ``z`` [nm].

    Geometric optics: a ray through pupil point ``p`` [m] is deflected by the angle
    ``-grad W(p)`` [rad] (``W`` the wavefront, OPD in metres), so the PSF's second moment
    about its centroid is the pupil average of ``|grad W - <grad W>|**2``. Per axis (the mean
    of x and y) ``sigma**2 = (<|grad W|**2> - |<grad W>|**2) / 2``. With ``W = sum z_j
    Z_j(p / R)`` this is the quadratic form ``G``, computed here from galsim's annular
    Zernike gradients on a uniform grid over the annulus ``eps R <= |p| <= R`` (vignetting
    ignored). A Gaussian of that ``sigma`` has ``FWHM = 2.3548 sigma``; a real PSF with the
    same second moment has a different core, so the figure is Gaussian-equivalent. It holds
    where the aberration is large compared with the diffraction limit (lambda / D = 0.015
    arcsec at 622 nm); cross terms between Zernikes (Z4 and Z11 have correlated gradients)
    are kept.
    """
    import galsim

    g = (np.arange(n_grid) + 0.5) / n_grid * 2.0 - 1.0
    u, v = np.meshgrid(g, g)
    r = np.hypot(u, v)
    keep = (r <= 1.0) & (r >= eps)
    u, v = u[keep], v[keep]
    grads = []
    for j in _NOLL:
        coef = np.zeros(j + 1)
        coef[j] = 1.0
        zk = galsim.zernike.Zernike(coef, R_outer=1.0, R_inner=eps)
        gx, gy = zk.gradX(u, v), zk.gradY(u, v)
        grads.append((gx - gx.mean(), gy - gy.mean()))
    gx = np.array([a for a, _ in grads])  # (19, n) per unit pupil radius
    gy = np.array([b for _, b in grads])
    # nm of OPD per unit radius -> rad: 1e-9 / R; the 1/2 makes it a per-axis variance
    g2 = (gx @ gx.T + gy @ gy.T) / u.size / 2.0 * (1e-9 / pupil_radius_m * _RAD_TO_ARCSEC) ** 2
    g2.setflags(write=False)
    return g2


def fwhm_arcsec(zernikes_nm: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Gaussian-equivalent geometric PSF FWHM [arcsec] of Z4..Z22 aberrations.

    ``zernikes_nm`` is (19,) for one field point, or (n, 19) with ``weights`` (n,) (default
    uniform) to average the PSF variance over the field: ``2.3548 sqrt(sum w_i sigma_i**2 /
    sum w)``.
    """
    z = np.atleast_2d(np.asarray(zernikes_nm, dtype=np.float64))
    var = np.einsum("ij,jk,ik->i", z, fwhm_matrix_arcsec2_per_nm2(), z)
    w = np.ones(z.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    return float(FWHM_PER_SIGMA * np.sqrt(np.sum(w * var) / np.sum(w)))


def field_truth(telescope: batoid.Optic, band: str, *, wavelength_nm: float,
                nx: int = FIELD_NX) -> FieldTruth:
    """Field wavefront error and optical FWHM of ``telescope`` (any rotator angle) vs the
    nominal design of ``band``."""
    z = (field_zernikes_nm(telescope, wavelength_nm=wavelength_nm, nx=nx)
         - design_field_zernikes_nm(band, float(wavelength_nm), nx))
    return FieldTruth(field_rms_nm(z), fwhm_arcsec(z, gq_weights()), z)


if __name__ == "__main__":  # per-state cost, printed (no assertion)
    import time

    from cwfs_ros.sim.perturbation import random_perturbation
    from cwfs_ros.sim.telescope import perturbed_telescope

    design_field_zernikes_nm("r", 622.0)
    for kind in ("rigid", "bending", "mixed"):
        tel = perturbed_telescope(random_perturbation(kind, 1), "r", rotator_angle_deg=35.0)
        t0 = time.perf_counter()
        ft = field_truth(tel, "r", wavelength_nm=622.0)
        print(f"{kind:8s} field {ft.field_wavefront_rms_nm:7.1f} nm  FWHM "
              f"{ft.fwhm_arcsec:.3f} arcsec  {time.perf_counter() - t0:.2f} s")
