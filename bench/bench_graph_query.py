#!/usr/bin/env python
"""What the publisher checks of "who may act" cost per message (docs/reliability.md).

A consumer (ofc_node, camera_sim_node) asks, for every message it takes, its subscription's
matched status (writers matched now and ever) and how many publisher endpoints the graph lists
on the topic (``PublisherTrust.problem``); only to name the endpoints of a refusal does it list
them. They read the reader's status and rmw's local graph cache. This times each on a node with
one publisher on its topic, in one process.

``--lease``: how long a SIGKILLed publisher (a process of its own) stays in the graph and
matched, i.e. how long a restarted producer's messages are refused (FastDDS profile as the
entry points load it; FASTRTPS_DEFAULT_PROFILES_FILE= for FastDDS's defaults).

Usage: .venv/bin/python bench/bench_graph_query.py [--calls N] [--domain D] [--lease]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(REPO / "config" /
                                                             "fastdds_profile.xml"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=20000)
    ap.add_argument("--domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "77")))
    ap.add_argument("--lease", action="store_true",
                    help="time a SIGKILLed publisher's stay in the graph instead")
    args = ap.parse_args()
    if args.lease:
        return lease(args.domain)

    import rclpy
    from cwfs_msgs.msg import WavefrontVector
    from rclpy.executors import SingleThreadedExecutor

    from cwfs_ros.layout import VECTOR_TOPIC
    from cwfs_ros.ros.common import OUTPUT_QOS

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=args.domain)
    owner = rclpy.create_node("bench_owner", context=ctx)
    consumer = rclpy.create_node("bench_consumer", context=ctx)
    topic = "/" + VECTOR_TOPIC.lstrip("/")
    owner.create_publisher(WavefrontVector, topic, OUTPUT_QOS)
    sub = consumer.create_subscription(WavefrontVector, topic, lambda m: None, OUTPUT_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(owner)
    ex.add_node(consumer)
    t_end = time.monotonic() + 10
    while sub.get_publisher_count() < 1 and time.monotonic() < t_end:
        ex.spin_once(timeout_sec=0.05)
    from cwfs_ros.ros.common import PublisherTrust

    trust = PublisherTrust(consumer, topic, 1)
    trust.attach(sub)
    queries = {
        "matched status (event handle)": trust._matched,
        "PublisherTrust.problem (per message)": trust.problem,
        "Subscription.get_publisher_count": sub.get_publisher_count,
        "Node.count_publishers": lambda: consumer.count_publishers(topic),
        "Node.get_publishers_info_by_topic": lambda: consumer.get_publishers_info_by_topic(topic),
    }
    for name, query in queries.items():
        t = time.perf_counter()
        for _ in range(args.calls):
            out = query()
        per_us = (time.perf_counter() - t) / args.calls * 1e6
        print(f"{name:38s} {per_us:7.1f} us per call ({args.calls} calls): {out!r:.60}")
    trust.detach()
    ctx.try_shutdown()
    return 0


_CHILD = """
import time, rclpy
from cwfs_msgs.msg import WavefrontVector
from cwfs_ros.ros.common import OUTPUT_QOS
rclpy.init(domain_id={domain})
node = rclpy.create_node("bench_producer")
node.create_publisher(WavefrontVector, "{topic}", OUTPUT_QOS)
time.sleep(120)
"""


def lease(domain: int) -> int:
    """A publisher in a process of its own, SIGKILLed: seconds until the graph and the
    subscription's matched count drop it."""
    import rclpy
    from cwfs_msgs.msg import WavefrontVector

    from cwfs_ros.ros.common import OUTPUT_QOS

    topic = "/bench/lease"
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_consumer", context=ctx)
    sub = node.create_subscription(WavefrontVector, topic, lambda m: None, OUTPUT_QOS)
    child = subprocess.Popen([sys.executable, "-c", _CHILD.format(domain=domain, topic=topic)],
                             start_new_session=True)
    try:
        t_end = time.monotonic() + 60
        while (node.count_publishers(topic) < 1 or sub.get_publisher_count() < 1) and \
                time.monotonic() < t_end:
            time.sleep(0.01)
        os.killpg(child.pid, signal.SIGKILL)
        child.wait()
        t0 = time.monotonic()
        gone: dict[str, float] = {}
        while len(gone) < 2 and time.monotonic() - t0 < 60:
            if "graph" not in gone and node.count_publishers(topic) == 0:
                gone["graph"] = time.monotonic() - t0
            if "matched" not in gone and sub.get_publisher_count() == 0:
                gone["matched"] = time.monotonic() - t0
            time.sleep(0.01)
        profile = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") or "FastDDS defaults"
        print(f"SIGKILLed publisher gone from the graph after {gone.get('graph', -1):.2f} s, "
              f"unmatched after {gone.get('matched', -1):.2f} s ({profile})")
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
        ctx.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
