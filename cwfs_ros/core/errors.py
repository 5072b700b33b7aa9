"""Exceptions raised by the core on bad input: each names the problem in its message."""

from __future__ import annotations

__all__ = [
    "CwfsError", "ConfigError", "ImageError", "NonFiniteImageError", "FlatImageError",
    "DonutCutError", "ShapeMismatchError", "StampTooSmallError", "SaturatedImageError",
    "SwappedImagesError",
]


class CwfsError(Exception):
    """Base class of every error the core raises on purpose."""


class ConfigError(CwfsError, ValueError):
    """An instrument or configuration file, or a parameter, is missing, mistyped or invalid."""


class ImageError(CwfsError, ValueError):
    """A donut image cannot be used. ``reason`` is a short machine-readable tag."""

    reason = "bad_image"


class NonFiniteImageError(ImageError):
    reason = "non_finite"


class FlatImageError(ImageError):
    reason = "flat_or_empty"


class DonutCutError(ImageError):
    reason = "donut_cut_by_edge"


class ShapeMismatchError(ImageError):
    reason = "shape_mismatch"


class StampTooSmallError(ImageError):
    reason = "stamp_too_small"


class SaturatedImageError(ImageError):
    """Pixels at the detector's saturation level, or a clipped flat top (:mod:`.checks`)."""

    reason = "saturated"


class SwappedImagesError(ImageError):
    """The intra- and extra-focal images look exchanged (:mod:`.checks`)."""

    reason = "swapped"
