"""The simulator's field truth (cwfs_ros.sim.field_truth) against batoid measured directly."""

from __future__ import annotations

import batoid
import numpy as np
import pytest

from cwfs_ros.ofc.field import gq_field_points_deg, gq_weights
from cwfs_ros.sim import perturbed_telescope, plate_scale_um_per_arcsec, true_zernikes_nm
from cwfs_ros.sim.field_truth import (
    FWHM_PER_SIGMA,
    field_truth,
    fwhm_arcsec,
    fwhm_matrix_arcsec2_per_nm2,
)

WL = 622.0


def _dof(**kv: float) -> np.ndarray:
    d = np.zeros(50)
    for k, v in kv.items():
        d[int(k[1:])] = v
    return d


@pytest.mark.parametrize(("dof", "field_deg"), [
    (_dof(d1=300.0), (0.0, 0.0)),                      # M2 decentre: coma
    (_dof(d1=300.0, d8=0.01), (0.8, -0.5)),            # + camera tilt
    (_dof(d12=0.3, d34=0.2), (1.0, 1.0)),              # bending modes
    (_dof(d5=20.0), (0.3, 0.2)),                       # camera piston: defocus
])
def test_fwhm_matches_the_second_moment_of_batoid_spots(dof, field_deg):
    """The Zernike quadratic form gives the spot's rms size that batoid's rays show."""
    tel = perturbed_telescope(dof)
    th = np.deg2rad(field_deg)
    rays = tel.trace(batoid.RayVector.asPolar(optic=tel, wavelength=WL * 1e-9, theta_x=th[0],
                                              theta_y=th[1], nrad=60, naz=180))
    ok = ~(rays.vignetted | rays.failed)
    scale_m = plate_scale_um_per_arcsec(tel, field_deg) * 1e-6
    sigma_spot = np.sqrt((rays.x[ok].var() + rays.y[ok].var()) / 2.0) / scale_m
    z = true_zernikes_nm(tel, field_deg, wavelength_nm=WL, nx=255)  # total, design included
    sigma_zk = np.sqrt(z @ fwhm_matrix_arcsec2_per_nm2() @ z)
    assert sigma_zk == pytest.approx(sigma_spot, rel=0.05)
    assert fwhm_arcsec(z) == pytest.approx(FWHM_PER_SIGMA * sigma_zk)


def test_field_truth_is_batoids_departure_from_the_design_at_the_gq_points():
    dof = _dof(d1=250.0, d3=0.004, d6=-400.0, d9=0.006, d12=0.2, d34=0.1)
    ft = field_truth(perturbed_telescope(dof), "r", wavelength_nm=WL)
    pts = gq_field_points_deg()
    nominal = perturbed_telescope(None)
    z = np.array([true_zernikes_nm(perturbed_telescope(dof), tuple(p), wavelength_nm=WL)
                  - true_zernikes_nm(nominal, tuple(p), wavelength_nm=WL) for p in pts])
    np.testing.assert_allclose(ft.field_zernikes_nm, z, atol=1.5)  # a 64 vs a 128 grid
    w = gq_weights()
    expect = np.sqrt(np.sum(w * np.sum(z * z, axis=1)))
    assert ft.field_wavefront_rms_nm == pytest.approx(expect, rel=0.005)
    assert ft.field_wavefront_rms_nm > 300.0
    assert 0.05 < ft.fwhm_arcsec < 2.0


def test_field_truth_of_the_design_is_zero_at_any_rotator_angle():
    """The camera optics are axisymmetric: a rotated nominal camera adds no aberration."""
    for angle in (0.0, 35.0, -120.0):
        ft = field_truth(perturbed_telescope(None, rotator_angle_deg=angle), "r",
                         wavelength_nm=WL)
        assert ft.field_wavefront_rms_nm < 0.05
        assert ft.fwhm_arcsec < 1e-4
