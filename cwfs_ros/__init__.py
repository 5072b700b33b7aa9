"""cwfs_ros: curvature wavefront sensing and active-optics control for wide-field telescopes.

The science is a ROS-free library (:mod:`cwfs_ros.wfs`, :mod:`cwfs_ros.frames`,
:mod:`cwfs_ros.ofc`, :mod:`cwfs_ros.runtime`); the ROS 2 nodes in :mod:`cwfs_ros.ros` are thin.
``from cwfs_ros.core import estimate_wavefront`` is the stable entry point of the estimator.
"""

__version__ = "0.1.0"

__all__ = ["__version__", "estimate_wavefront"]


def __getattr__(name: str):
    # ``cwfs_ros.estimate_wavefront``: the documented entry point, imported on first use so
    # that ``import cwfs_ros`` stays light (the nodes' worker processes import only what
    # their jobs need).
    if name == "estimate_wavefront":
        from cwfs_ros.wfs.estimator import estimate_wavefront

        return estimate_wavefront
    raise AttributeError(f"module 'cwfs_ros' has no attribute {name!r}")
