#!/usr/bin/env python3
"""Load: visits back to back at 10x the LSST cadence or faster, for minutes (reliability issue).

The nodes run in a separate process (``python -m cwfs_ros.ros.launch bringup``: wavefront_node +
ofc_node, default parameters), on a private DDS domain. This process publishes one
ray-traced visit (8 stamps, re-stamped each time) every ``--period`` seconds for
``--duration`` seconds and reports:

* latency, last image published -> DofCorrection received: p50 / p90 / p99 / max;
* dropped visits: no DofCorrection within 30 s, or an invalid one (there should be none);
* memory: resident set size of the node process and its estimator workers, sampled every
  5 s (it should stay flat);
* then a ramp of shorter periods (``--ramp``), 20 s each, for the highest sustained visit
  rate: every visit answered, valid, and the p90 latency below the period.

LSST takes a visit about every 40 s (30 s exposure plus readout and slew), so 10x is one
visit every 4 s.

    .venv/bin/python bench/bench_load.py                       # 4 s period, 180 s
    .venv/bin/python bench/bench_load.py --period 1 --duration 300 --ramp 0.5,0.25,0.15,0.1
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
from bench_latency import CORNERS, render_visit  # noqa: E402
from graph_process import start_bringup, stop_bringup, stop_client  # noqa: E402

PAGE_KB = os.sysconf("SC_PAGE_SIZE") / 1024


def tree_rss_mb(pid: int) -> float:
    """RSS of ``pid`` and all its descendants [MB] (from /proc; no psutil needed)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
                children.setdefault(int(fields[1]), []).append(int(d))
            except (OSError, IndexError):
                continue
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            total += int(Path(f"/proc/{p}/statm").read_text().split()[1]) * PAGE_KB / 1024
        except (OSError, IndexError):
            pass
        todo.extend(children.get(p, []))
    return total


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--period", type=float, default=4.0, help="seconds between visits")
    ap.add_argument("--duration", type=float, default=180.0, help="seconds of load")
    ap.add_argument("--ramp", default="1.0,0.5,0.25,0.15,0.1",
                    help="shorter periods to try afterwards, 20 s each ('' = none)")
    ap.add_argument("--photons", type=float, default=3e5)
    ap.add_argument("--domain", type=int, default=None)
    args = ap.parse_args()

    domain = args.domain if args.domain is not None else 20 + os.getpid() % 80
    profile = str(REPO / "config" / "fastdds_profile.xml")
    os.environ.update(ROS_DOMAIN_ID=str(domain))
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", profile)
    images = render_visit(args.photons)

    import rclpy
    from cwfs_msgs.msg import DofCorrection
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns
    from cwfs_ros.ros.convert import image_msg

    # One visit's images are sent again and again under new stamps, faster than visits come
    # and with no rotator: the controller's repeat and cadence guards and its rotator input
    # are set aside for this load benchmark.
    proc = start_bringup(["--log-level", "warn", "-p", "rotator_angle_source:=fixed",
                          "-p", "min_visit_period_s:=0.0", "-p", "refuse_repeats:=false"],
                         domain)
    rclpy.init()
    node = rclpy.create_node("bench_load")
    pubs = {(c, s): node.create_publisher(Image, f"aos/wfs/{c}/{s}/image", IMAGE_QOS)
            for c in CORNERS for s in ("intra", "extra")}
    got: dict[int, tuple[float, bool]] = {}
    ready = threading.Event()

    def on_dof(m) -> None:
        got[stamp_to_ns(m.header.stamp)] = (time.perf_counter(), bool(m.valid))

    def on_diag(arr) -> None:
        for st in arr.status:
            if st.name.startswith("wavefront_node") and any(
                    kv.key == "state" and kv.value == "ready" for kv in st.values):
                ready.set()

    node.create_subscription(DofCorrection, "aos/ofc/dof_correction", on_dof, OUTPUT_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    spin_thread = threading.Thread(target=ex.spin, daemon=True)
    spin_thread.start()
    msgs = {k: image_msg(v, 0) for k, v in images.items()}

    def run_phase(period: float, duration: float, sample_rss: bool) -> dict:
        sent: dict[int, float] = {}
        rss: list[tuple[float, float]] = []
        t0 = time.perf_counter()
        next_t, next_rss = t0, t0
        while time.perf_counter() - t0 < duration:
            now = time.perf_counter()
            if sample_rss and now >= next_rss:
                rss.append((now - t0, tree_rss_mb(proc.pid)))
                next_rss += 5.0
            if now < next_t:
                time.sleep(min(next_t - now, 0.05))
                continue
            stamp = time.time_ns()
            for k, m in msgs.items():
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
                pubs[k].publish(m)
            sent[stamp] = time.perf_counter()
            next_t += period
        end = time.perf_counter() + 30.0
        while time.perf_counter() < end and not all(s in got for s in sent):
            time.sleep(0.05)
        lat = np.array([got[s][0] - t for s, t in sent.items() if s in got]) * 1e3
        dropped = sum(1 for s in sent if s not in got)
        invalid = sum(1 for s in sent if s in got and not got[s][1])
        return {"period": period, "visits": len(sent), "lat": lat, "dropped": dropped,
                "invalid": invalid, "rss": rss}

    def show(r: dict) -> None:
        lat = r["lat"]
        q = (np.percentile(lat, [50, 90, 99]).round(1).tolist() + [round(float(lat.max()), 1)]
             if lat.size else ["-"] * 4)
        print(f"period {r['period']:5.2f} s: {r['visits']:4d} visits, latency p50/p90/p99/max "
              f"{q[0]} / {q[1]} / {q[2]} / {q[3]} ms, dropped {r['dropped']}, "
              f"invalid {r['invalid']}", flush=True)

    code = 0
    try:
        if not ready.wait(120):
            raise RuntimeError("wavefront_node never reported ready")
        end = time.perf_counter() + 20
        while time.perf_counter() < end and not all(p.get_subscription_count() > 0
                                                    for p in pubs.values()):
            time.sleep(0.05)
        main_run = run_phase(args.period, args.duration, sample_rss=True)
        show(main_run)
        rss = np.array(main_run["rss"])
        if rss.size:
            half = len(rss) // 2
            print(f"memory (node + workers): start {rss[0, 1]:.0f} MB, end {rss[-1, 1]:.0f} "
                  f"MB, max {rss[:, 1].max():.0f} MB; mean of 2nd half - 1st half "
                  f"{rss[half:, 1].mean() - rss[:half, 1].mean():+.1f} MB over "
                  f"{rss[-1, 0]:.0f} s")
        best = None
        for period in [float(p) for p in args.ramp.split(",") if p.strip()]:
            r = run_phase(period, 20.0, sample_rss=False)
            show(r)
            ok = (r["dropped"] == 0 and r["invalid"] == 0 and r["lat"].size
                  and np.percentile(r["lat"], 90) < period * 1e3)
            if ok:
                best = period
            else:
                break
        if best is not None:
            print(f"highest sustained rate: {1 / best:.1f} visits/s (period {best:g} s); "
                  f"{40.0 / best:.0f}x the LSST cadence")
    except Exception as exc:  # noqa: BLE001
        print(f"bench failed: {exc}", file=sys.stderr)
        code = 1
    finally:
        stop_bringup(proc, 15.0)
        stop_client(ex, spin_thread, node)
    return code


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    raise SystemExit(main())
