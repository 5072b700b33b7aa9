"""Frames through the graph: camera_sim_node publishes half-chip frames with several stars
(plus a blended pair and a too-faint star); wavefront_node detects, pairs and combines the
donuts and publishes the corner with n_pairs and a per-term uncertainty. With
``input_mode: frames`` the warm-up builds the field tiles of the corner's half-chips, so the
first visit builds none. The tile store is a directory that cannot be made, which the warm-up
says in the log and on /diagnostics and which costs nothing else. Real DDS, one process, the
test's own domain."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import spin_thread, wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import CornerWavefront, SimTruth  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from cwfs_ros.ros.camera_sim_node import CameraSimNode  # noqa: E402
from cwfs_ros.ros.common import OUTPUT_QOS  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor  # noqa: E402
from cwfs_ros.ros.wavefront_node import WavefrontNode  # noqa: E402


def _diag(node) -> dict[str, str]:
    return {kv.key: kv.value for kv in node.diagnostics().values}


def test_frames_are_selected_paired_and_combined(ros_context, tmp_path):
    P = Parameter
    blocker = tmp_path / "a_file"
    blocker.write_text("x")  # no directory can be made under a file
    cam = CameraSimNode(context=ros_context, parameter_overrides=[
        P("corners", value=["R00"]),  # the one corner the wavefront node serves
        P("visit_period_s", value=0.0), P("frames", value=True), P("frame_rows", value=1000),
        P("frame_cols", value=1000), P("frame_stars_min", value=2),
        P("frame_stars_max", value=2), P("frame_flux_min", value=3e5),
        P("frame_flux_max", value=3e5), P("render_seed", value=3)])
    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        P("corners", value=["R00"]), P("workers", value=1), P("assemble", value=False),
        P("solver", value="lsq"), P("visit_timeout_s", value=60.0),
        P("input_mode", value="frames"), P("tile_store", value=str(blocker / "tiles"))])
    tester = rclpy.create_node("frames_tester", context=ros_context)
    got: list[CornerWavefront] = []
    truth: list[SimTruth] = []
    tester.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront", got.append,
                               OUTPUT_QOS)
    tester.create_subscription(SimTruth, "aos/sim/truth", truth.append, OUTPUT_QOS)
    trigger = tester.create_client(Trigger, "camera_sim_node/trigger")
    ex = MultiThreadedExecutor(num_threads=4, context=ros_context)
    for n in (cam, wf, tester):
        ex.add_node(n)
    th = spin_thread(ex)
    th.start()
    try:
        wait_for(lambda: wf.ready, 180, "warm-up")
        warm = _diag(wf)
        assert int(warm["warm_tiles.R00"].split()[0]) > 0, warm
        assert "failed writes" in warm["tile_store.R00"], warm
        assert "cannot write" in warm["tile_store.R00"] and str(blocker) in warm["tile_store.R00"]
        assert trigger.wait_for_service(timeout_sec=10)
        wait_for(lambda: cam.pubs[("R00", "intra")].get_subscription_count() > 0, 10,
                 "discovery")
        fut = trigger.call_async(Trigger.Request())
        wait_for(fut.done, 10, "trigger")
        assert fut.result().success
        wait_for(lambda: bool(got) and bool(truth), 180, "the corner result")
        m = got[0]
        # 2 isolated stars + a blended pair + a faint one were injected on each half.
        assert cam.last_frame_stars[("R00", "intra")] == 5
        assert m.valid, m.status
        assert wf.stats["frame_pairs"] == 1
        assert 1 <= m.n_pairs <= 2, m.n_pairs
        assert "blended" in m.status and "too_faint" in m.status, m.status
        unc = np.asarray(m.uncertainty_nm)
        assert unc.shape == (19,) and np.all(np.isfinite(unc)) and np.all(unc > 0)
        # The telescope is nominal: the truth at R00 is its design wavefront.
        err = np.asarray(m.zernikes_nm) - np.asarray(truth[0].zernikes_nm)[:19]
        print(f"\n{m.status}; n_pairs {m.n_pairs}; error {np.sqrt(np.mean(err ** 2)):.1f} nm "
              f"rms; uncertainty median {np.median(unc):.1f} nm")
        assert np.sqrt(np.mean(err ** 2)) < 50.0, err
        # The first visit after start read every tile it needed from the warm-up.
        after = _diag(wf)
        assert after["frame_transport"] == "shared memory 1, pipe 0", after
        assert "(0 builds;" not in after["cache.pair_geometry"]  # the pairs were new fields
        for kind in ("map", "design"):
            assert " 0 builds;" in after[f"cache.{kind}"], after[f"cache.{kind}"]
            assert not after[f"cache.{kind}"].startswith("hit -"), after[f"cache.{kind}"]
    finally:
        ex.shutdown(timeout_sec=2.0)
        th.join(5)
        for n in (cam, wf, tester):
            n.destroy_node()
