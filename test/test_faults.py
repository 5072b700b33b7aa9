"""Faults: the wavefront node killed in the middle of a visit and restarted.

wavefront_node runs in its own process group, started as a user would
(``python -m cwfs_ros.ros.launch node wavefront_node``), on the test's DDS domain; ofc_node and a
tester run in this process. Half of visit A's images are published, the node is SIGKILLed
(with its workers) while it holds them, and a new node is started. The rest of visit A and a
complete visit B follow. Expected: the new node recovers and visit B gets a valid
correction; visit A, whose images were half lost with the old node, never gets a valid one.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import kill_group, spin_thread, wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor  # noqa: E402
from cwfs_ros.ros.ofc_node import OfcNode  # noqa: E402
from cwfs_ros.sim import load_corner_geometry, perturbed_telescope  # noqa: E402
from cwfs_ros.sim.visit import DonutSpec, render_visit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CORNERS = ("R00", "R04", "R40", "R44")
SEC = 1_000_000_000


def _visit_images() -> dict[tuple[str, str], np.ndarray]:
    geo = load_corner_geometry()
    dof = np.zeros(50)
    dof[[1, 6]] = [120.0, -80.0]  # M2 and camera decentres: a few hundred nm
    specs = [DonutSpec((c, s), f, dz, (1.0, -1.0), 17 + i)
             for i, (c, s, f, dz) in enumerate(
                 (c, s, *((geo[c].intra_field_deg, geo[c].intra_offset_mm) if s == "intra"
                          else (geo[c].extra_field_deg, geo[c].extra_offset_mm)))
                 for c in CORNERS for s in ("intra", "extra"))]
    return render_visit(perturbed_telescope(dof, "r"), specs, wavelength_nm=622.0,
                        n_photons=2e5, sky_per_pixel=20.0)


def _start_node(domain: int) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    cmd = [sys.executable, "-m", "cwfs_ros.ros.launch", "node", "wavefront_node", "--ros-args",
           "-p", "workers:=2", "-p", "visit_timeout_s:=1.5", "-p", "diagnostics_period_s:=0.2"]
    # Own process group: SIGKILL takes the node and its estimator workers down together, as
    # a crash of the container would.
    return subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)




def test_wavefront_node_killed_mid_visit_recovers_and_publishes_nothing_stale(ros_domain):
    images = _visit_images()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    ex = MultiThreadedExecutor(num_threads=3, context=ctx)
    ofc = OfcNode(context=ctx, parameter_overrides=[
        Parameter("diagnostics_period_s", value=0.5),
        Parameter("rotator_angle_source", value="fixed")])  # no rotator on this bench
    tester = rclpy.create_node("fault_tester", context=ctx)
    ex.add_node(ofc)
    ex.add_node(tester)
    pubs = {(c, s): tester.create_publisher(Image, f"aos/wfs/{c}/{s}/image", IMAGE_QOS)
            for c in CORNERS for s in ("intra", "extra")}
    vectors: list[WavefrontVector] = []
    dofs: list[DofCorrection] = []
    ready_at: list[float] = []

    images_seen: list[int] = []  # the wavefront node's own count of images received

    def on_diag(arr: DiagnosticArray) -> None:
        for st in arr.status:
            if st.name.startswith("wavefront_node") and any(
                    kv.key == "state" and kv.value == "ready" for kv in st.values):
                ready_at.append(time.monotonic())
                images_seen.extend(int(kv.value) for kv in st.values if kv.key == "images")

    tester.create_subscription(WavefrontVector, "aos/wfs/wavefront", vectors.append,
                               OUTPUT_QOS)
    tester.create_subscription(DofCorrection, "aos/ofc/dof_correction", dofs.append,
                               OUTPUT_QOS)
    tester.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    th = spin_thread(ex)
    th.start()

    def publish(stamp: int, keys) -> None:
        for k in keys:
            m = image_msg(images[k], stamp)
            pubs[k].publish(m)

    keys = [(c, s) for c in CORNERS for s in ("intra", "extra")]
    # Stamps a camera would give (the nodes refuse images and visits stamped beyond their
    # max_future_s ahead of the clock): two visits 40 s apart, the second at the test's start.
    stamp_b = (time.time_ns() // SEC) * SEC
    stamp_a = stamp_b - 40 * SEC
    proc = _start_node(ros_domain)
    try:
        wait_for(lambda: bool(ready_at), 90, "the first wavefront_node to be ready")
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20,
                 "discovery")
        publish(stamp_a, keys[:5])            # R00, R04 complete; R40 intra only
        wait_for(lambda: bool(images_seen) and images_seen[-1] >= 5, 10,
                 "the node to hold half a visit (its diagnostics count the 5 images)")
        kill_group(proc)
        n_ready = len(ready_at)
        images_seen.clear()
        t_kill = time.monotonic()
        proc = _start_node(ros_domain)
        wait_for(lambda: len(ready_at) > n_ready and ready_at[-1] > t_kill + 0.5, 90,
                 "the restarted wavefront_node to be ready")
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20,
                 "rediscovery")
        # The killed process's writer stays in the graph until its lease expires (3 s,
        # config/fastdds_profile.xml), and ofc_node acts on no vector while its input has two
        # publishers (docs/reliability.md, "Who may act"). A restart that is ready sooner
        # than that would see visit B refused as untrusted_source, by design.
        wait_for(lambda: ofc.count_publishers("aos/wfs/wavefront") == 1, 20,
                 "the killed node's writer to leave ofc_node's graph")
        publish(stamp_a, keys[5:])            # the rest of visit A reaches the new node
        publish(stamp_b, keys)                # and a complete visit B
        wait_for(lambda: any(stamp_to_ns(d.header.stamp) == stamp_b for d in dofs), 60,
                 "the correction of visit B")
        time.sleep(2.0)                       # let any late output of visit A arrive
        by_stamp = {}
        for d in dofs:
            by_stamp.setdefault(stamp_to_ns(d.header.stamp), []).append(d)
        (b,) = by_stamp[stamp_b]
        assert b.valid, b.status
        vb = [v for v in vectors if stamp_to_ns(v.header.stamp) == stamp_b]
        assert len(vb) == 1 and all(vb[0].corner_valid)
        # Visit A: at most one correction, and it is not valid (corners lost with the node).
        a = by_stamp.get(stamp_a, [])
        assert len(a) <= 1 and not any(d.valid for d in a), [d.status for d in a]
        assert set(by_stamp) <= {stamp_a, stamp_b}
        print(f"\nvisit A: {[d.status for d in a]}; visit B: {b.status}")
    finally:
        kill_group(proc)
        ex.shutdown(timeout_sec=2.0)
        th.join(5)
        ofc.destroy_node()
        tester.destroy_node()
        ctx.try_shutdown()
