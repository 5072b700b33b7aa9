"""The simulator's rotated camera: telescope, donuts, frames and the estimator's frame (no ROS).

Truth comes from batoid directly (the telescope built as batoid_rubin builds it, in
test_rotation.py) and from the estimator, which is unchanged: it estimates in the camera
frame from camera-frame images at camera-frame fields.
"""

from __future__ import annotations

import batoid
import numpy as np
import pytest
from test_rotation import STATE, _build, _camera_frame_zernikes_nm

from cwfs_ros.ofc.rotation import telescope_field_deg
from cwfs_ros.sim import (
    camera_zernikes_nm,
    load_corner_geometry,
    perturbed_telescope,
    render_donut,
    true_zernikes_nm,
)
from cwfs_ros.sim.frames import StarSpec, render_frame
from cwfs_ros.wfs.estimator import estimate_wavefront

WL = 622.0


@pytest.mark.parametrize("angle_deg", [35.0, -120.0])
def test_perturbed_telescope_rotates_the_camera_as_batoid_rubin(angle_deg):
    ours = perturbed_telescope(STATE, "r", rotator_angle_deg=angle_deg)
    ref = _build(STATE, angle_deg)
    for name in ("M1", "M2", "M3", "LSSTCamera", "L1", "L2", "Filter", "L3", "Detector"):
        np.testing.assert_allclose(ours[name].coordSys.origin, ref[name].coordSys.origin,
                                   atol=1e-15)
        np.testing.assert_allclose(ours[name].coordSys.rot, ref[name].coordSys.rot, atol=1e-15)
    assert perturbed_telescope(STATE, "r", rotator_angle_deg=angle_deg) is ours  # cached
    assert perturbed_telescope(STATE, "r") is not ours
    with pytest.raises(ValueError):
        perturbed_telescope(STATE, "r", rotator_angle_deg=float("nan"))


@pytest.mark.parametrize("angle_deg", [35.0, 90.0])
def test_camera_zernikes_are_the_fit_in_the_rotated_pupil(angle_deg):
    tel = perturbed_telescope(STATE, "r", rotator_angle_deg=angle_deg)
    for c in load_corner_geometry().values():
        g = telescope_field_deg(c.mid_field_deg, np.deg2rad(angle_deg))[0]
        np.testing.assert_allclose(
            camera_zernikes_nm(tel, c.mid_field_deg, angle_deg, wavelength_nm=WL),
            _camera_frame_zernikes_nm(tel, g, angle_deg), atol=1e-3)


def test_rotated_donut_is_the_turned_donut_of_the_equivalent_telescope():
    """At 90 deg the rotated camera's stamp is the unrotated (M x) telescope's stamp turned
    by -90 deg: camera x = telescope y, camera y = -telescope x."""
    from cwfs_ros.ofc.rotation import dof_rotation_matrix

    f = load_corner_geometry()["R04"].extra_field_deg
    g = tuple(telescope_field_deg(f, np.pi / 2)[0])
    kw = dict(wavelength_nm=WL, npix=160, n_photons=2.0**19, poisson=False, sampling="quasi")
    rotated = render_donut(perturbed_telescope(STATE, "r", rotator_angle_deg=90.0), g, 1.5,
                           rng=np.random.default_rng(1), **kw)
    equivalent = render_donut(perturbed_telescope(dof_rotation_matrix(np.pi / 2) @ STATE, "r"),
                              g, 1.5, rng=np.random.default_rng(1), **kw)
    # image[row=y, col=x]: rotated[r, c] = equivalent at (x = -r, y = c)
    turned = equivalent.T[::-1, :]  # turned[r, c] = equivalent[c, 159 - r]
    corr = np.corrcoef(rotated.ravel(), turned.ravel())[0, 1]
    unturned = np.corrcoef(rotated.ravel(), equivalent.ravel())[0, 1]
    print(f"\nrotated vs turned equivalent stamp: correlation {corr:.4f} (unturned {unturned:.4f})")
    assert corr > 0.98 and unturned < corr - 0.1, (corr, unturned)


def test_estimator_reads_a_rotated_corner_in_the_camera_frame():
    """wavefront_node's estimator, given the rotated camera's images and the sensor's nominal
    (camera-frame) fields, returns the camera-frame Zernikes: it needs no rotator input."""
    angle = 90.0
    corner = load_corner_geometry()["R00"]
    dof = np.zeros(50)
    dof[[1, 2, 8]] = [300.0, -150.0, 0.006]  # M2 decentre, camera tilt: coma, astigmatism
    tel = perturbed_telescope(dof, "r", rotator_angle_deg=angle)
    rng = np.random.default_rng(3)
    intra, extra = (render_donut(tel, tuple(telescope_field_deg(f, np.deg2rad(angle))[0]), dz,
                                 wavelength_nm=WL, npix=160, n_photons=3e6, rng=rng,
                                 poisson=False, offset_px=(1.5, -2.0))
                    for f, dz in ((corner.intra_field_deg, -1.5), (corner.extra_field_deg, 1.5)))
    r = estimate_wavefront(intra, extra, field_intra_deg=corner.intra_field_deg,
                           field_extra_deg=corner.extra_field_deg)
    g = telescope_field_deg(corner.mid_field_deg, np.deg2rad(angle))[0]
    truth_camera = _camera_frame_zernikes_nm(tel, g, angle)
    truth_telescope = true_zernikes_nm(tel, tuple(g), wavelength_nm=WL)
    err_camera = float(np.sqrt(np.mean((r.zernikes_nm - truth_camera) ** 2)))
    err_telescope = float(np.sqrt(np.mean((r.zernikes_nm - truth_telescope) ** 2)))
    print(f"\nrotated R00 at {angle:g} deg: rms error {err_camera:.1f} nm vs the camera-frame "
          f"truth, {err_telescope:.1f} nm vs the telescope-frame Zernikes")
    assert err_camera < 20.0
    assert err_telescope > 3 * err_camera


def test_rotated_frame_places_stars_at_their_telescope_fields():
    """A frame of the rotated camera: each star's chief ray lands on its pixel, and its
    recorded field is the telescope field of that pixel (through the rotated design)."""
    angle = 35.0
    h = load_corner_geometry()["R40"]
    tel = perturbed_telescope(np.zeros(50), "r", rotator_angle_deg=angle)
    stars = [StarSpec(300.0, 400.0, 3e5), StarSpec(700.0, 1500.0, 3e5)]
    frame = render_frame(tel, stars, field_ref_deg=h.extra_field_deg, detector_offset_mm=1.5,
                         shape_px=(2000, 1000), sky_per_pixel=0.0,
                         rng=np.random.default_rng(2), rotator_angle_deg=angle)
    unrotated = render_frame(perturbed_telescope(np.zeros(50), "r"), stars,
                             field_ref_deg=h.extra_field_deg, detector_offset_mm=1.5,
                             shape_px=(2000, 1000), sky_per_pixel=0.0,
                             rng=np.random.default_rng(2))
    for s_rot, s_nom in zip(frame.stars, unrotated.stars, strict=True):
        expect = telescope_field_deg(s_nom.field_deg, np.deg2rad(angle))[0]
        np.testing.assert_allclose(s_rot.field_deg, expect, atol=1e-6)
        # independently: the chief ray of that field lands at the same detector point
        th = np.deg2rad(s_rot.field_deg)
        rv = batoid.RayVector.fromStop(np.zeros(1), np.zeros(1), tel, wavelength=WL * 1e-9,
                                       theta_x=th[0], theta_y=th[1])
        th0 = np.deg2rad(s_nom.field_deg)
        nominal = perturbed_telescope(np.zeros(50), "r")
        rv0 = batoid.RayVector.fromStop(np.zeros(1), np.zeros(1), nominal,
                                        wavelength=WL * 1e-9, theta_x=th0[0], theta_y=th0[1])
        a, b = tel.trace(rv), nominal.trace(rv0)
        np.testing.assert_allclose([a.x[0], a.y[0]], [b.x[0], b.y[0]], atol=1e-8)
    # the nominal telescope is axisymmetric: the rotated frame is the same image
    assert np.corrcoef(frame.image.ravel(), unrotated.image.ravel())[0, 1] > 0.95
