"""The science field: Gaussian-quadrature points, their weights and the field-averaged figure.

What users care about is the image quality over the whole science field, not at the four
corner sensors where the wavefront is measured. ts_ofc samples the field at 31 points
(``config/ofc/sample_points/lsst_gaussian_quadrature_points.yaml``): the centre (weight 0)
and five rings of six azimuths. The file carries no weights; they follow from the ring radii,
which are the Gauss-Legendre nodes of the area integral over the disk of radius
:data:`FIELD_RADIUS_DEG`: with ``s = (r / R)**2`` the area element is ``ds / 2``, so a 5-point
Gauss-Legendre rule in ``s`` gives rings at ``r_k = R sqrt((1 + x_k) / 2)`` with weight
``w_k / 2`` shared by the six azimuths. :func:`gq_weights` recomputes the nodes and checks
them against the file's radii (to 1e-3 deg), so a changed file cannot silently get wrong
weights.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from cwfs_ros.config import config_dir, load_yaml
from cwfs_ros.errors import ConfigError

__all__ = ["FIELD_RADIUS_DEG", "field_rms_nm", "gq_field_points_deg", "gq_weights"]

#: Radius of the science field sampled by the quadrature [deg].
FIELD_RADIUS_DEG = 1.75
_GQ_FILE = "ofc/sample_points/lsst_gaussian_quadrature_points.yaml"
_N_RINGS = 5
_N_AZIMUTHS = 6
_RADIUS_TOL_DEG = 1e-3


@lru_cache(maxsize=1)
def gq_field_points_deg() -> np.ndarray:
    """(31, 2) field points ``(x, y)`` in degrees, in the file's order (read-only)."""
    path = config_dir() / _GQ_FILE
    raw = load_yaml(path, "Gaussian-quadrature field points", copy_=False)
    try:
        pts = np.array([raw[k] for k in sorted(k for k in raw if isinstance(k, int))],
                       dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read the Gaussian-quadrature points ({exc})") from exc
    if pts.shape != (1 + _N_RINGS * _N_AZIMUTHS, 2) or not np.all(np.isfinite(pts)):
        raise ConfigError(f"{path}: expected 31 finite (x, y) points, got {pts.shape}")
    pts.setflags(write=False)
    return pts


@lru_cache(maxsize=1)
def gq_weights() -> np.ndarray:
    """(31,) quadrature weights of :func:`gq_field_points_deg`, summing to 1 (read-only).

    Raises ConfigError when a point's radius is not the Gauss-Legendre ring radius.
    """
    pts = gq_field_points_deg()
    x, w = np.polynomial.legendre.leggauss(_N_RINGS)
    ring_r = FIELD_RADIUS_DEG * np.sqrt((1.0 + x) / 2.0)
    r = np.hypot(pts[:, 0], pts[:, 1])
    weights = np.zeros(pts.shape[0])
    for i in range(1, pts.shape[0]):
        k = int(np.argmin(np.abs(ring_r - r[i])))
        if abs(ring_r[k] - r[i]) > _RADIUS_TOL_DEG:
            raise ConfigError(f"quadrature point {i} at r = {r[i]:.4f} deg is on no "
                              f"Gauss-Legendre ring of a {FIELD_RADIUS_DEG} deg field")
        weights[i] = w[k] / 2.0 / _N_AZIMUTHS
    if r[0] > _RADIUS_TOL_DEG:
        raise ConfigError("quadrature point 0 must be the field centre (weight 0)")
    weights /= weights.sum()
    weights.setflags(write=False)
    return weights


def field_rms_nm(zernikes_nm: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Field-averaged wavefront error: ``sqrt(sum_i w_i sum_j z_ij**2)`` [nm].

    ``zernikes_nm`` is ``(n_points, n_terms)`` of unit-RMS (Noll-normalised) Zernike
    coefficients with the design removed, so ``sum_j z_ij**2`` is the wavefront variance at
    point ``i`` over the pupil; the weights (default :func:`gq_weights`) average it over the
    field. The square root of the mean variance, not the mean of the RMS, is what the image
    quality follows.
    """
    z = np.asarray(zernikes_nm, dtype=np.float64)
    w = gq_weights() if weights is None else np.asarray(weights, dtype=np.float64)
    if z.ndim != 2 or z.shape[0] != w.shape[0]:
        raise ConfigError(f"field_rms_nm: {z.shape} Zernikes for {w.shape[0]} weights")
    return float(np.sqrt(np.sum(w * np.sum(z * z, axis=1)) / np.sum(w)))
