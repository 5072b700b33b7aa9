"""Where the package finds its data-only configuration (``config/``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["config_dir"]


def config_dir() -> Path:
    """The ``config/`` directory: ``$CWFS_ROS_CONFIG``, else the source tree's, else the install's.

    The source-tree copy wins over the installed one so that an editable checkout always reads
    the YAML it ships; an ament/pip install reads ``<prefix>/share/cwfs_ros/config``.
    """
    env = os.environ.get("CWFS_ROS_CONFIG")
    if env:
        return Path(env)
    src = Path(__file__).resolve().parents[1] / "config"
    if src.is_dir():
        return src
    return Path(sys.prefix) / "share" / "cwfs_ros" / "config"
