"""The package's data-only configuration (``config/``): where it is, and how it is read.

* :func:`config_dir`: the directory, from ``$CWFS_ROS_CONFIG``, the source tree or the install.
* :func:`load_yaml`: the one YAML reader, cached per file and modification time, raising
  :class:`~cwfs_ros.errors.ConfigError` that names the file.
* :func:`load_sensor_geometry`: the one reader of the corner-sensor file
  (``config/sensors/lsst_corners.yaml``): each corner's half-chip field points, their
  mid-point and detector offsets. The live pairing, the controller, the frames path and the
  simulator all take the geometry from here.
"""

from __future__ import annotations

import copy
import os
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import yaml

from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import SIDES

__all__ = ["AUTO_TILE_STORE", "SENSOR_FILE", "CornerGeometry", "config_dir",
           "load_sensor_geometry", "load_yaml", "ros_home", "sensor_file", "tile_store_dir"]

# The corner-sensor file, relative to config_dir().
SENSOR_FILE = Path("sensors") / "lsst_corners.yaml"


def ros_home() -> Path:
    """``$ROS_HOME``, else ``~/.ros``: where ROS 2 keeps a node's files (logs, state)."""
    home = os.environ.get("ROS_HOME", "")
    return Path(home).expanduser() if home else Path.home() / ".ros"


#: ``tile_store`` value that means :func:`tile_store_dir`'s default directory.
AUTO_TILE_STORE = "auto"


def tile_store_dir(value: str) -> str:
    """The directory a ``tile_store`` parameter names: ``auto`` is
    ``$ROS_HOME/cwfs_ros/tiles``, ``""`` none (no store), anything else that path (``~``
    expanded). Field tiles are kept there across processes (:mod:`cwfs_ros.wfs.tile_store`)."""
    if value == AUTO_TILE_STORE:
        return str(ros_home() / "cwfs_ros" / "tiles")
    return str(Path(value).expanduser()) if value else ""


def config_dir() -> Path:
    """The ``config/`` directory: ``$CWFS_ROS_CONFIG``, else the source tree's, else the install's.

    The source-tree copy wins over the installed one so that an editable checkout always reads
    the YAML it ships; an ament/pip install reads ``<prefix>/share/cwfs_ros/config``.
    """
    env = os.environ.get("CWFS_ROS_CONFIG")
    if env:
        return Path(env)
    src = _source_config()
    if src.is_dir():
        return src
    return Path(sys.prefix) / "share" / "cwfs_ros" / "config"


@lru_cache(maxsize=1)
def _source_config() -> Path:
    # Resolved once: resolving the path costs a system call per component, and every
    # pair estimate reads the configuration (load_algorithm, load_checks, load_instrument).
    return Path(__file__).resolve().parents[1] / "config"


@lru_cache(maxsize=64)
def _parsed(path: str, mtime_ns: int, what: str) -> Any:
    # The C loader when available: the 1 MB sensitivity matrix parses 10x faster.
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        with open(path, encoding="utf-8") as f:
            return yaml.load(f, Loader=loader)  # noqa: S506 - a safe loader
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read {what} {path}: {exc}") from exc


def load_yaml(path: str | Path, what: str = "configuration file", *, copy_: bool = True
              ) -> Any:
    """The parsed YAML file ``path``; the parse is cached per file and modification time.

    ``copy_=False`` returns the cached object itself, for a caller that only reads it (the
    1 MB sensitivity matrix is not worth copying); by default the caller gets its own copy.

    Raises:
        ConfigError: ``cannot read <what> <path>: <why>`` (missing, unreadable, not YAML).
    """
    p = Path(path)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {p}: {exc.strerror or exc}") from exc
    parsed = _parsed(str(p.resolve()), mtime, what)
    return copy.deepcopy(parsed) if copy_ else parsed


@dataclass(frozen=True)
class CornerGeometry:
    """One corner wavefront sensor: its two half-chips, in degrees of the batoid field frame.

    Attributes:
        name: the raft, e.g. ``R00``.
        intra_field_deg, extra_field_deg: field point ``(x, y)`` of each half-chip [deg].
        mid_field_deg: where the corner's Zernikes are reported: the file's ``mid_deg``, else
            the mean of the two half-chips [deg].
        intra_offset_mm, extra_offset_mm: detector offset from focus (intra negative) [mm].
        intra_sensor, extra_sensor: the half-chips' names (``SW1``, ``SW0``).
    """

    name: str
    intra_field_deg: tuple[float, float]
    extra_field_deg: tuple[float, float]
    mid_field_deg: tuple[float, float]
    intra_offset_mm: float
    extra_offset_mm: float
    intra_sensor: str = ""
    extra_sensor: str = ""

    def field_deg(self, side: str) -> tuple[float, float]:
        """The field point of half-chip ``side`` (``intra`` or ``extra``) [deg]."""
        return self.intra_field_deg if side == "intra" else self.extra_field_deg


def sensor_file(path: str | Path | None = None) -> Path:
    """``path``, or the package's corner-sensor file when it is None or empty."""
    return Path(path) if path else config_dir() / SENSOR_FILE


def _pair(value: Any, where: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be a pair of numbers, got {value!r}") from None
    return x, y


def load_sensor_geometry(path: str | Path | None = None) -> dict[str, CornerGeometry]:
    """``{corner: CornerGeometry}`` of the corner-sensor file, in the file's order.

    Raises:
        ConfigError naming the file and the missing or bad key.
    """
    p = sensor_file(path)
    raw = load_yaml(p, "sensor file")
    try:
        offsets = raw.get("detector_offset_mm", {"extra": 1.5, "intra": -1.5})
        out = {}
        for corner, c in raw["corners"].items():
            f = {s: _pair(c[s]["field_deg"], f"{p}: {corner}.{s}.field_deg") for s in SIDES}
            mid = (_pair(c["mid_deg"], f"{p}: {corner}.mid_deg") if "mid_deg" in c else
                   (0.5 * (f["intra"][0] + f["extra"][0]), 0.5 * (f["intra"][1] + f["extra"][1])))
            out[str(corner)] = CornerGeometry(
                name=str(corner), intra_field_deg=f["intra"], extra_field_deg=f["extra"],
                mid_field_deg=mid, intra_offset_mm=float(offsets["intra"]),
                extra_offset_mm=float(offsets["extra"]),
                intra_sensor=str(c["intra"].get("sensor", "")),
                extra_sensor=str(c["extra"].get("sensor", "")))
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"sensor file {p}: missing or bad key {exc}") from exc
    return out
