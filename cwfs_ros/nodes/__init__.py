"""ROS 2 nodes of cwfs_ros: thin wrappers that convert messages and call :mod:`cwfs_ros.core`.

* :mod:`.wavefront_node`: donut image pairs in, per-corner wavefronts and the 76-vector out.
* :mod:`.ofc_node`: the 76-vector in, the 50-DoF correction out.
* :mod:`.convert`: message <-> numpy conversion; :mod:`.common`: QoS, parameters, diagnostics.

Importing this package imports no ROS module (the worker processes of the wavefront node
import only :mod:`cwfs_ros.core`).
"""
