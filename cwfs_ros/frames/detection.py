"""Donut detection in a corner half-chip frame: sky background, matched filter, rejections.

A corner wavefront sensor half-chip (LSST: 2k x 4k pixels of 10 µm) records several
defocused stars at once.  The paper (Xin et al. 2015, Fig. 2 caption) leaves "the strategy
in making use of multiple stars on each half-chip" open; this module is its first step:
find the usable donuts of one frame and cut the stamps the estimator expects (§3.4 then
treats each stamp on its own).

Steps (all on a frame already in the focal-plane orientation, ``[row=y, col=x]``):

1. **Sky background** (:func:`estimate_background`): the frame is binned ``bin_px`` x
   ``bin_px``; a sigma-clipped median per mesh cell of the binned frame (clipped from above,
   because donuts only add light) gives a coarse, spatially varying sky map, median
   filtered over 3 x 3 cells and interpolated bilinearly.
2. **Candidates** (:func:`detect_donuts`): matched filter of the binned, sky-subtracted frame
   with the expected donut, a zero-mean annulus of the outer/inner radius the instrument
   predicts at this defocus (:func:`expected_donut_radii_px`), by FFT.  Local maxima above
   ``detect_snr`` (in units of the filter's own noise) are candidates.  The zero-mean annulus
   has side lobes (a donut correlates positively with the template shifted by about one
   radius), so a weaker peak near a stronger one counts as a second source only if it stands
   clearly above the stronger one's side lobe (measured on the template itself).
3. **Measurement** at full resolution around each candidate: centroid, flux, surface
   brightness, S/N, the highest raw pixel, and two shape numbers: the fraction of the flux in
   the donut's central hole and outside its footprint (both near zero for an isolated donut,
   large for two overlapping ones).
4. **Rejection**, each with a reason (:data:`REASONS`), in this order:
   ``bad_pixels`` (the stamp holds a NaN or Inf pixel, or a dead one: a frame with a few
   NaN or Inf, up to ``max_nonfinite_fraction``, or with dead regions (blocks of identical
   values, a dead or unread amplifier) is searched with them set to its median, and only the
   stars whose stamps hold one are dropped), ``donut_cut_by_edge`` (the stamp does not fit
   in the frame), ``saturated`` (a raw pixel in
   the footprint reaches ``saturation_level``), ``blended`` (another source within
   ``blend_distance_px`` - by default close enough for its light to enter this stamp -, or a
   flux centroid pulled away from the ring's centre, or light in the ring's hole or outside
   its footprint: an overlapping companion), ``too_faint`` (S/N < ``min_snr``).

Pixel coordinates are pixel-centre based: pixel (col i, row j) is centred at (x, y) = (i, j).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache, partial

import numpy as np
from scipy import fft as sfft
from scipy.ndimage import find_objects, label, maximum_filter1d, median_filter

from cwfs_ros.errors import (
    ConfigError,
    DonutCutError,
    FlatImageError,
    FrameUnitsError,
    ImageError,
    NonFiniteImageError,
)
from cwfs_ros.wfs.donuts import order_statistics
from cwfs_ros.wfs.instrument import Instrument

__all__ = [
    "REASONS",
    "DetectionConfig",
    "DetectedDonut",
    "Background",
    "estimate_background",
    "expected_donut_radii_px",
    "detect_donuts",
    "cut_stamp",
]

# Rejection reasons.  The edge reason is the estimator's own (errors.DonutCutError), so that a
# node counts a donut cut by the frame edge and one cut by a stamp edge together.
REASON_BAD_PIXELS = "bad_pixels"
REASON_EDGE = DonutCutError.reason
REASON_SATURATED = "saturated"
REASON_BLENDED = "blended"
REASON_FAINT = "too_faint"
REASONS = (REASON_BAD_PIXELS, REASON_EDGE, REASON_SATURATED, REASON_BLENDED, REASON_FAINT)


@dataclass(frozen=True)
class DetectionConfig:
    """Parameters of the detector (``config/selection.yaml``, section ``detection``).

    Attributes:
        bin_px: binning factor of the frame for background and matched filter.  A donut is
            ~130 px across with a ~26 px ring, so 8 x 8 binning keeps ~16 binned px per
            donut and a 3 px ring; centroids and shapes are measured at full resolution.
            Against 4 x 4 the selection of the simulated frames is the same (blends, faint
            and isolated stars, centroids) at two thirds of the detection time
            (docs/performance.md, Frames).
        mesh_px: side of a background mesh cell, full-resolution pixels.  Larger than a
            donut, so that a cell is never mostly donut.
        detect_snr: matched-filter S/N above which a peak is a source (used for blend
            checks too, so it is lower than ``min_snr``).
        min_snr: flux S/N below which a donut is rejected as ``too_faint``.
        saturation_level: raw pixel value (frame units, before sky subtraction) at or above
            which a donut is ``saturated``; ``None`` disables the check.
        gain_e_per_adu: electrons per frame unit, for the Poisson part of the S/N.
        spill_px: light beyond the unaberrated outer radius that belongs to the donut
            (aberrations and blur move the edge by a few pixels; as in :mod:`.donuts`).
        blend_distance_px: a source closer than this (centre to centre, px) blends; ``None``
            means ``stamp_px / sqrt(2) + outer radius + spill_px``: closer, the neighbour's
            light may reach this donut's stamp (its corners included), where the estimator
            would take it for the donut's or the background's.
        max_hole_fraction: largest fraction of the flux allowed inside the central hole
            (radius ``0.8 * inner`` around the ring centre found by the matched filter),
            above which light from another donut is assumed ...
        max_outside_fraction: ... and the same for the flux outside the footprint, within
            the stamp's circumscribed circle.
        max_centre_offset_px: largest distance between the flux centroid and the ring
            centre (an overlapping companion pulls the centroid towards itself).
        shape_nsigma: each of the three shape limits is raised by this many times the
            measurement's own noise, so that faint donuts are not called blended by noise.
        sidelobe_margin: a peak within two donut diameters of a stronger one is a source
            if its S/N exceeds ``sidelobe_margin * side lobe * S/N of the stronger`` ...
        unexplained_fraction: ... or if the stronger donut's own light (inside its
            footprint) leaves more of the peak unexplained than ``detect_snr +
            unexplained_fraction * S/N of the stronger``: a fainter star close by.
        max_candidates: at most this many peaks are measured (brightest first).
        max_nonfinite_fraction: a frame with more of its pixels NaN or Inf than this is
            refused whole; with fewer, only the stars whose stamps hold one are.
    """

    bin_px: int = 8
    mesh_px: int = 256
    detect_snr: float = 8.0
    min_snr: float = 40.0
    saturation_level: float | None = 1.0e5
    gain_e_per_adu: float = 1.0
    spill_px: float = 8.0
    blend_distance_px: float | None = None
    max_hole_fraction: float = 0.03
    max_outside_fraction: float = 0.03
    max_centre_offset_px: float = 3.0
    shape_nsigma: float = 4.0
    sidelobe_margin: float = 1.5
    unexplained_fraction: float = 0.02
    max_candidates: int = 64
    max_nonfinite_fraction: float = 0.25

    def __post_init__(self) -> None:
        problems = []
        if not isinstance(self.bin_px, int) or not 1 <= self.bin_px <= 16:
            problems.append(f"bin_px must be an integer in 1..16, got {self.bin_px!r}")
        if not isinstance(self.mesh_px, int) or self.mesh_px < 4 * self.bin_px:
            problems.append(f"mesh_px must be an integer >= 4 * bin_px, got {self.mesh_px!r}")
        for name in ("detect_snr", "min_snr", "gain_e_per_adu", "sidelobe_margin"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                problems.append(f"{name} must be a positive number, got {v!r}")
        for name in ("spill_px", "max_hole_fraction", "max_outside_fraction",
                     "max_centre_offset_px", "shape_nsigma", "unexplained_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0):
                problems.append(f"{name} must be >= 0, got {v!r}")
        if self.saturation_level is not None and not self.saturation_level > 0:
            problems.append(f"saturation_level must be > 0 or null, got "
                            f"{self.saturation_level!r}")
        if self.blend_distance_px is not None and not self.blend_distance_px >= 0:
            problems.append(f"blend_distance_px must be >= 0 or null, got "
                            f"{self.blend_distance_px!r}")
        if not isinstance(self.max_candidates, int) or self.max_candidates < 1:
            problems.append(f"max_candidates must be an integer >= 1, got "
                            f"{self.max_candidates!r}")
        v = self.max_nonfinite_fraction
        if not (isinstance(v, (int, float)) and 0.0 <= v < 1.0):
            problems.append(f"max_nonfinite_fraction must be in [0, 1), got {v!r}")
        if problems:
            raise ConfigError("detection: " + "; ".join(problems))

    def with_overrides(self, **kw: object) -> DetectionConfig:
        """A copy with some fields replaced (validated again)."""
        return replace(self, **kw)


@dataclass(frozen=True)
class DetectedDonut:
    """One source found in a frame, accepted (``status == "ok"``) or rejected.

    Attributes:
        x, y: flux centroid (col, row), pixel-centre convention, full-resolution pixels.
        flux: sky-subtracted flux inside the footprint (frame units).
        snr: flux S/N (Poisson of the flux plus the measured sky noise).
        peak_value: highest raw pixel value (before sky subtraction) inside the footprint.
        detect_snr: matched-filter S/N of the peak.
        hole_fraction, outside_fraction: flux in the central hole / outside the footprint
            (within the stamp) as fractions of ``flux``.
        status: ``"ok"`` or the first failed check, one of :data:`REASONS`.
        reasons: every failed check.
        message: a sentence explaining the first failure (``""`` when ok).
        neighbour_px: distance to the nearest other source (px), ``inf`` if none.
        centre_offset_px: flux centroid minus matched-filter ring centre (px).
    """

    x: float
    y: float
    flux: float
    snr: float
    peak_value: float
    detect_snr: float
    hole_fraction: float
    outside_fraction: float
    status: str
    reasons: tuple[str, ...] = ()
    message: str = ""
    neighbour_px: float = float("inf")
    centre_offset_px: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


# A sky noise below this fraction of one electron's shot noise is none at all (a model
# frame without noise; float rounding leaves ~1e-13).
_NO_NOISE_FRACTION = 1e-6


@dataclass(frozen=True)
class Background:
    """Sky model of a frame.

    Attributes:
        mesh: sky level per mesh cell (frame units per full-resolution pixel).
        cell_px: (rows, cols) of a cell, full-resolution pixels; cell (i, j) is centred at
            x = (j + 0.5) * cell_px[1] - 0.5, y = (i + 0.5) * cell_px[0] - 0.5.
        noise: rms of the sky-subtracted pixels (frame units per full-resolution pixel).
        n_nonfinite: NaN or Inf pixels of the frame, set to its median for the search.
        n_dead: pixels of the frame in dead blocks (``bin_px`` square blocks of one value
            that a neighbour block shares), set to its median for the search.
        measured_noise: the sky's own rms when it was below one electron's shot noise and
            ``noise`` was raised to that (None otherwise).
    """

    mesh: np.ndarray
    cell_px: tuple[float, float]
    noise: float
    n_nonfinite: int = 0
    n_dead: int = 0
    measured_noise: float | None = None

    @property
    def quiet_sky(self) -> bool:
        """The sky had noise, but less than one electron's shot noise (to which ``noise``
        was raised): the frame's units may not be electrons.  A model frame without noise
        has none at all, and is not quiet in this sense."""
        return (self.measured_noise is not None
                and self.measured_noise > _NO_NOISE_FRACTION * self.noise)

    def _weights(self, coords: np.ndarray, axis: int) -> np.ndarray:
        """Bilinear weights (len(coords), mesh cells along ``axis``).

        Between the outer cell centres and the frame edge (half a cell) the outer two cells
        are extrapolated linearly, so that a sky gradient is followed to the edge; no further.
        """
        n = self.mesh.shape[axis]
        # np.minimum/np.maximum: np.clip's call overhead dominates on stamp-sized inputs.
        c = np.minimum(np.maximum((np.asarray(coords, dtype=np.float64) + 0.5)
                                  / self.cell_px[axis] - 0.5, -0.5), n - 0.5)
        if n == 1:
            return np.ones((c.size, 1))
        i0 = np.minimum(np.maximum(np.floor(c).astype(np.int64), 0), n - 2)
        t = c - i0
        w = np.zeros((c.size, n))
        rows = np.arange(c.size)
        w[rows, i0] = 1.0 - t
        w[rows, i0 + 1] += t
        return w

    def grid(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Sky level on the grid of pixel-centre coordinates ``ys`` (rows) x ``xs`` (cols).

        Bilinear between cell centres, constant beyond the outer ones; separable, so it
        costs two small matrix products rather than a per-pixel interpolation.
        """
        return self._weights(ys, 0) @ self.mesh @ self._weights(xs, 1).T

    def level(self, x0: int, y0: int, nx: int, ny: int) -> np.ndarray:
        """Sky level on the full-resolution pixels ``[y0:y0+ny, x0:x0+nx]``."""
        return self.grid(np.arange(x0, x0 + nx), np.arange(y0, y0 + ny))


def expected_donut_radii_px(inst: Instrument, defocal_offset_mm: float | None = None
                            ) -> tuple[float, float]:
    """Outer and inner radius (px) of an unaberrated donut on axis, from the instrument.

    The marginal ray of an f/N beam leaves the pupil edge at ``sin u = 1 / (2N)`` (aplanatic
    telescope), so a detector ``l`` from focus sees an outer radius ``l tan u``; the paraxial
    ``l / (2N)`` is 9 % short at LSST's f/1.23 (paper §3.2).  The inner radius scales with the
    obscuration (0.61 for LSST).
    """
    l_mm = inst.defocal_offset_mm if defocal_offset_mm is None else float(defocal_offset_mm)
    s = 1.0 / (2.0 * inst.f_number)
    r_out = l_mm * 1e3 * np.tan(np.arcsin(min(s, 0.99))) / inst.pixel_size_um
    return float(r_out), float(inst.obscuration * r_out)


def _binned(frame: np.ndarray, b: int) -> np.ndarray:
    """Sum over b x b blocks, in float64 (the frame is trimmed to a multiple of b).

    Rows first: each ``frame[k::b]`` is a set of whole rows, so the pass over the full frame
    reads contiguous memory and writes a frame b times smaller; the column sums then run on
    that.  (numpy's reduction over the inner axes of a 4-D reshape is ~20x slower for b = 4;
    columns first, or a float64 copy of the frame, cost 3-4x more: 14 against 4 ms on a
    2-Mpixel float32 frame, docs/performance.md, Frames.)
    """
    ny, nx = (frame.shape[0] // b) * b, (frame.shape[1] // b) * b
    a = frame[:ny, :nx]
    if b == 1:
        return np.array(a, dtype=np.float64)
    # A float32 frame's row sums stay float32 (b values: exact for photon counts below
    # 2^24 / b, 1e-7 relative otherwise), halving the traffic of the full-frame pass; the
    # block sums are float64.
    # NaN, Inf and overflow propagate silently into the sums: _nonfinite reads them there.
    with np.errstate(over="ignore", invalid="ignore"):
        rows = np.add(a[0::b], a[1::b],
                      dtype=np.float32 if a.dtype == np.float32 else np.float64)
        for k in range(2, b):
            rows += a[k::b]
        out = rows[:, 0::b].astype(np.float64)
        for k in range(1, b):
            out += rows[:, k::b]
    return out


def _local_maxima(snr_map: np.ndarray, threshold: float, half: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels above ``threshold`` that are the maximum of their
    (2 half + 1)^2 window (cut at the map's edges).

    Only the boxes around the connected above-threshold regions are filtered, each padded by
    ``half`` so that every window of its pixels lies inside: the same pixels as filtering the
    whole map, for the few percent of it that donuts cover (7 ms -> well under 1 ms on a
    2-Mpixel frame's binned map).
    """
    above = snr_map > threshold
    labels, n = label(above)
    if n == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    ny, nx = snr_map.shape
    loc = np.zeros_like(above)
    for sy, sx in find_objects(labels):
        y0, y1 = max(sy.start - half, 0), min(sy.stop + half, ny)
        x0, x1 = max(sx.start - half, 0), min(sx.stop + half, nx)
        # Max over the window, cut at the map's edges (-inf beyond them): the two passes
        # of maximum_filter, called directly (its own set-up is most of the cost on boxes
        # of a few hundred pixels).
        peak = snr_map[y0:y1, x0:x1]
        for axis in (0, 1):
            peak = maximum_filter1d(peak, 2 * half + 1, axis=axis, mode="constant",
                                    cval=-np.inf)
        box = (slice(sy.start, sy.stop), slice(sx.start, sx.stop))
        inner = (slice(sy.start - y0, sy.stop - y0), slice(sx.start - x0, sx.stop - x0))
        loc[box] |= above[box] & (snr_map[box] == peak[inner])
    return np.nonzero(loc)


def _clipped_level(cells: np.ndarray, n_iter: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Per-row median and sigma of ``cells`` (n_cells, n_values), clipped from above.

    Sigma comes from the lower half (median minus 15.9th percentile), which sources do not
    touch; values above median + 3 sigma are dropped and the median recomputed.  Clipping
    from above only shortens each sorted row, so one sort serves every pass.
    """
    srt = np.sort(cells, axis=1)
    rows = np.arange(srt.shape[0])
    n = np.full(srt.shape[0], srt.shape[1])
    for _ in range(n_iter + 1):
        med = 0.5 * (srt[rows, (n - 1) // 2] + srt[rows, n // 2])
        lo = srt[rows, np.clip((0.1587 * (n - 1)).astype(np.int64), 0, None)]
        sig = np.maximum(med - lo, 1e-12)
        # Values <= the clip level per row (searchsorted "right" on each sorted row).
        n_new = np.maximum(np.count_nonzero(srt <= (med + 3.0 * sig)[:, None], axis=1), 8)
        if np.array_equal(n_new, n):
            break
        n = np.minimum(n_new, srt.shape[1])
    return med, sig


def _sky_binned(bg: Background, shape_b: tuple[int, int], b: int) -> np.ndarray:
    """The sky model on the binned grid (the mesh is per full pixel; a binned pixel sums b^2).

    Binned pixel i covers full pixels [i b, (i + 1) b): its centre is (i + 0.5) b - 0.5.
    """
    return bg.grid((np.arange(shape_b[1]) + 0.5) * b - 0.5,
                   (np.arange(shape_b[0]) + 0.5) * b - 0.5) * (b * b)


def _lower_sigma(values: np.ndarray) -> float:
    """Median minus 15.87th percentile (one sigma of the lower half) of a flat array."""
    lo, med = order_statistics(values, [int(0.1587 * (values.size - 1)),
                                        (values.size - 1) // 2])
    return med - lo


def _background_from_binned(binned: np.ndarray, b: int, mesh_px: int,
                            live: np.ndarray | None = None) -> tuple[Background, np.ndarray]:
    """Background model from a binned frame (see :func:`estimate_background`), and the
    sky-subtracted binned frame it was measured on; the noise from the ``live`` blocks only
    (those without pixels set aside), when given."""
    m = max(2, mesh_px // b)  # cell side in binned pixels
    ny, nx = binned.shape
    gy, gx = max(1, ny // m), max(1, nx // m)
    my, mx = ny // gy, nx // gx  # cells tile the frame; the last rows/cols go to no cell
    cells = binned[:gy * my, :gx * mx].reshape(gy, my, gx, mx).transpose(0, 2, 1, 3)
    med, sig = _clipped_level(cells.reshape(gy * gx, my * mx))
    mesh = med.reshape(gy, gx) / (b * b)
    if min(gy, gx) >= 3:
        mesh = median_filter(mesh, size=3, mode="nearest")  # one cell on a bright star
    bg = Background(mesh=mesh, cell_px=(float(my * b), float(mx * b)), noise=0.0)
    # Noise from the sky-subtracted binned frame (a sky gradient inside a cell would inflate
    # the cells' own spread): lower-half sigma, untouched by sources; white noise of sigma s
    # per full pixel is b s per binned pixel.
    sub = binned - _sky_binned(bg, binned.shape, b)
    noise = max(_lower_sigma(sub[live] if live is not None and live.any() else sub.ravel()),
                1e-12) / b
    return Background(mesh=mesh, cell_px=bg.cell_px, noise=noise), sub


def estimate_background(frame: np.ndarray, config: DetectionConfig | None = None
                        ) -> Background:
    """Robust, spatially varying sky model of a frame.

    Args:
        frame: 2-D frame ``[row=y, col=x]`` (frame units, e.g. electrons).
        config: detector parameters (``bin_px``, ``mesh_px``).

    Returns:
        A :class:`Background` (sky per full-resolution pixel on a coarse mesh, and the pixel
        noise).
    """
    cfg = config or DetectionConfig()
    return _background_from_binned(_binned(np.asarray(frame), cfg.bin_px), cfg.bin_px,
                                   cfg.mesh_px)[0]


def _annulus(n: int, centre: float, r_out: float, r_in: float, sub: int = 4) -> np.ndarray:
    """Area fraction of each pixel of an (n, n) grid inside the annulus (supersampled)."""
    s = (np.arange(n * sub) + 0.5) / sub - 0.5 - centre
    yy, xx = np.meshgrid(s, s, indexing="ij")
    r = np.hypot(xx, yy)
    inside = ((r <= r_out) & (r >= r_in)).astype(np.float64)
    return inside.reshape(n, sub, n, sub).mean(axis=(1, 3))


@lru_cache(maxsize=16)
def _template(r_out_b: float, r_in_b: float, support_b: float) -> tuple[np.ndarray, float]:
    """Zero-mean annulus template (binned px) and its largest side lobe (fraction of peak).

    Zero mean over the support disk: a flat sky (or a residual sky gradient's mean) gives no
    response.  Normalised to unit L2 norm, so that correlating white noise of sigma s gives a
    response of rms s.
    """
    n = 2 * int(np.ceil(support_b)) + 1
    c = (n - 1) / 2.0
    ring = _annulus(n, c, r_out_b, r_in_b)
    disk = _annulus(n, c, support_b, 0.0)
    t = ring - disk * (ring.sum() / disk.sum())
    t /= np.sqrt((t * t).sum())
    # Autocorrelation: its maximum beyond the central lobe is the side lobe.
    m = 2 * n
    ft = sfft.rfft2(t, (m, m))
    ac = sfft.irfft2(ft * np.conj(ft), (m, m))
    ac = np.fft.fftshift(ac)
    yy, xx = np.indices(ac.shape) - m // 2
    far = np.hypot(xx, yy) > max(2.0, 0.5 * (r_out_b - r_in_b))
    side = float(ac[far].max() / ac[m // 2, m // 2])
    t.setflags(write=False)
    return t, max(side, 0.0)


@lru_cache(maxsize=16)
def _template_spectrum(r_out_b: float, r_in_b: float, support_b: float,
                       shape: tuple[int, int]) -> np.ndarray:
    """rfft2 (complex64) of the flipped template, zero-padded to ``shape`` (cached: the
    frame size and the donut radii repeat from visit to visit)."""
    tmpl, _ = _template(r_out_b, r_in_b, support_b)
    spec = sfft.rfft2(tmpl[::-1, ::-1].astype(np.float32), shape)
    spec.setflags(write=False)
    return spec


def _correlate(image: np.ndarray, template_key: tuple[float, float, float]) -> np.ndarray:
    """Same-size correlation of an image with the symmetric odd-sized :func:`_template` of
    ``template_key``, by FFT in single precision.

    Single precision halves the cost (7 -> 3 ms on a 2-Mpixel frame's binned map); its
    rounding, ~1e-7 of the map's largest values, is far below the filter's noise of 1.
    """
    ny, nx = image.shape
    k = _template(*template_key)[0].shape[0]
    shape = (sfft.next_fast_len(ny + k - 1, real=True), sfft.next_fast_len(nx + k - 1, real=True))
    f = sfft.rfft2(image.astype(np.float32), shape)
    f *= _template_spectrum(*template_key, shape)
    full = sfft.irfft2(f, shape)
    h = k // 2
    return full[h:h + ny, h:h + nx].astype(np.float64)


@dataclass
class _Candidate:
    x: float
    y: float
    detect_snr: float


def _find_peaks(snr_map: np.ndarray, threshold: float, min_sep_b: float, sidelobe: float,
                margin: float, near_b: float, max_n: int, b: int,
                explained: Callable[[tuple[int, int], tuple[int, int]], float] | None = None,
                unexplained: float = 0.0) -> list[_Candidate]:
    """Local maxima above threshold, minus the side lobes of stronger peaks.

    A weaker peak near a stronger one is its side lobe if it is below ``margin * sidelobe``
    of it (plus the threshold), unless ``explained(strong, weak)`` -- the S/N that the
    stronger donut's own light gives at the weaker peak -- leaves more than ``threshold +
    unexplained * strong`` of it unexplained.  The side-lobe level is that of the central
    lobe's shoulder, which also covers the bumps that real (vignetted, aberrated) donuts
    make in the filter's response, so a faint star next to a bright one needs the second
    test to be seen.
    """
    half = max(1, int(np.ceil(min_sep_b)))
    iy, ix = _local_maxima(snr_map, threshold, half)
    vals = snr_map[iy, ix]
    order = np.argsort(vals)[::-1]
    kept: list[tuple[int, int, float]] = []
    for k in order:
        y, x, v = int(iy[k]), int(ix[k]), float(vals[k])
        lobe = False
        for ky, kx, kv in kept:
            if abs(y - ky) <= half and abs(x - kx) <= half:
                # Inside a kept peak's window: both are the maximum of windows holding the
                # other, so they tie, a plateau of one source (a noise-free donut centred on
                # a binned-pixel boundary).  Kept twice, the two would converge on the same
                # centroid and blend each other away.
                lobe = True
                break
            if np.hypot(y - ky, x - kx) <= near_b and v < margin * sidelobe * kv + threshold:
                lobe = (explained is None or v - explained((ky, kx), (y, x))
                        < threshold + unexplained * kv)
                if lobe:
                    break
        if not lobe:
            kept.append((y, x, v))
        if len(kept) >= max_n:
            break
    out = []
    ny, nx = snr_map.shape
    for y, x, v in kept:
        # Sub-pixel peak: a parabola through the peak and its two neighbours on each axis
        # (the ring's centre to ~0.2 binned px; it is what the blend test compares the flux
        # centroid with).
        fy = fx = 0.0
        if 0 < y < ny - 1:
            a, c = snr_map[y - 1, x], snr_map[y + 1, x]
            den = a - 2 * v + c
            fy = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0
        if 0 < x < nx - 1:
            a, c = snr_map[y, x - 1], snr_map[y, x + 1]
            den = a - 2 * v + c
            fx = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0
        # Binned pixel i covers full pixels [i b, (i + 1) b): its centre is (i + 0.5) b - 0.5.
        out.append(_Candidate((x + fx + 0.5) * b - 0.5, (y + fy + 0.5) * b - 0.5, v))
    return out


@lru_cache(maxsize=8)
def _offsets(n: int) -> np.ndarray:
    g = np.arange(n, dtype=np.float64)
    g.setflags(write=False)
    return g


def _spans(gy: np.ndarray, cx: float, cy: float, radius2: float | np.ndarray, x0: int,
           w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per stamp row, the stamp columns ``[lo, hi)`` of the pixels whose centres lie within
    ``sqrt(radius2)`` of (cx, cy); ``gy`` the rows' frame coordinates, ``x0`` the stamp's
    first frame column, ``w`` its width (a row the disk misses gets ``lo == hi``).  A column
    of squared radii, shape (k, 1), gives the (k, rows) spans of k disks."""
    # (np.minimum/np.maximum rather than np.clip, whose call overhead is ~20 us: this runs
    # seven times per candidate on 160-element rows.)
    d2 = radius2 - (gy - cy) ** 2
    half_w = np.sqrt(np.maximum(d2, 0.0))
    lo = np.minimum(np.maximum(np.ceil(cx - half_w - x0), 0), w).astype(np.intp)
    hi = np.minimum(np.maximum(np.floor(cx + half_w - x0) + 1, 0), w).astype(np.intp)
    return lo, np.where(d2 >= 0, np.maximum(hi, lo), lo)


@dataclass(frozen=True)
class _DiskSums:
    """Row-wise running sums of a stamp's light and of its x moment: the sum over any disk
    is then two look-ups per row of its column span (:func:`_spans`), so each disk costs
    O(rows) rather than a pass over the stamp.  A pixel is inside a disk when its centre is
    within the radius.

    Attributes:
        sums: (rows, cols + 1) complex running sums: the light in the real part, light times
            column in the imaginary part.  One complex ``cumsum`` costs what one real one
            does (a running sum is bound by the latency of each add, and the two parts'
            adds are independent), and gives both parts to the bit.
        gy: the rows' frame coordinates; ``x0`` the stamp's first frame column, ``w`` its
            width.
    """

    sums: np.ndarray
    gy: np.ndarray
    x0: int
    w: int

    @classmethod
    def of(cls, img: np.ndarray, x0: int, y0: int) -> _DiskSums:
        h_, w_ = img.shape
        moments = np.empty((h_, w_), complex)
        moments.real = img
        np.multiply(img, _offsets(w_) + x0, out=moments.imag)
        sums = np.empty((h_, w_ + 1), complex)
        sums[:, 0] = 0.0
        np.cumsum(moments, axis=1, out=sums[:, 1:])
        return cls(sums, _offsets(h_) + y0, x0, w_)

    @property
    def cs(self) -> np.ndarray:
        """(rows, cols + 1) running sums of the light."""
        return self.sums.real

    def disk(self, xc: float, yc: float, radius2: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
        """Column spans of a disk, its light per row, in all, and its pixel count."""
        rows = np.arange(self.gy.size)
        lo, hi = _spans(self.gy, xc, yc, radius2, self.x0, self.w)
        s0 = self.cs[rows, hi] - self.cs[rows, lo]
        return lo, hi, s0, float(s0.sum()), int((hi - lo).sum())

    def disk_totals(self, xc: float, yc: float, radii2: Sequence[float]
                    ) -> tuple[np.ndarray, np.ndarray]:
        """The light and the pixel count of several disks about one centre (``radii2``:
        their squared radii), in one pass: each as :meth:`disk` gives it."""
        lo, hi = _spans(self.gy, xc, yc, np.asarray(radii2, float)[:, None], self.x0, self.w)
        rows = np.arange(self.gy.size)
        return (self.cs[rows, hi] - self.cs[rows, lo]).sum(axis=1), (hi - lo).sum(axis=1)

    def centroid(self, cx: float, cy: float, radius2: float, passes: int = 3
                 ) -> tuple[float, float]:
        """The centroid of the light within the disk, re-centred on it ``passes - 1`` times
        (left where it is if the disk holds no light)."""
        rows = np.arange(self.gy.size)
        for _ in range(passes):
            lo, hi = _spans(self.gy, cx, cy, radius2, self.x0, self.w)
            both = self.sums[rows, hi] - self.sums[rows, lo]
            s0 = both.real
            tot = float(s0.sum())
            if not tot > 0:
                break
            cx = float(both.imag.sum() / tot)
            cy = float((s0 * self.gy).sum() / tot)
        return cx, cy


def _measure(frame: np.ndarray, bg: Background, cand: _Candidate, r_out: float, r_in: float,
             cfg: DetectionConfig, stamp_px: int) -> dict:
    """Centroid, flux, S/N, peak pixel and shape fractions of one candidate (full res)."""
    ny, nx = frame.shape
    half = stamp_px // 2
    x0 = min(max(round(cand.x) - half, 0), max(nx - stamp_px, 0))
    y0 = min(max(round(cand.y) - half, 0), max(ny - stamp_px, 0))
    w_, h_ = min(stamp_px, nx), min(stamp_px, ny)
    raw = frame[y0:y0 + h_, x0:x0 + w_].astype(np.float64)
    sums = _DiskSums.of(raw - bg.level(x0, y0, w_, h_), x0, y0)
    foot2 = (r_out + cfg.spill_px) ** 2
    cx, cy = sums.centroid(cand.x, cand.y, foot2)
    lo, hi, _s, flux, npix = sums.disk(cx, cy, foot2)
    var = max(flux, 0.0) / cfg.gain_e_per_adu + npix * bg.noise ** 2
    snr = flux / np.sqrt(var) if var > 0 else 0.0
    shape = _shape_fractions(sums, cand, flux, r_in, 2.0 * half * half, foot2, bg.noise,
                             cfg.gain_e_per_adu)
    # The centroid's own noise: the flux-weighted scatter of pixel radii over sqrt(N_eff).
    cen_sig = np.sqrt(npix * bg.noise ** 2 * (r_out * r_out)
                      + max(flux, 0.0) / cfg.gain_e_per_adu * r_out * r_out) / max(flux, 1e-300)
    peak_raw = _disk_peak(raw, lo, hi) if npix else float("nan")
    return dict(x=cx, y=cy, flux=flux, snr=float(snr), peak_value=peak_raw, **shape,
                centre_offset=float(np.hypot(cx - cand.x, cy - cand.y)),
                centre_sigma=float(cen_sig))


def _disk_peak(img: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """The largest pixel of ``img`` within the column spans ``[lo, hi)`` of its rows (at
    least one row not empty): one running maximum per row's span, rather than a mask of
    the whole stamp."""
    w_ = img.shape[1]
    rows = np.flatnonzero(hi > lo)
    bounds = np.empty(2 * rows.size, np.intp)
    bounds[0::2] = rows * w_ + lo[rows]
    bounds[1::2] = rows * w_ + hi[rows]
    if bounds[-1] == img.size:
        bounds = bounds[:-1]  # the last span runs to the end, as reduceat's last one does
    # (Every other segment lies between two spans, and is not read.)
    return float(np.maximum.reduceat(img.ravel(), bounds)[0::2].max())


def _shape_fractions(sums: _DiskSums, cand: _Candidate, flux: float, r_in: float,
                     ring2: float, foot2: float, noise: float, gain: float
                     ) -> dict[str, float]:
    """The fractions of the flux in the central hole and outside the footprint (within the
    stamp's half-diagonal, ``sqrt(ring2)``), and their noise.

    They are taken around the ring centre found by the matched filter rather than the
    centroid: a companion pulls the centroid towards itself, but not the filter's peak,
    which stays on the brighter ring; its light then shows up in that ring's hole and
    outside its footprint.  Signed sums, so that sky noise averages out.  The noise is the
    sky's and the light's own Poisson noise (variance flux / gain in frame units).
    """
    pos = max(flux, 1e-300)
    totals, counts = sums.disk_totals(cand.x, cand.y, ((0.8 * r_in) ** 2, ring2, foot2))
    (hole_sum, ring_sum, foot_sum), (hole_n, ring_n, foot_n) = totals.tolist(), counts.tolist()
    # Empty if the footprint covers the whole ring disk.
    out_sum, out_n = (ring_sum - foot_sum, ring_n - foot_n) if ring_n > foot_n else (0.0, 0)
    hole_frac = hole_sum / pos if hole_n else 0.0
    out_frac = out_sum / pos if out_n else 0.0
    with np.errstate(over="ignore"):  # no flux (a peak of noise): infinite, as it should be
        hole_sig = np.sqrt(hole_n * noise ** 2 + max(hole_frac * flux, 0.0) / gain) / pos
        out_sig = np.sqrt(out_n * noise ** 2 + max(out_frac * flux, 0.0) / gain) / pos
    return dict(hole_fraction=hole_frac, outside_fraction=out_frac,
                hole_sigma=float(hole_sig), outside_sigma=float(out_sig))


def _check_frame(frame: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(frame)
    if a.ndim != 2:
        raise ImageError(f"{name} frame must be 2-D, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise ImageError(f"{name} frame must be real numbers, got dtype {a.dtype}")
    if a.dtype != np.float32 and a.dtype != np.float64:
        a = a.astype(np.float64)
    return a


def _nonfinite(frame: np.ndarray, binned: np.ndarray, b: int, name: str,
               max_fraction: float) -> np.ndarray | None:
    """The mask of the frame's NaN and Inf pixels, or None when it has none;
    NonFiniteImageError when more than ``max_fraction`` of them are.

    A block sum is finite exactly when its pixels are (NaN and Inf propagate; only pixel
    values beyond ~1e37 could overflow a sum, and those are refused as such), so the binned
    frame answers for the whole frame but the few rows and columns its trimming left out,
    at a thousandth of the cost of ``isfinite`` over 2 Mpixel.  Only a frame with some is
    looked at pixel by pixel.
    """
    ny, nx = binned.shape[0] * b, binned.shape[1] * b
    ok = (np.isfinite(binned).all() and np.isfinite(frame[ny:]).all()
          and np.isfinite(frame[:ny, nx:]).all())
    if ok:
        return None
    bad = ~np.isfinite(frame)
    n_bad = int(np.count_nonzero(bad))
    if not n_bad:
        raise ImageError(f"{name} frame has pixel values too large to sum (float64 overflow)")
    if n_bad > max_fraction * frame.size:
        raise NonFiniteImageError(
            f"{name} frame has {n_bad} non-finite pixel(s) ({n_bad / frame.size:.1%}, more "
            f"than max_nonfinite_fraction {max_fraction:g} of the frame)")
    return bad


def detect_donuts(frame: np.ndarray, *, outer_radius_px: float, inner_radius_px: float,
                  stamp_px: int, config: DetectionConfig | None = None, name: str = "frame",
                  background: Background | None = None
                  ) -> tuple[list[DetectedDonut], Background]:
    """Find the donuts of a frame and judge each one.

    Args:
        frame: 2-D frame ``[row=y, col=x]`` in the focal-plane orientation, frame units
            (electrons unless ``gain_e_per_adu`` says otherwise), sky not subtracted.
        outer_radius_px, inner_radius_px: expected donut radii (px), e.g. from
            :func:`expected_donut_radii_px`.
        stamp_px: side of the stamp the estimator gets (LSST at 1.5 mm: 160 px).
        config: detector parameters.
        name: used in messages (``"intra"``, ``"extra"``).
        background: a precomputed sky model (else estimated here).

    Returns:
        ``(donuts, background)``: every source found, brightest (matched-filter S/N) first,
        with its status; and the sky model.

    Raises:
        ImageError subclasses for a frame that is not a 2-D numeric array, or has more
        than ``max_nonfinite_fraction`` of its pixels NaN or Inf (NonFiniteImageError).
    """
    cfg = config or DetectionConfig()
    a, bg, sub, bad = _frame_and_sky(frame, cfg, name, background)
    cands = _candidates(sub, bg.noise, outer_radius_px, inner_radius_px, cfg)
    if bg.n_dead:
        # A peak centred in a dead region is the matched filter reading its edge, not a star.
        cands = [c for c in cands
                 if not bad[min(max(round(c.y), 0), bad.shape[0] - 1),
                            min(max(round(c.x), 0), bad.shape[1] - 1)]]
    half = stamp_px / 2.0
    blend_d = (cfg.blend_distance_px if cfg.blend_distance_px is not None
               else half * np.sqrt(2.0) + outer_radius_px + cfg.spill_px)
    meas = [_measure(a, bg, c, outer_radius_px, inner_radius_px, cfg, stamp_px) for c in cands]
    pos = np.array([[m["x"], m["y"]] for m in meas]).reshape(-1, 2)
    out: list[DetectedDonut] = []
    for i, (c, m) in enumerate(zip(cands, meas, strict=True)):
        d = np.hypot(*(pos - pos[i]).T)
        d[i] = np.inf
        near = float(d.min()) if d.size else float("inf")
        reasons, msgs = _judge(m, near, blend_d, a.shape, stamp_px, cfg, name)
        n_bad = _stamp_count(bad, m["x"], m["y"], stamp_px)
        if n_bad:
            reasons.insert(0, REASON_BAD_PIXELS)
            msgs.insert(0, f"its stamp holds {n_bad} non-finite or dead pixel(s) of the "
                           f"{name} frame")
        status = reasons[0] if reasons else "ok"
        out.append(DetectedDonut(m["x"], m["y"], m["flux"], m["snr"], m["peak_value"],
                                 c.detect_snr, m["hole_fraction"], m["outside_fraction"],
                                 status, tuple(reasons), msgs[0] if msgs else "", near,
                                 m["centre_offset"]))
    return out, bg


# A sky noise below this fraction of one electron's shot noise, yet not zero (a model frame
# without noise has none), is no frame in electrons: real sky and read noise are several.
_UNITS_FRACTION = 0.5


def _check_units(noise: float, floor: float, gain: float, name: str) -> None:
    """FrameUnitsError for a sky noise that is there but below ``_UNITS_FRACTION`` of one
    electron's shot noise (frame units): the noise-aware blend limits would be raised to
    one electron's and let blends through (frames x 1e-2 gave valid corners 240 nm off)."""
    if _NO_NOISE_FRACTION * floor < noise < _UNITS_FRACTION * floor:
        raise FrameUnitsError(
            f"{name} frame's sky noise is {noise:.3g} per pixel, below one electron's shot "
            f"noise at gain_e_per_adu {gain:g}: the frame is not in electrons. Set "
            "detection.gain_e_per_adu (electrons per frame unit), and saturation_level in "
            "frame units, in the selection file")


def _stamp_origin(x: float, y: float, stamp_px: int) -> tuple[int, int]:
    """The frame pixel (col, row) of the ``[0, 0]`` of the stamp centred, to the nearest
    pixel, on (x, y)."""
    return int(round(x - (stamp_px - 1) / 2.0)), int(round(y - (stamp_px - 1) / 2.0))


def _stamp_count(mask: np.ndarray | None, x: float, y: float, stamp_px: int) -> int:
    """How many of ``mask``'s pixels the stamp centred on (x, y) holds (as
    :func:`cut_stamp` cuts it; 0 for no mask)."""
    if mask is None:
        return 0
    x0, y0 = _stamp_origin(x, y, stamp_px)
    return int(np.count_nonzero(mask[max(y0, 0):max(y0 + stamp_px, 0),
                                     max(x0, 0):max(x0 + stamp_px, 0)]))


def _frame_and_sky(frame: np.ndarray, cfg: DetectionConfig, name: str,
                   background: Background | None
                   ) -> tuple[np.ndarray, Background, np.ndarray, np.ndarray | None]:
    """(frame, sky model, binned sky-subtracted frame, mask of the pixels set aside or None)
    of a checked frame: its NaN, Inf and dead pixels are set to its median
    (:func:`_set_aside`), and counted on the sky model.

    The pixel noise is taken as at least one electron's shot noise: a sky without noise (a
    simulation with neither sky nor read noise) would otherwise make the filter's float
    rounding sources by the dozen, and blend every real donut with them.  Real sky and read
    noise are several electrons.
    """
    a = _check_frame(frame, name)
    if min(a.shape) < 4 * cfg.bin_px:
        raise ImageError(f"{name} frame {a.shape[1]}x{a.shape[0]} px is too small")
    b = cfg.bin_px
    a, binned, bad, dead = _set_aside(a, _binned(a, b), cfg, name)
    aside = _union(bad, dead)
    # The noise from the blocks that hold no pixel set aside: the filled ones have none.
    live = None if aside is None else _binned(aside.astype(np.float32), b) == 0
    if background is None:
        bg, sub = _background_from_binned(binned, b, cfg.mesh_px, live)
    else:
        bg, sub = background, binned - _sky_binned(background, binned.shape, b)
    floor = 1.0 / cfg.gain_e_per_adu
    if not bg.noise >= floor:
        _check_units(bg.noise, floor, cfg.gain_e_per_adu, name)
        bg = replace(bg, noise=floor, measured_noise=float(bg.noise))
    bg = replace(bg, n_nonfinite=0 if bad is None else int(bad.sum()),
                 n_dead=0 if dead is None else int(dead.sum()))
    return a, bg, sub, aside


def _set_aside(a: np.ndarray, binned: np.ndarray, cfg: DetectionConfig, name: str
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(frame, its binned sums, NaN/Inf mask, dead mask): the NaN and Inf pixels (up to
    ``max_nonfinite_fraction``), then the dead ones, set to the median of the others; a
    frame of one value is refused, as it holds no data."""
    b = cfg.bin_px
    bad = _nonfinite(a, binned, b, name, cfg.max_nonfinite_fraction)
    if bad is not None:
        a = np.where(bad, np.median(a[~bad]), a)
        binned = _binned(a, b)
    if binned.min() == binned.max() and (a == a.flat[0]).all():
        raise FlatImageError(f"{name} frame is constant ({float(a.flat[0]):g}"
                             f"{', where finite' if bad is not None else ''}): no data")
    dead = _union(_dead_blocks(a, binned, b, cfg.saturation_level, exclude=bad),
                  _dead_lines(a, binned, b))
    if dead is not None:
        a = np.where(dead, np.median(a[~dead]), a)
        binned = _binned(a, b)
    return a, binned, bad, dead


# A constant block is dead when its value lies this many robust sigmas of the frame's
# other blocks from their median: a dead amplifier at 0 or a hot one at full scale does, the
# sky of a model frame without noise (every block without a donut) does not.
_DEAD_NSIGMA = 5.0


def _dead_blocks(a: np.ndarray, binned: np.ndarray, b: int, saturation: float | None,
                 exclude: np.ndarray | None = None) -> np.ndarray | None:
    """Full-resolution mask of the frame's dead pixels, or None when it has none.

    A dead block is a ``b`` x ``b`` block whose pixels all hold one value that a neighbouring
    block shares (a dead or unread amplifier, a zero-padded border: sky noise never leaves a
    block constant), and which stands out from the frame's other blocks (:data:`_DEAD_NSIGMA`):
    the constant sky of a model frame without noise, where the donuts are the only
    non-constant blocks, does not.  Equal neighbour sums are the cheap first test (by chance
    they happen for integer counts too, so the blocks are then checked pixel by pixel).
    Constant blocks at or above the saturation level are a saturated star's core, left to
    its own rejection; ``exclude`` (pixels already set aside) marks no block dead.  The
    pixels of the neighbouring blocks that hold the dead value are dead too: a dead region's
    edge seldom falls on the block grid.  Without this, its edge is a step the matched
    filter takes for dozens of blended sources.
    """
    eq_r = binned[:, 1:] == binned[:, :-1]
    eq_c = binned[1:, :] == binned[:-1, :]
    cand = np.zeros(binned.shape, bool)
    cand[:, 1:] |= eq_r
    cand[:, :-1] |= eq_r
    cand[1:] |= eq_c
    cand[:-1] |= eq_c
    iy, ix = np.nonzero(cand)
    if b > 1 and iy.size:
        # A block whose first two pixels differ is not constant: on integer counts, where
        # equal sums are common, nearly every candidate ends here, before its b * b pixels
        # are gathered.
        first_two = a[iy * b, ix * b] == a[iy * b, ix * b + 1]
        iy, ix = iy[first_two], ix[first_two]
    if not iy.size:
        return None
    rows = (iy[:, None] * b + np.arange(b))[:, :, None]
    cols = (ix[:, None] * b + np.arange(b))[:, None, :]
    blocks = a[rows, cols]
    first = blocks[:, 0, 0]
    const = (blocks == first[:, None, None]).all(axis=(1, 2))
    if exclude is not None:
        const &= ~exclude[rows, cols].any(axis=(1, 2))
    if saturation is not None:
        const &= first < saturation
    if not const.any():
        return None
    live = np.ones(binned.shape, bool)
    live[iy[const], ix[const]] = False
    others = binned[live]
    if others.size < 16:
        return None
    q1, med, q3 = np.percentile(others, [25, 50, 75])
    sigma = (q3 - q1) / 1.349
    keep = np.abs(first[const] * b * b - med) > _DEAD_NSIGMA * sigma
    if not keep.any():
        return None
    values = np.full(binned.shape, np.nan)
    values[iy[const][keep], ix[const][keep]] = first[const][keep]
    return _dead_pixels(a, values, b)


def _union(*masks: np.ndarray | None) -> np.ndarray | None:
    have = [m for m in masks if m is not None]
    return None if not have else have[0] if len(have) == 1 else np.logical_or.reduce(have)


def _dead_lines(a: np.ndarray, binned: np.ndarray, b: int, samples: int = 16
                ) -> np.ndarray | None:
    """Mask of whole dead columns and rows (a bad column of a CCD: one value from end to
    end, not the sky level), or None.
    Narrower than a block, they escape :func:`_dead_blocks`, and their edges read as
    sources.  Found on ``samples`` rows (columns) first, then checked whole."""
    mask, sky = None, None
    for axis in (0, 1):  # columns (constant along axis 0), then rows
        n = a.shape[axis]
        pick = np.linspace(0, n - 1, min(samples, n)).astype(int)
        sample = np.take(a, pick, axis=axis)
        first = np.take(sample, [0], axis=axis)
        cand = np.flatnonzero((sample == first).all(axis=axis))
        if not cand.size:
            continue
        if sky is None:
            q1, med, q3 = np.percentile(binned, [25, 50, 75])
            sky, sigma = med / (b * b), (q3 - q1) / 1.349 / b  # per full-resolution pixel
        lines = np.take(a, cand, axis=1 - axis)
        vals = np.take(lines, 0, axis=axis)
        whole = (lines == np.expand_dims(vals, axis)).all(axis=axis)
        # A whole line of one value is no sky unless it is the sky level itself (a model
        # frame without noise): the test is against the sky estimate's own precision.
        n_line = a.shape[axis]
        out = np.abs(vals - sky) > max(_DEAD_NSIGMA * sigma / np.sqrt(n_line),
                                       1e-9 * max(abs(sky), 1.0))
        dead = cand[whole & out]
        if dead.size:
            mask = np.zeros(a.shape, bool) if mask is None else mask
            if axis == 0:
                mask[:, dead] = True
            else:
                mask[dead, :] = True
    return mask


def _dead_pixels(a: np.ndarray, values: np.ndarray, b: int) -> np.ndarray:
    """Full-resolution mask: the dead blocks (their value in ``values``, NaN elsewhere), and
    the pixels of the blocks around them, trimmed rows and columns included, that hold the
    value of a dead neighbour."""
    ny, nx = a.shape
    full = np.full(a.shape, np.nan)
    full[:values.shape[0] * b, :values.shape[1] * b] = np.repeat(
        np.repeat(values, b, axis=0), b, axis=1)
    mask = ~np.isnan(full)
    spread = full.copy()
    for dy in (-b, 0, b):
        for dx in (-b, 0, b):
            if not (dy or dx):
                continue
            src = full[max(-dy, 0):ny - max(dy, 0), max(-dx, 0):nx - max(dx, 0)]
            dst = spread[max(dy, 0):ny - max(-dy, 0), max(dx, 0):nx - max(-dx, 0)]
            np.copyto(dst, src, where=np.isnan(dst) & ~np.isnan(src))
    # The trimmed rows and columns take the value of the block beside them.
    nyb, nxb = values.shape[0] * b, values.shape[1] * b
    spread[:, nxb:] = np.where(np.isnan(spread[:, nxb:]), spread[:, nxb - 1:nxb],
                               spread[:, nxb:])
    spread[nyb:, :] = np.where(np.isnan(spread[nyb:, :]), spread[nyb - 1:nyb, :],
                               spread[nyb:, :])
    return mask | (a == spread)


def _candidates(sub: np.ndarray, noise: float, outer_radius_px: float,
                inner_radius_px: float, cfg: DetectionConfig) -> list[_Candidate]:
    """The matched filter's peaks on the binned sky-subtracted frame (:func:`_find_peaks`),
    brightest first; a side-lobe peak is kept only if the brighter donut's light does not
    explain it (:func:`_explained_snr`)."""
    b = cfg.bin_px
    support = (outer_radius_px + cfg.spill_px) / b + 1.0
    key = (round(outer_radius_px / b, 3), round(inner_radius_px / b, 3), round(support, 3))
    tmpl, sidelobe = _template(*key)
    resp = _correlate(sub, key)
    noise_b = noise * b  # binned-pixel sky noise
    snr_map = resp / max(noise_b, 1e-12)
    foot_b = (outer_radius_px + cfg.spill_px) / b
    explained = partial(_explained_snr, sub, tmpl, foot_b, noise_b)
    return _find_peaks(snr_map, cfg.detect_snr, 0.5 * outer_radius_px / b, sidelobe,
                       cfg.sidelobe_margin, 2.0 * foot_b, cfg.max_candidates, b,
                       explained, cfg.unexplained_fraction)


def _explained_snr(sub: np.ndarray, tmpl: np.ndarray, foot_b: float, noise_b: float,
                   strong: tuple[int, int], weak: tuple[int, int]) -> float:
    """S/N at ``weak`` of the light within the footprint (radius ``foot_b``) of the donut at
    ``strong`` (binned px): the filter's response to that donut alone."""
    # The template's window on the map, cut at the map's edges (slices, not index arrays:
    # this runs for every side-lobe candidate, ~25 times a frame).
    c = tmpl.shape[0] // 2
    y0, y1 = max(weak[0] - c, 0), min(weak[0] + c + 1, sub.shape[0])
    x0, x1 = max(weak[1] - c, 0), min(weak[1] + c + 1, sub.shape[1])
    dy2 = (np.arange(y0, y1) - strong[0]) ** 2
    dx2 = (np.arange(x0, x1) - strong[1]) ** 2
    inside = dy2[:, None] + dx2[None, :] <= foot_b * foot_b
    window = tmpl[y0 - weak[0] + c:y1 - weak[0] + c, x0 - weak[1] + c:x1 - weak[1] + c]
    light = sub[y0:y1, x0:x1] * window
    return float(light[inside].sum() / max(noise_b, 1e-12))


def _judge(m: dict, near: float, blend_d: float, shape: tuple[int, int], stamp_px: int,
           cfg: DetectionConfig, name: str) -> tuple[list[str], list[str]]:
    """(reasons, messages) for rejecting a measured donut, in order of precedence: its stamp
    cut by the frame edge, a saturated pixel, a blend (a neighbour within ``blend_d``, or
    shape numbers beyond their noise-aware limits), too faint.  Empty if it is usable."""
    ny, nx = shape
    at = f"{name} donut at (col {m['x']:.0f}, row {m['y']:.0f})"
    reasons: list[str] = []
    msgs: list[str] = []
    # Edge: the stamp centred on the donut (as cut_stamp cuts it) must lie in the frame.
    x0, y0 = _stamp_origin(m["x"], m["y"], stamp_px)
    if x0 < 0 or y0 < 0 or x0 + stamp_px > nx or y0 + stamp_px > ny:
        reasons.append(REASON_EDGE)
        msgs.append(f"{at}: its {stamp_px} px stamp extends beyond the {nx}x{ny} frame")
    if cfg.saturation_level is not None and m["peak_value"] >= cfg.saturation_level:
        reasons.append(REASON_SATURATED)
        msgs.append(f"{at} has a pixel of {m['peak_value']:.6g} >= saturation level "
                    f"{cfg.saturation_level:.6g}")
    k = cfg.shape_nsigma
    lim_hole = cfg.max_hole_fraction + k * m["hole_sigma"]
    lim_out = cfg.max_outside_fraction + k * m["outside_sigma"]
    lim_cen = cfg.max_centre_offset_px + k * m["centre_sigma"]
    why = ""
    if near < blend_d:
        why = f"another source {near:.0f} px away (< {blend_d:.0f} px)"
    elif m["centre_offset"] > lim_cen:
        why = (f"its flux centroid is {m['centre_offset']:.1f} px from its ring's centre "
               f"(limit {lim_cen:.1f} px): light from an overlapping donut, or a donut "
               f"too aberrated for the expected ring (no other source within "
               f"{min(near, 9999):.0f} px)")
    elif m["hole_fraction"] > lim_hole or m["outside_fraction"] > lim_out:
        why = (f"{m['hole_fraction']:.1%} of its flux in the central hole and "
               f"{m['outside_fraction']:.1%} outside the footprint (limits "
               f"{lim_hole:.1%}, {lim_out:.1%}; no other source within "
               f"{min(near, 9999):.0f} px: an unseen companion, or a donut too aberrated "
               "for the expected ring)")
    if why:
        reasons.append(REASON_BLENDED)
        msgs.append(f"{at} is blended: {why}")
    if not m["snr"] >= cfg.min_snr:
        reasons.append(REASON_FAINT)
        msgs.append(f"{at} is too faint: S/N {m['snr']:.1f} < {cfg.min_snr:g}")
    return reasons, msgs


def cut_stamp(frame: np.ndarray, x: float, y: float, stamp_px: int,
              background: Background | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """Cut a ``stamp_px`` square stamp centred (to the nearest pixel) on (x, y).

    Args:
        frame: the frame, focal-plane orientation.
        x, y: centre (col, row), pixel-centre convention.
        stamp_px: stamp side.
        background: if given, its sky is subtracted from the stamp.

    Returns:
        ``(stamp, (x0, y0))``: float64 stamp and the frame pixel of its ``[0, 0]``.

    Raises:
        DonutCutError if the stamp does not fit in the frame.
    """
    ny, nx = frame.shape
    x0, y0 = _stamp_origin(x, y, stamp_px)
    if x0 < 0 or y0 < 0 or x0 + stamp_px > nx or y0 + stamp_px > ny:
        raise DonutCutError(f"stamp of {stamp_px} px at (col {x:.1f}, row {y:.1f}) extends "
                            f"beyond the {nx}x{ny} frame")
    st = np.asarray(frame[y0:y0 + stamp_px, x0:x0 + stamp_px], dtype=np.float64)
    if background is not None:
        st = st - background.level(x0, y0, stamp_px, stamp_px)
    return st, (x0, y0)


__all__ += ["REASON_EDGE", "REASON_SATURATED", "REASON_BLENDED", "REASON_FAINT"]
