"""Shared pytest fixtures: repository root and isolated ROS 2 contexts.

Every ROS test gets its own ``rclpy.Context`` on its own DDS domain id, so tests
(and concurrent pytest runs on one host) do not discover each other's nodes; discovery is
kept to this host, so a suite running on another machine does not either.
Subprocess nodes started by a test should get ``ROS_DOMAIN_ID=<ros_domain>``.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# Same settings as `make test`, for a bare `pytest` run. Both are read at import /
# participant-creation time, so they must be set before rclpy or messages load.
os.environ.setdefault("ROS_PYTHON_CHECK_FIELDS", "1")
# One BLAS thread, as the entry points set it (cwfs_ros.runtime.threads).
from cwfs_ros.runtime.threads import limit_blas_threads  # noqa: E402

limit_blas_threads()
os.environ.setdefault(
    "FASTRTPS_DEFAULT_PROFILES_FILE", str(REPO_ROOT / "config" / "fastdds_profile.xml")
)

from cwfs_ros.ros.launch import DISCOVERY_ENV  # noqa: E402

# Every participant of the suite stays on this host. With the default range (SUBNET) each
# one announces itself by multicast on the network, and a machine next to this one running
# the same suite (same commit, same domain ids) joins its graphs: a foreign publisher on a
# test's topic, a foreign node of the same name whose services cannot be reached. LOCALHOST
# does not separate processes on this host: the domain ids do that.
TEST_DISCOVERY_RANGE = "LOCALHOST"
os.environ[DISCOVERY_ENV] = TEST_DISCOVERY_RANGE

# CI (`.ci/run` sets CWFS_CI=1) replays the same hypothesis examples every run and keeps no
# example database: a landing is decided by the code, not by which random inputs came up.
# Local runs keep exploring new examples.
if os.environ.get("CWFS_CI") == "1":
    from hypothesis import settings

    settings.register_profile("ci", derandomize=True, database=None)
    settings.load_profile("ci")

_N_DOMAINS = 102  # ROS-recommended ids 0..101 stay clear of the ephemeral port range
_domain_counter = itertools.count()
_domain_base = (os.getpid() * 37) % _N_DOMAINS
# Never the domain a graph of the user's may run on: the default (0) and the shell's own.
_USER_DOMAINS = {0} | ({int(os.environ["ROS_DOMAIN_ID"]) % _N_DOMAINS}
                      if os.environ.get("ROS_DOMAIN_ID", "").isdigit() else set())


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(autouse=True)
def _discovery_on_this_host(monkeypatch):
    """Every test starts with discovery kept to this host, whatever code run by an earlier
    test left in the environment (``bringup --sim`` sets the range for the rest of its
    process; the demo sets OFF while its nodes start)."""
    monkeypatch.setenv(DISCOVERY_ENV, TEST_DISCOVERY_RANGE)


@pytest.fixture(autouse=True, scope="module")
def _ros_home_module(tmp_path_factory):
    """``$ROS_HOME`` of a module's shared graphs: a directory of its own (ofc_node keeps its
    state under ``$ROS_HOME`` by default, and one module's visits must not be another's)."""
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_HOME", str(tmp_path_factory.mktemp("ros_home")))
    yield
    mp.undo()


@pytest.fixture(autouse=True)
def _ros_home(_ros_home_module, tmp_path_factory, monkeypatch):
    """``$ROS_HOME`` of one test (nodes in this process and the processes it starts): no
    state file is shared between tests, and none is written to ``~/.ros``."""
    monkeypatch.setenv("ROS_HOME", str(tmp_path_factory.mktemp("ros_home")))


def next_domain() -> int:
    """A domain id in 1..101, never the shell's ``ROS_DOMAIN_ID``; one not used by this
    pytest process for the last ~100 uses (the suite needs a few more than that: a test's
    participants are gone long before its domain comes round again)."""
    while True:
        d = (_domain_base + next(_domain_counter)) % _N_DOMAINS
        if d not in _USER_DOMAINS:
            return d


@pytest.fixture
def ros_domain() -> int:
    """A domain id of its own for one test (:func:`next_domain`)."""
    return next_domain()


@pytest.fixture(scope="module")
def ros_domain_module() -> int:
    """A domain id of its own for a module's shared graph (:func:`next_domain`)."""
    return next_domain()


@pytest.fixture
def ros_context(ros_domain):
    """An initialised ``rclpy.Context`` on ``ros_domain``; shut down after the test."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        yield ctx
    finally:
        ctx.try_shutdown()


def wait_for(cond, timeout: float, what: str) -> None:
    """Poll ``cond()`` every 10 ms until true; fail the test after ``timeout`` seconds."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def spin_thread(executor) -> threading.Thread:
    """A daemon thread (not started) spinning ``executor`` until the test shuts its context
    down (:func:`cwfs_ros.ros.launch.spin_until_shutdown`: a bare
    ``Thread(target=executor.spin)`` ends with an unhandled-thread-exception warning when the
    shutdown races the executor's wait set)."""
    from cwfs_ros.ros.launch import spin_until_shutdown

    return threading.Thread(target=spin_until_shutdown, args=(executor,), daemon=True)


@pytest.fixture
def spin(ros_context):
    """The project's executor spinning in a thread on the test's context; yields
    ``add(node)``, and destroys the added nodes after the test."""
    from cwfs_ros.ros.executor import MultiThreadedExecutor

    ex = MultiThreadedExecutor(num_threads=4, context=ros_context)
    th = spin_thread(ex)
    nodes = []

    def add(node):
        nodes.append(node)
        ex.add_node(node)
        return node

    th.start()
    yield add
    ex.shutdown(timeout_sec=2.0)
    for n in nodes:
        n.destroy_node()


def of(msgs, stamp: int) -> list:
    """The messages of ``msgs`` (a list a subscription appends to) whose header stamp is
    ``stamp`` [ns]."""
    from cwfs_ros.ros.common import stamp_to_ns

    return [m for m in list(msgs) if stamp_to_ns(m.header.stamp) == stamp]


def quiet_ofc_node(ctx, **params):
    """An ``OfcNode`` on ``ctx`` with no rotator to follow (``rotator_angle_source: fixed``),
    its /diagnostics every 0.2 s, and ``params`` over the bundled parameters."""
    from rclpy.parameter import Parameter

    from cwfs_ros.ros.ofc_node import OfcNode

    over = {"rotator_angle_source": "fixed", "diagnostics_period_s": 0.2, **params}
    return OfcNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                     for k, v in over.items()])


def vector_msg(stamp_ns: int, zernikes_nm, uncertainty_nm: float = 10.0):
    """A ``WavefrontVector`` as a wavefront node publishes a visit of four valid corners,
    one donut pair each, built field by field (not with the package's converter)."""
    import numpy as np
    from cwfs_msgs.msg import WavefrontVector

    m = WavefrontVector()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    m.zernikes_nm = np.asarray(zernikes_nm, dtype=np.float64)
    m.corner_valid = [True] * 4
    m.corners = ["R00", "R04", "R40", "R44"]
    m.uncertainty_nm = np.full(m.zernikes_nm.size, float(uncertainty_nm))
    m.n_pairs = [1] * 4
    return m


class VectorProducer:
    """A node named ``name`` on its own context on ``domain``: it publishes vectors on
    ``aos/wfs/wavefront`` and records the corrections by stamp, spinning in a thread."""

    def __init__(self, domain: int, name: str = "wavefront_node") -> None:
        import rclpy
        from cwfs_msgs.msg import DofCorrection, WavefrontVector

        from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns
        from cwfs_ros.ros.executor import MultiThreadedExecutor

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.ex = MultiThreadedExecutor(num_threads=2, context=self.ctx)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.ex.add_node(self.node)
        self.pub = self.node.create_publisher(WavefrontVector, "aos/wfs/wavefront",
                                              OUTPUT_QOS)
        self.got: dict[int, list] = {}
        self.node.create_subscription(
            DofCorrection, "aos/ofc/dof_correction",
            lambda m: self.got.setdefault(stamp_to_ns(m.header.stamp), []).append(m),
            OUTPUT_QOS)
        self._th = spin_thread(self.ex)
        self._th.start()

    def send(self, stamp_ns: int, zernikes_nm, timeout_s: float = 30.0):
        """Publish the visit and return the correction of ``stamp_ns`` it brings."""
        seen = len(self.got.get(stamp_ns, []))
        self.pub.publish(vector_msg(stamp_ns, zernikes_nm))
        wait_for(lambda: len(self.got.get(stamp_ns, [])) > seen, timeout_s,
                 f"the correction of the visit stamped {stamp_ns}")
        return self.got[stamp_ns][-1]

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self._th.join(5)


@pytest.fixture
def r00_graph(ros_context):
    """A wavefront node serving R00 (the bundled parameters but one worker, a 1-s visit
    timeout and ``params``) and a tester node publishing its two image topics and recording
    its outputs. Yields ``start(tester="tester", **params) -> (wavefront node, tester node,
    {side: publisher}, [CornerWavefront], [WavefrontVector])``, ready and discovered."""
    from cwfs_msgs.msg import CornerWavefront, WavefrontVector
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS
    from cwfs_ros.ros.executor import MultiThreadedExecutor
    from cwfs_ros.ros.wavefront_node import WavefrontNode

    ex = MultiThreadedExecutor(num_threads=4, context=ros_context)
    th = spin_thread(ex)
    made = []

    def start(tester: str = "tester", **params):
        import rclpy

        over = {"corners": ["R00"], "workers": 1, "visit_timeout_s": 1.0, **params}
        wf = WavefrontNode(context=ros_context, parameter_overrides=[
            Parameter(k, value=v) for k, v in over.items()])
        node = rclpy.create_node(tester, context=ros_context)
        made.extend([wf, node])
        ex.add_node(wf)
        ex.add_node(node)
        pub = {s: node.create_publisher(Image, f"aos/wfs/R00/{s}/image", IMAGE_QOS)
               for s in ("intra", "extra")}
        corner, vector = [], []
        node.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront", corner.append,
                                 OUTPUT_QOS)
        node.create_subscription(WavefrontVector, "aos/wfs/wavefront", vector.append,
                                 OUTPUT_QOS)
        wait_for(lambda: wf.ready, 60, "warm-up")
        wait_for(lambda: all(p.get_subscription_count() for p in pub.values()), 10,
                 "discovery")
        return wf, node, pub, corner, vector

    th.start()
    yield start
    ex.shutdown(timeout_sec=2.0)
    for n in made:
        n.destroy_node()

def kill_group(proc) -> None:
    """SIGKILL a process started with ``start_new_session=True`` and its whole group."""
    import signal

    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """In CI (CWFS_CI=1) a skipped test fails the run.

    The suite's ``importorskip`` calls keep a bare ``pytest`` usable where ROS or the
    simulator is missing, but in CI every dependency is installed by the bootstrap: a skip
    there means an import broke, and a green run would hide the tests it skipped.
    """
    if os.environ.get("CWFS_CI") != "1":
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    skipped = reporter.stats.get("skipped", []) if reporter is not None else []
    if not skipped:
        return
    lines = []
    for rep in skipped:
        reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
        lines.append(f"  {rep.nodeid}: {reason}")
    message = (f"CI: {len(skipped)} test(s) or module(s) skipped; every test must run in CI:\n"
               + "\n".join(lines))
    if reporter is not None:
        reporter.ensure_newline()
        reporter.write_line(message, red=True)
    else:
        print(message)
    if session.exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
