#!/usr/bin/env python3
"""Inter-process DDS latency for bursts of donut images.

Two processes on one ROS domain: a publisher sends bursts of 8
``sensor_msgs/Image`` (160x160 32FC1, ~820 kB per burst) with RELIABLE QoS, a
subscriber measures ``receive time - header.stamp`` per image. Run once with
FastDDS defaults and once with ``config/fastdds_profile.xml`` (enlarged
shared-memory segment); the defaults show ~100 ms retransmission spikes.

    python bench/dds_image_latency.py                 # both configurations
    python bench/dds_image_latency.py --config profile --bursts 50
    python bench/dds_image_latency.py --config profile --rows 2000 --cols 1000 --period 3
                                                      # visits of 8 half-chip frames
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "config" / "fastdds_profile.xml"
TOPIC = "bench_donuts"
SIZE = 160
PER_BURST = 8


def _qos():
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE
    )


def run_pub(bursts: int, period: float, rows: int, cols: int) -> None:
    import numpy as np
    import rclpy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("bench_pub")
    pub = node.create_publisher(Image, TOPIC, _qos())
    deadline = time.monotonic() + 20.0
    while pub.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            sys.exit("publisher: no subscriber matched within 20 s")
        time.sleep(0.05)
    time.sleep(0.5)  # let discovery settle on both sides

    data = np.random.default_rng(0).random((rows, cols), dtype=np.float32).tobytes()
    msgs = []
    for i in range(PER_BURST):
        m = Image(height=rows, width=cols, encoding="32FC1", is_bigendian=0, step=cols * 4)
        m.header.frame_id = f"donut{i}"
        m.data = data
        msgs.append(m)
    for _ in range(bursts):
        for m in msgs:
            now = time.time_ns()
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(now, 1_000_000_000)
            pub.publish(m)
        # The burst's last image: the latency of a burst is that of its last image.
        time.sleep(period)
    time.sleep(1.0)  # give RELIABLE retransmissions time before tearing down
    node.destroy_node()
    rclpy.shutdown()


def run_sub(expected: int, timeout: float, work_ms: float) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("bench_sub")
    lat_ms: list[float] = []

    def cb(msg: Image) -> None:
        sent = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        lat_ms.append((time.time_ns() - sent) / 1e6)
        if work_ms > 0:  # simulate a busy consumer (e.g. a wavefront solve per image)
            end = time.perf_counter() + work_ms / 1e3
            while time.perf_counter() < end:
                pass

    node.create_subscription(Image, TOPIC, cb, _qos())
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    deadline = time.monotonic() + timeout
    while len(lat_ms) < expected and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.1)
    print(json.dumps(lat_ms), flush=True)
    node.destroy_node()
    rclpy.shutdown()


def measure(config: str, bursts: int, period: float, domain: int, work_ms: float,
            rows: int = SIZE, cols: int = SIZE) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    if config == "profile":
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(PROFILE)
    expected = bursts * PER_BURST
    timeout = 30.0 + bursts * (period + 1.0 + PER_BURST * work_ms / 1e3)
    me = [sys.executable, __file__]
    sub = subprocess.Popen(
        [*me, "--role", "sub", "--expected", str(expected), "--timeout", str(timeout),
         "--work-ms", str(work_ms)],
        env=env, stdout=subprocess.PIPE, text=True,
    )
    pub = subprocess.run(
        [*me, "--role", "pub", "--bursts", str(bursts), "--period", str(period),
         "--rows", str(rows), "--cols", str(cols)], env=env
    )
    out, _ = sub.communicate(timeout=timeout + 30)
    if pub.returncode or sub.returncode:
        raise SystemExit(f"{config}: pub rc={pub.returncode} sub rc={sub.returncode}")
    lat = json.loads(out.strip().splitlines()[-1])
    lat_sorted = sorted(lat)
    return {
        "config": config,
        "received": len(lat),
        "expected": expected,
        "p50_ms": statistics.median(lat) if lat else float("nan"),
        "p95_ms": lat_sorted[int(0.95 * (len(lat) - 1))] if lat else float("nan"),
        "max_ms": max(lat) if lat else float("nan"),
        "over_50ms": sum(x > 50.0 for x in lat),
        "burst_last_p50_ms": (statistics.median(lat[PER_BURST - 1::PER_BURST])
                              if len(lat) >= PER_BURST else float("nan")),
        "burst_last_max_ms": (max(lat[PER_BURST - 1::PER_BURST])
                              if len(lat) >= PER_BURST else float("nan")),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", choices=["default", "profile", "both"], default="both")
    ap.add_argument("--bursts", type=int, default=30)
    ap.add_argument("--period", type=float, default=0.25, help="pause between bursts [s]")
    ap.add_argument("--domain", type=int, default=None, help="ROS domain id (0..101)")
    ap.add_argument("--work-ms", type=float, default=0.0,
                    help="busy time the subscriber spends per image [ms]")
    ap.add_argument("--json", action="store_true", help="print results as JSON")
    ap.add_argument("--rows", type=int, default=SIZE, help="image rows [px]")
    ap.add_argument("--cols", type=int, default=SIZE, help="image columns [px]")
    ap.add_argument("--role", choices=["pub", "sub"], help=argparse.SUPPRESS)
    ap.add_argument("--expected", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--timeout", type=float, default=60.0, help=argparse.SUPPRESS)
    a = ap.parse_args()

    if a.role == "pub":
        run_pub(a.bursts, a.period, a.rows, a.cols)
        return 0
    if a.role == "sub":
        run_sub(a.expected, a.timeout, a.work_ms)
        return 0

    domain = a.domain if a.domain is not None else (os.getpid() + random.randrange(102)) % 102
    configs = ["default", "profile"] if a.config == "both" else [a.config]
    results = [measure(c, a.bursts, a.period, domain, a.work_ms, a.rows, a.cols)
               for c in configs]
    if a.json:
        print(json.dumps(results, indent=1))
    else:
        print(f"DDS latency, 2 processes, bursts of {PER_BURST} x {a.rows}x{a.cols} 32FC1 Image, "
              f"{a.bursts} bursts, subscriber work {a.work_ms:g} ms/image, domain {domain}")
        print(f"{'config':<8} {'recv':>9} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8} {'>50ms':>6}"
              f" {'last of burst p50/max ms':>25}")
        for r in results:
            print(f"{r['config']:<8} {r['received']:>4}/{r['expected']:<4} {r['p50_ms']:8.2f} "
                  f"{r['p95_ms']:8.2f} {r['max_ms']:8.2f} {r['over_50ms']:>6} "
                  f"{r['burst_last_p50_ms']:12.2f} / {r['burst_last_max_ms']:.2f}")
    # Only the project's profile must deliver everything; the default transport
    # may drop images when streaming (KEEP_LAST history overflows).
    bad = [r for r in results if r["config"] == "profile" and r["received"] < r["expected"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
