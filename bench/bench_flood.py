#!/usr/bin/env python
"""Floods from outside: the nodes' memory over time and what they report dropping.

  frames   a wavefront_node (its own process, all four corners, 2 workers) gets N unpaired
           2000x1000 frames on one image topic as fast as DDS takes them; its resident
           memory (with its workers) is sampled every 0.5 s, with its /diagnostics'
           pending_mb and rejected.memory_limit.
  vectors  an ofc_node (its own process) gets M distinct WavefrontVectors as fast as
           possible, stamped 1 ms apart; an outside subscriber counts the DofCorrections,
           and the node's /diagnostics the guards' counts and the queue drops.

Usage: .venv/bin/python bench/bench_flood.py [frames] [vectors] [--frames N] [--vectors M]
       [--max-pending-mb MB]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOMAIN = 87


def rss_mb(root: int) -> float:
    """Resident memory of ``root`` and its descendants [MB] (from /proc)."""
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                text = (d / "stat").read_text()
            except OSError:
                continue
            ppid = int(text[text.rindex(")") + 2:].split()[1])
            kids.setdefault(ppid, []).append(int(d.name))
    total, todo = 0.0, [root]
    while todo:
        p = todo.pop()
        todo += kids.get(p, [])
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024.0
        except OSError:
            pass
    return total


def start_node(name: str, *params: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    args = [a for p in params for a in ("-p", p)]
    return subprocess.Popen([sys.executable, "-m", "cwfs_ros.ros.launch", "node", name,
                             "--ros-args", *args], env=env, cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


class Probe:
    """An rclpy node listening to /diagnostics (and optionally the corrections)."""

    def __init__(self) -> None:
        import rclpy
        from cwfs_msgs.msg import DofCorrection
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from cwfs_ros.ros.common import OUTPUT_QOS

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=DOMAIN)
        self.node = rclpy.create_node("flood_probe", context=self.ctx)
        self.diag: dict[str, dict[str, str]] = {}
        self.corrections = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.node.create_subscription(DofCorrection, "aos/ofc/dof_correction",
                                      self.corrections.append, OUTPUT_QOS)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.ex.spin()
        except Exception:  # noqa: BLE001, S110 - shutdown
            pass

    def _on_diag(self, arr) -> None:
        for st in arr.status:
            self.diag[st.name.split(":")[0]] = {kv.key: kv.value for kv in st.values}

    def close(self) -> None:
        self.ex.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def wait(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return False


def bench_frames(n: int, max_mb: float) -> None:
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.common import IMAGE_QOS
    from cwfs_ros.ros.convert import image_msg

    print(f"\n== frames: {n} unpaired 2000x1000 32FC1 frames on /aos/wfs/R00/intra/image, "
          f"max_pending_mb {max_mb:g}")
    node = start_node("wavefront_node", "workers:=2", f"max_pending_mb:={max_mb}",
                      "visit_timeout_s:=600.0", "diagnostics_period_s:=0.5")
    probe = Probe()
    try:
        pub = probe.node.create_publisher(Image, "aos/wfs/R00/intra/image", IMAGE_QOS)
        wait(lambda: probe.diag.get("wavefront_node", {}).get("state") == "ready", 120)
        wait(lambda: pub.get_subscription_count() > 0, 20)
        base = rss_mb(node.pid)
        print(f"  ready: {base:.0f} MB resident (node + workers)")
        rng = np.random.default_rng(0)
        frame = rng.normal(100.0, 5.0, (2000, 1000)).astype(np.float32)
        t0 = time.monotonic()
        samples = []
        stamp0 = time.time_ns() - 3600 * 10**9

        def sample() -> None:
            d = probe.diag.get("wavefront_node", {})
            samples.append((time.monotonic() - t0, rss_mb(node.pid), d.get("pending_mb", "?"),
                            d.get("rejected.memory_limit", "0"), d.get("images", "?"),
                            d.get("queue_dropped.R00.intra", "0")))

        for k in range(n):  # distinct stamps: each its own visit, none paired
            pub.publish(image_msg(frame, stamp0 + k * 10**9))
            if time.monotonic() - t0 >= 0.5 * len(samples):
                sample()
        sent = n
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            sample()
            time.sleep(0.5)
        print("  t [s]   resident [MB]   pending_mb   memory_limit drops   images taken"
              "   never taken (queue)")
        for t, r, p, m, i, q in samples:
            print(f"  {t:5.1f}   {r:13.0f}   {p:>10}   {m:>18}   {i:>12}   {q:>19}")
        d = probe.diag.get("wavefront_node", {})
        lost = {k: v for k, v in d.items() if k.startswith("messages_lost")}
        print(f"  sent {sent}; node took {d.get('images')}; dropped for memory "
              f"{d.get('rejected.memory_limit', '0')}; never taken (sequence gaps) "
              f"{d.get('queue_dropped.R00.intra', '0')}; middleware losses reported {lost or 0}; "
              f"peak resident {max(s[1] for s in samples):.0f} MB (ready {base:.0f} MB)")
    finally:
        probe.close()
        node.kill()
        node.wait(10)


def bench_vectors(m: int) -> None:
    from cwfs_msgs.msg import WavefrontVector

    from cwfs_ros.ofc import control as C
    from cwfs_ros.ros.common import OUTPUT_QOS

    print(f"\n== vectors: {m} distinct WavefrontVectors 1 ms apart (stamps), as fast as "
          "possible")
    # a fixed rotator: without one, every vector is refused before the rate guard is tested
    node = start_node("ofc_node", "diagnostics_period_s:=0.5", "rotator_angle_source:=fixed")
    probe = Probe()
    try:
        pub = probe.node.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
        wait(lambda: "ofc_node" in probe.diag, 60)
        wait(lambda: pub.get_subscription_count() > 0, 20)
        y = C.OFCSolver(C.SensitivityMatrix.from_bundled(), band="r").intrinsic_nm
        rng = np.random.default_rng(1)
        stamp0 = time.time_ns() - 3600 * 10**9
        t0 = time.monotonic()
        for k in range(m):
            v = WavefrontVector()
            v.header.stamp.sec, v.header.stamp.nanosec = divmod(stamp0 + k * 10**6, 10**9)
            v.zernikes_nm = y + rng.normal(0.0, 5.0, 76)
            v.corner_valid = [True] * 4
            v.corners = ["R00", "R04", "R40", "R44"]
            pub.publish(v)
        dt = time.monotonic() - t0
        time.sleep(3.0)
        d = probe.diag.get("ofc_node", {})
        print(f"  sent {m} in {dt:.2f} s; corrections published {len(probe.corrections)} "
              f"(valid {sum(c.valid for c in probe.corrections)}); vectors taken "
              f"{d.get('vectors')}; too_soon {d.get('guard.too_soon', 0)}; "
              f"queue_dropped {d.get('queue_dropped')}; n_steps {d.get('n_steps')}")
    finally:
        probe.close()
        node.kill()
        node.wait(10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", default=["frames", "vectors"])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--vectors", type=int, default=500)
    ap.add_argument("--max-pending-mb", type=float, default=256.0)
    a = ap.parse_args()
    if "frames" in a.sections:
        bench_frames(a.frames, a.max_pending_mb)
    if "vectors" in a.sections:
        bench_vectors(a.vectors)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
