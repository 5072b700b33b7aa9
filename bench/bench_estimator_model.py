#!/usr/bin/env python
"""The controller's measurement model as the wavefront estimator reads it (rotator angle 0).

The Kalman controller models a visit as ``r = H x + n``, with ``H`` the true-optics
sensitivity of the corners' Z4-Z22 and the design wavefront subtracted. The estimator does
not report the true Z4-Z22: wavefront beyond Z22 (mostly from bending modes the corners
barely see in Z4-Z22) is read into Z4-Z22, so the loop chases a bias with the modes it sees
(bench_bending_bias.py). Here the model is replaced by what the estimator reports:

* ``H_est`` (76 x 50): central differences through the estimator. Each DoF is stepped by
  ``±s`` with ``s`` giving ``STEP_NM`` rss of Z4-Z37 at the worst corner (batoid), each
  corner's split pair rendered noise-free (quasi-random pupil, no Poisson noise, 0.7 arcsec
  seeing, ``N_RAYS`` rays) with the same random numbers for ``+s`` and ``-s``, and estimated
  with the shipped lsq solver. A subset of DoF is also stepped by ``±2s`` (linearity).
* the estimator's reading of the design (mean of ``NOMINAL_SEEDS`` renders), in place of
  the design wavefront.
* the aliasing fit: per corner, ``H_est - H = A H_23..37`` by least squares over the 50
  columns (``A``: 19 x 15), the form a model at any rotator angle would need.

Then the in-process image loop (one split pair per corner, 1e6 photons, 0.7 arcsec seeing,
±3 px offsets, sky 50 e/pixel, as camera_sim) runs the closed-loop benchmark's seed-1 starts
with the shipped model and with the estimator's, and prints the field error per visit and
the reduction ``v1 / min(v2..v4)``.

``response`` is the model ofc_node ships as ``measurement_model: estimator``: the same idea
for any rotator angle, from the estimator's measured response to single Zernike terms
(``config/ofc/estimator_response_r.npz``). It needs no ``H_est``; with ``--angle`` the loop
runs with the camera turned (``shipped`` and ``response`` only).

The figures are in docs/closed-loop.md, "The measurement model ``estimator``". Building
``H_est`` takes about 35 min; one image-loop visit 40-60 s.

Usage: .venv/bin/python bench/bench_estimator_model.py [--cache out/estimator_model.npz]
       [--classes bending rigid mixed] [--visits 6] [--seed 1]
       [--models shipped estimator estimator_h estimator_design estimator_bending response]
       [--angle 0]
The matrix is cached (and resumed) in ``--cache``; the loops take about 5 min per class
and model.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from cwfs_ros import layout
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.kalman import KalmanOFC
from cwfs_ros.ofc.model import ModelAtAngle, OpticalModel
from cwfs_ros.ofc.rotation import telescope_field_deg
from cwfs_ros.runtime.corner_pool import stamp_uncertainty_nm
from cwfs_ros.sim.perturbation import stroke_perturbation
from cwfs_ros.sim.render import render_donut, true_zernikes_nm
from cwfs_ros.sim.telescope import perturbed_telescope
from cwfs_ros.validation.loop_model import TruthModel
from cwfs_ros.validation.readings import ReadingSettings, corner_fields_deg, corner_reading_nm
from cwfs_ros.wfs import estimate_wavefront

WAVELENGTH_NM = 622.0
SEEING_ARCSEC = 0.7
N_RAYS = 2**19  # per donut of a finite difference (powers of 2 keep the Sobol balance)
NOMINAL_RAYS = 2**20
NOMINAL_SEEDS = (1, 2, 3)
STEP_NM = 70.0  # rss of Z4-Z37 at the worst corner per finite-difference step
JMAX_HIGH = 37
LINEARITY_DOF = (0, 5, 6, 10, 12, 20, 28, 30, 41, 45)
CLASS_COLUMN = {"rigid": 0, "bending": 1, "mixed": 2}


def corner_fields() -> list[tuple[tuple[float, float], tuple[float, float], tuple[float, float]]]:
    """Per corner (layout order): intra field, extra field, mid-point field [deg]."""
    return [corner_fields_deg(c) for c in layout.CORNERS]


def estimated_corners_nm(dof: np.ndarray, n_rays: int, seed: int) -> np.ndarray:
    """(76,) the estimator's Z4-Z22 at the four corners for a noise-free render of ``dof``
    (:func:`cwfs_ros.validation.readings.corner_reading_nm`: every donut uses
    ``default_rng(seed)``, so that differences between states are free of most of the
    sampling noise)."""
    tel = perturbed_telescope(np.asarray(dof, dtype=np.float64), band="r")
    settings = ReadingSettings(n_rays=n_rays, seed=seed, wavelength_nm=WAVELENGTH_NM,
                               seeing_arcsec=SEEING_ARCSEC)
    return np.concatenate([corner_reading_nm(tel, c, settings) for c in layout.CORNERS])


def true_corners_nm(dof: np.ndarray, jmax: int) -> np.ndarray:
    """(4, jmax - 3) batoid's Z4..Zjmax at the corners' mid-points [nm]."""
    tel = perturbed_telescope(np.asarray(dof, dtype=np.float64), band="r")
    return np.array([true_zernikes_nm(tel, mid, wavelength_nm=WAVELENGTH_NM, jmax=jmax)
                     for _, _, mid in corner_fields()])


def batoid_sensitivity(range_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 34, 50) batoid's Z4-Z37 sensitivity at the corners [nm per DoF unit], and the
    finite-difference step of each DoF (``STEP_NM`` of Z4-Z37 at the worst corner)."""
    h = np.zeros((4, JMAX_HIGH - 3, layout.N_DOF))
    for i in range(layout.N_DOF):
        e = np.zeros(layout.N_DOF)
        e[i] = 0.01 * range_[i]
        h[:, :, i] = (true_corners_nm(e, JMAX_HIGH) - true_corners_nm(-e, JMAX_HIGH)) / (2 * e[i])
    worst = np.sqrt((h**2).sum(axis=1)).max(axis=0)
    return h, STEP_NM / worst


def _fd_columns(cache: dict, i: int) -> None:
    """Fill DoF ``i``'s readings at ±step (and ±2 step for :data:`LINEARITY_DOF`)."""
    e = np.zeros(layout.N_DOF)
    e[i] = cache["step"][i]
    if not cache["done"][i]:
        cache["plus"][:, i] = estimated_corners_nm(e, N_RAYS, 1)
        cache["minus"][:, i] = estimated_corners_nm(-e, N_RAYS, 1)
        cache["done"][i] = True
    if i in LINEARITY_DOF and not cache["done2"][i]:
        cache["plus2"][:, i] = estimated_corners_nm(2 * e, N_RAYS, 1)
        cache["minus2"][:, i] = estimated_corners_nm(-2 * e, N_RAYS, 1)
        cache["done2"][i] = True


def build_estimator_model(path: Path) -> dict:
    """The finite-difference readings, the design reading and batoid's Z4-Z37 sensitivity,
    from ``path`` when there, else built (saved after every DoF, so a stopped build resumes)."""
    cache = dict(np.load(path)) if path.is_file() else {}
    if "h37" not in cache:
        cache["h37"], cache["step"] = batoid_sensitivity(C.load_dof_spec().range)
        for k in ("plus", "minus", "plus2", "minus2"):
            cache[k] = np.zeros((layout.N_ZK * layout.N_CORNERS, layout.N_DOF))
        cache["done"] = np.zeros(layout.N_DOF, bool)
        cache["done2"] = np.zeros(layout.N_DOF, bool)
    t0 = time.perf_counter()
    if "nominal" not in cache:
        cache["nominal"] = np.array([estimated_corners_nm(np.zeros(layout.N_DOF),
                                                          NOMINAL_RAYS, s)
                                     for s in NOMINAL_SEEDS])
        cache["nominal_fd"] = estimated_corners_nm(np.zeros(layout.N_DOF), N_RAYS, 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    for i in range(layout.N_DOF):
        if cache["done"][i] and (i not in LINEARITY_DOF or cache["done2"][i]):
            continue
        _fd_columns(cache, i)
        np.savez(path, **cache)
        print(f"   DoF {i}: {time.perf_counter() - t0:.0f} s so far", flush=True)
    np.savez(path, **cache)
    return cache


def h_est(cache: dict) -> np.ndarray:
    """(76, 50) the estimator's sensitivity [nm per DoF unit]."""
    return (cache["plus"] - cache["minus"]) / (2 * cache["step"][None, :])


def report_model(cache: dict) -> None:
    """Per DoF, the column of H and of H_est at the step; linearity; the aliasing fit."""
    names = C.load_dof_spec().names
    step, h37 = cache["step"], cache["h37"]
    hb = C.sensitivity_for_source("bundled").matrix_nm
    he = h_est(cache)
    design = true_corners_nm(np.zeros(layout.N_DOF), 22).reshape(-1)

    def per_corner(v: np.ndarray) -> np.ndarray:
        return np.sqrt((v.reshape(layout.N_CORNERS, layout.N_ZK) ** 2).sum(axis=1))

    off = per_corner(cache["nominal"].mean(axis=0) - design)
    print("design reading - batoid design, rss per corner [nm]: "
          + " ".join(f"{x:5.1f}" for x in off))
    print("DoF        |H s|  |H_est s|  |H_est s - H s|  |Z23-37 s|   (nm, worst corner)")
    for i in range(layout.N_DOF):
        hi = np.sqrt((h37[:, layout.N_ZK:, i] ** 2).sum(axis=1)).max() * step[i]
        print(f"{names[i]:9s} {per_corner(hb[:, i]).max() * step[i]:6.1f} "
              f"{per_corner(he[:, i]).max() * step[i]:9.1f} "
              f"{per_corner(he[:, i] - hb[:, i]).max() * step[i]:15.1f} {hi:10.1f}")
    for i in LINEARITY_DOF:
        d1 = (cache["plus"][:, i] - cache["minus"][:, i]) / 2
        d2 = (cache["plus2"][:, i] - cache["minus2"][:, i]) / 4
        print(f"linearity {names[i]:9s}: |FD(s)| {np.linalg.norm(d1):6.1f}  |FD(2s)/2| "
              f"{np.linalg.norm(d2):6.1f}  |difference| {np.linalg.norm(d1 - d2):5.1f} nm")
    for c in range(layout.N_CORNERS):
        rows = slice(c * layout.N_ZK, (c + 1) * layout.N_ZK)
        y = (he[rows] - hb[rows]) * step
        x = h37[c, layout.N_ZK:, :] * step
        a, *_ = np.linalg.lstsq(x.T, y.T, rcond=None)
        print(f"aliasing fit, corner {c}: |H_est - H| {np.linalg.norm(y):6.1f} nm, after "
              f"A H_23..37 {np.linalg.norm(y - a.T @ x):6.1f} nm (50 steps)")


class EstimatorModel(OpticalModel):
    """The bundled model, except at rotator angle 0: ``H_est`` and the design reading."""

    def __init__(self, h_est_nm: np.ndarray, design_reading_nm: np.ndarray) -> None:
        super().__init__("bundled")
        self.h_est_nm = np.ascontiguousarray(h_est_nm, dtype=np.float64)
        self.design_reading_nm = np.ascontiguousarray(design_reading_nm, dtype=np.float64)

    def _build(self, angle_deg: float) -> ModelAtAngle:
        if angle_deg != 0:
            raise NotImplementedError("the estimator's model is measured at angle 0 only")
        return replace(super()._build(angle_deg), H=self.h_est_nm,
                       intrinsic_nm=self.design_reading_nm)


MODELS = ("shipped", "estimator", "estimator_h", "estimator_design", "estimator_bending",
          "response")


def make_model(name: str, cache: dict) -> OpticalModel:
    """The controller's model ``name`` (:data:`MODELS`): the shipped one, or the estimator's
    in whole or in part, to tell what each half does."""
    if name == "shipped":
        return OpticalModel("bundled")
    if name == "response":
        return OpticalModel("bundled", measurement="estimator")
    at0 = OpticalModel("bundled").at(0.0)
    h, design = h_est(cache), cache["nominal"].mean(axis=0)
    if name == "estimator_h":
        design = at0.intrinsic_nm
    elif name == "estimator_design":
        h = at0.H
    elif name == "estimator_bending":
        h = np.where(np.arange(layout.N_DOF) >= 10, h, at0.H)
    return EstimatorModel(h, design)


def run_image_loop(kind: str, seed: int, visits: int, model: OpticalModel,
                   truth: TruthModel, angle_deg: float = 0.0) -> list[float]:
    """Field error [nm] per visit of the in-process image loop (before each correction), the
    camera turned by ``angle_deg`` (the stars at the telescope fields the turned corners see,
    the images and the fields the estimator is given in the camera frame)."""
    theta = np.deg2rad(angle_deg)
    target = float(np.random.default_rng(2026).uniform(300.0, 1000.0, (5, 3))
                   [seed, CLASS_COLUMN[kind]])
    dof = stroke_perturbation(kind, 1000 + seed, target)
    rng = np.random.default_rng(100 + seed)
    ctl = KalmanOFC(model)
    field_nm = []
    for v in range(visits):
        field_nm.append(truth.field_error_nm(dof))
        tel = perturbed_telescope(dof, band="r", rotator_angle_deg=angle_deg)
        meas, unc = [], []
        for fi, fe, _ in corner_fields():
            imgs = [render_donut(tel, tuple(telescope_field_deg(f, theta)[0]), dz,
                                 wavelength_nm=WAVELENGTH_NM, npix=160,
                                 n_photons=1e6, sky_per_pixel=50, subtract_sky=True, rng=rng,
                                 seeing_fwhm_arcsec=SEEING_ARCSEC,
                                 offset_px=tuple(rng.uniform(-3, 3, 2)))
                    for f, dz in ((fi, -1.5), (fe, 1.5))]
            r = estimate_wavefront(*imgs, field_intra_deg=fi, field_extra_deg=fe,
                                   solver="lsq", seeing_fwhm_arcsec=SEEING_ARCSEC)
            meas.append(r.zernikes_nm)
            unc.append(stamp_uncertainty_nm(r, "lsq"))
        res = ctl.step(np.concatenate(meas), uncertainty_nm=np.concatenate(unc),
                       stamp_ns=(v + 1) * 40_000_000_000, rotator_angle_deg=angle_deg)
        if res.valid:
            dof = dof + res.dof
    return field_nm


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", type=Path, default=Path("out/estimator_model.npz"))
    p.add_argument("--classes", nargs="*", default=["bending", "rigid", "mixed"])
    p.add_argument("--models", nargs="*", default=["shipped", "estimator"], choices=MODELS,
                   help="shipped; estimator (H_est and the design reading); estimator_h "
                        "(H_est only); estimator_design (the design reading only); "
                        "estimator_bending (H_est in the bending columns only, and the "
                        "design reading)")
    p.add_argument("--visits", type=int, default=6)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--angle", type=float, default=0.0,
                   help="rotator angle [deg]; the models measured at 0 only (all but shipped "
                        "and response) need 0")
    args = p.parse_args()
    cache = {}
    if set(args.models) - {"shipped", "response"}:
        t0 = time.perf_counter()
        cache = build_estimator_model(args.cache)
        print(f"estimator model ready in {time.perf_counter() - t0:.0f} s", flush=True)
        report_model(cache)
    truth = TruthModel()
    for kind in args.classes:
        for name in args.models:
            model = make_model(name, cache)
            f = run_image_loop(kind, args.seed, args.visits, model, truth, args.angle)
            print(f"{kind:8s} seed {args.seed} rotator {args.angle:g} {name:9s}: field "
                  + " ".join(f"{x:4.0f}" for x in f)
                  + f" nm; reduction {f[0] / min(f[1:4]):4.1f}x", flush=True)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
