"""The camera-rotator conventions of cwfs_ros.ofc.rotation, checked against batoid and galsim.

The truth never comes from the module under test: the rotated, perturbed telescope is built
here with batoid calls that follow batoid_rubin's ``LSSTBuilder`` (``_apply_rtp`` before
``_apply_rigid_body_perturbations``), the field a rotated corner sensor sees is found by
tracing chief rays, and the camera-frame Zernikes are fitted here to batoid's wavefront in the
rotated camera's pupil coordinates.
"""

from __future__ import annotations

import batoid
import galsim
import numpy as np
import pytest

from cwfs_ros.ofc.rotation import (
    dof_rotation_matrix,
    noll_to_nm,
    telescope_field_deg,
    zernike_rotation_matrix,
)
from cwfs_ros.sim import bending_zernikes, load_corner_geometry, load_lsst

WL_M = 622e-9
NX = 128
JMAX = 22
ANGLES_DEG = (0.0, 35.0, 90.0, -120.0)
CAM = "LSSTCamera"

# Rigid decentres and tilts of both hexapods (camera tilt included) and two bending modes.
STATE = np.zeros(50)
STATE[:10] = [15.0, 300.0, -200.0, 0.004, -0.003, -20.0, 500.0, 400.0, 0.006, -0.008]
STATE[12] = 0.2  # M1M3 mode 3
STATE[34] = 0.1  # M2 mode 5


def _rigid(optic: batoid.Optic, name: str, b: np.ndarray) -> batoid.Optic:
    """batoid_rubin's rigid-body step (rx, ry in degrees here, arcsec there)."""
    dz, dx, dy, rx, ry = b
    optic = optic.withGloballyShiftedOptic(name, np.array([-dx, dy, -dz]) * 1e-6)
    return optic.withLocallyRotatedOptic(
        name, batoid.RotX(np.deg2rad(-rx)) @ batoid.RotY(np.deg2rad(ry)))


def _build(dof: np.ndarray, angle_deg: float) -> batoid.Optic:
    """The rotated, perturbed telescope, built with batoid as batoid_rubin builds it."""
    optic = load_lsst("r")
    if angle_deg:
        optic = optic.withLocallyRotatedOptic(CAM, batoid.RotZ(np.deg2rad(angle_deg)))
    optic = _rigid(optic, "M2", dof[0:5])
    optic = _rigid(optic, CAM, dof[5:10])
    for surface, (coef, r_outer) in bending_zernikes(dof).items():
        if np.any(coef):
            optic = optic.withSurface(surface, batoid.Sum(
                [optic[surface].surface, batoid.Zernike(coef, R_outer=r_outer)]))
    return optic


def _chief_local(optic: batoid.Optic, field_deg) -> np.ndarray:
    th = np.deg2rad(np.asarray(field_deg, dtype=float))
    rv = batoid.RayVector.fromStop(np.zeros(1), np.zeros(1), optic, wavelength=WL_M,
                                   theta_x=th[0], theta_y=th[1])
    out = optic.trace(rv)  # detector-local coordinates
    return np.array([out.x[0], out.y[0]])


def _field_seen(optic: batoid.Optic, target_m: np.ndarray, start_deg) -> np.ndarray:
    """Field (deg) whose chief ray lands at detector-local ``target_m`` (Newton)."""
    th = np.asarray(start_deg, dtype=float)
    h = 1e-4
    for _ in range(8):
        p0 = _chief_local(optic, th)
        jac = np.stack([(_chief_local(optic, th + [h, 0]) - p0) / h,
                        (_chief_local(optic, th + [0, h]) - p0) / h], axis=1)
        step = np.linalg.solve(jac, target_m - p0)
        th = th + step
        if np.abs(step).max() < 1e-10:
            break
    return th


def _camera_frame_zernikes_nm(optic: batoid.Optic, field_deg, angle_deg: float) -> np.ndarray:
    """Z4..Z22 [nm] of batoid's wavefront, fitted in the rotated camera's pupil axes.

    The entrance-pupil point (x, y) of the telescope frame is (x, y) R(angle) in camera
    axes: the rotated detector sees the pupil turned by -angle.
    """
    thx, thy = np.deg2rad(field_deg)
    wf = batoid.wavefront(optic, thx, thy, WL_M, nx=NX)
    rays = batoid.RayVector.asGrid(optic=optic, wavelength=WL_M, nx=NX,
                                   dirCos=batoid.utils.fieldToDirCos(thx, thy))
    ep = rays.toCoordSys(optic.stopSurface.coordSys)
    optic.stopSurface.surface.intersect(ep)
    x, y = np.asarray(ep.x).reshape(NX, NX), np.asarray(ep.y).reshape(NX, NX)
    a = np.deg2rad(angle_deg)
    xc, yc = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y
    w = ~wf.array.mask
    r = optic.pupilSize / 2
    basis = galsim.zernike.zernikeBasis(JMAX, xc[w], yc[w], R_outer=r, R_inner=0.61 * r)
    coef, *_ = np.linalg.lstsq(basis.T, wf.array[w], rcond=None)
    return coef[4:] * WL_M * 1e9


def _zernikes_nm(optic: batoid.Optic, field_deg) -> np.ndarray:
    thx, thy = np.deg2rad(field_deg)
    return batoid.zernike(optic, thx, thy, WL_M, nx=NX, jmax=JMAX, eps=0.61)[4:] * WL_M * 1e9


def test_noll_orders_match_galsim():
    for j in range(1, 67):
        assert noll_to_nm(j) == galsim.zernike.noll_to_zern(j), j


@pytest.mark.parametrize("angle_deg", ANGLES_DEG)
def test_zernike_rotation_matches_galsim_on_rotated_pupil(angle_deg):
    """Rz maps camera-frame coefficients to the telescope frame: W_cam(u) = W_tel(R u)."""
    rng = np.random.default_rng(3)
    z_tel = np.zeros(JMAX + 1)
    z_tel[4:] = rng.normal(0, 100, JMAX - 3)
    a = np.deg2rad(angle_deg)
    u = rng.uniform(-1, 1, (2, 4000))
    u = u[:, np.hypot(*u) < 1]
    ux, uy = np.cos(a) * u[0] - np.sin(a) * u[1], np.sin(a) * u[0] + np.cos(a) * u[1]
    w_cam = galsim.zernike.Zernike(z_tel, R_inner=0.61)(ux, uy)
    keep = np.hypot(*u) > 0.61
    basis = galsim.zernike.zernikeBasis(JMAX, u[0][keep], u[1][keep], R_inner=0.61)
    z_cam = np.linalg.lstsq(basis.T, w_cam[keep], rcond=None)[0][4:]
    np.testing.assert_allclose(zernike_rotation_matrix(a) @ z_cam, z_tel[4:], atol=1e-9)
    np.testing.assert_allclose(zernike_rotation_matrix(a).T @ z_tel[4:], z_cam, atol=1e-9)


@pytest.mark.parametrize("angle_deg", ANGLES_DEG)
def test_rotated_corner_sees_the_rotated_field(angle_deg):
    """Where field f lands on the unrotated detector, the rotated one sees R(angle) f."""
    nominal = _build(np.zeros(50), 0.0)
    rotated = _build(np.zeros(50), angle_deg)
    for corner in load_corner_geometry().values():
        f = np.asarray(corner.mid_field_deg)
        seen = _field_seen(rotated, _chief_local(nominal, f), f)
        expect = telescope_field_deg(f, np.deg2rad(angle_deg))[0]
        np.testing.assert_allclose(expect, seen, atol=2e-6)  # deg (7 mas)


@pytest.mark.parametrize("angle_deg", ANGLES_DEG)
def test_camera_tilt_turns_with_the_camera(angle_deg):
    """Rotated camera + x is the camera of (unrotated + M x), turned about its own axis."""
    a = np.deg2rad(angle_deg)
    rotated = _build(STATE, angle_deg)
    equivalent = _build(dof_rotation_matrix(a) @ STATE, 0.0)
    for item in (CAM, "L1", "L3", "Detector"):
        cs_r, cs_e = rotated[item].coordSys, equivalent[item].coordSys
        np.testing.assert_allclose(cs_r.origin, cs_e.origin, atol=1e-12)
        # second order in the ~1e-4 rad tilt: the two parameterisations differ by ~1e-8
        np.testing.assert_allclose(cs_r.rot, cs_e.rot @ batoid.RotZ(a), atol=1e-7)
    # M2 and the mirrors do not move with the camera
    np.testing.assert_allclose(rotated["M2"].coordSys.rot, equivalent["M2"].coordSys.rot)


@pytest.mark.parametrize("angle_deg", ANGLES_DEG)
def test_camera_frame_zernikes_follow_the_composition(angle_deg):
    """z_cam(rotated telescope, x, corner f) = Rz.T @ z(unrotated, M x, R(angle) f)."""
    a = np.deg2rad(angle_deg)
    nominal = _build(np.zeros(50), 0.0)
    rotated_design = _build(np.zeros(50), angle_deg)
    rotated = _build(STATE, angle_deg)
    equivalent = _build(dof_rotation_matrix(a) @ STATE, 0.0)
    unturned_tilt = _build(STATE, 0.0)  # M = identity: the camera tilt left in camera axes
    rz = zernike_rotation_matrix(a)
    worst, naive = 0.0, 0.0
    for corner in load_corner_geometry().values():
        f = np.asarray(corner.mid_field_deg)
        # the sensor's field is fixed by the design (astrometry), not by the perturbed
        # telescope, whose decentres move the images
        g = _field_seen(rotated_design, _chief_local(nominal, f), f)
        truth = _camera_frame_zernikes_nm(rotated, g, angle_deg)
        g_model = telescope_field_deg(f, a)[0]
        model = rz.T @ _zernikes_nm(equivalent, g_model)
        worst = max(worst, np.abs(model - truth).max() / max(1.0, 0.01 * np.linalg.norm(truth)))
        naive = max(naive, np.abs(rz.T @ _zernikes_nm(unturned_tilt, g_model) - truth).max())
        # the measured corners really are perturbed: hundreds of nm, not the design
        assert np.linalg.norm(truth - _camera_frame_zernikes_nm(
            rotated_design, g, angle_deg)) > 200.0
    assert worst < 1.0, f"worst |model - truth| = {worst:.2f} x max(1 nm, 1 % of |truth|)"
    if abs(np.sin(a)) > 0.5:  # the camera-tilt rotation matters: without it, tens of nm off
        assert naive > 20.0, naive
