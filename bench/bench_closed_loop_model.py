#!/usr/bin/env python
"""Closed-loop figures of the controllers against batoid's telescope, measurements drawn from
the estimator's noise model (no images): floor and creep over long runs, hexapod-only masks,
the camera rotator, the model mismatch, and the controller's time per visit.

Each visit: the true corner wavefront of the perturbed telescope (batoid, camera frame at the
rotator angle) plus Gaussian noise of ``--noise`` nm per term (the per-term 1-sigma the
wavefront node reports for a corner at 1e6 photons, README Accuracy) is given to the
controller, and its correction is applied. The figure is the true wavefront error over the
science field (31 Gaussian-quadrature points, design removed); the corner figure is printed
beside it. ``kalman`` is the shipped default (config/params.yaml); ``pid`` is ts_ofc's scheme
with ts_ofc's gains (kp 0.18, ki 0.022, range-fwhm weights, 12 modes).

Usage: .venv/bin/python bench/bench_closed_loop_model.py [--long-visits 50] [--seeds 5]
       [--noise 15] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cwfs_ros import layout
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.kalman import KalmanOFC
from cwfs_ros.ofc.model import OpticalModel
from cwfs_ros.sim.perturbation import stroke_perturbation
from cwfs_ros.validation.loop_model import LoopTrace, TruthModel, run_model_loop

GROUPS = {"M2 hexapod": slice(0, 5), "camera hexapod": slice(5, 10),
          "M1M3 bending": slice(10, 30), "M2 bending": slice(30, 50)}


def perturbation(kind: str, seed: int, target_nm: float) -> np.ndarray:
    """The closed-loop issue's classes (:func:`cwfs_ros.sim.perturbation.stroke_perturbation`)
    scaled to ``target_nm`` of corner wavefront error."""
    return stroke_perturbation(kind, seed, target_nm)


def pid() -> C.OFCSolver:
    return C.OFCSolver(C.sensitivity_for_source("bundled"), kp=0.18, ki=0.022)


def kalman(source: str = "bundled", mask: np.ndarray | None = None) -> KalmanOFC:
    return KalmanOFC(OpticalModel(source), dof_mask=mask)


def row(label: str, tr: LoopTrace, shown: int = 10) -> str:
    f = tr.field_nm
    return (f"{label:<40} " + " ".join(f"{x:6.0f}" for x in f[:shown])
            + f"   x{f[0] / min(f[1:4]):5.1f} within 4 visits"
            + ("" if all(tr.valid) else f"  ({sum(not v for v in tr.valid)} refused)"))


def creep(tr: LoopTrace, start: int = 10) -> dict[str, tuple[float, float]]:
    """Per DoF group: RMS of the state in range units, mean over visits 10-20 and 40-50."""
    rng = C.load_dof_spec().range
    s = np.array(tr.states) / rng[None, :]
    out = {}
    for name, sl in GROUPS.items():
        v = np.sqrt(np.mean(s[:, sl] ** 2, axis=1))
        out[name] = (float(np.mean(v[start:start + 10])), float(np.mean(v[-10:])))
    return out


def long_runs(a: argparse.Namespace, truth: TruthModel) -> None:
    print(f"\n== floor and creep, {a.long_visits} visits, one seed per class, noise "
          f"{a.noise:g} nm per term (field error, nm; floor = mean of visits 10-{a.long_visits})")
    for kind in ("rigid", "bending", "mixed"):
        start = perturbation(kind, 100, 600.0)
        res = {}
        for name, ctl in (("kalman", kalman()), ("pid (ts_ofc)", pid())):
            tr = run_model_loop(ctl, start, a.long_visits, truth=truth, noise_nm=a.noise,
                                seed=7)
            res[name] = tr
            print(row(f"{kind} {name}", tr) + f"   floor {np.mean(tr.field_nm[9:]):6.1f}")
        fk, fp = (np.mean(res[n].field_nm[9:]) for n in ("kalman", "pid (ts_ofc)"))
        print(f"   floor ratio kalman / pid = {fk / fp:.2f} (target <= 0.6)")
        for name, tr in res.items():
            c = creep(tr)
            print(f"   {name:<14} state RMS / range, visits 10-20 -> last 10: "
                  + ", ".join(f"{g} {b:.3f}->{e:.3f}" for g, (b, e) in c.items()))


def short_runs(a: argparse.Namespace, truth: TruthModel) -> None:
    print(f"\n== shipped defaults, {a.seeds} seeds per class, 300-1000 nm, 6 visits")
    rng = np.random.default_rng(11)
    worst = {}
    for kind in ("rigid", "bending", "mixed"):
        for s in range(a.seeds):
            target = float(rng.uniform(300, 1000))
            tr = run_model_loop(kalman(), perturbation(kind, 200 + s, target), 6, truth=truth,
                                noise_nm=a.noise, seed=s)
            print(row(f"{kind} seed {s}, corner {target:.0f} nm", tr))
            worst[kind] = min(worst.get(kind, np.inf), tr.field_nm[0] / min(tr.field_nm[1:4]))
    print("   worst reduction within 4 visits: "
          + ", ".join(f"{k} x{v:.1f}" for k, v in worst.items()) + " (target >= 10)")


def variants(a: argparse.Namespace, truth: TruthModel) -> None:
    start = perturbation("rigid", 300, 800.0)
    print("\n== hexapod-only dof_mask, every other parameter as shipped, 6 visits")
    hex_mask = np.r_[np.ones(10, bool), np.zeros(40, bool)]
    for s in range(a.seeds):
        tr = run_model_loop(kalman(mask=hex_mask), perturbation("rigid", 400 + s, 800.0), 6,
                            truth=truth, noise_nm=a.noise, seed=s)
        print(row(f"hexapods only, seed {s}", tr) + f"   x{tr.reduction(6):.1f} within 5")
    print("\n== camera rotator (kalman, bundled; mixed start), 6 visits")
    mixed = perturbation("mixed", 500, 800.0)
    for ang in (0.0, 35.0, 90.0, -120.0):
        tr = run_model_loop(kalman(), mixed, 6, truth=truth, noise_nm=a.noise, seed=3,
                            angle_deg=ang)
        print(row(f"rotator {ang:+.0f} deg", tr))
    print("\n== the controller's model is not the simulator's (matrix_source), 6 visits")
    for src in ("bundled", "ts_ofc"):
        tr = run_model_loop(kalman(src), start, 6, truth=truth, noise_nm=a.noise, seed=4)
        print(row(f"kalman, matrix_source {src}", tr))


def creep_cause() -> None:
    """The bending creep of ts_ofc's scheme, isolated: a linear telescope (the bundled matrix
    is both truth and model), no noise, only hexapod decentres to correct."""
    print("\n== the creep's cause: decentres outside the 12 kept modes, linear truth, no noise")
    A = C.sensitivity_for_source("bundled").matrix_nm
    rng_ = C.load_dof_spec().range
    intr = C.intrinsic_vector_nm("r", C.corner_mid_field_points_deg())
    for name, ctl in (("pid (kp 0.6, ki 0)", C.OFCSolver(C.sensitivity_for_source("bundled"),
                                                         kp=0.6, ki=0.0)),
                      ("pid (ts_ofc gains)", pid()), ("kalman", kalman())):
        x = np.zeros(layout.N_DOF)
        x[[1, 2, 6, 7]] = [600.0, -450.0, -900.0, 500.0]
        bend, wf = [], []
        for k in range(50):
            y = intr + A @ x
            res = (ctl.step(y, uncertainty_nm=np.full(layout.N_MEAS, 15.0), stamp_ns=k + 1)
                   if isinstance(ctl, KalmanOFC) else ctl.step(y, stamp_ns=k + 1))
            x = x + res.dof
            bend.append(np.sqrt(np.mean((x[10:] / rng_[10:]) ** 2)))
            wf.append(np.mean(np.linalg.norm((A @ x).reshape(4, 19), axis=1)))
        print(f"{name:<20} bending RMS / range after visits 2, 5, 8, 20, 50: "
              + " ".join(f"{bend[i]:.3f}" for i in (1, 4, 7, 19, 49))
              + "; corner error: " + " ".join(f"{wf[i]:.0f}" for i in (1, 4, 7, 19, 49)))


def speed() -> None:
    ctl = kalman()
    at = ctl.model.at(0.0)
    rng = np.random.default_rng(0)
    times = []
    for k in range(200):
        y = at.intrinsic_nm + rng.normal(0, 15.0, layout.N_MEAS)
        angle = float(rng.uniform(-90, 90))  # a new bin most visits: the worst case
        t = time.perf_counter()
        ctl.step(y, uncertainty_nm=np.full(layout.N_MEAS, 15.0), stamp_ns=k + 1,
                 rotator_angle_deg=angle)
        times.append(time.perf_counter() - t)
    t = np.array(times) * 1e3
    print(f"\n== controller time per visit (200 visits, random rotator angles): median "
          f"{np.median(t):.1f} ms, p90 {np.percentile(t, 90):.1f} ms, max {t.max():.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-visits", type=int, default=50)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--noise", type=float, default=15.0)
    ap.add_argument("--quick", action="store_true", help="12 long visits, 2 seeds")
    a = ap.parse_args()
    if a.quick:
        a.long_visits, a.seeds = 12, 2
    t0 = time.perf_counter()
    truth = TruthModel()
    creep_cause()
    speed()
    variants(a, truth)
    short_runs(a, truth)
    long_runs(a, truth)
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
