"""ofc_node killed at visit 5 and restarted: it continues from its persisted state.

ofc_node runs in its own process (``python -m cwfs_ros.ros.launch node ofc_node``, as a user
starts it) with ``state_file`` set; this process is the telescope: it publishes each visit's
76-vector, computed from its own state with the *ts_ofc* matrix while the controller uses
the bundled one, and applies each valid correction. After the correction of visit 5 the node
is SIGKILLed and started again. Expected: visit 5 sent again is refused (not applied twice),
visit 6 continues from the accumulated state (``dof_total`` carries on), and the wavefront
error keeps falling.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import VectorProducer, kill_group, vector_msg, wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection  # noqa: E402

from cwfs_ros import layout  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SEC = 1_000_000_000


def _start_ofc(domain: int, state_file: Path | None) -> subprocess.Popen:
    """ofc_node in a process of its own; ``state_file`` None: the shipped default."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    cmd = [sys.executable, "-m", "cwfs_ros.ros.launch", "node", "ofc_node", "--ros-args",
           "-p", "rotator_angle_source:=fixed"]
    if state_file is not None:
        cmd += ["-p", f"state_file:={state_file}"]
    return subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)




def test_ofc_node_killed_at_visit_5_continues_from_its_state(ros_domain, tmp_path):
    state_file = tmp_path / "ofc_state.json"
    truth = C.SensitivityMatrix.from_ts_ofc(fields_deg=C.corner_mid_field_points_deg())
    intrinsic = C.intrinsic_vector_nm("r", truth.field_points_deg)
    telescope = np.zeros(layout.N_DOF)
    telescope[[1, 2, 6, 8]] = [500.0, -300.0, 400.0, 0.004]  # decentres and a camera tilt
    producer = VectorProducer(ros_domain, "telescope")
    # visits 40 s apart (the LSST cadence), all in the past of the node's clock
    t0 = (time.time_ns() // SEC) * SEC - 400 * SEC
    errors: list[float] = []
    noise = np.random.default_rng(12)

    def visit(k: int) -> DofCorrection:
        wf = truth.matrix_nm @ telescope
        errors.append(float(np.linalg.norm(wf)))
        # photon noise
        return producer.send(t0 + k * 40 * SEC,
                             intrinsic + wf + noise.normal(0.0, 1.0, layout.N_MEAS))

    proc = _start_ofc(ros_domain, state_file)
    try:
        wait_for(lambda: producer.pub.get_subscription_count() > 0, 60, "ofc_node to start")
        for k in range(1, 6):
            d = visit(k)
            assert d.valid, d.status
            telescope += np.asarray(d.dof)
        total_5 = np.asarray(d.dof_total)
        saved = json.loads(state_file.read_text())
        assert saved["last_stamp_ns"] == t0 + 5 * 40 * SEC and saved["n_steps"] == 5
        kill_group(proc)
        wait_for(lambda: producer.pub.get_subscription_count() == 0, 30,
                 "the old node to vanish")
        proc = _start_ofc(ros_domain, state_file)
        wait_for(lambda: producer.pub.get_subscription_count() > 0, 60, "ofc_node to restart")
        again = visit(5)
        assert not again.valid and again.status.startswith("stale_visit"), again.status
        assert not np.any(again.dof)
        d6 = visit(6)
        assert d6.valid, d6.status
        np.testing.assert_allclose(np.asarray(d6.dof_total), total_5 + np.asarray(d6.dof),
                                   rtol=0, atol=1e-9 * (1 + np.abs(total_5).max()))
        telescope += np.asarray(d6.dof)
        visit(7)
        assert errors[-1] < errors[0] / 10, errors
        # a new node does not start from the prior: its uncertainty is the persisted one,
        # far below the prior of a first visit (0.2 x 6700 um for M2_dx)
        assert 0 < d6.dof_uncertainty[1] < 0.1 * 0.2 * 6700
    finally:
        kill_group(proc)
        producer.close()


def test_a_state_that_cannot_be_written_withholds_the_correction(ros_context, tmp_path):
    """state_file under a regular file (no directory can be made there): the visit is
    refused as state_not_saved, the controller is where it was, /diagnostics says ERROR;
    the restart guarantee is never silently lost."""
    from rclpy.parameter import Parameter

    from cwfs_ros.ros.ofc_node import OfcNode

    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    ofc = OfcNode(context=ros_context, parameter_overrides=[
        Parameter("state_file", value=str(blocker / "ofc.json")),
        Parameter("rotator_angle_source", value="fixed")])
    try:
        sent: list[DofCorrection] = []
        ofc.pub.publish = sent.append  # what the node publishes, without a subscriber
        x = np.zeros(layout.N_DOF)
        x[1] = 300.0
        sm = C.sensitivity_for_source("bundled")
        ofc._on_vector(vector_msg((time.time_ns() // SEC - 100) * SEC,
                                  C.intrinsic_vector_nm("r", sm.field_points_deg)
                                  + sm.matrix_nm @ x))
        assert len(sent) == 1 and not sent[0].valid, sent
        assert sent[0].status.startswith("state_not_saved"), sent[0].status
        assert ofc.solver.n_steps == 0 and not np.any(ofc.solver.dof_total)
        st = ofc.diagnostics()
        assert st.level == b"\x02" or st.level == 2, st.level  # ERROR
        assert "state_not_saved" in st.message
    finally:
        ofc.destroy_node()


def test_the_shipped_default_keeps_the_state_across_a_restart(ros_domain, tmp_path,
                                                             monkeypatch):
    """ofc_node started as a user starts it, without naming a state file: the state is kept
    under $ROS_HOME, so a visit applied before a SIGKILL is refused after the restart, and
    ~/reset clears the file."""
    from std_srvs.srv import Trigger

    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    default_file = tmp_path / "ros_home" / "cwfs_ros" / "ofc_node.state.json"
    sm = C.sensitivity_for_source("bundled")
    intrinsic = C.intrinsic_vector_nm("r", sm.field_points_deg)
    producer = VectorProducer(ros_domain)
    reset = producer.node.create_client(Trigger, "ofc_node/reset")
    t0 = (time.time_ns() // SEC) * SEC - 400 * SEC

    def visit(k: int) -> DofCorrection:
        x = np.zeros(layout.N_DOF)
        x[1] = 300.0 / k
        return producer.send(t0 + k * 40 * SEC, intrinsic + sm.matrix_nm @ x)

    proc = _start_ofc(ros_domain, None)
    try:
        wait_for(lambda: producer.pub.get_subscription_count() > 0, 60, "ofc_node to start")
        assert visit(1).valid and visit(2).valid
        assert json.loads(default_file.read_text())["n_steps"] == 2
        kill_group(proc)
        wait_for(lambda: producer.pub.get_subscription_count() == 0, 30,
                 "the old node to vanish")
        proc = _start_ofc(ros_domain, None)
        wait_for(lambda: producer.pub.get_subscription_count() > 0, 60, "ofc_node to restart")
        again = visit(2)
        assert not again.valid and again.status.startswith("stale_visit"), again.status
        assert visit(3).valid
        assert reset.wait_for_service(timeout_sec=20)
        fut = reset.call_async(Trigger.Request())
        wait_for(fut.done, 10, "the reset")
        assert fut.result().success, fut.result().message
        saved = json.loads(default_file.read_text())
        assert saved["n_steps"] == 0 and saved["last_stamp_ns"] is None, saved
    finally:
        kill_group(proc)
        producer.close()
