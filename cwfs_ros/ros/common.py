"""Shared pieces of the cwfs_ros nodes: QoS, parameter descriptors, stamps, diagnostics.

QoS, chosen on purpose
----------------------
* Images (:data:`IMAGE_QOS`): RELIABLE, KEEP_LAST, depth 10. One lost image loses its whole
  corner for the visit, so the images must not be dropped by the transport (best-effort
  ``sensor_data`` QoS would). Each image topic carries one image per visit; a depth of 10 lets
  the subscriber absorb a burst of up to 10 visits (a bag replayed fast, a stalled executor)
  without loss, while KEEP_LAST (not KEEP_ALL) bounds memory and back-pressure if the node
  falls behind for good: the oldest images are then dropped and reported as unpaired. A
  RELIABLE subscription does **not** match a BEST_EFFORT publisher (DDS: the offered
  reliability must be at least the requested one), so a camera driver publishing with
  ``sensor_data`` QoS would never be heard: the wavefront node reports such a publisher on
  /diagnostics (:class:`QosEventMonitor`) and its ``image_reliability`` parameter can be set
  to ``best_effort`` to match it. Large bursts need the FastDDS profile of
  ``config/fastdds_profile.xml`` (16 MiB shared-memory segment), which the entry points load.
* Outputs (:data:`OUTPUT_QOS`): RELIABLE, KEEP_LAST 10, VOLATILE: every visit's result must
  reach the controller and recorders; stale corrections must not be replayed to a late joiner
  (a DoF correction is only meaningful for the telescope state it was computed against).
* ``/diagnostics`` (:data:`DIAGNOSTICS_QOS`): the ROS default (reliable, keep-last 10), as
  diagnostic aggregators expect.
"""

from __future__ import annotations

import os
import re
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from functools import lru_cache
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = [
    "DIAGNOSTICS_QOS",
    "IMAGE_QOS",
    "ManagedNode",
    "NodeBasics",
    "OUTPUT_QOS",
    "GUARD_PARAMETERS",
    "ParameterAudit",
    "endpoint_label",
    "PublisherTrust",
    "QosEventMonitor",
    "image_qos",
    "RejectionCounter",
    "MAX_STRING_PARAM_LEN",
    "SequenceGaps",
    "bundled_declarer",
    "foreign_publishers",
    "refresh_foreign",
    "string_param_problem",
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
RELIABILITIES = ("reliable", "best_effort")


def image_qos(reliability: str = "reliable") -> QoSProfile:
    """:data:`IMAGE_QOS` with the given reliability (``reliable`` or ``best_effort``)."""
    if reliability not in RELIABILITIES:
        raise ValueError(f"image reliability must be one of {RELIABILITIES}, "
                         f"got {reliability!r}")
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=IMAGE_QOS.depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliability == "reliable"
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)

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


@lru_cache(maxsize=4)
def _bundled_params(path: str) -> dict[str, dict[str, Any]]:
    from cwfs_ros.ros.params import read_params_file

    return {key.lstrip("/"): values for key, values in read_params_file(path).items()}


# Safety guards: read-only, set at start only (config/params.yaml, --params, -p). The
# parameter services take a change from any process on the domain without saying which, so a
# guard that could be switched off at runtime would be no guard (docs/reliability.md, "Who may
# change a parameter"). Every other parameter stays changeable at runtime, and each change is
# logged and reported on /diagnostics (:class:`ParameterAudit`).
GUARD_PARAMETERS: dict[str, frozenset[str]] = {
    "wavefront_node": frozenset({"pairing_tolerance_s", "max_pending_mb", "max_future_s",
                                 "max_image_publishers"}),
    "ofc_node": frozenset({
        "controller", "matrix_source", "measurement_model", "allow_partial", "max_step_scale",
        "clip_to_range", "max_condition", "max_abs_zernike_nm", "max_future_s", "max_inconsistency",
        "min_visit_period_s", "refuse_repeats", "plausibility_margin_nm",
        "plausibility_n_sigma", "min_corner_rms_nm", "repeat_fraction", "repeat_floor_nm",
        "min_uncertainty_nm", "max_uncertainty_nm", "max_pairs", "rotator_angle_source",
        "vector_publishers"}),
    "camera_sim_node": frozenset({"correction_max_step_scale", "correction_publishers"}),
}
# Changed as part of routine operation (the seeing monitor sets the seeing every visit, the
# simulator's rotator follows the visit plan): logged and listed, but no WARN.
ROUTINE_PARAMETERS: dict[str, frozenset[str]] = {
    "wavefront_node": frozenset({"seeing_fwhm_arcsec"}),
    "camera_sim_node": frozenset({"rotator_angle_deg"}),
}
_GUARD_NOTE = (" Read-only: a safety guard, set at start only (params file or -p), never "
               "through the parameter services.")


def bundled_declarer(node: Any, section: str) -> Callable[[str, ParameterDescriptor], Any]:
    """``declare(name, descriptor)`` for ``node``, with the default value taken from the
    ``section`` of ``config/params.yaml``.

    That file is what every entry point loads, so it is the one place a default is written:
    a node built without it (a test, an embedding program) starts with the same values as
    ``cwfs-ros bringup`` (a literal beside each declaration had drifted: wavefront_node
    declared solver ``exp`` while the file set ``lsq``).  The descriptor's range fixes the
    type the file's YAML cannot: a number for a floating-point range is declared as a float
    (``5`` as 5.0: declared as an integer, the parameter would refuse a later 2.5), and a
    value of the wrong kind (``1e6`` is a string to YAML 1.1) is a ConfigError naming the
    file and the key, as is a parameter the file lacks.

    A parameter of :data:`GUARD_PARAMETERS` is declared read-only whatever its descriptor
    says, and every declared parameter is watched by the node's :class:`ParameterAudit`.
    """
    from cwfs_ros.errors import ConfigError
    from cwfs_ros.ros.params import default_params_file

    path = str(default_params_file())
    values = _bundled_params(path).get(section, {})
    guards = GUARD_PARAMETERS.get(section, frozenset())
    # (a stand-in node without parameter callbacks, as a test may pass, is not audited)
    audit = (ParameterAudit.of(node, ROUTINE_PARAMETERS.get(section, frozenset()))
             if hasattr(node, "add_post_set_parameters_callback") else None)

    def declare(name: str, descriptor: ParameterDescriptor) -> Any:
        where = f"{path}: {section}.{name}"
        if name not in values:
            raise ConfigError(f"{where} is missing: every declared parameter takes its "
                              "default from that file")
        value = values[name]
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if descriptor.floating_point_range:
            if not number:
                raise ConfigError(f"{where} must be a number, got {value!r}")
            value = float(value)
        elif descriptor.integer_range and not (number and isinstance(value, int)):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        if name in guards and not descriptor.read_only:
            descriptor.read_only = True
            descriptor.description += _GUARD_NOTE
        declared = node.declare_parameter(name, value, descriptor)
        if audit is not None and declared is not None:
            audit.watch(name, declared.value)
        return declared

    return declare


class ParameterAudit:
    """Every runtime change of a node's parameters, logged and reported on /diagnostics.

    The parameter services accept a change from any process on the domain and do not say
    which one sent it; the node can still say what changed. Each change is logged (WARN, INFO
    for the node's routine parameters) with the old and new value, counted, and, for
    :attr:`warn_s` seconds after it, raises the node's /diagnostics status to WARN naming the
    parameter and both values (:meth:`annotate`, applied by
    :meth:`NodeBasics.publish_diagnostics`). Safety guards are read-only instead
    (:data:`GUARD_PARAMETERS`).
    """

    warn_s = 60.0

    def __init__(self, node: Any, routine: frozenset[str] = frozenset()) -> None:
        self._node = node
        self._routine = routine
        self._lock = threading.Lock()
        self._known: dict[str, Any] = {}
        self.changes = 0
        self.last_change = ""
        self._last_warn: tuple[float, str] | None = None
        node.add_post_set_parameters_callback(self._after_set)

    @classmethod
    def of(cls, node: Any, routine: frozenset[str] = frozenset()) -> ParameterAudit:
        """The node's audit, made on first use."""
        audit = getattr(node, "_parameter_audit", None)
        if audit is None:
            audit = cls(node, routine)
            node._parameter_audit = audit
        return audit

    def watch(self, name: str, value: Any) -> None:
        """Start watching a declared parameter at its starting value."""
        with self._lock:
            self._known[name] = value

    def _after_set(self, params: Sequence[Any]) -> None:
        for p in params:
            with self._lock:
                if p.name not in self._known or _same_value(self._known[p.name], p.value):
                    continue  # a declaration, or a set to the value it had
                old, self._known[p.name] = self._known[p.name], p.value
                text = (f"parameter {p.name} changed at runtime: {_show_value(old)} -> "
                        f"{_show_value(p.value, old)}")
                self.changes += 1
                self.last_change = text
                if p.name not in self._routine:
                    self._last_warn = (time.monotonic(), text)
            # two call sites: rclpy refuses one call site logging at two severities
            if p.name in self._routine:
                self._node.get_logger().info(text)
            else:
                self._node.get_logger().warning(text)

    def warning(self) -> str | None:
        """The latest non-routine change if it is less than :attr:`warn_s` old, else None."""
        with self._lock:
            w = self._last_warn
        return w[1] if w is not None and time.monotonic() - w[0] < self.warn_s else None

    def annotate(self, status: DiagnosticStatus) -> DiagnosticStatus:
        """Add the counts to ``status``; raise an OK status to WARN after a recent change."""
        with self._lock:
            status.values += [KeyValue(key="parameter_changes", value=str(self.changes)),
                              KeyValue(key="last_parameter_change",
                                       value=self.last_change or "none")]
        w = self.warning()
        if w is not None and status.level == OK:
            status.level, status.message = WARN, w
        return status


def _same_value(a: Any, b: Any) -> bool:
    try:
        return bool(a == b) if not hasattr(a, "__len__") or isinstance(a, str) else \
            list(a) == list(b)
    except Exception:  # noqa: BLE001 - values of different kinds are different
        return False


def _show_value(value: Any, old: Any = None) -> str:
    """A parameter value for a log line: short; for a list, the entries that changed."""
    if isinstance(value, str):
        return repr(value if len(value) <= 80 else value[:77] + "...")
    if hasattr(value, "__len__"):
        new = list(value)
        if old is not None and hasattr(old, "__len__") and len(old) == len(new):
            diff = [f"[{i}] {old[i]!r}->{v!r}" for i, v in enumerate(new) if old[i] != v]
            return f"{len(new)} values, changed {', '.join(diff[:8])}" + (
                f" (+{len(diff) - 8} more)" if len(diff) > 8 else "")
        return f"{len(new)} values"
    return repr(value)


def result(ok: bool, reason: str = "") -> SetParametersResult:
    return SetParametersResult(successful=bool(ok), reason=reason)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=int(sec), nanosec=int(nsec))


class RejectionCounter:
    """Thread-safe counts of rejected inputs by reason, plus the last one.

    :meth:`log_due` throttles the log per reason: a flood of one reason would otherwise write
    a line per message, and one throttle shared by every reason (rclpy's
    ``throttle_duration_sec`` keeps one per call site) would hide a second reason under it.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.suppressed: Counter[str] = Counter()
        self.logged: Counter[str] = Counter()
        self._logged_at: dict[str, float] = {}
        self.last_reason = ""
        self.last_message = ""
        self.last_time = 0.0

    def log_due(self, reason: str, period_s: float) -> tuple[bool, int]:
        """(whether a line for ``reason`` may be logged now, lines suppressed since the last
        one). At most one line per reason per ``period_s`` (0: every one)."""
        now = time.monotonic()
        with self._lock:
            last = self._logged_at.get(reason)
            if period_s > 0 and last is not None and now - last < period_s:
                self.suppressed[reason] += 1
                return False, 0
            self._logged_at[reason] = now
            self.logged[reason] += 1
            n = self.suppressed.pop(reason, 0)
            return True, n

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


# Longest string parameter taken (frame_id, ...): a frame name is a few words; a megabyte
# would be copied into every message header.
MAX_STRING_PARAM_LEN = 256


# A frame_id as tf2 takes one: no leading slash, no empty segment, no spaces or escapes.
FRAME_ID = re.compile(r"[A-Za-z0-9_]+(/[A-Za-z0-9_]+)*")


def string_param_problem(name: str, value: object,
                         max_len: int = MAX_STRING_PARAM_LEN) -> str | None:
    """Why a string parameter value is refused (too long, control characters; a
    ``frame_id`` that is not a frame name, :data:`FRAME_ID`), or None."""
    if not isinstance(value, str):
        return None
    if len(value) > max_len:
        return f"{name} is {len(value)} characters long; at most {max_len} are taken"
    if any(ord(ch) < 32 for ch in value):
        return f"{name} must not hold control characters"
    if name.split(".")[-1] == "frame_id" and not FRAME_ID.fullmatch(value):
        return (f"{name} {value!r} is not a frame name: words of letters, digits and _, "
                f"joined by / (no leading /, as tf2 names frames)")
    return None


def endpoint_label(info: Any) -> str:
    """``/ns/node (gid 0f1e...)`` of a TopicEndpointInfo: the whole gid (its trailing zero
    padding cut), because a node name proves nothing and the last bytes alone are the
    endpoint's entity id, which two processes that create their endpoints in the same order
    share."""
    ns = str(info.node_namespace).rstrip("/")
    gid = bytes(info.endpoint_gid).hex().rstrip("0")[:32] or "0"
    return f"{ns}/{info.node_name} (gid {gid})"


def refresh_foreign(node: Any, topics: Sequence[str]) -> list[str]:
    """:func:`foreign_publishers` of ``node``'s ``topics``, logged when the list changes
    (a warning naming the new ones; a note when none are left), against ``node.foreign``."""
    new = foreign_publishers(node, topics)
    old = list(getattr(node, "foreign", []) or [])
    if new != old:
        added = [f for f in new if f not in old]
        if added:
            node.get_logger().warning(
                "another publisher on this node's outputs or under its name (consumers "
                "cannot tell its messages from this node's): " + "; ".join(added))
        elif not new:
            node.get_logger().info("no other publisher on this node's outputs any more")
    return new


def foreign_publishers(node: Any, topics: Sequence[str]) -> list[str]:
    """``"<topic>: <namespace>/<node> (gid ...)"`` for every publisher endpoint on ``topics``
    (this node's own outputs) that is not one of ``node``'s own publishers.

    Without DDS Security nothing stops another process from publishing on a topic this node
    owns; consumers cannot tell its messages from the node's, so the node names such
    publishers on /diagnostics. A node name proves nothing (any process may call its node
    ``ofc_node``): the endpoints named like this node are counted against the publishers it
    created on the topic, and any beyond them are reported too, with their endpoint gids.
    ``topics`` are names as the node created them (resolved here). Another node of the same
    name and namespace anywhere in the graph is named first: its parameter services and
    lifecycle services collide with this node's, so ``param set`` or ``lifecycle set`` may
    reach either.
    """
    me = (node.get_namespace().rstrip("/"), node.get_name())
    out = []
    try:
        same = sum(1 for n, ns in node.get_node_names_and_namespaces()
                   if (ns.rstrip("/"), n) == me)
    except Exception:  # noqa: BLE001 - a graph query must not break diagnostics
        same = 1
    if same > 1:
        out.append(f"node name: {same} nodes named {me[0]}/{me[1]} in the graph (another "
                   f"process under this node's name: parameter and lifecycle requests may "
                   f"reach either)")
    for t in topics:
        try:
            name = node.resolve_topic_name(t)
            infos = node.get_publishers_info_by_topic(name)
            own = sum(1 for p in node.publishers if p.topic_name == name)
        except Exception:  # noqa: BLE001 - a graph query must not break diagnostics
            continue
        named_me = [i for i in infos
                    if (str(i.node_namespace).rstrip("/"), str(i.node_name)) == me]
        out += [f"{name}: {endpoint_label(i)}" for i in infos if i not in named_me]
        if len(named_me) > own:
            out.append(f"{name}: {len(named_me)} endpoints named {me[0]}/{me[1]} for this "
                       f"node's {own} (another process under its name: "
                       f"{', '.join(endpoint_label(i) for i in named_me)})")
    return out[:1] + sorted(out[1:]) if same > 1 else sorted(out)


class PublisherTrust:
    """Whether a consumer may act on what arrives on its input topic: only while the topic
    has exactly the publishers it expects.

    rclpy's message info names no publisher, so a message cannot be traced to its sender.
    What the node can know is the topic's writers: DDS delivers no sample from a writer
    before discovery has matched it with this reader, and the reader's matched status counts
    every writer that ever matched (``total_count``), however briefly. A message is acted on
    only while the reader has exactly ``expected`` matched writers, the graph lists exactly
    that many publisher endpoints (whatever their node names), and no writer has matched
    since the publishers were last trusted that is not still listed: a writer that matched,
    sent and left before the message was taken is still counted (the writers matched ever,
    against the endpoint gids the graph lists now), while a restarted producer, whose new
    endpoint is listed in place of the old one, is trusted at once (the receiver cannot tell a
    restart from a replacement anyway). A writer that came and went is forgotten once the
    count has been ``expected`` (with ``at_most``: at most ``expected``) for :attr:`settle_s`.
    Anything else refuses the message (``untrusted_source``). The matched status is read
    when a message is taken and every :attr:`poll_s` on a timer, so that a writer that
    matched and left without sending (a camera process that ended between visits) is seen
    leaving, not first noticed when the next producer's first message arrives. It is read
    synchronously from an event handle of the subscription's own (no executor involved); a
    crashed publisher stays matched until its discovery lease expires
    (config/fastdds_profile.xml). ``expected`` 0 turns the check off. The queries read the
    local graph cache and the reader's status: a few microseconds each (docs/reliability.md).
    """

    settle_s = 2.0
    poll_s = 0.25  # the timer's period: a few microseconds a read

    def __init__(self, node: Any, topic: str, expected: int, at_most: bool = False) -> None:
        self._node = node
        self.topic = node.resolve_topic_name(topic)
        self.expected = int(expected)
        # at_most: fewer publishers than expected are fine (a camera or bag player that has
        # sent its last images and left); more, now or since last trusted, are not.
        self.at_most = bool(at_most)
        self.sub: Any = None
        self._event: Any = None
        self._timer: Any = None
        self._lock = threading.Lock()
        self._baseline: int | None = None  # writers ever matched when last trusted
        self._baseline_gids: set[bytes] = set()  # their endpoints then
        self._seen: tuple[int, int] | None = None  # (ever matched, matched) at the last poll
        self._changed_at = -1e9
        self._what = ""

    def attach(self, sub: Any, callback_group: Any = None) -> None:
        """Watch ``sub`` (the subscription of :attr:`topic`), also every :attr:`poll_s` on a
        timer of the node's in ``callback_group`` (None: the node's default group)."""
        from rclpy.event_handler import QoSSubscriptionEventType
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        self.sub = sub
        with sub.handle:
            self._event = _rclpy.EventHandle(
                sub.handle, QoSSubscriptionEventType.RCL_SUBSCRIPTION_MATCHED)
        if self.expected > 0:
            self._timer = self._node.create_timer(self.poll_s, self._poll_quietly,
                                                  callback_group=callback_group)

    def detach(self) -> None:
        """Release the timer and the event handle (before the subscription is destroyed)."""
        timer, self._timer = self._timer, None
        if timer is not None:
            self._node.destroy_timer(timer)
        with self._lock:
            event, self._event, self.sub = self._event, None, None
        if event is not None:
            event.destroy_when_not_in_use()

    def _poll_quietly(self) -> None:
        try:
            self._poll()
        except Exception:  # noqa: BLE001, S110 - the next message's check reads it again
            pass

    def _matched(self) -> tuple[int, int] | None:
        """(writers ever matched, writers matched now), read now."""
        event = self._event
        if event is None:
            return None
        with event:
            status = event.take_event()
        return None if status is None else (int(status.total_count),
                                            int(status.current_count))

    def _poll(self) -> tuple[int, int] | None:
        """Read the matched status and note a change of it (from a message's check and the
        timer: one reader of the event at a time)."""
        with self._lock:
            seen = self._matched()
            if seen is None:
                return None
            now = time.monotonic()
            first = self._seen is None
            changed = seen != self._seen and not (first and seen[0] == 0)
            if changed and self._baseline is None and seen[0] == seen[1] == self.expected:
                self._trust_now(seen[0])  # the first writers: none came and went
            elif changed:
                self._changed_at = now
                self._what = (f"the writers matched on {self.topic} changed "
                              f"({self._seen[1] if self._seen else 0} -> {seen[1]} now, "
                              f"{seen[0]} ever)")
            elif self._settled_count(seen[1]) and seen[0] != self._baseline and \
                    now - self._changed_at >= self.settle_s:
                self._trust_now(seen[0])
            self._seen = seen
        return seen

    def _settled_count(self, matched: int) -> bool:
        """Whether ``matched`` writers may become the trusted ones once settled: exactly
        ``expected``, or with ``at_most`` any number up to it (a camera that has left)."""
        return matched <= self.expected if self.at_most else matched == self.expected

    def _gids(self) -> set[bytes]:
        return {bytes(i.endpoint_gid)
                for i in self._node.get_publishers_info_by_topic(self.topic)}

    def _trust_now(self, total: int) -> None:
        """Take the writers matched now as the trusted ones (under the lock)."""
        self._baseline = total
        self._baseline_gids = self._gids()

    def _replaced_only(self, total: int) -> bool:
        """Whether every writer matched since the last trust is still listed (a restart or a
        replacement, not one that came and went); if so, trust them now."""
        with self._lock:
            if self._baseline is None:
                return False
            new = self._gids() - self._baseline_gids
            if total - self._baseline <= len(new):
                self._trust_now(total)
                return True
            return False

    def problem(self) -> str | None:
        """Why a message taken now must not be acted on, or None."""
        if self.expected <= 0:
            return None
        try:
            seen = self._poll()
            n_graph = int(self._node.count_publishers(self.topic))
        except Exception as exc:  # noqa: BLE001 - an unanswered query is no trust
            return f"the publishers of {self.topic} cannot be read: {exc}"
        n_matched = n_graph if seen is None else seen[1]
        if self.at_most:
            if n_graph > self.expected or n_matched > self.expected:
                return (f"{self.topic} has {n_graph} publisher(s) ({n_matched} matched), "
                        f"at most {self.expected} expected: {self.publishers()}")
            if seen is not None and seen[0] <= self.expected:
                return None  # never more writers than expected matched
        elif n_graph != self.expected or n_matched != self.expected:
            return (f"{self.topic} has {n_graph} publisher(s) ({n_matched} matched), "
                    f"expected exactly {self.expected}: {self.publishers()}")
        with self._lock:
            baseline, age, what = self._baseline, time.monotonic() - self._changed_at, \
                self._what
        if seen is not None and seen[0] != baseline and not self._replaced_only(seen[0]):
            return (f"{what} {age:.1f} s ago: a writer matched and left since the publishers "
                    f"were last trusted; trusted again once they have been exactly "
                    f"{self.expected} for {self.settle_s:g} s (now: {self.publishers()})")
        return None

    def excess(self) -> str | None:
        """``untrusted_source: ...`` while the graph lists more publishers on the topic than
        expected (the nodes' /diagnostics ERROR), else None."""
        n_pub = self._node.count_publishers(self.topic)
        if not n_pub > self.expected > 0:
            return None
        return (f"untrusted_source: {n_pub} publishers on {self.topic}, expected "
                f"{self.expected}: {self.publishers()}")

    def key_values(self, name: str) -> list[tuple[str, str]]:
        """/diagnostics values: the topic's publishers (as ``name``) and the last change of
        its matched writers within a minute."""
        return [(name, f"{self.publishers()} (expected {self.expected or 'any'})"),
                ("untrusted_recent", self.recent(60.0) or "none")]

    def recent(self, window_s: float) -> str | None:
        """The last change of the matched writers if within ``window_s``, else None."""
        try:
            self._poll()
        except Exception:  # noqa: BLE001 - diagnostics go on
            pass
        with self._lock:
            age, what = time.monotonic() - self._changed_at, self._what
        return f"{what} {age:.0f} s ago" if age < window_s else None

    def publishers(self) -> str:
        """The topic's publisher endpoints, for a message."""
        try:
            infos = self._node.get_publishers_info_by_topic(self.topic)
        except Exception:  # noqa: BLE001
            return "unknown"
        return ", ".join(endpoint_label(i) for i in infos) or "none"


class SequenceGaps:
    """Messages a subscription never took, from the publishers' sequence numbers.

    A RELIABLE KEEP_LAST reader whose queue overflows drops the oldest samples without any
    ``message_lost`` event (FastDDS reports none for them); each message's
    ``publication_sequence_number`` (rclpy's message info) still counts every sample its
    writer sent, so a forward jump of more than one is that many messages dropped. Counted
    from the first message taken: a reader that joins late sees a writer's numbers from
    where it is.

    The numbers are per writer, and rclpy's message info names no writer (no publisher gid:
    only the sequence numbers and timestamps). With one publisher matched the count is
    exact. A caller that passes the number of publishers matched (``publishers``, e.g.
    ``Subscription.get_publisher_count()``) gets an honest lower bound with several: a
    message taken while more than one is matched is not compared with any other (its
    number may be another writer's), and the next comparison starts afresh once one
    publisher is left; :attr:`unchecked` counts those messages and :attr:`exact` says
    whether there were any. Without ``publishers`` (None) every jump is counted, an
    estimate when several publishers share the topic.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: int | None = None
        self.dropped = 0
        self.unchecked = 0
        self.max_publishers = 0

    def note(self, info: Any, publishers: int | None = None) -> int:
        """Account one taken message; return how many were dropped just before it."""
        try:
            seq = int(info["publication_sequence_number"])
        except (TypeError, KeyError, ValueError):
            return 0
        with self._lock:
            if publishers is not None:
                self.max_publishers = max(self.max_publishers, int(publishers))
                if publishers > 1:
                    self._last = None
                    self.unchecked += 1
                    return 0
            last, self._last = self._last, seq
            gap = seq - last - 1 if last is not None and seq > last + 1 else 0
            self.dropped += gap
            return gap

    @property
    def exact(self) -> bool:
        """Whether every message taken was compared (one publisher matched throughout)."""
        return self.unchecked == 0

    def describe(self) -> str:
        """The count for /diagnostics, saying when it is only a lower bound."""
        if self.exact:
            return str(self.dropped)
        return (f"at least {self.dropped} ({self.unchecked} message(s) taken while up to "
                f"{self.max_publishers} publishers were matched are not counted: sequence "
                "numbers are per publisher and rclpy names none)")


def diagnostic_status(name: str, level: bytes, message: str,
                      values: Sequence[tuple[str, object]], hardware_id: str = "") -> \
        DiagnosticStatus:
    """A status whose last value is ``process`` (``host:pid``): two nodes run under one name
    publish statuses of one name, and this tells them apart."""
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v)) for k, v in values]
                            + [KeyValue(key="process",
                                        value=f"{socket.gethostname()}:{os.getpid()}")])


def diagnostics_array(stamp: Time, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    arr = DiagnosticArray()
    arr.header.stamp = stamp
    arr.status = list(statuses)
    return arr


class QosEventMonitor:
    """Counts and describes QoS events of a node's subscriptions and publishers.

    A QoS mismatch in DDS is silent: the two endpoints simply never connect. A message lost
    by the middleware (a reader that fell behind a best-effort writer) is silent too. This
    turns both into log lines and /diagnostics entries, so that a camera or controller that
    cannot be heard is reported instead of waited for.

    Use :meth:`subscription_callbacks` / :meth:`publisher_callbacks` as the
    ``event_callbacks`` argument of ``create_subscription`` / ``create_publisher``.
    """

    def __init__(self, logger) -> None:
        self._logger = logger
        self._lock = threading.Lock()
        self.incompatible: Counter[str] = Counter()
        self.lost: Counter[str] = Counter()
        self.last_problem = ""
        self._last_t = -1e9

    def _note(self, text: str) -> None:
        with self._lock:
            self.last_problem = text
            self._last_t = time.monotonic()
        self._logger.error(text)

    def subscription_callbacks(self, topic: str):
        from rclpy.event_handler import SubscriptionEventCallbacks

        def incompatible(event) -> None:
            with self._lock:
                self.incompatible[topic] += 1
            self._note(f"a publisher on {topic} offers a QoS incompatible with this "
                       f"subscription (policy {_policy_name(event.last_policy_kind)}): no "
                       "messages will arrive from it")

        def lost(event) -> None:
            with self._lock:
                self.lost[topic] += int(event.total_count_change)
            self._note(f"{event.total_count_change} message(s) lost on {topic} "
                       f"({event.total_count} in all)")

        return SubscriptionEventCallbacks(incompatible_qos=incompatible, message_lost=lost)

    def publisher_callbacks(self, topic: str):
        from rclpy.event_handler import PublisherEventCallbacks

        def incompatible(event) -> None:
            with self._lock:
                self.incompatible[topic] += 1
            self._note(f"a subscriber on {topic} requests a QoS this publisher does not "
                       f"offer (policy {_policy_name(event.last_policy_kind)}): it will "
                       "receive nothing")

        return PublisherEventCallbacks(incompatible_qos=incompatible)

    def problem(self) -> str | None:
        """The latest problem if any topic has an incompatible peer, else ``None``."""
        with self._lock:
            return self.last_problem if self.incompatible else None

    def recent(self, window_s: float) -> bool:
        with self._lock:
            return time.monotonic() - self._last_t < window_s

    def key_values(self) -> list[tuple[str, str]]:
        with self._lock:
            out = [(f"qos_incompatible.{t}", str(n)) for t, n in sorted(self.incompatible.items())]
            out += [(f"messages_lost.{t}", str(n)) for t, n in sorted(self.lost.items())]
        return out


def _policy_name(kind) -> str:
    name = getattr(kind, "name", str(kind))
    return name.replace("RMW_QOS_POLICY_", "").lower()


class NodeBasics:
    """What every cwfs_ros node does alike (a mixin for rclpy nodes): read a parameter, and
    publish its ``diagnostics()`` status on ``self.pub_diag`` without ever raising."""

    def _param(self, name: str):
        return self.get_parameter(name).value

    def publish_diagnostics(self) -> None:
        """Publish :meth:`diagnostics`, with the parameter changes of
        :class:`ParameterAudit` added."""
        try:
            status = self.diagnostics()
            audit = getattr(self, "_parameter_audit", None)
            if audit is not None:
                status = audit.annotate(status)
            self.pub_diag.publish(diagnostics_array(self.get_clock().now().to_msg(),
                                                    [status]))
        except Exception as exc:  # noqa: BLE001 - a diagnostics failure must not stop a node
            self.get_logger().error(f"diagnostics failed: {exc}")


class ManagedNode(NodeBasics, LifecycleNode):
    """A lifecycle node whose resources exist only between configure and cleanup.

    Subclasses declare their parameters and the always-on parts (/diagnostics, parameter
    callbacks) in ``__init__``, and build everything else in :meth:`_configure_resources`
    (read the parameters, start workers, load state, create the topics), released again by
    :meth:`_release_resources` on cleanup, shutdown or an error (``destroy_node`` stops only the
    worker processes, :meth:`_release_processes`; rclpy destroys the rest). rclpy turns
    an exception in a transition callback into a bare ERROR; here the exception of a failed
    configure is kept in :attr:`configure_error`, logged, and raised again by :meth:`start`,
    so that a node built and started in one go (``autostart``) fails with the reason, as a
    plain node failing in its constructor would.
    """

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.configure_error: BaseException | None = None
        self.configured = False

    # ------------------------------------------------------------------ subclass hooks
    def _configure_resources(self) -> None:
        """Read the parameters and build the node's resources (raise to refuse)."""
        raise NotImplementedError

    def _release_resources(self) -> None:
        """Release what :meth:`_configure_resources` built (also after a partial build)."""
        raise NotImplementedError

    def _release_processes(self) -> None:
        """Stop what outlives the node's ROS entities (worker processes); default: nothing.

        ``destroy_node`` calls only this: rclpy destroys the node's topics, timers and
        services itself, after the executor has stopped, so none is destroyed while a
        callback that is still finishing could use it.
        """

    # ------------------------------------------------------------------ state
    @property
    def lifecycle_state(self) -> str:
        """The lifecycle state's label: unconfigured, inactive, active, finalized, or a
        transition state such as deactivating."""
        return str(self._state_machine.current_state[1])

    @property
    def is_active(self) -> bool:
        return self.lifecycle_state == "active"

    def start(self, activate: bool = True) -> None:
        """Configure, then activate unless ``activate`` is False; raise why either failed."""
        if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
            raise self.configure_error or RuntimeError(f"{self.get_name()}: configure failed")
        if activate and self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
            raise RuntimeError(f"{self.get_name()}: activate failed")

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.configure_error = None
        try:
            self._configure_resources()
        except Exception as exc:  # noqa: BLE001 - kept and reported; the node stays unconfigured
            self.configure_error = exc
            self.get_logger().error(f"configure failed: {type(exc).__name__}: {exc}")
            self._release_quietly()
            return TransitionCallbackReturn.FAILURE
        self.configured = True
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_activate(state)  # enables the lifecycle publishers
        self.get_logger().info("active")
        return ret

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_deactivate(state)
        self.get_logger().info(f"inactive: {self._inactive_effect()}")
        return ret

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release_quietly()
        self.get_logger().info("unconfigured: resources released")
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release_quietly()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        # A transition raised: release everything and go back to unconfigured.
        self._release_quietly()
        return TransitionCallbackReturn.SUCCESS

    def _inactive_effect(self) -> str:
        """What an inactive node does not do, for the log and /diagnostics."""
        return "paused"

    def _release_quietly(self) -> None:
        self.configured = False
        try:
            self._release_resources()
        except Exception as exc:  # noqa: BLE001 - releasing must not fail a transition
            self.get_logger().error(f"releasing resources: {type(exc).__name__}: {exc}")

    def lifecycle_status(self, name: str, hardware_id: str) -> DiagnosticStatus | None:
        """The /diagnostics status of a node that is not configured, else None."""
        if self.configured:
            return None
        state = self.lifecycle_state
        if self.configure_error is not None:
            level, message = ERROR, (f"{state}: configure failed: "
                                     f"{type(self.configure_error).__name__}: "
                                     f"{self.configure_error}")
        else:
            level, message = WARN, f"{state}: not configured (no inputs taken, no outputs)"
        return diagnostic_status(name, level, message, [("lifecycle", state)],
                                 hardware_id=hardware_id)

    def destroy_node(self) -> None:
        self.configured = False
        try:
            self._release_processes()
        except Exception as exc:  # noqa: BLE001 - destroying must go on
            self.get_logger().error(f"releasing workers: {type(exc).__name__}: {exc}")
        super().destroy_node()
