#!/usr/bin/env python
"""What holds the bending starts of the closed loop at 45-80 nm over the field: the
estimator's bias at a state the loop has converged on.

For the closed-loop benchmark's seed-1 starts (bench_closed_loop.py: `stroke_perturbation`,
bending and rigid), the shipped Kalman controller is run against batoid's telescope with
noise-free measurements (the true corner wavefront) for 5 visits: the field error it reaches
is the floor of what the four corners cannot see. At that state, each corner's split pair is
rendered noise-free (quasi-random pupil sampling, no Poisson noise, 0.7 arcsec seeing) and
estimated with the shipped lsq solver (Z22 fit) and with the fit widened to Z28; the
estimate's distance from the true Z4-Z22 at the corner's mid-point is the estimator's bias.
A bias that does not average out over visits is what the loop then "corrects" with the modes
it sees.

Usage: .venv/bin/python bench/bench_bending_bias.py   (about 3 minutes)
"""

from __future__ import annotations

import numpy as np

from cwfs_ros import layout
from cwfs_ros.ofc.kalman import KalmanOFC
from cwfs_ros.ofc.model import OpticalModel
from cwfs_ros.sim.perturbation import stroke_perturbation
from cwfs_ros.sim.render import true_zernikes_nm
from cwfs_ros.sim.telescope import perturbed_telescope
from cwfs_ros.validation.loop_model import TruthModel, run_model_loop
from cwfs_ros.validation.readings import ReadingSettings, corner_fields_deg, corner_pair
from cwfs_ros.wfs import estimate_wavefront

WAVELENGTH_NM = 622.0
SEEING = 0.7
FITS = {"Z22 (shipped)": {},
        "Z28": dict(jmax=28, outer_iterations=18,
                    compensation_sequence=(4, 4, 6, 6, 13, 13, 13, 13, 22, 22, 28))}


def converged_state(kind: str, truth: TruthModel) -> tuple[np.ndarray, list[float]]:
    """The benchmark's seed-1 start of ``kind`` and the state after 4 noise-free corrections."""
    col = {"rigid": 0, "bending": 1}[kind]
    target = float(np.random.default_rng(2026).uniform(300.0, 1000.0, (5, 3))[1, col])
    start = stroke_perturbation(kind, 1001, target)
    tr = run_model_loop(KalmanOFC(OpticalModel("bundled")), start, 5, truth=truth,
                        noise_nm=1e-3, seed=1)
    return tr.states[-1], tr.field_nm


def corner_bias_nm(dof: np.ndarray) -> dict[str, list[float]]:
    """Per fit, the rss over Z4-Z22 of (noise-free estimate - truth) at each corner [nm]."""
    tel = perturbed_telescope(dof, band="r")
    settings = ReadingSettings(n_rays=4_000_000, seed=1, wavelength_nm=WAVELENGTH_NM,
                               seeing_arcsec=SEEING)
    out: dict[str, list[float]] = {k: [] for k in FITS}
    for corner in layout.CORNERS:
        fi, fe, mid = corner_fields_deg(corner)
        truth = true_zernikes_nm(tel, mid, wavelength_nm=WAVELENGTH_NM)
        imgs = corner_pair(tel, corner, settings)  # one render, read by each fit
        for name, kw in FITS.items():
            r = estimate_wavefront(*imgs, field_intra_deg=fi, field_extra_deg=fe,
                                   solver="lsq", seeing_fwhm_arcsec=SEEING, **kw)
            out[name].append(float(np.linalg.norm(r.zernikes_nm - truth)))
    return out


def main() -> None:
    truth = TruthModel()
    for kind in ("bending", "rigid"):
        dof, field = converged_state(kind, truth)
        print(f"{kind} seed 1: field error over visits 1-5 with exact measurements "
              + " ".join(f"{x:.0f}" for x in field) + " nm", flush=True)
        for name, rss in corner_bias_nm(dof).items():
            print(f"   estimator bias at the converged state, fit to {name:<14}: "
                  + " ".join(f"{x:5.1f}" for x in rss) + " nm rss per corner", flush=True)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
