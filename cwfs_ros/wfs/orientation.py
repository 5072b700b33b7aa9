"""Image orientation into the focal-plane frame, and padding of stamps.

The estimator works in the focal-plane frame of the field angles, ``[row=y, col=x]``.
:func:`orient_image` applies a per-sensor rotation by ``k * 90`` degrees and a flip that
brings a received stamp into that frame; :func:`pad_stamp` embeds a stamp in a larger one
filled with its border level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FLIPS", "Orientation", "orient_image", "pad_stamp"]

FLIPS = ("none", "lr", "ud")


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
