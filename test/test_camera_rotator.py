"""camera_sim_node's camera rotator: joint_states, the rotated truth and the field figures."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from conftest import wait_for

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")
sim = pytest.importorskip("cwfs_ros.sim")

from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402
from test_camera_sim import make_system  # noqa: E402
from test_rotation import _camera_frame_zernikes_nm  # noqa: E402

from cwfs_ros.layout import CORNERS  # noqa: E402
from cwfs_ros.ofc.field import field_rms_nm, gq_field_points_deg, gq_weights  # noqa: E402
from cwfs_ros.ofc.rotation import dof_rotation_matrix, telescope_field_deg  # noqa: E402
from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.sim.field_truth import fwhm_arcsec  # noqa: E402
from cwfs_ros.sim.perturbation import wavefront_error_nm  # noqa: E402


def test_rotator_joint_state_and_rotated_truth(ros_domain):
    node, t, close = make_system(ros_domain, perturbation_seed=3, rotator_angle_deg=35.0,
                                 offset_px_max=0.0)
    order: list[tuple[str, int]] = []
    lock = threading.Lock()
    joints: list[JointState] = []

    def on_joint(msg: JointState) -> None:
        with lock:
            joints.append(msg)
            order.append(("joint", stamp_to_ns(msg.header.stamp)))

    def on_image(msg) -> None:
        with lock:
            order.append(("image", stamp_to_ns(msg.header.stamp)))

    t.node.create_subscription(JointState, "joint_states", on_joint, OUTPUT_QOS)
    t.node.create_subscription(Image, "aos/wfs/R00/intra/image", on_image, IMAGE_QOS)
    try:
        wait_for(lambda: node.pub_joint.get_subscription_count() > 0, 10, "discovery")
        assert t.call_trigger().success
        wait_for(lambda: t.truth and all(t.images.values()), 90, "visit 1")
        # a new angle for the next visit; out of range is refused
        bad = node.set_parameters([Parameter("rotator_angle_deg", value=300.0)])[0]
        assert not bad.successful and "rotator_angle_deg" in bad.reason
        assert node.set_parameters([Parameter("rotator_angle_deg", value=-120.0)])[0].successful
        # the node finishes its visit bookkeeping after publishing; until then a trigger is
        # skipped, so retry it
        wait_for(lambda: t.call_trigger().success, 30, "trigger of visit 2")
        wait_for(lambda: len(t.truth) == 2, 90, "visit 2")
    finally:
        close()

    assert [j.name for j in joints] == [["camera_rotator"]] * 2
    np.testing.assert_allclose([j.position[0] for j in joints], np.deg2rad([35.0, -120.0]))
    for truth, joint in zip(t.truth, joints, strict=True):
        assert stamp_to_ns(joint.header.stamp) == stamp_to_ns(truth.header.stamp)
    with lock:
        for stamp in {s for _, s in order}:  # each visit's angle came before its images
            kinds = [k for k, s in order if s == stamp]
            assert kinds[0] == "joint", order
    assert [tr.rotator_angle_deg for tr in t.truth] == [35.0, -120.0]

    geo = sim.load_corner_geometry()
    # the donuts were traced at the telescope field the rotated sensor sees, R(35 deg) f,
    # and imaged in the rotated camera's frame: the noise-free render of that field matches
    # the published stamp better than the one of the unrotated field f
    first = t.truth[0]
    tel = sim.perturbed_telescope(np.asarray(first.dof_state), "r", rotator_angle_deg=35.0)
    for c in ("R00", "R44"):
        img = np.frombuffer(bytes(t.images[(c, "intra")][0].data), dtype="<f4").reshape(160, 160)
        f = geo[c].intra_field_deg
        corr = {}
        for name, field in (("rotated", tuple(telescope_field_deg(f, np.deg2rad(35.0))[0])),
                            ("unrotated", f)):
            model = sim.render_donut(tel, field, -1.5, wavelength_nm=622.0, npix=160,
                                     n_photons=2.0**19, poisson=False, sampling="quasi",
                                     rng=np.random.default_rng(0))
            corr[name] = np.corrcoef(img.ravel(), model.ravel())[0, 1]
        assert corr["rotated"] > corr["unrotated"] + 0.01, (c, corr)
    for truth in t.truth:
        a = truth.rotator_angle_deg
        dof = np.asarray(truth.dof_state)
        tel = sim.perturbed_telescope(dof, "r", rotator_angle_deg=a)
        design = sim.perturbed_telescope(np.zeros(50), "r", rotator_angle_deg=a)
        want, want_intr = (np.concatenate([
            _camera_frame_zernikes_nm(o, telescope_field_deg(geo[c].mid_field_deg,
                                                             np.deg2rad(a))[0], a)
            for c in CORNERS]) for o in (tel, design))
        np.testing.assert_allclose(truth.zernikes_nm, want, atol=1e-3)
        np.testing.assert_allclose(truth.intrinsic_nm, want_intr, atol=1e-3)
        assert truth.corner_wavefront_rms_nm == pytest.approx(
            wavefront_error_nm(want, want_intr), abs=1e-3)
        # the field figure of the rotated telescope is that of the unrotated one with the
        # camera tilt turned into the telescope frame (128-pixel pupil grid here)
        equiv = sim.perturbed_telescope(dof_rotation_matrix(np.deg2rad(a)) @ dof, "r")
        nominal = sim.perturbed_telescope(np.zeros(50), "r")
        z = np.array([sim.true_zernikes_nm(equiv, tuple(p), wavelength_nm=622.0)
                      - sim.true_zernikes_nm(nominal, tuple(p), wavelength_nm=622.0)
                      for p in gq_field_points_deg()])
        assert truth.field_wavefront_rms_nm == pytest.approx(field_rms_nm(z), rel=0.01)
        assert truth.fwhm_arcsec == pytest.approx(fwhm_arcsec(z, gq_weights()), rel=0.02)
        assert truth.field_wavefront_rms_nm > 50.0
