"""Where the simulator's package data are (``cwfs_ros/sim/data``: the bending modes)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["sim_data_dir"]


def sim_data_dir() -> Path:
    """Return the simulator's package-data directory (``cwfs_ros/sim/data``)."""
    return Path(__file__).resolve().parent / "data"
