"""Preparation of one donut stamp: validation, local background, centroid and flux.

Paper §3.4: with a split sensor the intra and extra images come from different stars, so each
image gets its own local background subtraction and flux normalisation before the TIE is
solved.  Normalisation itself happens in the compensation (:mod:`.compensation`), where the
flux inside the computation region is divided by the pupil area the image illuminates.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache, partial

import numpy as np

from cwfs_ros.errors import (
    DonutCutError,
    FlatImageError,
    ImageError,
    NonFiniteImageError,
    StampTooSmallError,
)
from cwfs_ros.wfs.checks import CheckConfig, check_saturation

__all__ = ["PreparedDonut", "prepare_donut", "MIN_SNR"]

# Below this signal-to-noise ratio a stamp is treated as holding no donut.
MIN_SNR = 10.0
# Aberrations move the donut edge by up to a few pixels beyond the unaberrated radius (about
# 2 px for 250 nm of 5th-order coma at 1 mm), and blur spreads it further; the centroid and
# flux must include that light (Z16 of 250 nm was recovered at 64%, 86%, 91% with 2, 6, 10).
_SPILL_PX = 10.0
# A donut whose flux along the stamp border exceeds this fraction of its median surface
# brightness is cut by the edge.
_EDGE_FRACTION = 0.1


@dataclass(frozen=True)
class PreparedDonut:
    """A background-subtracted stamp and its measured properties.

    Attributes:
        image: background-subtracted image (float64), ``[row=y, col=x]``.
        background: subtracted background level per pixel (input units).
        noise: rms of the background pixels (input units).
        centroid_xy: flux-weighted centroid (col, row) in pixels.
        flux: total donut flux (input units).
        snr: flux signal-to-noise ratio.
    """

    image: np.ndarray
    background: float
    noise: float
    centroid_xy: tuple[float, float]
    flux: float
    snr: float


def order_statistics(values: np.ndarray, ks: list[int]) -> list[float]:
    """The ``k``-th smallest of the flat array ``values`` for each ``k`` in ``ks``.

    Largest ``k`` first, each a single-kth partition of the part left of the previous one
    (which holds exactly the smaller values): numpy's partition with a list of kth is ~6x
    slower (0.7 against 0.12 ms for three quartiles of 20k values).
    """
    found: dict[int, float] = {}
    part = values
    for k in sorted(set(ks), reverse=True):
        part = np.partition(part, k)
        found[k] = float(part[k])
        part = part[:k]
    return [found[k] for k in ks]


def _robust_level(values: np.ndarray) -> tuple[float, float]:
    """Median and quartile-based sigma of background pixels (robust to a few stars/cosmics).

    The three quartiles are order statistics; sigma = IQR / 1.349 for Gaussian noise.
    """
    n = values.size
    q1, med, q3 = order_statistics(values, [n // 4, n // 2, (3 * n) // 4])
    return med, (q3 - q1) / 1.349


@lru_cache(maxsize=8)
def _pixel_axes(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Row and column coordinates (px) of a stamp of ``shape``."""
    ys, xs = np.arange(shape[0], dtype=np.float64), np.arange(shape[1], dtype=np.float64)
    ys.setflags(write=False)
    xs.setflags(write=False)
    return ys, xs


def _centroid(w: np.ndarray, ys: np.ndarray, xs: np.ndarray, tot: float
              ) -> tuple[float, float]:
    """Weighted centroid (col, row) from the weights' column and row sums (two small dot
    products instead of two full-stamp products)."""
    return float(w.sum(axis=0) @ xs / tot), float(w.sum(axis=1) @ ys / tot)


def _radius2(ys: np.ndarray, xs: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """Squared distance (px^2) of every pixel from (cx, cy), by one broadcast sum."""
    return ((ys - cy) ** 2)[:, None] + ((xs - cx) ** 2)[None, :]


def _light_radius(work: np.ndarray, r2: np.ndarray, r0: float, sigma: float,
                  total: float, step_px: float = 5.0) -> float:
    """Radius of the window that holds all of a donut's light: ``r0`` or more.

    Several microns of aberration move the donut's edge by more than ``_SPILL_PX``
    (astigmatism and coma of 3 um each at an LSST corner: ~10 px, independent of the
    defocus), and a centroid that misses that light aligns the compensation wrongly: the
    M2-tilt linearity test (validation Fig. 9) then left linearity at 3 um of Z5, long
    before the geometric limit, without any caustic flag.  The window grows by ``step_px``
    rings while a ring holds significant light: more than 3 sigma of its background noise
    and more than 0.01 % of the flux (for noise-free model images).
    """
    r_max = float(np.sqrt(r2.max()))
    r = r0
    while r < r_max:
        # Two rings ahead, so that one faint ring inside a coma tail does not end it.
        ring = (r2 > r * r) & (r2 <= (r + 2 * step_px) ** 2)
        n = int(ring.sum())
        if n == 0:
            break
        flux = float(work[ring].sum())
        if flux <= max(3.0 * sigma * np.sqrt(n), 1e-4 * total):
            break
        r += step_px
    return r


def prepare_donut(image: np.ndarray, *, name: str, outer_radius_px: float,
                  margin_px: float, saturation_level: float | None = None,
                  checks: CheckConfig | None = None) -> PreparedDonut:
    """Validate a donut stamp and measure background, centroid and flux.

    Paper §3.4: each image gets its own local background and flux measurement, as the two
    images of a split sensor come from different stars.  The steps: the stamp is checked
    (:func:`_checked_stamp`), a first centroid found above a threshold over the border's
    background (:func:`_thresholded_centroid`), the background re-measured away from the
    donut (:func:`_sky_outside`), the centroid iterated with a window holding all the light
    (:func:`_window_centroid`), and the donut tested for saturation, S/N and the stamp
    edges (:func:`_check_edges`).

    Args:
        image: 2-D stamp ``[row=y, col=x]``.
        name: ``"intra"`` or ``"extra"`` (used in error messages).
        outer_radius_px: expected outer radius of the donut image in pixels.
        margin_px: extra room needed around the donut (the computation boundary).
        saturation_level: pixel value (input units, as the stamp is given) at or above
            which a pixel is saturated; None when unknown (the plateau test still runs).
        checks: thresholds of the saturation tests (:class:`.checks.CheckConfig`); the
            defaults when None.

    Raises:
        ImageError subclasses naming the problem: non-finite pixels, an empty or flat image,
        a stamp too small for the donut at this defocus, a donut cut by the stamp edge, a
        saturated or clipped donut.
    """
    img = _checked_stamp(image, name, outer_radius_px, margin_px)
    border = np.concatenate([img[:2].ravel(), img[-2:].ravel(), img[2:-2, :2].ravel(),
                             img[2:-2, -2:].ravel()])
    bg, sig = _robust_level(border)
    ys, xs = _pixel_axes(img.shape)
    peak, first = _thresholded_centroid(img - bg, ys, xs, name)
    oversized = partial(_oversized, img, bg, ys, xs, first, outer_radius_px)
    sky, bg, sig = _sky_outside(img, ys, xs, first, outer_radius_px, border, (bg, sig))
    work = img - bg
    try:
        centre, r_win = _window_centroid(work, ys, xs, first, outer_radius_px, sig, name)
    except FlatImageError as exc:
        raise FlatImageError(f"{exc}{oversized()}") from None
    cx, cy = centre
    r2 = _radius2(ys, xs, cx, cy)
    inside = r2 <= r_win * r_win
    # Saturation before the flux tests: a donut clipped near its background would otherwise
    # be reported as faint.  A background that is exactly constant means a noise-free
    # (model) image, whose flat top need not be saturation.
    body_mask = (r2 <= outer_radius_px**2) & (work > 0.3 * peak)
    check_saturation(img, name=name, background=bg, noise_present=bool(np.ptp(sky) > 0),
                     donut=inside, body_pixels=int(body_mask.sum()), level=saturation_level,
                     config=checks or CheckConfig())
    flux = float(work[inside].sum())
    npix = int(inside.sum())
    # Background-limited S/N: the input units need not be photons, so no Poisson term.
    noise_var = npix * sig * sig
    snr = flux / np.sqrt(noise_var) if noise_var > 0 else np.inf
    if flux <= 0 or snr < MIN_SNR:
        raise FlatImageError(
            f"{name} image holds no donut: flux {flux:.4g} at S/N {snr:.1f} "
            f"(minimum {MIN_SNR:g}) around its light's centroid; a stamp holds one donut "
            "(frames with several stars: cwfs_ros.frames.estimate_corner_frames)"
            + oversized()
        )
    body = work[body_mask]
    _check_edges(work, centre, outer_radius_px, margin_px,
                 float(np.median(body)) if body.size else peak, name)
    return PreparedDonut(work, bg, sig, (cx, cy), flux, float(snr))


# The fraction of a refused stamp's light (above its border's level) beyond the expected
# donut from which the refusal says the donut is larger than expected: a neighbour's light
# or a sky gradient stays well below it, a donut twice its size puts nearly all its light
# there.
_OVERSIZED_FRACTION = 0.5


def _oversized(img: np.ndarray, border_level: float, ys: np.ndarray, xs: np.ndarray,
               centre: tuple[float, float], outer_radius_px: float) -> str:
    """For a stamp refused as holding no flux: the reason when most of its light (above
    the border's level) lies beyond the donut's expected radius around the first centroid
    (a donut larger than the geometry predicts, whose "sky" was measured on the donut),
    else ""."""
    above_border = img - border_level
    total = float(above_border.sum())
    beyond = _radius2(ys, xs, *centre) > (outer_radius_px + 2 * _SPILL_PX) ** 2
    if not total > 0:
        return ""
    frac = float(above_border[beyond].sum()) / total
    if frac <= _OVERSIZED_FRACTION:
        return ""
    return (f" ({frac:.0%} of its light lies beyond the donut's expected radius of "
            f"{outer_radius_px:.0f} px: the donut is larger than this instrument and defocal "
            "offset give. A stamp resampled to other pixels than the instrument's, or a "
            "wrong defocal offset or instrument?)")


def _checked_stamp(image: np.ndarray, name: str, outer_radius_px: float,
                   margin_px: float) -> np.ndarray:
    """The stamp as a float64 copy, if it is a finite 2-D real image large enough for the
    donut and its margin and not constant; otherwise the ImageError naming why not."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ImageError(f"{name} image must be 2-D, got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.number) or np.iscomplexobj(img):
        raise ImageError(f"{name} image must be real numbers, got dtype {img.dtype}")
    img = img.astype(np.float64, copy=True)
    bad = ~np.isfinite(img)
    if bad.any():
        raise NonFiniteImageError(
            f"{name} image has {int(bad.sum())} non-finite pixel(s) (NaN or Inf)"
        )
    need = int(np.ceil(2 * (outer_radius_px + margin_px)))
    if min(img.shape) < need:
        raise StampTooSmallError(
            f"{name} stamp {img.shape[1]}x{img.shape[0]} px is too small for a donut of "
            f"radius {outer_radius_px:.1f} px plus {margin_px:.0f} px margin: need at least "
            f"{need}x{need} px (the radius follows from the instrument and the defocal "
            "offset: check both if the stamp holds the whole donut)"
        )
    if float(img.max() - img.min()) == 0.0:
        raise FlatImageError(f"{name} image is constant ({float(img.flat[0]):g}): no donut")
    return img


def _thresholded_centroid(work: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                          name: str) -> tuple[float, tuple[float, float]]:
    """(peak, (col, row)): a robust peak level (the 99.5th percentile of every other pixel)
    of the background-subtracted stamp, and the centroid of the pixels above 30 % of it: a
    first guess that stray pixels cannot pull far."""
    sub = work[::2, ::2].ravel()
    k = int(0.995 * (sub.size - 1))
    peak = float(np.partition(sub, k)[k])
    if peak <= 0:
        raise FlatImageError(f"{name} image has no flux above its background")
    w = np.where(work > 0.3 * peak, work, 0.0)
    return peak, _centroid(w, ys, xs, w.sum())


def _sky_outside(img: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                 centre: tuple[float, float], outer_radius_px: float, border: np.ndarray,
                 level: tuple[float, float]) -> tuple[np.ndarray, float, float]:
    """(sky pixels, background, noise): from the pixels well outside the donut where there
    are enough of them (at least 50 and 5 % of the stamp), else the border's ``level``."""
    r2 = _radius2(ys, xs, *centre)
    outside = r2 > (outer_radius_px + 2 * _SPILL_PX) ** 2
    if outside.sum() >= max(50, 0.05 * img.size):
        sky = img[outside]
        bg, sig = _robust_level(sky)
        return sky, bg, sig
    return border, level[0], level[1]


def _window_centroid(work: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                     centre: tuple[float, float], outer_radius_px: float, sig: float,
                     name: str) -> tuple[tuple[float, float], float]:
    """((col, row), window radius): the flux-weighted centroid of all the donut's light.

    The window and the centroid depend on each other: the window is re-centred on the
    centroid of the light inside it, and grown to all the light (:func:`_light_radius`),
    until the centroid stops moving (0.01 px; at most 10 passes).  A window centred on the
    first, thresholded centroid cuts a comatic donut's far side and pulls the centroid by
    pixels (3 px at 3 um of Z5).
    """
    cx, cy = centre
    w = np.where(_radius2(ys, xs, cx, cy) <= (outer_radius_px + _SPILL_PX) ** 2, work, 0.0)
    tot = w.sum()
    if tot <= 0:
        raise FlatImageError(f"{name} image has no flux above its background")
    cx, cy = _centroid(w, ys, xs, tot)
    for _ in range(10):
        r2 = _radius2(ys, xs, cx, cy)
        r_win = _light_radius(work, r2, outer_radius_px + _SPILL_PX, sig, tot)
        w = np.where(r2 <= r_win * r_win, work, 0.0)
        tot = w.sum()
        if tot <= 0:
            raise FlatImageError(f"{name} image has no flux above its background")
        nx_, ny_ = _centroid(w, ys, xs, tot)
        moved = np.hypot(nx_ - cx, ny_ - cy)
        cx, cy = nx_, ny_
        if moved < 0.01:
            break
    return (cx, cy), r_win


def _check_edges(work: np.ndarray, centre: tuple[float, float], outer_radius_px: float,
                 margin_px: float, level: float, name: str) -> None:
    """DonutCutError unless the donut's circle lies inside the stamp and the stamp's border
    is dark (below ``_EDGE_FRACTION`` of the donut's median ``level``); StampTooSmallError
    unless it also leaves the solver's margin inside the stamp."""
    ny, nx = work.shape
    cx, cy = centre
    lo_x, hi_x = cx - outer_radius_px, cx + outer_radius_px
    lo_y, hi_y = cy - outer_radius_px, cy + outer_radius_px
    if lo_x < 0 or lo_y < 0 or hi_x > nx - 1 or hi_y > ny - 1:
        raise DonutCutError(
            f"{name} donut (centre col {cx:.1f}, row {cy:.1f}, radius {outer_radius_px:.1f} px) "
            f"extends beyond the {nx}x{ny} stamp"
        )
    edge_means = [work[0].mean(), work[-1].mean(), work[:, 0].mean(), work[:, -1].mean()]
    if max(edge_means) > _EDGE_FRACTION * level:
        raise DonutCutError(
            f"{name} donut is cut by the stamp edge: border brightness "
            f"{max(edge_means):.4g} is {max(edge_means) / level:.0%} of the donut's"
        )
    if lo_x < margin_px or lo_y < margin_px or hi_x > nx - 1 - margin_px or \
            hi_y > ny - 1 - margin_px:
        raise StampTooSmallError(
            f"{name} donut is off-centre: centre (col {cx:.1f}, row {cy:.1f}) leaves less than "
            f"the {margin_px:.0f} px margin the solver needs inside the {nx}x{ny} stamp"
        )
