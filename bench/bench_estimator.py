#!/usr/bin/env python
"""Accuracy and speed of the core wavefront estimator (issue: core estimator).

Prints the figures quoted in the README.  Sections (all by default):

  zemax     120-px ZEMAX pairs against the original code's outputs
  fam       the 25 FAM ZEMAX pairs against the ZEMAX truth (g band, 500 nm)
  gram      Gram matrix of Z4-Z22 on the vignetted pupils (paper §3.3), and FAM with the
            feedback truncated in the basis orthonormalised on that pupil
  batoid    on-axis ray-traced pairs of randomly perturbed telescopes (Poisson noise)
  linearity single terms 0-1.5 um on the paraxial f/1.23 lens, 1 mm
  speed     wall time per estimate, 160x160, 14 outer iterations, warm and first call

Usage: .venv/bin/python bench/bench_estimator.py [section ...] [--solvers exp,fft,lsq]
       [--data ../shared/data/zemax-lsst]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # "one core", as the targets say

import numpy as np  # noqa: E402

from cwfs_ros.wfs import estimate_wavefront, load_instrument  # noqa: E402
from cwfs_ros.wfs.io import read_image  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def bench_zemax(data: Path, solvers: list[str]) -> None:
    print("\n== 120-px ZEMAX pairs vs the original code's outputs (max |diff| over Z4-Z22, nm)")
    cases = [("F1.23_1mm_v61", "z7_0.25", "paraxial", (0.0, 0.0), 7),
             ("LSST_C_SN26", "z7_0.25", "lsst_analytic", (0.0, 0.0), 7),
             ("LSST_NE_SN25", "z11_0.25", "lsst", (1.185, 1.185), 11),
             ("LSST_NE_SN25", "z11_0.25", "lsst_poly10", (1.185, 1.185), 11)]
    for folder, stem, inst, field, j in cases:
        intra = read_image(data / folder / f"{stem}_intra.txt")
        extra = read_image(data / folder / f"{stem}_extra.txt")
        for solver in solvers:
            refs = {}
            for kind in ("exp", "fft"):
                p = data / "reference-outputs" / f"{folder}_{stem}_{kind}.txt"
                if p.exists():
                    refs[kind] = np.loadtxt(p)
            r = estimate_wavefront(intra, extra, field_intra_deg=field, field_extra_deg=field,
                                   instrument=inst, defocal_offset_mm=1.0, solver=solver)
            # The original code's off-axis mode reports the departure from design.
            est = r.zernikes_nm - r.intrinsic_nm
            diffs = "  ".join(f"vs ref-{k}: {np.abs(est - v).max():5.1f}"
                              for k, v in refs.items())
            print(f"  {folder:14s} {inst:13s} {solver}: Z{j} = {est[j - 4]:8.1f}  {diffs}"
                  f"  caustic={r.caustic}")


def bench_fam(data: Path, solvers: list[str], **algorithm) -> None:
    print("\n== FAM: 25 ZEMAX pairs vs ZEMAX truth (band g, 500 nm, 1.5 mm)"
          + (f" {algorithm}" if algorithm else ""))
    rows = [ln.split() for ln in (data / "FAM" / "ccdCenterTestImg.txt").read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]
    for solver in solvers:
        per_field, worst = [], []
        t = []
        for fx, fy, raft, sensor in rows:
            tag = f"R{raft}_S{sensor}"
            intra = read_image(data / "FAM" / f"Image_intra_{tag}.txt")
            extra = read_image(data / "FAM" / f"Image_extra_{tag}.txt")
            truth = np.loadtxt(data / "FAM" / f"zn_{tag}.txt")[3:22] * 500.0
            f = (float(fx), float(fy))
            r = estimate_wavefront(intra, extra, field_intra_deg=f, field_extra_deg=f, band="g",
                                   wavelength_nm=500.0, solver=solver, **algorithm)
            e = r.zernikes_nm - truth
            per_field.append(rms(e))
            worst.append(np.abs(e).max())
            t.append(r.wall_time_s - r.geometry_time_s)
        pf = np.array(per_field)
        centre = pf[[i for i, row in enumerate(rows) if row[2:] == ["22", "11"]][0]]
        print(f"  {solver}: per-field RMS median {np.median(pf):.2f}  max {pf.max():.2f}  "
              f"worst term {max(worst):.1f}  centre {centre:.2f} nm   "
              f"(targets: median<=5, max<=10, term<=25, centre<=3.5)")
        print("       per field: " + " ".join(f"{v:.1f}" for v in pf))


def bench_gram(data: Path, solvers: list[str]) -> None:
    import yaml

    from cwfs_ros.config import config_dir
    from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
    from cwfs_ros.wfs.zernike import gram_summary

    print("\n== Gram matrix of Z4-Z22 over the pupil (area average; identity on a full annulus)")
    inst = load_instrument("lsst")
    corners = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())[
        "corners"]
    cases = [("on axis", "g", 500.0, (0.0, 0.0), (0.0, 0.0)),
             ("FAM R43_S11 (1.58 deg)", "g", 500.0, (1.41111111, 0.70555556)),
             ("FAM R34_S12 (1.79 deg)", "g", 500.0, (0.70555556, 1.64583333))]
    cases = [c if len(c) == 5 else (*c, c[3]) for c in cases]
    for name, geo in corners.items():
        cases.append((f"corner {name} split", "r", 622.0, tuple(geo["intra"]["field_deg"]),
                      tuple(geo["extra"]["field_deg"])))
    for label, band, wl, fi, fe in cases:
        g = pair_geometry(inst, band, wl, fi, fe, 1.5, load_algorithm("exp"))
        off, cond = gram_summary(np.asarray(g.gram_common)[3:22, 3:22])
        r = np.hypot(g.x, g.y)
        frac = g.mask_common.sum() / ((r <= 1) & (r >= inst.obscuration)).sum()
        print(f"  {label:24s} common pupil {frac:6.1%} of the annulus: max |off-diagonal| "
              f"{off:.3f}, condition number {cond:.2f}")
    print("  (the same on the sampled full annulus: max |off-diagonal| ~0.02 from the "
          "pixel-grid edge, 1e-14 with exact quadrature)")
    bench_fam(data, solvers, feedback_basis="orthonormal")


def bench_batoid(solvers: list[str], n: int) -> None:
    from cwfs_ros.sim.render import render_donut, true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    print(f"\n== on-axis ray-traced pairs: {n} random rigid-body perturbations, r band, "
          "1e6 photons, sky 50/px, Poisson, few-px offsets")
    rng = np.random.default_rng(2026)
    errs: dict[str, list[float]] = {s: [] for s in solvers}
    totals = []
    for _ in range(n):
        while True:  # draw until the total wavefront is 300-900 nm rms (sqrt sum of squares)
            dof = np.zeros(50)
            dof[:10] = rng.normal(0, 1, 10) * [15, 300, 300, 0.01, 0.01, 15, 300, 300, 0.01, 0.01]
            tel = perturbed_telescope(dof, band="r")
            truth = true_zernikes_nm(tel, (0.0, 0.0), wavelength_nm=622.0)
            tot = float(np.sqrt(np.sum(truth**2)))
            if 300 <= tot <= 900:
                break
        totals.append(tot)
        imgs = [render_donut(tel, (0.0, 0.0), dz, wavelength_nm=622.0, npix=160,
                             n_photons=1e6, sky_per_pixel=50.0, subtract_sky=True,
                             offset_px=tuple(rng.uniform(-3, 3, 2)), rng=rng)
                for dz in (-1.5, 1.5)]
        for s in solvers:
            r = estimate_wavefront(*imgs, field_intra_deg=(0, 0), field_extra_deg=(0, 0),
                                   solver=s)
            errs[s].append(rms(r.zernikes_nm - truth))
    print(f"  total wavefront {min(totals):.0f}-{max(totals):.0f} nm")
    for s, e in errs.items():
        print(f"  {s}: RMS error median {np.median(e):.1f}  max {np.max(e):.1f} nm  "
              "(target <= 15)")


def bench_linearity(solvers: list[str]) -> None:
    from cwfs_ros.sim.paraxial import render_paraxial_pair

    print("\n== linearity: single terms on the paraxial f/1.23 lens, 1 mm, 5e6 photons; "
          "largest amplitude (um) up to which every step 0.25..1.5 um is recovered within 5% "
          "(or 10 nm, the photon-noise floor, whichever is larger); 0 = fails at 0.25 um")
    inst = load_instrument("paraxial")
    amps = np.array([0.25, 0.5, 0.75, 1.0, 1.25, 1.5]) * 1000.0
    for s in solvers:
        line = []
        for j in range(4, 23):
            ok_to = 0.0
            for a in amps:
                i, e = render_paraxial_pair(inst, {j: a}, npix=120, n_photons=5e6,
                                            rng=np.random.default_rng(j))
                r = estimate_wavefront(i, e, field_intra_deg=(0, 0), field_extra_deg=(0, 0),
                                       instrument=inst, solver=s)
                if r.caustic or abs(r.zernikes_nm[j - 4] - a) > max(0.05 * a, 10.0):
                    break
                ok_to = a / 1000.0
            line.append(f"Z{j}:{ok_to:g}")
        print(f"  {s}: " + " ".join(line))


def bench_speed(solvers: list[str]) -> None:
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    print("\n== speed: 160x160 LSST on-axis pair, 14 outer iterations, one BLAS thread")
    tel = perturbed_telescope(np.zeros(50), band="r")
    rng = np.random.default_rng(0)
    imgs = [render_donut(tel, (0, 0), dz, wavelength_nm=622.0, npix=160, n_photons=1e6,
                         rng=rng) for dz in (-1.5, 1.5)]
    for s in solvers:
        kw = dict(field_intra_deg=(0, 0), field_extra_deg=(0, 0), solver=s, tolerance_nm=0.0)
        estimate_wavefront(*imgs, **kw)
        ts = []
        for _ in range(40):
            t0 = time.perf_counter()
            estimate_wavefront(*imgs, **kw)
            ts.append(time.perf_counter() - t0)
        print(f"  {s}: median {np.median(ts) * 1e3:.1f} ms  p90 {np.percentile(ts, 90) * 1e3:.1f}"
              f" ms  (targets: exp<=20, fft<=60)")
    code = ("import time,numpy as np;t=time.perf_counter();"
            "from cwfs_ros.wfs import estimate_wavefront;"
            "d=np.load('/tmp/_cwfs_pair.npy');"
            "t1=time.perf_counter();r=estimate_wavefront(d[0],d[1],field_intra_deg=(0.3,-0.2),"
            "field_extra_deg=(0.3,-0.2));t2=time.perf_counter();"
            "print(f'{t1-t:.3f} {t2-t1:.3f} {r.geometry_time_s:.3f}')")
    np.save("/tmp/_cwfs_pair.npy", np.array(imgs))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    print(f"  first call in a fresh process: import {out[0]} s, first estimate {out[1]} s "
          f"(geometry {out[2]} s; target <= 1 s)")
    bench_new_fields(solvers)


def bench_new_fields(solvers: list[str], n: int = 10) -> None:
    """Geometry of a pair at new star fields on corner R00's half-chips, in a warm process.

    The first new field of a process also builds the field-independent fit operator and the
    design-wavefront tile of its mid-point (once per pupil grid / 0.125 deg tile); the median
    over ``n`` further random fields is the per-visit cost.
    """
    from threadpoolctl import threadpool_limits

    from cwfs_ros.frames.field_position import load_half_chips
    from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
    from cwfs_ros.wfs.instrument import load_instrument

    h = load_half_chips()["R00"]
    inst = load_instrument("lsst")
    fi0, fe0 = np.array(h["intra"].field_deg), np.array(h["extra"].field_deg)
    rng = np.random.default_rng(1)
    print(f"  new star fields (corner R00, {n} random pairs of fields on its half-chips), "
          "geometry build:")
    for s in solvers:
        algo = load_algorithm(s)
        with threadpool_limits(1):
            t0 = time.perf_counter()
            pair_geometry(inst, "r", 622.0, tuple(fi0), tuple(fe0), 1.5, algo)
            first = time.perf_counter() - t0
            ts = []
            for _ in range(n):
                d = rng.uniform([-0.03, -0.06, -0.03, -0.06], [0.03, 0.06, 0.03, 0.06])
                fi, fe = tuple(map(float, fi0 + d[:2])), tuple(map(float, fe0 + d[2:]))
                t0 = time.perf_counter()
                pair_geometry(inst, "r", 622.0, fi, fe, 1.5, algo)
                ts.append(time.perf_counter() - t0)
        print(f"    {s}: median {np.median(ts) * 1e3:.0f} ms  max {max(ts) * 1e3:.0f} ms  "
              f"(first in the process {first * 1e3:.0f} ms)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*",
                    default=["zemax", "fam", "batoid", "linearity", "speed"])
    ap.add_argument("--solvers", default="exp,fft,lsq")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "zemax-lsst")
    ap.add_argument("--n-batoid", type=int, default=10)
    a = ap.parse_args()
    solvers = a.solvers.split(",")
    t0 = time.perf_counter()
    for sec in a.sections:
        {"zemax": lambda: bench_zemax(a.data, solvers),
         "fam": lambda: bench_fam(a.data, solvers),
         "gram": lambda: bench_gram(a.data, solvers),
         "batoid": lambda: bench_batoid(solvers, a.n_batoid),
         "linearity": lambda: bench_linearity(solvers),
         "speed": lambda: bench_speed(solvers)}[sec]()
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
