"""Entry points that start the nodes, as ``ros2 launch`` / ``ros2 run`` would.

The PyPI ROS 2 wheels have no ``ros2`` command and no ``launch`` package, so this module is the
project's launcher:

* ``cwfs-ros bringup [--sim] [--params FILE] [--ros-args ...]`` runs wavefront_node and
  ofc_node (plus camera_sim_node with ``--sim``) composed in one process on a
  MultiThreadedExecutor (:mod:`cwfs_ros.ros.executor`: rclpy's, less a busy loop), like a
  launch file with a component container would;
* ``cwfs-ros node NAME [--params FILE] [--ros-args ...]`` runs one node;
* the executables ``wavefront_node`` / ``ofc_node`` (``ros2 run``-style) call
  :func:`run_node_main`.

wavefront_node and ofc_node are managed (lifecycle) nodes: they are created unconfigured,
their parameters are checked, and then they are configured and activated, unless
``--no-autostart`` leaves them unconfigured for ``cwfs-ros lifecycle set``.

Parameters come from ``config/params.yaml`` (``ros__parameters`` keyed by node name), then
from each ``--params FILE`` in order (later files win), then from ``--ros-args`` (``-p``,
``--params-file``, remappings, ``--log-level`` ...), exactly as rcl orders them. Before ROS
starts, ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set to ``config/fastdds_profile.xml`` unless the
environment already sets it (the large-image shared-memory settings).

Usable without the project CLI as ``python -m cwfs_ros.ros.launch bringup|node ...``. To register
the subcommands in another argparse CLI::

    from cwfs_ros.ros.launch import add_bringup_parser, add_node_parser
    add_bringup_parser(subparsers); add_node_parser(subparsers)
    args = parser.parse_args(); sys.exit(args.func(args))
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from cwfs_ros.config import config_dir
from cwfs_ros.errors import LaunchError
from cwfs_ros.ros.dds import ensure_fastdds_profile
from cwfs_ros.ros.params import check_declared, check_overrides, default_params_file
from cwfs_ros.runtime.memory import keep_freed_memory
from cwfs_ros.runtime.threads import limit_blas_threads

__all__ = [
    "BRINGUP_NODES",
    "LaunchError",
    "NODES",
    "add_bringup_parser",
    "add_node_parser",
    "default_params_file",
    "ensure_fastdds_profile",
    "load_node_class",
    "main",
    "ros_arguments",
    "run_node_main",
    "run_nodes",
    "spin_until_shutdown",
]

# node name -> (module, class). camera_sim_node is written separately and imported lazily.
NODES: dict[str, tuple[str, str]] = {
    "wavefront_node": ("cwfs_ros.ros.wavefront_node", "WavefrontNode"),
    "ofc_node": ("cwfs_ros.ros.ofc_node", "OfcNode"),
    "camera_sim_node": ("cwfs_ros.ros.camera_sim_node", "CameraSimNode"),
}
BRINGUP_NODES: tuple[str, ...] = ("wavefront_node", "ofc_node")
SIM_NODE = "camera_sim_node"


def ros_arguments(params_files: Sequence[str | Path] = (),
                  ros_args: Sequence[str] = (), *, defaults: bool = True) -> list[str]:
    """The rcl command line: default params, ``--params`` files, then the user's ROS args."""
    files = ([default_params_file()] if defaults and default_params_file().is_file() else [])
    for f in params_files:
        p = Path(f)
        if not p.is_file():
            raise LaunchError(f"parameter file not found: {f}")
        files.append(p)
    out: list[str] = []
    if files:
        out.append("--ros-args")
        for f in files:
            out += ["--params-file", str(f)]
    rest = list(ros_args)
    if rest:
        if rest[0] != "--ros-args":
            rest.insert(0, "--ros-args")
        out += rest
    return out


def load_node_class(name: str) -> type:
    """The node class of ``name``, imported on first use (rclpy loads only when a node runs)."""
    if name not in NODES:
        raise LaunchError(f"unknown node {name!r}; known: {', '.join(sorted(NODES))}")
    module, cls = NODES[name]
    return getattr(importlib.import_module(module), cls)


def spin_until_shutdown(executor) -> None:
    """``executor.spin()``, returning when its context is shut down from another thread.

    rclpy reports that as ``ExternalShutdownException``, or, when the shutdown lands while
    the executor builds its wait set, as ``RCLError`` (seen in CI, 2026-12-01), or as
    ``InvalidHandle`` when the nodes' entities are being destroyed at that moment (seen in a
    test teardown, 2026-12-02), or as ``AttributeError`` on a guard condition already
    released (``'NoneType' object has no attribute 'handle'``, seen in CI the same day):
    all the same clean end.  Any of these while the context is still up and the executor
    not shut down is a real failure and is raised.
    """
    from rclpy._rclpy_pybind11 import InvalidHandle, RCLError
    from rclpy.executors import ExternalShutdownException

    try:
        executor.spin()
    except ExternalShutdownException:
        pass
    except (RCLError, InvalidHandle, AttributeError):
        # rclpy has no public "is shut down" for an executor; its spin loop reads this flag.
        if executor.context.ok() and not getattr(executor, "_is_shutdown", False):
            raise


def run_nodes(names: Sequence[str], *, params_files: Sequence[str | Path] = (),
              ros_args: Sequence[str] = (), context=None, domain_id: int | None = None,
              threads: int = 0, on_ready=None, autostart: bool = True) -> int:
    """Start the named nodes in this process on one MultiThreadedExecutor; spin until shutdown.

    Args:
        names: node names (keys of :data:`NODES`); each node is created with its default name
            (remappable with ``--ros-args -r __node:=...`` for a single node).
        params_files, ros_args: see :func:`ros_arguments`.
        context: an rclpy Context to use (default: the global one, with SIGINT/SIGTERM
            handlers); it is initialised here, on ``domain_id`` if given (else
            ``ROS_DOMAIN_ID``).
        threads: executor threads (0 = max(4, CPUs)).
        on_ready: optional callable(nodes, executor) called once the nodes exist.
        autostart: configure and activate the managed (lifecycle) nodes once their
            parameters are checked; False leaves them unconfigured, for an operator or a
            lifecycle manager (``cwfs-ros lifecycle set NODE configure``).

    Returns:
        Process exit code (0 after a clean shutdown, 2 when a node could not start).
    """
    ensure_fastdds_profile()
    checked = _checked_arguments(names, params_files, ros_args)
    if checked is None:
        return 2
    classes, argv, files = checked
    ctx = _init_context(context, argv, domain_id)
    if ctx is None:
        return 2

    from cwfs_ros.ros.executor import MultiThreadedExecutor

    nodes = []
    executor = None
    code = 0
    try:
        if not _create_nodes(names, classes, ctx, argv, files, nodes, autostart):
            return 2
        executor = MultiThreadedExecutor(num_threads=threads or max(4, os.cpu_count() or 1),
                                         context=ctx)
        for n in nodes:
            executor.add_node(n)
        if on_ready is not None:
            on_ready(nodes, executor)
        spin_until_shutdown(executor)
    except KeyboardInterrupt:
        code = 0
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        for n in nodes:
            try:
                n.destroy_node()
            except Exception:  # noqa: BLE001, S110 - best effort at shutdown
                pass
        ctx.try_shutdown()
    return code


def _checked_arguments(names: Sequence[str], params_files: Sequence[str | Path],
                       ros_args: Sequence[str]) -> tuple[list[type], list[str], list[Path]] | None:
    """(node classes, argv, parameter files), every file read as YAML before rcl reads it;
    None, with the reason on stderr, if a name or a file is wrong."""
    from cwfs_ros.errors import ParamsFileError
    from cwfs_ros.ros.params import read_params_file

    try:
        classes = [load_node_class(n) for n in names]
        argv = ["cwfs-ros", *ros_arguments(params_files, ros_args)]
        files = _params_files_of(argv)
        for f in files:
            read_params_file(f)
    except (LaunchError, ParamsFileError) as exc:
        print(f"cwfs-ros: error: {exc}", file=sys.stderr)
        return None
    return classes, argv, list(files)


def _init_context(context, argv: Sequence[str], domain_id: int | None):
    """``context`` (or the global one) initialised with ``argv``; None, with the reason on
    stderr, if rcl refuses the arguments."""
    import rclpy

    try:
        if context is None:
            rclpy.init(args=argv, domain_id=domain_id)
            return rclpy.get_default_context()
        rclpy.init(args=argv, context=context, domain_id=domain_id)
        return context
    except Exception as exc:  # noqa: BLE001 - rcl's RCLError for bad --ros-args
        print(f"cwfs-ros: error: ROS could not start: {' '.join(str(exc).split())}",
              file=sys.stderr)
        return None


def _create_nodes(names: Sequence[str], classes: Sequence[type], ctx, argv: Sequence[str],
                  files: Sequence[Path], nodes: list, autostart: bool) -> bool:
    """Create the nodes into ``nodes``, check every parameter name, then configure and
    activate the managed ones (``autostart``); False, with the reason on stderr, if any
    step failed.  Managed nodes start only once their parameters are known good: a
    misspelt override never reaches a running controller."""
    for name, cls in zip(names, classes, strict=True):
        if not _start_node(name, lambda cls=cls: nodes.append(_construct(cls, ctx))):
            return False
    kinds = {n.get_name(): declared_kinds(n) for n in nodes}
    problems = [msg for n, k in kinds.items() for msg in check_declared(files, n, k)]
    problems += check_overrides(argv, kinds)
    if problems:
        print("cwfs-ros: error: parameter problems; not running:\n  "
              + "\n  ".join(problems), file=sys.stderr)
        return False
    return all(_start_node(name, node.start) for name, node in zip(names, nodes, strict=True)
               if autostart and _is_managed(node))


def _is_managed(node_or_class) -> bool:
    from cwfs_ros.ros.common import ManagedNode

    cls = node_or_class if isinstance(node_or_class, type) else type(node_or_class)
    return issubclass(cls, ManagedNode)


def _construct(cls: type, ctx):
    """A node of ``cls``; a managed one unconfigured (started after the parameter check)."""
    return cls(context=ctx, autostart=False) if _is_managed(cls) else cls(context=ctx)


def _start_node(name: str, step) -> bool:
    """Run a start-up step of node ``name``; on failure say why on stderr and return False."""
    try:
        step()
        return True
    except Exception as exc:  # noqa: BLE001 - report any start-up failure clearly
        print(f"cwfs-ros: error: {name} could not start: {type(exc).__name__}: {exc}",
              file=sys.stderr)
        return False


def _params_files_of(argv: Sequence[str]) -> list[Path]:
    """Every ``--params-file`` of an rcl command line, in order."""
    return [Path(argv[i + 1]) for i, a in enumerate(argv[:-1]) if a == "--params-file"]


_KINDS = {1: "bool", 2: "integer", 3: "double", 4: "string", 5: "byte_array",
          6: "bool_array", 7: "integer_array", 8: "double_array", 9: "string_array"}


def declared_kinds(node) -> dict[str, str]:
    """Name -> kind (:func:`cwfs_ros.ros.params.yaml_kind` names) of a node's declared
    parameters."""
    names = node.list_parameters([], 0).names
    return {n: _KINDS.get(int(node.get_parameter(n).type_.value), "unset") for n in names}


def _split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    argv = list(argv)
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []


def run_node_main(name: str, argv: Sequence[str] | None = None) -> int:
    """``ros2 run``-style main of one node: ``NAME [--params FILE] [--ros-args ...]``."""
    limit_blas_threads()
    keep_freed_memory()  # large messages reuse the heap's pages (runtime.memory)
    own, ros = _split_ros_args(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog=name, description=f"Run {name} (cwfs_ros).")
    ap.add_argument("--params", action="append", default=[], metavar="FILE",
                    help="extra ROS parameter YAML over config/params.yaml (repeatable)")
    ap.add_argument("--no-autostart", action="store_true",
                    help="leave the node unconfigured (cwfs-ros lifecycle set NODE configure)")
    args = ap.parse_args(own)
    return run_nodes([name], params_files=args.params, ros_args=ros,
                     autostart=not args.no_autostart)


# -------------------------------------------------------------------- argparse subcommands
def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--params", action="append", default=[], metavar="FILE",
                   help="ROS parameter YAML overlaid on config/params.yaml (repeatable; "
                        "ros__parameters keyed by node name)")
    p.add_argument("--no-autostart", action="store_true",
                   help="leave wavefront_node and ofc_node unconfigured (managed nodes: "
                        "configure and activate them with `cwfs-ros lifecycle set NODE "
                        "configure|activate`); by default they are configured and activated")
    p.add_argument("--threads", type=int, default=0,
                   help="executor threads (default max(4, CPUs))")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="everything after this goes to ROS (-p name:=value, -r, "
                        "--params-file, --log-level ...)")


def sim_params_file() -> Path:
    """config/sim.yaml: the simulated loop's settings, loaded after params.yaml with --sim."""
    return config_dir() / "sim.yaml"


# rcl's discovery range; read when the context is initialised.
DISCOVERY_ENV = "ROS_AUTOMATIC_DISCOVERY_RANGE"
SIM_DISCOVERY_RANGE = "LOCALHOST"


def cmd_bringup(args: argparse.Namespace) -> int:
    names = list(BRINGUP_NODES) + ([SIM_NODE] if args.sim else [])
    files = ([sim_params_file()] if args.sim else []) + list(args.params)
    if args.sim and not args.visible:
        # A simulated loop must never reach real actuators: its corrections stay on this
        # host (where `cwfs-ros topic echo` still sees them), never on the network.
        os.environ[DISCOVERY_ENV] = SIM_DISCOVERY_RANGE
        print(f"cwfs-ros bringup: --sim: DDS discovery limited to this host "
              f"({DISCOVERY_ENV}={SIM_DISCOVERY_RANGE}; --visible to open it)",
              file=sys.stderr, flush=True)
    return run_nodes(names, params_files=files, ros_args=args.ros_args or [],
                     threads=args.threads, autostart=not args.no_autostart)


def cmd_node(args: argparse.Namespace) -> int:
    if args.name == "list":  # `node list`, as `ros2 node list`
        from cwfs_ros.ros.tools import node_list

        return node_list(args.all, args.spin_time)
    return run_nodes([args.name], params_files=args.params, ros_args=args.ros_args or [],
                     threads=args.threads, autostart=not args.no_autostart)


def add_bringup_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``bringup`` on an argparse subparsers object (sets ``func``)."""
    p = subparsers.add_parser(
        "bringup", help="run wavefront_node + ofc_node (+ camera_sim_node) in one process",
        description="Run the cwfs_ros nodes composed in one process on a MultiThreadedExecutor "
                    "(like a launch file). Parameters: config/params.yaml, then --params "
                    "files, then --ros-args.")
    p.add_argument("--sim", action="store_true",
                   help="also run camera_sim_node (cwfs_ros.ros.camera_sim_node), with "
                        "config/sim.yaml over config/params.yaml")
    p.add_argument("--visible", action="store_true",
                   help="with --sim: let other hosts on the DDS domain discover the graph "
                        "(by default a simulated loop is kept to this host, so that its "
                        "corrections never reach a real telescope's actuators)")
    _add_common(p)
    p.set_defaults(func=cmd_bringup)
    return p


def add_node_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``node NAME`` on an argparse subparsers object (sets ``func``)."""
    from cwfs_ros.ros.tools import add_node_list_arguments

    p = subparsers.add_parser(
        "node", help="run one cwfs_ros node, or list the running nodes (node list)",
        description="Run one node (like `ros2 run cwfs_ros NAME`), or list the nodes of the "
                    "running graph (`node list`, like `ros2 node list`).")
    p.add_argument("name", choices=[*sorted(NODES), "list"],
                   help="node to run, or `list`")
    _add_common(p)
    add_node_list_arguments(p)
    p.set_defaults(func=cmd_node)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cwfs_ros.ros.launch bringup|node ...`` (the same subcommands as cwfs-ros)."""
    limit_blas_threads()
    keep_freed_memory()  # large messages reuse the heap's pages (runtime.memory)
    ap = argparse.ArgumentParser(prog="python -m cwfs_ros.ros.launch",
                                 description="Start cwfs_ros nodes.")
    sub = ap.add_subparsers(dest="command", required=True)
    add_bringup_parser(sub)
    add_node_parser(sub)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
