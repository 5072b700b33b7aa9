"""Locate the package's ``config/`` and data directories (source tree or installed share)."""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["config_dir", "sim_data_dir"]


def config_dir() -> Path:
    """Return the ``config/`` directory of cwfs_ros.

    In a source checkout (or an editable install) this is ``<repo>/config``; in an installed
    package it is ``<sys.prefix>/share/cwfs_ros/config`` (where ``setup.py`` puts it).
    """
    repo_config = Path(__file__).resolve().parents[2] / "config"
    if repo_config.is_dir():
        return repo_config
    return Path(sys.prefix) / "share" / "cwfs_ros" / "config"


def sim_data_dir() -> Path:
    """Return the simulator's package-data directory (``cwfs_ros/sim/data``)."""
    return Path(__file__).resolve().parent / "data"
