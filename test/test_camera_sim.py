"""camera_sim_node: rendered visits, ground truth, and the DoF state driven by DofCorrection.

Each test runs the node in this process on its own rclpy Context and DDS domain, with a tester
node on the same context, spun by a MultiThreadedExecutor in a thread.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import spin_thread, wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")
sim = pytest.importorskip("cwfs_ros.sim")

from cwfs_msgs.msg import DofCorrection, SimTruth  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from cwfs_ros.layout import CORNERS  # noqa: E402
from cwfs_ros.ofc.control import load_dof_spec  # noqa: E402
from cwfs_ros.ros.camera_sim_node import RIGID_SCALE, CameraSimNode  # noqa: E402
from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import dof_correction_msg  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor  # noqa: E402

NPIX = 160
FAST = {"visit_period_s": 0.0, "n_photons": 2e5, "npix": NPIX, "render_seed": 7}


class Tester:
    __test__ = False

    def __init__(self, ctx):
        self.node = rclpy.create_node("camera_sim_tester", context=ctx)
        self.images: dict[tuple[str, str], list[Image]] = {
            (c, s): [] for c in CORNERS for s in ("intra", "extra")}
        for key, lst in self.images.items():
            self.node.create_subscription(Image, f"aos/wfs/{key[0]}/{key[1]}/image",
                                          lst.append, IMAGE_QOS)
        self.truth: list[SimTruth] = []
        self.node.create_subscription(SimTruth, "aos/sim/truth", self.truth.append, OUTPUT_QOS)
        self.diag: list[DiagnosticArray] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)
        self.pub = self.node.create_publisher(DofCorrection, "aos/ofc/dof_correction",
                                              OUTPUT_QOS)
        self.trigger = self.node.create_client(Trigger, "camera_sim_node/trigger")

    def call_trigger(self):
        assert self.trigger.wait_for_service(timeout_sec=10)
        fut = self.trigger.call_async(Trigger.Request())
        wait_for(fut.done, 10, "~/trigger response")
        return fut.result()


def make_system(ros_domain, **params):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    overrides = [Parameter(k, value=v) for k, v in {**FAST, **params}.items()]
    node = CameraSimNode(context=ctx, parameter_overrides=overrides)
    tester = Tester(ctx)
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    ex.add_node(node)
    ex.add_node(tester.node)
    th = spin_thread(ex)
    th.start()
    wait_for(lambda: tester.pub.get_subscription_count() > 0
             and all(node.pubs[k].get_subscription_count() > 0 for k in node.pubs)
             and node.pub_truth.get_subscription_count() > 0, 10, "discovery")

    def close():
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        tester.node.destroy_node()
        ctx.try_shutdown()
        th.join(5)

    return node, tester, close


@pytest.fixture
def camera(ros_domain):
    node, tester, close = make_system(ros_domain, perturbation_seed=3)
    try:
        yield node, tester
    finally:
        close()


def correction(dof, *, stamp_ns=1, valid=True, dry_run=False, status="ok"):
    return dof_correction_msg(stamp_ns=stamp_ns, frame_id="telescope", dof=np.asarray(dof, float),
                              dof_total=np.asarray(dof, float), valid=valid, status=status,
                              wavefront_rms_nm=1.0, predicted_residual_rms_nm=0.5,
                              dry_run=dry_run, n_modes_used=12)


def test_visit_images_and_truth(camera):
    node, t = camera
    # the seeded rigid-body perturbation: DoF 0-9 only, at the documented scale
    dof0 = node.dof_state
    assert np.all(dof0[10:] == 0) and np.all(dof0[:10] != 0)
    expected = np.random.default_rng(3).normal(0.0, 1.0, 10) * 1.0 * RIGID_SCALE
    np.testing.assert_allclose(dof0[:10], expected)

    res = t.call_trigger()
    assert res.success, res.message
    again = t.call_trigger()  # the first visit is still rendering: refused, not queued
    assert not again.success and "still rendering" in again.message
    wait_for(lambda: t.truth and all(t.images.values()), 60, "a rendered visit")

    stamps = set()
    for (c, s), msgs in t.images.items():
        assert len(msgs) == 1, (c, s)
        m = msgs[0]
        assert m.encoding == "32FC1" and (m.height, m.width) == (NPIX, NPIX)
        assert m.step == 4 * NPIX and len(m.data) == 4 * NPIX * NPIX and not m.is_bigendian
        assert m.header.frame_id == "focal_plane"
        img = np.frombuffer(bytes(m.data), dtype="<f4").reshape(NPIX, NPIX)
        # sky-subtracted Poisson image holding (most of) the 2e5 photons
        assert np.all(np.isfinite(img)) and 1.2e5 < img.sum() < 2.1e5, (c, s, img.sum())
        stamps.add(stamp_to_ns(m.header.stamp))
    assert len(stamps) == 1

    (truth,) = t.truth
    assert stamp_to_ns(truth.header.stamp) in stamps
    assert truth.visit == 1 and truth.band == "r"
    np.testing.assert_array_equal(truth.dof_state, dof0)
    geo = sim.load_corner_geometry()
    tel = sim.perturbed_telescope(np.asarray(truth.dof_state), "r")
    nominal = sim.perturbed_telescope(np.zeros(50), "r")
    want = np.concatenate([sim.true_zernikes_nm(tel, geo[c].mid_field_deg, wavelength_nm=622.0)
                           for c in CORNERS])
    want_intr = np.concatenate([sim.true_zernikes_nm(nominal, geo[c].mid_field_deg,
                                                     wavelength_nm=622.0) for c in CORNERS])
    assert len(truth.zernikes_nm) == 76 and len(truth.intrinsic_nm) == 76
    np.testing.assert_allclose(truth.zernikes_nm, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(truth.intrinsic_nm, want_intr, rtol=0, atol=1e-9)
    # the perturbation is visible over the design wavefront
    assert np.sqrt(np.mean((want - want_intr) ** 2)) > 10.0

    wait_for(lambda: any(kv.key == "visits_rendered" and kv.value == "1"
                         for d in list(t.diag) for st in d.status for kv in st.values),
             5, "diagnostics reporting the visit")
    # ... with the visit's true wavefront error: mean over corners of sqrt(sum of squares).
    d = (want - want_intr).reshape(4, 19)
    wfe = float(np.mean(np.sqrt(np.sum(d ** 2, axis=1))))
    wait_for(lambda: any(kv.key == "true_wavefront_error_nm" and kv.value == f"{wfe:.1f}"
                         for d in list(t.diag) for st in d.status for kv in st.values),
             5, "diagnostics reporting the true wavefront error")


def visit(t) -> int:
    """Render one visit; its stamp (a correction is applied only for a visit published)."""
    n = len(t.truth)
    # The node is ready again before it publishes a visit's truth; a trigger it refuses
    # anyway (counted as visits_skipped) is tried again.
    wait_for(lambda: t.call_trigger().success, 30, "a visit trigger")
    wait_for(lambda: len(t.truth) > n, 60, "a rendered visit")
    return stamp_to_ns(t.truth[-1].header.stamp)


def test_corrections_change_the_state(camera):
    node, t = camera
    applied = lambda n: node.stats["corrections_applied"] == n  # noqa: E731
    ignored = lambda n: node.stats["corrections_ignored"] == n  # noqa: E731
    before = node.dof_state
    s1 = visit(t)
    # Within the step limits (dof.yaml's max_step).
    step = np.linspace(-1.0, 1.0, 50) * 0.5 * load_dof_spec().max_step
    t.pub.publish(correction(step, stamp_ns=s1))
    wait_for(lambda: applied(1), 5, "a valid correction applied")
    np.testing.assert_array_equal(node.dof_state, before + step)

    state = node.dof_state
    t.pub.publish(correction(step, stamp_ns=s1, valid=False, status="refused: test"))
    wait_for(lambda: ignored(1), 5, "invalid correction ignored")
    t.pub.publish(correction(step, stamp_ns=s1, dry_run=True))
    wait_for(lambda: ignored(2), 5, "dry-run correction ignored")
    bad = step.copy()
    bad[3] = np.nan
    t.pub.publish(correction(bad, stamp_ns=s1))
    wait_for(lambda: ignored(3), 5, "non-finite correction ignored")
    node.set_parameters([Parameter("apply_corrections", value=False)])
    t.pub.publish(correction(step, stamp_ns=s1))
    wait_for(lambda: ignored(4), 5, "correction ignored with apply_corrections false")
    assert node.stats["corrections_applied"] == 1
    np.testing.assert_array_equal(node.dof_state, state)
    assert node.ignored.counts == {"invalid": 1, "dry_run": 1, "bad_dof": 1, "not_applied": 1}

    # back on: the next rendered visit uses the corrected state
    node.set_parameters([Parameter("apply_corrections", value=True)])
    s2 = visit(t)
    np.testing.assert_array_equal(t.truth[-1].dof_state, state)
    t.pub.publish(correction(step, stamp_ns=s2))
    wait_for(lambda: applied(2), 5, "correction applied again")
    np.testing.assert_array_equal(node.dof_state, state + step)
    visit(t)
    np.testing.assert_array_equal(t.truth[-1].dof_state, state + step)


def test_actuator_noise_scales_each_dof(ros_domain):
    node, t, close = make_system(ros_domain, actuator_noise=0.1,
                                 correction_max_step_scale=0.0)  # no step limit
    try:
        step = np.full(50, 2.0)
        t.pub.publish(correction(step, stamp_ns=visit(t)))
        wait_for(lambda: node.stats["corrections_applied"] == 1, 5, "correction applied")
        d = node.dof_state
        assert np.all(d != step) and np.all(np.abs(d / step - 1.0) < 0.6)
    finally:
        close()


def test_periodic_visits_skip_while_rendering(ros_domain):
    # a 0.1 s period is far shorter than a visit: periods are skipped, visits never overlap
    node, t, close = make_system(ros_domain, visit_period_s=0.1, n_photons=2e4)
    try:
        wait_for(lambda: len(t.truth) >= 2, 30, "two periodic visits")
        assert node.stats["visits_skipped"] > 0
        visits = [m.visit for m in t.truth]
        assert visits == sorted(visits) and len(set(visits)) == len(visits)
        for m in t.truth:  # each visit's 8 images share its stamp
            s = stamp_to_ns(m.header.stamp)
            assert all(any(stamp_to_ns(i.header.stamp) == s for i in lst)
                       for lst in t.images.values())
    finally:
        close()


def test_a_visit_triggered_right_after_another_waits_for_the_readout(ros_domain):
    """A trigger right after a visit (a driver that asks as soon as the correction is
    applied): the camera exposes once readout_s has passed since the last exposure, so
    ofc_node's min_visit_period_s (sim.yaml, at most readout_s) never refuses the visit."""
    from cwfs_ros.cli.replay import node_parameters
    from cwfs_ros.config import config_dir, load_yaml

    readout = 1.5
    node, t, close = make_system(ros_domain, readout_s=readout, n_photons=2e4)
    try:
        stamps = [visit(t), visit(t), visit(t)]
        gaps_s = np.diff(stamps) / 1e9
        assert np.all(gaps_s >= readout), gaps_s
        assert np.all(gaps_s < readout + 5.0), gaps_s  # waited for, not skipped
        assert node.stats["visits_skipped"] == 0
    finally:
        close()
    shipped = node_parameters("camera_sim_node")["readout_s"]
    sim_ofc = load_yaml(config_dir() / "sim.yaml")["ofc_node"]["ros__parameters"]
    assert sim_ofc["min_visit_period_s"] <= shipped


def test_a_corner_subset_is_rendered_and_published_alone(ros_domain):
    """``corners: [R04]``: only R04's two image topics have a publisher and receive the
    visit; the truth still covers the four corners. A name that is not a corner stops the
    node at start."""
    node, t, close = make_system(ros_domain, corners=["R04"])
    try:
        counts = {(c, s): t.node.count_publishers(f"/aos/wfs/{c}/{s}/image")
                  for c in CORNERS for s in ("intra", "extra")}
        assert counts == {k: int(k[0] == "R04") for k in counts}, counts
        assert t.call_trigger().success
        wait_for(lambda: t.truth and all(t.images[("R04", s)] for s in ("intra", "extra")),
                 60, "the R04 visit")
        assert not any(msgs for (c, _), msgs in t.images.items() if c != "R04")
        assert len(t.truth[0].zernikes_nm) == 76
    finally:
        close()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        with pytest.raises(ValueError, match="corners must be distinct names"):
            CameraSimNode(context=ctx, parameter_overrides=[
                Parameter("corners", value=["R00", "R99"])])
    finally:
        ctx.try_shutdown()
