"""ROS parameter YAML files, checked before anything acts on them (no ROS imports).

rcl is lenient in two ways that are dangerous on a telescope: a parameter name no node
declares is ignored silently (a misspelt ``dryrun: true`` leaves the controller live), and
when two layered files give the same parameter values of different types, the later file is
dropped silently (``kp: "fast"`` over config/params.yaml leaves kp at 0.18). The entry points
therefore read every file themselves first (:func:`read_params_file`) and, once the nodes
have declared their parameters, refuse unknown names and wrong types
(:func:`check_declared`), naming the file and the key.  The command line's
``--ros-args -p NAME:=VALUE`` overrides are held to the same rules
(:func:`check_overrides`), and an unknown name is given its close match.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from cwfs_ros.config import config_dir, ros_home
from cwfs_ros.errors import ParamsFileError

__all__ = ["AUTO_STATE_FILE", "check_declared", "check_overrides", "close_match",
           "default_params_file", "flatten", "parse_parameter_text", "read_params_file",
           "ros_home", "state_file_path", "yaml_kind"]

#: ``state_file`` value that means the node's own file under :func:`ros_home`.
AUTO_STATE_FILE = "auto"

# Numbers with an exponent that YAML 1.1 (PyYAML) reads as text and rcl as doubles: no dot
# before the exponent (1e-3), or an unsigned exponent (1.0e308).
_EXPONENT_FLOAT = r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$"


@lru_cache(maxsize=1)
def _parameter_loader() -> type:
    """A safe YAML loader that types values as rcl does: also 1e-3 and 1.0e308 are doubles."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(_EXPONENT_FLOAT),
                                 list("-+0123456789."))
    return Loader


def parse_parameter_text(text: str) -> Any:
    """A parameter value written as YAML (a file, ``-p NAME:=VALUE``, ``param set``), typed
    as rcl types it: PyYAML's YAML 1.1 reads ``1e-3`` or ``1.0e308`` as text, rcl as a
    double. Raises ``yaml.YAMLError`` for text that is not YAML."""
    import yaml

    return yaml.load(text, Loader=_parameter_loader())  # noqa: S506 - a SafeLoader subclass


def default_params_file() -> Path:
    """The parameters every node starts from: ``config/params.yaml``."""
    return config_dir() / "params.yaml"


def state_file_path(value: str, namespace: str, node_name: str) -> str:
    """The file a node's ``state_file`` parameter names: ``auto`` is
    ``$ROS_HOME/cwfs_ros/<namespace>/<node name>.state.json`` (one per node, so that two
    nodes never share one), ``""`` none, anything else that path (``~`` expanded)."""
    if value == AUTO_STATE_FILE:
        parts = [q for q in namespace.split("/") if q]
        return str(ros_home().joinpath("cwfs_ros", *parts, f"{node_name}.state.json"))
    return str(Path(value).expanduser()) if value else ""


def flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested ``ros__parameters`` to dotted names, as rcl reads them."""
    out: dict[str, Any] = {}
    for k, v in params.items():
        name = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, name + "."))
        else:
            out[name] = v
    return out


def read_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """``{node key: {dotted name: value}}`` of a parameter file (node keys as written, e.g.
    ``ofc_node``, ``/ofc_node`` or ``/**``). Raises ParamsFileError for unreadable YAML or
    a section without a ``ros__parameters`` mapping."""
    import yaml

    p = Path(path)
    try:
        data = parse_parameter_text(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ParamsFileError(f"parameter file {p}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise ParamsFileError(f"parameter file {p} is not valid YAML: "
                              f"{' '.join(str(exc).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ParamsFileError(f"parameter file {p} must map node names to ros__parameters, "
                              f"not a {type(data).__name__}")
    out: dict[str, dict[str, Any]] = {}
    for key, section in data.items():
        params = section.get("ros__parameters") if isinstance(section, Mapping) else None
        if not isinstance(params, Mapping):
            raise ParamsFileError(f"parameter file {p}: {key!r} has no ros__parameters "
                                  "mapping")
        out[str(key)] = flatten(params)
    return out


def yaml_kind(value: Any) -> str:
    """The parameter kind a YAML value makes: bool, integer, double, string, or ``*_array``
    (an empty or mixed list is ``array``)."""
    def one(v: Any) -> str:
        if isinstance(v, bool):
            return "bool"
        if isinstance(v, int):
            return "integer"
        if isinstance(v, float):
            return "double"
        if isinstance(v, str):
            return "string"
        return type(v).__name__

    if isinstance(value, (list, tuple)):
        kinds = {one(v) for v in value}
        if kinds == {"integer", "double"}:
            kinds = {"double"}
        return f"{kinds.pop()}_array" if len(kinds) == 1 else "array"
    return one(value)


def _compatible(given: str, declared: str) -> bool:
    # As strict as rclpy: "kp: 1" is an integer and kp a double (write 1.0). An empty list
    # has no element type and fits any array.
    return given == declared or (given == "array" and declared.endswith("_array"))


def check_declared(files: list[Path], node: str, declared: Mapping[str, str]) -> list[str]:
    """Problems of ``files`` for a node that declared ``declared`` (name -> kind, kinds as
    :func:`yaml_kind` names them): unknown names and wrong types, one line each."""
    problems = []
    for f in files:
        for key, values in read_params_file(f).items():
            if key.lstrip("/") not in (node, "**"):
                continue
            for name, value in values.items():
                if name not in declared:
                    if key.lstrip("/") == node:  # a wildcard section may hold other nodes'
                        problems.append(f"{f}: {node}.{name}: {node} declares no such "
                                        "parameter (misspelt? it would be ignored)"
                                        + close_match(name, declared))
                    continue
                given = yaml_kind(value)
                if not _compatible(given, declared[name]):
                    problems.append(f"{f}: {node}.{name}: {value!r} is a {given}, the "
                                    f"parameter is a {declared[name]}")
    return problems


def close_match(name: str, declared: Iterable[str]) -> str:
    """``"; did you mean 'dry_run'?"`` for the nearest declared name, or ``""``."""
    import difflib

    near = difflib.get_close_matches(name, list(declared), n=1, cutoff=0.6)
    return f"; did you mean {near[0]!r}?" if near else ""


def _overrides(ros_args: Sequence[str]) -> list[tuple[str | None, str, str]]:
    """``(node or None, name, value text)`` of every ``-p``/``--param`` of an rcl command
    line (``NAME:=VALUE``, or ``NODE:NAME:=VALUE`` for one node)."""
    out = []
    for flag, rule in zip(ros_args, ros_args[1:], strict=False):
        if flag not in ("-p", "--param") or ":=" not in rule:
            continue
        lhs, _, value = rule.partition(":=")
        node, _, name = lhs.rpartition(":")
        out.append((node.lstrip("/") or None, name, value))
    return out


def check_overrides(ros_args: Sequence[str], declared: Mapping[str, Mapping[str, str]]
                    ) -> list[str]:
    """Problems of the ``-p NAME:=VALUE`` overrides of ``ros_args`` for the nodes of
    ``declared`` (node -> name -> kind): a name no node declares (rcl would ignore it) and
    a value of another type than the parameter's, one line each.  A name without a node
    prefix reaches every node, so it must be declared by at least one."""
    import yaml

    problems = []
    for node, name, text in _overrides(ros_args):
        targets = {n: d for n, d in declared.items() if node is None or n == node}
        if node is not None and not targets:
            problems.append(f"-p {node}:{name}:={text}: no node {node} here (running: "
                            f"{', '.join(sorted(declared))})")
            continue
        holders = {n: d[name] for n, d in targets.items() if name in d}
        if not holders:
            known = {k for d in targets.values() for k in d}
            problems.append(f"-p {name}:={text}: {' or '.join(sorted(targets))} declares no "
                            "such parameter (misspelt? it would be ignored)"
                            + close_match(name, known))
            continue
        try:
            given = yaml_kind(parse_parameter_text(text))
        except yaml.YAMLError:
            given = "string"
        for n, kind in sorted(holders.items()):
            if not _compatible(given, kind):
                problems.append(f"-p {name}:={text}: {n}.{name} is a {kind}, {text!r} is "
                                f"a {given}")
    return problems
