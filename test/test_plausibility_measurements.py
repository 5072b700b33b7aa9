"""What a measurement may be: a re-sent measurement with a jitter far below the noise, two
corners of one visit that are one estimate, and uncertainties or pair counts no estimate has.

Genuine consecutive measurements are drawn from the estimator's calibrated noise model
(config/selection.yaml, read here with yaml and numpy, not through the module under test).
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cwfs_ros.config import config_dir
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc import plausibility as P

T = 1_750_000_000_000_000_000
SEC = 1_000_000_000
VISIT = 40 * SEC
ONES = np.ones(4, bool)


@pytest.fixture(scope="module")
def bounds() -> P.PlausibilityBounds:
    return P.physical_bounds("r", "bundled", 300.0)


def _state_vector(rng: np.random.Generator, scale: float = 0.01) -> np.ndarray:
    """The noise-free wavefront of a telescope state within the strokes (linear model)."""
    sm = C.SensitivityMatrix.from_bundled()
    x = rng.uniform(-1, 1, 50) * C.load_dof_spec().range * scale
    return C.intrinsic_vector_nm("r", sm.field_points_deg) + sm.matrix_nm @ x


def _noise_model(solver: str = "lsq") -> tuple[np.ndarray, np.ndarray]:
    """(c_j, f_j) of the per-pair noise model sigma_j^2 = (c_j q)^2 + f_j^2."""
    cfg = yaml.safe_load((config_dir() / "selection.yaml").read_text())
    m = cfg["combination"]["noise_model"][solver]
    return np.asarray(m["noise_coefficient_nm"], float), np.asarray(m["pair_floor_nm"], float)


def test_a_jittered_repeat_is_one_measurement():
    """The measurement re-sent with 1e-9 nm of noise, 40 s later, and one corner of it
    replayed inside otherwise new data: refused, naming the corner."""
    rng = np.random.default_rng(1)
    g = P.VisitGuard(min_period_s=15.0)
    z = _state_vector(rng) + rng.normal(0, 5.0, 76)
    unc = np.full(76, 12.0)
    assert g.check(T, z, ONES, unc).ok
    g.integrated(T, z, ONES, unc)
    for k in range(1, 4):
        v = g.check(T + k * VISIT, z + rng.normal(0, 1e-9, 76), ONES, unc)
        assert v.reason == "repeated_measurement" and "R00" in v.message, v
    fresh = _state_vector(rng) + rng.normal(0, 5.0, 76)
    fresh[38:57] = z[38:57] + rng.normal(0, 1e-9, 19)
    v = g.check(T + VISIT, fresh, ONES, unc)
    assert v.reason == "repeated_measurement" and "R40" in v.message, v
    # ... not once that corner is invalid in the new visit
    assert g.check(T + VISIT, fresh, np.array([True, True, False, True]), unc).ok
    # refuse_repeats off (benchmarks replaying one visit): only the period applies
    g.refuse_repeats = False
    assert g.check(T + VISIT, z, ONES, unc).ok


def test_how_close_is_a_repeat_follows_the_reported_uncertainty():
    """0.002 x the reported one-sigma (rms over the corner), never below 0.01 nm: a jitter of
    0.02 nm rms is a repeat of a corner reporting 15 nm (threshold 0.03 nm) but not of one
    reporting 1 nm (threshold: the floor); without a reported uncertainty the default 15 nm
    counts."""
    rng = np.random.default_rng(2)
    z = _state_vector(rng)
    jitter = rng.normal(0, 1.0, 76)
    jitter *= 0.02 / np.sqrt(np.mean(jitter[:19] ** 2))  # R00: 0.02 nm rms exactly
    jitter[19:] *= 1e3  # the other corners are new
    for u, repeat in ((15.0, True), (1.0, False), (0.0, True)):
        g = P.VisitGuard()
        unc = np.full(76, u)
        g.integrated(T, z, ONES, unc)
        v = g.check(T + VISIT, z + jitter, ONES, unc)
        assert (v.reason == "repeated_measurement") == repeat, (u, v)


def test_genuine_consecutive_measurements_are_not_repeats():
    """Two estimates of one state differ by photon noise: the noise model's c_j q per term,
    from the brightest donut below the full well (~8e8 e-, S/N 2.8e4 per side) to the
    faintest the selection takes (S/N 40). The one-sigma each reports is the full model
    (floors included); the floors are taken as equal in both estimates (the worst case)."""
    rng = np.random.default_rng(3)
    c, f = _noise_model("lsq")
    z = _state_vector(rng)
    refused = 0
    n = 0
    for snr in np.geomspace(2.8e4, 40.0, 12):
        q = np.sqrt(2.0) / snr
        sigma = np.tile(np.sqrt((c * q) ** 2 + f ** 2), 4)
        for _ in range(100):
            g = P.VisitGuard(min_period_s=0.0)
            a = z + rng.normal(0, 1, 76) * np.tile(c * q, 4)
            b = z + rng.normal(0, 1, 76) * np.tile(c * q, 4)
            g.integrated(T, a, ONES, sigma)
            refused += not g.check(T + VISIT, b, ONES, sigma).ok
            n += 1
    assert n == 1200 and refused == 0


def test_the_minimum_period_default_is_the_survey_cadence():
    g = P.VisitGuard()
    assert g.min_period_s == 15.0
    rng = np.random.default_rng(4)
    z = _state_vector(rng)
    g.integrated(T, z, ONES)
    assert g.check(T + 5 * SEC, z + rng.normal(0, 5, 76), ONES).reason == "too_soon"
    assert g.check(T + 17 * SEC, z + rng.normal(0, 5, 76), ONES).ok  # the next 15 s snap


@pytest.mark.parametrize("copy", ["R04=R00", "R04=R00+1e-9", "all=R00"])
def test_copied_corners_are_refused(bounds, copy):
    rng = np.random.default_rng(5)
    z = _state_vector(rng) + rng.normal(0, 5.0, 76)
    if copy == "all=R00":
        z = np.tile(z[:19], 4)
    else:
        z[19:38] = z[:19] + (rng.normal(0, 1e-9, 19) if copy.endswith("e-9") else 0.0)
    v = P.check_vector(z, ONES, bounds, uncertainty_nm=np.full(76, 10.0),
                       n_pairs=np.ones(4))
    assert v.reason == "copied_corner" and "R00" in v.message and "R04" in v.message, v
    # a copy into a corner flagged invalid is not judged
    assert P.check_vector(z, np.array([True, False, copy != "all=R00", copy != "all=R00"]),
                          bounds).ok


def test_genuine_corners_are_never_copies(bounds):
    """Four sensors, four photon noises: 500 genuine vectors of states within 30 % of the
    strokes with the noise of the brightest donut (c_j q at S/N 2.8e4) are all accepted."""
    rng = np.random.default_rng(6)
    c, f = _noise_model("lsq")
    q = np.sqrt(2.0) / 2.8e4
    sigma = np.tile(np.sqrt((c * q) ** 2 + f ** 2), 4)
    for _ in range(500):
        z = _state_vector(rng, 0.3) + rng.normal(0, 1, 76) * np.tile(c * q, 4)
        v = P.check_vector(z, ONES, bounds, uncertainty_nm=sigma, n_pairs=np.ones(4))
        assert v.ok, v


@pytest.mark.parametrize("case", ["u=1e4", "u=5e-324", "u=2001 in one term", "pairs=65535",
                                  "pairs=5"])
def test_claims_no_estimate_makes_are_refused(bounds, case):
    rng = np.random.default_rng(7)
    z = _state_vector(rng) + rng.normal(0, 5.0, 76)
    unc = np.full(76, 10.0)
    pairs = np.ones(4, dtype=int)
    if case == "u=1e4":
        unc[:] = 1e4
        z[:19] += 5000.0  # within the bound that 5 x 1e4 nm would have widened
    elif case == "u=5e-324":
        unc[:] = 5e-324
    elif case == "u=2001 in one term":
        unc[40] = 2001.0
    else:
        pairs[2] = int(case.split("=")[1])
    v = P.check_vector(z, ONES, bounds, uncertainty_nm=unc, n_pairs=pairs)
    assert v.reason == "implausible_uncertainty", v
    assert ("R40" if case != "u=1e4" and case != "u=5e-324" else "R00") in v.message


def test_genuine_claims_are_accepted(bounds):
    """The noise model's one-sigma from the brightest to the faintest donut, combinations of
    1 to 4 pairs: accepted."""
    rng = np.random.default_rng(8)
    for solver in ("lsq", "exp"):
        c, f = _noise_model(solver)
        for snr in np.geomspace(2.8e4, 40.0, 8):
            for n in (1, 2, 4):
                sigma = np.tile(np.sqrt((c * np.sqrt(2.0) / snr) ** 2 + f ** 2), 4)
                sigma /= np.sqrt(n)
                z = _state_vector(rng) + rng.normal(0, 1, 76) * sigma
                v = P.check_vector(z, ONES, bounds, uncertainty_nm=sigma,
                                   n_pairs=np.full(4, n))
                assert v.ok, (solver, snr, n, v)
