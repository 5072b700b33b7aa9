#!/usr/bin/env python3
"""Executor busy loop: rclpy's MultiThreadedExecutor against cwfs_ros.ros.executor's.

One process holds ofc_node and a client node on one executor (3 threads), as the composed
bringup does. The client publishes ``--messages`` WavefrontVector messages at ``--rate`` Hz
(the main thread, sleeping between them) and receives the corrections. Each run is a fresh
subprocess on its own DDS domain; the two executors alternate, so drifts of the machine's
speed fall on both. Printed per executor (median over runs, and worst):

* CPU seconds the process used during the burst, against its wall-clock length;
* overrun of the client's sleeps (a starved main thread sleeps long);
* latency, WavefrontVector published -> DofCorrection received: p50 / max;
* callbacks submitted to the thread pool per callback run (1 when each is handed over once).

    .venv/bin/python bench/bench_executor.py                 # 5 runs each, 40 messages
    .venv/bin/python bench/bench_executor.py --runs 3 --messages 100 --rate 20
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
EXECUTORS = ("rclpy", "cwfs_ros")


def one_run(kind: str, n_messages: int, rate_hz: float, domain: int) -> dict:
    """One burst on a fresh context; the figures of this process."""
    import rclpy
    from cwfs_msgs.msg import DofCorrection, WavefrontVector
    from rclpy.parameter import Parameter

    from cwfs_ros.ofc import control as C
    from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns
    from cwfs_ros.ros.executor import count_pool_submissions
    from cwfs_ros.ros.ofc_node import OfcNode

    if kind == "rclpy":
        from rclpy.executors import MultiThreadedExecutor
    else:
        from cwfs_ros.ros.executor import MultiThreadedExecutor

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    # A fixed rotator and no rate guards, so that every vector is integrated and published
    # (with the defaults, the vectors without a rotator angle would all be refused).
    ofc = OfcNode(context=ctx, parameter_overrides=[
        Parameter("rotator_angle_source", value="fixed"),
        Parameter("min_visit_period_s", value=0.0), Parameter("refuse_repeats", value=False)])
    client = rclpy.create_node("bench_client", context=ctx)
    pub = client.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    got: dict[int, float] = {}
    client.create_subscription(
        DofCorrection, "aos/ofc/dof_correction",
        lambda m: got.__setitem__(stamp_to_ns(m.header.stamp), time.monotonic()), OUTPUT_QOS)
    ex = MultiThreadedExecutor(num_threads=3, context=ctx)
    ex.add_node(ofc)
    ex.add_node(client)
    # Count what is handed to the thread pool, to set against the callbacks run.
    runs = count_pool_submissions(ex)
    threading.Thread(target=ex.spin, daemon=True).start()
    t_end = time.monotonic() + 20
    while pub.get_subscription_count() == 0 or ofc.pub.get_subscription_count() == 0:
        if time.monotonic() > t_end:
            raise RuntimeError("discovery timed out")
        time.sleep(0.01)
    y = np.asarray(C.OFCSolver(C.SensitivityMatrix.from_bundled(), band="r").intrinsic_nm)
    period = 1.0 / rate_hz
    sent: dict[int, float] = {}
    overrun = []
    runs["n"] = 0
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.monotonic()
    for k in range(n_messages):
        m = WavefrontVector()
        stamp = (3000 + k) * 1_000_000_000
        m.header.stamp.sec = 3000 + k
        m.zernikes_nm = y
        m.corner_valid = [True] * 4
        m.corners = ["R00", "R04", "R40", "R44"]
        sent[stamp] = time.monotonic()
        pub.publish(m)
        a = time.monotonic()
        time.sleep(period)
        overrun.append(time.monotonic() - a - period)
    t_end = time.monotonic() + 30
    while len(got) < n_messages and time.monotonic() < t_end:
        time.sleep(0.01)
    wall = time.monotonic() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    lat = [got[s] - t for s, t in sent.items() if s in got]
    # Two callbacks per message (ofc's and the client's), plus ofc's 1 Hz diagnostics timer.
    callbacks = 2 * len(got) + int(wall)
    return {"kind": kind, "wall_s": wall, "cpu_s": cpu, "received": len(got),
            "overrun_med_s": float(np.median(overrun)), "overrun_max_s": float(max(overrun)),
            "lat_p50_s": float(np.median(lat)) if lat else float("nan"),
            "lat_max_s": float(max(lat)) if lat else float("nan"),
            "submissions_per_callback": runs["n"] / max(callbacks, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="runs per executor (alternating)")
    ap.add_argument("--messages", type=int, default=40)
    ap.add_argument("--rate", type=float, default=10.0, help="messages per second")
    ap.add_argument("--one", choices=EXECUTORS, help=argparse.SUPPRESS)
    ap.add_argument("--domain", type=int, default=90, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one_run(a.one, a.messages, a.rate, a.domain)), flush=True)
        os._exit(0)  # rclpy's threads need not wind down for a figure already printed

    env = dict(os.environ)
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(REPO / "config" / "fastdds_profile.xml"))
    results: dict[str, list[dict]] = {k: [] for k in EXECUTORS}
    for r in range(a.runs):
        for i, kind in enumerate(EXECUTORS):
            out = subprocess.run(
                [sys.executable, __file__, "--one", kind, "--messages", str(a.messages),
                 "--rate", str(a.rate), "--domain", str(80 + (2 * r + i) % 20)],
                env=env, capture_output=True, text=True, check=True)
            line = [x for x in out.stdout.splitlines() if x.startswith("{")][-1]
            results[kind].append(json.loads(line))
            print(f"run {r + 1} {kind:9s} " + " ".join(
                f"{k} {v:.3g}" for k, v in results[kind][-1].items() if k != "kind"),
                flush=True)
    burst = a.messages / a.rate
    print(f"\n{a.messages} messages at {a.rate:g} Hz ({burst:g} s of sleeps), {a.runs} runs each;"
          " median (worst)")
    print(f"{'executor':10s} {'CPU s':>13s} {'wall s':>13s} {'worst sleep overrun ms':>22s} "
          f"{'latency p50 ms':>16s} {'latency max ms':>16s} {'submits/callback':>17s}")
    for kind, rs in results.items():
        def col(key: str, scale: float = 1.0, fmt: str = ".2f", rs=rs) -> str:
            v = [x[key] * scale for x in rs]
            return f"{np.median(v):{fmt}} ({max(v):{fmt}})"
        print(f"{kind:10s} {col('cpu_s'):>13s} {col('wall_s'):>13s} "
              f"{col('overrun_max_s', 1e3, '.1f'):>22s} {col('lat_p50_s', 1e3, '.1f'):>16s} "
              f"{col('lat_max_s', 1e3, '.1f'):>16s} "
              f"{col('submissions_per_callback', 1.0, '.0f'):>17s}")
        lost = [x for x in rs if x["received"] < a.messages]
        if lost:
            print(f"  {kind}: {len(lost)} run(s) missed corrections")
    return 0


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    sys.exit(main())
