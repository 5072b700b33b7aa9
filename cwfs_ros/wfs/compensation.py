"""Image compensation: remap a defocused image onto the pupil through the current wavefront.

Paper §2.1, eqs. (9)-(12): each image is "restored" to the state where the estimated wavefront
is absent by sampling it at ``x' = x'_0 + C grad W`` and multiplying by the Jacobian
``J = det(d(x', y')/d(x, y))`` (flux conservation, eq. 12).  With the fast-beam (§3.2) and
off-axis (§3.3) models ``x'_0`` and its Jacobian come from :mod:`.mapping`.  A fold of the
mapping (``J`` changing sign inside the pupil) means the rays cross before the image plane:
the image is in caustic and the compensation is not trusted (§2.1, last paragraph).

The sampler is bilinear and hand-written: ``scipy.ndimage.map_coordinates(order=1)`` gives
identical values but costs about 2.5x more per call, and this runs 28 times per estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cwfs_ros.wfs.mapping import ImageMapping

__all__ = ["Compensated", "compensate", "sample_bilinear"]


@dataclass(frozen=True)
class Compensated:
    """A compensated image on the pupil points.

    Attributes:
        intensity: flux density normalised to 1 on the transmitted pupil (dimensionless).
        caustic: True if the mapping folds (J / J_0 <= 0) somewhere on the transmitted pupil.
        min_jacobian_ratio: smallest J / J_0 on the transmitted pupil.
    """

    intensity: np.ndarray
    caustic: bool
    min_jacobian_ratio: float


def sample_bilinear(image: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``image`` at (row, col) pixel-centre coordinates; 0 outside."""
    ny, nx = image.shape
    r0 = np.floor(row)
    c0 = np.floor(col)
    fr = row - r0
    fc = col - c0
    valid = (r0 >= 0) & (r0 < ny - 1) & (c0 >= 0) & (c0 < nx - 1)
    idx = np.where(valid, r0 * nx + c0, 0).astype(np.intp)
    flat = image.ravel()
    a, b = flat[idx], flat[idx + 1]
    c, d = flat[idx + nx], flat[idx + nx + 1]
    top = a + (b - a) * fc
    bottom = c + (d - c) * fc
    out = top + (bottom - top) * fr
    out[~valid] = 0.0
    return out


def compensate(image: np.ndarray, centre_xy: tuple[float, float], mapping: ImageMapping,
               derivs: np.ndarray) -> Compensated:
    """Sample ``image`` at the mapped positions of the pupil points, times the Jacobian.

    Args:
        image: background-subtracted stamp ``[row=y, col=x]``.
        centre_xy: (col, row) pixel position of the mapping's reference point in the stamp.
        mapping: the unperturbed mapping at the pupil points.
        derivs: ``[W_x, W_y, W_xx, W_xy, W_yy]`` of the wavefront to compensate (nm per
            reduced pupil unit, and per unit squared), shape (5, npoints); see
            :meth:`.zernike.ZernikeBasis.derivative_fields`.
    """
    c = np.float32(mapping.c_px_per_nm)
    gx, gy, hxx, hxy, hyy = derivs
    col = (np.float32(centre_xy[0]) + c * gx) + mapping.x_px
    row = (np.float32(centre_xy[1]) + c * gy) + mapping.y_px
    jac = (mapping.jxx + c * hxx) * (mapping.jyy + c * hyy)
    jac -= (mapping.jxy + c * hxy) * (mapping.jyx + c * hxy)
    tr = mapping.transmitted_index
    min_ratio = float((jac[tr] * mapping.inv_det_transmitted).min()) if tr.size else 1.0
    raw = sample_bilinear(image, row, col)
    raw *= np.abs(jac)
    # Flux per unit pupil area, normalised so the transmitted pupil averages 1: each image
    # is normalised to its own flux (split sensor: different stars, paper §3.4).
    level = float(raw.sum(dtype=np.float64)) / max(tr.size, 1)
    if level > 0:
        raw *= 1.0 / level
    return Compensated(raw, min_ratio <= 0.0, min_ratio)
