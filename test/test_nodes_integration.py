"""Headless integration: wavefront_node + ofc_node over real DDS, fed ray-traced donuts.

The nodes are started as ``cwfs-ros bringup`` does (:func:`cwfs_ros.ros.launch.run_nodes`:
config/params.yaml, composed on one MultiThreadedExecutor), in this process, on the test's own
rclpy Context and DDS domain. A tester node on the same context publishes the 8 images of a
visit (160x160 stamps, donut centred on the chief ray, rendered by cwfs_ros.sim with a known
DoF perturbation) and collects every output.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import yaml
from conftest import REPO_ROOT

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import CornerWavefront, DofCorrection, WavefrontVector  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402

from cwfs_ros.layout import CORNERS  # noqa: E402
from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor as ProjectExecutor  # noqa: E402
from cwfs_ros.ros.launch import run_nodes  # noqa: E402

WL = 622.0
N_PHOTONS = 5e5
# The solver the shipped parameter file configures (the node must report what it ran).
CONFIGURED_SOLVER = yaml.safe_load((REPO_ROOT / "config" / "params.yaml").read_text())[
    "wavefront_node"]["ros__parameters"]["solver"]
# Known perturbation (batoid_rubin/OCS convention): M2 dz 20 µm, M2 dx 100 µm, M1M3 B1 0.05 µm.
PERTURBATION = {0: 20.0, 1: 100.0, 10: 0.05}
# Per-corner bound on |estimate - truth| (rms over Z4..Z22) at the corner mid-point field
# (the corners are vignetted and split; measured 13-23 nm here, median 17, on 2026-12-02).
# The perturbation is 69-96 nm per corner, so an estimator recovering only half of it fails.
CORNER_RMS_BOUND_NM = 30.0
MEDIAN_RMS_BOUND_NM = 22.0
ENCODINGS = {"R00": "16UC1", "R04": "32SC1", "R40": "64FC1", "R44": "32FC1"}
S1 = 1_700_000_000_000_000_000
S2 = S1 + 30_000_000_000


@pytest.fixture(scope="module")
def visit():
    """The 8 rendered stamps of one visit and the true Zernikes at each corner mid-point."""
    sim = pytest.importorskip("cwfs_ros.sim")
    geo = sim.load_corner_geometry()
    dof = np.zeros(50)
    for i, v in PERTURBATION.items():
        dof[i] = v
    tel = sim.perturbed_telescope(dof, "r")
    rng = np.random.default_rng(20240611)
    images, truth = {}, {}
    for c in CORNERS:
        g = geo[c]
        images[(c, "intra")] = sim.render_donut(tel, g.intra_field_deg, g.intra_offset_mm,
                                                wavelength_nm=WL, npix=160,
                                                n_photons=N_PHOTONS, rng=rng)
        images[(c, "extra")] = sim.render_donut(tel, g.extra_field_deg, g.extra_offset_mm,
                                                wavelength_nm=WL, npix=160,
                                                n_photons=N_PHOTONS, rng=rng)
        truth[c] = sim.true_zernikes_nm(tel, g.mid_field_deg, wavelength_nm=WL)
    return images, truth


class Tester:
    """Publishes images and records every output of the nodes (thread-safe lists)."""

    __test__ = False

    def __init__(self, ctx):
        self.node = rclpy.create_node("tester", context=ctx)
        self.pubs = {(c, s): self.node.create_publisher(Image, f"aos/wfs/{c}/{s}/image",
                                                        IMAGE_QOS)
                     for c in CORNERS for s in ("intra", "extra")}
        self.corner: list[CornerWavefront] = []
        self.vector: list[WavefrontVector] = []
        self.dof: list[DofCorrection] = []
        self.diag: list[DiagnosticArray] = []
        for c in CORNERS:
            self.node.create_subscription(CornerWavefront, f"aos/wfs/{c}/wavefront",
                                          self.corner.append, OUTPUT_QOS)
        self.node.create_subscription(WavefrontVector, "aos/wfs/wavefront", self.vector.append,
                                      OUTPUT_QOS)
        self.node.create_subscription(DofCorrection, "aos/ofc/dof_correction",
                                      self.dof.append, OUTPUT_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)
        self.joints = self.node.create_publisher(JointState, "joint_states", 100)

    def publish_visit(self, images, stamp, replace=None):
        # the camera rotator's position at the visit, as the telescope publishes it
        js = JointState(name=["camera_rotator"], position=[0.0])
        js.header.stamp.sec, js.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        self.joints.publish(js)
        replace = replace or {}
        for (c, s), img in images.items():
            msg = replace.get((c, s)) or image_msg(img, stamp, encoding=ENCODINGS[c],
                                                   frame_id="focal_plane")
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            self.pubs[(c, s)].publish(msg)

    @staticmethod
    def of(msgs, stamp):
        return [m for m in list(msgs) if stamp_to_ns(m.header.stamp) == stamp]


from conftest import wait_for  # noqa: E402


@pytest.fixture
def system(ros_domain):
    """bringup (wavefront_node + ofc_node) in a thread on its own context, plus a tester."""
    ctx = rclpy.Context()
    started = {}
    ready = threading.Event()

    def on_ready(nodes, executor):
        started["nodes"] = {n.get_name(): n for n in nodes}
        started["executor"] = executor
        ready.set()

    ros_args = ["-p", "visit_timeout_s:=4.0", "-p", "workers:=2"]
    th = threading.Thread(target=run_nodes, args=(["wavefront_node", "ofc_node"],),
                          kwargs={"context": ctx, "domain_id": ros_domain,
                                  "ros_args": ros_args, "on_ready": on_ready}, daemon=True)
    th.start()
    assert ready.wait(30), "nodes did not start"
    tester = Tester(ctx)
    started["executor"].add_node(tester.node)
    started["tester"] = tester
    try:
        yield started
    finally:
        ctx.try_shutdown()
        th.join(15)


def test_visit_through_both_nodes(visit, system):
    images, truth = visit
    wf, ofc, t = system["nodes"]["wavefront_node"], system["nodes"]["ofc_node"], system["tester"]
    # bringup spins on the executor without rclpy 7.1.6's busy loop (test_executor.py)
    assert isinstance(system["executor"], ProjectExecutor)
    # params.yaml and --ros-args reached the nodes
    assert wf.get_parameter("visit_timeout_s").value == 4.0
    assert ofc.get_parameter("matrix_source").value == "bundled"
    wait_for(lambda: wf.ready, 60, "worker warm-up")
    wait_for(lambda: all(p.get_subscription_count() > 0 for p in t.pubs.values())
             and t.node.count_publishers("aos/ofc/dof_correction") > 0, 10, "discovery")

    # ---- a good visit
    t0 = time.monotonic()
    t.publish_visit(images, S1)
    wait_for(lambda: t.of(t.dof, S1), 30, "DofCorrection of visit 1")
    latency = time.monotonic() - t0
    corners = {m.corner: m for m in t.of(t.corner, S1)}
    assert sorted(corners) == sorted(CORNERS)
    errors = {}
    for c, m in corners.items():
        assert m.valid and m.status == "ok", (c, m.status)
        assert list(m.noll) == list(range(4, 23)) and len(m.zernikes_nm) == 19
        assert m.header.frame_id == "focal_plane" and m.n_pairs == 1
        assert m.solver == CONFIGURED_SOLVER
        assert m.compute_ms > 0 and m.iterations >= 1
        np.testing.assert_allclose(m.field_deg, system_mid(c), atol=1e-9)
        errors[c] = float(np.sqrt(np.mean((np.asarray(m.zernikes_nm) - truth[c]) ** 2)))
    print("\nper-corner rms |estimate - truth| (nm): "
          + ", ".join(f"{c} {e:.1f}" for c, e in errors.items())
          + "; truth rms: " + ", ".join(f"{c} {np.sqrt(np.mean(truth[c] ** 2)):.1f}"
                                          for c in CORNERS)
          + f"; last image -> DofCorrection {latency * 1e3:.0f} ms")
    assert max(errors.values()) < CORNER_RMS_BOUND_NM, errors
    assert float(np.median(list(errors.values()))) < MEDIAN_RMS_BOUND_NM, errors

    (vec,) = t.of(t.vector, S1)
    assert list(vec.corners) == list(CORNERS) and list(vec.corner_valid) == [True] * 4
    assert vec.status == "ok" and vec.header.frame_id == "focal_plane"
    np.testing.assert_array_equal(
        vec.zernikes_nm, np.concatenate([corners[c].zernikes_nm for c in CORNERS]))

    (dc,) = t.of(t.dof, S1)
    assert dc.valid and dc.status == "ok" and not dc.dry_run, dc.status
    assert np.all(np.isfinite(dc.dof)) and np.any(dc.dof != 0)
    np.testing.assert_allclose(dc.dof_total, dc.dof)  # first visit: state = this correction
    assert dc.wavefront_rms_nm > 0 and dc.predicted_residual_rms_nm < dc.wavefront_rms_nm
    assert dc.header.frame_id == "telescope" and dc.rotator_angle_deg == 0.0
    # the Kalman controller: what it kept and dropped, each DoF's uncertainty, the field
    assert dc.n_dropped > 0 and dc.n_modes_used + dc.n_dropped == 50 and "snr" in dc.dropped
    assert np.all(np.asarray(dc.dof_uncertainty)[:10] > 0)
    assert 0 <= dc.predicted_field_rms_nm < dc.field_rms_nm

    # ---- the telescope exposed again with a bad image on R40: no valid correction for that
    # visit. A new exposure has its own photon noise (the same pixels again would be one
    # measurement sent twice: ofc_node refuses that silently, as repeated_measurement).
    rng = np.random.default_rng(2)
    images = {k: v + rng.poisson(0.5, v.shape) for k, v in images.items()}
    bad = image_msg(images[("R40", "intra")], S2, encoding="32FC1")
    bad.data = bytes(bad.data)[:-100]  # truncated
    t.publish_visit(images, S2, replace={("R40", "intra"): bad})
    wait_for(lambda: t.of(t.dof, S2), 30, "DofCorrection of visit 2")
    c2 = {m.corner: m for m in t.of(t.corner, S2)}
    assert not c2["R40"].valid and c2["R40"].status.startswith("truncated_data"), c2["R40"].status
    assert "intra image" in c2["R40"].status
    assert np.all(np.isnan(c2["R40"].zernikes_nm))
    assert all(c2[c].valid for c in ("R00", "R04", "R44"))
    (vec2,) = t.of(t.vector, S2)
    assert list(vec2.corner_valid) == [True, True, False, True]
    assert "R40" in vec2.status and np.all(np.isnan(vec2.zernikes_nm[38:57]))
    dcs = t.of(t.dof, S2)
    assert len(dcs) == 1 and not dcs[0].valid
    assert dcs[0].status.startswith("corner_invalid") and "R40" in dcs[0].status
    assert np.all(np.asarray(dcs[0].dof) == 0)
    np.testing.assert_allclose(dcs[0].dof_total, dc.dof_total)  # state untouched

    # ---- diagnostics name what was rejected
    def wf_diag():
        for arr in reversed(list(t.diag)):
            for st in arr.status:
                kv = {v.key: v.value for v in st.values}
                if st.name.startswith("wavefront_node") and kv.get("rejected.truncated_data"):
                    return st, kv
        return None

    wait_for(lambda: (d := wf_diag()) and d[1]["visits_published"] == "2", 5,
             "diagnostics reporting the truncated image and both visits")
    st, kv = wf_diag()
    assert kv["state"] == "ready" and st.level == b"\x01"  # WARN: recent rejection
    assert "truncated_data" in kv["last_rejection"] and kv["visits_published"] == "2"
    wait_for(lambda: any(s.name.startswith("ofc_node") and
                         {v.key: v.value for v in s.values}.get("corrections_refused") == "1"
                         for arr in list(t.diag) for s in arr.status), 5,
             "ofc_node diagnostics counting the refusal")


def system_mid(c):
    from cwfs_ros.runtime.visits import load_corner_fields

    f = load_corner_fields()[c]
    return [(f["intra"][0] + f["extra"][0]) / 2, (f["intra"][1] + f["extra"][1]) / 2]


def test_node_output_equals_a_direct_core_call(visit):
    """The node is a thin wrapper: same numbers as estimate_wavefront on the same stamps."""
    from cwfs_ros.runtime.corner_pool import CornerJob, run_corner_job
    from cwfs_ros.runtime.visits import load_corner_fields
    from cwfs_ros.wfs.estimator import estimate_wavefront
    from cwfs_ros.wfs.settings import EstimatorSettings

    images, _ = visit
    f = load_corner_fields()["R44"]
    job = CornerJob("R44", S1, images[("R44", "intra")], images[("R44", "extra")],
                    f["intra"], f["extra"], EstimatorSettings())
    out = run_corner_job(job)
    # The same solver on both sides, named: the comparison holds whatever the defaults.
    ref = estimate_wavefront(images[("R44", "intra")], images[("R44", "extra")],
                             field_intra_deg=f["intra"], field_extra_deg=f["extra"],
                             solver=EstimatorSettings().solver)
    assert out.valid
    np.testing.assert_array_equal(out.zernikes_nm, ref.zernikes_nm)
