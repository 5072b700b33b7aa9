"""Benchmark and health report of the OFC core (cwfs_ros.ofc.control).

Prints: load and solve times, the singular-value spectrum of the normalised sensitivity
matrix, how much of random rigid-body and bending perturbations a gain-1 solve recovers, the
least observable DoF combinations, and the closed-loop response of the default controller.

Usage: ``python bench/bench_control.py [--draws N] [--seed S]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cwfs_ros import layout  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402


def timed(fn, repeat: int) -> tuple[float, object]:
    """Median wall time (s) of ``fn()`` over ``repeat`` calls, and its last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def describe_physical(x: np.ndarray, spec: C.DofSpec, top: int = 4) -> str:
    """A DoF-space direction as fractions of each DoF's range, largest first."""
    frac = x / spec.range
    frac = frac / np.max(np.abs(frac))
    order = np.argsort(-np.abs(frac))[:top]
    return " ".join(f"{frac[i]:+.2f}*{spec.names[i]}" for i in order)


def recovered_fraction(s: C.OFCSolver, sm: C.SensitivityMatrix, sel: np.ndarray,
                       sigma: np.ndarray, draws: int, rng: np.random.Generator) -> dict:
    """Gain-1 recovery of random perturbations of the DoFs in ``sel`` (normalised units)."""
    ratio, proj, ratio_r, proj_r, explained = [], [], [], [], []
    rng_units = C.load_dof_spec().range
    for _ in range(draws):
        x = np.zeros(layout.N_DOF)
        x[sel] = rng.normal(0.0, sigma[sel])
        r = sm.matrix_nm @ x
        est = s.estimate(r)
        for scale, rat, prj in ((s.weights, ratio, proj), (rng_units, ratio_r, proj_r)):
            z_true, z_est = x / scale, est.dof_error / scale
            rat.append(np.linalg.norm(z_est) / np.linalg.norm(z_true))
            prj.append(z_est @ z_true / (z_true @ z_true))
        explained.append(1.0 - est.fit_residual_rms_nm / est.wavefront_rms_nm)
    return {k: np.percentile(v, [10, 50, 90]) for k, v in
            (("|z_est|/|z_true|  (w)", ratio), ("z_est.z_true/|z|^2 (w)", proj),
             ("|x/range| ratio", ratio_r), ("x.x_true/|x|^2 (range)", proj_r),
             ("wavefront explained", explained))}


def closed_loop(sm: C.SensitivityMatrix, x0: np.ndarray, n: int, **kw) -> np.ndarray:
    s = C.OFCSolver(sm, intrinsic_nm=np.zeros(sm.matrix_nm.shape[0]), **kw)
    x, rms = x0.copy(), []
    for _ in range(n):
        res = s.step(sm.matrix_nm @ x)
        x = x + res.dof
        rms.append(res.wavefront_rms_nm)
    return np.array(rms)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--weights", default="range-fwhm",
                    help="solver normalisation for the recovery section: range-fwhm|range|none")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    np.set_printoptions(precision=3, linewidth=110)

    t0 = time.perf_counter()
    sm = C.SensitivityMatrix.from_ts_ofc()
    t_load = time.perf_counter() - t0
    t_eval, _ = timed(C.SensitivityMatrix.from_ts_ofc, 3)
    spec = C.load_dof_spec()
    solver = C.OFCSolver(sm, band="r")
    y = C.intrinsic_vector_nm("r") + sm.matrix_nm @ np.where(np.arange(50) == 1, 200.0, 0.0)
    t_est, _ = timed(lambda: solver.estimate(y), 200)
    t_step, _ = timed(lambda: solver.step(y), 200)
    cold = C.OFCSolver(sm, band="r")
    t_cold, _ = timed(lambda: (cold._inverse_cache.clear(), cold.estimate(y)), 50)
    print("== timing")
    print(f"  first load (yaml parse + 50 DoubleZernike evals): {t_load * 1e3:8.1f} ms")
    print(f"  re-evaluate at 4 corners (yaml cached):           {t_eval * 1e3:8.1f} ms")
    print(f"  estimate, SVD cached:                              {t_est * 1e6:8.1f} us")
    print(f"  estimate, fresh SVD (new corner mask):             {t_cold * 1e6:8.1f} us")
    print(f"  full controller step:                              {t_step * 1e6:8.1f} us")

    print("\n== singular values, A x diag(w_range-fwhm) (ts_ofc normalisation), s/s0")
    rep = C.observability(sm, rel_tol=1e-6)
    print(f"  s0 = {rep.singular_values[0]:.4g} nm per normalised unit")
    print("  " + np.array2string(rep.relative, precision=2, separator=" ")[1:-1])
    for tol in (1e-3, 1e-4, 1e-5, 1e-6, 1e-7):
        print(f"  directions with s/s0 < {tol:.0e}: {int(np.sum(rep.relative < tol)):2d}")
    print(f"  12-mode effective condition number: {rep.relative[0] / rep.relative[11]:.3g}")

    print("\n== singular values, A x diag(range): nm (norm of the 76-vector) per full-range move")
    rng_rep = C.observability(sm, weights="range", rel_tol=1e-6)
    sv = rng_rep.singular_values
    print("  " + np.array2string(sv, precision=3, separator=" ", max_line_width=106)[1:-1])
    for thr in (100.0, 10.0, 1.0):
        print(f"  directions whose full-range excursion moves the corners < {thr:5.0f} nm: "
              f"{int(np.sum(sv < thr)):2d}")

    print("\n== least observable directions in the solver's range-fwhm normalised space")
    for k in range(49, 49 - 10, -1):
        print(f"  {rep.describe(k, spec.names)}")
    print("  ... and in the range basis (fractions of range a full-range move cannot show):")
    for k in range(49, 49 - 6, -1):
        x = rng_rep.weights * rng_rep.vt[k]
        print(f"  {sv[k]:8.3g} nm: {describe_physical(x, spec)}")

    print(f"\n== gain-1 recovery of random perturbations, 12-mode TSVD, weights {args.weights}"
          f" ({args.draws} draws, 10/50/90 %)")
    sigma = np.where(np.arange(50) < 10, 0.01, 0.2) * spec.range
    s12 = C.OFCSolver(sm, intrinsic_nm=np.zeros(76), weights=args.weights)
    groups = {
        "rigid body (1 % of range)": np.arange(10),
        "rigid, no camera dx/dy": np.array([0, 1, 2, 3, 4, 5, 8, 9]),
        "M1M3+M2 bending (20 % of range)": np.arange(10, 50),
        "bending modes 1-5 of each mirror": np.r_[10:15, 30:35],
    }
    for label, sel in groups.items():
        stats = recovered_fraction(s12, sm, sel, sigma, args.draws, rng)
        print(f"  {label}")
        for k, v in stats.items():
            print(f"    {k:<25} {v[0]:7.3f} {v[1]:7.3f} {v[2]:7.3f}")

    print("\n== closed loop (perfect sensing): M2 dx 200 um + cam dz 20 um + M1M3 B1 0.1 + M2 B2 "
          "0.05 um")
    x0 = np.zeros(50)
    x0[1], x0[5], x0[10], x0[31] = 200.0, 20.0, 0.1, 0.05
    for label, kw in (("PI kp 0.18 ki 0.022 (ts_ofc)", {}), ("P  kp 0.18", {"ki": 0.0}),
                      ("PI, no limits", {"max_step": None, "clip_range": None})):
        rms = closed_loop(sm, x0, 60, **kw)
        k_min = int(np.argmin(rms[:20]))
        print(f"  {label:<30} rms[0]={rms[0]:6.1f} min={rms[k_min]:6.1f} @visit {k_min:2d}"
              f"  max after={rms[k_min:].max():6.1f}  rms[59]={rms[-1]:6.1f} nm")
    kp, ki = 0.18, 0.022
    poles = np.roots([1.0, -(2 - kp - ki), 1 - kp])
    print(f"  PI error poles: {poles[0]:.3f}, {poles[1]:.3f} (|p| = {abs(poles[0]):.3f}); "
          f"non-oscillatory needs ki <= {(2 - kp - 2 * np.sqrt(1 - kp)):.4f}")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
