"""The project's one exception hierarchy: every error raised on purpose is a :class:`CwfsError`.

    CwfsError
    ├── ConfigError (ValueError)        a configuration file, parameter or parameter file
    │   └── ParamsFileError             a ROS parameter file that cannot be used
    ├── ImageError (ValueError)         a donut image or frame that cannot be used (``reason``)
    ├── BagError                        a rosbag2 bag that cannot be written, read or decoded
    ├── TileStoreError                  a stored field tile that is not the one asked for
    ├── LaunchError (RuntimeError)      a node that cannot be started
    ├── ToolError                       a graph tool's target is missing or refused the request
    ├── LoopError (RuntimeError)        the closed-loop demo could not run
    └── CliError                        a command-line user error (exit status 2)

Each names the problem in its message, on one line where a user reads it.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "CwfsError", "ConfigError", "ImageError", "NonFiniteImageError", "FlatImageError",
    "DonutCutError", "ShapeMismatchError", "FrameSizeError", "StampTooSmallError",
    "SaturatedImageError", "SwappedImagesError", "MisorientedImageError", "ParamsFileError",
    "BagError",
    "TileStoreError", "LaunchError", "ToolError", "LoopError", "CliError", "Problem",
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


class FrameUnitsError(ImageError):
    """A frame whose sky is quieter than one electron's shot noise: not in electrons, or
    ``gain_e_per_adu`` wrong; the detection's noise-aware limits would pass blends."""

    reason = "frame_units"


class DonutCutError(ImageError):
    reason = "donut_cut_by_edge"


class ShapeMismatchError(ImageError):
    reason = "shape_mismatch"


class FrameSizeError(ImageError):
    """A frame larger than its half-chip, or the two halves of a sensor of different sizes."""

    reason = "frame_size"


class StampTooSmallError(ImageError):
    reason = "stamp_too_small"


class SaturatedImageError(ImageError):
    """Pixels at the detector's saturation level, or a clipped flat top (:mod:`.checks`)."""

    reason = "saturated"


class SwappedImagesError(ImageError):
    """The intra- and extra-focal images look exchanged (:mod:`.checks`)."""

    reason = "swapped"


class MisorientedImageError(ImageError):
    """One image looks turned or mirrored against its predicted footprint (:mod:`.checks`)."""

    reason = "misoriented"


class ParamsFileError(ConfigError):
    """A parameter file that cannot be used; the message names the file and the key."""


class BagError(CwfsError):
    """A bag cannot be written, read or decoded; the message says why, on one line."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class TileStoreError(CwfsError):
    """A stored field tile that cannot be used (unreadable, damaged, another tile's): the
    tile is rebuilt; the store records why (:mod:`cwfs_ros.wfs.tile_store`)."""


class LaunchError(CwfsError, RuntimeError):
    """A node cannot be started; the message says why and what to do."""


class ToolError(CwfsError):
    """A target that is not there or a request the graph refused: one line, exit 1."""

    exit_code = 1


class LoopError(CwfsError, RuntimeError):
    """The loop could not run (a node failed to start, a visit timed out); says which."""


class CliError(CwfsError):
    """A user-facing error of a sub-command: reported on stderr, exit status 2."""


@dataclass(frozen=True)
class Problem:
    """Why something was not used: a ``reason`` tag (counted, compared) and a ``message``.

    Results carry the tag as data, so that no caller parses it back out of text; ``status``
    is the one-line text for logs and messages, ``"<reason>: <message>"``.
    """

    reason: str
    message: str

    @property
    def status(self) -> str:
        return f"{self.reason}: {self.message}" if self.message else self.reason

    def __str__(self) -> str:
        return self.status
