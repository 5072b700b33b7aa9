"""wavefront_node and ofc_node as managed (lifecycle) nodes, and `cwfs-ros lifecycle`.

The nodes run in this process on the test's own DDS domain; the CLI is run through the real
command line (``cli.main``), which starts its own rclpy context and reaches the nodes'
``lifecycle_msgs`` services over DDS.  Corrections are watched by a real subscriber.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import quiet_ofc_node, wait_for

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.lifecycle import TransitionCallbackReturn  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros import cli  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ros import launch as L  # noqa: E402
from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402

SEC = 1_000_000_000
T0 = 5000 * SEC
VISIT = 40 * SEC
# lifecycle_msgs/State ids, as `ros2 lifecycle get` prints them.
STATES = {"unconfigured": 1, "inactive": 2, "active": 3, "finalized": 4}


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _vector(stamp: int, z: np.ndarray) -> WavefrontVector:
    m = WavefrontVector()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
    m.zernikes_nm = np.asarray(z, dtype=float)
    m.corner_valid = [True] * 4
    m.corners = ["R00", "R04", "R40", "R44"]
    return m


@pytest.fixture
def loop(ros_domain, ros_context, spin, monkeypatch):
    """A started ofc_node (no rotator) and a tester publishing vectors and recording the
    corrections and ofc_node's /diagnostics, spinning on the test's domain."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    ofc = spin(quiet_ofc_node(ros_context))
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    out: list[DofCorrection] = []
    diag: list[dict[str, str]] = []
    tester.create_subscription(DofCorrection, "aos/ofc/dof_correction", out.append, OUTPUT_QOS)
    tester.create_subscription(
        DiagnosticArray, "/diagnostics",
        lambda a: diag.extend({"message": s.message, **{v.key: v.value for v in s.values}}
                              for s in a.status if s.name.startswith("ofc_node")), 10)
    wait_for(lambda: pub.get_subscription_count() > 0 and
             ofc.pub.get_subscription_count() > 0, 10, "discovery")
    return ofc, pub, out, diag


def test_a_deactivated_ofc_node_publishes_no_correction_until_activated(loop, capsys):
    ofc, pub, out, diag = loop
    y = C.OFCSolver(C.SensitivityMatrix.from_bundled(), band="r").intrinsic_nm
    rng = np.random.default_rng(24)

    def visit(k: int) -> None:
        pub.publish(_vector(T0 + k * VISIT, y + rng.normal(0.0, 5.0, y.shape)))

    assert _run(capsys, "lifecycle", "get", "ofc_node") == (0, "active [3]\n", "")
    visit(0)
    wait_for(lambda: len(out) == 1, 10, "the first correction")
    assert out[0].valid, out[0].status

    code, text, err = _run(capsys, "lifecycle", "set", "ofc_node", "deactivate")
    assert (code, text) == (0, "Transitioning successful\n"), err
    assert ofc.lifecycle_state == "inactive"
    visit(1)
    wait_for(lambda: ofc.guard_counts.counts["inactive"] == 1, 10, "the vector taken")
    time.sleep(1.5)  # a correction would be out in well under this (the first took less)
    assert len(out) == 1, [m.status for m in out[1:]]
    assert ofc.solver.n_steps == 1  # not integrated either
    # /diagnostics goes on, and says why nothing comes out.
    n = len(diag)
    wait_for(lambda: any(d.get("lifecycle") == "inactive" for d in diag[n:]), 5,
             "/diagnostics of the inactive node")
    inactive = next(d for d in diag[n:] if d.get("lifecycle") == "inactive")
    assert inactive["message"].startswith("inactive: vectors are not integrated")
    assert inactive["guard.inactive"] == "1"

    code, text, err = _run(capsys, "lifecycle", "set", "/ofc_node", "activate")
    assert (code, text) == (0, "Transitioning successful\n"), err
    assert _run(capsys, "lifecycle", "get", "ofc_node")[1] == "active [3]\n"
    visit(2)
    wait_for(lambda: len(out) == 2, 10, "the correction after activation")
    assert out[1].valid, out[1].status
    assert stamp_to_ns(out[1].header.stamp) == T0 + 2 * VISIT
    assert ofc.solver.n_steps == 2


def test_an_unavailable_transition_is_refused_with_the_state_and_a_nonzero_exit(loop, capsys):
    ofc, *_ = loop
    code, text, err = _run(capsys, "lifecycle", "set", "ofc_node", "activate")
    assert code == 1 and text == ""
    assert "'activate' is not available from state active" in err, err
    assert "available: deactivate, shutdown" in err, err
    code, text, err = _run(capsys, "lifecycle", "set", "ofc_node", "pause")
    assert code == 1 and "'pause' is not available" in err, err
    assert ofc.lifecycle_state == "active"
    code, text, _ = _run(capsys, "lifecycle", "list", "ofc_node")
    assert code == 0
    assert [line for line in text.splitlines() if line.startswith("- ")] == [
        "- deactivate [4]", "- shutdown [7]"], text
    # A node that is not a managed one, and one that is not there.
    code, _, err = _run(capsys, "lifecycle", "get", "tester", "--timeout", "4")
    assert code == 1 and "/tester is not a managed (lifecycle) node" in err, err
    code, _, err = _run(capsys, "lifecycle", "get", "no_such_node", "--timeout", "1")
    assert code == 1 and "node /no_such_node not found" in err, err


def test_bringup_starts_both_nodes_active_and_no_autostart_leaves_them_for_the_cli(
        ros_domain, monkeypatch, capsys):
    """``run_nodes`` as ``cwfs-ros bringup`` calls it: both nodes active by default; with
    autostart off, unconfigured, then taken through the whole lifecycle from the CLI."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    small = ["-p", "wavefront_node:corners:=[R00]", "-p", "wavefront_node:workers:=1"]

    def run(autostart: bool, script) -> dict:
        ctx = rclpy.Context()
        seen: dict = {}

        def on_ready(nodes, _executor):
            seen["states"] = {n.get_name(): n.lifecycle_state for n in nodes}

            def drive():
                try:
                    seen["cli"] = [_run(capsys, *argv) for argv in script]
                    seen["final"] = {n.get_name(): n.lifecycle_state for n in nodes}
                finally:
                    ctx.try_shutdown()

            threading.Thread(target=drive, daemon=True).start()

        code = L.run_nodes(["wavefront_node", "ofc_node"], ros_args=small, context=ctx,
                           domain_id=ros_domain, on_ready=on_ready, autostart=autostart)
        assert code == 0
        return seen

    seen = run(True, [("lifecycle", "get", "wavefront_node")])
    assert seen["states"] == {"wavefront_node": "active", "ofc_node": "active"}
    assert seen["cli"] == [(0, "active [3]\n", "")]

    steps = [("get", "unconfigured"), ("configure", "inactive"), ("activate", "active"),
             ("deactivate", "inactive"), ("cleanup", "unconfigured"),
             ("shutdown", "finalized")]
    script = [("lifecycle", "get", "wavefront_node")]
    script += [("lifecycle", "set", "ofc_node", t) for t, _ in steps[1:]]
    script += [("lifecycle", "get", "ofc_node"), ("lifecycle", "set", "ofc_node", "configure")]
    seen = run(False, script)
    assert seen["states"] == {"wavefront_node": "unconfigured", "ofc_node": "unconfigured"}
    assert seen["cli"][0] == (0, "unconfigured [1]\n", ""), seen["cli"]
    for (code, text, err), (step, _) in zip(seen["cli"][1:-2], steps[1:], strict=True):
        assert (code, text) == (0, "Transitioning successful\n"), (step, err)
    assert seen["cli"][-2] == (0, "finalized [4]\n", "")
    code, text, err = seen["cli"][-1]
    assert code == 1 and text == "", err
    assert "'configure' is not available from state finalized; available: none" in err, err
    assert seen["final"] == {"wavefront_node": "unconfigured", "ofc_node": "finalized"}


def test_a_deactivated_wavefront_node_says_it_does_not_process_images(ros_context, spin):
    from cwfs_ros.ros.wavefront_node import WavefrontNode

    wf = spin(WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1)]))
    tester = spin(rclpy.create_node("camera", context=ros_context))
    pub = tester.create_publisher(Image, "aos/wfs/R00/intra/image", 10)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    assert wf.is_active
    assert wf.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    img = Image(height=8, width=8, encoding="32FC1", step=32, data=bytes(256))
    img.header.stamp.sec = 7000
    pub.publish(img)
    wait_for(lambda: wf.rejected.counts["inactive"] == 1, 10, "the image counted")
    assert wf.stats["images"] == 0  # not decoded, not paired
    assert "not processed: the node is inactive" in wf.rejected.last_message
    st = wf.diagnostics()
    kv = {v.key: v.value for v in st.values}
    assert st.message.startswith("inactive: images are not processed"), st.message
    assert (kv["lifecycle"], kv["rejected.inactive"]) == ("inactive", "1")
    # cleanup releases the workers; an unconfigured node still reports itself.
    assert wf.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert wf.pool is None and wf.lifecycle_state == "unconfigured"
    st = wf.diagnostics()
    assert st.message.startswith("unconfigured") and st.values[0].value == "unconfigured"
    # Configured again: a new pool, warmed, and images taken again.
    wf.start()
    wait_for(lambda: wf.ready, 30, "the new workers warm")
    pub.publish(img)
    wait_for(lambda: wf.stats["images"] == 1, 10, "the image taken once active")


def test_a_configure_that_fails_exits_nonzero_and_leaves_the_node_unconfigured(
        ros_context, ros_domain, spin, monkeypatch, capsys, tmp_path):
    """A managed node whose configure cannot succeed (its selection file is missing): the
    CLI says the transition failed (exit 1); the node stays unconfigured and reports the
    reason on /diagnostics as an error."""
    from cwfs_ros.ros.common import ERROR
    from cwfs_ros.ros.wavefront_node import WavefrontNode

    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    missing = tmp_path / "no_such_selection.yaml"
    wf = spin(WavefrontNode(context=ros_context, autostart=False, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("selection_config", value=str(missing))]))
    assert _run(capsys, "lifecycle", "get", "wavefront_node") == (0, "unconfigured [1]\n", "")
    code, text, err = _run(capsys, "lifecycle", "set", "wavefront_node", "configure")
    assert code == 1 and text == ""
    assert "Transitioning failed: /wavefront_node refused 'configure'" in err, err
    assert wf.lifecycle_state == "unconfigured" and wf.pool is None
    st = wf.diagnostics()
    assert st.level == ERROR and "configure failed" in st.message, st.message
    assert "no_such_selection.yaml" in st.message
