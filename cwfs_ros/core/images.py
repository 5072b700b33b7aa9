"""Raw image decoding and stamp orientation (no ROS imports).

A ``sensor_msgs/Image`` is a header plus ``height``, ``width``, ``encoding``,
``is_bigendian``, ``step`` (bytes per row) and ``data``. :func:`decode_image` turns those
fields into a 2-D float64 array ``[row, col]`` or raises :class:`ImageDecodeError` naming the
problem (unsupported encoding, bad step, truncated data, ...). It does not judge the content
(NaNs, flat or tiny images are the estimator's business, which raises its own
:class:`~cwfs_ros.core.errors.ImageError`).

:func:`orient_image` applies a per-sensor rotation by ``k * 90`` degrees and a flip, to bring a
stamp into the focal-plane frame of the field angles (``[row=y, col=x]``) that the estimator
expects. :func:`pad_stamp` embeds a stamp in a larger one filled with its border level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ImageError

__all__ = [
    "ENCODINGS",
    "FLIPS",
    "ImageDecodeError",
    "Orientation",
    "decode_image",
    "orient_image",
    "pad_stamp",
]

# Single-channel encodings accepted: name -> numpy base type (byte order set per message).
# The ROS names (sensor_msgs/image_encodings.hpp) and their OpenCV-style aliases.
ENCODINGS: dict[str, str] = {
    "mono8": "u1", "8UC1": "u1", "8SC1": "i1",
    "mono16": "u2", "16UC1": "u2", "16SC1": "i2",
    "32SC1": "i4", "32FC1": "f4", "64FC1": "f8",
}
FLIPS = ("none", "lr", "ud")
# A generous upper bound on a stamp side: corner donuts need ~160 px, full CCDs are 4k.
MAX_SIDE_PX = 8192


class ImageDecodeError(ImageError):
    """The raw message fields do not describe a usable single-channel image.

    ``reason`` is a short tag: ``unsupported_encoding``, ``bad_dimensions``, ``bad_step``,
    ``truncated_data``, ``excess_data``, ``bad_data``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


def decode_image(data: bytes | bytearray | memoryview | np.ndarray | list[int], *,
                 height: int, width: int, encoding: str, step: int,
                 is_bigendian: bool | int = False) -> np.ndarray:
    """Decode raw ``sensor_msgs/Image`` fields into a float64 ``(height, width)`` array.

    Args:
        data: the pixel bytes (``bytes``, ``array.array('B')``, a uint8 numpy array, ...).
        height, width: image size in pixels (rows, columns).
        encoding: one of :data:`ENCODINGS` (single channel).
        step: bytes per row, ``>= width * bytes_per_pixel`` (rows may be padded).
        is_bigendian: byte order of multi-byte pixels.

    Returns:
        A new, writable float64 array ``[row, col]``; padding bytes at the end of each row are
        dropped.

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
    return np.ascontiguousarray(rows).view(dtype).reshape(h, w).astype(np.float64)


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


@dataclass(frozen=True)
class Orientation:
    """How to bring a received stamp into the focal-plane frame: rotate, then flip.

    Attributes:
        rot90: number of counter-clockwise quarter turns, as ``numpy.rot90(image, rot90)``
            (0..3; any integer is taken modulo 4).
        flip: ``"none"``, ``"lr"`` (mirror the columns, x -> -x) or ``"ud"`` (mirror the rows,
            y -> -y), applied after the rotation.
    """

    rot90: int = 0
    flip: str = "none"

    def __post_init__(self) -> None:
        if self.flip not in FLIPS:
            raise ValueError(f"flip must be one of {FLIPS}, got {self.flip!r}")
        object.__setattr__(self, "rot90", int(self.rot90) % 4)

    @property
    def identity(self) -> bool:
        return self.rot90 == 0 and self.flip == "none"


def orient_image(image: np.ndarray, orientation: Orientation) -> np.ndarray:
    """Apply ``orientation`` (rotation by ``rot90 * 90`` deg, then the flip) to a stamp."""
    out = np.rot90(image, orientation.rot90) if orientation.rot90 else image
    if orientation.flip == "lr":
        out = out[:, ::-1]
    elif orientation.flip == "ud":
        out = out[::-1, :]
    return np.ascontiguousarray(out)


def pad_stamp(image: np.ndarray, pad_px: int) -> np.ndarray:
    """Embed ``image`` in a stamp ``pad_px`` larger on every side, filled with its border median.

    Corner donuts fill a 160 px stamp almost to the edge; the estimator needs room for its
    computation boundary around the donut, which padding with the background level provides
    without changing the donut. Non-finite border pixels are ignored for the fill value (the
    estimator rejects non-finite images anyway).
    """
    pad = int(pad_px)
    if pad <= 0 or image.ndim != 2 or image.size == 0:
        return image
    border = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
    border = border[np.isfinite(border)]
    fill = float(np.median(border)) if border.size else 0.0
    return np.pad(image, pad, mode="constant", constant_values=fill)
