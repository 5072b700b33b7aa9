"""The middleware settings every process of the graph shares (FastDDS profile).

Large donut images need FastDDS shared-memory segments bigger than its default; the profile
``config/fastdds_profile.xml`` sets them. Every process that joins the graph (nodes, bag
recorder, graph tools) points FastDDS at it before rclpy initialises, unless the environment
already names a profile.
"""

from __future__ import annotations

import os

from cwfs_ros.config import config_dir

__all__ = ["PROFILE_ENV", "ensure_fastdds_profile"]

PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"


def ensure_fastdds_profile() -> str | None:
    """Point FastDDS at config/fastdds_profile.xml unless the environment chose a profile."""
    if not os.environ.get(PROFILE_ENV):
        prof = config_dir() / "fastdds_profile.xml"
        if prof.is_file():
            os.environ[PROFILE_ENV] = str(prof)
    return os.environ.get(PROFILE_ENV)
