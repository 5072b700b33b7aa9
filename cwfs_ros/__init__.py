"""cwfs_ros: curvature wavefront sensing and active-optics control for wide-field telescopes.

The science is a ROS-free library (:mod:`cwfs_ros.wfs`, :mod:`cwfs_ros.frames`,
:mod:`cwfs_ros.ofc`, :mod:`cwfs_ros.runtime`); the ROS 2 nodes in :mod:`cwfs_ros.ros` are thin.
``from cwfs_ros.core import estimate_wavefront`` is the stable entry point of the estimator.
"""

__version__ = "0.1.0"
