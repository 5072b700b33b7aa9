"""Tests of the photon-tracing LSST simulator (cwfs_ros.sim).

Every expectation here comes from outside the simulator: first-order optics of an f/1.23
beam, photon statistics, or batoid rays traced directly. None comes from the wavefront
estimator.
"""

from __future__ import annotations

import batoid
import numpy as np
import pytest

from cwfs_ros.sim import (
    N_DOF,
    TS_OFC_FLIPPED_DOF,
    RenderSettings,
    bending_zernikes,
    corner_fields,
    defocused,
    load_corner_geometry,
    load_lsst,
    perturbed_telescope,
    plate_scale_um_per_arcsec,
    pupil_vignetting_fraction,
    render_donut,
    trace_pupil_rays,
    true_zernikes_nm,
)

WL = 622.0  # nm, r band
F_M = 10.312  # LSST effective focal length (m), lsst.param
D_M = 8.36  # LSST aperture (m)
EPS = 0.612  # M1 inner/outer radius ratio (2.558 / 4.18)
PIX_UM = 10.0


@pytest.fixture(scope="module")
def nominal() -> batoid.Optic:
    return load_lsst("r")


@pytest.fixture(scope="module")
def z_nominal_centre(nominal) -> np.ndarray:
    return true_zernikes_nm(nominal, (0.0, 0.0), wavelength_nm=WL)


def _dof(**kv: float) -> np.ndarray:
    names = {
        "m2_dz": 0,
        "m2_dx": 1,
        "m2_dy": 2,
        "m2_rx": 3,
        "m2_ry": 4,
        "cam_dz": 5,
        "cam_dx": 6,
        "cam_dy": 7,
        "cam_rx": 8,
        "cam_ry": 9,
    }
    d = np.zeros(N_DOF)
    for k, v in kv.items():
        d[names[k] if k in names else int(k.split("_")[1])] = v
    return d


def _radial_edges_px(img: np.ndarray) -> tuple[float, float]:
    """Inner and outer radius (px) where the azimuthal mean crosses half the plateau level."""
    n = img.shape[0]
    c = (n - 1) / 2.0  # the chief ray lands on the shared corner of the 4 central pixels
    yy, xx = np.indices(img.shape)
    r = np.hypot(xx - c, yy - c).ravel()
    edges = np.arange(0.0, n / 2.0, 0.5)
    k = np.digitize(r, edges)
    s = np.bincount(k, weights=img.ravel(), minlength=edges.size + 1)[1 : edges.size + 1]
    cnt = np.bincount(k, minlength=edges.size + 1)[1 : edges.size + 1]
    prof = s / np.maximum(cnt, 1)
    rc = edges + 0.25
    plateau = np.median(prof[prof > 0.2 * prof.max()])
    above = np.flatnonzero(prof > 0.5 * plateau)
    return float(rc[above[0]]), float(rc[above[-1]])


def _rebin(img: np.ndarray, f: int = 4) -> np.ndarray:
    n = img.shape[0] // f
    return img[: n * f, : n * f].reshape(n, f, n, f).sum(axis=(1, 3))


def _rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    a, b = _rebin(a), _rebin(b)
    return float(np.linalg.norm(a - b) / np.linalg.norm(a))


# ------------------------------------------------------------------------------------------
# Conventions
# ------------------------------------------------------------------------------------------


def test_defocus_sign_is_intra_negative(nominal):
    """Negative detector offset puts the detector between L3 and focus (intra-focal)."""
    z_l3 = nominal["L3_exit"].coordSys.origin[2]
    z_det = nominal["Detector"].coordSys.origin[2]
    z_intra = defocused(nominal, -1.5)["Detector"].coordSys.origin[2]
    z_extra = defocused(nominal, +1.5)["Detector"].coordSys.origin[2]
    assert z_l3 < z_intra < z_det < z_extra
    assert z_intra == pytest.approx(z_det - 1.5e-3, abs=1e-12)

    # The light reaches the detector travelling along +z: the lower-z detector is met first.
    rv = batoid.RayVector.fromStop(
        3.5, 0.0, nominal, wavelength=WL * 1e-9, theta_x=0.0, theta_y=0.0
    )
    assert nominal.trace(rv).vz[0] > 0.9

    # The beam passes through focus between the two planes: the image of a pupil point is on
    # opposite sides of the chief ray, and the spot is smallest at zero offset.
    rng = np.random.default_rng(3)
    sizes, corr = {}, {}
    for off in (-1.5, -0.5, 0.0, 0.5, 1.5):
        r = trace_pupil_rays(nominal, (0.0, 0.0), off, wavelength_nm=WL, n_rays=4000, rng=rng)
        dx = (r.x - r.chief_x)[r.ok]
        sizes[off] = float(np.sqrt(np.mean(dx**2 + ((r.y - r.chief_y)[r.ok]) ** 2)))
        corr[off] = float(np.corrcoef(r.pupil_x[r.ok], dx)[0, 1])
    assert min(sizes, key=sizes.get) == 0.0
    assert corr[-1.5] > 0.99 and corr[1.5] < -0.99


def test_dof_validation_and_cache(nominal):
    assert perturbed_telescope(np.zeros(N_DOF)) is perturbed_telescope(None)
    d = _dof(m2_dx=100.0)
    assert perturbed_telescope(d) is perturbed_telescope(d.copy())
    with pytest.raises(ValueError):
        perturbed_telescope(np.zeros(49))
    with pytest.raises(ValueError):
        perturbed_telescope(np.full(N_DOF, np.nan))
    # Rigid-body mapping of batoid_rubin (OCS -> batoid: x -> -x, z -> -z), in µm.
    t = perturbed_telescope(_dof(m2_dz=10.0, m2_dx=20.0, m2_dy=30.0))
    shift = t["M2"].coordSys.origin - nominal["M2"].coordSys.origin
    np.testing.assert_allclose(shift, [-20e-6, 30e-6, -10e-6], atol=1e-12)
    # Rotations are in degrees: M2 ry = 0.01 deg tilts M2's axis by 0.01 deg.
    t = perturbed_telescope(_dof(m2_ry=0.01))
    zaxis = t["M2"].coordSys.rot[:, 2]
    assert np.degrees(np.arccos(zaxis[2])) == pytest.approx(0.01, rel=1e-6)


def test_ts_ofc_convention_flips_dz_dx_rx(nominal):
    d = np.arange(1.0, N_DOF + 1.0) * 1e-3
    flipped = d.copy()
    flipped[list(TS_OFC_FLIPPED_DOF)] *= -1
    assert perturbed_telescope(d, convention="ts_ofc") is perturbed_telescope(flipped)
    assert TS_OFC_FLIPPED_DOF == (0, 1, 3, 5, 6, 8)
    # ts_ofc +dz of the camera moves it along batoid +z (batoid_rubin: -z).
    t = perturbed_telescope(_dof(cam_dz=10.0), convention="ts_ofc")
    dz = t["LSSTCamera"].coordSys.origin[2] - nominal["LSSTCamera"].coordSys.origin[2]
    assert dz == pytest.approx(10e-6, abs=1e-12)
    with pytest.raises(ValueError):
        perturbed_telescope(d, convention="phosim")


def test_plate_scale_from_model(nominal):
    # 10.31 m focal length -> 50.0 µm/arcsec (0.2"/10 µm pixel).
    assert plate_scale_um_per_arcsec(nominal) == pytest.approx(F_M * np.pi / 648000 * 1e6, rel=5e-3)


# ------------------------------------------------------------------------------------------
# (a) donut geometry
# ------------------------------------------------------------------------------------------


def test_nominal_donut_diameter_and_hole(nominal):
    img = render_donut(
        nominal,
        (0.0, 0.0),
        1.5,
        wavelength_nm=WL,
        n_photons=1e6,
        n_rays=300_000,
        poisson=False,
        rng=np.random.default_rng(1),
    )
    r_in, r_out = _radial_edges_px(img)
    # Paraxial D*l/f = 121.6 px ignores that LSST is an f/1.23 beam: the marginal ray's
    # slope is tan(u) with sin(u) = D/(2f) (sine condition), giving 133.0 px. The ZEMAX FAM
    # donuts at 1.5 mm (test data set) are also 134 px across.
    l_um = 1.5e3
    paraxial = D_M * l_um / F_M / PIX_UM
    fast = 2 * l_um * np.tan(np.arcsin(D_M / (2 * F_M))) / PIX_UM
    fast_in = 2 * l_um * np.tan(np.arcsin(EPS * D_M / (2 * F_M))) / PIX_UM
    assert paraxial == pytest.approx(121.6, abs=0.1)
    assert 2 * r_out == pytest.approx(fast, rel=0.02)
    assert 2 * r_in == pytest.approx(fast_in, rel=0.04)
    # Obscuration hole: nothing well inside the inner edge, and the centre pixels are empty.
    yy, xx = np.indices(img.shape)
    rr = np.hypot(xx - 79.5, yy - 79.5)
    assert img[rr < 0.85 * fast_in / 2].sum() == 0.0
    assert img[rr > 1.03 * fast / 2].sum() < 1e-3 * img.sum()


def test_render_settings_are_checked_and_a_call_overrides_them(nominal):
    """One RenderSettings for several donuts, each call replacing what differs: an integer
    offset_px of 5 moves the same rays (same seed, no Poisson draw) by exactly 5 columns."""
    settings = RenderSettings(wavelength_nm=WL, npix=200, n_photons=1e5, poisson=False)
    a = render_donut(nominal, (0.0, 0.0), 1.5, settings, rng=np.random.default_rng(3))
    b = render_donut(nominal, (0.0, 0.0), 1.5, settings, offset_px=(5.0, 0.0),
                     rng=np.random.default_rng(3))
    assert a.shape == (200, 200) and a.sum() > 0.9e5 * 0.9
    np.testing.assert_array_equal(b[:, 5:], a[:, :-5])
    assert settings.offset_px == (0.0, 0.0)  # the shared settings are unchanged
    for bad in (dict(npix=0), dict(n_photons=0.0), dict(centre="middle")):
        with pytest.raises(ValueError):
            RenderSettings(wavelength_nm=WL, **bad)
        with pytest.raises(ValueError):
            render_donut(nominal, (0.0, 0.0), 1.5, settings, **bad)
    with pytest.raises(TypeError):
        render_donut(nominal, (0.0, 0.0), 1.5, settings, n_photon=1e5)  # misspelt
    with pytest.raises(TypeError):
        render_donut(nominal, (0.0, 0.0), 1.5, npix=160)  # no wavelength


# ------------------------------------------------------------------------------------------
# (b) intra vs extra
# ------------------------------------------------------------------------------------------


def test_intra_extra_rotation(nominal):
    """Intra- and extra-focal donuts are 180°-rotated copies of each other when the wavefront
    is near-perfect. The beam passes through focus between them, so a pupil feature such as
    the vignetting cut at a corner field swaps sides."""
    kw = dict(wavelength_nm=WL, n_photons=1e6, n_rays=200_000, poisson=False)
    rng = np.random.default_rng(5)
    intra = render_donut(nominal, (0.0, 0.0), -1.5, rng=rng, **kw)
    intra2 = render_donut(nominal, (0.0, 0.0), -1.5, rng=rng, **kw)
    extra = render_donut(nominal, (0.0, 0.0), +1.5, rng=rng, **kw)
    noise = _rel_diff(intra, intra2)  # ray-sampling noise floor (~0.075)
    # Centre field: the same to within noise plus the small intrinsic (~0.1) profile
    # difference. The r-band design has ~200 nm of Z4/Z11 at 622 nm, which makes the intra
    # hole 1 px larger.
    rot_centre = _rel_diff(intra, np.rot90(extra, 2))
    assert rot_centre < 0.2
    assert not np.allclose(intra, extra)

    # Corner field (same field point for both): the asymmetric vignetted donut flips by 180°.
    fld = corner_fields()["R44"]["extra"]
    ci = render_donut(nominal, fld, -1.5, rng=rng, **kw)
    ce = render_donut(nominal, fld, +1.5, rng=rng, **kw)
    assert _rel_diff(ci, np.rot90(ce, 2)) < 2 * noise
    assert _rel_diff(ci, ce) > 2 * _rel_diff(ci, np.rot90(ce, 2))

    # Odd aberrations (coma from a 1 mm M2 decenter) do NOT flip: the coma pattern keeps its
    # orientation, so rot180(extra) is now the worse match. This is the odd-term sign signal
    # that curvature sensing relies on.
    coma = perturbed_telescope(_dof(m2_dx=1000.0))
    mi = render_donut(coma, (0.0, 0.0), -1.5, rng=rng, **kw)
    me = render_donut(coma, (0.0, 0.0), +1.5, rng=rng, **kw)
    assert _rel_diff(mi, np.rot90(me, 2)) > 2 * _rel_diff(mi, me)
    assert _rel_diff(mi, np.rot90(me, 2)) > 2 * rot_centre


# ------------------------------------------------------------------------------------------
# (c) rigid-body DoF vs true Zernikes
# ------------------------------------------------------------------------------------------


def test_m2_decenter_gives_coma(z_nominal_centre):
    zx = true_zernikes_nm(perturbed_telescope(_dof(m2_dx=500.0)), (0, 0), wavelength_nm=WL)
    zy = true_zernikes_nm(perturbed_telescope(_dof(m2_dy=500.0)), (0, 0), wavelength_nm=WL)
    dx, dy = zx - z_nominal_centre, zy - z_nominal_centre
    z7, z8 = 7 - 4, 8 - 4
    # 0.5 mm decenter: a few hundred nm of coma (batoid: ~320 nm), in the decenter's axis.
    assert 100 < abs(dx[z8]) < 1000 and abs(dx[z7]) < 0.02 * abs(dx[z8])
    assert 100 < abs(dy[z7]) < 1000 and abs(dy[z8]) < 0.02 * abs(dy[z7])
    assert np.argmax(np.abs(dx)) == z8 and np.argmax(np.abs(dy)) == z7
    assert abs(dx[z8]) == pytest.approx(abs(dy[z7]), rel=1e-3)  # axisymmetric telescope


def test_camera_piston_is_defocus(z_nominal_centre):
    dz = true_zernikes_nm(perturbed_telescope(_dof(cam_dz=50.0)), (0, 0), wavelength_nm=WL)
    dz -= z_nominal_centre
    # Longitudinal defocus. The paraxial full-circle estimate is Z4 ~ dz / (16 sqrt(3) N^2)
    # ~ 1.2 µm for dz = 50 µm at N = 1.23; batoid (annular, camera lenses move too) gives
    # ~0.8 µm.
    assert 300 < abs(dz[0]) < 3000
    assert np.all(np.abs(dz[1:]) < 0.05 * abs(dz[0]))


# ------------------------------------------------------------------------------------------
# (d) flux
# ------------------------------------------------------------------------------------------


def test_flux_conserved_within_poisson(nominal):
    rng = np.random.default_rng(7)
    n = 4e5
    img = render_donut(nominal, (0.0, 0.0), -1.5, wavelength_nm=WL, n_photons=n, rng=rng)
    assert abs(img.sum() - n) < 5 * np.sqrt(n)  # on axis nothing is vignetted

    corner = corner_fields()["R40"]["intra"]
    vig = pupil_vignetting_fraction(nominal, corner, -1.5, WL)
    img = render_donut(nominal, corner, -1.5, wavelength_nm=WL, n_photons=n, rng=rng)
    expect = n * (1 - vig)
    sigma = np.sqrt(expect + n * vig * (1 - vig))  # Poisson + ray-sampling binomial
    assert abs(img.sum() - expect) < 5 * sigma

    # Sky and read noise: mean and variance of an empty corner of the stamp.
    img = render_donut(
        nominal,
        (0.0, 0.0),
        1.5,
        wavelength_nm=WL,
        n_photons=1e4,
        sky_per_pixel=100.0,
        read_noise_e=5.0,
        rng=rng,
    )
    patch = img[:12, :12]
    assert patch.mean() == pytest.approx(100.0, abs=3.0)
    assert patch.var() == pytest.approx(125.0, rel=0.35)


# ------------------------------------------------------------------------------------------
# (e) vignetting
# ------------------------------------------------------------------------------------------


def test_vignetting_fraction(nominal):
    assert pupil_vignetting_fraction(nominal, (0.0, 0.0), 1.5, WL) < 1e-3
    geo = load_corner_geometry()
    assert sorted(geo) == ["R00", "R04", "R40", "R44"]
    for s in geo.values():
        assert s.intra_offset_mm == -1.5 and s.extra_offset_mm == 1.5
        for fld, off in ((s.extra_field_deg, 1.5), (s.intra_field_deg, -1.5)):
            assert 0.05 < pupil_vignetting_fraction(nominal, fld, off, WL) < 0.12


# ------------------------------------------------------------------------------------------
# (f) bending modes
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("mode_index", "mirror", "lo", "hi"),
    [
        # M2 faces down; a +sag bump delays the light (travelling +z): W ≈ -2 sag.
        (30, "M2", -2.3, -1.9),
        (33, "M2", -2.3, -1.9),
        # M1 (W ≈ +2 sag) and M3 (same polynomial on a ~0.6x smaller footprint) add up.
        (10, "M1", 2.5, 3.3),
        (13, "M1", 2.5, 3.3),
    ],
)
def test_bending_mode_matches_zernike_data(z_nominal_centre, mode_index, mirror, lo, hi):
    d = np.zeros(N_DOF)
    d[mode_index] = 1.0  # 1 µm of mode
    sag_nm = bending_zernikes(d)[mirror][0][4:23] * 1e9
    dw = true_zernikes_nm(perturbed_telescope(d), (0, 0), wavelength_nm=WL) - z_nominal_centre
    j = int(np.argmax(np.abs(sag_nm)))
    assert int(np.argmax(np.abs(dw))) == j
    assert 500 < abs(sag_nm[j]) < 2000  # the data are ~1 µm of sag per µm of mode
    assert lo < dw[j] / sag_nm[j] < hi


# ------------------------------------------------------------------------------------------
# (g) image frame
# ------------------------------------------------------------------------------------------


def test_image_is_histogram_of_batoid_rays(nominal):
    """Row = detector y, col = detector x, and the chief ray on the shared corner of the 4 central
    pixels."""
    fld = (1.5, 0.0)
    img = render_donut(
        nominal,
        fld,
        1.5,
        wavelength_nm=WL,
        n_photons=5e4,
        poisson=False,
        rng=np.random.default_rng(11),
        offset_px=(3.0, -2.0),
    )
    r = trace_pupil_rays(
        nominal, fld, 1.5, wavelength_nm=WL, n_rays=50_000, rng=np.random.default_rng(11)
    )
    x = (r.x[r.ok] - r.chief_x) / (PIX_UM * 1e-6) + 80 + 3.0
    y = (r.y[r.ok] - r.chief_y) / (PIX_UM * 1e-6) + 80 - 2.0
    ref, _, _ = np.histogram2d(y, x, bins=160, range=[[0, 160], [0, 160]])
    np.testing.assert_allclose(img, ref)


def test_frame_transpose_symmetry(nominal):
    """The telescope is symmetric under x <-> y, so the (0, 1.5) donut is the transpose of the
    (1.5, 0) one, and different from its untransposed self (vignetting breaks the symmetry)."""
    kw = dict(wavelength_nm=WL, n_photons=1e6, n_rays=200_000, poisson=False)
    rng = np.random.default_rng(13)
    a = render_donut(nominal, (1.5, 0.0), 1.5, rng=rng, **kw)
    a2 = render_donut(nominal, (1.5, 0.0), 1.5, rng=rng, **kw)
    b = render_donut(nominal, (0.0, 1.5), 1.5, rng=rng, **kw)
    noise = _rel_diff(a, a2)
    assert _rel_diff(a, b.T) < 1.5 * noise
    assert _rel_diff(a, b) > 2 * noise


def test_camera_shift_moves_image_as_batoid_rays(nominal):
    fld = (1.5, 0.0)
    shifted = perturbed_telescope(_dof(cam_dx=200.0))  # OCS +x = batoid -x for the camera
    # Independent reference: batoid's own rays, mean position on the defocused detector.
    ref = []
    for tel in (nominal, shifted):
        opt = defocused(tel, 1.5)
        rv = batoid.RayVector.asPolar(
            optic=opt,
            wavelength=WL * 1e-9,
            nrad=30,
            naz=90,
            theta_x=np.deg2rad(fld[0]),
            theta_y=np.deg2rad(fld[1]),
        )
        out = opt.trace(rv)
        ok = ~(out.vignetted | out.failed)
        ref.append(np.array([out.x[ok].mean(), out.y[ok].mean()]))
    expect_px = (ref[1] - ref[0]) / (PIX_UM * 1e-6)
    # The detector moved 200 µm to batoid -x, so the star moves ~+20 px in detector x.
    assert 15 < expect_px[0] < 25 and abs(expect_px[1]) < 0.1

    chief0 = trace_pupil_rays(nominal, fld, 1.5, wavelength_nm=WL, n_rays=1).chief_x
    # A 240 px stamp holds the 133 px donut even after it moves by 20 px.
    kw = dict(
        wavelength_nm=WL,
        n_photons=1e6,
        n_rays=200_000,
        poisson=False,
        npix=240,
        centre=(chief0, 0.0),
    )
    yy, xx = np.indices((240, 240))
    cents = []
    for tel in (nominal, shifted):
        img = render_donut(tel, fld, 1.5, rng=np.random.default_rng(17), **kw)
        cents.append(np.array([(img * xx).sum(), (img * yy).sum()]) / img.sum())
    got = cents[1] - cents[0]
    np.testing.assert_allclose(got, expect_px, atol=0.3)


def test_seeing_broadens_edges(nominal):
    kw = dict(wavelength_nm=WL, n_photons=1e6, n_rays=200_000, poisson=False)
    sharp = render_donut(nominal, (0, 0), 1.5, rng=np.random.default_rng(2), **kw)
    blur = render_donut(
        nominal, (0, 0), 1.5, seeing_fwhm_arcsec=1.0, rng=np.random.default_rng(2), **kw
    )
    assert sharp.sum() == pytest.approx(blur.sum(), rel=1e-3)
    yy, xx = np.indices(sharp.shape)
    rr = np.hypot(xx - 79.5, yy - 79.5)
    # 1" FWHM = 50 µm = 5 px FWHM: light spills into the central hole and outside the rim.
    assert sharp[rr < 30].sum() == 0 and blur[rr < 36].sum() > 1e-3 * blur.sum()
    assert blur[rr > 70].sum() > 10 * sharp[rr > 70].sum()


def test_corner_fields_config():
    f = corner_fields()
    assert f["R00"]["extra"] == pytest.approx((-1.1902777777777778, -1.1902777777777778))
    assert f["R44"]["intra"] == pytest.approx((1.2549166666666665, 1.1903333333333332))
    for v in f.values():
        np.testing.assert_allclose(v["mid"], np.add(v["extra"], v["intra"]) / 2, atol=1e-12)


def test_quasi_random_rays_render_a_nearly_noise_free_donut(nominal):
    """Sobol-sampled rays without a Poisson draw: two scrambles of the same donut agree far
    better than two sets of as many random rays, and the light is the same."""
    kw = dict(wavelength_nm=WL, n_photons=1e6, n_rays=2**18, poisson=False)
    field = (1.19, 1.19)
    q1, q2 = (render_donut(nominal, field, 1.5, sampling="quasi",
                           rng=np.random.default_rng(s), **kw) for s in (1, 2))
    r1, r2 = (render_donut(nominal, field, 1.5, sampling="random",
                           rng=np.random.default_rng(s), **kw) for s in (1, 2))
    lit = q1 > 0.2 * q1.max()
    quasi = np.std((q1 - q2)[lit]) / np.mean(q1[lit])
    random = np.std((r1 - r2)[lit]) / np.mean(q1[lit])
    assert quasi < 0.4 * random, (quasi, random)
    # The same vignetted flux (1e6 per unvignetted pupil) to well within the random rays'
    # scatter: sqrt(2^18) rays are 0.2 %.
    assert abs(q1.sum() - r1.sum()) / r1.sum() < 0.01
    assert abs(q1.sum() - q2.sum()) / q1.sum() < 0.002
    with pytest.raises(ValueError, match="sampling"):
        render_donut(nominal, field, 1.5, sampling="grid", **kw)
