"""The live machinery without ROS: image decoding, visit pairing and assembly, corner jobs.

* :mod:`.images`: decoding of ``sensor_msgs/Image`` payloads with their pixel checks;
* :mod:`.visits`: image records, the pairing buffer and the visit assembler;
* :mod:`.corner_pool`: corner jobs (stamp or frame) and the worker pool that runs them;
* :mod:`.shared_frames`: a frames job's frames handed to its worker in shared memory;
* :mod:`.pipeline`: wavefront_node's decisions from image to visit vector, which the node and
  the offline replay both call;
* :mod:`.workload`: the workers' measured costs and caches, the visit-timeout promise and
  the cost-balanced assignment of corners to workers.

The ROS nodes (:mod:`cwfs_ros.ros`) and the offline replay (:mod:`cwfs_ros.cli.replay`)
both drive these; nothing here imports rclpy.
"""

from cwfs_ros.runtime.corner_pool import CornerJob, CornerOutcome, CornerPool, run_corner_job
from cwfs_ros.runtime.images import decode_checked
from cwfs_ros.runtime.visits import ImageRecord, PairingBuffer, VisitAssembler, VisitVector
from cwfs_ros.runtime.workload import WorkloadMonitor, balanced_affinity

__all__ = ["CornerJob", "CornerOutcome", "CornerPool", "ImageRecord", "PairingBuffer",
           "VisitAssembler", "VisitVector", "WorkloadMonitor", "balanced_affinity",
           "decode_checked", "run_corner_job"]
