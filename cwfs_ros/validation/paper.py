"""The paper's validation figures, regenerated with the package's own code (Xin et al. 2015).

Each function returns ``(verdicts, data)``: the verdicts carry the numbers of the report,
``data`` what :mod:`.plots` draws.  The thresholds are fixed here, before any run, from the
paper's text or the project's targets (docs/accuracy.md); a FAIL is reported as a FAIL.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from cwfs_ros.validation.common import (
    EPS,
    NOLL,
    PAPER,
    R_PUPIL_M,
    SPLIT,
    SensorSetup,
    Verdict,
    rms,
    wfe,
)

__all__ = ["Options", "estimate_pair", "lsst_pair", "fig4_orthogonality",
           "fig5_6_convergence", "fig7_perturbed", "fig9_linearity", "fig10_atmosphere"]


@dataclass(frozen=True)
class Options:
    """How much work each figure does (``--quick`` or the full run)."""

    quick: bool
    seed: int = 2015
    # Figs. 5-7 and 9 reproduce the paper's noise-free test images (ZEMAX, no photon
    # noise): rays on a scrambled Sobol sequence, no Poisson draw.  With 2^21 rays a
    # pixel's relative error is ~1.2 %, that of ~6e7 photons (measured against a second
    # scramble); the estimate's photon noise is the noise-floor section's subject.
    rays: int = 2**21                  # per donut, convergence and perturbed-telescope pairs
    linearity_rays: int = 2**20
    solver_photons: float = 1e6        # the solver section's estimated pairs: Poisson noise
    linearity_step_deg: float = 0.01   # M2 rx step
    atm_realisations: int = 12
    atm_rays: int = 2**19              # noise-free (quasi-random) rays per donut, as ZEMAX's
    atm_screen_scale_m: float = 0.4
    atm_screen_size_m: float = 204.8
    atm_times: int = 100               # time samples of the ideal sensor's 15-s average
    noise_levels: tuple[float, ...] = (3e3, 1e4, 3e4, 1e5, 3e5, 1e6, 3e6)
    noise_seeds: int = 4
    noise_sky: float = 50.0
    solver_render: bool = True

    @classmethod
    def make(cls, quick: bool, seed: int = 2015) -> Options:
        if quick:
            return cls(quick=True, seed=seed)
        return cls(quick=False, seed=seed, rays=2**22, linearity_rays=2**21,
                   linearity_step_deg=0.005, atm_realisations=60, atm_rays=2**20,
                   atm_screen_scale_m=0.2, atm_screen_size_m=409.6, atm_times=300,
                   noise_levels=(1e3, 2e3, 5e3, 1e4, 2e4, 5e4, 1e5, 2e5, 5e5, 1e6, 3e6, 1e7),
                   noise_seeds=12)


# -- Fig. 4 -------------------------------------------------------------------------------

def fig4_orthogonality(eps: float = EPS, jmax: int = 22) -> tuple[list[Verdict], dict]:
    """Inner products of Z1..Z22 on the ``eps``-obscured annulus (paper §3.1, Fig. 4).

    Standard (circle) Zernikes come from galsim with no inner radius; the annular ones from
    the package's basis (:func:`cwfs_ros.wfs.zernike.zernike_basis`, galsim's Mahajan
    polynomials).  The integral is the package's exact annulus quadrature (Gauss-Legendre in
    r, uniform in azimuth), normalised as the area average (Noll): the identity for an
    orthonormal set.
    """
    from galsim.zernike import zernikeBasis

    from cwfs_ros.wfs.zernike import annulus_quadrature, zernike_basis

    x, y, w = annulus_quadrature(eps)
    std = zernikeBasis(jmax, x, y, R_outer=1.0, R_inner=0.0)[1:]
    ann = zernike_basis(x, y, jmax=jmax, eps=eps).z
    g_std = (std * w) @ std.T
    g_ann = (ann * w) @ ann.T
    dev_ann = float(np.abs(g_ann - np.eye(jmax)).max())
    off_std = float(np.abs(g_std - np.diag(np.diag(g_std))).max())
    i, j = np.unravel_index(np.argmax(np.abs(g_std - np.diag(np.diag(g_std)))), g_std.shape)
    v = Verdict("Fig. 4 orthogonality", dev_ann <= 1e-6 and off_std > 0.1,
                f"annular max|G-I| = {dev_ann:.1e}; standard max|off-diag| = {off_std:.3f} "
                f"(Z{i + 1}.Z{j + 1}), cond {np.linalg.cond(g_std):.0f}",
                "annular identity to 1e-6; standard visibly not orthogonal (> 0.1)",
                {"eps": eps, "annular_max_dev": dev_ann, "standard_max_offdiag": off_std,
                 "standard_cond": float(np.linalg.cond(g_std)),
                 "annular_cond": float(np.linalg.cond(g_ann))})
    return [v], {"standard": g_std, "annular": g_ann, "eps": eps}


# -- Figs. 5 and 6 ------------------------------------------------------------------------

def estimate_pair(intra: np.ndarray, extra: np.ndarray, fi: tuple, fe: tuple, **kw: Any) -> Any:
    from cwfs_ros.wfs import estimate_wavefront

    return estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                              solver="exp", **kw)


def lsst_pair(tel: Any, fi: tuple, fe: tuple, setup: SensorSetup, wl: float,
               photons: float | None, rng: np.random.Generator, rays: int = 2**21
               ) -> tuple[np.ndarray, np.ndarray]:
    """Ray-traced (intra, extra) donuts: ``photons`` with Poisson noise, or, for None, the
    noise-free image of ``rays`` quasi-random rays (scaled to 1e6 photons)."""
    from cwfs_ros.sim.render import RenderSettings, render_donut

    settings = RenderSettings(wavelength_nm=wl, npix=setup.npix, n_photons=1e6, n_rays=rays,
                              poisson=False, sampling="quasi")
    if photons is not None:
        settings = RenderSettings(wavelength_nm=wl, npix=setup.npix, n_photons=photons)
    return tuple(render_donut(tel, f, s * setup.defocus_mm, settings, rng=rng)
                 for f, s in ((fi, -1.0), (fe, 1.0)))  # type: ignore[return-value]


def _convergence_verdict(label: str, noll: int, amp: float, est_dep: np.ndarray,
                         err: np.ndarray, caustic: bool) -> Verdict:
    k = noll - 4
    others = np.delete(np.arange(19), k)
    got = float(est_dep[k])
    tol = max(0.05 * abs(amp), 10.0)
    max_other = float(np.abs(est_dep[others]).max())
    max_other_err = float(np.abs(err[others]).max())
    worst = int(NOLL[others][np.argmax(np.abs(err[others]))])
    ok = abs(got - amp) <= tol and max_other_err <= 30.0 and not caustic
    return Verdict(label, ok,
                   f"Z{noll} {got:.1f} of {amp:.1f} nm ({100 * (got - amp) / amp:+.1f}%); "
                   f"other terms max |est| {max_other:.1f}, max |err| {max_other_err:.1f} nm "
                   f"(Z{worst})",
                   "injected term within 5% (or 10 nm); others within 30 nm of truth "
                   "(paper: 'no more than ~20-30 nm')",
                   {"noll": noll, "injected_nm": amp, "estimated_nm": got,
                    "max_other_estimate_nm": max_other, "max_other_error_nm": max_other_err,
                    "worst_other_noll": worst,
                    "caustic": caustic})


def fig5_6_convergence(opts: Options) -> tuple[list[Verdict], dict]:
    """Convergence of single-term tests (paper §4.1-4.2, Figs. 5 and 6).

    Paraxial Z4 (f/1.23, 1 mm; the package's paraxial renderer); LSST on axis, 0.5 wave of
    Z11 at 770 nm; LSST at (1.185, 1.185) deg, 2 waves of Z5.  The LSST terms are put in
    with a sag Zernike on M1 (:func:`.common.inject_m1_zernike`), the donuts ray-traced
    through batoid's i-band model at 770 nm.  Then the same LSST cases on the as-built
    split sensor (R44: intra at SW1, extra at SW0, 1.5 mm).
    """
    from cwfs_ros.sim.paraxial import render_paraxial_pair
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import load_lsst
    from cwfs_ros.wfs import load_instrument

    rng = np.random.default_rng(opts.seed)
    cases: list[dict] = []
    verdicts = []
    # Paraxial Z4: 1 wave at 770 nm, the scale of the paper's LSST tests.
    inst = load_instrument("paraxial")
    amp = 770.0
    intra, extra = render_paraxial_pair(inst, {4: amp}, npix=120, n_photons=opts.rays,
                                        rng=rng, poisson=False, sampling="quasi")
    r = estimate_pair(intra, extra, (0.0, 0.0), (0.0, 0.0), instrument=inst)
    truth = np.zeros(19)
    truth[0] = amp
    dep = r.zernikes_nm - r.intrinsic_nm
    cases.append(dict(label="paraxial Z4, 1 mm", setup="paper", noll=4, amp=amp, intra=intra,
                      extra=extra, history=r.history_nm[:, 3:22], truth=truth, estimate=dep,
                      caustic=r.caustic))
    verdicts.append(_convergence_verdict("Fig. 5 paraxial Z4", 4, amp, dep, dep - truth,
                                         r.caustic))
    tel0 = load_lsst("i")
    wl = 770.0
    lsst_cases = [("Fig. 6 on-axis Z11", 11, 0.5 * wl, None, (0.0, 0.0)),
                  ("Fig. 6 off-axis Z5", 5, 2.0 * wl, "R44", (1.185, 1.185))]
    for setup in (PAPER, SPLIT):
        for label, noll, amp, corner, field in lsst_cases:
            fi, fe, mid = setup.fields(corner, field)
            tel, delta = inject_m1(tel0, noll, amp, mid, wl)
            nominal = true_zernikes_nm(tel0, mid, wavelength_nm=wl, eps=EPS)
            intra, extra = lsst_pair(tel, fi, fe, setup, wl, None, rng, opts.rays)
            r = estimate_pair(intra, extra, fi, fe, band="i", wavelength_nm=wl,
                          defocal_offset_mm=setup.defocus_mm)
            dep = r.zernikes_nm - nominal  # the departure from design, as injected
            err = r.zernikes_nm - (nominal + delta)
            name = f"{label} ({setup.name})" if setup is SPLIT else label
            cases.append(dict(label=f"{label[7:]}, {setup.name} {setup.defocus_mm:g} mm",
                              setup=setup.name, noll=noll, amp=amp, intra=intra, extra=extra,
                              # history_nm is the departure from the design model; shift
                              # it onto the departure from the nominal truth, like ``dep``.
                              history=r.history_nm[:, 3:22] + (r.intrinsic_nm - nominal),
                              truth=delta, estimate=dep, caustic=r.caustic))
            verdicts.append(_convergence_verdict(name, noll, amp, dep, err, r.caustic))
    return verdicts, {"cases": cases}


def inject_m1(tel: Any, noll: int, amp: float, field: tuple, wl: float) -> tuple[Any, np.ndarray]:
    from cwfs_ros.validation.common import inject_m1_zernike

    return inject_m1_zernike(tel, noll, amp, field, wl)


# -- Fig. 7 -------------------------------------------------------------------------------

def fig7_perturbed(opts: Options) -> tuple[list[Verdict], dict]:
    """All design aberrations plus a 0.5 mm M2 decenter (x), at (-1.185, 1.185) deg (Fig. 7).

    Truth: ``true_zernikes_nm`` of the perturbed model at the pair's (mid-point) field;
    r band, 622 nm.  Paper set-up at 1 mm, then the split sensor R04 at 1.5 mm.
    """
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    rng = np.random.default_rng(opts.seed + 7)
    dof = np.zeros(50)
    dof[1] = 500.0  # M2 dx, um
    tel = perturbed_telescope(dof, band="r")
    wl = 622.0
    verdicts, panels = [], []
    for setup in (PAPER, SPLIT):
        fi, fe, mid = setup.fields("R04", (-1.185, 1.185))
        intra, extra = lsst_pair(tel, fi, fe, setup, wl, None, rng, opts.rays)
        r = estimate_pair(intra, extra, fi, fe, band="r", wavelength_nm=wl,
                      defocal_offset_mm=setup.defocus_mm)
        truth = true_zernikes_nm(tel, mid, wavelength_nm=wl, eps=EPS)
        err = r.zernikes_nm - truth
        e_rms, e_max = rms(err), float(np.abs(err).max())
        worst = int(NOLL[np.argmax(np.abs(err))])
        verdicts.append(Verdict(f"Fig. 7 M2 decenter ({setup.name})",
                                e_rms <= 15.0 and not r.caustic,
                                f"RMS error {e_rms:.1f} nm over Z4-Z22 (max {e_max:.1f} at "
                                f"Z{worst}); wavefront {wfe(truth):.0f} nm",
                                "RMS error <= 15 nm (target for ray-traced pairs)",
                                {"rms_error_nm": e_rms, "max_error_nm": e_max,
                                 "worst_noll": worst, "truth_nm": truth.tolist(),
                                 "estimate_nm": r.zernikes_nm.tolist(),
                                 "field_mid_deg": list(mid)}))
        panels.append(dict(setup=setup, truth=truth, estimate=r.zernikes_nm, fields=(fi, fe)))
    return verdicts, {"panels": panels}


# -- Fig. 9 -------------------------------------------------------------------------------

def fig9_linearity(opts: Options) -> tuple[list[Verdict], dict]:
    """M2 tilt (rx) stepped up to and past the geometric limit; Z5 at a corner (Fig. 9).

    The geometric limit is found on the ray-traced model itself, as the first step at which
    the pupil-to-detector map folds (:func:`.common.fold_fraction`, either image), and
    compared with the estimator's own ``caustic`` flag.  Linearity: the slope of recovered
    against true Z5 over the steps before the limit, fitted with an intercept.
    """
    rng = np.random.default_rng(opts.seed + 9)
    verdicts, panels = [], []
    for setup, top in ((PAPER, 0.07), (SPLIT, 0.08)):
        fi, fe, _mid = setup.fields("R44", (1.185, 1.185))
        rows = _linearity_steps(setup, top, opts, rng)
        verdict, panel = _linearity_verdict(setup, rows)
        verdicts.append(verdict)
        panels.append(dict(panel, fields=(fi, fe)))
    return verdicts, {"panels": panels}


def _linearity_steps(setup: SensorSetup, top_deg: float, opts: Options,
                     rng: np.random.Generator) -> list[dict]:
    """One row per M2 rx step up to ``top_deg``: true and recovered Z5 (nm), the ray fold
    fraction, the caustic flag, the outer loop's last update and the RMS error."""
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope
    from cwfs_ros.validation.common import fold_fraction

    wl = 622.0
    fi, fe, mid = setup.fields("R44", (1.185, 1.185))
    steps = np.round(np.arange(0.0, top_deg + 1e-9, opts.linearity_step_deg), 6)
    rows = []
    for rx in steps:
        dof = np.zeros(50)
        dof[3] = rx
        tel = perturbed_telescope(dof, band="r")
        truth = true_zernikes_nm(tel, mid, wavelength_nm=wl, eps=EPS)
        fold = max(fold_fraction(tel, fi, -setup.defocus_mm, wl),
                   fold_fraction(tel, fe, setup.defocus_mm, wl))
        # A large stamp: the tilted M2 throws the donut off its chief ray by coma.
        intra, extra = lsst_pair(tel, fi, fe, SensorSetup(setup.name, setup.defocus_mm, 256),
                                 wl, None, rng, opts.linearity_rays)
        try:
            r = estimate_pair(intra, extra, fi, fe, band="r", wavelength_nm=wl,
                              defocal_offset_mm=setup.defocus_mm)
            est, caustic, status = float(r.zernikes_nm[1]), bool(r.caustic), "ok"
            # The outer loop's last update: a few nm while linear; it stays large where
            # the loop has no consistent fixed point (the breakdown, flagged or not).
            last = float(r.residual_rms_nm[-1])
            err_rms = rms(r.zernikes_nm - truth)
        except Exception as exc:  # noqa: BLE001 - an image past the limit may be refused
            est, caustic, status = float("nan"), False, type(exc).__name__
            last = err_rms = float("nan")
        rows.append(dict(rx=float(rx), true=float(truth[1]), est=est, fold=fold,
                         caustic=caustic, status=status, last_update_nm=last,
                         rms_error_nm=err_rms))
    return rows


def _linearity_verdict(setup: SensorSetup, rows: list[dict]) -> tuple[Verdict, dict]:
    """Fig. 9's verdict from the steps: the slope before the geometric limit (first fold),
    where linearity breaks down, and whether the caustic flag is raised there."""
    folded = [i for i, rw in enumerate(rows) if rw["fold"] > 0]
    limit = folded[0] if folded else len(rows)
    lin = [rw for rw in rows[:limit] if np.isfinite(rw["est"])]
    t = np.array([rw["true"] for rw in lin])
    e = np.array([rw["est"] for rw in lin])
    slope, icpt = np.polyfit(t, e, 1) if len(lin) >= 2 else (float("nan"), float("nan"))
    # Within 5 % of the true value, or 50 nm near zero (the design's own Z5 at rx = 0
    # is -0.1 um; the estimator's bias there is a few tens of nm, Fig. 7).
    clean = [rw for rw in lin if not rw["caustic"]]
    slope_clean = (float(np.polyfit([rw["true"] for rw in clean],
                                    [rw["est"] for rw in clean], 1)[0])
                   if len(clean) >= 2 else float("nan"))
    dev = [abs(rw["est"] - rw["true"]) / max(0.05 * abs(rw["true"]), 50.0) for rw in rows]
    good = [i for i, d in enumerate(dev) if np.isfinite(d) and d <= 1.0]
    # First step that is not within tolerance: where linearity breaks down.
    breaks = next((i for i, d in enumerate(dev) if not (np.isfinite(d) and d <= 1.0)),
                  len(rows))
    value = (f"slope {slope:.3f} over rx <= {rows[limit - 1]['rx']:g} deg "
             f"({slope_clean:.3f} without the caustic-flagged steps); within 5% "
             f"(50 nm) up to rx {rows[breaks - 1]['rx'] if breaks else 0:g} deg "
             f"(Z5 {rows[breaks - 1]['true'] if breaks else 0:.0f} nm); ")
    value += _linearity_limits(rows, breaks, limit)
    ok = bool(np.isfinite(slope) and abs(slope - 1.0) <= 0.05)
    verdict = Verdict(f"Fig. 9 linearity ({setup.name})", ok, value,
                      "slope of recovered vs true Z5 within 1 +- 0.05 before the "
                      "geometric limit",
                      {"slope": float(slope), "intercept_nm": float(icpt),
                       "slope_unflagged": slope_clean,
                       "steps": rows, "limit_index": limit,
                       "within_5pct_to_index": breaks - 1,
                       "n_within_5pct": len(good)})
    return verdict, dict(setup=setup, rows=rows, limit=limit, slope=slope, icpt=icpt)


def _linearity_limits(rows: list[dict], breaks: int, limit: int) -> str:
    """The verdict's text on the breakdown step and the geometric limit, with the caustic
    flag at each."""
    first_caustic = next((rw["rx"] for rw in rows if rw["caustic"]), None)
    value = ""
    if breaks < len(rows):
        b = rows[breaks]
        value += (f"linearity breaks down at rx {b['rx']:g} deg (Z5 {b['true']:.0f} nm, "
                  f"recovered {b['est']:.0f}): caustic flag {b['caustic']} there; ")
    if limit < len(rows):
        at_limit = rows[limit]
        value += (f"geometric limit (ray fold) at rx {at_limit['rx']:g} deg, Z5 "
                  f"{at_limit['true']:.0f} nm: caustic flag {at_limit['caustic']} there "
                  f"(first flagged at rx {first_caustic})")
    else:
        value += "no fold within the steps"
    return value


# -- Fig. 10 ------------------------------------------------------------------------------

# Six Kolmogorov layers: a ground layer and five free-atmosphere ones, fractions of the
# turbulence (r0^(-5/3) weights) typical of Cerro Pachon site surveys; speeds and wind
# directions are drawn per realisation.
_LAYER_KM = (0.0, 2.5, 5.0, 7.5, 12.5, 16.0)
_LAYER_WEIGHT = (0.65, 0.17, 0.055, 0.025, 0.075, 0.025)


class TimeIntegratedAtmosphere:
    """A 15-s, six-layer frozen-flow Kolmogorov atmosphere (galsim), r0 = 17 cm at 500 nm.

    ``L0=None``: galsim's spectrum with no outer scale; the screens are periodic, so the
    largest scale actually present is the screen size (stated in the report).
    """

    def __init__(self, seed: int, screen_size_m: float, screen_scale_m: float,
                 exposure_s: float = 15.0) -> None:
        import galsim

        rng = np.random.default_rng(seed)
        speed = rng.uniform(2.0, 20.0, len(_LAYER_KM))
        direction = [a * galsim.degrees for a in rng.uniform(0.0, 360.0, len(_LAYER_KM))]
        self.exposure_s = exposure_s
        self.atm = galsim.Atmosphere(screen_size=screen_size_m, screen_scale=screen_scale_m,
                                     rng=galsim.BaseDeviate(seed), r0_500=0.17, L0=None,
                                     altitude=list(_LAYER_KM), r0_weights=list(_LAYER_WEIGHT),
                                     speed=list(speed), direction=direction)
        self.atm.instantiate()

    def _theta(self, field_deg: tuple[float, float]) -> tuple:
        import galsim

        return (field_deg[0] * galsim.degrees, field_deg[1] * galsim.degrees)

    def gradient(self, field_deg: tuple[float, float]):
        """``(x, y, t) -> (dW/dx, dW/dy)`` in nm/m at the stop for a star at ``field_deg``."""
        theta = self._theta(field_deg)
        return lambda x, y, t: self.atm.wavefront_gradient(x, y, t, theta=theta)

    def ideal_zernikes_nm(self, field_deg: tuple[float, float], n_times: int) -> np.ndarray:
        """Z4..Z22 (nm) of the exposure-averaged OPD over the pupil annulus: the ideal sensor.

        The time average is linear, so it is taken on the OPD at annulus quadrature points
        (the package's exact rule), then projected on galsim's annular Zernikes (eps 0.61).
        """
        from galsim.zernike import zernikeBasis

        from cwfs_ros.wfs.zernike import annulus_quadrature

        x, y, w = annulus_quadrature(EPS, n_radial=16, n_azimuth=64)
        theta = self._theta(field_deg)
        times = (np.arange(n_times) + 0.5) * self.exposure_s / n_times
        u = np.tile(x * R_PUPIL_M, n_times)
        v = np.tile(y * R_PUPIL_M, n_times)
        t = np.repeat(times, x.size)
        opd = self.atm.wavefront(u, v, t, theta=theta).reshape(n_times, x.size).mean(axis=0)
        basis = zernikeBasis(22, x, y, R_outer=1.0, R_inner=EPS)  # row j is Noll j
        return ((basis * w) @ opd)[4:23]


def fig10_atmosphere(opts: Options) -> tuple[list[Verdict], dict]:
    """Atmosphere against algorithm noise: covariance of the 76 coefficients (Fig. 10).

    For each realisation of a 15-s time-integrated atmosphere, intra and extra donuts are
    ray-traced at the four corners through the nominal r-band telescope with every ray
    deflected by the screens' gradient at its own pupil point and arrival time
    (:func:`.common.render_deflected`), noise-free like the paper's ZEMAX images
    (quasi-random rays, no photon noise: the comparison is with the algorithm's own
    noise), and estimated.  The ideal sensor is the atmosphere's own Zernikes of the
    exposure-averaged OPD: at the pair's field for the paper's set-up; on the split sensor
    the two images are two stars, ~0.065 deg apart, whose lines of sight through the high
    layers differ, and a pair measures their mean (to first order the TIE signal is
    ``laplacian(W_intra + W_extra) / 2``), so the ideal there is the mean of the two stars'
    (the mid-field value is reported too).  Compared: the covariances' largest singular
    values, and the covariance of (estimate - ideal), the algorithm's own noise.
    """
    from cwfs_ros.sim.render import load_corner_geometry
    from cwfs_ros.sim.telescope import load_lsst

    corners = load_corner_geometry()
    tel = load_lsst("r")
    verdicts, panels = [], []
    for setup in (PAPER, SPLIT):
        t0 = time.perf_counter()
        est_rows, ideal_rows, mid_rows, fails = [], [], [], 0
        for k in range(opts.atm_realisations):
            est_v, ideal_v, mid_v = _atm_realisation(setup, k, opts, tel, corners)
            if np.all(np.isfinite(est_v)):
                est_rows.append(est_v)
                ideal_rows.append(ideal_v)
                mid_rows.append(mid_v)
            else:
                fails += 1
        wall = time.perf_counter() - t0
        verdict, panel = _atm_verdict(setup, opts, np.array(est_rows), np.array(ideal_rows),
                                      np.array(mid_rows), fails, wall)
        verdicts.append(verdict)
        panels.append(panel)
    return verdicts, {"panels": panels}


def _atm_realisation(setup: SensorSetup, k: int, opts: Options, tel: Any,
                     corners: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Realisation ``k``: the 76 estimated coefficients (NaN for a failed corner), the ideal
    sensor's (the pair's, or the two stars' mean on the split sensor) and the mid-field's."""
    from cwfs_ros.validation.common import render_deflected

    wl = 622.0
    rng = np.random.default_rng(opts.seed * 1000 + k)
    atm = TimeIntegratedAtmosphere(opts.seed * 1000 + k, opts.atm_screen_size_m,
                                   opts.atm_screen_scale_m)
    est, ideal, at_mid = [], [], []
    for name, c in corners.items():
        paper_field = tuple(float(np.sign(v)) * 1.185 for v in c.mid_field_deg)
        fi, fe, mid = setup.fields(name, paper_field)
        intra, extra = (render_deflected(tel, f, s * setup.defocus_mm, wavelength_nm=wl,
                                         npix=setup.npix, n_photons=opts.atm_rays,
                                         rng=rng, gradient=atm.gradient(f),
                                         noise_free=True)
                        for f, s in ((fi, -1.0), (fe, 1.0)))
        try:
            r = estimate_pair(intra, extra, fi, fe, band="r", wavelength_nm=wl,
                              defocal_offset_mm=setup.defocus_mm)
            est.append(r.zernikes_nm)
        except Exception:  # noqa: BLE001 - counted and reported
            est.append(np.full(19, np.nan))
        z_mid = atm.ideal_zernikes_nm(mid, opts.atm_times)
        at_mid.append(z_mid)
        ideal.append(z_mid if fi == fe else
                     0.5 * (atm.ideal_zernikes_nm(fi, opts.atm_times)
                            + atm.ideal_zernikes_nm(fe, opts.atm_times)))
    return np.concatenate(est), np.concatenate(ideal), np.concatenate(at_mid)


def _atm_verdict(setup: SensorSetup, opts: Options, e: np.ndarray, i: np.ndarray,
                 m: np.ndarray, fails: int, wall: float) -> tuple[Verdict, dict]:
    """Fig. 10's verdict from the estimated (``e``), ideal (``i``) and mid-field ideal
    (``m``) coefficients, one row per realisation kept: the covariances' largest singular
    values, and the algorithm's own noise (the covariance of ``e - i``)."""
    n = len(e)
    cov_e, cov_i = np.cov(e, rowvar=False), np.cov(i, rowvar=False)
    cov_d = np.cov(e - i, rowvar=False)
    s_e, s_i, s_d = (np.linalg.svd(c, compute_uv=False) for c in (cov_e, cov_i, cov_d))
    top = max(1, min(3, n - 1))
    ratio = s_e[:top] / s_i[:top]
    noise_frac = float(np.sqrt(s_d[0] / s_i[0]))
    # Against the mid-field ideal instead (the same for the paper's set-up).
    s_dm = np.linalg.svd(np.cov(e - m, rowvar=False), compute_uv=False)
    noise_frac_mid = float(np.sqrt(s_dm[0] / np.linalg.svd(np.cov(m, rowvar=False),
                                                           compute_uv=False)[0]))
    ok = bool(np.all(np.abs(ratio - 1.0) <= 0.2) and noise_frac <= 0.35)
    ideal_is = "mean of the two stars'" if setup is SPLIT else "at the pair's field"
    extra_txt = (f" (against the mid-field ideal: {100 * noise_frac_mid:.0f}%)"
                 if setup is SPLIT else "")
    verdict = Verdict(
        f"Fig. 10 atmosphere ({setup.name})", ok,
        f"top-{top} singular values sensor/ideal {', '.join(f'{x:.2f}' for x in ratio)}; "
        f"algorithm noise sqrt(s1) {100 * noise_frac:.0f}% of the atmosphere's"
        f"{extra_txt}; ideal sensor {ideal_is}; noise-free images; "
        f"{n} realisations ({fails} dropped), {wall:.0f} s",
        "largest singular values agree within 20%, algorithm-noise amplitude <= 35% of "
        "the atmosphere's",
        {"realisations": n, "dropped": fails, "wall_s": wall,
         "singular_sensor": s_e[:10].tolist(), "singular_ideal": s_i[:10].tolist(),
         "singular_difference": s_d[:10].tolist(),
         "atm_rms_per_corner_nm": float(np.sqrt(np.trace(cov_i) / 4)),
         "screen_scale_m": opts.atm_screen_scale_m,
         "screen_size_m": opts.atm_screen_size_m, "rays": opts.atm_rays,
         "noise_fraction": noise_frac, "noise_fraction_vs_mid_field": noise_frac_mid})
    return verdict, dict(setup=setup, cov_e=cov_e, cov_i=cov_i, s_e=s_e, s_i=s_i, s_d=s_d, n=n)
