#!/usr/bin/env python
"""Systematic error of each solver against atmospheric seeing, without noise.

Every other accuracy benchmark renders its donuts without seeing. On the sky a donut's edges
are blurred by ~0.6-1.0 arcsec FWHM. This benchmark measures what that does to the estimates
alone, without photon noise:

  axis   both donuts on axis                                    (truth there)
  same   both halves at the R00 SW0 field point                 (truth there)
  split  intra at R00 SW1, extra at SW0, as the corner sensor   (truth at the mid-point)

Each telescope is rendered noise-free: quasi-random pupil rays (``sampling="quasi"``,
``poisson=False``). The seeing is then applied as a Gaussian of the given FWHM, convolved with
the noise-free image. It is deterministic, so every figure is a bias and not a noise draw.
The renderer's own seeing option kicks each ray at random, which adds ray noise. The plate
scale comes from batoid at each field (``plate_scale_um_per_arcsec``). The telescopes are
the nominal design and ``--trials`` random M2/camera hexapod perturbations (drawn as
bench_frames.py draws them: 300-900 nm at the corner).

Prints the RMS error over Z4..Z22 and the worst single term (nm) per solver, geometry and
seeing, as the median over the telescopes.

Usage: .venv/bin/python bench/bench_seeing.py [--trials 2] [--seeing 0,0.4,0.7,1.0]
       [--variants exp,lsq-,lsq]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.ndimage import gaussian_filter  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_frames as bf  # noqa: E402

from cwfs_ros.sim.render import (  # noqa: E402
    corner_fields,
    plate_scale_um_per_arcsec,
    render_donut,
    true_zernikes_nm,
)
from cwfs_ros.sim.telescope import perturbed_telescope  # noqa: E402
from cwfs_ros.wfs import estimate_wavefront  # noqa: E402
from cwfs_ros.wfs.blur import FWHM_PER_SIGMA  # noqa: E402

WL = bf.WL
PIXEL_UM = 10.0


def telescopes(n: int, rng: np.random.Generator) -> list[tuple[str, object]]:
    """The design and ``n`` perturbed telescopes drawn as bench_frames.py draws them."""
    mid = corner_fields()["R00"]["mid"]
    out = [("nominal", perturbed_telescope(np.zeros(50), band="r"))]
    out += [(f"perturbed {k + 1}", bf.draw_telescope(rng, mid)[0]) for k in range(n)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2, help="perturbed telescopes (+ nominal)")
    ap.add_argument("--seeing", default="0,0.4,0.7,1.0", help="FWHM values, arcsec")
    ap.add_argument("--variants", default="exp,lsq-,lsq",
                    help="solvers; a trailing '-' turns the blur reference off (lsq- is lsq "
                         "as before it; README, Accuracy), a trailing '+' turns it on "
                         "(exp+)")
    ap.add_argument("--photons", type=float, default=4e6, help="rays of the quasi render")
    a = ap.parse_args()
    seeing = [float(s) for s in a.seeing.split(",")]
    solvers = a.variants.split(",")
    cf = corner_fields()["R00"]
    geoms = {"axis": ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0)),
             "same": (cf["extra"], cf["extra"], cf["extra"]),
             "split": (cf["intra"], cf["extra"], cf["mid"])}
    rng = np.random.default_rng(7)
    tels = telescopes(a.trials, rng)
    nominal = tels[0][1]
    rows: dict[tuple[str, str, float], list[np.ndarray]] = {}
    t0 = time.perf_counter()
    with threadpool_limits(1), warnings.catch_warnings():
        # Sobol' balance warning for a non-power-of-2 ray count: irrelevant here.
        warnings.simplefilter("ignore", UserWarning)
        for _name, tel in tels:
            for geo, (fi, fe, fm) in geoms.items():
                truth = (true_zernikes_nm(tel, fm, wavelength_nm=WL)
                         - true_zernikes_nm(nominal, fm, wavelength_nm=WL))
                sharp = [render_donut(tel, f, dz, wavelength_nm=WL, npix=160,
                                      n_photons=a.photons, poisson=False, sampling="quasi")
                         for f, dz in ((fi, -1.5), (fe, 1.5))]
                scales = [plate_scale_um_per_arcsec(tel, f, wavelength_nm=WL) for f in (fi, fe)]
                for fwhm in seeing:
                    imgs = [gaussian_filter(im, fwhm / FWHM_PER_SIGMA * s / PIXEL_UM,
                                            mode="constant") if fwhm > 0 else im
                            for im, s in zip(sharp, scales, strict=True)]
                    for solver in solvers:
                        kw = ({"blur_reference": solver.endswith("+")}
                              if solver[-1] in "+-" else {})
                        r = estimate_wavefront(*imgs, field_intra_deg=fi, field_extra_deg=fe,
                                               solver=solver.rstrip("+-"), wavelength_nm=WL,
                                               seeing_fwhm_arcsec=fwhm, **kw)
                        err = (r.zernikes_nm - r.intrinsic_nm) - truth
                        rows.setdefault((solver, geo, fwhm), []).append(err)
    print(f"{len(tels)} telescopes (nominal + {a.trials} perturbed), noise-free, seeing as a "
          f"Gaussian convolution; {time.perf_counter() - t0:.0f} s")
    print("RMS error over Z4..Z22 / worst single term (nm), median over the telescopes")
    head = "".join(f"{s:>15g}\"" for s in seeing)
    for solver in solvers:
        print(f"\n{solver:<6}{'geometry':<8}{head}")
        for geo in geoms:
            cells = []
            for fwhm in seeing:
                errs = np.array(rows[(solver, geo, fwhm)])
                rms = np.median(np.sqrt(np.mean(errs ** 2, axis=1)))
                worst = np.median(np.abs(errs).max(axis=1))
                cells.append(f"{rms:7.1f} / {worst:5.1f} ")
            print(f"{'':<6}{geo:<8}" + "".join(f"{c:>16}" for c in cells))
        # Which terms carry the bias at the worst seeing, on the split corner.
        e = np.mean(rows[(solver, "split", seeing[-1])], axis=0)
        top = np.argsort(-np.abs(e))[:4]
        print(f"{'':<6}split, {seeing[-1]:g}\", mean error of the largest terms: " +
              ", ".join(f"Z{k + 4} {e[k]:+.1f}" for k in top))


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
