"""The blur of the donuts' edges, as the outer loop sees it after compensation.

The compensated images of a perfect wavefront are flat on the pupil, but only up to their
edges.  There each image carries its own blur, pulled back to the pupil through its own
mapping: atmospheric seeing, the pixels, and the light smoothing the estimator applies
before it samples the images (:func:`.estimator.estimate_wavefront`).  The two mappings
differ (the fast beam, §3.2; the design aberrations off axis, §3.3; two fields on a split
sensor, §3.4), so the blurred rim and obscuration of the two compensated images differ
by a few hundredths of a pixel, and the curvature of a blurred circle moves its
half-light edge by ``sigma^2 / 2R``.  The TIE signal, the difference of the images
(§2.1), then holds an edge signal that no wavefront made.  The least-squares solver reads
the wavefront from the edges (:class:`.tie.LeastSquares`).  Without noise, at the corner
sensors and with 1" seeing, it read 10-14 nm rms of astigmatism and trefoil out of that
signal (``bench/bench_seeing.py``).

:func:`blur_reference` predicts that signal. It renders the design donut of each side
from its mapping (:func:`design_donut`: the uniform pupil carried to the image and
integrated over the pixels), blurs it like the data, and compensates it as the data are
compensated.  The outer loop subtracts the difference of the two from the measured one.

The vignetting edges are rendered where batoid traces them (:func:`design_donut`): with
them cut at the pupil grid's staircase instead, the split corner sensor kept 5-6 nm rms of
Z6 and Z10 on a perfect telescope, noise-free (docs/accuracy.md, Seeing).

The prediction is made once per pair geometry, for the design wavefront.  Made again at
the loop's current estimate it did worse on perturbed telescopes (on axis 1.2 -> 2.2 nm
rms without seeing), and leaving it out near vignetting edges did worse with seeing
(corner, 1": 1.7 -> 4.5 nm); docs/accuracy.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.ndimage import gaussian_filter

from cwfs_ros.errors import ConfigError
from cwfs_ros.wfs.compensation import compensate
from cwfs_ros.wfs.mapping import ImageMapping

__all__ = ["FWHM_PER_SIGMA", "MAX_SEEING_FWHM_ARCSEC", "check_seeing", "design_donut",
           "blur_reference", "image_blur_sigma_px", "seeing_sigma_px"]

FWHM_PER_SIGMA = float(2.0 * np.sqrt(2.0 * np.log(2.0)))
_ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi
# The seeing accepted as an input (estimator, nodes, CLI), arcsec FWHM; 0 = none given.
MAX_SEEING_FWHM_ARCSEC = 10.0


def check_seeing(seeing_fwhm_arcsec: object) -> float:
    """The seeing as a float; ConfigError unless a finite number in
    [0, MAX_SEEING_FWHM_ARCSEC]."""
    v = seeing_fwhm_arcsec
    if not (isinstance(v, (int, float)) and np.isfinite(v)
            and 0.0 <= v <= MAX_SEEING_FWHM_ARCSEC):
        raise ConfigError(f"seeing_fwhm_arcsec must be in [0, {MAX_SEEING_FWHM_ARCSEC:g}] "
                          f"arcsec, got {v!r}")
    return float(v)


def seeing_sigma_px(seeing_fwhm_arcsec: float, pixel_size_um: float,
                    focal_length_m: float) -> float:
    """Gaussian sigma (px) of a seeing FWHM (arcsec), at the plate scale
    ``pixel / focal length`` (LSST: 0.200 arcsec/px; batoid's 0.1995 at the corners)."""
    arcsec_per_px = _ARCSEC_PER_RAD * pixel_size_um * 1e-6 / focal_length_m
    return float(seeing_fwhm_arcsec) / FWHM_PER_SIGMA / arcsec_per_px


def image_blur_sigma_px(seeing_fwhm_arcsec: float, smooth_sigma_px: float,
                        pixel_size_um: float, focal_length_m: float) -> float:
    """Gaussian sigma (px) of the images as the estimator compensates them: the seeing
    (:func:`seeing_sigma_px`) and the estimator's own smoothing, in quadrature.  The pixels'
    blur is in the design donut itself (:func:`design_donut`)."""
    return float(np.hypot(seeing_sigma_px(seeing_fwhm_arcsec, pixel_size_um, focal_length_m),
                          smooth_sigma_px))


def design_donut(mapping: ImageMapping, x: np.ndarray, y: np.ndarray, spacing: float,
                 obscuration: float, shape: tuple[int, int], centre_xy: tuple[float, float],
                 transmission: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                 grid: tuple[tuple[int, int], np.ndarray] | None = None,
                 sub: int = 3, over: int = 3) -> np.ndarray:
    """Pixel image of the uniform annular pupil carried to the image by ``mapping``.

    Every pupil-grid cell is split into ``sub x sub`` points, each placed by the mapping's
    position and Jacobian at the cell's centre.  Points outside the annulus are dropped, so
    the rim and the obscuration are exact circles.  On a vignetting edge (the grid cells
    with a 4-neighbour of the other state) each point is asked of ``transmission``
    (:func:`.mapping.pupil_transmission`), so that edge is exact too; without it, or
    elsewhere, a cell whose centre is vignetted is dropped whole.  The
    points are splatted bilinearly on a grid ``over`` times finer than the pixels, then
    summed over each pixel: the pixel integration of the real detector.  The fine grid is
    about as fine as the points, which keeps their lattice from beating with the pixels (a
    moire that a splat straight onto the pixels leaves in the image).

    Args:
        mapping: the side's mapping at the computation points ``x, y`` (reduced pupil).
        spacing: pupil-grid step (reduced pupil units).
        obscuration: inner radius of the annulus.
        shape: (rows, cols) of the image.
        centre_xy: (col, row) where the mapping's reference point falls.
        transmission: ``f(x, y) -> bool`` for pupil points of this side, or None.
        grid: ``(shape, flat indices)`` of the points on their pupil grid (needed with
            ``transmission``, to find the edge cells).
    Returns:
        The image (float64), in units of points per pixel (flux is arbitrary).
    """
    offs = ((np.arange(sub) + 0.5) / sub - 0.5) * spacing
    dx, dy = (a.ravel().astype(np.float32) for a in np.meshgrid(offs, offs))
    cells, keep = _transmitted_points(mapping, x, y, (dx, dy), spacing, obscuration,
                                      transmission, grid)
    f = [a[cells, None].astype(np.float32) for a in
         (mapping.x_px, mapping.y_px, mapping.jxx, mapping.jxy, mapping.jyx, mapping.jyy)]
    # Fine pixel j spans [j / over - 0.5, (j + 1) / over - 0.5) in pixel-centre coordinates.
    cu = np.float32((centre_xy[0] + 0.5) * over - 0.5)
    cv = np.float32((centre_xy[1] + 0.5) * over - 0.5)
    u = ((f[0] + f[2] * dx + f[3] * dy) * over + cu)[keep]
    v = ((f[1] + f[4] * dx + f[5] * dy) * over + cv)[keep]
    return _splat_to_pixels(u, v, shape, over)


def _transmitted_points(mapping: ImageMapping, x: np.ndarray, y: np.ndarray,
                        offsets: tuple[np.ndarray, np.ndarray], spacing: float,
                        obscuration: float,
                        transmission: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
                        grid: tuple[tuple[int, int], np.ndarray] | None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(cells, keep): the grid cells that can hold transmitted light, and which of their
    sub-points (``offsets`` from the cell centre) are transmitted, shape (cells, sub^2).

    A cell qualifies if it can hold part of the annulus and its centre is not vignetted
    (points outside the annulus are not "transmitted" in the mapping, but their cells may
    reach in), or if it lies on a vignetting edge, where each sub-point is asked of
    ``transmission`` (§3.3: the vignetting as batoid traces it).
    """
    dx, dy = offsets
    r = np.hypot(x, y)
    half_diag = spacing / np.sqrt(2.0)
    annulus = (r <= 1.0) & (r >= obscuration)
    near = (r <= 1.0 + half_diag) & (r >= obscuration - half_diag)
    clear = mapping.transmitted | ~annulus
    edge = np.zeros(x.size, bool)
    blocked = annulus & ~mapping.transmitted
    if transmission is not None and grid is not None and blocked.any():
        edge = near & _boundary(grid, mapping.transmitted, blocked)
    cells = np.flatnonzero(near & (clear | edge))
    px = (x[cells, None] + dx).astype(np.float32)
    py = (y[cells, None] + dy).astype(np.float32)
    rp2 = px * px + py * py
    keep = (rp2 <= 1.0) & (rp2 >= obscuration * obscuration)
    if edge.any():
        rows = np.flatnonzero(edge[cells])
        ask = keep[rows]
        ok = transmission(px[rows][ask].astype(float), py[rows][ask].astype(float))
        sub_keep = keep[rows].copy()
        sub_keep[ask] = ok
        keep[rows] = sub_keep
    return cells, keep


def _splat_to_pixels(u: np.ndarray, v: np.ndarray, shape: tuple[int, int],
                     over: int) -> np.ndarray:
    """Points at fine-grid coordinates (u, v) splatted bilinearly on a grid ``over`` times
    finer than the pixels, then summed over each pixel's ``over x over`` block: the pixel
    integration of the detector.  Only the donut's box of the fine grid is built (whole
    pixels, one pixel of margin); points falling off the image are dropped."""
    ny, nx = shape
    u_lo = max(int(np.floor(u.min() / over)) - 1, 0) * over if u.size else 0
    v_lo = max(int(np.floor(v.min() / over)) - 1, 0) * over if v.size else 0
    fx = min(int(np.ceil((u.max() + 2) / over)) + 1, nx) * over - u_lo if u.size else over
    fy = min(int(np.ceil((v.max() + 2) / over)) + 1, ny) * over - v_lo if v.size else over
    u -= u_lo
    v -= v_lo
    u0, v0 = np.floor(u), np.floor(v)
    tu, tv = u - u0, v - v0
    iu, iv = u0.astype(np.int64), v0.astype(np.int64)
    ok = (iu >= 0) & (iu < fx - 1) & (iv >= 0) & (iv < fy - 1)
    iu, iv, tu, tv = iu[ok], iv[ok], tu[ok], tv[ok]
    k = iv * fx + iu
    idx = np.concatenate([k, k + 1, k + fx, k + fx + 1])
    w = np.concatenate([(1 - tu) * (1 - tv), tu * (1 - tv), (1 - tu) * tv, tu * tv])
    fine = np.bincount(idx, weights=w, minlength=fy * fx).reshape(fy, fx)
    # Sum over each pixel's over x over block: rows first, then columns (contiguous passes).
    rows = fine[0::over].copy()
    for j in range(1, over):
        rows += fine[j::over]
    box = rows[:, 0::over].copy()
    for j in range(1, over):
        box += rows[:, j::over]
    img = np.zeros(shape)
    img[v_lo // over:v_lo // over + box.shape[0], u_lo // over:u_lo // over + box.shape[1]] = box
    return img


def _boundary(grid: tuple[tuple[int, int], np.ndarray], a: np.ndarray,
              b: np.ndarray) -> np.ndarray:
    """Points of ``a`` with a 4-neighbour in ``b`` and points of ``b`` with one in ``a``, on
    the grid ``(shape, flat indices of the points)``."""
    shape, region = grid
    ga = np.zeros(shape[0] * shape[1], bool)
    gb = np.zeros_like(ga)
    ga[region], gb[region] = a, b
    ga, gb = ga.reshape(shape), gb.reshape(shape)

    def touches(m: np.ndarray) -> np.ndarray:
        t = np.zeros_like(m)
        t[1:] |= m[:-1]
        t[:-1] |= m[1:]
        t[:, 1:] |= m[:, :-1]
        t[:, :-1] |= m[:, 1:]
        return t

    return ((ga & touches(gb)) | (gb & touches(ga))).ravel()[region]


def blur_reference(mappings: tuple[ImageMapping, ImageMapping], x: np.ndarray,
                   y: np.ndarray, spacing: float, obscuration: float, weight: np.ndarray,
                   stamp_shape: tuple[int, int], blur_px: float,
                   transmissions: tuple[Callable | None, Callable | None] = (None, None),
                   grid: tuple[tuple[int, int], np.ndarray] | None = None) -> np.ndarray:
    """The difference of the two compensated design donuts, ``(I_intra - I_extra) * weight``
    on the computation points (float32): the edge signal of the blur alone.

    Args:
        mappings: (intra, extra) mappings at the computation points.
        x, y: the points' reduced pupil coordinates, on a grid of step ``spacing``.
        weight: the estimator's signal weight at the points.
        stamp_shape: shape of the stamps the data come in.
        blur_px: sigma (px) of the image blur beyond the pixels: seeing and the estimator's
            smoothing, in quadrature.
        transmissions: each side's ``f(x, y) -> bool`` of pupil points (exact vignetting
            edges, :func:`design_donut`), or None; ``grid`` the points' ``(shape, flat
            indices)`` on their pupil grid.
    """
    centre = ((stamp_shape[1] - 1) / 2.0, (stamp_shape[0] - 1) / 2.0)
    zero = np.zeros((5, x.size), np.float32)  # the design: no wavefront compensated
    out = []
    for m, tr in zip(mappings, transmissions, strict=True):
        img = design_donut(m, x, y, spacing, obscuration, stamp_shape, centre, tr, grid)
        if blur_px > 0:
            img = gaussian_filter(img, blur_px, mode="constant")
        out.append(compensate(img.astype(np.float32), centre, m, zero).intensity)
    return ((out[0] - out[1]) * weight).astype(np.float32)
