"""A slow consumer is not hung on: a subscriber of /aos/ofc/dof_correction that takes 0.5 s
per message does not delay ofc_node's answers to a fast one (real DDS, one process, the slow
subscriber on its own executor thread, as a separate process's would be)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor  # noqa: E402

from cwfs_ros.core import control as C  # noqa: E402
from cwfs_ros.nodes.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.nodes.ofc_node import OfcNode  # noqa: E402

SEC = 1_000_000_000
N = 20
PERIOD_S = 0.1
SLOW_S = 0.5


def test_slow_subscriber_does_not_delay_the_controller(ros_context):
    ex = MultiThreadedExecutor(num_threads=3, context=ros_context)
    slow_ex = SingleThreadedExecutor(context=ros_context)
    ofc = OfcNode(context=ros_context)
    fast = rclpy.create_node("fast_consumer", context=ros_context)
    slow = rclpy.create_node("slow_consumer", context=ros_context)
    pub = fast.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    got: dict[int, float] = {}
    slow_got: list[int] = []
    fast.create_subscription(DofCorrection, "aos/ofc/dof_correction",
                             lambda m: got.__setitem__(stamp_to_ns(m.header.stamp),
                                                       time.monotonic()), OUTPUT_QOS)

    def crawl(m: DofCorrection) -> None:
        time.sleep(SLOW_S)
        slow_got.append(stamp_to_ns(m.header.stamp))

    slow.create_subscription(DofCorrection, "aos/ofc/dof_correction", crawl, OUTPUT_QOS)
    ex.add_node(ofc)
    ex.add_node(fast)
    slow_ex.add_node(slow)
    threads = [threading.Thread(target=e.spin, daemon=True) for e in (ex, slow_ex)]
    for t in threads:
        t.start()
    try:
        wait_for(lambda: pub.get_subscription_count() > 0 and
                 ofc.count_subscribers("aos/ofc/dof_correction") >= 2, 10, "discovery")
        y = C.OFCSolver(C.SensitivityMatrix.from_bundled(), band="r").intrinsic_nm
        sent: dict[int, float] = {}
        for k in range(N):
            m = WavefrontVector()
            stamp = (2000 + k) * SEC
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
            m.zernikes_nm = np.asarray(y, dtype=float)
            m.corner_valid = [True] * 4
            m.corners = ["R00", "R04", "R40", "R44"]
            pub.publish(m)
            sent[stamp] = time.monotonic()
            time.sleep(PERIOD_S)
        wait_for(lambda: len(got) == N, 10, "every correction at the fast consumer")
        lat = np.array([got[s] - t for s, t in sent.items()])
        # The slow consumer needs N x 0.5 s; the fast one must not wait for it.
        print("LAT", np.round(lat, 2), "slow", len(slow_got))
        assert np.max(lat) < 5 * PERIOD_S, lat
        assert np.median(lat) < PERIOD_S, lat
    finally:
        ex.shutdown(timeout_sec=2.0)
        slow_ex.shutdown(timeout_sec=2.0)
        for t in threads:
            t.join(5)
        for n in (ofc, fast, slow):
            n.destroy_node()
