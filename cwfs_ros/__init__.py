"""cwfs_ros: curvature wavefront sensing and active-optics control for wide-field telescopes.

The science lives in :mod:`cwfs_ros.core` (no ROS imports); the ROS 2 nodes are thin wrappers.
"""

__version__ = "0.1.0"
