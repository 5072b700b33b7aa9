#!/usr/bin/env python3
"""Frames through the real graph: multi-star half-chip frames to a `cwfs-ros bringup` in its
own process, visit after visit, timed from the last image sent to the WavefrontVector.

Frames are rendered in advance by the simulator (ray-traced through a perturbed telescope,
sky 50/px): every visit has new star positions, 4 corners x 2 half-chips of ``--rows`` x
``--cols`` px with ``--stars`` isolated stars each, plus a blended pair and a faint star (the
camera_sim_node defaults of config/params.yaml). They are kept in ``--cache`` and reused.

The graph is ``cwfs-ros bringup`` (wavefront_node + ofc_node, the shipped parameters) with
``input_mode:=frames``, as a camera that sends frames is configured
(docs/connecting-a-camera.md). This process is the camera: it publishes the 8 frames of a
visit as sensor_msgs/Image (32FC1, built here by hand), waits for the visit's
WavefrontVector, then ``--gap`` seconds, and goes on. The first visit is sent as soon as
wavefront_node reports ready on /diagnostics.

Prints, per visit and in summary: the time from the last image published to the complete
WavefrontVector (first visit, median, p90, max), whether every corner was valid, each
corner's compute_ms (from its CornerWavefront), the node's warm-up time (the tiles a
previous run left in the tile store, ``$ROS_HOME/cwfs_ros/tiles``, are read, not traced:
``warm_tiles.<corner>`` says how many; a fresh ``ROS_HOME`` times a first start) and its workers'
cache hit rates (from /diagnostics).

    .venv/bin/python bench/bench_frames_graph.py                 # 20 visits
    .venv/bin/python bench/bench_frames_graph.py --visits 5 --render-only
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
from graph_process import start_bringup, stop_bringup, stop_client  # noqa: E402

CORNERS = ("R00", "R04", "R40", "R44")
SIDES = ("intra", "extra")


def _visit_specs(k: int, a: argparse.Namespace) -> list:
    """Visit ``k``'s frame specifications, keyed ``R00_intra`` ...: windows of ``--rows`` x
    ``--cols`` along their half-chips, as camera_sim_node renders them."""
    from dataclasses import replace

    from cwfs_ros.sim.visit import FrameScene, frame_specs

    scene = FrameScene((a.rows, a.cols), (a.stars[0], a.stars[1]), (2e5, 1e6))
    specs = frame_specs(CORNERS, scene, np.random.default_rng(a.seed + 1000 * k))
    return [replace(s, key=f"{s.key[0]}_{s.key[1]}") for s in specs]


def _cached(path: Path) -> dict[str, np.ndarray]:
    if not path.exists():
        return {}
    with np.load(path) as z:
        return {key: z[key] for key in z.files}


def render(cache: Path, visits: int, a: argparse.Namespace) -> list[dict[str, np.ndarray]]:
    """The visits' frames, keyed ``R00_intra`` ...; rendered on first use into ``cache``.
    A cached frame of another shape than its specification is rendered again (the others
    are kept: each frame has its own seed)."""
    cache.mkdir(parents=True, exist_ok=True)
    out, pool = [], None
    try:
        for k in range(visits):
            path = cache / f"visit{k:02d}.npz"
            have = _cached(path)
            todo = [s for s in _visit_specs(k, a)
                    if have.get(s.key, np.empty(0)).shape != s.shape_px]
            if todo:
                from cwfs_ros.sim.perturbation import stroke_perturbation
                from cwfs_ros.sim.telescope import perturbed_telescope
                from cwfs_ros.sim.visit import make_render_pool, render_frames

                if pool is None:
                    pool = make_render_pool(a.render_workers)
                    tel = perturbed_telescope(stroke_perturbation("mixed", a.seed, 500.0),
                                              band="r")
                t0 = time.perf_counter()
                frames = render_frames(tel, todo, band="r", wavelength_nm=622.0,
                                       sky_per_pixel=50.0, executor=pool)
                have.update({key: f.image.astype(np.float32) for key, f in frames.items()})
                np.savez(path, **have)
                n = sum(len(f.stars) for f in frames.values())
                print(f"rendered visit {k}: {len(todo)} frames, {n} stars in "
                      f"{time.perf_counter() - t0:.0f} s", flush=True)
            out.append(have)
    finally:
        if pool is not None:
            pool.shutdown()
    return out


def image_message(img: np.ndarray, stamp_ns: int, frame_id: str):
    """A sensor_msgs/Image of a float32 frame, written out field by field."""
    from sensor_msgs.msg import Image

    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    m.header.frame_id = frame_id
    m.height, m.width = (int(v) for v in img.shape)
    m.encoding = "32FC1"
    m.is_bigendian = 0
    m.step = 4 * int(img.shape[1])
    m.data = np.ascontiguousarray(img, dtype="<f4").tobytes()
    return m


class Listener:
    """This process's side of the graph: vectors, corner estimates and diagnostics."""

    def __init__(self, node) -> None:
        from cwfs_msgs.msg import CornerWavefront, WavefrontVector
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy

        self.lock = threading.Lock()
        self.vectors: dict[int, tuple[float, object]] = {}
        self.corners: dict[tuple[int, str], object] = {}
        self.diag: dict[str, str] = {}
        self.ready = threading.Event()
        out_qos = QoSProfile(depth=10, reliability=QoSReliabilityPolicy.RELIABLE,
                             durability=QoSDurabilityPolicy.VOLATILE)
        node.create_subscription(WavefrontVector, "/aos/wfs/wavefront", self.on_vector,
                                 out_qos)
        for c in CORNERS:
            node.create_subscription(CornerWavefront, f"/aos/wfs/{c}/wavefront",
                                     self.on_corner, out_qos)
        node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diag, 10)

    @staticmethod
    def stamp(msg) -> int:
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)

    def on_vector(self, msg) -> None:
        with self.lock:
            self.vectors[self.stamp(msg)] = (time.perf_counter(), msg)

    def on_corner(self, msg) -> None:
        with self.lock:
            self.corners[(self.stamp(msg), str(msg.corner))] = msg

    def on_diag(self, arr) -> None:
        for st in arr.status:
            if st.name.startswith("wavefront_node"):
                values = {kv.key: kv.value for kv in st.values}
                with self.lock:
                    self.diag = values
                if values.get("state") == "ready":
                    self.ready.set()


def run_visits(node, pubs: dict, listener: Listener, visits: list[dict], gap_s: float,
               wait_s: float) -> list[dict]:
    rows = []
    for k, frames in enumerate(visits):
        stamp = time.time_ns()
        msgs = {key: image_message(img, stamp, "focal_plane") for key, img in frames.items()}
        for key, m in msgs.items():
            pubs[key].publish(m)
        t_last = time.perf_counter()
        end = t_last + wait_s
        while time.perf_counter() < end and stamp not in listener.vectors:
            time.sleep(0.005)
        time.sleep(0.2)  # the corner estimates are published before the vector
        with listener.lock:
            got = listener.vectors.get(stamp)
            corners = {c: listener.corners.get((stamp, c)) for c in CORNERS}
        row = {"visit": k, "latency_s": (got[0] - t_last) if got else float("nan"),
               "valid": bool(got and all(got[1].corner_valid)),
               "compute_ms": {c: float(m.compute_ms) if m else float("nan")
                              for c, m in corners.items()},
               "n_pairs": {c: int(m.n_pairs) if m else 0 for c, m in corners.items()},
               "status": got[1].status if got else "no vector"}
        rows.append(row)
        print(f"visit {k:2d}: {row['latency_s'] * 1e3:7.0f} ms  valid={row['valid']!s:5}  "
              + "  ".join(f"{c} {row['compute_ms'][c]:6.0f} ms/{row['n_pairs'][c]}p"
                          for c in CORNERS)
              + ("" if row["valid"] else f"  [{row['status']}]"), flush=True)
        time.sleep(gap_s)
    return rows


def summarise(rows: list[dict], diag: dict[str, str], timeout_s: float) -> None:
    lat = np.array([r["latency_s"] for r in rows]) * 1e3
    ok = np.isfinite(lat)
    late = sum(1 for r, x in zip(rows, lat, strict=True)
               if not r["valid"] or not np.isfinite(x) or x > timeout_s * 1e3)
    rest = lat[1:][ok[1:]]
    print(f"\nlast image -> WavefrontVector: first visit {lat[0]:.0f} ms; visits 2-{len(rows)}: "
          f"median {np.median(rest):.0f} ms, p90 {np.percentile(rest, 90):.0f} ms, "
          f"max {rest.max():.0f} ms; all {len(rows)}: median {np.nanmedian(lat):.0f} ms, "
          f"max {np.nanmax(lat):.0f} ms")
    print(f"visits not complete and valid within the visit timeout ({timeout_s:g} s): "
          f"{late} of {len(rows)}")
    for c in CORNERS:
        v = np.array([r["compute_ms"][c] for r in rows])
        print(f"compute_ms {c}: first {v[0]:.0f}, median {np.nanmedian(v[1:]):.0f}, "
              f"max {np.nanmax(v[1:]):.0f}")
    keys = sorted(k for k in diag if k.startswith(("warm_s.", "warm_tiles.", "cache.", "workers",
                                                   "affinity", "timeout.")))
    for k in keys:
        print(f"{k}: {diag[k]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--visits", type=int, default=20)
    ap.add_argument("--rows", type=int, default=2000)
    ap.add_argument("--cols", type=int, default=1000)
    ap.add_argument("--stars", type=int, nargs=2, default=(3, 6), metavar=("MIN", "MAX"))
    ap.add_argument("--seed", type=int, default=20261203)
    ap.add_argument("--cache", type=Path, default=REPO / "out" / "bench_frames_graph")
    ap.add_argument("--render-workers", type=int, default=2)
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--gap", type=float, default=3.0, help="seconds between visits")
    ap.add_argument("--domain", type=int, default=None)
    ap.add_argument("-p", dest="params", action="append", default=[],
                    help="extra bringup parameter, name:=value (repeatable)")
    a = ap.parse_args()
    visits = render(a.cache, a.visits, a)
    if a.render_only:
        return 0
    domain = a.domain if a.domain is not None else 20 + os.getpid() % 80
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE",
                          str(REPO / "config" / "fastdds_profile.xml"))
    extra = [x for p in a.params for x in ("-p", p)]
    t_start = time.perf_counter()
    proc = start_bringup(["--log-level", "warn", "-p", "input_mode:=frames",
                          "-p", "rotator_angle_source:=fixed", *extra], domain)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("bench_frames_graph")
    img_qos = QoSProfile(depth=4, reliability=QoSReliabilityPolicy.RELIABLE)
    pubs = {f"{c}_{s}": node.create_publisher(Image, f"/aos/wfs/{c}/{s}/image", img_qos)
            for c in CORNERS for s in SIDES}
    listener = Listener(node)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    code = 0
    try:
        if not listener.ready.wait(600):
            raise RuntimeError("wavefront_node never reported ready")
        print(f"graph ready {time.perf_counter() - t_start:.1f} s after start", flush=True)
        end = time.perf_counter() + 30
        while time.perf_counter() < end and not all(p.get_subscription_count() > 0
                                                    for p in pubs.values()):
            time.sleep(0.05)
        with listener.lock:
            timeout_s = float(listener.diag.get("visit_timeout_s", "2.0"))
        rows = run_visits(node, pubs, listener, visits, a.gap, max(10.0, 3 * timeout_s))
        time.sleep(2.5)  # one more diagnostics period
        with listener.lock:
            diag = dict(listener.diag)
        summarise(rows, diag, timeout_s)
    except Exception as exc:  # noqa: BLE001
        print(f"bench failed: {exc}", file=sys.stderr)
        code = 1
    finally:
        stop_bringup(proc)
        stop_client(ex, spinner, node)
    return code


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    raise SystemExit(main())
