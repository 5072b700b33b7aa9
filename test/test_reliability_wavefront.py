"""wavefront_node's input guards over real DDS: conflicting images, future stamps, frame_id,
bounded pending memory, log throttling, other publishers, and the uncertainty and pair count
of a stamp pair carried into the vector. One corner (R00), one worker."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import of

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import WavefrontVector  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.ros.common import OUTPUT_QOS  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.runtime.corner_pool import synthetic_donut  # noqa: E402
from cwfs_ros.runtime.pipeline import frame_id_problem  # noqa: E402

T = 1_750_000_000_000_000_000
SEC = 1_000_000_000


@pytest.fixture
def graph(r00_graph):
    """A wavefront node serving R00 and a tester node with its publishers and recorders
    (conftest's ``r00_graph``)."""
    return r00_graph

DONUT = synthetic_donut(160, 60.0, 0.61)
OTHER = synthetic_donut(160, 58.0, 0.61)  # another exposure: a different picture


def test_two_exposures_under_one_stamp_never_make_a_pair(graph):
    from conftest import wait_for

    wf, _, pub, corner, vector = graph()
    # While waiting: intra A, intra B (0.5 ms off, same visit), extra A.
    a = T + 1 * SEC
    pub["intra"].publish(image_msg(DONUT, a))
    pub["intra"].publish(image_msg(OTHER, a + 500_000))
    time.sleep(0.2)
    pub["extra"].publish(image_msg(DONUT, a))
    # After pairing: intra A + extra B paired (a chimera), then intra B arrives.
    b = T + 2 * SEC
    pub["intra"].publish(image_msg(DONUT, b))
    pub["extra"].publish(image_msg(OTHER, b))
    pub["intra"].publish(image_msg(OTHER, b))
    # An identical re-send is only a duplicate: the visit stays good.
    c = T + 3 * SEC
    for _ in range(3):
        pub["intra"].publish(image_msg(DONUT, c))
    pub["extra"].publish(image_msg(DONUT, c))
    wait_for(lambda: all(of(vector, s) for s in (a, b, c)), 20, "the three vectors")
    for s in (a, b):
        (v,) = of(vector, s)
        assert not v.corner_valid[0] and "conflicting_images" in v.status, v.status
        assert not any(m.valid for m in of(corner, s))
    (v,) = of(vector, c)
    assert v.corner_valid[0], v.status
    assert wf.rejected.counts["conflicting_images"] == 2
    assert wf.rejected.counts["duplicate"] >= 2


def test_future_stamps_are_refused_and_do_not_make_a_good_visit_late(graph):
    from conftest import wait_for

    wf, _, pub, corner, vector = graph()
    now = time.time_ns()
    t0 = time.monotonic()
    for k in range(260):  # paced: the image subscription keeps 10
        pub["intra" if k % 2 else "extra"].publish(image_msg(DONUT, now + 60 * SEC + k))
        time.sleep(0.01)
    wait_for(lambda: wf.rejected.counts["future_stamp"] == 260, 20, "260 refusals")
    elapsed = time.monotonic() - t0
    assert wf.pairing.pending_count() == 0
    good = now - 5 * SEC
    for s in ("intra", "extra"):
        pub[s].publish(image_msg(DONUT, good))
    wait_for(lambda: of(corner, good), 20, "the good visit's corner")
    assert of(corner, good)[0].valid
    assert wf.rejected.counts["late"] == 0
    # One line per reason per log_throttle_s (5 s), not one per image; all are counted.
    assert 1 <= wf.rejected.logged["future_stamp"] <= 1 + elapsed / 5.0


def test_frame_id_naming_another_corner_or_side_is_refused(graph):
    from conftest import wait_for

    wf, _, pub, corner, _ = graph()
    cases = [("R04_intra", "intra"), ("R00/extra", "intra"), ("r40", "extra"),
             ("R00_SW0", "intra")]
    for k, (fid, side) in enumerate(cases):
        pub[side].publish(image_msg(DONUT, T + k * SEC, frame_id=fid))
    wait_for(lambda: wf.rejected.counts["frame_mismatch"] == len(cases), 10, "refusals")
    # Taken: the topic's own corner and side, or no corner or side at all.
    s = T + 10 * SEC
    pub["intra"].publish(image_msg(DONUT, s, frame_id="R00_SW1"))
    pub["extra"].publish(image_msg(DONUT, s, frame_id="focal_plane"))
    wait_for(lambda: of(corner, s), 20, "the good visit")
    assert of(corner, s)[0].valid


def test_frame_id_rules():
    assert frame_id_problem("", "R00", "intra") is None
    assert frame_id_problem("focal_plane", "R44", "extra") is None
    assert frame_id_problem("lsstcam_R44_extra", "R44", "extra") is None
    assert "R04" in frame_id_problem("R04", "R00", "intra")
    assert "extra" in frame_id_problem("R00_SW0", "R00", "intra")
    assert frame_id_problem("R004", "R00", "intra") is None  # not the word R00


def test_pending_frames_are_bounded_oldest_first(graph):
    from conftest import wait_for

    wf, _, pub, _, _ = graph(max_pending_mb=20.0, visit_timeout_s=60.0)
    frame = np.zeros((1000, 1000), np.float32)
    frame[500, 500] = 1.0
    for k in range(8):  # 4 MB each, decoded as float32: the limit keeps 5
        pub["intra"].publish(image_msg(frame, T + k * SEC))
    wait_for(lambda: wf.rejected.counts["memory_limit"] == 3, 20, "3 dropped")
    assert wf.pairing.pending_bytes() <= 20e6 and wf.pairing.pending_count() == 5
    kv = {x.key: x.value for x in wf.diagnostics().values}
    assert float(kv["pending_mb"]) <= 20.0 and kv["rejected.memory_limit"] == "3"


def test_stamp_pair_carries_uncertainty_and_pair_count(graph):
    from conftest import wait_for

    wf, _, pub, corner, vector = graph()
    s = T + 7 * SEC
    for side in ("intra", "extra"):
        pub[side].publish(image_msg(DONUT, s))
    wait_for(lambda: of(vector, s), 20, "the vector")
    (c,) = of(corner, s)
    unc = np.asarray(c.uncertainty_nm)
    # The noise model's one-sigma: positive where it has a coefficient or a floor.
    assert c.valid and c.n_pairs == 1 and np.all(unc >= 0) and np.count_nonzero(unc) >= 10
    (v,) = of(vector, s)
    u = np.asarray(v.uncertainty_nm).reshape(4, 19)
    assert list(v.n_pairs) == [1, 0, 0, 0]
    np.testing.assert_array_equal(u[0], np.asarray(c.uncertainty_nm))
    assert np.all(u[1:] == 0.0)


def test_other_publishers_and_long_frame_id(graph, ros_context):
    from conftest import wait_for

    wf, tester, _, _, _ = graph()
    assert {x.key: x.value for x in wf.diagnostics().values}["foreign_publishers"] == "none"
    tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    wait_for(lambda: "tester" in {x.key: x.value for x in wf.diagnostics().values}[
        "foreign_publishers"], 10, "the tester named")
    (res,) = wf.set_parameters([Parameter("frame_id", value="f" * 1_000_000)])
    assert not res.successful and "at most 256" in res.reason


def test_images_never_taken_are_counted(graph):
    """A burst of images faster than the node takes them: those its queue dropped (no DDS
    event reports them) are counted from the sequence numbers; taken + counted = sent."""
    from conftest import wait_for
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    wf, tester, camera, _, _ = graph(max_pending_mb=4096.0, visit_timeout_s=60.0)
    tester.destroy_publisher(camera["intra"])  # one publisher per image topic
    pub = tester.create_publisher(Image, "aos/wfs/R00/intra/image", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE))
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    # A publisher replaced before the node took any image of the topic: its images are
    # trusted once the topic has had one publisher for PublisherTrust.settle_s.
    wait_for(lambda: wf.image_source_problem("R00", "intra") is None, 10,
             "the replacement publisher trusted")
    frame = np.random.default_rng(9).normal(100.0, 5.0, (160, 160)).astype(np.float32)
    pub.publish(image_msg(frame, T))
    wait_for(lambda: wf.stats["images"] == 1, 10, "the first frame taken")
    orig = wf._on_image

    def busy(msg, corner, side):  # a node busy elsewhere: 50 ms an image
        time.sleep(0.05)
        orig(msg, corner, side)

    wf._on_image = busy
    n = 60
    for k in range(1, n + 1):
        pub.publish(image_msg(frame, T + k * SEC))
    gaps = wf.image_gaps[("R00", "intra")]
    wait_for(lambda: wf.stats["images"] - 1 + gaps.dropped >= n, 30, "all accounted for")
    time.sleep(0.5)
    assert gaps.dropped > 0
    assert wf.stats["images"] - 1 + gaps.dropped == n
    kv = {x.key: x.value for x in wf.diagnostics().values}
    assert kv["queue_dropped.R00.intra"] == str(gaps.dropped)
