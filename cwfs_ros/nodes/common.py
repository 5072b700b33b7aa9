"""Shared pieces of the cwfs_ros nodes: QoS, parameter descriptors, stamps, diagnostics.

QoS, chosen on purpose
----------------------
* Images (:data:`IMAGE_QOS`): RELIABLE, KEEP_LAST, depth 10. One lost image loses its whole
  corner for the visit, so the images must not be dropped by the transport (best-effort
  ``sensor_data`` QoS would). Each image topic carries one image per visit; a depth of 10 lets
  the subscriber absorb a burst of up to 10 visits (a bag replayed fast, a stalled executor)
  without loss, while KEEP_LAST (not KEEP_ALL) bounds memory and back-pressure if the node
  falls behind for good: the oldest images are then dropped and reported as unpaired. A
  RELIABLE subscription still matches a BEST_EFFORT camera publisher (the images then simply
  are best-effort). Large bursts need the FastDDS profile of ``config/fastdds_profile.xml``
  (16 MiB shared-memory segment), which the entry points load.
* Outputs (:data:`OUTPUT_QOS`): RELIABLE, KEEP_LAST 10, VOLATILE: every visit's result must
  reach the controller and recorders; stale corrections must not be replayed to a late joiner
  (a DoF correction is only meaningful for the telescope state it was computed against).
* ``/diagnostics`` (:data:`DIAGNOSTICS_QOS`): the ROS default (reliable, keep-last 10), as
  diagnostic aggregators expect.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Sequence

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = [
    "DIAGNOSTICS_QOS",
    "IMAGE_QOS",
    "OUTPUT_QOS",
    "RejectionCounter",
    "describe",
    "diagnostic_status",
    "diagnostics_array",
    "ns_to_stamp",
    "result",
    "stamp_to_ns",
]

IMAGE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
DIAGNOSTICS_QOS = QoSProfile(depth=10)

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR


def describe(description: str, *, read_only: bool = False,
             fp_range: tuple[float, float] | None = None,
             int_range: tuple[int, int] | None = None,
             constraints: str = "") -> ParameterDescriptor:
    """A ParameterDescriptor with a description and an optional numeric range."""
    d = ParameterDescriptor(description=description, read_only=read_only,
                            additional_constraints=constraints)
    if fp_range is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(fp_range[0]),
                                                     to_value=float(fp_range[1]), step=0.0)]
    if int_range is not None:
        d.integer_range = [IntegerRange(from_value=int(int_range[0]),
                                        to_value=int(int_range[1]), step=1)]
    return d


def result(ok: bool, reason: str = "") -> SetParametersResult:
    return SetParametersResult(successful=bool(ok), reason=reason)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=int(sec), nanosec=int(nsec))


class RejectionCounter:
    """Thread-safe counts of rejected inputs by reason, plus the last one."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.last_reason = ""
        self.last_message = ""
        self.last_time = 0.0

    def add(self, reason: str, message: str) -> None:
        with self._lock:
            self.counts[reason] += 1
            self.last_reason, self.last_message = reason, message
            self.last_time = time.monotonic()

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def recent(self, window_s: float) -> bool:
        with self._lock:
            return bool(self.counts) and time.monotonic() - self.last_time < window_s

    def key_values(self) -> list[tuple[str, str]]:
        with self._lock:
            out = [("rejected_total", str(sum(self.counts.values())))]
            out += [(f"rejected.{k}", str(v)) for k, v in sorted(self.counts.items())]
            out += [("last_rejection", self.last_message or "none")]
            return out


def diagnostic_status(name: str, level: bytes, message: str,
                      values: Sequence[tuple[str, object]], hardware_id: str = "") -> \
        DiagnosticStatus:
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v)) for k, v in values])


def diagnostics_array(stamp: Time, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    arr = DiagnosticArray()
    arr.header.stamp = stamp
    arr.status = list(statuses)
    return arr
