"""``ros2``-shaped graph tools for a venv-only install: topic, param and node commands.

The ROS 2 wheels on PyPI carry rclpy but not the ``ros2`` command line, so a running graph
(``cwfs-ros bringup``, a camera driver, a bag being played) could only be inspected with
hand-written rclpy scripts.  These commands are the everyday subset of ``ros2``, with its
output formats:

* ``cwfs-ros topic list [-t]``, ``topic echo TOPIC [--once | -n N]`` (each message as YAML,
  followed by ``---``; arrays and strings cut at 128 items unless ``--full-length``),
  ``topic hz TOPIC`` (``average rate: ...`` then ``min/max/std dev/window`` once a second);
* ``cwfs-ros param list NODE [--param-type]``, ``param get NODE NAME`` (``Double value is:
  0.18``), ``param set NODE NAME VALUE`` (the value read as YAML, as ``ros2 param set`` does),
  ``param dump NODE`` (a parameter file: ``/NODE: ros__parameters: ...``);
* ``cwfs-ros node list [-a]``;
* ``cwfs-ros lifecycle get NODE`` (``active [3]``), ``lifecycle set NODE TRANSITION``
  (``Transitioning successful``), ``lifecycle list NODE`` (the transitions available now,
  each as ``- activate [3]`` with its start and goal states), through the node's
  ``lifecycle_msgs`` services.

Each command runs its own hidden node (``_cwfs_ros_cli_<pid>``) on the domain of
``ROS_DOMAIN_ID``; there is no daemon, so a command first waits for discovery: up to
``--timeout`` seconds for the node or topic it names; a list, ``--spin-time`` seconds and
until another node is known and the graph has not changed for 0.75 s (at most 4 s more).
A graph started isolated (``cwfs-ros demo``; ``bringup --sim`` without ``--visible``) is
not visible to these tools by design.

Exit status: 0 done; 1 the node or topic was not found, a parameter was not set, a
transition is not available or failed, or no message came within ``--timeout`` (each with
one line on stderr saying which); 2 usage.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import yaml

from cwfs_ros.argtypes import nonnegative_float, positive_float, positive_int
from cwfs_ros.errors import ToolError
from cwfs_ros.ros.params import close_match, parse_parameter_text

__all__ = [
    "EXIT_NOT_FOUND",
    "ToolError",
    "add_node_list_arguments",
    "add_lifecycle_parser",
    "add_param_parser",
    "add_topic_parser",
    "hz_report",
    "message_to_yaml",
    "node_list",
    "to_yaml_value",
]

EXIT_NOT_FOUND = ToolError.exit_code
DEFAULT_TRUNCATE = 128  # ros2 topic echo's default --truncate-length
# Default --timeout: a new participant finds a node's services within a second on an idle
# host, but several seconds later while the graph's workers build their caches; the wait
# ends as soon as the node or topic is there.
DEFAULT_WAIT_S = 10.0
_TOOL_NODE_PREFIX = "_cwfs_ros_cli_"


# ------------------------------------------------------------------------------ graph node
@contextmanager
def graph_node() -> Iterator[tuple[Any, Any]]:
    """A hidden rclpy node and a single-threaded executor on ``ROS_DOMAIN_ID``'s domain."""
    from cwfs_ros.ros.dds import ensure_fastdds_profile

    # The same transport settings as the nodes (large images over shared memory).
    ensure_fastdds_profile()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    node = executor = None
    try:
        node = rclpy.create_node(f"{_TOOL_NODE_PREFIX}{os.getpid()}", context=ctx,
                                 start_parameter_services=False, enable_rosout=False)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        yield node, executor
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


# Without a daemon each command discovers the graph afresh.  FastDDS re-announces a
# participant every 3 s, so one whose first announcements were missed is seen within ~3 s.
_DISCOVERY_GRACE_S = 4.0
_STABLE_S = 0.75


def _settle(executor: Any, view: Callable[[], Any], spin_time_s: float,
            found: Callable[[Any], bool]) -> Any:
    """The graph as ``view()`` lists it, once ``spin_time_s`` has passed, ``found(view)``
    holds (another node is known) and the view has not changed for ``_STABLE_S``; at most
    ``spin_time_s + _DISCOVERY_GRACE_S`` (an empty graph takes that long)."""
    t0 = time.monotonic()
    last, since = view(), t0
    while True:
        now = time.monotonic()
        if now - t0 >= spin_time_s + _DISCOVERY_GRACE_S or (
                now - t0 >= spin_time_s and found(last) and now - since >= _STABLE_S):
            return last
        executor.spin_once(timeout_sec=0.05)
        current = view()
        if current != last:
            last, since = current, time.monotonic()


def _others(node: Any) -> Callable[[Any], bool]:
    own = f"/{node.get_name()}"
    return lambda names: any(n != own for n in names)


def _wait_until(executor: Any, cond: Callable[[], Any], timeout_s: float) -> Any:
    """Spin until ``cond()`` is truthy (its value) or ``timeout_s`` passes (None)."""
    t_end = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value or time.monotonic() >= t_end:
            return value or None
        executor.spin_once(timeout_sec=0.05)


def absolute_name(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def _node_names(node: Any, include_hidden: bool = False) -> list[str]:
    out = []
    for name, ns in node.get_node_names_and_namespaces():
        if name.startswith("_") and not include_hidden:
            continue
        out.append(f"{ns.rstrip('/')}/{name}")
    return sorted(set(out))


def _wait_for_node(node: Any, executor: Any, name: str, timeout_s: float) -> str:
    full = absolute_name(name)
    if not _wait_until(executor, lambda: full in _node_names(node, True), timeout_s):
        raise ToolError(f"node {full} not found (waited {timeout_s:g} s; is it running on "
                        f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0') or '0'}?)")
    return full


# ------------------------------------------------------------------------------ node list
def node_list(include_hidden: bool, spin_time_s: float) -> int:
    with graph_node() as (node, executor):
        others = _others(node)
        names = _settle(executor, lambda: _node_names(node, True), spin_time_s, others)
        for name in names:
            if include_hidden or not name.rsplit("/", 1)[-1].startswith("_"):
                print(name)
    return 0


def add_node_list_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``node list`` on the parser of ``cwfs-ros node``."""
    p.add_argument("-a", "--all", action="store_true",
                   help="node list: include hidden nodes (names starting with _)")
    p.add_argument("--spin-time", type=nonnegative_float, default=1.0, metavar="S",
                   help="node list: seconds of discovery before listing (default: 1)")


# -------------------------------------------------------------------------- message YAML
def to_yaml_value(value: Any, truncate: int | None, no_arr: bool, no_str: bool) -> Any:
    """A message field as ``ros2 topic echo`` shows it: nested messages as mappings, arrays
    as lists cut after ``truncate`` items with a ``'...'`` item, numpy scalars as numbers."""
    if hasattr(value, "get_fields_and_field_types"):
        return message_to_dict(value, truncate, no_arr, no_str)
    if isinstance(value, (bytes, str)):
        text = value if isinstance(value, str) else "".join(chr(c) for c in value)
        if no_str:
            return f"<string length: <{len(text)}>>"
        return text[:truncate] + "..." if truncate and len(text) > truncate else text
    if hasattr(value, "__len__") and not isinstance(value, dict):  # list, array, ndarray
        if no_arr:
            return f"<sequence type: {type(value).__name__}, length: {len(value)}>"
        items = list(value[:truncate]) if truncate and len(value) > truncate else list(value)
        out = [to_yaml_value(v, truncate, no_arr, no_str) for v in items]
        return out + ["..."] if truncate and len(value) > truncate else out
    if hasattr(value, "item"):  # numpy scalar
        return value.item()
    return value


def message_to_dict(msg: Any, truncate: int | None = DEFAULT_TRUNCATE, no_arr: bool = False,
                    no_str: bool = False) -> dict[str, Any]:
    return {name: to_yaml_value(getattr(msg, name), truncate, no_arr, no_str)
            for name in msg.get_fields_and_field_types()}


def message_to_yaml(msg: Any, truncate: int | None = DEFAULT_TRUNCATE, no_arr: bool = False,
                    no_str: bool = False) -> str:
    """``ros2 topic echo``'s YAML of one message (field order kept)."""
    return yaml.dump(message_to_dict(msg, truncate, no_arr, no_str), sort_keys=False,
                     allow_unicode=True, width=sys.maxsize, default_flow_style=False)


def _message_class(type_name: str) -> type:
    parts = type_name.split("/")
    try:
        if len(parts) != 3:
            raise ImportError
        return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])
    except (ImportError, AttributeError):
        raise ToolError(f"message type {type_name} is not installed in this environment"
                        ) from None


def _topic_type(node: Any, executor: Any, topic: str, timeout_s: float) -> str:
    def types() -> list[str] | None:
        return dict(node.get_topic_names_and_types()).get(topic)

    found = _wait_until(executor, types, timeout_s)
    if not found:
        raise ToolError(f"topic {topic} not found (waited {timeout_s:g} s): no publisher "
                        "or subscriber is known on it")
    return found[0]


def _matching_qos(node: Any, topic: str) -> Any:
    """Reliable and transient-local only where every publisher offers it (as ros2 does):
    a reliable request would never hear a best-effort publisher."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    infos = node.get_publishers_info_by_topic(topic)
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    latched = bool(infos) and all(
        i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSProfile(depth=10,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def _field_of(msg: Any, path: str | None) -> Any:
    for part in (path.split(".") if path else []):
        if not hasattr(msg, part):
            raise ToolError(f"the message has no field {part!r} (of --field {path})")
        msg = getattr(msg, part)
    return msg


def topic_echo(args: argparse.Namespace) -> int:
    topic = absolute_name(args.topic)
    count = 1 if args.once else args.times
    truncate = None if args.full_length else args.truncate_length
    with graph_node() as (node, executor):
        cls = _message_class(args.type or _topic_type(node, executor, topic, args.timeout))
        _wait_until(executor, lambda: node.get_publishers_info_by_topic(topic), args.timeout)
        received: list[int] = []

        def show(msg: Any) -> None:
            if count is not None and len(received) >= count:
                return
            received.append(1)
            value = to_yaml_value(_field_of(msg, args.field), truncate, args.no_arr,
                                  args.no_str)
            text = (yaml.dump(value, sort_keys=False, allow_unicode=True, width=sys.maxsize,
                              default_flow_style=False) if isinstance(value, (dict, list))
                    else f"{value}\n")
            sys.stdout.write(text + "---\n")
            sys.stdout.flush()

        node.create_subscription(cls, topic, show, _matching_qos(node, topic))
        t_end = None if args.wait is None else time.monotonic() + args.wait
        while count is None or len(received) < count:
            if t_end is not None and time.monotonic() > t_end:
                raise ToolError(f"{topic}: {len(received)} of {count} message(s) within "
                                f"{args.wait:g} s")
            executor.spin_once(timeout_sec=0.1)
    return 0


# --------------------------------------------------------------------------------- hz
def hz_report(stamps_ns: list[int]) -> str | None:
    """``ros2 topic hz``'s two lines for receive times ``stamps_ns`` (None below two)."""
    if len(stamps_ns) < 2:
        return None
    deltas = [b - a for a, b in zip(stamps_ns, stamps_ns[1:], strict=False)]
    n = len(deltas)
    mean = sum(deltas) / n
    rate = 1.0 / mean if mean > 0 else 0.0
    std = math.sqrt(sum((d - mean) ** 2 for d in deltas) / n)
    return (f"average rate: {rate * 1e9:.3f}\n\tmin: {min(deltas) * 1e-9:.3f}s max: "
            f"{max(deltas) * 1e-9:.3f}s std dev: {std * 1e-9:.5f}s window: {n + 1}")


def topic_hz(args: argparse.Namespace) -> int:
    topic = absolute_name(args.topic)
    with graph_node() as (node, executor):
        cls = _message_class(args.type or _topic_type(node, executor, topic, args.timeout))
        _wait_until(executor, lambda: node.get_publishers_info_by_topic(topic), args.timeout)
        stamps: list[int] = []
        # Raw: the rate of 8 MB images is measured without deserialising them.
        node.create_subscription(
            cls, topic, lambda _m: stamps.append(time.monotonic_ns()),
            _matching_qos(node, topic), raw=True)
        reports, seen, next_print = 0, 0, time.monotonic() + 1.0
        while args.reports is None or reports < args.reports:
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() < next_print:
                continue
            next_print += 1.0
            del stamps[:-args.window]
            text = hz_report(stamps) if len(stamps) != seen else None
            seen = len(stamps)
            print(text or "no new messages", flush=True)
            reports += text is not None
    return 0


# ------------------------------------------------------------------------------- list
def topic_list(args: argparse.Namespace) -> int:
    with graph_node() as (node, executor):
        # Nodes in the view too: their topics follow them in discovery.
        others = _others(node)
        _, topics = _settle(executor, lambda: (_node_names(node, True),
                                               sorted(node.get_topic_names_and_types())),
                            args.spin_time, lambda view: others(view[0]))
        for name, types in topics:
            print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return 0


def add_topic_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``topic list|echo|hz`` (sets ``func``)."""
    p = subparsers.add_parser("topic", help="inspect topics of a running graph (list, echo, hz)",
                              description="Inspect the topics of a running ROS 2 graph, as "
                                          "`ros2 topic` does (domain: ROS_DOMAIN_ID).")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    lst = verbs.add_parser("list", help="print the topics")
    lst.add_argument("-t", "--show-types", action="store_true", help="print their types too")
    lst.add_argument("--spin-time", type=nonnegative_float, default=1.0, metavar="S",
                     help="seconds of discovery before listing (default: 1)")
    lst.set_defaults(func=topic_list)
    for verb, helptext, func in (("echo", "print messages as YAML", topic_echo),
                                 ("hz", "print the receive rate", topic_hz)):
        v = verbs.add_parser(verb, help=helptext)
        v.add_argument("topic", metavar="TOPIC")
        v.add_argument("type", metavar="TYPE", nargs="?",
                       help="message type, e.g. cwfs_msgs/msg/CornerWavefront "
                            "(default: the graph's)")
        v.add_argument("--timeout", type=positive_float, default=DEFAULT_WAIT_S, metavar="S",
                       help=f"seconds to wait for the topic to appear "
                            f"(default: {DEFAULT_WAIT_S:g})")
        v.set_defaults(func=func)
        if verb == "hz":
            v.add_argument("-w", "--window", type=positive_int, default=10000,
                           help="messages in the statistics' window (default: 10000)")
            v.add_argument("-n", "--reports", type=positive_int, metavar="N",
                           help="exit after N reports (default: until interrupted)")
            continue
        v.add_argument("--once", action="store_true", help="print one message and exit")
        v.add_argument("-n", "--times", type=positive_int, metavar="N",
                       help="print N messages and exit")
        v.add_argument("--wait", type=positive_float, metavar="S",
                       help="with --once/-n: fail (exit 1) unless they come within S s")
        v.add_argument("--field", metavar="NAME[.NAME]",
                       help="print only this field of each message")
        v.add_argument("-l", "--truncate-length", type=positive_int, default=DEFAULT_TRUNCATE,
                       help="cut arrays and strings after this many items (default: 128)")
        v.add_argument("-f", "--full-length", action="store_true",
                       help="print arrays and strings in full")
        v.add_argument("--no-arr", action="store_true", help="print arrays as their length")
        v.add_argument("--no-str", action="store_true", help="print strings as their length")
    return p


# ------------------------------------------------------------------------------- params
def _param_client(node: Any, executor: Any, service: str, srv_type: type,
                  timeout_s: float) -> Any:
    client = node.create_client(srv_type, service)
    if not _wait_until(executor, client.service_is_ready, timeout_s):
        raise ToolError(f"service {service} is not available (waited {timeout_s:g} s)")
    return client


def _call(node: Any, executor: Any, service: str, srv_type: type, request: Any,
          timeout_s: float) -> Any:
    client = _param_client(node, executor, service, srv_type, timeout_s)
    future = client.call_async(request)
    executor.spin_until_future_complete(future, timeout_sec=timeout_s)
    if not future.done() or future.result() is None:
        raise ToolError(f"service {service} did not answer within {timeout_s:g} s")
    return future.result()


def _list_names(node: Any, executor: Any, full: str, timeout_s: float) -> list[str]:
    from rcl_interfaces.srv import ListParameters

    resp = _call(node, executor, f"{full}/list_parameters", ListParameters,
                 ListParameters.Request(), timeout_s)
    return sorted(resp.result.names)


def _get_values(node: Any, executor: Any, full: str, names: list[str],
                timeout_s: float) -> list[Any]:
    from rcl_interfaces.srv import GetParameters

    resp = _call(node, executor, f"{full}/get_parameters", GetParameters,
                 GetParameters.Request(names=names), timeout_s)
    return list(resp.values)


_LABELS = {1: ("Boolean value is:", "bool_value"), 2: ("Integer value is:", "integer_value"),
           3: ("Double value is:", "double_value"), 4: ("String value is:", "string_value"),
           5: ("Byte values are:", "byte_array_value"),
           6: ("Boolean values are:", "bool_array_value"),
           7: ("Integer values are:", "integer_array_value"),
           8: ("Double values are:", "double_array_value"),
           9: ("String values are:", "string_array_value")}
_TYPE_NAMES = {0: "not set", 1: "boolean", 2: "integer", 3: "double", 4: "string",
               5: "byte array", 6: "boolean array", 7: "integer array", 8: "double array",
               9: "string array"}


def plain_value(pv: Any) -> Any:
    """A ParameterValue as a Python value (arrays as lists; None when not set)."""
    if pv.type not in _LABELS:
        return None
    value = getattr(pv, _LABELS[pv.type][1])
    return list(value) if pv.type >= 5 else value


def param_list(args: argparse.Namespace) -> int:
    from rcl_interfaces.srv import DescribeParameters

    with graph_node() as (node, executor):
        full = _wait_for_node(node, executor, args.node, args.timeout)
        names = _list_names(node, executor, full, args.timeout)
        kinds: dict[str, str] = {}
        if args.param_type:
            resp = _call(node, executor, f"{full}/describe_parameters", DescribeParameters,
                         DescribeParameters.Request(names=names), args.timeout)
            kinds = {d.name: _TYPE_NAMES.get(d.type, str(d.type)) for d in resp.descriptors}
        for name in names:
            print(f"  {name} (type: {kinds[name]})" if args.param_type else f"  {name}")
    return 0


def param_get(args: argparse.Namespace) -> int:
    with graph_node() as (node, executor):
        full = _wait_for_node(node, executor, args.node, args.timeout)
        values = _get_values(node, executor, full, [args.name], args.timeout)
        names = [] if values and values[0].type in _LABELS else _list_names(
            node, executor, full, args.timeout)
    if not values or values[0].type not in _LABELS:
        raise ToolError(f"{full}: parameter {args.name} not set (the node declares no such "
                        f"parameter{close_match(args.name, names)})")
    value = plain_value(values[0])
    print(value if args.hide_type else f"{_LABELS[values[0].type][0]} {value}")
    return 0


def parameter_value(text: str) -> Any:
    """The ``rcl_interfaces/ParameterValue`` of ``param set``'s VALUE: YAML as ``ros2 param
    set`` reads it, except that a number with an exponent YAML 1.1 takes for text (1e-3,
    1.0e308) is a double, as rcl reads it in a file or a ``-p`` override."""
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rclpy.parameter import get_parameter_value

    try:
        parsed = parse_parameter_text(text)
    except yaml.YAMLError:  # not YAML (a tab, an unclosed quote): the text itself, as ros2
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=text)
    if isinstance(parsed, dict):  # rclpy would fail on it while sending
        raise ToolError(f"VALUE {text!r} is a YAML mapping: a parameter takes a bool, an "
                        "integer, a double, a string or a list of one of them (quote text "
                        f"that YAML would read otherwise: \"'{text}'\")")
    value = get_parameter_value(string_value=text)
    if value.type == ParameterType.PARAMETER_STRING and isinstance(parsed, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=parsed)
    return value


def param_set(args: argparse.Namespace) -> int:
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.srv import SetParameters

    with graph_node() as (node, executor):
        full = _wait_for_node(node, executor, args.node, args.timeout)
        request = SetParameters.Request(parameters=[ParameterMsg(
            name=args.name, value=parameter_value(args.value))])
        resp = _call(node, executor, f"{full}/set_parameters", SetParameters, request,
                     args.timeout)
        result = resp.results[0]
        if not result.successful and "undeclared" in result.reason:
            # rclpy's reason names no parameter: name it, and the nearest declared one.
            names = _list_names(node, executor, full, args.timeout)
            raise ToolError(f"Set parameter failed: {full} declares no parameter "
                            f"{args.name!r}{close_match(args.name, names)}")
    if not result.successful:
        hint = ""
        if "Type.DOUBLE" in result.reason and "Type.INTEGER" in result.reason:
            hint = f" (a double is written with a point: {args.value}.0)"
        raise ToolError("Set parameter failed" + (f": {result.reason}" if result.reason else "")
                        + hint)
    print("Set parameter successful")
    return 0


def _nest(out: dict[str, Any], dotted: str, value: Any) -> None:
    head, _, rest = dotted.partition(".")
    if rest:
        _nest(out.setdefault(head, {}), rest, value)
    else:
        out[head] = value


def param_dump(args: argparse.Namespace) -> int:
    with graph_node() as (node, executor):
        full = _wait_for_node(node, executor, args.node, args.timeout)
        names = _list_names(node, executor, full, args.timeout)
        values = _get_values(node, executor, full, names, args.timeout)
    params: dict[str, Any] = {}
    for name, pv in zip(names, values, strict=True):
        _nest(params, name, plain_value(pv))
    print(yaml.dump({full: {"ros__parameters": params}}, default_flow_style=False))
    return 0


def add_param_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``param list|get|set|dump`` (sets ``func``)."""
    p = subparsers.add_parser("param", help="list, get, set or dump a running node's parameters",
                              description="Read and change the parameters of a running node, "
                                          "as `ros2 param` does (domain: ROS_DOMAIN_ID).")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    spec = {"list": ("list the parameters", param_list, ()),
            "get": ("print a parameter's value", param_get, ("name",)),
            "set": ("set a parameter (VALUE read as YAML: true, 0.2, [1, 2], text)",
                    param_set, ("name", "value")),
            "dump": ("print every parameter as a parameter file", param_dump, ())}
    for verb, (helptext, func, positionals) in spec.items():
        v = verbs.add_parser(verb, help=helptext, description=helptext)
        v.add_argument("node", metavar="NODE", help="node name, e.g. ofc_node or /ofc_node")
        for name in positionals:
            v.add_argument(name, metavar=name.upper())
        v.add_argument("--timeout", type=positive_float, default=DEFAULT_WAIT_S, metavar="S",
                       help=f"seconds to wait for the node and each answer "
                            f"(default: {DEFAULT_WAIT_S:g})")
        if verb == "list":
            v.add_argument("--param-type", action="store_true",
                           help="print each parameter's type")
        if verb == "get":
            v.add_argument("--hide-type", action="store_true",
                           help="print the value alone")
        v.set_defaults(func=func)
    return p


# ---------------------------------------------------------------------------- lifecycle
_SERVICES = {"get_state": "GetState", "get_available_transitions": "GetAvailableTransitions",
             "change_state": "ChangeState"}
_RESEND_S = 1.0


@contextmanager
def _lifecycle_clients(args: argparse.Namespace) -> Iterator[tuple[Any, str, dict[str, Any]]]:
    """The tool's executor, the node's full name and a ready client of each of its lifecycle
    services.  The clients are made together, so that the node discovers their endpoints
    together: the answer to the first query then says the others' answers can reach us."""
    import lifecycle_msgs.srv as srv

    with graph_node() as (node, executor):
        full = _wait_for_node(node, executor, args.node, args.timeout)
        clients = {name: node.create_client(getattr(srv, kind), f"{full}/{name}")
                   for name, kind in _SERVICES.items()}
        if not _wait_until(executor, lambda: all(c.service_is_ready()
                                                 for c in clients.values()), args.timeout):
            raise ToolError(f"{full} is not a managed (lifecycle) node: it offers no "
                            f"{full}/get_state (waited {args.timeout:g} s)")
        yield executor, full, clients


def _query(executor: Any, client: Any, request: Any, timeout_s: float) -> Any:
    """A read-only service's answer, the request sent again every second: a reply sent
    before the node has discovered this new process's reader is lost (rmw_fastrtps drops
    it), and a query is safe to repeat."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        future = client.call_async(request)
        executor.spin_until_future_complete(
            future, timeout_sec=min(_RESEND_S, max(0.0, t_end - time.monotonic())))
        if future.done() and future.result() is not None:
            return future.result()
        client.remove_pending_request(future)
    raise ToolError(f"service {client.srv_name} did not answer within {timeout_s:g} s")


def lifecycle_get(args: argparse.Namespace) -> int:
    from lifecycle_msgs.srv import GetState

    with _lifecycle_clients(args) as (executor, _, clients):
        resp = _query(executor, clients["get_state"], GetState.Request(), args.timeout)
    print(f"{resp.current_state.label} [{resp.current_state.id}]")
    return 0


def lifecycle_list(args: argparse.Namespace) -> int:
    from lifecycle_msgs.srv import GetAvailableTransitions

    with _lifecycle_clients(args) as (executor, _, clients):
        resp = _query(executor, clients["get_available_transitions"],
                      GetAvailableTransitions.Request(), args.timeout)
    for t in resp.available_transitions:
        print(f"- {t.transition.label} [{t.transition.id}]\n\tStart: {t.start_state.label}"
              f"\n\tGoal: {t.goal_state.label}")
    return 0


def lifecycle_set(args: argparse.Namespace) -> int:
    """Ask for a transition by label (or id), after checking it is available from the
    node's current state, so that a refusal names the state and the transitions there are.
    The change itself is sent once (a repeat could be a second transition)."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState

    want = args.transition
    with _lifecycle_clients(args) as (executor, full, clients):
        transitions = _query(executor, clients["get_available_transitions"],
                             GetAvailableTransitions.Request(),
                             args.timeout).available_transitions
        match = [t for t in transitions
                 if t.transition.label == want or str(t.transition.id) == want]
        if not match:
            start = (transitions[0].start_state.label if transitions else _query(
                executor, clients["get_state"], GetState.Request(),
                args.timeout).current_state.label)
            there = ", ".join(t.transition.label for t in transitions)
            raise ToolError(f"{full}: transition {want!r} is not available from state "
                            f"{start}; available: {there or 'none'}")
        future = clients["change_state"].call_async(ChangeState.Request(
            transition=Transition(id=match[0].transition.id, label=match[0].transition.label)))
        executor.spin_until_future_complete(future, timeout_sec=args.timeout)
        if not future.done() or future.result() is None:
            raise ToolError(f"{full} did not answer the {want} request within "
                            f"{args.timeout:g} s: it may or may not have changed state "
                            f"(`cwfs-ros lifecycle get {args.node}`)")
        ok = future.result().success
    if not ok:
        raise ToolError(f"Transitioning failed: {full} refused {want!r} (its log says why; "
                        f"`cwfs-ros lifecycle get {args.node}` shows the state it is in)")
    print("Transitioning successful")
    return 0


def add_lifecycle_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``lifecycle get|set|list`` (sets ``func``)."""
    p = subparsers.add_parser(
        "lifecycle", help="get or change the state of a managed node (get, set, list)",
        description="Read and change the lifecycle state of a managed node (wavefront_node, "
                    "ofc_node), as `ros2 lifecycle` does (domain: ROS_DOMAIN_ID). "
                    "Transitions: configure, activate, deactivate, cleanup, shutdown.")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    spec = {"get": ("print the current state, e.g. `active [3]`", lifecycle_get),
            "set": ("trigger a transition (configure, activate, deactivate, cleanup, "
                    "shutdown)", lifecycle_set),
            "list": ("print the transitions available from the current state",
                     lifecycle_list)}
    for verb, (helptext, func) in spec.items():
        v = verbs.add_parser(verb, help=helptext, description=helptext)
        v.add_argument("node", metavar="NODE", help="node name, e.g. ofc_node or /ofc_node")
        if verb == "set":
            v.add_argument("transition", metavar="TRANSITION",
                           help="transition label (or id)")
        v.add_argument("--timeout", type=positive_float, default=DEFAULT_WAIT_S, metavar="S",
                       help=f"seconds to wait for the node and each answer "
                            f"(default: {DEFAULT_WAIT_S:g})")
        v.set_defaults(func=func)
    return p
