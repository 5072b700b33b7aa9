"""Who may act, over DDS: a consumer acts on a message only while its input topic has exactly
the publishers it expects, and an owner names every publisher endpoint on its topics beyond
its own, an impostor under its own node name included.

The impostors are nodes of another rclpy context (another DDS participant, as another process
would be) on the test's domain, named like the real producers.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from conftest import quiet_ofc_node, vector_msg, wait_for

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from cwfs_ros import layout  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402

SEC = 1_000_000_000


def good_vector(stamp_ns: int, dx_um: float = 300.0) -> WavefrontVector:
    """A vector a telescope with an M2 decentre of ``dx_um`` gives (bundled matrix, r band)."""
    sm = C.sensitivity_for_source("bundled")
    x = np.zeros(layout.N_DOF)
    x[1] = dx_um
    return vector_msg(stamp_ns, C.intrinsic_vector_nm("r", sm.field_points_deg)
                      + sm.matrix_nm @ x)


class Impostor:
    """A node of its own DDS participant on ``domain``, named ``name``, publishing ``msg_type``
    on ``topic``."""

    def __init__(self, domain: int, name: str, msg_type, topic: str) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.pub = self.node.create_publisher(msg_type, topic, OUTPUT_QOS)

    def close(self) -> None:
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _statuses(diag: list[DiagnosticArray], prefix: str) -> list[DiagnosticStatus]:
    return [st for arr in list(diag) for st in arr.status if st.name.startswith(prefix)]


def _values(st: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in st.values}


@pytest.fixture
def ofc_graph(ros_context, spin):
    """ofc_node (no rotator), the one legitimate vector producer (named wavefront_node) and an
    observer of the corrections and /diagnostics, on one context spinning in a thread."""
    ofc = spin(quiet_ofc_node(ros_context))
    owner = spin(rclpy.create_node("wavefront_node", context=ros_context))
    pub = owner.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    obs = spin(rclpy.create_node("observer", context=ros_context))
    got: dict[int, list[DofCorrection]] = {}
    obs.create_subscription(
        DofCorrection, "aos/ofc/dof_correction",
        lambda m: got.setdefault(stamp_to_ns(m.header.stamp), []).append(m), OUTPUT_QOS)
    diag: list[DiagnosticArray] = []
    obs.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 50)
    wait_for(lambda: pub.get_subscription_count() > 0, 20, "ofc_node to hear its producer")
    return ofc, pub, got, diag


def test_a_vector_is_integrated_only_while_its_topic_has_its_one_publisher(ofc_graph,
                                                                           ros_domain):
    ofc, pub, got, diag = ofc_graph
    t0 = (time.time_ns() // SEC - 1000) * SEC

    def send(p, k: int) -> int:
        stamp = t0 + k * 40 * SEC
        p.publish(good_vector(stamp, dx_um=150.0 * k))
        return stamp

    s1 = send(pub, 1)
    wait_for(lambda: s1 in got, 10, "the correction of visit 1")
    assert got[s1][0].valid, got[s1][0].status
    # Another process, its node named like the producer, sends a good-looking vector.
    imp = Impostor(ros_domain, "wavefront_node", WavefrontVector, "aos/wfs/wavefront")
    try:
        wait_for(lambda: imp.pub.get_subscription_count() > 0, 20, "the impostor to match")
        s2 = send(imp.pub, 2)
        untrusted = ofc.guard_counts.counts
        wait_for(lambda: untrusted["untrusted_source"] == 1, 10, "the impostor's vector refused")
        # While the impostor is there the producer's own vectors cannot be told from its
        # messages either: refused too.
        s3 = send(pub, 3)
        wait_for(lambda: untrusted["untrusted_source"] == 2, 10, "the next vector refused")
        wait_for(lambda: any(st.level == DiagnosticStatus.ERROR
                             and "untrusted_source" in st.message
                             and "/wavefront_node" in st.message
                             for st in _statuses(diag, "ofc_node")), 10,
                 "ERROR on /diagnostics naming the publishers")
        time.sleep(0.5)
        assert s2 not in got and s3 not in got, "no correction answers an untrusted vector"
        assert ofc.solver.n_steps == 1
        assert ofc.stats["vectors_untrusted"] == 2
    finally:
        imp.close()
    # The impostor gone (and its match settled), the producer is trusted again.
    wait_for(lambda: ofc.trust.problem() is None, 15, "the topic back to its one publisher")
    s4 = send(pub, 4)
    wait_for(lambda: s4 in got, 10, "the correction of visit 4")
    assert got[s4][0].valid and ofc.solver.n_steps == 2, got[s4][0].status


def test_an_impostor_under_the_owners_name_is_reported(ofc_graph, ros_domain):
    ofc, _, _, diag = ofc_graph
    imp = Impostor(ros_domain, "ofc_node", DofCorrection, "aos/ofc/dof_correction")
    try:
        def reported() -> bool:
            for st in _statuses(diag, "ofc_node")[-5:]:
                foreign = _values(st).get("foreign_publishers", "")
                if "2 endpoints named /ofc_node" in foreign and "gid" in foreign:
                    return st.level >= DiagnosticStatus.WARN
            return False

        wait_for(reported, 15, "the second ofc_node endpoint on the correction topic reported")
    finally:
        imp.close()


def test_a_second_node_under_the_same_name_is_reported_even_without_publishers(
        ofc_graph, ros_domain):
    """Another process's node named ofc_node that publishes nothing: its parameter and
    lifecycle services collide with the real node's, so /diagnostics warns, the node's log
    says so once, and each status names its process."""
    from rcl_interfaces.msg import Log
    from rclpy.executors import SingleThreadedExecutor

    ofc, _, _, diag = ofc_graph
    logs: list[Log] = []
    listener = rclpy.create_node("log_listener", context=ofc.context)
    listener.create_subscription(Log, "/rosout", logs.append, 100)
    ex = SingleThreadedExecutor(context=ofc.context)
    ex.add_node(listener)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    twin = rclpy.create_node("ofc_node", context=ctx)
    try:
        def reported() -> bool:
            for st in _statuses(diag, "ofc_node")[-5:]:
                foreign = _values(st).get("foreign_publishers", "")
                if foreign.startswith("node name: 2 nodes named /ofc_node in the graph"):
                    return st.level >= DiagnosticStatus.WARN
            return False

        wait_for(reported, 15, "the second node named ofc_node reported")
        said = [m for m in logs if m.name == "ofc_node" and m.level == Log.WARN
                and "node name: 2 nodes named /ofc_node" in m.msg]
        deadline = time.monotonic() + 10
        while not said and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.2)
            said = [m for m in logs if m.name == "ofc_node" and m.level == Log.WARN
                    and "node name: 2 nodes named /ofc_node" in m.msg]
        assert len(said) == 1, [m.msg for m in logs if m.name == "ofc_node"]
        assert "another publisher on this node's outputs or under its name" in said[0].msg
        process = _values(_statuses(diag, "ofc_node")[-1]).get("process", "")
        assert process.endswith(f":{os.getpid()}"), process
    finally:
        ex.shutdown()
        listener.destroy_node()
        twin.destroy_node()
        ctx.try_shutdown()


def test_camera_sim_applies_corrections_only_from_the_one_publisher(ros_domain):
    sim = pytest.importorskip("cwfs_ros.sim")  # noqa: F841
    from test_camera_sim import correction, make_system, visit

    from cwfs_ros.ofc.control import load_dof_spec

    node, t, close = make_system(ros_domain)
    try:
        s1 = visit(t)
        state = node.dof_state
        small = 0.5 * load_dof_spec().max_step * np.sign(np.linspace(-1, 1, 50) + 0.01)
        imp = Impostor(ros_domain, "ofc_node", DofCorrection, "aos/ofc/dof_correction")
        try:
            wait_for(lambda: imp.pub.get_subscription_count() > 0, 20, "the impostor to match")
            # A correction for the visit just published, within the step limits: only the
            # second publisher on the topic gives it away.
            imp.pub.publish(correction(small, stamp_ns=s1))
            wait_for(lambda: node.ignored.counts["untrusted_source"] == 1, 10,
                     "the impostor's correction ignored")
            np.testing.assert_array_equal(node.dof_state, state)
            assert node.stats["corrections_applied"] == 0
            wait_for(lambda: any(st.level == DiagnosticStatus.ERROR
                                 and "untrusted_source" in st.message
                                 for st in _statuses(t.diag, "camera_sim_node")), 10,
                     "ERROR on /diagnostics")
        finally:
            imp.close()
        wait_for(lambda: node.trust.problem() is None, 15, "one publisher again")
        t.pub.publish(correction(small, stamp_ns=s1))
        wait_for(lambda: node.stats["corrections_applied"] == 1, 10, "the correction applied")
        np.testing.assert_array_equal(node.dof_state, state + small)
    finally:
        close()


def test_an_impostor_that_sends_and_leaves_at_once_is_still_refused(ofc_graph, ros_domain):
    """The impostor matches, waits past the settle time, sends one vector and leaves before
    ofc_node takes it: the publisher count is back to one by then, but the reader's matched
    status still counts the writer that came and went."""
    ofc, pub, got, _ = ofc_graph
    t0 = (time.time_ns() // SEC - 1000) * SEC
    untrusted = ofc.guard_counts.counts
    for k in (1, 2, 3):
        imp = Impostor(ros_domain, "wavefront_node", WavefrontVector, "aos/wfs/wavefront")
        wait_for(lambda imp=imp: imp.pub.get_subscription_count() > 0, 20, "the impostor")
        time.sleep(2.5)
        stamp = t0 + k * 40 * SEC
        imp.pub.publish(good_vector(stamp, dx_um=100.0 * k))
        imp.close()
        wait_for(lambda k=k: untrusted["untrusted_source"] == k, 10, f"vector {k} refused")
        assert stamp not in got
    assert ofc.solver.n_steps == 0
    # and the one producer is trusted again once its topic has settled
    wait_for(lambda: ofc.trust.problem() is None, 15, "trust back")
    s = t0 + 10 * 40 * SEC
    pub.publish(good_vector(s, dx_um=500.0))
    wait_for(lambda: s in got, 10, "the producer's correction")
    assert got[s][0].valid, got[s][0].status


def test_a_camera_that_came_and_went_between_visits_does_not_refuse_the_next_one(
        ros_context, ros_domain, spin):
    """An image topic (``at_most`` one camera): camera A sends a visit and ends, B matches and
    ends without sending (a run that failed before its first image), and C starts after the
    topic has settled: C's first image is trusted, because the check watches the topic on a
    timer and saw A and B leave, not only when C's image arrives. A camera that matched and
    left less than the settle time before an image is still refused."""
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.common import PublisherTrust

    node = spin(rclpy.create_node("wavefront_node", context=ros_context))
    trust = PublisherTrust(node, "aos/wfs/R00/intra/image", 1, at_most=True)
    verdicts: list[tuple[str, str | None]] = []
    sub = node.create_subscription(Image, "aos/wfs/R00/intra/image",
                                   lambda m: verdicts.append((m.header.frame_id,
                                                              trust.problem())), OUTPUT_QOS)
    trust.attach(sub)

    def camera(name: str, send: bool) -> None:
        cam = Impostor(ros_domain, "camera", Image, "aos/wfs/R00/intra/image")
        try:
            wait_for(lambda: cam.pub.get_subscription_count() > 0, 20, f"camera {name}")
            if send:
                n = len(verdicts)
                cam.pub.publish(Image(header=Header(frame_id=name)))
                wait_for(lambda: len(verdicts) > n, 10, f"camera {name}'s image")
        finally:
            cam.close()

    try:
        camera("A", send=True)
        camera("B", send=False)
        time.sleep(PublisherTrust.settle_s + 1.0)
        camera("C", send=True)
        camera("D", send=False)
        camera("E", send=True)  # within the settle time of D leaving
        assert [v[0] for v in verdicts] == ["A", "C", "E"], verdicts
        assert verdicts[0][1] is None and verdicts[1][1] is None, verdicts
        assert verdicts[2][1] is not None and "matched and left" in verdicts[2][1], verdicts
    finally:
        trust.detach()
