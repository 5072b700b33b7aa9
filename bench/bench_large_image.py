#!/usr/bin/env python
"""One very large image pair into a wavefront_node in its own process: its peak memory.

An outside publisher sends one intra and one extra image of SIDE x SIDE pixels (16UC1) on
R00's topics; the node's resident memory (with its workers) is sampled every 0.1 s until
the corner's result is published, and the node's /diagnostics reasons are printed. With the
bundled ``max_pending_mb`` (256) an 8192 x 8192 pair (1074 MB as float64) is refused
``too_large`` before it is decoded.

Usage: .venv/bin/python bench/bench_large_image.py [--side 8192] [--max-pending-mb 256]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_flood import Probe, rss_mb, start_node, wait  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=8192)
    ap.add_argument("--max-pending-mb", type=float, default=256.0)
    a = ap.parse_args()
    from cwfs_msgs.msg import CornerWavefront
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS
    from cwfs_ros.ros.convert import image_msg

    node = start_node("wavefront_node", "workers:=1", "corners:=[R00]",
                      f"max_pending_mb:={a.max_pending_mb}", "diagnostics_period_s:=0.5",
                      "visit_timeout_s:=30.0")
    probe = Probe()
    got = []
    try:
        pub = {s: probe.node.create_publisher(Image, f"aos/wfs/R00/{s}/image", IMAGE_QOS)
               for s in ("intra", "extra")}
        probe.node.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront", got.append,
                                       OUTPUT_QOS)
        wait(lambda: probe.diag.get("wavefront_node", {}).get("state") == "ready", 120)
        wait(lambda: all(p.get_subscription_count() for p in pub.values()), 20)
        time.sleep(1.0)
        base = rss_mb(node.pid)
        img = np.random.default_rng(0).integers(900, 1100, (a.side, a.side), dtype=np.uint16)
        stamp = time.time_ns() - 10**9
        msgs = {s: image_msg(img, stamp, encoding="16UC1") for s in pub}
        t0 = time.monotonic()
        for s, m in msgs.items():
            pub[s].publish(m)
        peak = base
        while time.monotonic() - t0 < 60.0 and not got:
            peak = max(peak, rss_mb(node.pid))
            time.sleep(0.1)
        for _ in range(10):  # what follows the result
            peak = max(peak, rss_mb(node.pid))
            time.sleep(0.1)
        dt = time.monotonic() - t0
        d = probe.diag.get("wavefront_node", {})
        print(f"{a.side} x {a.side} 16UC1 pair ({2 * img.nbytes / 1e6:.0f} MB on the wire, "
              f"{2 * img.size * 8 / 1e6:.0f} MB as float64), max_pending_mb "
              f"{a.max_pending_mb:g}: resident {base:.0f} MB ready, {peak:.0f} MB at most "
              f"(+{peak - base:.0f} MB); result after {dt:.1f} s: "
              + (f"valid={got[0].valid} status {got[0].status[:160]!r}" if got else "none"))
        print("  rejected: " + ", ".join(f"{k[9:]} {v}" for k, v in sorted(d.items())
                                         if k.startswith("rejected.")))
    finally:
        probe.close()
        node.kill()
        node.wait(10)


if __name__ == "__main__":
    main()
