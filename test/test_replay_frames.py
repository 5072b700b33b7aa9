"""A recorded run with half-chip FRAMES replays to the live numbers.

camera_sim_node publishes frames with several stars (``frames: true``); wavefront_node routes
each pair to the frame job (detection, per-star field, selection, combination) in its worker
processes and ofc_node computes the correction, all over real DDS in this process with the
bag recorder on the same executor (as ``cwfs-ros bringup --sim`` plus ``cwfs-ros bag
record``). ``cwfs-ros replay``, a fresh process without middleware, must then give back the
live per-corner Zernikes to 1e-6 nm, with the same status (pairs used and rejected), and the
live DoF corrections, since it runs the node's own pipeline (:mod:`cwfs_ros.runtime.pipeline`)
and the same frame job.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from recorded_graph import record_visits, start_graph

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("cwfs_ros.sim")

from cwfs_ros.layout import CORNERS, NOLL  # noqa: E402
from cwfs_ros.ros.common import stamp_to_ns  # noqa: E402
from cwfs_ros.runtime.visits import format_stamp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VISITS = 2
OVERLAY = {
    # Frames take seconds per corner on a shared 2-core machine: a generous visit timeout,
    # so that the live visits are complete and the comparison is about the numbers.
    "wavefront_node": {"ros__parameters": {"visit_timeout_s": 60.0, "input_mode": "frames"}},
    # the simulated camera renders a visit per trigger, faster than the survey's cadence
    # (min_visit_period_s 15 s): the readout's 2 s, as config/sim.yaml sets it
    "ofc_node": {"ros__parameters": {"kp": 0.6, "ki": 0.0, "min_visit_period_s": 2.0}},
    "camera_sim_node": {"ros__parameters": {
        "visit_period_s": 0.0, "frames": True, "frame_rows": 800, "frame_cols": 800,
        "frame_stars_min": 2, "frame_stars_max": 2, "frame_flux_min": 1e5,
        "frame_flux_max": 1e5, "frame_blend": False, "frame_faint": False,
        "n_photons": 2e5, "perturbation_seed": 11, "perturbation_scale": 1.0,
        "render_seed": 5}},
}


def _record(ctx, started: dict, bag_dir: Path) -> dict:
    """Trigger the visits with the recorder on the graph's executor; what the tester got."""
    nodes = started["nodes"]
    out = record_visits(ctx, started, bag_dir, VISITS, tester="replay_frames_tester",
                        dof_timeout_s=120, warm_up_timeout_s=180)
    return {"live_corners": out["live_corners"], "live_dofs": out["live_dofs"],
            "frame_pairs": nodes["wavefront_node"].stats["frame_pairs"],
            "stars": dict(nodes["camera_sim_node"].last_frame_stars)}


@pytest.fixture(scope="module")
def frames_run(tmp_path_factory, ros_domain_module):
    """Record two frame visits of the simulated loop, then replay the bag with the CLI."""
    tmp = tmp_path_factory.mktemp("replay_frames")
    overlay = tmp / "overlay.yaml"
    overlay.write_text(yaml.safe_dump(OVERLAY))
    bag_dir = tmp / "frames_bag"
    ctx = rclpy.Context()
    t0 = time.monotonic()
    th, started = start_graph(ctx, ros_domain_module, overlay)
    try:
        out = _record(ctx, started, bag_dir)
    finally:
        ctx.try_shutdown()
        th.join(15)
    t1 = time.monotonic()
    # `cwfs-ros replay` as a user runs it: a fresh process, no middleware.
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    proc = subprocess.run([sys.executable, "-m", "cwfs_ros.cli", "replay", str(bag_dir),
                           "--out", str(tmp / "o"), "--params", str(overlay),
                           "--no-progress", "--no-plots"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr
    print(f"\nlive run {t1 - t0:.1f} s, replay {time.monotonic() - t1:.1f} s\n{proc.stdout}")
    with open(tmp / "o" / "zernikes.csv", newline="") as f:
        out["zernikes"] = list(csv.DictReader(f))
    with open(tmp / "o" / "dof.csv", newline="") as f:
        out["dof"] = list(csv.DictReader(f))
    out["summary"] = json.loads((tmp / "o" / "summary.json").read_text())
    return out


def test_the_live_run_estimated_frames(frames_run):
    """The live corners came from the frame job: two stars per frame detected, paired and
    combined, every corner of both visits valid."""
    live = frames_run["live_corners"]
    assert frames_run["frame_pairs"] == VISITS * len(CORNERS)
    assert set(frames_run["stars"].values()) == {2}
    assert len(live) == VISITS * len(CORNERS)
    assert all(m.valid for m in live), [m.status for m in live if not m.valid]
    assert all(1 <= m.n_pairs <= 2 for m in live), [m.n_pairs for m in live]
    assert sum(m.n_pairs for m in live) > len(live), "no corner combined two pairs"


def test_replay_gives_the_live_corner_wavefronts(frames_run):
    rows = {(r["corner"], r["stamp"]): r for r in frames_run["zernikes"]}
    live = frames_run["live_corners"]
    assert len(frames_run["zernikes"]) == len(live) == VISITS * len(CORNERS)
    worst = 0.0
    for m in live:
        r = rows[(m.corner, format_stamp(stamp_to_ns(m.header.stamp)))]
        assert r["valid"] == "1", r["status"]
        assert r["status"] == m.status  # the same pairs used, the same ones rejected
        z = np.array([float(r[f"Z{j}"]) for j in NOLL])
        diff = float(np.abs(z - np.asarray(m.zernikes_nm)).max())
        worst = max(worst, diff)
        assert diff <= 1e-6, (m.corner, diff)
    print(f"max |Z replay - Z live| over {len(live)} frame corners = {worst:.3g} nm")


def test_replay_gives_the_live_dof_corrections(frames_run):
    live = frames_run["live_dofs"]
    assert len(live) == VISITS and all(m.valid for m in live), [m.status for m in live]
    rows = {r["stamp"]: r for r in frames_run["dof"]}
    assert len(rows) == VISITS
    names = [h[len("dof."):] for h in frames_run["dof"][0] if h.startswith("dof.")]
    for m in live:
        r = rows[format_stamp(stamp_to_ns(m.header.stamp))]
        assert r["valid"] == "1", r["status"]
        dof = np.array([float(r[f"dof.{n}"]) for n in names])
        total = np.array([float(r[f"total.{n}"]) for n in names])
        np.testing.assert_allclose(dof, np.asarray(m.dof), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(total, np.asarray(m.dof_total), rtol=1e-9, atol=1e-12)
        assert int(r["n_modes_used"]) == m.n_modes_used
    assert np.abs(np.asarray(live[0].dof[:10])).max() > 1e-3  # a real correction
    cmp = frames_run["summary"]["comparison"]
    assert cmp["corners_compared"] == VISITS * len(CORNERS) and cmp["dof_compared"] == VISITS
    assert cmp["corners_validity_mismatch"] == 0 and cmp["max_zernike_diff_nm"] <= 1e-6
