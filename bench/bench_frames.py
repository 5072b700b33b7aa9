#!/usr/bin/env python
"""Donut selection from corner half-chip frames, several pairs per corner, uncertainties.

Ray-traces random rigid-body perturbations of LSST (M2 and camera hexapods, 300-900 nm of
total wavefront at the corners), and for each renders the two half-chip frames of one corner
(default R00, 1000 x 2000 px each, focal-plane orientation) with 3-6 isolated donuts of
log-uniform brightness at their own field angles, plus one blended pair and one too-faint
star per frame, sky 50 e-/px and Poisson noise (cwfs_ros.sim.frames). Each corner is then
processed from its frames (cwfs_ros.frames.selection.estimate_corner_frames) and reports:

  selection   blended/faint stars rejected (and with which reason), isolated stars accepted,
              detected positions against the injected chief rays
  accuracy    RMS error over Z4..Z22 against the truth at the corner's reference field
              (cwfs_ros.sim.true_zernikes_nm), for the brightest single pair and for all pairs
  timing      ms per corner frame pair, detection included, one BLAS thread: "cold" (new star
              fields: the estimator builds a geometry per pair) and "warm" (same frames again)
  calibration fraction of |error| < 1 sigma over terms x trials, single pair and combined

The first --calib-trials trials fit the per-pair noise model (sigma_j^2 = (c_j q)^2 + f_j^2,
cwfs_ros.frames.combination.fit_noise_model) against the truth; the remaining trials are
evaluated with it (independent seeds). --write-config stores the fit in config/selection.yaml
(combination.noise_model.<solver>).

Usage: .venv/bin/python bench/bench_frames.py [--trials 16] [--calib-trials 14] [--solver lsq]
       [--write-config]   (the defaults are the reported run: ~8 min on 2 shared cores)
       [--timing-only]    (selection and timing of --trials trials, no noise-model fit)
       [--seeing 0.7]     (every star blurred by that FWHM in arcsec; the reported run: 0)
       [--estimator-seeing 0]  (the seeing the estimator is told; default --seeing)
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from cwfs_ros.config import config_dir  # noqa: E402
from cwfs_ros.frames.combination import (  # noqa: E402
    CombinationConfig,
    combine_pairs,
    fit_noise_model,
    pair_sigma_nm,
)
from cwfs_ros.frames.field_position import load_half_chips  # noqa: E402
from cwfs_ros.frames.selection import (  # noqa: E402
    estimate_corner_frames,
    load_selection_config,
)
from cwfs_ros.sim.frames import random_stars, render_frame  # noqa: E402
from cwfs_ros.sim.render import true_zernikes_nm  # noqa: E402
from cwfs_ros.sim.telescope import load_lsst, perturbed_telescope  # noqa: E402
from cwfs_ros.wfs.settings import EstimatorSettings  # noqa: E402

SCALE = np.array([8, 150, 150, 0.005, 0.005, 8, 150, 150, 0.005, 0.005])
WL = 622.0


def rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(v))))


def draw_telescope(rng: np.random.Generator, mid: tuple[float, float]):
    while True:
        dof = np.zeros(50)
        dof[:10] = rng.normal(0, 1, 10) * SCALE
        tel = perturbed_telescope(dof, band="r")
        tot = float(np.sqrt(np.sum(true_zernikes_nm(tel, mid, wavelength_nm=WL) ** 2)))
        if 300 <= tot <= 900:
            return tel, tot


def render_trial(k: int, args, halves):
    """Trial ``k``'s telescope, its total wavefront (nm) and the corner's two frames
    (``SimulatedFrame`` per side), all drawn from the trial's own seed."""
    rng = np.random.default_rng(args.seed + 1000 * k)
    tel, tot = draw_telescope(rng, halves["intra"].mid_deg)
    shape = (args.rows, args.cols)
    frames = {}
    for side in ("intra", "extra"):
        h = halves[side]
        stars = random_stars(rng, shape, n_good=(args.min_stars, args.max_stars),
                             flux_range=(args.flux_min, args.flux_max), blend=True, faint=True,
                             faint_flux=args.faint_flux)
        frames[side] = render_frame(tel, stars, field_ref_deg=h.field_deg,
                                    detector_offset_mm=h.detector_offset_mm, shape_px=shape,
                                    sky_per_pixel=args.sky, rng=rng,
                                    seeing_fwhm_arcsec=args.seeing)
    return tel, tot, frames


def run_trial(k: int, args, halves, settings, sel_cfg, nominal) -> dict:
    ref = halves["intra"].mid_deg
    t0 = time.perf_counter()
    tel, tot, frames = render_trial(k, args, halves)
    t_render = time.perf_counter() - t0
    with threadpool_limits(1):
        cold = estimate_corner_frames(frames["intra"].image, frames["extra"].image,
                                      corner=args.corner, settings=settings, config=sel_cfg)
        warm = estimate_corner_frames(frames["intra"].image, frames["extra"].image,
                                      corner=args.corner, settings=settings, config=sel_cfg)
    res = warm
    truth_ref = true_zernikes_nm(tel, ref, wavelength_nm=WL)
    # Selection outcome per injected star: the nearest detection within 40 px.
    sel = {"blend_rejected": 0, "blend": 0, "faint_rejected": 0, "faint": 0, "good": 0,
           "good_accepted": 0, "pos_err": [], "reasons": {}}
    for side in ("intra", "extra"):
        dets = res.detections[side]
        for s in frames[side].stars:
            near = [d for d in dets if np.hypot(d.x - s.x, d.y - s.y) < 40.0]
            acc = [d for d in near if d.ok]
            kind = "blend" if "blend" in s.flags else "faint" if "faint" in s.flags else "good"
            sel[kind] += 1
            if kind == "good":
                if acc:
                    sel["good_accepted"] += 1
                    d = min(acc, key=lambda d: np.hypot(d.x - s.x, d.y - s.y))
                    sel["pos_err"].append(float(np.hypot(d.x - s.x, d.y - s.y)))
            else:
                # Blend partners may be merged into one detection, or undetected: rejected
                # means no accepted detection near the injected star.
                if not acc:
                    sel[f"{kind}_rejected"] += 1
                for d in near:
                    if not d.ok:
                        sel["reasons"][f"{kind}:{d.status}"] = sel["reasons"].get(
                            f"{kind}:{d.status}", 0) + 1
    pairs = []
    for p in res.pairs:
        if p.status != "ok":
            continue
        t_mid = true_zernikes_nm(tel, p.field_mid_deg, wavelength_nm=WL)
        d_mid = true_zernikes_nm(nominal, p.field_mid_deg, wavelength_nm=WL)
        pairs.append({"departure": p.departure_nm, "q": p.noise_scale,
                      "truth_departure_mid": t_mid - d_mid, "snr": (p.snr_intra, p.snr_extra)})
    design_ref = true_zernikes_nm(nominal, ref, wavelength_nm=WL)
    return {"k": k, "tot": tot, "render_s": t_render, "cold_ms": cold.timing_ms,
            "warm_ms": warm.timing_ms, "n_pairs": res.n_pairs, "status": res.status,
            "pair_status": [p.status for p in res.pairs], "sel": sel, "pairs": pairs,
            "truth_ref": truth_ref, "design_ref": design_ref,
            "truth_departure_ref": truth_ref - design_ref}


class MachineReference:
    """The machine's speed: a warm lsq estimate of one on-axis 160-px pair (one BLAS
    thread, 14 outer iterations), timed on demand, to compare frame timings across machines
    (README Speed measured this kind of estimate at 6.1 ms on the machine of the earlier
    figures)."""

    def __init__(self) -> None:
        from cwfs_ros.sim.render import render_donut
        from cwfs_ros.sim.telescope import perturbed_telescope

        tel = perturbed_telescope(np.zeros(50), band="r")
        rng = np.random.default_rng(0)
        self.images = [render_donut(tel, (0, 0), dz, wavelength_nm=WL, npix=160,
                                    n_photons=2e5, rng=rng) for dz in (-1.5, 1.5)]
        self.kw = dict(field_intra_deg=(0, 0), field_extra_deg=(0, 0), solver="lsq",
                       tolerance_nm=0.0)

    def time_ms(self) -> float:
        """One estimate, timed after an untimed one (which builds its geometry if a caller
        cleared the caches, and brings its data back into the CPU caches)."""
        from cwfs_ros.wfs import estimate_wavefront

        with threadpool_limits(1):
            estimate_wavefront(*self.images, **self.kw)
            t0 = time.perf_counter()
            estimate_wavefront(*self.images, **self.kw)
            return (time.perf_counter() - t0) * 1e3


def machine_reference_ms(samples: int = 20) -> float:
    """Median of ``samples`` :class:`MachineReference` estimates."""
    ref = MachineReference()
    return float(np.median([ref.time_ms() for _ in range(samples)]))


def evaluate(trials: list[dict], comb: CombinationConfig) -> dict:
    one, many, z1, zn, n_used, unc1, uncn = [], [], [], [], [], [], []
    for t in trials:
        ps = t["pairs"]
        if not ps:
            continue
        dep = np.array([p["departure"] for p in ps])
        q = np.array([p["q"] for p in ps])
        c1 = combine_pairs(dep[:1], q[:1], design_ref_nm=t["design_ref"], config=comb)
        cn = combine_pairs(dep, q, design_ref_nm=t["design_ref"], config=comb)
        e1, en = c1.zernikes_nm - t["truth_ref"], cn.zernikes_nm - t["truth_ref"]
        one.append(rms(e1))
        many.append(rms(en))
        n_used.append(cn.n_pairs)
        z1.append(np.abs(e1) / c1.uncertainty_nm)
        zn.append(np.abs(en) / cn.uncertainty_nm)
        unc1.append(np.median(c1.uncertainty_nm))
        uncn.append(np.median(cn.uncertainty_nm))
    z1a, zna = np.concatenate(z1), np.concatenate(zn)
    return {"rms_1": np.array(one), "rms_n": np.array(many), "n_used": np.array(n_used),
            "cal_1": float(np.mean(z1a < 1.0)), "cal_n": float(np.mean(zna < 1.0)),
            "cal2_1": float(np.mean(z1a < 2.0)), "cal2_n": float(np.mean(zna < 2.0)),
            "unc_1": float(np.median(unc1)), "unc_n": float(np.median(uncn)),
            "n_terms": int(zna.size)}


def consistency(trials: list[dict], comb: CombinationConfig, seed: int = 5) -> None:
    """The pairs-agree test (``max_reduced_chi2``: the kept pairs' scatter, and no rival
    group among the rejected ones) on every trial's corner as simulated, and on the same
    corners (those with 4 pairs) with two pairs spoilt: each term of both moved by a normal
    draw times 3-10 times that pair's noise sigma, either the same draw for both (a shared
    cause: two groups of two) or one each."""
    rng = np.random.default_rng(seed)
    cases: dict[str, list] = {"as simulated": [], "2 spoilt alike": [], "2 spoilt apart": []}
    for t in trials:
        ps = t["pairs"]
        if len(ps) < 2:
            continue
        dep = np.array([p["departure"] for p in ps])
        q = np.array([p["q"] for p in ps])
        cases["as simulated"].append((t, dep, q))
        if len(ps) >= 4:
            sig = pair_sigma_nm(q, comb)
            bad = rng.choice(len(ps), 2, replace=False)
            for name, alike in (("2 spoilt alike", True), ("2 spoilt apart", False)):
                d2 = dep.copy()
                d2[bad] += (rng.normal(size=(1 if alike else 2, dep.shape[1]))
                            * rng.uniform(3.0, 10.0) * sig[bad])
                cases[name].append((t, d2, q))
    limits = (4.0, 9.0, 16.0)
    at = comb.max_reduced_chi2 if comb.max_reduced_chi2 > 0 else 4.0
    limits = tuple(sorted({*limits, at}))
    print(f"\npairs-agree test (configured max_reduced_chi2 {comb.max_reduced_chi2:g}): "
          "reduced chi^2 of the kept pairs about their combination, and what each threshold "
          "refuses (scatter above it, or a rival group among the rejected pairs); RMS error "
          f"vs truth of the corners passed and refused at {at:g}:")
    for name, rows in cases.items():
        if not rows:
            continue
        chi, refused, err = [], {lim: [] for lim in limits}, []
        for t, d, q in rows:
            for lim in limits:
                cn = combine_pairs(d, q, design_ref_nm=t["design_ref"],
                                   config=comb.with_overrides(max_reduced_chi2=lim))
                refused[lim].append(not cn.consistent)
            chi.append(cn.reduced_chi2)
            err.append(rms(cn.zernikes_nm - t["truth_ref"]))
        chi_a, err_a, bad = np.array(chi), np.array(err), np.array(refused[at])
        passed = f"{np.mean(err_a[~bad]):.1f}" if (~bad).any() else "-"
        failed = f"{np.mean(err_a[bad]):.1f}" if bad.any() else "-"
        print(f"  {name:15s} {len(rows):3d} corners: chi2 median {np.nanmedian(chi_a):6.2f}, "
              f"95th pct {np.nanquantile(chi_a, 0.95):6.2f}, max {np.nanmax(chi_a):7.2f}; "
              "refused at " + " / ".join(f"{v:g}" for v in limits) + ": "
              + " / ".join(str(sum(v)) for v in refused.values())
              + f"; error passed {passed}, refused {failed} nm mean")


def parser() -> argparse.ArgumentParser:
    """The command line (bench_frames_timing.py reads its scene defaults)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=16, help="evaluation trials")
    ap.add_argument("--calib-trials", type=int, default=14, help="noise-model fit trials")
    ap.add_argument("--solver", default="lsq")
    ap.add_argument("--corner", default="R00")
    ap.add_argument("--rows", type=int, default=2000)
    ap.add_argument("--cols", type=int, default=1000)
    ap.add_argument("--min-stars", type=int, default=3)
    ap.add_argument("--max-stars", type=int, default=6)
    ap.add_argument("--flux-min", type=float, default=2e5)
    ap.add_argument("--flux-max", type=float, default=1e6)
    ap.add_argument("--faint-flux", type=float, default=1.2e4)
    ap.add_argument("--sky", type=float, default=50.0)
    ap.add_argument("--max-pairs", type=int, default=4)
    ap.add_argument("--seeing", type=float, default=0.0,
                    help="FWHM of the atmospheric blur of every star, arcsec (0: none)")
    ap.add_argument("--estimator-seeing", type=float, default=None,
                    help="the seeing the estimator is told (default: --seeing; 0: none, "
                         "the estimator as it was before it took a seeing)")
    ap.add_argument("--seed", type=int, default=20261126)
    ap.add_argument("--write-config", action="store_true",
                    help="store the fitted noise model in config/selection.yaml")
    ap.add_argument("--timing-only", action="store_true",
                    help="run --trials trials (no calibration trials) and report timing only")
    return ap


def main() -> None:
    a = parser().parse_args()
    if a.timing_only:
        a.calib_trials = 0
    halves = load_half_chips()[a.corner]
    told = a.seeing if a.estimator_seeing is None else a.estimator_seeing
    settings = EstimatorSettings(solver=a.solver, seeing_fwhm_arcsec=told)
    sel_cfg = load_selection_config(solver=a.solver, max_pairs=a.max_pairs)
    nominal = load_lsst("r")
    n_all = a.calib_trials + a.trials
    print(f"corner {a.corner}, frames {a.cols}x{a.rows} px, {a.min_stars}-{a.max_stars} "
          f"isolated donuts of {a.flux_min:.0e}-{a.flux_max:.0e} photons + 1 blend + 1 faint "
          f"({a.faint_flux:.0e}) per frame, sky {a.sky:g}/px, seeing {a.seeing:g}\" "
          f"(estimator told {told:g}\"), solver {a.solver}, "
          f"up to {a.max_pairs} pairs; {a.calib_trials} calibration + {a.trials} evaluation "
          "trials", flush=True)
    trials = []
    t0 = time.perf_counter()
    for k in range(n_all):
        t = run_trial(k, a, halves, settings, sel_cfg, nominal)
        trials.append(t)
        print(f"  trial {k:2d}: {t['tot']:4.0f} nm total, {len(t['pairs'])} ok pairs "
              f"({','.join(t['pair_status'])}), cold {t['cold_ms']['total']:6.0f} ms, warm "
              f"{t['warm_ms']['total']:5.0f} ms (detect {t['warm_ms']['detect']:4.0f}), "
              f"render {t['render_s']:4.0f} s", flush=True)
    print(f"total wall time {time.perf_counter() - t0:.0f} s")

    # -- selection
    sel = {k: sum(t["sel"][k] for t in trials) for k in
           ("blend", "blend_rejected", "faint", "faint_rejected", "good", "good_accepted")}
    reasons: dict[str, int] = {}
    for t in trials:
        for r, n in t["sel"]["reasons"].items():
            reasons[r] = reasons.get(r, 0) + n
    pos = np.concatenate([t["sel"]["pos_err"] for t in trials])
    print("\nselection (all trials):")
    print(f"  blended stars rejected  {sel['blend_rejected']}/{sel['blend']}")
    print(f"  faint stars rejected    {sel['faint_rejected']}/{sel['faint']}")
    print(f"  isolated stars accepted {sel['good_accepted']}/{sel['good']}")
    print(f"  rejection reasons       {dict(sorted(reasons.items()))}")
    print(f"  centroid - injected chief ray: median {np.median(pos):.2f} px, max "
          f"{pos.max():.2f} px")

    # -- timing
    cold = np.array([t["cold_ms"]["total"] for t in trials])
    warm = np.array([t["warm_ms"]["total"] for t in trials])
    det = np.array([t["warm_ms"]["detect"] for t in trials])
    est = np.array([t["warm_ms"]["estimate"] for t in trials])
    npairs = np.array([len(t["pair_status"]) for t in trials])
    print("\ntiming per corner (two frames, one BLAS thread), median over trials:")
    print(f"  cold (new star fields) {np.median(cold):7.0f} ms   (max {cold.max():.0f})")
    print(f"  warm (geometry cached) {np.median(warm):7.0f} ms   (max {warm.max():.0f}); "
          f"detection {np.median(det):.0f} ms, estimates {np.median(est):.0f} ms for "
          f"{np.median(npairs):.0f} pairs ({np.median(est / np.maximum(npairs, 1)):.0f} "
          "ms/pair)")
    four = npairs == 4
    if four.any():
        print(f"  4-pair corners: warm {np.median(warm[four]):.0f} ms, cold "
              f"{np.median(cold[four]):.0f} ms (n={int(four.sum())})")
    print(f"  machine reference: a warm on-axis lsq estimate takes {machine_reference_ms():.1f} "
          "ms here (6.1 ms on the machine of README Speed's table)")

    if a.timing_only:
        return

    # -- noise model from the calibration trials
    cal, ev = trials[:a.calib_trials], trials[a.calib_trials:]
    errs = np.array([p["departure"] - p["truth_departure_mid"] for t in cal for p in t["pairs"]])
    qs = np.array([p["q"] for t in cal for p in t["pairs"]])
    c, f = fit_noise_model(errs, qs)
    # Field-dependence: how much the departure from design differs between the pairs'
    # mid-points and the reference field (a bias of reporting the combination there).
    fd = np.array([rms(p["truth_departure_mid"] - t["truth_departure_ref"])
                   for t in trials for p in t["pairs"]])
    print(f"\nnoise model fitted on {len(errs)} calibration pairs: c_j (nm per unit q) median "
          f"{np.median(c):.0f} [{c.min():.0f}..{c.max():.0f}], floor f_j median "
          f"{np.median(f):.1f} [{f.min():.1f}..{f.max():.1f}] nm; median q "
          f"{np.median(qs):.4f}")
    print(f"  truth departure at pair mid-point vs reference field: rms median "
          f"{np.median(fd):.2f} nm, max {fd.max():.2f} nm")
    base = load_selection_config(solver=a.solver).combination
    fitted = base.with_overrides(noise_coefficient_nm=tuple(c), pair_floor_nm=tuple(f),
                                 common_floor_nm=0.0)
    # Common floor: what the combined error of the calibration trials has beyond the
    # combination's own uncertainty (errors shared by all pairs of a corner do not average).
    e2, s2 = [], []
    for t in cal:
        if len(t["pairs"]) < 2:
            continue
        dep = np.array([p["departure"] for p in t["pairs"]])
        cn = combine_pairs(dep, np.array([p["q"] for p in t["pairs"]]),
                           design_ref_nm=t["design_ref"], config=fitted)
        e2.append((cn.zernikes_nm - t["truth_ref"]) ** 2)
        s2.append(cn.uncertainty_nm ** 2)
    g = np.sqrt(np.maximum(np.mean(e2, axis=0) - np.mean(s2, axis=0), 0.0)) if e2 else \
        np.zeros(len(c))
    fitted = fitted.with_overrides(common_floor_nm=tuple(g))
    print(f"  common floor g_j (from {len(e2)} combined calibration corners) median "
          f"{np.median(g):.1f} [{g.min():.1f}..{g.max():.1f}] nm")
    # Coverage: the factor on a multi-pair uncertainty that puts 68.3 % of the calibration
    # corners' errors within 1 sigma (their variance was matched above; the shape of the
    # error distribution, with an estimated scale, is not Gaussian).
    zs = []
    for t in cal:
        if len(t["pairs"]) < 2:
            continue
        cn = combine_pairs(np.array([p["departure"] for p in t["pairs"]]),
                           np.array([p["q"] for p in t["pairs"]]),
                           design_ref_nm=t["design_ref"], config=fitted)
        if cn.n_pairs >= 2:
            zs.append(np.abs(cn.zernikes_nm - t["truth_ref"]) / cn.uncertainty_nm)
    k = float(np.clip(np.quantile(np.concatenate(zs), 0.6827), 0.5, 3.0)) if zs else 1.0
    fitted = fitted.with_overrides(multi_pair_scale=k)
    print(f"  multi-pair uncertainty factor {k:.3f} (68.3 % coverage on {len(zs)} calibration "
          f"corners)")
    for name, comb in (("config", base), ("fitted", fitted)):
        r = evaluate(ev, comb)
        print(f"\naccuracy and calibration on {len(ev)} evaluation trials, noise model "
              f"'{name}':")
        print(f"  RMS error vs truth at the reference field: 1 pair  median "
              f"{np.median(r['rms_1']):5.1f}  mean {np.mean(r['rms_1']):5.1f} nm")
        print(f"                                           N pairs median "
              f"{np.median(r['rms_n']):5.1f}  mean {np.mean(r['rms_n']):5.1f} nm  "
              f"(N = {np.mean(r['n_used']):.1f} on average)")
        print(f"  N pairs better than 1 pair in {np.mean(r['rms_n'] < r['rms_1']):.0%} of trials")
        print(f"  |error| < 1 sigma: 1 pair {r['cal_1']:.0%}, N pairs {r['cal_n']:.0%} "
              f"(< 2 sigma: {r['cal2_1']:.0%}, {r['cal2_n']:.0%}; {r['n_terms']} terms); median "
              f"sigma {r['unc_1']:.1f} / {r['unc_n']:.1f} nm")
    consistency(trials, base)
    if a.write_config:
        path = config_dir() / "selection.yaml"
        text = path.read_text()
        old = (yaml.safe_load(text).get("combination") or {}).get("noise_model") or {}
        fit = {"noise_coefficient_nm": [round(float(v), 1) for v in c],
               "pair_floor_nm": [round(float(v), 2) for v in f],
               "common_floor_nm": [round(float(v), 2) for v in g],
               "multi_pair_scale": round(k, 3)}
        block = {**old, a.solver: fit}
        marker = "  # Fitted by bench/bench_frames.py"
        dumped = yaml.safe_dump({"noise_model": block}, default_flow_style=None, width=95)
        dumped = "".join("  " + line + "\n" for line in dumped.splitlines())
        if marker in text:  # replace an earlier fit (always the file's last block)
            text = text[:text.index(marker)]
        text = text.rstrip("\n") + "\n" + (
            f"  # Fitted by bench/bench_frames.py (last: {a.solver}, {len(errs)} pairs, "
            f"{a.calib_trials} trials, seed {a.seed}).\n") + dumped
        path.write_text(text)
        print(f"\nwrote the fitted noise model for {a.solver!r} to {path}")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
