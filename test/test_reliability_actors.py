"""Who may act: camera_sim_node applies only a correction for a visit it published and has
not corrected, within the step limits; an impostor on the correction topic moves nothing,
and other publishers on the simulator's own topics are named on /diagnostics."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import wait_for

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import SimTruth  # noqa: E402
from test_camera_sim import correction, make_system, visit  # noqa: E402

from cwfs_ros.ofc.control import load_dof_spec  # noqa: E402
from cwfs_ros.ros.common import OUTPUT_QOS  # noqa: E402


def test_impostor_corrections_move_nothing(ros_domain):
    node, t, close = make_system(ros_domain)
    try:
        ignored = node.ignored.counts
        s1 = visit(t)
        state = node.dof_state
        max_step = load_dof_spec().max_step
        huge = np.zeros(50)
        huge[0] = 1e6  # 1e6 um of M2 piston
        small = 0.5 * max_step * np.sign(np.linspace(-1, 1, 50) + 0.01)
        cases = [(0, small, "not_our_visit"), (s1 + 1, small, "not_our_visit"),
                 (s1, huge, "step_limit")]
        for k, (stamp, dof, reason) in enumerate(cases):
            t.pub.publish(correction(dof, stamp_ns=stamp))
            wait_for(lambda k=k: node.stats["corrections_ignored"] == k + 1, 5, reason)
            assert ignored[reason] >= 1, (reason, dict(ignored))
        np.testing.assert_array_equal(node.dof_state, state)
        # The visit's own correction: applied once; the same stamp again: ignored.
        t.pub.publish(correction(small, stamp_ns=s1))
        wait_for(lambda: node.stats["corrections_applied"] == 1, 5, "applied")
        t.pub.publish(correction(small, stamp_ns=s1))
        wait_for(lambda: ignored["already_corrected"] == 1, 5, "repeat ignored")
        np.testing.assert_array_equal(node.dof_state, state + small)
        assert node.stats["corrections_applied"] == 1

        # Another publisher on the simulator's truth topic is named.
        t.node.create_publisher(SimTruth, "aos/sim/truth", OUTPUT_QOS)
        wait_for(lambda: "camera_sim_tester" in dict(
            (kv.key, kv.value) for kv in node.diagnostics().values)["foreign_publishers"], 10,
            "the other truth publisher named")
    finally:
        close()
