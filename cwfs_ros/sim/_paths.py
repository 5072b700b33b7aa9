"""Locate the package's ``config/`` and data directories (source tree or installed share)."""

from __future__ import annotations

from pathlib import Path

from cwfs_ros.config import config_dir as _config_dir

__all__ = ["config_dir", "sim_data_dir"]


def config_dir() -> Path:
    """The package's ``config/`` directory (see :func:`cwfs_ros.config.config_dir`)."""
    return _config_dir()


def sim_data_dir() -> Path:
    """Return the simulator's package-data directory (``cwfs_ros/sim/data``)."""
    return Path(__file__).resolve().parent / "data"
