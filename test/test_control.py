"""Tests of cwfs_ros.ofc.control (optical feedback control core).

Expected values come from the ts_ofc data files read directly here, from independent numpy
linear algebra, or from batoid ray tracing, never from the code under test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cwfs_ros.errors import ConfigError
from cwfs_ros.ofc import control as C

OFC = Path(__file__).resolve().parents[1] / "config" / "ofc"
CORNERS_DEG = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * 1.1902777777777778
STROKES = [5900, 6700, 6700, 0.12, 0.12, 8700, 7600, 7600, 0.24, 0.24]  # ts_ofc rb_stroke


@pytest.fixture(scope="module")
def sm() -> C.SensitivityMatrix:
    return C.SensitivityMatrix.from_ts_ofc()


@pytest.fixture(scope="module")
def weights() -> np.ndarray:
    with open(OFC / "normalization_weights" / "range-fwhm.yaml") as f:
        return np.array(yaml.safe_load(f), dtype=float)


@pytest.fixture(scope="module")
def senm_um() -> np.ndarray:
    return np.load(OFC / "senM_corners_76x50_um_per_dof.npy")


def perturbation() -> np.ndarray:
    """M2 dx 200 µm + camera dz 20 µm + M1M3 mode 1 0.1 µm + M2 mode 2 0.05 µm."""
    x = np.zeros(50)
    x[1], x[5], x[10], x[31] = 200.0, 20.0, 0.1, 0.05
    return x


def solver(sm: C.SensitivityMatrix, **kw) -> C.OFCSolver:
    kw.setdefault("intrinsic_nm", np.zeros(76))
    return C.OFCSolver(sm, **kw)


def rms4(r: np.ndarray, n: int = 4) -> float:
    return float(np.sqrt(np.sum(r**2) / n))


def kept_modes(an: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    u, _, vt = np.linalg.svd(an, full_matrices=False)
    return u[:, :k], vt[:k]


# ------------------------------------------------------------------ data / loading
def test_ts_ofc_matrix_reproduces_corner_npy(sm, senm_um):
    """Evaluating the double-Zernike yaml at the SW0 corners gives the 76x50 npy (µm, -sign).

    In ts_ofc's own DoF convention exactly; in the default (batoid_rubin) convention with the
    columns of M2/camera dz, dx, rx negated.
    """
    assert sm.matrix_nm.shape == (76, 50)
    assert sm.source == "ts_ofc"
    plain = C.SensitivityMatrix.from_ts_ofc(dof_convention="ts_ofc")
    np.testing.assert_allclose(plain.matrix_nm, -1000.0 * senm_um, rtol=0, atol=1e-6)
    flip = np.ones(50)
    flip[[0, 1, 3, 5, 6, 8]] = -1.0
    np.testing.assert_allclose(sm.matrix_nm, -1000.0 * senm_um * flip, rtol=0, atol=1e-6)
    np.testing.assert_allclose(sm.field_points_deg, CORNERS_DEG, atol=1e-12)
    again = C.SensitivityMatrix.from_npy(OFC / "senM_corners_76x50_um_per_dof.npy",
                                         units="um", convention="ts_ofc", n_fields=4,
                                         dof_convention="ts_ofc")
    np.testing.assert_allclose(again.matrix_nm, sm.matrix_nm, atol=1e-6)


def test_dof_convention_conversion():
    assert C.TS_OFC_FLIPPED_DOF == (0, 1, 3, 5, 6, 8)
    sim = pytest.importorskip("cwfs_ros.sim")
    assert sim.TS_OFC_FLIPPED_DOF == C.TS_OFC_FLIPPED_DOF
    x = np.arange(1.0, 51.0)
    y = C.convert_dof_convention(x, "ts_ofc", "batoid_rubin")
    assert y[0] == -1 and y[2] == 3 and y[8] == -9 and y[10] == 11
    np.testing.assert_array_equal(C.convert_dof_convention(y, "batoid_rubin", "ts_ofc"), x)
    np.testing.assert_array_equal(C.convert_dof_convention(x, "ts_ofc", "ts_ofc"), x)
    m = np.ones((3, 50))
    assert np.all(C.convert_dof_convention(m, "ts_ofc", "batoid_rubin")[:, 5] == -1)
    with pytest.raises(ConfigError):
        C.convert_dof_convention(x, "ocs", "ts_ofc")
    with pytest.raises(ConfigError):
        C.convert_dof_convention(np.ones(49), "ts_ofc", "batoid_rubin")


def test_rotation_dof_units_are_degrees(senm_um):
    """1° of M2 tilt ~ 0.117 m of M2 decenter in coma: the pivot distance ~ M2's 6.8 m radius."""
    ratio = np.linalg.norm(senm_um[:, 3]) / np.linalg.norm(senm_um[:, 2])  # rx / dy, µm/µm
    pivot_m = ratio * 1e-6 / np.deg2rad(1.0)
    assert 5.0 < pivot_m < 9.0


def test_bundled_loader_validates(tmp_path, sm):
    good = tmp_path / "bundled.npy"
    np.save(good, sm.matrix_nm)
    b = C.SensitivityMatrix.from_bundled(good)
    assert b.source == "bundled" and b.n_fields == 4
    np.testing.assert_array_equal(b.matrix_nm, sm.matrix_nm)
    # the bundled matrix is evaluated at the corner mid-points (SW0/SW1), where the
    # estimator reports
    np.testing.assert_allclose(b.field_points_deg, C.corner_mid_field_points_deg(), atol=1e-12)
    np.testing.assert_allclose(b.field_points_deg[0], [-1.2225972222222222, -1.1903055555555555])
    bad = tmp_path / "bad.npy"
    np.save(bad, sm.matrix_nm[:75])
    with pytest.raises(ConfigError, match="shape"):
        C.SensitivityMatrix.from_bundled(bad)
    nan = sm.matrix_nm.copy()
    nan[3, 4] = np.nan
    np.save(bad, nan)
    with pytest.raises(ConfigError, match="finite"):
        C.SensitivityMatrix.from_bundled(bad)
    with pytest.raises(ConfigError):
        C.SensitivityMatrix.from_bundled(tmp_path / "missing.npy")


def test_dof_yaml_is_consistent():
    spec = C.load_dof_spec()
    assert len(spec.names) == 50 and len(set(spec.names)) == 50
    assert [i for i, u in enumerate(spec.units) if u == "deg"] == [3, 4, 8, 9]
    assert set(spec.units) == {"um", "deg"}
    np.testing.assert_allclose(spec.range[:10], STROKES)
    assert np.all(spec.max_step <= spec.range) and np.all(spec.max_step > 0)
    assert spec.names[1] == "M2_dx" and spec.index("Cam_dz") == 5
    assert spec.index("M1M3_B1") == 10 and spec.index("M2_B20") == 49


def test_band_wavelengths_follow_ts_ofc():
    wl = {b: C.band_wavelength_um(b) for b in C.BANDS}
    assert wl == {"u": 0.365, "g": 0.480, "r": 0.622, "i": 0.754, "z": 0.869, "y": 0.971,
                  "ref": 0.5}
    with pytest.raises(ConfigError):
        C.band_wavelength_um("q")


# ------------------------------------------------------------------ batoid cross-checks
@pytest.mark.parametrize("band, wl_nm", [("r", 622.0), ("g", 480.0)])
def test_intrinsic_matches_batoid(band, wl_nm):
    """ts_ofc intrinsics (waves x band wavelength) = batoid's nominal wavefront at a corner."""
    batoid = pytest.importorskip("batoid")
    tel = batoid.Optic.fromYaml(f"LSST_{band}.yaml")
    fx, fy = CORNERS_DEG[1]
    ref = batoid.zernike(tel, np.deg2rad(fx), np.deg2rad(fy), wl_nm * 1e-9, jmax=22,
                         eps=0.612, nx=128)[4:23] * wl_nm
    got = C.intrinsic_zernikes_nm(band, CORNERS_DEG[1:2])[0]
    assert np.max(np.abs(ref)) > 80.0  # a real, large design aberration at the corner
    assert np.max(np.abs(got - ref)) < 12.0


def test_sensitivity_sign_and_scale_vs_batoid():
    """A (wavefront sign, ts_ofc DoF convention) = batoid finite differences, plain frame."""
    sm = C.SensitivityMatrix.from_ts_ofc(dof_convention="ts_ofc")
    batoid = pytest.importorskip("batoid")
    tel = batoid.Optic.fromYaml("LSST_r.yaml")
    c = 1  # corner R04_SW0
    fx, fy = np.deg2rad(CORNERS_DEG[c])

    def zk_nm(optic):
        return batoid.zernike(optic, fx, fy, 622e-9, jmax=22, eps=0.612, nx=128)[4:23] * 622.0

    z0 = zk_nm(tel)
    cases = [
        (0, 50.0, tel.withGloballyShiftedOptic("M2", [0, 0, 50e-6])),
        (1, 200.0, tel.withGloballyShiftedOptic("M2", [200e-6, 0, 0])),
        (3, 0.005, tel.withLocallyRotatedOptic("M2", batoid.RotX(np.deg2rad(0.005)))),
        (5, 20.0, tel.withGloballyShiftedOptic("LSSTCamera", [0, 0, 20e-6])),
        (9, 0.01, tel.withLocallyRotatedOptic("LSSTCamera", batoid.RotY(np.deg2rad(0.01)))),
    ]
    for idx, amount, optic in cases:
        d = (zk_nm(optic) - z0) / amount
        col = sm.matrix_nm[19 * c : 19 * c + 19, idx]
        ratio = d @ col / (col @ col)
        corr = d @ col / np.linalg.norm(d) / np.linalg.norm(col)
        assert 0.98 < ratio < 1.02, (idx, ratio)
        assert corr > 0.999, (idx, corr)


def test_bending_sign_vs_batoid(sm):
    """M2 bending mode 1 as a +sag Zernike on M2 gives +A's column (j<=28 part only)."""
    batoid = pytest.importorskip("batoid")
    fits = pytest.importorskip("astropy.io.fits")
    bend_dir = Path(C.__file__).resolve().parents[1] / "sim" / "data" / "bending"
    zk_file = bend_dir / "M2_bend_zk.fits.gz"
    if not zk_file.exists():
        pytest.skip("bending tables not present")
    tel = batoid.Optic.fromYaml("LSST_r.yaml")
    fx, fy = np.deg2rad(CORNERS_DEG[1])
    sag = np.asarray(fits.getdata(zk_file), dtype=float)[0]  # m per µm of mode 1
    bent = tel.withSurface("M2", batoid.Sum([tel["M2"].surface,
                                             batoid.Zernike(sag, R_outer=1.71)]))
    d = (batoid.zernike(bent, fx, fy, 622e-9, jmax=22, eps=0.612, nx=128)
         - batoid.zernike(tel, fx, fy, 622e-9, jmax=22, eps=0.612, nx=128))[4:23] * 622.0
    col = sm.matrix_nm[19:38, 30]
    assert 0.9 < d @ col / (col @ col) < 1.15
    assert d @ col / np.linalg.norm(d) / np.linalg.norm(col) > 0.999


# ------------------------------------------------------------------ estimation
def test_gain1_recovers_observable_part(sm, weights):
    """The 12-mode estimate equals an independent lstsq in the same normalised modes."""
    x = perturbation()
    intr = C.intrinsic_vector_nm("r")
    y = intr + sm.matrix_nm @ x
    est = C.OFCSolver(sm, band="r").estimate(y)
    assert est.valid and est.status == "ok" and est.n_modes_used == 12

    r = sm.matrix_nm @ x
    an = sm.matrix_nm * weights[None, :]
    _, vt = kept_modes(an, 12)
    c, *_ = np.linalg.lstsq(an @ vt.T, r, rcond=None)
    expected = weights * (vt.T @ c)
    np.testing.assert_allclose(est.dof_error, expected, atol=1e-9 * np.abs(expected).max())
    # ... which is the projection of the true normalised state onto those modes
    np.testing.assert_allclose(est.dof_error / weights, vt.T @ (vt @ (x / weights)),
                               atol=1e-9 * np.abs(x / weights).max())
    # and it explains the wavefront: residual << input
    fit = r - sm.matrix_nm @ est.dof_error
    assert est.wavefront_rms_nm == pytest.approx(rms4(r), rel=1e-9)
    assert est.wavefront_rms_nm > 400.0
    assert est.fit_residual_rms_nm == pytest.approx(rms4(fit), rel=1e-9)
    assert est.fit_residual_rms_nm < 0.05 * est.wavefront_rms_nm


def test_full_rank_subset_recovers_exactly(sm):
    """With the well-observed DoFs only and all their modes kept, x is recovered exactly."""
    mask = np.zeros(50, bool)
    mask[[0, 3, 4, 5, 8, 9, 10, 11, 30, 31]] = True
    x = np.zeros(50)
    x[[0, 3, 5, 9, 10, 31]] = [30.0, 0.003, -25.0, 0.004, 0.08, -0.04]
    s = solver(sm, dof_mask=mask, n_modes=int(mask.sum()))
    est = s.estimate(sm.matrix_nm @ x)
    assert est.valid, est.status
    np.testing.assert_allclose(est.dof_error, x, rtol=1e-6, atol=1e-9)
    assert est.fit_residual_rms_nm < 1e-6


def test_tikhonov_matches_normal_equations(sm, weights):
    x = perturbation()
    r = sm.matrix_nm @ x
    alpha = 1e-3
    est = solver(sm, method="tikhonov", alpha=alpha).estimate(r)
    assert est.valid
    an = sm.matrix_nm * weights[None, :]
    s0 = np.linalg.svd(an, compute_uv=False)[0]
    z = np.linalg.solve(an.T @ an + (alpha * s0) ** 2 * np.eye(50), an.T @ r)
    np.testing.assert_allclose(est.dof_error, weights * z, atol=1e-7 * np.abs(weights * z).max())
    assert 0 < est.n_modes_used < 50


def test_allow_partial_drops_invalid_corner_rows(sm):
    x = perturbation()
    y = sm.matrix_nm @ x
    y[19:38] = np.nan  # corner R04 unusable
    valid = [True, False, True, True]
    est = solver(sm, allow_partial=True).estimate(y, valid)
    assert est.valid and est.corners_used == (True, False, True, True)
    keep = np.repeat(valid, 19)
    three = C.SensitivityMatrix(sm.matrix_nm[keep], CORNERS_DEG[[0, 2, 3]])
    ref = solver(three, intrinsic_nm=np.zeros(57)).estimate(y[keep])
    np.testing.assert_allclose(est.dof_error, ref.dof_error, rtol=1e-12, atol=1e-15)
    assert est.wavefront_rms_nm == pytest.approx(rms4(y[keep], 3))
    assert np.all(np.isnan(est.wavefront_nm[19:38]))


# ------------------------------------------------------------------ closed loop
def _loop(s: C.OFCSolver, sm: C.SensitivityMatrix, x0: np.ndarray, n: int):
    x = x0.copy()
    rms, results = [], []
    for _ in range(n):
        res = s.step(sm.matrix_nm @ x)
        assert res.valid, res.status
        x = x + res.dof  # apply the correction to the "telescope"
        rms.append(res.wavefront_rms_nm)
        results.append(res)
    return np.array(rms), results, x


def test_closed_loop_proportional_is_monotonic(sm):
    s = solver(sm, kp=0.18, ki=0.0, max_step=None, clip_range=None)
    rms, res, _ = _loop(s, sm, perturbation(), 40)
    assert np.all(np.diff(rms) <= 1e-9)
    assert rms[1] < 0.85 * rms[0]
    assert res[0].predicted_residual_rms_nm == pytest.approx(rms[1], rel=1e-9)
    assert rms[-1] < 0.05 * rms[0]


def test_closed_loop_pi_follows_second_order_recursion(sm, weights):
    """kp 0.18, ki 0.022: every observable mode obeys c+ = c - kp c - ki sum(c)."""
    kp, ki, n = 0.18, 0.022, 60
    x0 = perturbation()
    s = solver(sm, kp=kp, ki=ki, max_step=None, clip_range=None)
    rms, _, _ = _loop(s, sm, x0, n)
    r0 = sm.matrix_nm @ x0
    u12, _ = kept_modes(sm.matrix_nm * weights[None, :], 12)
    a = np.linalg.norm(u12.T @ r0)
    b = np.linalg.norm(r0 - u12 @ (u12.T @ r0))
    c, total, expected = 1.0, 0.0, []
    for _ in range(n):
        expected.append(np.sqrt(c**2 * a**2 + b**2) / 2.0)
        total += c
        c = c - kp * c - ki * total
    np.testing.assert_allclose(rms, expected, rtol=1e-6)
    assert rms[1] < rms[0]  # the correction has the right sign
    assert rms[-1] < 1.05 * b / 2.0  # converged to the unobservable floor


def test_step_limit_and_range_clip(sm):
    spec = C.load_dof_spec()
    big = np.zeros(50)
    big[0], big[5], big[10] = 3000.0, -2000.0, 0.3  # M2 dz, camera dz, M1M3 mode 1
    s = solver(sm, kp=1.0, ki=0.0, dof_mask=np.arange(50) < 30)
    _, res, _ = _loop(s, sm, big, 3)
    for r in res:
        assert np.all(np.abs(r.dof) <= spec.max_step * (1 + 1e-12))
        assert np.all(np.abs(r.dof_total) <= spec.range * (1 + 1e-12))
    first = res[0]
    assert first.clipped[10] and np.isclose(abs(first.dof[10]), spec.max_step[10])
    for i in np.flatnonzero(first.clipped):  # every clipped DoF sits exactly at a limit
        assert np.isclose(abs(first.dof[i]), spec.max_step[i]) or np.isclose(
            abs(first.dof_total[i]), spec.range[i])
    assert abs(first.dof_error[10]) > spec.max_step[10]  # the limit really was binding

    s = solver(sm, kp=0.18, ki=0.022, max_step=1e-4)
    r = s.step(sm.matrix_nm @ big)
    assert r.clipped.any()
    assert np.all(s.integral[r.clipped] == 0.0)  # no wind-up while saturated
    np.testing.assert_allclose(s.integral[~r.clipped], r.dof_error[~r.clipped])

    lim = np.full(50, 10.0)
    s = solver(sm, kp=1.0, ki=0.0, max_step=None, clip_range=lim)
    _, res, _ = _loop(s, sm, big, 4)
    for r in res:
        assert np.all(np.abs(r.dof_total) <= 10.0 + 1e-12)
    assert np.isclose(abs(res[-1].dof_total[5]), 10.0)
    np.testing.assert_allclose(sum(r.dof for r in res), res[-1].dof_total, atol=1e-9)


def test_step_limit_holds_when_the_state_is_out_of_range(sm):
    """A state beyond the DoF ranges (range clipping switched off for a while, then on again)
    returns into range at the step limit per visit, never in one jump."""
    spec = C.load_dof_spec()
    s = solver(sm, kp=0.18, ki=0.0)
    out = np.zeros(50)
    out[0], out[5] = 3.0 * spec.range[0], -3.0 * spec.range[5]
    s.restore((out, np.zeros(50), 0, None, s.ki))
    y = np.zeros(76)  # no wavefront error: only the range clip asks for a move
    r = s.step(y)
    assert r.valid, r.status
    assert np.all(np.abs(r.dof) <= spec.max_step * (1 + 1e-12))
    assert r.dof[0] == pytest.approx(-spec.max_step[0]) and r.clipped[0]
    assert r.dof[5] == pytest.approx(spec.max_step[5]) and r.clipped[5]
    n = int(np.ceil(2.0 * spec.range[0] / spec.max_step[0]))
    for _ in range(n):
        r = s.step(y)
        assert np.all(np.abs(r.dof) <= spec.max_step * (1 + 1e-12))
    assert np.all(np.abs(s.dof_total) <= spec.range * (1 + 1e-12))


def test_integral_is_bumpless_across_changes_of_ki(sm):
    """No integral accumulates while ki = 0, and a solver rebuilt with another ki keeps the
    integral's contribution ki * sum(e): switching integral action on in a converged loop
    does not kick it."""
    y = sm.matrix_nm @ perturbation()
    p_only = solver(sm, kp=0.18, ki=0.0, max_step=None, clip_range=None)
    for _ in range(5):
        assert p_only.step(y).valid
    assert np.all(p_only.integral == 0)

    pi = solver(sm, kp=0.18, ki=0.022, max_step=None, clip_range=None)
    for _ in range(5):
        assert pi.step(y).valid
    doubled = solver(sm, kp=0.18, ki=0.044, max_step=None, clip_range=None)
    doubled.restore(pi.state())
    np.testing.assert_allclose(0.044 * doubled.integral, 0.022 * pi.integral, rtol=1e-12)
    off = solver(sm, kp=0.18, ki=0.0, max_step=None, clip_range=None)
    off.restore(pi.state())
    assert np.all(off.integral == 0)

    # A noisy loop converged proportional-only, then ki switched on: the error stays at
    # its floor (when the unused integral summed the noise, it rose from 95 to 229 nm).
    rng = np.random.default_rng(5)
    s = solver(sm, kp=0.18, ki=0.0, max_step=None, clip_range=None)
    x = perturbation()
    for _ in range(60):
        r = s.step(sm.matrix_nm @ x + rng.normal(0.0, 20.0, 76))
        x = x + r.dof
    floor = r.wavefront_rms_nm
    on = solver(sm, kp=0.18, ki=0.022, max_step=None, clip_range=None)
    on.restore(s.state())
    worst = 0.0
    for _ in range(8):
        r = on.step(sm.matrix_nm @ x + rng.normal(0.0, 20.0, 76))
        x = x + r.dof
        worst = max(worst, r.wavefront_rms_nm)
    assert worst < 1.5 * floor + 10.0, (floor, worst)


def test_dof_mask_keeps_excluded_dofs_at_zero(sm):
    mask = np.ones(50, bool)
    mask[[3, 4, 8, 9]] = False  # no tilts
    mask[20:30] = False  # no high M1M3 modes
    s = solver(sm, dof_mask=mask)
    _, res, _ = _loop(s, sm, perturbation(), 5)
    for r in res:
        assert np.all(r.dof[~mask] == 0.0) and np.all(r.dof_total[~mask] == 0.0)
        assert np.all(r.dof_error[~mask] == 0.0)
    assert np.any(res[-1].dof_total[mask] != 0.0)
    with pytest.raises(ConfigError):
        solver(sm, dof_mask=np.zeros(50, bool))


def test_set_band_changes_intrinsic(sm):
    s = C.OFCSolver(sm, band="r")
    y = C.intrinsic_vector_nm("g")
    assert s.estimate(y).wavefront_rms_nm > 10.0
    s.set_band("g")
    assert s.band == "g" and s.estimate(y).wavefront_rms_nm < 1e-9


def test_reset_clears_state(sm):
    s = solver(sm)
    y = sm.matrix_nm @ perturbation()
    first = s.step(y)
    s.step(y)
    assert np.any(s.dof_total != 0) and np.any(s.integral != 0)
    s.reset()
    assert np.all(s.dof_total == 0) and np.all(s.integral == 0) and s.n_steps == 0
    again = s.step(y)
    np.testing.assert_array_equal(again.dof, first.dof)


# ------------------------------------------------------------------ refusal
@pytest.mark.parametrize(
    "kw, y_fn, valid, tag",
    [
        ({}, lambda y: np.append(y, 0.0), None, "bad_shape"),
        ({}, lambda y: y[:75], None, "bad_shape"),
        ({}, lambda y: y.reshape(19, 4), None, "bad_shape"),
        ({}, lambda y: ["a"] * 76, None, "bad_shape"),
        ({}, lambda y: y, [True, True, True], "bad_shape"),
        ({}, lambda y: np.where(np.arange(76) == 40, np.nan, y), None, "non_finite"),
        ({}, lambda y: np.where(np.arange(76) == 3, np.inf, y), None, "non_finite"),
        ({}, lambda y: y, [True, False, True, True], "corner_invalid"),
        ({"allow_partial": True}, lambda y: y, [False] * 4, "no_valid_corners"),
        ({"n_modes": 50}, lambda y: y, None, "ill_conditioned"),
        ({"n_modes": 19, "allow_partial": True, "max_condition": 1e5}, lambda y: y,
         [True, False, False, False],
         "ill_conditioned"),
    ],
)
def test_invalid_inputs_refused(sm, kw, y_fn, valid, tag):
    s = solver(sm, **kw)
    y = y_fn(sm.matrix_nm @ perturbation())
    res = s.step(y, valid)
    assert not res.valid
    assert res.status.startswith(tag + ":"), res.status
    assert np.all(res.dof == 0.0) and np.all(res.dof_total == 0.0)
    assert np.all(s.integral == 0.0) and s.n_steps == 0


def test_refusal_names_the_corner(sm):
    res = solver(sm).step(sm.matrix_nm @ perturbation(), [True, False, True, True])
    assert "R04" in res.status and "allow_partial" in res.status
    y = sm.matrix_nm @ perturbation()
    y[60] = np.nan  # corner 3 = R44_SW0
    res = solver(sm).step(y)
    assert "R44" in res.status


def test_invalid_visit_leaves_state_alone(sm):
    s = solver(sm)
    y = sm.matrix_nm @ perturbation()
    s.step(y)
    before = (s.dof_total.copy(), s.integral.copy())
    bad = y.copy()
    bad[0] = np.nan
    res = s.step(bad)
    assert not res.valid and np.all(res.dof == 0)
    np.testing.assert_array_equal(res.dof_total, before[0])
    np.testing.assert_array_equal(s.integral, before[1])


def test_visit_order_rules(sm):
    """With stamps, a visit is applied once and in order: a repeated, older or unset stamp,
    or one beyond ``max_future_s`` ahead of the clock, is refused with the state unchanged;
    reset forgets the last stamp."""
    s = solver(sm, max_future_s=60.0)
    y = sm.matrix_nm @ perturbation()
    now = 1_750_000_000 * 10**9
    assert s.step(y, stamp_ns=now - 10, now_ns=now).valid
    state = s.state()
    for stamp, tag in ((now - 10, "stale_visit"), (now - 11, "stale_visit"), (0, "no_stamp"),
                       (now + 61 * 10**9, "future_stamp")):
        res = s.step(y, stamp_ns=stamp, now_ns=now)
        assert not res.valid and res.status.startswith(tag + ":"), (stamp, res.status)
        assert np.all(res.dof == 0)
    np.testing.assert_array_equal(s.state()[0], state[0])
    np.testing.assert_array_equal(s.state()[1], state[1])
    assert s.n_steps == 1 and s.last_stamp_ns == now - 10
    # A clock gone back by a day is refused too (an operator decides), naming the way out.
    res = s.step(y, stamp_ns=now - 86_400 * 10**9, now_ns=now)
    assert not res.valid and "~/reset" in res.status and "86400 s back" in res.status
    assert s.step(y, stamp_ns=now + 59 * 10**9, now_ns=now).valid  # within max_future_s
    assert s.step(y, stamp_ns=now + 61 * 10**9).valid  # no clock given: no future test
    s.reset()
    assert s.last_stamp_ns is None and s.step(y, stamp_ns=now - 10, now_ns=now).valid
    # A dry run computes the correction the real step gives, and leaves the state (the stamp
    # included) as it was.
    before = s.state()
    dry = s.step(y, stamp_ns=now, now_ns=now, dry_run=True)
    assert dry.valid and s.last_stamp_ns == now - 10 and s.n_steps == 1
    np.testing.assert_array_equal(s.dof_total, before[0])
    np.testing.assert_array_equal(s.integral, before[1])
    real = s.step(y, stamp_ns=now, now_ns=now)
    np.testing.assert_array_equal(real.dof, dry.dof)
    np.testing.assert_array_equal(real.dof_total, dry.dof_total)
    assert s.last_stamp_ns == now and s.n_steps == 2


def test_implausible_wavefront_refused(sm):
    s = solver(sm, max_abs_zernike_nm=20_000.0)
    y = np.zeros(76)
    y[19 + 5] = 1e5  # R04's Z9
    res = s.step(y)
    assert not res.valid and res.reason == "implausible_wavefront"
    assert res.status.startswith("implausible_wavefront"), res.status
    assert "R04" in res.status and "R00" not in res.status
    assert s.n_steps == 0 and np.all(s.dof_total == 0)
    y[19 + 5] = 19_999.0  # within the limit: solved (the step limit bounds the correction)
    assert s.step(y).valid


def test_a_valid_corner_of_zeros_is_refused(sm):
    """A corner flagged valid but filled with exact zeros is not a measurement (every measured
    wavefront holds the design's): refused, state unchanged, the corner named."""
    s = C.OFCSolver(sm, band="r")
    y = s.intrinsic_nm.copy()
    assert s.step(y).valid  # the design alone: a perfect telescope, nothing to do
    before = s.state()
    y[19:38] = 0.0  # R04 left unfilled
    res = s.step(y)
    assert not res.valid and res.reason == "implausible_wavefront"
    assert res.status.startswith("implausible_wavefront"), res.status
    assert "R04" in res.status and np.all(res.dof == 0)
    np.testing.assert_array_equal(s.dof_total, before[0])
    assert s.n_steps == 1
    # Flagged invalid, the same corner is simply dropped (allow_partial).
    p = C.OFCSolver(sm, band="r", allow_partial=True)
    assert p.step(y, [True, False, True, True]).valid


def test_overflowing_input_never_reaches_the_state(sm):
    """Without the plausibility limit, finite values near the float64 maximum overflow the
    solve; the step is refused and the state stays finite (it used to become NaN and stay
    so for every later visit)."""
    s = solver(sm)
    y = sm.matrix_nm @ perturbation()
    assert s.step(y).valid
    before = s.state()
    res = s.step(np.full(76, 1.7e308))
    assert not res.valid and res.reason == "non_finite_result"
    assert res.status.startswith("non_finite_result"), res.status
    np.testing.assert_array_equal(s.dof_total, before[0])
    np.testing.assert_array_equal(s.integral, before[1])
    assert np.all(np.isfinite(s.dof_total)) and s.step(y).valid


def test_solver_from_params_limits():
    """0 means no limit; the shipped parameters set both limits."""
    import yaml

    from cwfs_ros.config import config_dir

    p = yaml.safe_load((config_dir() / "params.yaml").read_text())["ofc_node"]["ros__parameters"]
    s = C.solver_from_params(lambda n: p[n])
    assert s.max_abs_zernike_nm == 20_000.0 and s.max_future_s == 1.0
    p = {**p, "max_abs_zernike_nm": 0.0, "max_future_s": 0.0}
    s = C.solver_from_params(lambda n: p[n])
    assert s.max_abs_zernike_nm is None and s.max_future_s is None
    with pytest.raises(ConfigError, match="max_future_s"):
        solver(C.SensitivityMatrix.from_bundled(), max_future_s=-1.0)


@pytest.mark.parametrize("name, value, match", [
    ("kp", 1.9, r"kp must be in \[0, 1\]"),
    ("ki", float("nan"), "ki must be in"),
    ("max_step_scale", -1.0, "max_step_scale must be in"),
    ("max_abs_zernike_nm", -5.0, "max_abs_zernike_nm must be in"),
    ("max_future_s", "60", "max_future_s must be a number"),
    ("n_modes", 12.9, "n_modes must be an integer"),
    ("n_modes", 0, "n_modes must be in"),
    ("n_modes", True, "n_modes must be an integer"),
    ("alpha", 0.0, "alpha must be in"),
    ("clip_to_range", "false", "clip_to_range must be true or false"),
    ("allow_partial", 1, "allow_partial must be true or false"),
    ("dof_mask", ["yes"] * 50, "dof_mask must hold 50 booleans"),
])
def test_solver_from_params_refuses_what_the_node_refuses(name, value, match):
    """The offline replay builds its solver here from a parameter file: a value ofc_node's
    descriptors refuse (out of range, wrong type) is a ConfigError, not a solver no node
    could run (a negative max_step_scale silently meant no step limit)."""
    import yaml

    from cwfs_ros.config import config_dir

    p = yaml.safe_load((config_dir() / "params.yaml").read_text())["ofc_node"]["ros__parameters"]
    p = {**p, name: value}
    with pytest.raises(ConfigError, match=match):
        C.solver_from_params(lambda n: p[n])


def test_normalisation_weights_are_named_not_paths():
    for name in ("../dof", "/etc/hostname", "x" * 300):
        with pytest.raises(ConfigError, match="unknown normalisation weights"):
            C.load_normalization_weights(name)


# ------------------------------------------------------------------ observability
def test_observability_null_space(sm, weights):
    rep = C.observability(sm, rel_tol=1e-6)
    assert rep.singular_values.shape == (50,)
    assert np.all(np.diff(rep.singular_values) <= 0)
    an = sm.matrix_nm * weights[None, :]
    ref = np.linalg.svd(an, compute_uv=False)
    np.testing.assert_allclose(rep.singular_values, ref, rtol=1e-10)
    assert rep.n_near_null == int(np.sum(ref / ref[0] < 1e-6))
    for v in rep.null_directions_norm:
        assert np.linalg.norm(an @ v) < 1e-6 * ref[0]
    # in the solver's normalised space the camera's lateral shift is the blindest direction
    names = C.load_dof_spec().names
    _, _, vt = np.linalg.svd(an)
    assert names[int(np.argmax(np.abs(vt[-1])))] in ("Cam_dx", "Cam_dy")
    assert "Cam_d" in rep.describe(49, names, top=1)
    np.testing.assert_allclose(np.abs(rep.null_directions_dof[-1]), np.abs(weights * vt[-1]),
                               atol=1e-9 * np.abs(weights * vt[-1]).max())

    one = C.observability(sm, corner_valid=[True, False, False, False])
    assert one.n_near_null >= 50 - 19  # 19 equations cannot pin 50 unknowns
