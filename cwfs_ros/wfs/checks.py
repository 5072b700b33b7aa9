"""Input checks that need more than one stamp's statistics: saturation, swapped intra/extra.

Both guard the estimator against input that looks like a donut pair but would give a wrong
wavefront without any other sign of trouble (issue: "bad input gets a clear error, and
nothing downstream acts on it").

Saturation (:func:`check_saturation`)
    A pixel at or above the instrument's ``saturation_level`` (configured, in the stamp's
    units) inside the donut rejects the stamp.  Without a level, a *plateau* does: a
    saturated or clipped donut has many pixels at exactly its maximum, while a genuine
    donut's brightest pixels are spread by photon noise (an integer image holds a few
    pixels at its maximum, a float image one).  The plateau must also stand out from the
    quantisation of the data: more pixels at the maximum than at the next value below it,
    which a Poisson tail, whose counts fall towards the maximum, hardly ever shows.  Images
    without any noise (the background exactly constant and a donut without pixel noise: a
    synthetic or noise-free model image, whose flat top may be real) are judged by the
    configured level only; a donut on a background of exactly zero but with photon noise
    in its light (second differences of its pixels as large as first ones) gets the plateau
    test.
    Measured (``bench/bench_input_checks.py``): 0 of 2880 genuine corner donuts (1e4-1e7
    photons, sky 0-50 e-/px, float and raw uint16) and 0 of the 12 ZEMAX/FAM test images
    rejected; clipped at any percentile from 50 to 99.5 (float64, float32, integer) 100%
    rejected; a uint16 full well (65535) 100% with the level given, and without it 100% when
    the unclipped peak would be 1.5x the full well or more, 20% at 1.05x (a few pixels).

Swapped intra/extra (:func:`check_not_swapped`)
    Off axis the pupil is vignetted, and the vignetted part of the donut lies on opposite
    sides of the intra- and extra-focal images (the image inverts through focus).  Each
    stamp is cross-correlated with the model's predicted image-plane footprint of both
    sides (:func:`pair_footprints`: the transmitted pupil points of a uniform pupil grid
    pushed through each image's unperturbed mapping, which holds the vignetting and the
    design aberrations).  The pair is rejected when the exchanged assignment matches
    clearly (``swap_threshold``) and significantly (``swap_min_significance``, against the
    pixel noise) better than the given one, unless the vignetted part alone (the own
    footprint against the same one with the mask turned by 180 degrees) favours the given
    order (``swap_vignetting_veto``).  On axis nothing is vignetted and the check abstains;
    for LSST it applies from a field radius of about 1.3 deg (vignetting contrast >= 0.01;
    the corner sensors, at 1.7 deg, have 0.02).  Measured at the four corners (rigid-body
    perturbations of 200-900 nm, +-3 px offsets, sky 10-50 e-/px): no correct pair of
    ~750 rejected; exchanged pairs rejected 87% at 1e4 photons, 94-100% at 3e4, 100% from
    1e5.  A pair whose stamps are both turned by 180 degrees looks exchanged too.

One stamp turned or mirrored (:func:`check_orientation`)
    The same footprints tell a stamp that arrives turned by a quarter turn or mirrored (a
    camera's readout orientation set wrong for one half): the vignetted lune then points
    the wrong way.  Each stamp is correlated with its own footprint as given and under each
    of the seven other orientations of the square (:data:`WRONG_ORIENTATIONS`); the stamp is
    rejected when one of them matches clearly (``orientation_threshold``) and significantly
    (``orientation_min_significance``) better than the given one.  An orientation under
    which the footprint is (nearly) symmetric, contrast below
    ``orientation_min_contrast`` (a corner's lune is symmetric about its radial direction,
    so the mirror about the corner's diagonal cannot be told), is not tested.  It runs with
    the swap check, on the footprints that check builds (0.6 ms an estimate).  Measured
    (``bench/bench_input_checks.py orientation``, rigid-body perturbations of 200-900 nm at
    the corners, +-3 px offsets, sky 10-50 e-/px): no correct corner pair of 328 rejected,
    nor any of the 25 FAM pairs; quarter turns and mirrors 98-100% detected from 1e5
    photons, 70-75% at 3e4 with sky 50; a corner's diagonal mirror only where it is not the
    lune's symmetry.  With 1-4 um at the corners the aberrations reshape the donut as much
    as the lune does: 2 of 249 correct pairs rejected, 30-60% of the turned ones.  A field
    in another direction than the star's makes the lune point the wrong way too, and is
    refused the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy.ndimage import gaussian_filter

from cwfs_ros.errors import (
    ConfigError,
    MisorientedImageError,
    SaturatedImageError,
    SwappedImagesError,
)
from cwfs_ros.wfs.orientation import Orientation, orient_image

__all__ = ["CheckConfig", "PairFootprints", "SwapScore", "OrientationScore", "StampWindows",
           "WRONG_ORIENTATIONS", "check_saturation", "check_not_swapped",
           "check_orientation", "orientation_score", "pair_footprints", "stamp_windows",
           "swap_score"]


@dataclass(frozen=True)
class CheckConfig:
    """Parameters of the input checks (``input_checks`` in ``config/algorithm.yaml``).

    Attributes:
        plateau_check: detect saturation without a configured level (see module docstring).
        plateau_min_pixels: fewest pixels at the maximum that can make a plateau.
        plateau_min_fraction: ... and at least this fraction of the donut's bright pixels.
        saturated_pixels_allowed: donut pixels at or above a configured saturation level
            that are tolerated (0: any such pixel rejects the stamp).
        swap_check: detect an exchanged intra/extra pair from the vignetting (off axis).
        swap_min_contrast: the check abstains unless each stamp's footprint differs from
            the same one with its vignetting turned by 180 degrees by at least this much
            (1 - their normalised correlation; 0.019-0.022 at the LSST corner sensors,
            0.012 at 1.4 deg, 0 on axis).
        swap_threshold: reject when the footprint preference for the given assignment
            (:class:`SwapScore`: +1 given, -1 exchanged) is below ``-swap_threshold`` ...
        swap_min_significance: ... and that preference is this many standard deviations
            of its photon/read noise from zero ...
        swap_vignetting_veto: ... and the vignetted part alone (same mapping, mask turned)
            does not favour the given order by this much or more: a veto against anything
            but the vignetting (e.g. a large aberration) making the footprints disagree.
            It separates less cleanly than the full footprints at the split corner sensors
            (the two halves' fields, hence lunes, differ): measured +0.15..+1.2 for correct
            pairs and -0.78..+0.06 for exchanged ones from 1e5 photons (the footprint
            preference: +0.57..+1.19 and its mirror).
        orientation_check: detect one stamp turned or mirrored, from its footprint (off
            axis; runs with the swap check and is skipped with it).
        orientation_min_contrast: an orientation is tested only where the footprint differs
            from itself under it by at least this much (1 - normalised correlation).
        orientation_threshold: reject when a wrong orientation's preference (+1: the stamp
            is that way round, -1: as given) is above this ...
        orientation_min_significance: ... at this many standard deviations of the noise.
    """

    plateau_check: bool = True
    plateau_min_pixels: int = 10
    plateau_min_fraction: float = 0.002
    saturated_pixels_allowed: int = 0
    swap_check: bool = True
    swap_min_contrast: float = 0.01
    swap_threshold: float = 0.5
    swap_min_significance: float = 5.0
    swap_vignetting_veto: float = 0.25
    orientation_check: bool = True
    orientation_min_contrast: float = 0.01
    orientation_threshold: float = 0.6
    orientation_min_significance: float = 5.0

    def __post_init__(self) -> None:
        problems = []
        for name in ("plateau_check", "swap_check", "orientation_check"):
            if not isinstance(getattr(self, name), bool):
                problems.append(f"{name} must be true or false, got {getattr(self, name)!r}")
        for name in ("plateau_min_pixels", "saturated_pixels_allowed"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                problems.append(f"{name} must be an integer >= 0, got {v!r}")
        for name, lo, hi in (("plateau_min_fraction", 0.0, 1.0),
                             ("swap_min_contrast", 0.0, 1.0), ("swap_threshold", 0.0, 1.0),
                             ("orientation_min_contrast", 0.0, 1.0),
                             ("orientation_threshold", 0.0, 1.0)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not lo <= v <= hi:
                problems.append(f"{name} must be a number in [{lo:g}, {hi:g}], got {v!r}")
        for name in ("swap_min_significance", "swap_vignetting_veto",
                     "orientation_min_significance"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= 0:
                problems.append(f"{name} must be a number >= 0, got {v!r}")
        if problems:
            raise ConfigError("input_checks: " + "; ".join(problems))

    @classmethod
    def from_mapping(cls, data: Any, **overrides: Any) -> CheckConfig:
        """From the ``input_checks`` mapping of the algorithm file, with keyword overrides."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"input_checks must be a mapping, got {type(data).__name__}")
        params = dict(data)
        params.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls(**params)
        except TypeError as exc:
            raise ConfigError(f"input_checks: {exc}") from exc


# -- saturation ---------------------------------------------------------------------------

def check_saturation(image: np.ndarray, *, name: str, background: float, noise_present: bool,
                     donut: np.ndarray, body_pixels: int, level: float | None,
                     config: CheckConfig) -> None:
    """Raise :class:`SaturatedImageError` if the stamp is saturated or clipped.

    Args:
        image: the stamp as given (float64, input units, background not subtracted).
        name: ``"intra"`` or ``"extra"`` (for the message).
        background: background level per pixel (input units).
        noise_present: the background pixels are not all identical (the image has noise).
        donut: boolean mask of the pixels within the donut's radius.
        body_pixels: number of the donut's bright pixels (its illuminated area, px).
        level: saturation level in input units, or None when unknown.
        config: thresholds.
    """
    if level is not None:
        n_sat = int(np.count_nonzero(image[donut] >= level))
        if n_sat > config.saturated_pixels_allowed:
            raise SaturatedImageError(
                f"{name} donut is saturated: {n_sat} pixel(s) at or above the saturation "
                f"level {level:.6g} (maximum {float(image.max()):.6g})")
    if not config.plateau_check:
        return
    top = float(image.max())
    if not top > background:
        return  # nothing above the background: the flat-image checks name that
    # "Exactly at the maximum" up to float32 rounding (a clipped float64 image sent as
    # 32FC1), far finer than any photon noise or integer quantum. Relative to the image's
    # own scale only: an absolute floor would put every pixel of a tiny-valued image "at
    # the maximum".
    tol = 4.0 * float(np.finfo(np.float32).eps) * max(abs(top), abs(background))
    at_top = image >= top - tol
    if not (noise_present or _donut_noisy(image, donut & ~at_top, background)):
        return
    n_top = int(np.count_nonzero(at_top))
    if n_top < max(config.plateau_min_pixels, config.plateau_min_fraction * body_pixels):
        return
    rest = image[~at_top]
    if rest.size:
        below = float(rest.max())
        n_below = int(np.count_nonzero(rest >= below - tol))
        # A Poisson tail holds fewer pixels at its maximum than one quantum below it; a
        # plateau holds more (its neighbours below are the few pixels of its rim).
        if n_top <= n_below:
            return
    raise SaturatedImageError(
        f"{name} donut is saturated or clipped: {n_top} pixels ({n_top / image.size:.1%} of "
        f"the stamp) sit at exactly its maximum, level {top:.6g} (background "
        f"{background:.4g}); a genuine donut's brightest pixels differ by photon noise. Set "
        "the instrument's saturation_level if that is the detector's full well")


# Photon noise makes a pixel's second difference about as large as its first difference
# (ratio sqrt(3/4) for white noise); a smooth noise-free model image has second differences
# far below its first ones (the ratio ~ 1/(surface brightness scale length in px)).
_NOISY_RATIO = 0.5
_NOISY_MIN_TRIPLES = 50


def _donut_noisy(image: np.ndarray, mask: np.ndarray, background: float) -> bool:
    """Whether the lit pixels of ``mask`` (above ``background``) show pixel noise.

    A clipped donut on a background of exactly zero has no noise in its background, but
    photon noise on its rim and body: judged here, so that it gets the plateau test.
    """
    lit = mask & (image > background)
    trip = lit[:, :-2] & lit[:, 1:-1] & lit[:, 2:]
    if int(np.count_nonzero(trip)) < _NOISY_MIN_TRIPLES:
        return False
    x0, x1, x2 = image[:, :-2][trip], image[:, 1:-1][trip], image[:, 2:][trip]
    d1 = float(np.median(np.abs(x1 - x0)))
    d2 = float(np.median(np.abs(x1 - 0.5 * (x0 + x2))))
    return d1 > 0 and d2 > _NOISY_RATIO * d1


# -- swapped intra/extra -------------------------------------------------------------------

@dataclass(frozen=True)
class PairFootprints:
    """The model's image-plane footprints of a pair, for the swap check.

    Per stamp (intra, extra), on its own mapping: ``own``, the pupil its field transmits,
    and ``alt``, that mask turned by 180 degrees in the pupil, which is where the *other*
    image's vignetted part appears when read with this image's mapping (the image inverts
    through focus).  ``own`` and ``alt`` differ only by the vignetted lunes.  The other
    stamp's ``own`` is this stamp's full alternative: it also differs by the design
    aberrations of the two sides (astigmatism elongates them at right angles).

    Attributes:
        size: side of the square correlation window (px); every footprint's flux centroid
            sits at its centre pixel ``size // 2``.
        spectra: (2, 2, size, size // 2 + 1) conjugate FFTs of the zero-mean, unit-norm
            footprints, ``[stamp (intra, extra), (own, alt)]``.
        diff_sq: (2, 2) squared norms of ``own - alt`` ([:, 0]) and of ``own - other own``
            ([:, 1]) per stamp, unit footprints at their own centroids: the weight of pixel
            noise in the two preferences (:func:`swap_score`).
        contrast: (2, 2) ``1 - max correlation`` of the same pairs: how much the two
            assignments can differ (0 on axis).
        max_shift_px: largest shift of an image against a footprint that is searched.
        shift_rows, shift_cols: factors of the inverse DFT at those shifts (see
            :func:`_shift_bases`).
        orient_spectra: (2, 7, size, size // 2 + 1) conjugate FFTs of each own footprint
            turned back from each of :data:`WRONG_ORIENTATIONS` (its inverse applied): a
            stamp correlates with one as it would, turned that way, with the footprint.
        orient_contrast: (2, 7) ``1 - max correlation`` of each own footprint with itself
            under each wrong orientation (0: symmetric under it).
        orient_diff_sq: (2, 7) squared norms of those differences (noise weights).
    """

    size: int
    spectra: np.ndarray
    diff_sq: np.ndarray
    contrast: np.ndarray
    max_shift_px: int
    shift_rows: np.ndarray
    shift_cols: np.ndarray
    orient_spectra: np.ndarray
    orient_contrast: np.ndarray
    orient_diff_sq: np.ndarray

    @property
    def shift_rows_32(self) -> np.ndarray:
        return self._shift_32[0]

    @property
    def shift_cols_32(self) -> np.ndarray:
        return self._shift_32[1]

    @cached_property
    def _shift_32(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.shift_rows.astype(np.complex64), self.shift_cols.astype(np.complex64))


def _splat(x: np.ndarray, y: np.ndarray, size: int) -> np.ndarray:
    """Bilinear histogram of unit weights at (x, y) (pixel-centre coordinates)."""
    i0 = np.floor(x).astype(np.int64)
    j0 = np.floor(y).astype(np.int64)
    fx, fy = x - i0, y - j0
    # The four corners of every point in one histogram.
    ii = np.concatenate((i0, i0 + 1, i0, i0 + 1))
    jj = np.concatenate((j0, j0, j0 + 1, j0 + 1))
    w = np.concatenate(((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy))
    ok = (ii >= 0) & (ii < size) & (jj >= 0) & (jj < size)
    return np.bincount(jj[ok] * size + ii[ok], weights=w[ok],
                       minlength=size * size).reshape(size, size)


def _unit(a: np.ndarray) -> np.ndarray:
    a = a - a.mean()
    n = float(np.linalg.norm(a))
    return a / n if n > 0 else a


def _shift_bases(size: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-DFT factors giving a circular correlation at shifts -k..k only.

    The alignment searches a few pixels, so the inverse transform is evaluated there alone
    (two small matrix products instead of a full ``irfft2``): rows by ``rows @ P``, then
    the Hermitian half-spectrum columns by ``Re(. @ cols)``.
    """
    shifts = np.arange(-k, k + 1)
    m = np.arange(size)
    rows = np.exp(2j * np.pi * np.outer(shifts, m) / size) / size
    half = np.arange(size // 2 + 1)
    weight = np.full(half.size, 2.0)
    weight[0] = 1.0
    if size % 2 == 0:
        weight[-1] = 1.0
    cols = weight[:, None] * np.exp(2j * np.pi * np.outer(half, shifts) / size) / size
    return rows, cols


def _peak(spectra: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Largest circular correlation within the searched shifts, from product spectra."""
    cc = ((rows @ spectra) @ cols).real
    return cc.max(axis=(-2, -1))


Points = tuple[np.ndarray, np.ndarray]


def pair_footprints(points: tuple[tuple[Points, Points], tuple[Points, Points]],
                    outer_radius_px: float, sigma_px: float = 1.5,
                    max_shift_px: int = 4) -> PairFootprints:
    """Predicted footprints of the intra and extra images (cheap; cached with the geometry).

    Args:
        points: ``((own, alt) intra, (own, alt) extra)``, each ``(x, y)``: image positions
            (px) of pupil points of a uniform pupil grid pushed through the image's
            unperturbed mapping (their density is the predicted surface brightness); ``own``
            the points its field transmits, ``alt`` the same mask turned by 180 degrees.
        outer_radius_px: radius around the flux centroid that holds the donut (px).
        sigma_px: Gaussian blur of the footprints (px): the pupil sampling is about one
            point per pixel, and real edges are blurred by seeing and aberrations.
        max_shift_px: search range of the alignment (px) around the flux centroids.
    """
    size = sfft.next_fast_len(2 * int(np.ceil(outer_radius_px + 3 * sigma_px + max_shift_px))
                              + 1, real=True)
    c = size // 2
    # Single precision: the footprints are models blurred by 1.5 px, compared with noisy
    # stamps; float32 transforms cost half as much, once per geometry.
    units = np.zeros((2, 2, size, size), np.float32)
    for s, pair in enumerate(points):
        for h, (x, y) in enumerate(pair):
            x = np.asarray(x, float)
            y = np.asarray(y, float)
            img = _splat(x - x.mean() + c, y - y.mean() + c, size)
            units[s, h] = _unit(gaussian_filter(img, sigma_px))
    spectra = np.conj(sfft.rfft2(units))
    rows, cols = _shift_bases(size, max_shift_px)
    bases_32 = (rows.astype(np.complex64), cols.astype(np.complex64))
    diff_sq = np.zeros((2, 2))
    contrast = np.zeros((2, 2))
    for s in range(2):
        for j, (t, h) in enumerate(((s, 1), (1 - s, 0))):
            diff_sq[s, j] = float(np.sum((units[s, 0] - units[t, h]) ** 2))
            prod = np.conj(spectra[s, 0]) * spectra[t, h]
            contrast[s, j] = 1.0 - float(_peak(prod, *bases_32))
    o_spectra, o_contrast, o_diff_sq = _turned_back(units[:, 0], spectra[:, 0], *bases_32)
    return PairFootprints(size, spectra, diff_sq, contrast, max_shift_px, rows, cols,
                          o_spectra, o_contrast, o_diff_sq)


def _inverse(o: Orientation) -> Orientation:
    """The orientation that undoes ``o`` (a mirror undoes itself)."""
    return o if o.flip == "lr" else Orientation(-o.rot90)


def _turned_back(units: np.ndarray, spectra: np.ndarray, rows: np.ndarray, cols: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each own footprint (``units[s]``, conjugate spectrum ``spectra[s]``) turned back from
    each wrong orientation: conjugate spectra (2, 7, ...), contrasts and squared
    differences against the footprint (2, 7).  Turning the footprint back instead of the
    stamp forward gives the same correlation (both are isometries of the window about its
    centre; an even window's half-pixel offset is within the searched shifts), once per
    geometry instead of at every estimate.

    Every turn is the footprint or its transpose with some axes reversed, whose spectrum is
    that one's with its frequencies reversed (:func:`_reversed_spectrum`): one transform of
    the transpose serves all seven."""
    n_o = len(WRONG_ORIENTATIONS)
    size = units.shape[-1]
    out = np.zeros((2, n_o, *spectra.shape[1:]), dtype=spectra.dtype)
    contrast = np.zeros((2, n_o))
    diff_sq = np.zeros_like(contrast)
    turns = [_as_reversals(_inverse(o), size) for o in WRONG_ORIENTATIONS]
    for s in range(2):
        plain = (np.conj(spectra[s]), sfft.rfft2(units[s].T))
        for k, (transposed, axes) in enumerate(turns):
            out[s, k] = np.conj(_reversed_spectrum(plain[transposed], axes))
            back = (units[s].T if transposed else units[s])[_reversal(axes[0]),
                                                             _reversal(axes[1])]
            diff_sq[s, k] = np.sum((back - units[s]) ** 2)
        contrast[s] = 1.0 - _peak(out[s] * np.conj(spectra[s]), rows, cols)
    return out, contrast, diff_sq


def _reversal(reverse: bool) -> slice:
    return slice(None, None, -1 if reverse else 1)


@lru_cache(maxsize=64)
def _as_reversals(o: Orientation, size: int) -> tuple[int, tuple[bool, bool]]:
    """``(transposed, (reverse rows, reverse columns))`` such that ``orient_image(a, o)`` of
    a square ``a`` is ``a`` (or ``a.T`` when transposed) with those axes reversed."""
    probe = np.arange(size * size).reshape(size, size)
    turned = orient_image(probe, o)
    for transposed, base in enumerate((probe, probe.T)):
        for axes in ((False, False), (True, False), (False, True), (True, True)):
            flipped = base[_reversal(axes[0]), _reversal(axes[1])]
            if np.array_equal(flipped, turned):
                return transposed, axes
    raise AssertionError(f"{o} is not a symmetry of the square")


def _reversed_spectrum(spec: np.ndarray, axes: tuple[bool, bool]) -> np.ndarray:
    """``rfft2`` of a real square image with the given axes reversed (``a[::-1]`` along
    them), from the image's own ``rfft2`` ``spec``.

    Reversing an axis of length n maps index i to n - 1 - i, which multiplies frequency k by
    ``exp(2 pi i k / n)`` and reverses it (k -> -k mod n); on the half spectrum of a real
    image, a reversed column frequency is the conjugate at the reversed row frequency.
    """
    neg, row_phase, col_phase = _reversal_factors(spec.shape[0], spec.shape[1],
                                                  np.dtype(spec.dtype).str)
    out = spec
    if axes[1]:
        out = np.conj(out[neg]) * col_phase
    if axes[0]:
        out = out[neg] * row_phase
    return out


@lru_cache(maxsize=8)
def _reversal_factors(n: int, half: int, dtype: str
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(-k mod n, the row phases (n, 1), the column phases (1, half)) of
    :func:`_reversed_spectrum`, in the spectrum's type."""
    k = np.arange(n)
    neg = (-k) % n
    phase = np.exp(2j * np.pi * k / n).astype(dtype)
    for a in (neg, phase):
        a.setflags(write=False)
    return neg, phase[:, None], phase[None, :half]


def _window(image: np.ndarray, centre_xy: tuple[float, float], size: int) -> np.ndarray:
    """The size x size window of ``image`` whose centre pixel is nearest the centroid."""
    cx, cy = int(round(centre_xy[0])), int(round(centre_xy[1]))
    h = size // 2
    out = np.zeros((size, size))
    ny, nx = image.shape
    r0, c0 = cy - h, cx - h
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(r0 + size, ny), min(c0 + size, nx)
    if rs < re and cs < ce:
        out[rs - r0:re - r0, cs - c0:ce - c0] = image[rs:re, cs:ce]
    return out


@dataclass(frozen=True)
class SwapScore:
    """How much better the given assignment of two stamps matches the model than the exchanged.

    Two comparisons (see :class:`PairFootprints`): ``vignetting`` (own footprint against the
    one with the mask turned, same mapping) and ``footprint`` (own against the other side's).

    Attributes:
        preference: ``(vignetting, footprint)``: the summed correlation difference, given
            minus exchanged, over its value for a noise-free model pair: about +1 for a
            correct pair, -1 for an exchanged one, 0 when the stamps cannot tell.
        significance: ``(vignetting, footprint)``: the same difference in standard deviations
            of its pixel noise.
        correlation: (2, 3) correlations ``[stamp, (own, alt, other side's own)]``.
        contrast: ``(vignetting, footprint)``: mean footprint contrast over the two stamps.
    """

    preference: tuple[float, float]
    significance: tuple[float, float]
    correlation: np.ndarray
    contrast: tuple[float, float]


def _pixel_noise(img: np.ndarray, bright: np.ndarray) -> float:
    """Per-pixel noise (input units) in the donut: robust rms of neighbour differences.

    Photon noise grows with the signal, so the background rms underestimates the noise in
    the donut; differences of adjacent pixels hold the noise (x sqrt 2) and hardly any of
    the smooth donut surface brightness.
    """
    d = (img[:, 1:] - img[:, :-1])[bright[:, 1:] & bright[:, :-1]]
    if d.size < 20:
        return 0.0
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad / np.sqrt(2.0)


@dataclass(frozen=True)
class StampWindows:
    """The two stamps as the footprint checks read them.

    Attributes:
        spectra: (2, size, size // 2 + 1) FFTs of each stamp's window about its flux
            centroid, zero-mean and unit-norm.
        sig_pix: (2,) per-pixel noise of each window relative to its norm.
    """

    spectra: np.ndarray
    sig_pix: np.ndarray


def stamp_windows(intra: np.ndarray, extra: np.ndarray,
                  centroids: tuple[tuple[float, float], tuple[float, float]],
                  noise: tuple[float, float], size: int) -> StampWindows | None:
    """The stamps' windows for :func:`swap_score` and :func:`orientation_score`, made once
    for both; None when a window is empty."""
    wins = np.zeros((2, size, size))
    sig_pix = np.zeros(2)
    for s, (img, cen, sig) in enumerate(((intra, centroids[0], noise[0]),
                                         (extra, centroids[1], noise[1]))):
        w = _window(img, cen, size)
        w = w - w.mean()
        nrm = float(np.linalg.norm(w))
        if nrm == 0:
            return None
        # Per-pixel noise: the larger of the background's and the in-donut one (photon noise
        # adds there), relative to the window's norm (the correlations are normalised).
        q = int(0.995 * (w.size - 1))
        peak = float(np.partition(w.ravel(), q)[q])
        sig_pix[s] = max(sig, _pixel_noise(w, w > 0.3 * peak)) / nrm
        wins[s] = w / nrm
    return StampWindows(sfft.rfft2(wins), sig_pix)


def swap_score(intra: np.ndarray, extra: np.ndarray, centroid_intra: tuple[float, float],
               centroid_extra: tuple[float, float], noise: tuple[float, float],
               fp: PairFootprints, windows: StampWindows | None = None) -> SwapScore:
    """Score the given against the exchanged assignment of a pair (see module docstring).

    Args:
        intra, extra: background-subtracted stamps (input units).
        centroid_intra, centroid_extra: their flux centroids (col, row), px.
        noise: rms background noise of each stamp (input units).
        fp: the pair's predicted footprints.
        windows: the stamps' :func:`stamp_windows`, if already made.
    """
    if windows is None:
        windows = stamp_windows(intra, extra, (centroid_intra, centroid_extra), noise,
                                fp.size)
    if windows is None:
        return SwapScore((0.0, 0.0), (0.0, 0.0), np.zeros((2, 3)), (0.0, 0.0))
    spec, sig_pix = windows.spectra, windows.sig_pix
    # [stamp, (own, alt, other side's own)] in one batched inverse transform.
    prod = np.stack([spec[0] * fp.spectra[0, 0], spec[0] * fp.spectra[0, 1],
                     spec[0] * fp.spectra[1, 0], spec[1] * fp.spectra[1, 0],
                     spec[1] * fp.spectra[1, 1], spec[1] * fp.spectra[0, 0]])
    corr = _peak(prod, fp.shift_rows, fp.shift_cols).reshape(2, 3)
    prefs, sigs, contrasts = [], [], []
    for j in range(2):  # vignetting (alt), footprint (other side's own)
        diff = float(corr[0, 0] + corr[1, 0] - corr[0, 1 + j] - corr[1, 1 + j])
        con = float(fp.contrast[:, j].sum())
        # Match quality A: the right footprint correlates ~A, the wrong one ~A (1 - contrast),
        # with A < 1 as noise and aberrations make the stamps unlike the model.
        quality = float(corr[0, 0] + corr[1, 0] + corr[0, 1 + j] + corr[1, 1 + j]) / \
            max(4.0 - con, 1e-12)
        denom = con * quality
        prefs.append(diff / denom if denom > 0 else 0.0)
        var = float(np.sum(sig_pix ** 2 * fp.diff_sq[:, j]))
        sigs.append(diff / np.sqrt(var) if var > 0 else 0.0)
        contrasts.append(0.5 * con)
    return SwapScore((prefs[0], prefs[1]), (sigs[0], sigs[1]), corr,
                     (contrasts[0], contrasts[1]))


def check_not_swapped(intra: np.ndarray, extra: np.ndarray,
                      centroid_intra: tuple[float, float],
                      centroid_extra: tuple[float, float], noise: tuple[float, float],
                      fp: PairFootprints, config: CheckConfig,
                      windows: StampWindows | None = None) -> SwapScore | None:
    """Raise :class:`SwappedImagesError` if the stamps look exchanged; else the score.

    Returns None when the check does not apply (disabled, or no vignetting to tell by).
    """
    if not config.swap_check or float(fp.contrast[:, 0].min()) < config.swap_min_contrast:
        return None
    s = swap_score(intra, extra, centroid_intra, centroid_extra, noise, fp, windows)
    (p_v, p_f), (z_v, z_f) = s.preference, s.significance
    if p_f < -config.swap_threshold and z_f < -config.swap_min_significance and \
            p_v < config.swap_vignetting_veto:
        raise SwappedImagesError(
            "intra and extra images look exchanged: each matches the model's predicted "
            "footprint of the other side better than its own (vignetted pupil and design "
            f"aberrations: preference {p_f:+.2f} at {z_f:+.1f} sigma; vignetted part alone: "
            f"{p_v:+.2f} at {z_v:+.1f} sigma; +1 = as given, -1 = exchanged). Check which "
            "image is intra-focal (negative detector offset), that neither camera "
            "delivers its stamps turned by 180 degrees, and that the images are this "
            "corner's and the field given is theirs: the diagonally opposite corner's (R00 "
            "and R44, R04 and R40), or a field of the opposite sign, are this corner's "
            "turned by 180 degrees, so all four look alike. Past the "
            "geometric limit of curvature sensing (several um of wavefront at a corner, "
            "validation Fig. 9) the donuts match neither footprint and are refused the same "
            "way")
    return s


# -- one stamp turned or mirrored ----------------------------------------------------------

# The seven ways besides the right one a stamp can arrive turned or mirrored (the
# dihedral group of the square, as wavefront_node's sensors.<corner>.<side>.rot90 and flip
# name them): a quarter-turn rotation, then a left-right mirror.
WRONG_ORIENTATIONS = tuple(Orientation(k, f) for f in ("none", "lr") for k in range(4))[1:]


@dataclass(frozen=True)
class OrientationScore:
    """How much better each stamp matches its footprint under a wrong orientation.

    Attributes:
        preference: (2, 7) ``[stamp, orientation]``: the correlation gained by turning the
            stamp that way, over what it would gain for a noise-free stamp that arrived so
            turned: about -1 for a stamp as given, +1 for one so turned; NaN where the
            orientation is not tested (footprint contrast below the minimum).
        significance: (2, 7) the same gain in standard deviations of its pixel noise.
    """

    preference: np.ndarray
    significance: np.ndarray


def orientation_score(intra: np.ndarray, extra: np.ndarray,
                      centroids: tuple[tuple[float, float], tuple[float, float]],
                      noise: tuple[float, float], fp: PairFootprints,
                      min_contrast: float, windows: StampWindows | None = None
                      ) -> OrientationScore | None:
    """Each stamp against its own footprint as given and under :data:`WRONG_ORIENTATIONS`
    (None when a stamp is empty; ``windows``: the stamps' :func:`stamp_windows`, if made)."""
    if windows is None:
        windows = stamp_windows(intra, extra, centroids, noise, fp.size)
    if windows is None:
        return None
    n_o = len(WRONG_ORIENTATIONS)
    pref = np.full((2, n_o), np.nan)
    sig = np.full((2, n_o), np.nan)
    for s in range(2):
        tested = fp.orient_contrast[s] >= min_contrast
        if not tested.any():
            continue
        # Single precision: the correlations are compared to ~1e-3, and this runs at every
        # estimate off axis (half the time of the product in double).
        spec = windows.spectra[s].astype(np.complex64)
        prod = np.empty((1 + n_o, *spec.shape), np.complex64)
        np.multiply(spec, fp.spectra[s, 0], out=prod[0], casting="same_kind")
        np.multiply(spec, fp.orient_spectra[s], out=prod[1:])
        corr = _peak(prod, fp.shift_rows_32, fp.shift_cols_32)
        gain, con = corr[1:] - corr[0], fp.orient_contrast[s]
        # Match quality A as for the swap: the right orientation correlates ~A, a wrong one
        # ~A (1 - contrast).
        quality = (corr[1:] + corr[0]) / np.maximum(2.0 - con, 1e-12)
        with np.errstate(divide="ignore", invalid="ignore"):
            p = gain / (con * quality)
            z = gain / (windows.sig_pix[s] * np.sqrt(fp.orient_diff_sq[s]))
        pref[s, tested], sig[s, tested] = p[tested], z[tested]
    return OrientationScore(pref, sig)


# Preferences this close to the best name the same fit (a footprint's mirror symmetry).
ORIENTATION_TIE = 0.15


def _turn_text(o: Orientation) -> str:
    return f"rot90 {o.rot90}" + (" then flip lr" if o.flip == "lr" else "")


def check_orientation(intra: np.ndarray, extra: np.ndarray,
                      centroids: tuple[tuple[float, float], tuple[float, float]],
                      noise: tuple[float, float], fp: PairFootprints,
                      config: CheckConfig, windows: StampWindows | None = None
                      ) -> OrientationScore | None:
    """Raise :class:`MisorientedImageError` if a stamp matches its footprint clearly
    better turned or mirrored; else the score (None when the check does not apply)."""
    if not config.orientation_check:
        return None
    sc = orientation_score(intra, extra, centroids, noise, fp, config.orientation_min_contrast,
                           windows)
    if sc is None:
        return None
    bad = (sc.preference > config.orientation_threshold) & \
        (sc.significance > config.orientation_min_significance)
    if not bad.any():
        return sc
    s, k = np.unravel_index(np.nanargmax(np.where(bad, sc.preference, np.nan)), bad.shape)
    # A footprint symmetric about a line (a corner's lune about its radial direction) fits
    # two turns equally: every one as good as the best, within the noise, is named.
    tied = [j for j in np.flatnonzero(bad[s])
            if sc.preference[s, j] >= sc.preference[s, k] - ORIENTATION_TIE]
    turns = ", or equally after ".join(_turn_text(WRONG_ORIENTATIONS[j]) for j in
                                       sorted(tied, key=lambda j: -sc.preference[s, j]))
    raise MisorientedImageError(
        f"the {('intra', 'extra')[s]} image looks turned or mirrored: it matches the model's "
        f"predicted footprint (vignetted pupil) best after {turns} (numpy.rot90 quarter "
        f"turns, then a left-right mirror; preference {sc.preference[s, k]:+.2f} at "
        f"{sc.significance[s, k]:+.1f} sigma, +1 = that way round). Check the orientation "
        "its camera delivers it in (wavefront_node: sensors.<corner>.<side>.rot90 and "
        "flip, applied before the estimate) and that the field given is this image's. "
        "Only with several um of wavefront (a telescope far out of alignment) do the "
        "aberrations reshape a donut as much as its lune, and can make a right one look "
        "turned (input_checks.orientation_check in config/algorithm.yaml turns the check "
        "off)"
        + (". An exchanged intra/extra pair looks turned by 180 degrees too, where the "
           "vignetting is too weak for the swap check" if WRONG_ORIENTATIONS[k] ==
           Orientation(2) else ""))
