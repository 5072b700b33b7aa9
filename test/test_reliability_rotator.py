"""Stamps ahead of the clock: a spoofed camera_rotator sample must not hide the genuine ones,
and a vector stamped far ahead must neither be applied nor block the visits after it."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import spin_thread, vector_msg, wait_for

from cwfs_ros.ofc.rotator import RotatorHistory

SEC = 1_000_000_000


def test_a_sample_stamped_ahead_hides_no_genuine_sample():
    h = RotatorHistory(tolerance_s=2.0)
    now = 1000 * SEC
    assert h.add(now - 2 * SEC, 0.0, now_ns=now, max_future_s=1.0) is None
    # +9 s: beyond the clock tolerance, ignored
    assert "ahead of the clock" in h.add(now + 9 * SEC, np.deg2rad(30.0), now_ns=now,
                                          max_future_s=1.0)
    # +0.5 s: within it, kept, but the genuine samples that follow are kept too
    assert h.add(now + SEC // 2, np.deg2rad(30.0), now_ns=now, max_future_s=1.0) is None
    assert h.add(now - SEC, np.deg2rad(5.0), now_ns=now, max_future_s=1.0) is None
    assert h.add(now, np.deg2rad(10.0), now_ns=now, max_future_s=1.0) is None
    a, how = h.angle_deg(now - SEC)
    assert a == pytest.approx(5.0) and how == "interpolated"
    # the spoofed angle disagrees with its genuine neighbour: a visit there is refused
    a, why = h.angle_deg(now + SEC // 4)
    assert a is None and "slewing" in why
    # a second angle at a stamp held: that stamp is no longer trusted
    assert "two rotator angles" in h.add(now - SEC, np.deg2rad(6.0))
    a, why = h.angle_deg(now - SEC)
    assert a is None and "two camera rotator angles" in why


def test_a_full_history_drops_the_oldest_stamps():
    h = RotatorHistory(tolerance_s=0.5, max_samples=3)
    for k in (5, 1, 3, 4):
        assert h.add(k * SEC, 0.0) is None
    assert len(h) == 3 and h.angle_deg(1 * SEC)[0] is None  # 1 s was the oldest
    assert "older than every one" in h.add(2 * SEC, 0.0)


# ------------------------------------------------------------------ over DDS
rclpy = pytest.importorskip("rclpy")


@pytest.fixture
def ofc_loop(ros_domain):
    """ofc_node with the rotator from joint_states (its default) and a tester publishing the
    vectors and the joint states, recording the corrections."""
    from cwfs_msgs.msg import DofCorrection, WavefrontVector
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns
    from cwfs_ros.ros.executor import MultiThreadedExecutor
    from cwfs_ros.ros.ofc_node import OfcNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    ofc = OfcNode(context=ctx, parameter_overrides=[Parameter("diagnostics_period_s",
                                                              value=0.5)])
    tester = rclpy.create_node("tester", context=ctx)
    vec = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    joints = tester.create_publisher(JointState, "joint_states", OUTPUT_QOS)
    got: dict[int, list] = {}
    tester.create_subscription(
        DofCorrection, "aos/ofc/dof_correction",
        lambda m: got.setdefault(stamp_to_ns(m.header.stamp), []).append(m), OUTPUT_QOS)
    ex = MultiThreadedExecutor(num_threads=2, context=ctx)
    ex.add_node(ofc)
    ex.add_node(tester)
    th = spin_thread(ex)
    th.start()
    wait_for(lambda: vec.get_subscription_count() > 0 and joints.get_subscription_count() > 0,
             20, "discovery")
    try:
        yield ofc, vec, joints, got
    finally:
        ex.shutdown(timeout_sec=2.0)
        ofc.destroy_node()
        tester.destroy_node()
        ctx.try_shutdown()
        th.join(5)


def _joint(stamp_ns: int, angle_deg: float):
    from sensor_msgs.msg import JointState

    m = JointState()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, SEC)
    m.name = ["camera_rotator"]
    m.position = [float(np.deg2rad(angle_deg))]
    return m


def _vector(ofc, stamp_ns: int, angle_deg: float, dx_um: float = 300.0):
    """The vector of a telescope with an M2 decentre, seen by a camera at ``angle_deg``."""

    from cwfs_ros import layout

    at = ofc.solver.model.at(angle_deg)
    x = np.zeros(layout.N_DOF)
    x[1] = dx_um
    return vector_msg(stamp_ns, at.intrinsic_nm + at.H @ x)


def test_a_spoofed_rotator_sample_does_not_change_the_visits_angle(ofc_loop):
    ofc, vec, joints, got = ofc_loop
    t1 = time.time_ns() - 20 * SEC
    t0 = t1 - 2 * SEC
    ignored = ofc.stats
    joints.publish(_joint(t0, 0.0))
    wait_for(lambda: ofc.stats["rotator_samples"] == 1, 10, "the first genuine sample")
    # another process: the rotator at 30 deg, stamped 9 s ahead of the clock
    joints.publish(_joint(time.time_ns() + 9 * SEC, 30.0))
    wait_for(lambda: ignored["rotator_samples"] + ignored["rotator_samples_ignored"] == 2, 10,
             "the spoofed sample taken")
    joints.publish(_joint(t1, 15.0))  # the genuine rotator turned to 15 deg (7.5 deg/s)
    wait_for(lambda: ignored["rotator_samples"] + ignored["rotator_samples_ignored"] == 3, 10,
             "the next genuine sample taken")
    vec.publish(_vector(ofc, t1, 15.0))
    wait_for(lambda: t1 in got, 20, "the visit's correction")
    d = got[t1][0]
    assert d.valid, d.status
    assert d.rotator_angle_deg == pytest.approx(15.0, abs=1e-6)
    assert ignored["rotator_samples_ignored"] == 1 and "ahead of the clock" in str(
        ofc.refused.last_message)


def test_a_vector_stamped_far_ahead_is_refused_and_blocks_nothing(ofc_loop):
    ofc, vec, joints, got = ofc_loop
    now = time.time_ns()
    ahead = now + 55 * SEC
    joints.publish(_joint(ahead, 0.0))
    taken = ofc.stats
    wait_for(lambda: taken["rotator_samples"] + taken["rotator_samples_ignored"] == 1, 10,
             "the rotator sample taken")
    vec.publish(_vector(ofc, ahead, 0.0))
    wait_for(lambda: ahead in got, 20, "the answer to the vector stamped ahead")
    assert not got[ahead][0].valid and got[ahead][0].status.startswith("future_stamp")
    # the next genuine visit is taken, not refused as older than the one ahead
    t = now - 10 * SEC
    joints.publish(_joint(t, 0.0))
    wait_for(lambda: taken["rotator_samples"] + taken["rotator_samples_ignored"] == 2, 10,
             "the genuine sample taken")
    vec.publish(_vector(ofc, t, 0.0))
    wait_for(lambda: t in got, 20, "the next visit's correction")
    assert got[t][0].valid, got[t][0].status
    assert ofc.solver.n_steps == 1
