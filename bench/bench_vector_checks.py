#!/usr/bin/env python
"""What a WavefrontVector may be: false refusals and detections of ofc_node's vector checks.

  repeats    genuine consecutive measurements of one telescope state: (a) the estimator's
             calibrated noise model (config/selection.yaml, lsq and exp, S/N 40 to 2.8e4, the
             floors taken as identical in both: the worst case), (b) pairs of real estimates
             (lsq) of one ray-traced corner pair, two Poisson realisations of the same
             expected images (1e5-1e8 photons): refused as repeated_measurement? And the
             jitters the rule catches.
  tampering  the Kalman filter's consistency statistic (chi-square per term against every
             state the strokes allow, KalmanOFC's inconsistent_measurement, threshold
             max_inconsistency) of genuine measurements (batoid true wavefronts of states at
             0, 10 % and 30 % of the strokes plus 10 nm of noise, 15 nm reported) and of
             tampered copies of them, for matrix_source bundled and ts_ofc; copied_corner
             for the copies.
  claims     the noise model's smallest and largest per-term one-sigma, and what a corner
             claiming max_uncertainty_nm can do to the correction.

Usage: .venv/bin/python bench/bench_vector_checks.py [repeats] [tampering] [claims]
       [--pairs N] [--states S]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from cwfs_ros.config import config_dir  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ofc import plausibility as P  # noqa: E402

ONES = np.ones(4, bool)
T = 1_750_000_000_000_000_000
SNR_BRIGHT = 2.8e4  # ~8e8 e- in a 160-px donut below the 1e5 e- full well, per side
SNR_FAINT = 40.0  # the selection's min_snr


def noise_model(solver: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = yaml.safe_load((config_dir() / "selection.yaml").read_text())["combination"][
        "noise_model"][solver]
    return (np.asarray(m["noise_coefficient_nm"], float), np.asarray(m["pair_floor_nm"], float),
            np.asarray(m["common_floor_nm"], float))


def state_vector(rng: np.random.Generator, scale: float) -> np.ndarray:
    sm = C.SensitivityMatrix.from_bundled()
    x = rng.uniform(-1, 1, 50) * C.load_dof_spec().range * scale
    return C.intrinsic_vector_nm("r", sm.field_points_deg) + sm.matrix_nm @ x


def repeat_refused(a: np.ndarray, ua: np.ndarray, b: np.ndarray, ub: np.ndarray) -> bool:
    g = P.VisitGuard(min_period_s=0.0)
    g.integrated(T, a, ONES, ua)
    return not g.check(T + 40 * 10**9, b, ONES, ub).ok


def bench_repeats_model(pairs: int, rng: np.random.Generator) -> None:
    print("\n== repeats, noise model: genuine consecutive pairs refused / total")
    z = state_vector(rng, 0.01)
    for solver in ("lsq", "exp"):
        c, f, _ = noise_model(solver)
        n = bad = 0
        lo = np.inf
        for snr in np.geomspace(SNR_BRIGHT, SNR_FAINT, 12):
            q = np.sqrt(2.0) / snr
            photon = np.tile(c * q, 4)
            sigma = np.tile(np.sqrt((c * q) ** 2 + f ** 2), 4)
            for _ in range(pairs):
                a = z + rng.normal(0, 1, 76) * photon
                b = z + rng.normal(0, 1, 76) * photon
                d = np.sqrt(np.mean((a - b).reshape(4, 19) ** 2, axis=1))
                lo = min(lo, float(np.min(d / np.sqrt(np.mean(sigma[:19] ** 2)))))
                bad += repeat_refused(a, sigma, b, sigma)
                n += 1
        print(f"  {solver}: {bad}/{n} refused; smallest corner rms difference / reported "
              f"one-sigma {lo:.4f} (the rule: {P.CopyRule().fraction:g})")
    u = np.full(76, 15.0)
    for eps in (1e-9, 1e-3, 0.01, 0.02, 0.05, 0.1):
        b = z + rng.normal(0, eps, 76)
        print(f"  a repeat with {eps:g} nm of jitter (15 nm reported): "
              f"{'refused' if repeat_refused(z, u, b, u) else 'accepted'}")


def bench_repeats_estimates(rng: np.random.Generator) -> None:
    import bench_input_checks as BIC

    from cwfs_ros.runtime.corner_pool import stamp_uncertainty_nm
    from cwfs_ros.wfs.estimator import estimate_wavefront

    print("\n== repeats, real estimates (lsq) of one corner, two Poisson realisations: "
          "rms difference / reported one-sigma")
    tels = BIC.telescopes(2, rng)
    traced = BIC.traced_pairs(tels, BIC.corner_fields(), 200_000, rng)
    rule = P.CopyRule()
    for photons in (1e5, 1e6, 1e7, 1e8):
        ratios, bad = [], 0
        for p in traced:
            est = []
            for _ in range(2):
                intra = BIC.noisy(p["intra"], photons, 0.0, False, rng)
                extra = BIC.noisy(p["extra"], photons, 0.0, False, rng)
                res = estimate_wavefront(intra, extra, field_intra_deg=p["fi"],
                                         field_extra_deg=p["fe"], solver="lsq")
                est.append((np.asarray(res.zernikes_nm, float), stamp_uncertainty_nm(res, "lsq")))
            (za, ua), (zb, ub) = est
            d = float(np.sqrt(np.mean((za - zb) ** 2)))
            ratios.append(d / min(rule.sigma_nm(ua), rule.sigma_nm(ub)))
            bad += rule.copy(za, ua, zb, ub) is not None
        print(f"  {photons:.0e} photons: {bad}/{len(traced)} refused; difference / one-sigma "
              f"min {min(ratios):.3f} median {np.median(ratios):.3f}")


def consistency(ctl, y: np.ndarray, u: np.ndarray) -> float:
    """KalmanOFC's inconsistent_measurement statistic (rotator at 0)."""
    from cwfs_ros.ofc.estimation import measurement_covariance

    at = ctl.model.at(0.0)
    rows = np.ones(76, bool)
    r = at.to_telescope(y) - at.intrinsic_nm
    cov = measurement_covariance(u, rows, at.zrot, default_nm=ctl.settings.default_uncertainty_nm,
                                 floor_nm=ctl.settings.model_floor_nm)
    m = ctl.dof_mask
    H = at.H[:, m]
    S = (H * ctl.spec.range[m] ** 2) @ H.T + cov
    return float(r @ np.linalg.solve(S, r)) / r.size


def tampered(z: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    out = {}
    w = z.copy()
    w[38:57] = rng.uniform(0.011, 1, 19) * rng.choice([-1, 1], 19)
    out["R40 every term 0.011-1 nm"] = w
    w = z.copy()
    w[19:38] = z[:19] + rng.normal(0, 1.0, 19)
    out["R04 = R00 + 1 nm noise"] = w
    out["all = R00 + 1 nm noise"] = np.tile(z[:19], 4) + rng.normal(0, 1.0, 76)
    w = z.copy()
    w[:19] = rng.permutation(z[:19])
    out["R00 terms shuffled"] = w
    out["all 76 terms shuffled"] = rng.permutation(z)
    w = z.copy()
    w[:19], w[57:] = z[57:], z[:19]
    out["R00 <-> R44 swapped"] = w
    w = z.copy()
    w[:19], w[19:38] = z[19:38], z[:19]
    out["R00 <-> R04 swapped"] = w
    out["corner blocks rotated by one"] = z.reshape(4, 19)[[1, 2, 3, 0]].reshape(-1)
    w = z.copy()
    w[:19] *= -1
    out["R00 sign flipped"] = w
    return out


def bench_tampering(states: int, rng: np.random.Generator) -> None:
    from cwfs_ros.ofc.kalman import KalmanOFC
    from cwfs_ros.ofc.model import OpticalModel
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    geo = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())
    mids = [tuple(c["mid_deg"]) for c in geo["corners"].values()]
    spec = C.load_dof_spec()
    sets = {}
    for scale in (0.0, 0.1, 0.3):
        zs = []
        for _ in range(1 if scale == 0 else states):
            tel = perturbed_telescope(rng.uniform(-1, 1, 50) * spec.range * scale, "r")
            zs.append(np.concatenate([true_zernikes_nm(tel, m, wavelength_nm=622.0)
                                      for m in mids]))
        sets[scale] = zs
    u = np.full(76, 15.0)
    bounds = P.physical_bounds("r", "bundled", 300.0)
    for src in ("bundled", "ts_ofc"):
        ctl = KalmanOFC(OpticalModel(src))
        lim = ctl.settings.max_inconsistency
        print(f"\n== tampering, matrix_source {src}: consistency chi2 per term (refused above "
              f"{lim:g}); 5 noise draws per state")
        for scale, zs in sets.items():
            gen, tam, guard = [], {}, {}
            for z in zs:
                for _ in range(5):
                    y = z + rng.normal(0, 10.0, 76)
                    gen.append(consistency(ctl, y, u))
                    for k, w in tampered(y, rng).items():
                        tam.setdefault(k, []).append(consistency(ctl, w, u))
                        v = P.check_vector(w, ONES, bounds, uncertainty_nm=u, n_pairs=np.ones(4))
                        guard.setdefault(k, []).append("" if v.ok else v.reason)
            print(f"  states x{scale:g} of the strokes ({len(gen)}): genuine max {max(gen):.3g}")
            for k, v in tam.items():
                refused = sum(s > lim for s in v)
                other = {r for r in guard[k] if r}
                print(f"    {k:30s} min {min(v):9.3g} median {np.median(v):9.3g}; "
                      f"refused {refused}/{len(v)}"
                      + (f"; input guards: {sorted(other)}" if other else ""))


def bench_claims() -> None:
    from cwfs_ros.ofc.kalman import KalmanOFC
    from cwfs_ros.ofc.model import OpticalModel

    print("\n== claims: the noise model's per-term one-sigma")
    for solver in ("lsq", "exp"):
        c, f, g = noise_model(solver)
        lo = np.sqrt((c * np.sqrt(2) / SNR_BRIGHT) ** 2 + f ** 2)
        lo4 = np.sqrt(lo ** 2 / 4 + g ** 2)
        hi = np.sqrt((c * np.sqrt(2) / SNR_FAINT) ** 2 + f ** 2)
        hi2 = np.sqrt(4 * hi ** 2 + g ** 2)  # scatter at the reduced chi2 limit 4
        print(f"  {solver}: brightest one pair {lo.min():.3g} nm (4 pairs {lo4.min():.3g}); "
              f"faintest one pair {hi.max():.4g} nm, scattered combination {hi2.max():.4g} nm")
    ctl = KalmanOFC(OpticalModel("bundled"))
    z0 = ctl.model.at(0.0).intrinsic_nm
    rng = np.random.default_rng(5)
    base = z0 + rng.normal(0, 10.0, 76)
    res = ctl.step(base, uncertainty_nm=np.full(76, 15.0), stamp_ns=1, dry_run=True)
    print(f"  genuine nominal visit: |correction| {np.linalg.norm(res.dof):.4g} "
          f"(predicted field rms {res.predicted_field_rms_nm:.1f} nm)")
    for umax in (2000.0,):
        u = np.full(76, 15.0)
        u[:19] = umax
        for off in (5000.0, 10000.0):
            z = base.copy()
            z[:19] += off
            r = ctl.step(z, uncertainty_nm=u, stamp_ns=1, dry_run=True)
            print(f"  R00 + {off:g} nm every term claiming {umax:g} nm: valid {r.valid}, "
                  f"|correction| {np.linalg.norm(r.dof):.4g}, largest |step| / max_step "
                  f"{np.max(np.abs(r.dof) / np.where(ctl.max_step > 0, ctl.max_step, 1)):.3g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", default=["repeats", "tampering", "claims"])
    ap.add_argument("--pairs", type=int, default=2000, help="noise-model pairs per S/N")
    ap.add_argument("--states", type=int, default=10, help="states per stroke fraction")
    ap.add_argument("--no-estimates", action="store_true", help="repeats: noise model only")
    a = ap.parse_args()
    rng = np.random.default_rng(2026)
    t0 = time.time()
    if "repeats" in a.sections:
        bench_repeats_model(a.pairs, rng)
        if not a.no_estimates:
            bench_repeats_estimates(rng)
    if "tampering" in a.sections:
        bench_tampering(a.states, rng)
    if "claims" in a.sections:
        bench_claims()
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    import sys
    from pathlib import Path

    from cwfs_ros.runtime.threads import limit_blas_threads

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    limit_blas_threads()
    main()
