"""Past the paper: the photon-noise floor of a corner pair, and what the 4 corners can solve.

* Noise floor: one as-built corner pair (R44 split, 1.5 mm, nominal r-band telescope) at
  photon counts from faint to bright; per-term error and wavefront error against photons,
  and the faint limits at which the wavefront error reaches 10 nm and 50 nm.
* Solver: a random 50-DoF perturbation (hexapods and bending modes), its corner wavefronts,
  the optical feedback estimate (``OFCSolver``, gain 1), how much of it is recovered, and
  which DoF combinations the corners cannot see (``observability``).
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from cwfs_ros.validation.common import EPS, SPLIT, Verdict, wfe
from cwfs_ros.validation.paper import Options, estimate_pair, lsst_pair

__all__ = ["noise_floor", "solver_recovery"]


def _crossing(photons: np.ndarray, err: np.ndarray, level: float) -> float | None:
    """Fewest photons at which ``err`` (falling with photons) is at or below ``level``.

    Log-log interpolation between the last level above and the first below; None if the
    error never gets down to ``level``; the faintest count if it is already below there.
    """
    ok = np.isfinite(err) & (err <= level)
    if not ok.any():
        return None
    k = int(np.argmax(ok))
    # Only trust a crossing after which the error stays below (noise can dip once).
    if not ok[k:].all():
        k = int(len(ok) - np.argmax(~ok[::-1]))
        if k >= len(ok):
            return None
    if k == 0:
        return float(photons[0])
    x0, x1 = np.log(photons[k - 1]), np.log(photons[k])
    y0, y1 = np.log(err[k - 1]) if np.isfinite(err[k - 1]) else np.log(1e6), np.log(err[k])
    f = (np.log(level) - y0) / (y1 - y0) if y1 != y0 else 1.0
    return float(np.exp(x0 + f * (x1 - x0)))


def noise_floor(opts: Options) -> tuple[list[Verdict], dict]:
    """Per-term and total wavefront error against photons per donut (sky subtracted).

    The expected (noise-free) images are ray-traced once with many rays; each trial is a
    Poisson draw of ``N * p + sky`` per pixel, minus the sky: exactly photon and sky shot
    noise, at no ray-tracing cost per trial.  The truth is ``true_zernikes_nm`` at the
    mid-point field.  The check: the noise part (spread over seeds) falls as N^-1/2.
    """
    levels = np.array(opts.noise_levels, float)
    sky = opts.noise_sky
    errs, sky_e = _noise_trials(opts, levels)
    total = np.sqrt(np.nansum(errs**2, axis=2))
    total[np.all(np.isnan(errs), axis=2)] = np.nan
    med = np.array([np.nanmedian(t) if np.isfinite(t).any() else np.nan for t in total])
    fails = np.sum(np.all(np.isnan(errs), axis=2), axis=1)
    # Noise part: the spread over seeds (the bias of the noise-free pair is the floor).
    with warnings.catch_warnings():  # levels where every trial failed are NaN, as meant
        warnings.simplefilter("ignore", RuntimeWarning)
        noise = np.sqrt(np.nansum(np.nanvar(errs, axis=1, ddof=1), axis=1))
        per_term = np.sqrt(np.nanmean(errs**2, axis=1))  # (levels, 19) rms over seeds
    # Shot noise of N photons on B sky electrons under the donut: sigma ~ sqrt(N + B) / N
    # (N^-1 while the sky dominates, N^-1/2 once the star does).
    model = np.sqrt(levels + sky_e) / levels
    use = np.isfinite(noise) & (fails == 0) & (noise > 0)
    slope = float(np.polyfit(np.log(model[use]), np.log(noise[use]), 1)[0]) \
        if use.sum() >= 3 else float("nan")
    lim10, lim50 = _crossing(levels, med, 10.0), _crossing(levels, med, 50.0)
    bright = float(med[-1])

    def reaches(nm: float, v: float | None) -> str:
        return (f"not {nm:g} nm within {levels[-1]:.0e} photons" if v is None
                else f"{nm:g} nm at {v:.2g} photons")

    ok = bool(np.isfinite(slope) and 0.85 <= slope <= 1.15)
    v = Verdict("Noise floor (split R44)", ok,
                f"WFE reaches {reaches(50.0, lim50)} and {reaches(10.0, lim10)} per "
                f"donut (sky {sky:g}/px); {bright:.1f} nm at {levels[-1]:.0e}; noise "
                f"~ (sqrt(N+B)/N)^{slope:.2f}, B = {sky_e:.2g} sky e",
                "the noise part follows shot noise sqrt(N+B)/N (exponent 1 +- 0.15)",
                {"photons": levels.tolist(), "median_wfe_nm": med.tolist(),
                 "noise_wfe_nm": noise.tolist(), "failures": fails.tolist(),
                 "limit_10nm_photons": lim10, "limit_50nm_photons": lim50,
                 "slope": slope, "sky_per_pixel": sky, "sky_electrons_under_donut": sky_e,
                 "seeds": opts.noise_seeds,
                 "floor_nm": bright})
    return [v], {"photons": levels, "median": med, "noise": noise, "per_term": per_term,
                 "lim10": lim10, "lim50": lim50, "sky": sky}


def _noise_trials(opts: Options, levels: np.ndarray) -> tuple[np.ndarray, float]:
    """The Z4..Z22 errors (nm) of ``opts.noise_seeds`` Poisson trials per photon level,
    ``(levels, seeds, 19)`` with NaN for a failed or caustic-flagged trial, and the sky
    electrons under one donut (the mean of the two: B of the shot-noise model)."""
    from cwfs_ros.sim.render import (
        RenderSettings,
        load_corner_geometry,
        render_donut,
        true_zernikes_nm,
    )
    from cwfs_ros.sim.telescope import load_lsst

    c = load_corner_geometry()["R44"]
    tel = load_lsst("r")
    wl = 622.0
    fi, fe, mid = c.intra_field_deg, c.extra_field_deg, c.mid_field_deg
    rng = np.random.default_rng(opts.seed + 11)
    n_rays = int(8e6 if not opts.quick else 3e6)
    # Probability per pixel of one photon entering the unvignetted pupil.
    unit = RenderSettings(wavelength_nm=wl, npix=SPLIT.npix, n_photons=1.0, n_rays=n_rays,
                          poisson=False)
    probs = [render_donut(tel, f, s * SPLIT.defocus_mm, unit, rng=rng)
             for f, s in ((fi, -1.0), (fe, 1.0))]
    truth = true_zernikes_nm(tel, mid, wavelength_nm=wl, eps=EPS)
    sky = opts.noise_sky
    errs = np.full((levels.size, opts.noise_seeds, 19), np.nan)
    for a, n in enumerate(levels):
        for s in range(opts.noise_seeds):
            imgs = [rng.poisson(p * n + sky).astype(float) - sky for p in probs]
            try:
                r = estimate_pair(*imgs, fi, fe, band="r", wavelength_nm=wl,
                                  defocal_offset_mm=SPLIT.defocus_mm)
                if not r.caustic:
                    errs[a, s] = r.zernikes_nm - truth
            except Exception:  # noqa: BLE001 - too faint to measure: counted as a failure
                pass
    return errs, sky * 0.5 * sum(int(np.count_nonzero(p)) for p in probs)


def solver_recovery(opts: Options) -> tuple[list[Verdict], dict]:
    """A random mixed 50-DoF state (600 nm of wavefront) seen by the 4 corners (OFC).

    The corner wavefronts are the simulator's truth at the mid-points (the ideal sensor),
    and, if ``opts.solver_render``, estimated from ray-traced split pairs too.  The gain-1
    estimate of ``OFCSolver`` (the package's matrix from the simulator, 12-mode truncated
    SVD in ts_ofc's normalised units) is taken off the state, and the remaining wavefront
    error measured on the simulator.  ``observability`` lists the blind combinations.
    """
    from cwfs_ros.ofc.control import OFCSolver, observability, sensitivity_for_source
    from cwfs_ros.sim.perturbation import random_perturbation, true_error_of_state_nm
    from cwfs_ros.sim.render import load_corner_geometry, true_zernikes_nm
    from cwfs_ros.sim.telescope import DOF_NAMES, perturbed_telescope

    t0 = time.perf_counter()
    wl = 622.0
    corners = load_corner_geometry()
    dof = random_perturbation("mixed", opts.seed, 600.0)
    tel, nominal = perturbed_telescope(dof), perturbed_telescope(None)
    mids = [c.mid_field_deg for c in corners.values()]
    y_true = np.concatenate([true_zernikes_nm(tel, m, wavelength_nm=wl) for m in mids])
    y0 = np.concatenate([true_zernikes_nm(nominal, m, wavelength_nm=wl) for m in mids])
    sens = sensitivity_for_source("bundled")
    solver = OFCSolver(sens, intrinsic_nm=y0)
    before = true_error_of_state_nm(dof)
    results: dict[str, Any] = {}
    inputs = {"ideal sensor": y_true}
    if opts.solver_render:
        inputs["estimated (split pairs)"] = _estimated_corners(opts, tel, corners, wl)
    for label, y in inputs.items():
        e = solver.estimate(y)
        after = true_error_of_state_nm(dof - e.dof_error) if e.valid else float("nan")
        results[label] = dict(before_nm=before, after_nm=after, dof_est=e.dof_error,
                              n_modes=e.n_modes_used, status=e.status)
    w = solver.weights
    frac_norm, wf_blind = _observable_part(sens.matrix_nm * w[None, :], dof / w,
                                           solver.n_modes)
    obs = observability(sens, weights="range-fwhm", rel_tol=1e-3)
    blind = [obs.describe(k, DOF_NAMES) for k in range(len(obs.relative))
             if obs.relative[k] < 1e-3][:6]
    ideal = results["ideal sensor"]
    ratio = ideal["after_nm"] / before
    ok = bool(np.isfinite(ratio) and ratio <= 0.2)
    ex = results.get("estimated (split pairs)")
    extra = f"; from estimated pairs {ex['after_nm']:.0f} nm" if ex is not None else ""
    v = Verdict("Solver (4 corners)", ok,
                f"{before:.0f} nm -> {ideal['after_nm']:.0f} nm after one gain-1 correction "
                f"from the ideal sensor ({100 * (1 - ratio):.0f}% removed){extra}; "
                f"{100 * frac_norm:.0f}% of the state's normalised norm in the "
                f"{solver.n_modes} kept modes; {obs.n_near_null} of 50 directions below "
                f"1e-3 of s_max",
                "one gain-1 correction leaves <= 20% of the wavefront error",
                {"before_nm": before,
                 **{f"after_nm[{k}]": r["after_nm"] for k, r in results.items()},
                 "kept_modes": solver.n_modes, "fraction_norm_observable": frac_norm,
                 "blind_wavefront_nm": wf_blind, "n_near_null": obs.n_near_null,
                 "blind_directions": blind, "wall_s": time.perf_counter() - t0})
    return [v], {"dof": dof, "results": results, "singular": obs.relative, "weights": w,
                 "n_modes": solver.n_modes, "blind": blind}


def _estimated_corners(opts: Options, tel: Any, corners: dict[str, Any],
                       wl: float) -> np.ndarray:
    """The 76 coefficients (nm) estimated from a ray-traced split pair at each corner of the
    perturbed telescope ``tel``."""
    rng = np.random.default_rng(opts.seed + 13)
    est = []
    for c in corners.values():
        intra, extra = lsst_pair(tel, c.intra_field_deg, c.extra_field_deg, SPLIT, wl,
                                 opts.solver_photons, rng)
        r = estimate_pair(intra, extra, c.intra_field_deg, c.extra_field_deg, band="r",
                          wavelength_nm=wl, defocal_offset_mm=SPLIT.defocus_mm)
        est.append(r.zernikes_nm)
    return np.concatenate(est)


def _observable_part(an: np.ndarray, z: np.ndarray, n_modes: int) -> tuple[float, float]:
    """Split the normalised state ``z`` into what the ``n_modes`` kept modes of the
    normalised matrix ``an`` see and the rest: the seen fraction of its norm, and the
    wavefront (nm per corner) of the unseen part."""
    _, _, vt = np.linalg.svd(an, full_matrices=True)
    kept = vt[:n_modes]
    z_obs = kept.T @ (kept @ z)
    frac_norm = float(np.linalg.norm(z_obs) / np.linalg.norm(z))
    wf_blind = wfe(an @ (z - z_obs)) / 2.0  # per corner: sqrt(sum)/sqrt(4 corners)
    return frac_norm, wf_blind
