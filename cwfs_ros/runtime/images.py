"""Raw image decoding with the checks only raw pixels allow (no ROS imports).

A ``sensor_msgs/Image`` is a header plus ``height``, ``width``, ``encoding``,
``is_bigendian``, ``step`` (bytes per row) and ``data``. :func:`decode_image` turns those
fields into a 2-D float array ``[row, col]`` (:func:`decoded_dtype`) or raises
:class:`ImageDecodeError` naming the problem (unsupported encoding, bad step, truncated data,
...). It does not judge the content (NaNs, flat or tiny images are the estimator's
business, which raises its own :class:`~cwfs_ros.errors.ImageError`).

Orienting a decoded stamp into the focal-plane frame is :mod:`cwfs_ros.wfs.orientation`.

:func:`decode_checked` decodes and then judges what only the raw pixels can tell
(:func:`inspect_pixels`): a byte order that disagrees with ``is_bigendian``, integer counts
that wrapped instead of clipping, pixels at the converter's full scale, and float values whose
scale no detector gives. The live node and the replay of a bag decode with it.
"""

from __future__ import annotations

import numpy as np

from cwfs_ros.errors import ImageError

__all__ = [
    "ENCODINGS",
    "ImageDecodeError",
    "decode_checked",
    "adc_depth",
    "background_floor",
    "decode_image",
    "decoded_dtype",
    "inspect_pixels",
    "full_scale",
    "full_scale_message",
]

# Single-channel encodings accepted: name -> numpy base type (byte order set per message).
# The ROS names (sensor_msgs/image_encodings.hpp) and their OpenCV-style aliases.
ENCODINGS: dict[str, str] = {
    "mono8": "u1", "8UC1": "u1", "8SC1": "i1",
    "mono16": "u2", "16UC1": "u2", "16SC1": "i2",
    "32SC1": "i4", "32FC1": "f4", "64FC1": "f8",
}
# A generous upper bound on a stamp side: corner donuts need ~160 px, full CCDs are 4k.
MAX_SIDE_PX = 8192


class ImageDecodeError(ImageError):
    """The raw message fields do not describe a usable single-channel image.

    ``reason`` is a short tag: ``unsupported_encoding``, ``bad_dimensions``, ``bad_step``,
    ``truncated_data``, ``excess_data``, ``bad_data``; from :func:`inspect_pixels`:
    ``byte_order``, ``wrapped``, ``saturated``, ``bad_scale``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


def decoded_dtype(encoding: str) -> np.dtype:
    """The float type :func:`decode_image` gives ``encoding``: float32 where it holds every
    value exactly (8- and 16-bit integers, 32FC1), float64 otherwise (32SC1, 64FC1).

    The narrowest exact type: a whole 4000 x 2000 half-chip is 32 MB as float32, and every
    byte of it is hashed, checked and copied to a worker on the node's thread, eight frames
    a visit (docs/performance.md, Whole half-chips).
    """
    base = np.dtype(ENCODINGS[str(encoding)])
    exact32 = base.kind in "ui" and base.itemsize <= 2 or base == np.float32
    return np.dtype(np.float32 if exact32 else np.float64)


def decode_image(data: bytes | bytearray | memoryview | np.ndarray | list[int], *,
                 height: int, width: int, encoding: str, step: int,
                 is_bigendian: bool | int = False) -> np.ndarray:
    """Decode raw ``sensor_msgs/Image`` fields into a ``(height, width)`` float array.

    Args:
        data: the pixel bytes (``bytes``, ``array.array('B')``, a uint8 numpy array, ...).
        height, width: image size in pixels (rows, columns).
        encoding: one of :data:`ENCODINGS` (single channel).
        step: bytes per row, ``>= width * bytes_per_pixel`` (rows may be padded).
        is_bigendian: byte order of multi-byte pixels.

    Returns:
        A float array ``[row, col]`` of :func:`decoded_dtype`, in native byte order; padding
        bytes at the end of each row are dropped. Where the data already are that type and
        order without padding (32FC1, 64FC1 little-endian on x86), a read-only view of
        ``data`` (no copy); otherwise a new array.

    Raises:
        ImageDecodeError: naming the problem. ``len(data)`` must be exactly ``step * height``.
    """
    base = ENCODINGS.get(str(encoding))
    if base is None:
        raise ImageDecodeError(
            "unsupported_encoding",
            f"encoding {encoding!r} is not supported; use a single-channel encoding: "
            + ", ".join(ENCODINGS))
    h, w, st = int(height), int(width), int(step)
    if h < 1 or w < 1 or h > MAX_SIDE_PX or w > MAX_SIDE_PX:
        raise ImageDecodeError("bad_dimensions",
                               f"height x width = {h} x {w} must be within 1..{MAX_SIDE_PX}")
    dtype = np.dtype(base).newbyteorder(">" if is_bigendian else "<")
    row_bytes = w * dtype.itemsize
    if st < row_bytes:
        raise ImageDecodeError(
            "bad_step", f"step {st} B is smaller than width {w} x {dtype.itemsize} B "
            f"per {encoding} pixel = {row_bytes} B")
    buf = _as_bytes(data)
    need = st * h
    if buf.size < need:
        raise ImageDecodeError(
            "truncated_data", f"{buf.size} B of data for step {st} x height {h} = {need} B")
    if buf.size > need:
        raise ImageDecodeError(
            "excess_data", f"{buf.size} B of data for step {st} x height {h} = {need} B")
    rows = buf.reshape(h, st)[:, :row_bytes]
    shared = rows.flags.c_contiguous  # no padding: the pixels below are data's own bytes
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(h, w)
    out = decoded_dtype(encoding)
    if pixels.dtype != out:
        return pixels.astype(out)
    if shared:
        pixels = pixels.view()
        pixels.flags.writeable = False
    return pixels


def decode_checked(data: bytes | bytearray | memoryview | np.ndarray | list[int], *,
                   height: int, width: int, encoding: str, step: int,
                   is_bigendian: bool | int = False) -> np.ndarray:
    """:func:`decode_image`, then :func:`inspect_pixels` on the result (same arguments).

    Raises:
        ImageDecodeError: a layout problem, or one of the content reasons of
            :func:`inspect_pixels`.
    """
    out = decode_image(data, height=height, width=width, encoding=encoding, step=step,
                       is_bigendian=is_bigendian)
    inspect_pixels(out, str(encoding))
    return out


# A wrong byte order multiplies the pixel-to-pixel variation by about 256 (the noisy low
# byte becomes the high one); the right order is never rougher than the wrong one for an
# image whose noise is below ~20000 counts. Refused when the order as given is this many
# times rougher than the other.
BYTE_ORDER_RATIO = 8.0
# Float images: the interquartile spread of log10|value| of a genuine image is a few decades;
# read in the wrong order, tens (float32) to hundreds (float64).
FLOAT_DECADES = 10.0
# Float pixel values whose largest magnitude lies outside this range are no detector's
# output in any unit, and their squares (noise, flux sums) underflow or overflow float64.
SCALE_RANGE = (1e-150, 1e150)
# Wrap steps: neighbours in the bottom and top WRAP_BAND of the type's range (a jump of more
# than half of it); at least WRAP_MIN_PIXELS pixels on each side, so that a single hot pixel
# next to the bias is not a wrap.
WRAP_BAND = 0.25
WRAP_MIN_PIXELS = 3
# Converters narrower than the type (a 12-bit ADC in 16UC1 wraps at 4096) are judged at the
# smallest depth that holds the data, from MIN_ADC_BITS: below it too few levels tell a wrap
# from a sharp donut edge, as for 8-bit types.
MIN_ADC_BITS = 10
# At that depth a genuine donut's edge can step from the bias to the top quarter in one pixel
# (the data fill 50-100 % of the range by construction), so a wrap must also show what no
# genuine pixel does: light pixels wrapped below the background, more than FLOOR_SIGMAS
# times its noise (median and MAD of the image's outer BORDER_PX frame); or, without a bias
# to fall below, at least WRAP_MIN_PIXELS bottom-quarter pixels buried in the light, all 4
# of their neighbours in the top quarter (an edge, even a pixel-sharp one of a convex
# donut or hole, leaves at most 3).
FLOOR_SIGMAS = 6.0
BORDER_PX = 4
# A clip, not a wrap: a clipped donut on a zero background drops from its plateau to 0 in
# one pixel as a wrap does, but its light holds a plateau of pixels at exactly the image
# maximum; a wrap leaves the light noisy just below the wrap point, where the maximum holds
# about as many pixels as the levels just under it. At least CLIP_MIN_PIXELS pixels at the
# maximum, CLIP_PLATEAU_FRACTION of the number of high step pixels, and CLIP_PEAK_RATIO
# times the mean count of the CLIP_LEVELS levels under it (a spike in the histogram) say
# clipped.
CLIP_MIN_PIXELS = 8
CLIP_PLATEAU_FRACTION = 0.1
CLIP_PEAK_RATIO = 4.0
CLIP_LEVELS = 3


def inspect_pixels(image: np.ndarray, encoding: str, *, full_scale_ok: bool = False) -> int:
    """Refuse pixels that a decoder alone can tell are wrong; raise :class:`ImageDecodeError`.

    Args:
        image: the decoded image (:func:`decode_image`) as the message declares it.
        encoding: its encoding (a key of :data:`ENCODINGS`).
        full_scale_ok: integer pixels at full scale are counted, not refused: a frame with
            several stars, where they make only their own star ``saturated`` (detection);
            a stamp holds one donut, refused whole.

    Returns:
        The number of integer pixels at the top of their type's range (0 for floats).

    Reasons:
        ``byte_order``: integers: the image as declared is :data:`BYTE_ORDER_RATIO` times
            rougher (mean absolute difference of neighbours) than with the other byte
            order; floats: its values spread over :data:`FLOAT_DECADES` more decades, or
            over 1 % of them are subnormal while none are in the other order (judged on
            the finite pixels: a NaN is the estimator's ``non_finite``).
        ``saturated``: an integer pixel at the top of its type's range (the converter's full
            scale: the true value is unknown).
        ``wrapped``: integer counts that wrapped around instead of clipping: neighbours a
            jump of more than half the type's range apart, from its bottom to its top
            quarter (at least :data:`WRAP_MIN_PIXELS` pixels each side), or a pixel in the
            bottom quarter with 2 or more of its 4 neighbours in the top one (a pixel or
            two wrapped inside the light). 16- and 32-bit integers only: 8 bits hold too
            few levels to tell a wrap from a sharp donut edge. The same at the depth of a
            narrower converter that holds the data (:func:`adc_depth`: a 12-bit ADC wraps
            at 4096), where the bottom-quarter pixels must also lie below the background
            (:func:`background_floor`), or be buried in the light (all 4 neighbours in
            the top quarter, :data:`WRAP_MIN_PIXELS` of them).
            When the steps are found but the light holds a plateau at the image maximum
            (:data:`CLIP_MIN_PIXELS` ...), the image was clipped: ``saturated``.
        ``bad_scale``: float pixels whose largest magnitude is outside :data:`SCALE_RANGE`.
    """
    base = np.dtype(ENCODINGS[encoding])
    if base.itemsize > 1:
        given = _row_blocks(image)
        _check_byte_order(given, _other_order(given, base), base)
    if base.kind in "ui":
        info = np.iinfo(base)
        n_top = int(np.count_nonzero(image >= info.max))
        # A clipped donut holds a plateau at full scale, and its edge can drop to the bias in
        # one pixel as a wrap does: many pixels at full scale say clipped. A wrap puts a
        # pixel exactly at full scale by chance only: the wrap test comes before the one
        # or two of those.
        if base.itemsize >= 2 and n_top < WRAP_MIN_PIXELS:
            bounds = (float(np.min(image)), float(np.max(image)))
            _check_wrap(image, encoding, float(info.min), float(info.max) - float(info.min) + 1,
                        peak=bounds[1])
            depth = adc_depth(bounds, base)
            if depth is not None:
                _check_wrap(image, f"{depth}-bit", 0.0, float(1 << depth),
                            background_floor(image), peak=bounds[1])
        if n_top and not full_scale_ok:
            raise ImageDecodeError("saturated", full_scale_message(n_top, encoding))
        return n_top
    peak = _finite_peak(image)
    if peak > 0 and not SCALE_RANGE[0] <= peak <= SCALE_RANGE[1]:
        raise ImageDecodeError(
            "bad_scale", f"largest pixel magnitude {peak:.3g} is outside "
            f"[{SCALE_RANGE[0]:.0e}, {SCALE_RANGE[1]:.0e}]: no detector gives such values, "
            "and their squares underflow or overflow; send counts, electrons or photons")
    return 0


def _finite_peak(image: np.ndarray) -> float:
    """The largest magnitude of the finite pixels (0 when there are none).

    An image without NaN or Inf gives it from its extremes: two passes and no copy, where
    selecting the finite pixels first copies the frame twice (~25 of a 2-Mpixel frame's
    ~40 ms in wavefront_node, one frame after the other). An extreme that is not finite
    says there are such pixels, and only then are they selected.
    """
    if image.size == 0:
        return 0.0
    lo, hi = float(np.min(image)), float(np.max(image))
    if np.isfinite(lo) and np.isfinite(hi):
        return max(abs(lo), abs(hi))
    finite = image[np.isfinite(image)]
    return float(np.max(np.abs(finite))) if finite.size else 0.0


def full_scale(encoding: str) -> float | None:
    """The top of an integer encoding's range (its converter's full scale), else None."""
    base = np.dtype(ENCODINGS[encoding])
    return float(np.iinfo(base).max) if base.kind in "ui" else None


def full_scale_message(n_pixels: int, encoding: str) -> str:
    """Why ``n_pixels`` pixels at the full scale of ``encoding`` make a stamp unusable."""
    return (f"{n_pixels} pixel(s) at {full_scale(encoding):.0f}, the full scale of {encoding}: "
            "the converter is saturated and their true values are unknown")


# Byte order is judged on blocks of BLOCK_ROWS whole rows spread over the image, about
# ORDER_PIXELS pixels in all (a stamp: all of it). A wrong order changes every pixel, so any
# blocks tell it; reading all of a frame's millions of pixels twice cost the node ~100 ms an
# image.
BLOCK_ROWS = 4
ORDER_PIXELS = 1 << 16


def _row_blocks(a: np.ndarray) -> np.ndarray:
    """``(n, rows, cols)`` blocks of whole rows evenly spread over ``a`` (all of it, as one
    block, when it is small)."""
    h, w = a.shape
    if a.size <= ORDER_PIXELS or h < 2 * BLOCK_ROWS:
        return a[None]
    n = int(np.clip(-(-ORDER_PIXELS // (BLOCK_ROWS * w)), 1, h // BLOCK_ROWS))
    starts = np.linspace(0, h - BLOCK_ROWS, n).astype(int)
    return np.stack([a[s:s + BLOCK_ROWS] for s in starts])


def _other_order(a: np.ndarray, base: np.dtype) -> np.ndarray:
    """``a`` (float values of a ``base`` image) as its bytes read in the other byte order:
    the values convert back to ``base`` exactly, and swapping their bytes is what a decoder
    with the other ``is_bigendian`` would read."""
    with np.errstate(all="ignore"):  # the wrong order may hold NaN, Inf, subnormals
        return a.astype(base).byteswap().astype(np.float64)


def _roughness(a: np.ndarray) -> float:
    """Mean absolute difference of horizontal and vertical neighbours (inf if not finite);
    ``a`` is an image or a stack of row blocks (neighbours within a block)."""
    total, n = 0.0, 0
    with np.errstate(all="ignore"):
        for k in (a.ndim - 2, a.ndim - 1):
            if a.shape[k] > 1:
                d = np.abs(np.diff(a, axis=k))
                total += float(np.sum(d))
                n += d.size
    return total / n if n else 0.0


def _log_spread(a: np.ndarray) -> float:
    """Interquartile range of log10|x| over the finite non-zero pixels (decades)."""
    x = np.abs(a[np.isfinite(a)])
    x = x[x > 0]
    if x.size < 4:
        return 0.0
    q1, q3 = np.percentile(np.log10(x), [25, 75])
    return float(q3 - q1)


def _subnormal_fraction(a: np.ndarray, tiny: float) -> float:
    x = np.abs(a[np.isfinite(a)])
    return float(np.count_nonzero((x > 0) & (x < tiny))) / max(x.size, 1)


def _check_byte_order(image: np.ndarray, swapped: np.ndarray, base: np.dtype) -> None:
    """Integers: the order as given must not be :data:`BYTE_ORDER_RATIO` times rougher than
    the other (both read the same range, so absolute differences compare). Floats: a wrong
    order puts mantissa bytes into the exponent, so the values spread over tens to hundreds
    of decades (or turn NaN/Inf); the order as given must not spread :data:`FLOAT_DECADES`
    more than the other."""
    fin_given = bool(np.all(np.isfinite(image)))
    fin_other = bool(np.all(np.isfinite(swapped)))
    if not fin_other:
        return
    if base.kind == "f":
        given, other = _log_spread(image), _log_spread(swapped)
        tiny = float(np.finfo(base).tiny)
        sub_given, sub_other = _subnormal_fraction(image, tiny), _subnormal_fraction(swapped,
                                                                                     tiny)
        # Integer-valued floats read in the wrong order have zero low mantissa bytes in the
        # exponent: subnormal numbers, which no detector's image holds.
        bad = given > other + FLOAT_DECADES or (sub_given > 0.01 and sub_other == 0.0)
        what = (f"their values span {other:.3g} decades (interquartile) against {given:.3g}, "
                f"{sub_other:.0%} subnormal against {sub_given:.0%}")
    else:
        given, other = _roughness(image), _roughness(swapped)
        bad = given > BYTE_ORDER_RATIO * other
        what = f"mean neighbour difference {other:.4g} against {given:.4g}"
    if bad:
        raise ImageDecodeError(
            "byte_order", "the pixels disagree with is_bigendian: read in the other byte "
            f"order they are plausible ({what}{'' if fin_given else ', with NaN/Inf'}); "
            "fix is_bigendian")


def adc_depth(bounds: tuple[float, float], base: np.dtype) -> int | None:
    """Bits of the narrowest converter that holds the data, when narrower than the type.

    A 12-bit ADC's counts stored in 16UC1 never exceed 4095, and a wrap there goes from 4095
    to 0, far below the type's range. ``bounds``: the image's (smallest, largest) value. The
    depth is that of the largest value (values >= 0 only: a signed image holding negative
    counts is no unsigned converter's); None below :data:`MIN_ADC_BITS` or when it is the
    type's own range (judged as such already).
    """
    low, peak = bounds
    if not (np.isfinite(low) and np.isfinite(peak)) or low < 0:
        return None
    depth = int(peak).bit_length()
    value_bits = 8 * base.itemsize - (1 if base.kind == "i" else 0)
    return depth if MIN_ADC_BITS <= depth < value_bits else None


def background_floor(image: np.ndarray) -> float:
    """The level below which no genuine pixel lies: the background (median of the outer
    :data:`BORDER_PX` frame) less :data:`FLOOR_SIGMAS` times its noise (1.4826 MAD, at
    least 1 count)."""
    h, w = image.shape
    b = min(BORDER_PX, h // 4, w // 4)
    if b < 1:
        return 0.0
    border = np.concatenate([image[:b].ravel(), image[-b:].ravel(), image[b:-b, :b].ravel(),
                             image[b:-b, -b:].ravel()])
    med = float(np.median(border))
    sigma = max(1.4826 * float(np.median(np.abs(border - med))), 1.0)
    return med - FLOOR_SIGMAS * sigma


def _step_counts(image: np.ndarray, low_below: float, high_from: float,
                 floor: float) -> tuple[int, int, int, int]:
    """Around the pixels at or above ``high_from`` (the top band; few in a donut image, so
    only they and their 4 neighbours are visited): (low pixels below ``min(low_below,
    floor)`` next to them, top-band pixels next to such a low one, such low pixels with 2 or
    more top-band neighbours, pixels below ``low_below`` with all 4 neighbours in the top
    band)."""
    hr, hc = np.nonzero(image >= high_from)
    if hr.size == 0:
        return 0, 0, 0, 0
    h, w = image.shape
    near_low = np.zeros(hr.size, dtype=bool)
    band, below = [], []  # flat indices of low neighbours, once per top-band neighbour
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        r, c = hr + dr, hc + dc
        ok = np.flatnonzero((r >= 0) & (r < h) & (c >= 0) & (c < w))
        v = image[r[ok], c[ok]]
        in_band = v < low_below
        band.append((r[ok] * w + c[ok])[in_band])
        low = in_band & (v < floor)
        below.append((r[ok] * w + c[ok])[low])
        near_low[ok[low]] = True
    _, n_band = np.unique(np.concatenate(band), return_counts=True)
    _, n_below = np.unique(np.concatenate(below), return_counts=True)
    return (int(n_below.size), int(np.count_nonzero(near_low)),
            int(np.count_nonzero(n_below >= 2)), int(np.count_nonzero(n_band == 4)))


def _check_wrap(image: np.ndarray, what: str, lo: float, span: float,
                floor: float | None = None, *, peak: float) -> None:
    """Raise ``wrapped`` for the steps a wrap at ``lo + span`` leaves (:data:`WRAP_BAND`),
    or ``saturated`` when their high side is a plateau at the image maximum (a clip).
    ``floor``: only low pixels below it count (:func:`background_floor`), or, without
    one, those buried in the top band. ``peak``: the image maximum."""
    if peak < lo + (1.0 - WRAP_BAND) * span:
        return  # nothing in the top band
    low_step, high_step, enclosed, buried = _step_counts(
        image, lo + WRAP_BAND * span, lo + (1.0 - WRAP_BAND) * span,
        np.inf if floor is None else floor)
    if floor is None:
        buried = 0
    # A pixel or two that wrapped sit inside the light: low, with at least 2 of its 4
    # neighbours high (a hot pixel is the opposite: high among low ones).
    if not ((low_step >= WRAP_MIN_PIXELS and high_step >= WRAP_MIN_PIXELS) or enclosed
            or buried >= WRAP_MIN_PIXELS):
        return
    at_peak = int(np.count_nonzero(image == peak))
    under = int(np.count_nonzero((image < peak) & (image >= peak - CLIP_LEVELS)))
    if at_peak >= max(CLIP_MIN_PIXELS, CLIP_PLATEAU_FRACTION * high_step,
                      CLIP_PEAK_RATIO * under / CLIP_LEVELS):
        raise ImageDecodeError(
            "saturated", f"{at_peak} pixel(s) sit at the image maximum {peak:g}, and "
            f"{high_step} at the top of sharp steps to the bottom of the {what} range: a "
            "clipped plateau (the converter or the camera's processing saturated), not a wrap")
    raise ImageDecodeError(
        "wrapped", f"{low_step} pixel(s) sit in the bottom quarter of the {what} range "
        f"(0..{span:g} above {lo:g})"
        + ("" if floor is None else f", below the background ({floor:.0f} at most),")
        + f" next to {high_step} in its top quarter ({enclosed} surrounded by them"
        + ("" if floor is None else f"; {buried} buried in it")
        + "): counts that wrapped around instead of clipping; clip at the full scale")


def _as_bytes(data: object) -> np.ndarray:
    """A flat uint8 view (or copy, for a list) of the pixel data."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)  # bytes, array.array('B'), memoryview
    except (TypeError, ValueError):
        try:
            return np.asarray(data, dtype=np.uint8).reshape(-1)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ImageDecodeError("bad_data", f"pixel data is not a byte sequence ({exc})"
                                   ) from None
