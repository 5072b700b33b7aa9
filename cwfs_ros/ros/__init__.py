"""The ROS 2 layer: thin nodes, the launcher, parameter files, bags and graph tools.

* :mod:`.wavefront_node`: donut image pairs in, per-corner wavefronts and the 76-vector out.
* :mod:`.ofc_node`: the 76-vector in, the 50-DoF correction out.
* :mod:`.camera_sim_node`: a ray-traced, perturbed telescope publishing the 8 image topics.
* :mod:`.convert`: message <-> numpy conversion; :mod:`.common`: QoS, parameters, diagnostics.
* :mod:`.launch`: ``bringup`` and ``node``; :mod:`.params`: parameter files and ``-p`` checks.
* :mod:`.bag`: rosbag2 record/play/info; :mod:`.tools`: ``topic``, ``param``, ``node``.

The science is in the ROS-free layers below (:mod:`cwfs_ros.wfs`, :mod:`cwfs_ros.frames`,
:mod:`cwfs_ros.ofc`, :mod:`cwfs_ros.runtime`). Importing this package imports no ROS module:
the worker processes of the wavefront node never load rclpy.
"""

__all__ = ["bag", "camera_sim_node", "common", "convert", "executor", "launch", "ofc_node",
           "params", "tools", "wavefront_node"]
