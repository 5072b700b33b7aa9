"""Frames with several stars: detection, field positions, selection and combination.

* :mod:`.detection`: donut detection and background in a half-chip frame;
* :mod:`.field_position`: pixel -> field angle per half-chip (``config/lsst_corners.yaml``);
* :mod:`.selection`: which stars to pair, and the per-corner frame job;
* :mod:`.combination`: the noise-weighted combination of a corner's pair estimates.

Built on :mod:`cwfs_ros.wfs`; no ROS import.
"""

from cwfs_ros.frames.combination import CombinedEstimate, combine_pairs
from cwfs_ros.frames.detection import detect_donuts
from cwfs_ros.frames.selection import (
    CornerFrameJob,
    CornerFrameResult,
    estimate_corner_frames,
    run_corner_frame_job,
)

__all__ = ["CombinedEstimate", "CornerFrameJob", "CornerFrameResult", "combine_pairs",
           "detect_donuts", "estimate_corner_frames", "run_corner_frame_job"]
