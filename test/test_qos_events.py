"""QoS mismatches are reported, not waited on: a best-effort camera and the image_reliability
parameter (wavefront_node over real DDS, one corner, one worker)."""

from __future__ import annotations

import pytest
from conftest import spin_thread, wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import CornerWavefront  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor  # noqa: E402
from cwfs_ros.ros.wavefront_node import WavefrontNode  # noqa: E402
from cwfs_ros.runtime.corner_pool import synthetic_donut  # noqa: E402

SEC = 1_000_000_000


def _system(ctx, reliability: str):
    ex = MultiThreadedExecutor(num_threads=3, context=ctx)
    wf = WavefrontNode(context=ctx, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("assemble", value=False), Parameter("image_reliability", value=reliability),
        Parameter("diagnostics_period_s", value=0.2)])
    tester = rclpy.create_node("camera", context=ctx)
    # A camera driver publishing with the common sensor_data QoS (best effort).
    pubs = {s: tester.create_publisher(Image, f"aos/wfs/R00/{s}/image",
                                       qos_profile_sensor_data) for s in ("intra", "extra")}
    got, diag = [], []
    tester.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront", got.append,
                               OUTPUT_QOS)
    tester.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 10)
    ex.add_node(wf)
    ex.add_node(tester)
    th = spin_thread(ex)
    th.start()

    def close():
        ex.shutdown(timeout_sec=2.0)
        th.join(5)
        wf.destroy_node()
        tester.destroy_node()

    return wf, pubs, got, diag, close


def _wf_status(diag):
    for arr in reversed(list(diag)):
        for st in arr.status:
            if st.name.startswith("wavefront_node"):
                return st
    return None


def test_best_effort_camera_is_reported_as_incompatible(ros_context):
    wf, pubs, got, diag, close = _system(ros_context, "reliable")
    try:
        def reported():
            st = _wf_status(diag)
            return (st is not None and st.level == DiagnosticStatus.ERROR
                    and "QoS" in st.message and "RELIABILITY".lower() in st.message)
        wait_for(reported, 20, "the incompatible camera on /diagnostics")
        kv = {v.key: v.value for v in _wf_status(diag).values}
        assert int(kv["qos_incompatible.aos/wfs/R00/intra/image"]) >= 1
        assert int(kv["qos_incompatible.aos/wfs/R00/extra/image"]) >= 1
        # ... and indeed nothing gets through.
        d = synthetic_donut(160, 60.0, 0.61)
        for p in pubs.values():
            p.publish(image_msg(d, 5 * SEC))
        with pytest.raises(AssertionError, match="timed out"):
            wait_for(lambda: bool(got), 2.0, "a corner result")
    finally:
        close()


def test_best_effort_subscription_hears_the_camera(ros_context):
    wf, pubs, got, diag, close = _system(ros_context, "best_effort")
    try:
        wait_for(lambda: wf.ready, 60, "warm-up")
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 10,
                 "discovery")
        d = synthetic_donut(160, 60.0, 0.61)
        for p in pubs.values():
            p.publish(image_msg(d, 7 * SEC))
        wait_for(lambda: any(stamp_to_ns(m.header.stamp) == 7 * SEC for m in got), 20,
                 "the corner result")
        st = _wf_status(diag)
        assert st is None or not any(v.key.startswith("qos_incompatible") for v in st.values)
    finally:
        close()


def test_image_reliability_parameter_is_validated(ros_context):
    with pytest.raises(Exception, match="image reliability must be one of"):
        WavefrontNode(context=ros_context, parameter_overrides=[
            Parameter("corners", value=["R00"]), Parameter("workers", value=1),
            Parameter("image_reliability", value="sometimes")])
