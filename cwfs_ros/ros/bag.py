"""Record, play and inspect rosbag2 bags of the cwfs_ros graph (``cwfs-ros bag ...``).

The PyPI ROS 2 wheels have no ``ros2 bag`` and no ``rosbag2_py``, so this module provides the
three verbs, shaped like the ROS tools::

    cwfs-ros bag record OUT [TOPIC ...] [-a] [-s mcap|sqlite3] [--duration S] [--max-messages N]
    cwfs-ros bag play BAG [-r RATE] [--topics TOPIC ...] [-l] [-d DELAY]
    cwfs-ros bag info BAG

Bags are rosbag2 directories (``metadata.yaml`` + storage files, metadata version 9 as Jazzy's
recorder writes) in mcap (default) or sqlite3 storage, written and read with the pure-Python
``rosbags`` library:

* **record** subscribes with rclpy *raw* subscriptions (the CDR bytes as received, never
  deserialised) and writes those bytes. Each topic's stored message definition and RIHS01 type
  hash come from a rosbags type store holding ROS 2 Jazzy's standard types plus ``cwfs_msgs``
  registered from its ``.msg`` text (``msg_defs/msg/``), so a real ``ros2 bag`` can read the
  bag. The publishers' offered QoS profiles are stored as rosbag2 does. The bag timestamp of a
  message is its receive time (``MessageInfo.received_timestamp``, ns since the epoch).
* **play** republishes the stored CDR bytes (``Publisher.publish(bytes)``) with the original
  spacing of the receive timestamps (divided by ``--rate``), on publishers with the recorded
  reliability and durability.
* **info** summarises a bag like ``ros2 bag info``.

Reading (:func:`open_bag`) accepts bags of a real ``ros2 bag record`` too (metadata versions
1-9, mcap or sqlite3, service-event topics included). It uses rosbags' low-level
:class:`rosbags.rosbag2.Reader` (its ``AnyReader`` refuses bags with service-event topics) and
decodes with the message definitions stored in the bag, falling back to the Jazzy + cwfs_msgs
type store for types the bag stores no definition of. Every problem (no such path, not a bag,
truncated or corrupt storage, ``metadata.yaml`` disagreeing with the storage file, unknown or
mismatching types) is a :class:`BagError` with a one-line message; the command line reports it
with exit status 2.

rclpy is imported inside the functions that need it; importing this module costs only the
standard library (the ``--help`` of the command line stays fast, and the offline replay of
:mod:`cwfs_ros.cli.replay` never loads the middleware).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib
import queue
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, nullcontext, suppress
from dataclasses import dataclass, field
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

from cwfs_ros.argtypes import nonnegative_float as _nonnegative_float
from cwfs_ros.argtypes import positive_float as _positive_float
from cwfs_ros.argtypes import positive_int as _positive_int
from cwfs_ros.errors import BagError, CliError
from cwfs_ros.layout import CORNERS as _CORNERS
from cwfs_ros.layout import (
    CORRECTION_TOPIC,
    JOINT_TOPIC,
    TRUTH_TOPIC,
    VECTOR_TOPIC,
    absolute,
    corner_topic,
    image_topic,
)
from cwfs_ros.layout import SIDES as _SIDES

__all__ = [
    "DEFAULT_TOPICS",
    "STORAGES",
    "Bag",
    "BagError",
    "BagMessage",
    "PlaySummary",
    "RecordSummary",
    "Recorder",
    "TopicInfo",
    "add_bag_parser",
    "cwfs_typestore",
    "format_info",
    "msg_defs_dir",
    "open_bag",
    "play",
    "record",
    "rosidl_type_hash",
]

STORAGES: tuple[str, ...] = ("mcap", "sqlite3")

# Everything the cwfs_ros graph publishes (camera_sim_node, wavefront_node, ofc_node), with
# its type: what `bag record` records when no topic is named.
DEFAULT_TOPICS: dict[str, str] = {
    **{absolute(image_topic(c, s)): "sensor_msgs/msg/Image" for c in _CORNERS for s in _SIDES},
    **{absolute(corner_topic(c)): "cwfs_msgs/msg/CornerWavefront" for c in _CORNERS},
    absolute(VECTOR_TOPIC): "cwfs_msgs/msg/WavefrontVector",
    absolute(CORRECTION_TOPIC): "cwfs_msgs/msg/DofCorrection",
    absolute(TRUTH_TOPIC): "cwfs_msgs/msg/SimTruth",
    absolute(JOINT_TOPIC): "sensor_msgs/msg/JointState",
    # The managed nodes' lifecycle transitions: when the loop was paused or resumed.
    "/wavefront_node/transition_event": "lifecycle_msgs/msg/TransitionEvent",
    "/ofc_node/transition_event": "lifecycle_msgs/msg/TransitionEvent",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
# `bag play` plays topics of this type only when they are named (see play()).
CORRECTION_TYPE = "cwfs_msgs/msg/DofCorrection"

_SEPARATOR = "=" * 80  # between the sections of a concatenated rosbag2 message definition
_SRV_SUFFIXES = ("_Event", "_Request", "_Response")


# ----------------------------------------------------------------------------- type stores
def msg_defs_dir() -> Path:
    """Directory of the ``cwfs_msgs`` ``.msg`` files.

    The source tree's ``msg_defs/msg`` (an editable checkout), else the installed
    ``<prefix>/share/cwfs_msgs/msg``.
    """
    src = Path(__file__).resolve().parents[1] / "msg_defs" / "msg"
    if src.is_dir():
        return src
    return Path(sys.prefix) / "share" / "cwfs_msgs" / "msg"


@lru_cache(maxsize=1)
def cwfs_typestore() -> Any:
    """A rosbags type store: ROS 2 Jazzy's standard types plus ``cwfs_msgs`` (from .msg text).

    Shared and cached: do not register more types into it.
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    files = sorted(msg_defs_dir().glob("*.msg"))
    if not files:
        raise BagError(f"no cwfs_msgs message definitions (*.msg) in {msg_defs_dir()}")
    types: dict[str, Any] = {}
    for f in files:
        types.update(get_types_from_msg(f.read_text(encoding="utf-8"), f"cwfs_msgs/msg/{f.stem}"))
    store.register(types)
    return store


def _nested_names(desc: Any) -> list[str]:
    """Type names a rosbags field description refers to (nested messages)."""
    from rosbags.interfaces import Nodetype

    kind, rest = desc
    if kind == Nodetype.NAME:
        return [rest]
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _nested_names(rest[0])
    return []


def _closure(fielddefs: Mapping[str, Any], typename: str) -> tuple[set[str], set[str]]:
    """(types reachable from ``typename``, the ones among them ``fielddefs`` lacks)."""
    seen: set[str] = set()
    missing: set[str] = set()
    todo = [typename]
    while todo:
        name = todo.pop()
        if name in seen or name in missing:
            continue
        if name not in fielddefs:
            missing.add(name)
            continue
        seen.add(name)
        for _, desc in fielddefs[name][1]:
            todo += _nested_names(desc)
    return seen, missing


def _char_as_uint8(desc: Any) -> Any:
    """A field description with ``char`` replaced by ``uint8`` (recursively)."""
    if isinstance(desc, tuple):
        if desc == ("char", 0):
            return ("uint8", 0)
        return tuple(_char_as_uint8(d) for d in desc)
    return desc


def rosidl_type_hash(fielddefs: Mapping[str, Any], typename: str) -> str:
    """The RIHS01 type hash of ``typename`` as rosidl computes it.

    rosbags' own ``hash_rihs01`` agrees with rosidl except for ``char`` fields: rosidl maps the
    .msg ``char`` to IDL ``uint8`` before hashing (type id 3), rosbags 0.11.9 hashes it as
    FIELD_TYPE_CHAR (13). That matters for every service-event topic
    (``service_msgs/ServiceEventInfo.client_gid`` is ``char[16]``) and for any message with a
    ``char`` field; the wire format is the same byte either way.
    """
    from rosbags.typesys import Stores, get_typestore

    names, missing = _closure(fielddefs, typename)
    if missing:
        raise BagError(f"cannot hash {typename}: unknown nested type(s) {sorted(missing)}")
    store = get_typestore(Stores.EMPTY)
    store.register({n: (fielddefs[n][0], [(f, _char_as_uint8(d)) for f, d in fielddefs[n][1]])
                    for n in names})
    return store.hash_rihs01(typename)


def _renamed(obj: Any, names: Mapping[str, str]) -> Any:
    if isinstance(obj, str):
        return names.get(obj, obj)
    if isinstance(obj, tuple):
        return tuple(_renamed(o, names) for o in obj)
    if isinstance(obj, list):
        return [_renamed(o, names) for o in obj]
    return obj


def _service_types(pkg: str, base: str, text: str) -> dict[str, Any]:
    """The Request, Response and Event types of service ``pkg/srv/base`` from its .srv text.

    rosbag2 stores a service-event topic's definition as the service's ``.srv`` text (request
    ``---`` response, then any ``MSG:`` dependency sections). rosbags' .msg parser only names
    ``pkg/msg/...`` types, so the three are parsed under ``msg`` placeholder names and renamed.
    The Event layout is rosidl's: ``ServiceEventInfo info``, ``Request[<=1] request``,
    ``Response[<=1] response``.
    """
    from rosbags.typesys import get_types_from_msg

    main, sep, deps = text.partition("\n" + _SEPARATOR + "\n")
    parts = re.split(r"^---[ \t]*$", main, flags=re.MULTILINE)
    if len(parts) != 2:
        raise BagError(f"the stored definition of service {pkg}/srv/{base} is not "
                       "'request --- response'")
    dep_text = ("\n" + _SEPARATOR + "\n" + deps) if sep else ""
    placeholder = f"{pkg}/msg/{base}"
    types: dict[str, Any] = {}
    types.update(get_types_from_msg(parts[0] + dep_text, placeholder + "_Request"))
    types.update(get_types_from_msg(parts[1] + dep_text, placeholder + "_Response"))
    types.update(get_types_from_msg(
        "service_msgs/msg/ServiceEventInfo info\n"
        f"{placeholder}_Request[<=1] request\n{placeholder}_Response[<=1] response\n",
        placeholder + "_Event"))
    names = {placeholder + s: f"{pkg}/srv/{base}{s}" for s in _SRV_SUFFIXES}
    return {names.get(k, k): _renamed(v, names) for k, v in types.items()}


def _split_srv_type(msgtype: str) -> tuple[str, str] | None:
    """(pkg, service base name) of ``pkg/srv/Name_Event`` (or _Request, _Response), else None."""
    parts = msgtype.split("/")
    if len(parts) == 3 and parts[1] == "srv":
        for suffix in _SRV_SUFFIXES:
            if parts[2].endswith(suffix):
                return parts[0], parts[2][: -len(suffix)]
    return None


def _types_from_definition(msgtype: str, fmt: str, text: str) -> dict[str, Any]:
    """rosbags types from one stored definition (``fmt``: ``msg`` or ``idl``)."""
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    if fmt == "idl":
        types: dict[str, Any] = {}
        if text.startswith(_SEPARATOR + "\nIDL: "):
            for section in text.split(_SEPARATOR + "\n")[1:]:
                types.update(get_types_from_idl(section.split("\n", 1)[1]))
        else:
            types.update(get_types_from_idl(text))
        return types
    srv = _split_srv_type(msgtype)
    if srv is not None:
        return _service_types(srv[0], srv[1], text)
    return dict(get_types_from_msg(text, msgtype))


# ----------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag.

    Attributes:
        offered_qos: the publishers' offered QoS profiles as recorded (rosbags ``Qos``).
        type_hash: the recorded RIHS01 type hash (``""`` before metadata version 7).
        has_definition: the bag stores this type's message definition.
    """

    name: str
    type: str
    count: int
    serialization_format: str
    offered_qos: tuple[Any, ...]
    type_hash: str
    has_definition: bool

    @property
    def is_service_event(self) -> bool:
        return self.name.endswith("/_service_event") and _split_srv_type(self.type) is not None


@dataclass(frozen=True)
class BagMessage:
    """One stored message: its topic, type, bag timestamp (receive time, ns) and CDR bytes."""

    topic: str
    type: str
    timestamp_ns: int
    data: bytes


def _qos_text(profiles: Sequence[Any]) -> str:
    """Reliability and durability of the recorded offered QoS (history only when known)."""
    if not profiles:
        return "none recorded"
    q = profiles[0]
    parts = [q.reliability.name.lower(), q.durability.name.lower()]
    if q.history.name in ("KEEP_LAST", "KEEP_ALL"):
        parts.append(f"{q.history.name.lower()} {q.depth}")
    more = f" ({len(profiles)} publishers)" if len(profiles) > 1 else ""
    return ", ".join(parts) + more


class Bag:
    """An open rosbag2 bag (use :func:`open_bag`; a context manager).

    Attributes:
        path: the bag directory (or storage file).
        storage: ``mcap`` or ``sqlite3``.
        version: metadata version (None for a bare storage file).
        ros_distro: as recorded ("" if none).
        files: the storage files.
        start_ns, end_ns: bag timestamps of the first and last message (ns since the epoch;
            both 0 for an empty bag).
        message_count: messages in the bag.
        topics: :class:`TopicInfo` by topic name, in the bag's order.
    """

    def __init__(self, path: str | Path) -> None:
        from rosbags.rosbag2 import Reader

        self.path = Path(path)
        p = self.path
        if not p.exists():
            raise BagError(f"{p}: no such file or directory")
        if p.is_dir():
            if not (p / "metadata.yaml").is_file():
                raise BagError(f"{p}: not a rosbag2 bag (the directory has no metadata.yaml)")
        elif p.suffix not in (".mcap", ".db3"):
            raise BagError(f"{p}: not a rosbag2 bag (a bag is a directory with metadata.yaml, "
                           "or an .mcap / .db3 storage file)")
        self._meta = self._read_metadata() if p.is_dir() else {}
        try:
            self._reader = Reader(p)
            self._reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags, apsw, struct ...: report one line
            raise BagError(f"{p}: cannot read the bag: {_why(exc)}") from None
        self._open = True
        self._types: Any = None
        self._problems: dict[str, str] = {}
        try:
            self._check_consistency()
            self._describe()
        except BagError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001 - odd values in metadata.yaml
            self.close()
            raise BagError(f"{p}: invalid bag metadata: {_why(exc)}") from None
        except BaseException:
            self.close()
            raise

    # -- opening
    def _read_metadata(self) -> dict[str, Any]:
        import yaml

        f = self.path / "metadata.yaml"
        try:
            data = yaml.safe_load(f.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise BagError(f"{f}: cannot read the bag metadata: {_why(exc)}") from None
        info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
        if not isinstance(info, dict):
            raise BagError(f"{f}: not rosbag2 metadata (no rosbag2_bagfile_information)")
        return info

    def _layers(self) -> tuple[list[Any], list[Any]]:
        """(connections as listed by metadata.yaml, connections of the storage files)."""
        storage = self._reader.storage
        subs = getattr(storage, "storages", None)
        if subs is None:  # a bare .mcap / .db3: no metadata to disagree with
            return list(storage.connections), list(storage.connections)
        return list(storage.connections), [c for s in subs for c in s.connections]

    def _check_consistency(self) -> None:
        """metadata.yaml must describe what the storage holds.

        rosbags matches metadata topics to storage channels by topic, type, serialization and
        QoS; when they disagree it silently yields no messages. Refuse such a bag instead.
        """
        meta, stored = self._layers()
        where = f"{self.path}: metadata.yaml disagrees with the storage file"
        for m in meta:
            same = [s for s in stored if s.topic == m.topic and s.msgtype == m.msgtype]
            if not same:
                raise BagError(f"{where}: topic {m.topic} ({m.msgtype}) is not in the storage")
            match = [s for s in same if s.ext == m.ext
                     and (not s.digest or not m.digest or s.digest == m.digest)]
            if not match:
                raise BagError(f"{where}: topic {m.topic} has a different serialization "
                               "format, QoS profile or type hash there")
            n = sum(s.msgcount for s in match)
            if n != m.msgcount:
                raise BagError(f"{where}: {m.msgcount} messages on {m.topic} in metadata.yaml, "
                               f"{n} in the storage")
        for s in stored:
            if s.msgcount and not any(m.topic == s.topic for m in meta):
                raise BagError(f"{where}: the storage holds {s.msgcount} messages on {s.topic}, "
                               "which metadata.yaml does not list")
        total = self._meta.get("message_count")
        have = sum(s.msgcount for s in stored)
        if total is not None and int(total) != have:
            raise BagError(f"{where}: {total} messages in metadata.yaml, {have} in the storage")

    def _describe(self) -> None:
        from rosbags.interfaces import MessageDefinitionFormat

        r = self._reader
        self.storage = str(self._meta.get("storage_identifier")
                           or ("mcap" if self.path.suffix == ".mcap" else "sqlite3"))
        self.version = self._meta.get("version")
        self.ros_distro = str(self._meta.get("ros_distro") or r.ros_distro or "")
        if self.path.is_dir():
            self.files = [self.path / Path(f).name
                          for f in self._meta.get("relative_file_paths", [])]
        else:
            self.files = [self.path]
        self.compression = str(self._meta.get("compression_mode") or "")
        self.message_count = int(r.message_count)
        # rosbags reports end_time as one past the last message.
        self.start_ns = int(r.start_time) if self.message_count else 0
        self.end_ns = int(r.end_time) - 1 if self.message_count else 0
        self.topics: dict[str, TopicInfo] = {}
        self._connections: dict[str, list[Any]] = {}
        for c in r.connections:
            self._connections.setdefault(c.topic, []).append(c)
        for name, conns in self._connections.items():
            types = {c.msgtype for c in conns}
            if len(types) != 1:
                raise BagError(f"{self.path}: topic {name} has several types {sorted(types)}")
            c0 = conns[0]
            self.topics[name] = TopicInfo(
                name, c0.msgtype, sum(c.msgcount for c in conns),
                c0.ext.serialization_format,
                tuple(q for c in conns for q in c.ext.offered_qos_profiles), c0.digest,
                any(c.msgdef.format != MessageDefinitionFormat.NONE and c.msgdef.data.strip()
                    for c in conns)
                or self._srv_definition(c0.msgtype) is not None)

    @property
    def duration_ns(self) -> int:
        return self.end_ns - self.start_ns

    @property
    def size_bytes(self) -> int:
        return sum(f.stat().st_size for f in self.files if f.is_file())

    def close(self) -> None:
        if getattr(self, "_open", False):
            self._open = False
            with suppress(Exception):
                self._reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- types
    def _srv_definition(self, msgtype: str) -> tuple[str, str] | None:
        """The stored .srv definition of a service-event type, if the storage has one.

        An sqlite3 bag of Jazzy's recorder files it under the service type (``pkg/srv/Name``)
        in its message_definitions table rather than under the event type.
        """
        srv = _split_srv_type(msgtype)
        if srv is None:
            return None
        want = f"{srv[0]}/srv/{srv[1]}"
        subs = getattr(self._reader.storage, "storages", [self._reader.storage])
        for s in subs:
            for row in getattr(s, "msgtypes", []):
                if row.get("name") == want and row.get("msgdef"):
                    return ("idl" if row.get("encoding") == "ros2idl" else "msg", row["msgdef"])
        return None

    def _typestore(self) -> Any:
        """The type store for decoding: the bag's own definitions over Jazzy + cwfs_msgs."""
        if self._types is not None:
            return self._types
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import Stores, get_typestore

        stored: dict[str, Any] = {}
        problems: dict[str, str] = {}
        done: set[str] = set()
        for conns in self._connections.values():
            for c in conns:
                if c.msgtype in done:
                    continue
                if c.msgdef.format == MessageDefinitionFormat.NONE or not c.msgdef.data.strip():
                    # rosbag2 (and our recorder) store "" when no definition was available:
                    # that is no definition, not an empty message
                    definition = self._srv_definition(c.msgtype)
                else:
                    fmt = "idl" if c.msgdef.format == MessageDefinitionFormat.IDL else "msg"
                    definition = (fmt, c.msgdef.data)
                if definition is None:
                    continue  # left to the fallback store (below)
                done.add(c.msgtype)
                try:
                    stored.update(_types_from_definition(c.msgtype, *definition))
                except Exception as exc:  # noqa: BLE001 - a bad definition spoils one type
                    problems[c.msgtype] = f"its stored message definition does not parse " \
                                          f"({_why(exc)})"
        fielddefs = {**cwfs_typestore().fielddefs, **stored}
        for t in self.topics.values():
            if t.type in problems:
                continue
            if t.serialization_format != "cdr":
                problems[t.type] = f"serialization format {t.serialization_format!r} is not cdr"
                continue
            _, missing = _closure(fielddefs, t.type)
            if missing:
                problems[t.type] = ("unknown message type: the bag stores no definition of "
                                    f"{', '.join(sorted(missing))} and it is not a ROS 2 Jazzy "
                                    "or cwfs_msgs type")
                continue
            if t.type_hash:
                have = rosidl_type_hash(fielddefs, t.type)
                if have != t.type_hash:
                    problems[t.type] = (f"type hash mismatch: the bag records {t.type_hash}, "
                                        f"the definition available gives {have}")
        store = get_typestore(Stores.EMPTY)
        store.register(fielddefs)
        self._types, self._problems = store, problems
        return store

    def decode_problem(self, topic: str) -> str | None:
        """Why messages of ``topic`` cannot be decoded, or None if they can."""
        self._typestore()
        info = self.topics.get(topic)
        if info is None:
            return f"topic {topic} is not in the bag"
        return self._problems.get(info.type)

    def require_decodable(self, topics: Iterable[str]) -> None:
        """Raise BagError naming the first topic whose messages cannot be decoded."""
        for t in topics:
            why = self.decode_problem(t)
            if why is not None:
                raise BagError(f"{self.path}: cannot decode {t} ({self.topics[t].type}): {why}"
                               if t in self.topics else f"{self.path}: {why}")

    def deserialize(self, msg: BagMessage) -> Any:
        """The rosbags message object of a stored message (fields as in the .msg)."""
        store = self._typestore()
        why = self._problems.get(msg.type)
        if why is not None:
            raise BagError(f"{self.path}: cannot decode {msg.topic} ({msg.type}): {why}")
        try:
            return store.deserialize_cdr(msg.data, msg.type)
        except Exception as exc:  # noqa: BLE001 - corrupt bytes: report, with where
            raise BagError(f"{self.path}: corrupt {msg.type} message on {msg.topic} at "
                           f"{_stamp_text(msg.timestamp_ns)}: {_why(exc)}") from None

    # -- messages
    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """The stored messages of ``topics`` (default all) in bag-timestamp order.

        Raises BagError on corrupt storage, or when the storage yields fewer or more messages
        than its index promised.
        """
        names = list(self.topics) if topics is None else list(topics)
        unknown = [t for t in names if t not in self.topics]
        if unknown:
            raise BagError(f"{self.path}: no topic {', '.join(unknown)} in the bag "
                           f"(it has {', '.join(self.topics) or 'none'})")
        conns = [c for t in names for c in self._connections[t]]
        expected = sum(self.topics[t].count for t in names)
        if not conns or expected == 0:
            return
        n = 0
        it = self._reader.messages(connections=conns)
        while True:
            try:
                item = next(it, None)
            except Exception as exc:  # noqa: BLE001 - corrupt chunk, bad record ...
                raise BagError(f"{self.path}: corrupt storage after {n} messages: "
                               f"{_why(exc)}") from None
            if item is None:
                break
            conn, timestamp, data = item
            n += 1
            yield BagMessage(conn.topic, conn.msgtype, int(timestamp), bytes(data))
        if n != expected:
            raise BagError(f"{self.path}: the storage yielded {n} messages on "
                           f"{', '.join(names)}, its index lists {expected} (truncated or "
                           "corrupt storage)")

    def decoded(self, topics: Iterable[str] | None = None) -> Iterator[tuple[BagMessage, Any]]:
        """Like :meth:`messages`, with each message deserialised (checked decodable first)."""
        names = list(self.topics) if topics is None else list(topics)
        self.require_decodable(names)
        for m in self.messages(names):
            yield m, self.deserialize(m)


def open_bag(path: str | Path) -> Bag:
    """Open and check a rosbag2 bag (directory, or a bare .mcap / .db3 file); raises BagError."""
    return Bag(path)


def _why(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text if isinstance(exc, (BagError, OSError)) else f"{text} ({type(exc).__name__})"


def _stamp_text(ns: int) -> str:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}"


def _date_text(ns: int) -> str:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    d = _dt.datetime.fromtimestamp(sec, tz=_dt.UTC)
    return f"{d:%b %d %Y %H:%M:%S}.{nsec:09d} UTC ({sec}.{nsec:09d})"


def _size_text(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} GiB"


def format_info(bag: Bag) -> str:
    """``ros2 bag info``-style summary: files, storage, duration, start/end, counts per topic."""
    topics = [t for t in bag.topics.values() if not t.is_service_event]
    services = [t for t in bag.topics.values() if t.is_service_event]
    lines = [
        f"{'Files:':<19}{', '.join(f.name for f in bag.files)}",
        f"{'Bag size:':<19}{_size_text(bag.size_bytes)}",
        f"{'Storage id:':<19}{bag.storage}",
        f"{'Metadata version:':<19}{bag.version if bag.version is not None else 'none'}",
        f"{'ROS Distro:':<19}{bag.ros_distro or 'unknown'}",
        f"{'Duration:':<19}{bag.duration_ns / 1e9:.9f}s",
        f"{'Start:':<19}{_date_text(bag.start_ns) if bag.message_count else 'none'}",
        f"{'End:':<19}{_date_text(bag.end_ns) if bag.message_count else 'none'}",
        f"{'Messages:':<19}{bag.message_count}",
    ]
    width = max((len(t.name) for t in bag.topics.values()), default=0)
    twidth = max((len(t.type) for t in bag.topics.values()), default=0)
    head = "Topic information: "
    for i, t in enumerate(topics):
        lines.append(f"{head if i == 0 else ' ' * len(head)}Topic: {t.name:<{width}} | "
                     f"Type: {t.type:<{twidth}} | Count: {t.count} | "
                     f"Serialization Format: {t.serialization_format} | "
                     f"QoS: {_qos_text(t.offered_qos)}")
    if not topics:
        lines.append(f"{head}none")
    if services:
        lines.append(f"{'Service:':<19}{len(services)}")
        head = "Service information: "
        for i, t in enumerate(services):
            pkg, base = _split_srv_type(t.type) or ("", t.type)
            lines.append(f"{head if i == 0 else ' ' * len(head)}Service: "
                         f"{t.name[: -len('/_service_event')]} | Type: {pkg}/srv/{base} | "
                         f"Event Count: {t.count} | "
                         f"Serialization Format: {t.serialization_format}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- rclpy helpers
def _absolute(topic: str) -> str:
    t = topic.strip()
    return t if t.startswith("/") else "/" + t


def _message_class(msgtype: str) -> type | None:
    """The Python (rosidl) class of ``pkg/msg/Name`` or ``pkg/srv/Name_Event``, or None."""
    parts = msgtype.split("/")
    if len(parts) != 3:
        return None
    try:
        mod = importlib.import_module(f"{parts[0]}.{parts[1]}")
        srv = _split_srv_type(msgtype)
        if srv is not None:
            return getattr(getattr(mod, srv[1]), parts[2][len(srv[1]) + 1:])
        return getattr(mod, parts[2])
    except (ImportError, AttributeError):
        return None


def _rosbags_qos(q: Any) -> Any:
    """rosbags ``Qos`` of an rclpy QoSProfile (the form rosbag2 stores offered profiles in)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    def enum(cls: Any, value: Any) -> Any:
        try:
            return cls(int(value))
        except ValueError:
            return cls.UNKNOWN

    def dur(d: Any) -> Any:
        return QosTime(*divmod(int(d.nanoseconds), 1_000_000_000))

    return Qos(enum(QosHistory, q.history), int(q.depth), enum(QosReliability, q.reliability),
               enum(QosDurability, q.durability), dur(q.deadline), dur(q.lifespan),
               enum(QosLiveliness, q.liveliness), dur(q.liveliness_lease_duration),
               bool(q.avoid_ros_namespace_conventions))


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT / SIGTERM set ``stop`` (main thread only), so the bag is closed cleanly."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, lambda *_: stop.set())
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _own_context(domain_id: int | None) -> Any:
    """A fresh rclpy Context without rclpy's signal handlers (ours close the bag first)."""
    from cwfs_ros.ros.dds import ensure_fastdds_profile

    ensure_fastdds_profile()  # big images need the 16 MiB shared-memory segments
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    return ctx


# ----------------------------------------------------------------------------- record
@dataclass
class _Topic:
    name: str
    type: str
    subscription: Any = None
    connected: bool = False
    count: int = 0
    bytes: int = 0
    best_effort: bool = False
    dropped: bool = False


@dataclass
class RecordSummary:
    """What :class:`Recorder` wrote: per-topic (type, messages, bytes) and totals."""

    path: Path
    storage: str
    duration_s: float
    topics: dict[str, tuple[str, int, int]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def message_count(self) -> int:
        return sum(n for _, n, _ in self.topics.values())

    def format(self) -> str:
        lines = [f"recorded {self.message_count} messages on "
                 f"{sum(1 for _, n, _ in self.topics.values() if n)} of {len(self.topics)} "
                 f"topics in {self.duration_s:.1f} s to {self.path} ({self.storage})"]
        width = max((len(t) for t in self.topics), default=0)
        for name, (typ, n, size) in self.topics.items():
            lines.append(f"  {name:<{width}}  {typ}  {n} msgs  {_size_text(size)}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


class Recorder:
    """A raw-subscription recorder node writing one rosbag2 bag (rosbags ``Writer``).

    Args:
        out: bag directory to create (must not exist).
        topics: topic names (relative names are taken from the root namespace); empty: the
            graph's :data:`DEFAULT_TOPICS`.
        storage: ``mcap`` or ``sqlite3``.
        all_topics: also record every other topic that appears in the graph.
        context: an initialised rclpy Context for the node.
        max_messages: stop writing (and set ``stop_event``) after this many messages.
        stop_event: set when ``max_messages`` is reached; the driver then calls :meth:`close`.
        depth: subscription history depth (a burst of images per topic must not overflow it).

    Topics of :data:`DEFAULT_TOPICS` are subscribed at once; others when they appear in the
    graph (checked every ``discovery_period_s``), with the type the graph reports. A
    subscription is RELIABLE unless a publisher of the topic is BEST_EFFORT (a RELIABLE reader
    would not match it), and TRANSIENT_LOCAL when every publisher is. Add :attr:`node` to an
    executor; callbacks may run on any of its threads. They only queue the bytes: one writer
    thread owns the bag (sqlite3 connections must stay in the thread that made them, and the
    executor never waits for the disk).
    """

    def __init__(self, out: str | Path, topics: Sequence[str] = (), *, storage: str = "mcap",
                 all_topics: bool = False, context: Any = None,
                 max_messages: int | None = None, stop_event: threading.Event | None = None,
                 depth: int = 100, discovery_period_s: float = 0.2,
                 node_name: str = "cwfs_bag_recorder") -> None:
        import rclpy

        if storage not in STORAGES:
            raise BagError(f"storage must be one of {STORAGES}, got {storage!r}")
        self.path = Path(out)
        if self.path.exists():
            raise BagError(f"{self.path} exists already; a bag is never overwritten")
        if not self.path.resolve().parent.is_dir():
            raise BagError(f"{self.path}: directory {self.path.parent} does not exist")
        self.storage = storage
        self.all_topics = bool(all_topics)
        self.max_messages = max_messages
        self.stop_event = stop_event if stop_event is not None else threading.Event()
        self.depth = int(depth)
        self.warnings: list[str] = []
        self._lock = threading.Lock()
        self._closed = False
        self._t0 = time.monotonic()
        self._types = cwfs_typestore()
        names = [_absolute(t) for t in topics] or list(DEFAULT_TOPICS)
        self._topics: dict[str, _Topic] = {}
        self._wanted = list(dict.fromkeys(names))
        self._queue: queue.SimpleQueue[tuple | None] = queue.SimpleQueue()
        self._writer_error: BaseException | None = None
        opened = threading.Event()
        self._writer_thread = threading.Thread(target=self._write_loop, args=(opened,),
                                               name="cwfs_bag_writer", daemon=True)
        self._writer_thread.start()
        opened.wait()
        if self._writer_error is not None:
            raise BagError(f"{self.path}: cannot create the bag: "
                           f"{_why(self._writer_error)}") from None
        try:
            self.node = rclpy.create_node(node_name, context=context)
            for name in self._wanted:
                if name in DEFAULT_TOPICS:
                    self._subscribe(name, DEFAULT_TOPICS[name])
            self._discover()
            self._timer = self.node.create_timer(discovery_period_s, self._discover)
        except BaseException:
            self._queue.put(None)  # let the writer thread finish (an empty bag)
            self._writer_thread.join()
            raise

    # -- subscriptions
    @property
    def subscriptions(self) -> dict[str, Any]:
        """Topic -> rclpy Subscription of the topics subscribed so far."""
        return {n: t.subscription for n, t in self._topics.items() if t.subscription}

    def _warn(self, text: str) -> None:
        self.warnings.append(text)
        self.node.get_logger().warning(text)

    def _qos(self, name: str) -> tuple[Any, bool]:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        pubs = [p.qos_profile for p in self.node.get_publishers_info_by_topic(name)]
        best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in pubs)
        latched = bool(pubs) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                     for q in pubs)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.depth,
                         reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                      else ReliabilityPolicy.RELIABLE),
                         durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                     else DurabilityPolicy.VOLATILE))
        return qos, best_effort

    def _subscribe(self, name: str, msgtype: str) -> None:
        cls = _message_class(msgtype)
        if cls is None:
            if name not in self._topics:
                self._topics[name] = _Topic(name, msgtype)
                self._warn(f"cannot record {name}: message type {msgtype} is not installed")
            return
        qos, best_effort = self._qos(name)
        t = self._topics.setdefault(name, _Topic(name, msgtype))
        if t.subscription is not None:
            self.node.destroy_subscription(t.subscription)
        t.best_effort = best_effort
        # raw=True: the callback gets the serialized CDR bytes, exactly what is written.
        t.subscription = self.node.create_subscription(
            cls, name, partial(self._on_message, name), qos, raw=True)

    def _discover(self) -> None:
        """Subscribe to wanted topics that appeared; adapt to best-effort publishers."""
        from rclpy.qos import ReliabilityPolicy

        if self._closed:
            return
        graph = dict(self.node.get_topic_names_and_types())
        wanted = list(self._wanted) + ([n for n in graph if n not in self._wanted]
                                       if self.all_topics else [])
        for name in wanted:
            t = self._topics.get(name)
            if t is None:
                types = graph.get(name)
                if not types:
                    continue
                if len(types) > 1:
                    self._warn(f"{name} has several types {types}; recording {types[0]}")
                self._subscribe(name, types[0])
            elif t.subscription is not None and not t.best_effort and any(
                    p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                    for p in self.node.get_publishers_info_by_topic(name)):
                self._subscribe(name, t.type)  # re-subscribe best effort so that it matches

    # -- writing
    def _write_loop(self, opened: threading.Event) -> None:
        """The writer thread: opens the bag, then adds connections and writes as queued."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        try:
            writer = Writer(self.path, version=9, storage_plugin=plugin)
            writer.open()
        except BaseException as exc:  # noqa: BLE001 - reported by __init__
            self._writer_error = exc
            opened.set()
            return
        opened.set()
        conns: dict[str, Any] = {}
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    break
                if item[0] == "connection":
                    _, name, kwargs = item
                    conns[name] = writer.add_connection(name, **kwargs)
                else:
                    _, name, stamp, data = item
                    writer.write(conns[name], stamp, data)
            writer.close()
        except BaseException as exc:  # noqa: BLE001 - reported by close()
            self._writer_error = exc
            with suppress(Exception):
                writer.abort()

    def _connection(self, t: _Topic) -> dict[str, Any] | None:
        """What the bag records about a topic: type, definition, hash, offered QoS.

        None when it cannot be recorded: a type neither in the type store nor hashed by the
        graph (the topic is then dropped, with a warning).
        """
        offered = [_rosbags_qos(p.qos_profile)
                   for p in self.node.get_publishers_info_by_topic(t.name)]
        fielddefs = self._types.fielddefs
        if t.type in fielddefs:
            msgdef, _ = self._types.generate_msgdef(t.type, ros_version=2)
            digest = rosidl_type_hash(fielddefs, t.type)
        else:
            # Not in the store: keep the bytes and the graph's hash; play still works.
            msgdef, digest = "", ""
            for p in self.node.get_publishers_info_by_topic(t.name):
                h = p.topic_type_hash
                if getattr(h, "version", -1) == 1:
                    digest = "RIHS01_" + bytes(h.value).hex()
            if not digest:
                self._warn(f"dropping {t.name}: no definition nor type hash of {t.type}")
                return None
            self._warn(f"{t.name}: no message definition of {t.type} available; recorded "
                       "without one")
        return {"msgtype": t.type, "msgdef": msgdef, "rihs01": digest,
                "serialization_format": "cdr", "offered_qos_profiles": offered}

    def _on_message(self, name: str, data: bytes, info: Any) -> None:
        stamp = 0
        if isinstance(info, Mapping):
            stamp = int(info.get("received_timestamp") or 0)
        stamp = stamp or time.time_ns()
        with self._lock:
            if self._closed or self.stop_event.is_set():
                return
            if self._writer_error is not None:  # the disk failed: stop, close() reports it
                self.stop_event.set()
                return
            t = self._topics[name]
            if not t.connected:
                if t.dropped:
                    return
                conn = self._connection(t)
                if conn is None:
                    t.dropped = True
                    return
                self._queue.put(("connection", name, conn))
                t.connected = True
            self._queue.put(("message", name, stamp, bytes(data)))
            t.count += 1
            t.bytes += len(data)
            if self.max_messages is not None and self.message_count >= self.max_messages:
                self.stop_event.set()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    def counts(self) -> dict[str, int]:
        """Messages taken so far, per topic (all of them are in the bag once closed)."""
        with self._lock:
            return {n: t.count for n, t in self._topics.items()}

    def close(self) -> RecordSummary:
        """Stop recording, write metadata.yaml, destroy the node; returns the summary."""
        with self._lock:
            if self._closed:
                return self._summary
            self._closed = True
            for t in self._topics.values():
                if t.subscription is not None and not t.connected and not t.dropped:
                    # subscribed but silent: listed with 0 messages, as rosbag2 does
                    conn = self._connection(t)
                    if conn is not None:
                        self._queue.put(("connection", t.name, conn))
                        t.connected = True
            self._queue.put(None)
        self._writer_thread.join()
        with suppress(Exception):
            self.node.destroy_node()
        for name in self._wanted:
            if name not in self._topics:
                self.warnings.append(f"{name} never appeared in the graph: not recorded")
        self._summary = RecordSummary(
            self.path, self.storage, time.monotonic() - self._t0,
            {n: (t.type, t.count, t.bytes) for n, t in self._topics.items()},
            list(self.warnings))
        if self._writer_error is not None:
            raise BagError(f"{self.path}: writing the bag failed: "
                           f"{_why(self._writer_error)}")
        return self._summary


def record(out: str | Path, topics: Sequence[str] = (), *, storage: str = "mcap",
           all_topics: bool = False, duration_s: float | None = None,
           max_messages: int | None = None, domain_id: int | None = None,
           on_start: Callable[[Recorder], None] | None = None) -> RecordSummary:
    """Record until SIGINT/SIGTERM, ``duration_s`` seconds or ``max_messages`` messages.

    Runs its own rclpy Context (``ROS_DOMAIN_ID`` unless ``domain_id``) and executor; the bag
    is always closed (metadata written) before returning.
    """
    from rclpy.executors import SingleThreadedExecutor

    if Path(out).exists():  # before starting the middleware: a quick, clear refusal
        raise BagError(f"{out} exists already; a bag is never overwritten")
    stop = threading.Event()  # SIGINT / SIGTERM
    full = threading.Event()  # max_messages reached
    ctx = _own_context(domain_id)
    executor = None
    rec = None
    try:
        with _stop_on_signals(stop):
            rec = Recorder(out, topics, storage=storage, all_topics=all_topics, context=ctx,
                           max_messages=max_messages, stop_event=full)
            executor = SingleThreadedExecutor(context=ctx)
            executor.add_node(rec.node)
            if on_start is not None:
                on_start(rec)
            t_end = None if duration_s is None else time.monotonic() + float(duration_s)
            while not (stop.is_set() or full.is_set()) and (
                    t_end is None or time.monotonic() < t_end):
                executor.spin_once(timeout_sec=0.05)
            # Messages the middleware delivered before the stop are still waiting to be
            # taken: take them (briefly), so that what was sent before Ctrl-C is in the bag.
            t_drain = time.monotonic() + 0.25
            while not full.is_set() and time.monotonic() < t_drain:
                executor.spin_once(timeout_sec=0.01)
            return rec.close()
    finally:
        if rec is not None:
            rec.close()
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        ctx.try_shutdown()


# ----------------------------------------------------------------------------- play
@dataclass
class PlaySummary:
    """What :func:`play` published: per-topic counts, wall time, loops."""

    path: Path
    rate: float
    wall_s: float
    loops: int
    counts: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)

    def format(self) -> str:
        n = sum(self.counts.values())
        lines = [f"played {n} messages on {len(self.counts)} topics from {self.path} in "
                 f"{self.wall_s:.2f} s (rate {self.rate:g}"
                 + (f", {self.loops} loops)" if self.loops > 1 else ")")]
        lines += [f"  skipped {t}: {why}" for t, why in self.skipped.items()]
        return "\n".join(lines)


def _publisher_qos(offered: Sequence[Any]) -> Any:
    """Publisher QoS from the recorded offered profiles.

    Reliability and durability as recorded (RELIABLE / VOLATILE when nothing usable was
    recorded); KEEP_LAST with at least depth 10, because DDS discovery does not advertise the
    original depth (the recorder stores 0 / UNKNOWN).
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability

    best_effort = any(q.reliability == QosReliability.BEST_EFFORT for q in offered)
    latched = bool(offered) and all(q.durability == QosDurability.TRANSIENT_LOCAL
                                    for q in offered)
    depth = max([10] + [int(q.depth) for q in offered if q.history == QosHistory.KEEP_LAST])
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                   else ReliabilityPolicy.RELIABLE),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def play(path: str | Path, *, rate: float = 1.0, topics: Sequence[str] | None = None,
         loop: bool = False, delay_s: float = 0.0, context: Any = None,
         domain_id: int | None = None, stop_event: threading.Event | None = None,
         on_ready: Callable[[Any, dict[str, Any]], None] | None = None,
         ack_timeout_s: float = 2.0, node_name: str = "cwfs_bag_player") -> PlaySummary:
    """Republish a bag's stored CDR bytes with the original timing.

    Args:
        rate: playback speed factor (2 = twice as fast).
        topics: topics to play (default all but the corrections). Topics whose message type
            is not installed are skipped with a warning when playing everything, and an error
            when named. DofCorrection topics are played only when named: a recorded
            correction played into a running graph would be applied by its actuators (or the
            simulated camera) a second time.
        loop: start over at the end, until stopped.
        delay_s: wait after creating the publishers, before the first message (gives
            subscribers time to discover them, as ``ros2 bag play --delay``).
        context: an initialised rclpy Context (default: a new one on ``domain_id`` /
            ``ROS_DOMAIN_ID``, with SIGINT/SIGTERM stopping playback).
        stop_event: set it to stop playback early.
        on_ready: ``on_ready(node, publishers)`` once the publishers exist (before the delay).
        ack_timeout_s: at the end, wait at most this long for reliable subscribers to
            acknowledge everything (so that the last messages are not lost at exit).

    Message ``k`` is published at ``t0 + (stamp_k - stamp_0) / rate`` on the monotonic clock,
    ``stamp`` being the bag (receive) timestamps.
    """
    if not rate > 0 or rate == float("inf"):
        raise BagError(f"rate must be a positive number, got {rate}")
    stop = stop_event if stop_event is not None else threading.Event()
    own = context is None
    summary = PlaySummary(Path(path), float(rate), 0.0, 0)
    with open_bag(path) as bag:
        classes = _play_classes(bag, topics, summary)
        ctx = _own_context(domain_id) if own else context
        import rclpy

        node = None
        try:
            with _stop_on_signals(stop) if own else nullcontext():
                node = rclpy.create_node(node_name, context=ctx)
                pubs = {t: node.create_publisher(cls, t,
                                                 _publisher_qos(bag.topics[t].offered_qos))
                        for t, cls in classes.items()}
                for t, why in summary.skipped.items():
                    node.get_logger().warning(f"skipping {t}: {why}")
                if on_ready is not None:
                    on_ready(node, pubs)
                if delay_s > 0:
                    stop.wait(float(delay_s))
                _play_loops(bag, pubs, rate, loop, stop, ack_timeout_s, summary)
        finally:
            if node is not None:
                with suppress(Exception):
                    node.destroy_node()
            if own:
                ctx.try_shutdown()
    return summary


def _play_classes(bag: Bag, topics: Sequence[str] | None,
                  summary: PlaySummary) -> dict[str, Any]:
    """The message class of each topic to play; the topics left out go to ``summary.skipped``.

    A named topic that cannot be played raises (the user asked for it); playing everything
    skips it, and the corrections (applied again by any actuator listening) unless named.
    """
    names = list(bag.topics) if topics is None else [_absolute(t) for t in topics]
    missing = [t for t in names if t not in bag.topics]
    if missing:
        raise BagError(f"{bag.path}: no topic {', '.join(missing)} in the bag "
                       f"(it has {', '.join(bag.topics) or 'none'})")
    classes = {}
    for t in names:
        if topics is None and bag.topics[t].type == CORRECTION_TYPE:
            summary.skipped[t] = ("corrections are played only when named (--topics): "
                                  "actuators listening would apply them again")
            continue
        cls = _message_class(bag.topics[t].type)
        if cls is None:
            why = f"message type {bag.topics[t].type} is not installed"
            if topics is not None:
                raise BagError(f"cannot play {t}: {why}")
            summary.skipped[t] = why
        else:
            classes[t] = cls
    if not classes:
        raise BagError(f"{bag.path}: nothing to play"
                       + (f" ({'; '.join(summary.skipped.values())})"
                          if summary.skipped else " (no topics)"))
    return classes


def _play_loops(bag: Bag, pubs: dict[str, Any], rate: float, loop: bool,
                stop: threading.Event, ack_timeout_s: float, summary: PlaySummary) -> None:
    """Play the bag once, or over and over with ``loop``, until ``stop``, then wait for the
    acknowledgements; the loops, counts and wall time (the wait included) go to ``summary``."""
    t_start = time.monotonic()
    counts = dict.fromkeys(pubs, 0)
    while not stop.is_set():
        summary.loops += 1
        _play_once(bag, pubs, counts, rate, stop)
        if not loop:
            break
    _wait_acked(pubs, ack_timeout_s)
    summary.counts = counts
    summary.wall_s = time.monotonic() - t_start


def _play_once(bag: Bag, pubs: dict[str, Any], counts: dict[str, int], rate: float,
               stop: threading.Event) -> None:
    """Publish the bag once through, each message at its recorded offset / ``rate`` from now
    (monotonic clock); return early when ``stop`` is set. ``counts`` counts per topic."""
    t0_wall, t0_bag = time.monotonic(), None
    for m in bag.messages(list(pubs)):
        if t0_bag is None:
            t0_bag = m.timestamp_ns
        due = t0_wall + (m.timestamp_ns - t0_bag) / 1e9 / rate
        wait = due - time.monotonic()
        if wait > 0 and stop.wait(wait):
            break
        if stop.is_set():
            break
        pubs[m.topic].publish(m.data)
        counts[m.topic] += 1


def _wait_acked(pubs: dict[str, Any], ack_timeout_s: float) -> None:
    """Reliable data still in flight would be lost when the node goes: wait for the
    subscribers' acknowledgements (at most ``ack_timeout_s`` in all)."""
    from rclpy.duration import Duration as RclDuration

    deadline = time.monotonic() + ack_timeout_s
    for p in pubs.values():
        left = max(0.0, deadline - time.monotonic())
        p.wait_for_all_acked(RclDuration(nanoseconds=int(left * 1e9)))


# ----------------------------------------------------------------------------- command line


def _cli_error(args: argparse.Namespace, exc: BagError) -> Exception:
    """The command line's user-error exception for ``exc`` (exit status 2, one line)."""
    cls = getattr(args, "cli_error", None) or CliError
    return cls(str(exc))


def cmd_record(args: argparse.Namespace) -> int:
    def started(rec: Recorder) -> None:
        subscribed = ", ".join(rec.subscriptions) or "none yet"
        print(f"recording to {rec.path} ({rec.storage}); subscribed: {subscribed}"
              + ("; plus any other topic that appears" if rec.all_topics else "")
              + "; Ctrl-C to stop", flush=True)

    try:
        summary = record(args.out, args.topics, storage=args.storage, all_topics=args.all,
                         duration_s=args.duration, max_messages=args.max_messages,
                         on_start=started)
    except BagError as exc:
        raise _cli_error(args, exc) from None
    print(summary.format())
    return 0


def cmd_play(args: argparse.Namespace) -> int:
    try:
        summary = play(args.bag, rate=args.rate, topics=args.topics, loop=args.loop,
                       delay_s=args.delay)
    except BagError as exc:
        raise _cli_error(args, exc) from None
    print(summary.format())
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    try:
        with open_bag(args.bag) as bag:
            print(format_info(bag))
    except BagError as exc:
        raise _cli_error(args, exc) from None
    return 0


def add_bag_parser(subparsers: Any, cli_error: type[Exception] | None = None
                   ) -> argparse.ArgumentParser:
    """Register ``bag record|play|info`` on an argparse subparsers object (sets ``func``).

    ``cli_error``: the exception class the command line reports as a one-line user error
    (default :class:`cwfs_ros.errors.CliError`); handlers raise it for a :class:`BagError`.
    """
    p = subparsers.add_parser(
        "bag", help="record, play and inspect rosbag2 bags (like ros2 bag)",
        description="Record, play and inspect rosbag2 bags (mcap or sqlite3), like `ros2 bag`.")
    p.set_defaults(cli_error=cli_error)
    verbs = p.add_subparsers(dest="bag_command", metavar="VERB", required=True)

    r = verbs.add_parser(
        "record", help="record topics into a new bag",
        description="Record topics (default: everything the cwfs_ros graph publishes) with raw "
                    "subscriptions into a new rosbag2 bag, until Ctrl-C, --duration or "
                    "--max-messages. Honours ROS_DOMAIN_ID.")
    r.add_argument("out", metavar="OUT", help="bag directory to create (must not exist)")
    r.add_argument("topics", nargs="*", metavar="TOPIC",
                   help="topics to record (default: " + ", ".join(DEFAULT_TOPICS) + ")")
    r.add_argument("-a", "--all", action="store_true",
                   help="also record every other topic that appears in the graph")
    r.add_argument("-s", "--storage", choices=STORAGES, default="mcap",
                   help="storage format (default: %(default)s)")
    r.add_argument("--duration", type=_positive_float, metavar="S",
                   help="stop after S seconds")
    r.add_argument("--max-messages", type=_positive_int, metavar="N",
                   help="stop after N messages in all")
    r.set_defaults(func=cmd_record)

    pl = verbs.add_parser(
        "play", help="republish a bag with the original timing",
        description="Republish the stored messages (their CDR bytes) with the original "
                    "timing, on publishers with the recorded QoS. Honours ROS_DOMAIN_ID.")
    pl.add_argument("bag", metavar="BAG", help="bag directory (or .mcap / .db3 file)")
    pl.add_argument("-r", "--rate", type=_positive_float, default=1.0,
                    help="playback speed factor (default: %(default)g)")
    pl.add_argument("--topics", nargs="+", metavar="TOPIC",
                    help="play only these topics (default: all but the DofCorrection "
                         "topics, which are played only when named: actuators listening "
                         "would apply a recorded correction again)")
    pl.add_argument("-l", "--loop", action="store_true", help="play in a loop until Ctrl-C")
    pl.add_argument("-d", "--delay", type=_nonnegative_float, default=0.0, metavar="S",
                    help="wait S seconds after creating the publishers (default: 0)")
    pl.set_defaults(func=cmd_play)

    i = verbs.add_parser("info", help="summarise a bag",
                         description="Summarise a bag like `ros2 bag info`.")
    i.add_argument("bag", metavar="BAG", help="bag directory (or .mcap / .db3 file)")
    i.set_defaults(func=cmd_info)
    return p
