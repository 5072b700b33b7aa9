"""Combining the wavefront estimates of several star pairs into one corner result.

With several donuts per half-chip (paper Fig. 2 caption: the strategy "is currently under
investigation"), each intra/extra pair gives an estimate of the total wavefront at its own
mid-point field (§3.4: the design part there is added back).  The pairs sit at slightly
different fields, and the design wavefront varies across a half-chip by several nm, so the
pairs are combined on their *departure from design*, ``z_k - intrinsic_k``, which the
telescope's perturbation makes nearly uniform across a half-chip; the design wavefront at the
corner's reference field is then added back once.

Noise model (per pair k, per Zernike term j)::

    sigma_kj^2 = (c_j q_k)^2 + f_j^2,   q_k = sqrt(1/SNR_intra^2 + 1/SNR_extra^2)

``c_j`` (nm) is the photon-noise response of term j (the TIE is linear in the intensity
difference, §2.1, whose noise scales as 1/SNR), ``f_j`` (nm) a per-pair floor (model errors
that differ between stars).  Both come from ``config/selection.yaml``, fitted on simulations
by :func:`fit_noise_model`.  The combination is the inverse-variance weighted mean after
outlier rejection; its uncertainty is the noise model's, rescaled by the observed scatter
between pairs (shrunk towards the model for few pairs), plus a common floor ``g_j`` that
averaging cannot reduce.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import N_ZK as N_TERMS

__all__ = ["CombinationConfig", "CombinedEstimate", "combine_pairs", "fit_noise_model",
           "pair_noise_scale", "pair_sigma_nm", "N_TERMS"]



def _vec(v: object, name: str) -> tuple[float, ...]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.full(N_TERMS, float(a[0]))
    if a.shape != (N_TERMS,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ConfigError(f"combination: {name} must be one number or {N_TERMS} numbers "
                          f">= 0 (Z4..Z22, nm), got {v!r}")
    return tuple(float(x) for x in a)


@dataclass(frozen=True)
class CombinationConfig:
    """Parameters of the pair combination (``config/selection.yaml``, ``combination``).

    Attributes:
        noise_coefficient_nm: c_j, nm per unit of the noise scale q (19 values or one).
        pair_floor_nm: f_j, per-pair error floor (nm).
        common_floor_nm: g_j, error common to all pairs of a corner (nm), added to the
            combined uncertainty.
        clip_sigma: a term of a pair further than this many sigma from the others' robust
            centre is dropped from that term's mean.
        pair_clip: a pair whose robust rms normalised residual over the terms (median |r| /
            0.6745) exceeds this is dropped entirely (a bad stamp spoils every term).
        prior_dof: weight, in pairs, of the noise model against the observed scatter when
            estimating the uncertainty (0 = scatter only, for n >= 2).
        max_iter: outlier-rejection passes.
        multi_pair_scale: factor on the uncertainty of a combination of two or more pairs.
            That uncertainty leans on the scatter of a few clipped pairs, itself a noisy
            estimate, and a Gaussian 1 sigma of it covers fewer than 68 % of the errors
            (64 % measured); ``bench/bench_frames.py --write-config`` fits the factor that
            makes 68 % of the calibration trials' errors fall within 1 sigma.  A single
            pair's model uncertainty is left as it is.
        max_reduced_chi2: the pairs kept must agree: their scatter about the combination,
            in units of their noise model (the reduced chi^2 over every kept term), above
            this makes the combination ``consistent=False``, for the caller to refuse; so
            does an ``ambiguous`` one (the pairs rejected as outliers hold a group as large
            as the one kept that agrees as well).  Two bad pairs among four defeat the
            outlier rejection: the median is then between good and bad, and the two pairs
            kept may be one of each, or the two bad ones.  0 = no such test.
    """

    noise_coefficient_nm: tuple[float, ...] = (2000.0,) * N_TERMS
    pair_floor_nm: tuple[float, ...] = (5.0,) * N_TERMS
    common_floor_nm: tuple[float, ...] = (0.0,) * N_TERMS
    clip_sigma: float = 4.0
    pair_clip: float = 3.0
    prior_dof: float = 3.0
    max_iter: int = 3
    multi_pair_scale: float = 1.0
    max_reduced_chi2: float = 0.0

    def __post_init__(self) -> None:
        for name in ("noise_coefficient_nm", "pair_floor_nm", "common_floor_nm"):
            object.__setattr__(self, name, _vec(getattr(self, name), name))
        for name in ("clip_sigma", "pair_clip"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ConfigError(f"combination: {name} must be > 0, got {v!r}")
        if not (isinstance(self.multi_pair_scale, (int, float))
                and 0.5 <= self.multi_pair_scale <= 3.0):
            raise ConfigError(f"combination: multi_pair_scale must be in [0.5, 3], got "
                              f"{self.multi_pair_scale!r}")
        if not (isinstance(self.prior_dof, (int, float)) and self.prior_dof >= 0):
            raise ConfigError(f"combination: prior_dof must be >= 0, got {self.prior_dof!r}")
        if not (isinstance(self.max_reduced_chi2, (int, float))
                and self.max_reduced_chi2 >= 0):
            raise ConfigError(f"combination: max_reduced_chi2 must be >= 0 (0 = off), got "
                              f"{self.max_reduced_chi2!r}")
        if not isinstance(self.max_iter, int) or self.max_iter < 1:
            raise ConfigError(f"combination: max_iter must be an integer >= 1, got "
                              f"{self.max_iter!r}")

    def with_overrides(self, **kw: object) -> CombinationConfig:
        return replace(self, **kw)


def pair_sigma_nm(noise_scale: np.ndarray, config: CombinationConfig) -> np.ndarray:
    """(n, 19) the noise model's one-sigma error of each pair's terms (nm):
    ``sqrt((c_j q_k)^2 + f_j^2)``."""
    q = np.asarray(noise_scale, dtype=np.float64).reshape(-1, 1)
    c = np.asarray(config.noise_coefficient_nm)[None, :]
    f = np.asarray(config.pair_floor_nm)[None, :]
    return np.sqrt((c * q) ** 2 + f ** 2)


def pair_noise_scale(snr_intra: float, snr_extra: float) -> float:
    """q = sqrt(1/SNR_intra^2 + 1/SNR_extra^2): the relative noise of the intensity
    difference the TIE is solved for (both images contribute; §3.4 normalises each)."""
    return float(np.sqrt(1.0 / max(snr_intra, 1e-9) ** 2 + 1.0 / max(snr_extra, 1e-9) ** 2))


@dataclass(frozen=True)
class CombinedEstimate:
    """Result of :func:`combine_pairs`.

    Attributes:
        zernikes_nm: (19,) combined Z4..Z22 (nm) at the reference field (NaN if no pair).
        uncertainty_nm: (19,) one-sigma uncertainty per term (nm).
        n_pairs: pairs that contributed to at least one term.
        used: (n,) bool, pair k contributed (not rejected as an outlier pair).
        term_used: (n, 19) bool, pair k contributed to term j.
        pair_chi: (n,) robust rms normalised residual of each pair over the terms.
        reduced_chi2: scatter of the kept pairs about the combination in units of their
            noise model: the sum over every term of every kept pair (clipped terms too) of
            ``min(((d_kj - mean_j) / sigma_kj)^2, clip_sigma^2)``, divided by
            ``19 (n_kept - 1)``; ~1 for pairs that agree as the noise model says; NaN with
            fewer than two pairs.
        fallback: the whole-pair clip left fewer than two pairs, so the two most
            consistent were kept.
        ambiguous: the pairs rejected as outliers, combined on their own, keep as many
            pairs as this combination did, within ``max_reduced_chi2`` of each other: two
            groups that each agree and not with each other, and no majority to choose
            (only evaluated when that test is on).
        consistent: not ``ambiguous``, and ``reduced_chi2`` within the configured
            ``max_reduced_chi2`` (or that test is off; one pair passes it).
    """

    zernikes_nm: np.ndarray
    uncertainty_nm: np.ndarray
    n_pairs: int
    used: np.ndarray
    term_used: np.ndarray
    pair_chi: np.ndarray
    reduced_chi2: float = float("nan")
    fallback: bool = False
    ambiguous: bool = False
    consistent: bool = True


def combine_pairs(departure_nm: np.ndarray, noise_scale: np.ndarray, *,
                  design_ref_nm: np.ndarray | None = None,
                  config: CombinationConfig | None = None) -> CombinedEstimate:
    """Combine per-pair departures from design into one estimate with uncertainties.

    Args:
        departure_nm: (n, 19) per-pair ``zernikes_nm - intrinsic_nm`` (nm): the non-design
            part of each pair's wavefront at its own mid-point field.
        noise_scale: (n,) q of each pair (:func:`pair_noise_scale`).
        design_ref_nm: (19,) design wavefront at the reference field (nm), added to the
            combined departure (zeros if None).
        config: the noise model and clipping parameters.

    Returns:
        A :class:`CombinedEstimate`.  With no pair, NaN values and ``n_pairs == 0``.
    """
    cfg = config or CombinationConfig()
    d = np.asarray(departure_nm, dtype=np.float64).reshape(-1, N_TERMS)
    q = np.asarray(noise_scale, dtype=np.float64).reshape(-1)
    if q.shape[0] != d.shape[0]:
        raise ValueError(f"{d.shape[0]} pairs but {q.shape[0]} noise scales")
    n = d.shape[0]
    design = (np.zeros(N_TERMS) if design_ref_nm is None
              else np.asarray(design_ref_nm, dtype=np.float64).reshape(N_TERMS))
    if n == 0:
        nan = np.full(N_TERMS, np.nan)
        return CombinedEstimate(nan, nan.copy(), 0, np.zeros(0, bool), np.zeros((0, N_TERMS),
                                bool), np.zeros(0))
    with np.errstate(invalid="ignore"):
        sig = np.maximum(pair_sigma_nm(q, cfg), 1e-6)  # (n, 19)
    # A pair without a finite noise scale has no weight to combine with (NaN would spread
    # to the combination where fewer than 3 pairs leave the robust loop out).
    finite = np.all(np.isfinite(d), axis=1) & np.isfinite(q)
    used, term_used, chi, fallback = _reject_outliers(d, sig, finite, cfg)
    mean, unc = _weighted_mean(d, sig, term_used, cfg)
    n_used = int(used.sum())
    if n_used >= 2:
        unc = unc * cfg.multi_pair_scale
    z = mean + design
    if not used.any():
        z = np.full(N_TERMS, np.nan)
        unc = np.full(N_TERMS, np.nan)
    red = _reduced_chi2(d, sig, used, mean, cfg)
    ambiguous = _has_rival(d, q, finite & ~used, n_used, cfg)
    consistent = not (cfg.max_reduced_chi2 > 0
                      and (ambiguous or red > cfg.max_reduced_chi2))
    return CombinedEstimate(z, unc, n_used, used, term_used, chi, red, fallback, ambiguous,
                            consistent)


def _reject_outliers(d: np.ndarray, sig: np.ndarray, finite: np.ndarray,
                     cfg: CombinationConfig
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """(used, term_used, chi, fallback): which pairs, and which terms of them, enter the
    mean, each pair's robust rms normalised residual, and whether the whole-pair clip had
    to fall back to the two most consistent pairs.

    With three pairs or more, up to ``max_iter`` passes: the robust centre of each term is
    the median of the pairs still in (a planted outlier cannot drag it, unlike the mean);
    a pair whose robust rms residual over the terms (median |r| / 0.6745) exceeds
    ``pair_clip`` is dropped whole (one wild term must not throw out its other 18), and a
    term further than ``clip_sigma`` from its centre is dropped alone, never below two pairs.
    """
    n = d.shape[0]
    used = finite.copy()
    term_used = np.repeat(used[:, None], N_TERMS, axis=1)
    chi = np.zeros(n)
    fallback = False
    if used.sum() < 3:
        return used, term_used, chi, fallback
    for _ in range(cfg.max_iter):
        centre = _masked_medians(d, term_used)
        r = (d - centre[None, :]) / sig
        r[~finite] = np.inf
        chi = np.median(np.abs(np.where(np.isfinite(r), r, 1e6)), axis=1) / 0.6745
        new_used = finite & (chi <= cfg.pair_clip)
        fallback = bool(new_used.sum() < 2)
        if fallback:  # keep the two most consistent pairs rather than none
            keep = np.argsort(chi)[:2]
            new_used = np.zeros(n, bool)
            new_used[keep] = finite[keep]
        new_term = new_used[:, None] & (np.abs(r) <= cfg.clip_sigma)
        for j in range(N_TERMS):
            if new_term[:, j].sum() < min(2, new_used.sum()):
                new_term[:, j] = new_used
        if np.array_equal(new_used, used) and np.array_equal(new_term, term_used):
            break
        used, term_used = new_used, new_term
    return used, term_used, chi, fallback


def _masked_medians(d: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Per column, the median of the entries ``use`` keeps (0 where it keeps none): as
    ``np.median`` gives it, from one sort of all the columns."""
    srt = np.sort(np.where(use, d, np.inf), axis=0)
    k = use.sum(axis=0)
    cols = np.arange(d.shape[1])
    lo, hi = srt[np.maximum(k - 1, 0) // 2, cols], srt[k // 2, cols]
    return np.where(k > 0, 0.5 * (lo + hi), 0.0)


def _weighted_mean(d: np.ndarray, sig: np.ndarray, term_used: np.ndarray,
                   cfg: CombinationConfig) -> tuple[np.ndarray, np.ndarray]:
    """(mean, uncertainty) per term: the inverse-variance weighted mean of the terms used,
    and the noise model's uncertainty of it rescaled by the observed scatter, shrunk towards
    the model with ``prior_dof`` pairs of weight (with 2-3 pairs the sample scatter alone is
    too noisy to be the error bar), plus the common floor in quadrature.  NaN for a term no
    pair contributes to."""
    w = np.where(term_used, 1.0 / sig ** 2, 0.0)
    wsum = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(wsum > 0, (w * np.where(term_used, d, 0.0)).sum(axis=0) / wsum, np.nan)
        var_model = np.where(wsum > 0, 1.0 / wsum, np.nan)
        nj = term_used.sum(axis=0)
        resid2 = (w * np.where(term_used, d - mean[None, :], 0.0) ** 2).sum(axis=0)
        chi2 = np.where(nj > 1, resid2 / np.maximum(nj - 1, 1), 1.0)
        dof = np.maximum(nj - 1, 0)
        # No scatter to see (one pair) and no prior weight: the model alone, not zero.
        weight = cfg.prior_dof + dof
        scale2 = np.where(weight > 0, (cfg.prior_dof + dof * chi2) / np.maximum(weight, 1e-12),
                          1.0)
    return mean, np.sqrt(var_model * scale2 + np.asarray(cfg.common_floor_nm) ** 2)


def _reduced_chi2(d: np.ndarray, sig: np.ndarray, used: np.ndarray, mean: np.ndarray,
                  cfg: CombinationConfig) -> float:
    """The kept pairs' agreement over all their terms, clipped ones included (NaN for fewer
    than two pairs): a kept pair whose terms were clipped one by one disagrees as much as
    one dropped whole.  Each term is capped at ``clip_sigma``, so that a single wild term
    still costs one term."""
    n_used = int(used.sum())
    if n_used < 2:
        return float("nan")
    r_kept = (d[used] - mean[None, :]) / sig[used]
    return float(np.minimum(r_kept ** 2, cfg.clip_sigma ** 2).sum() / (N_TERMS * (n_used - 1)))


def _has_rival(d: np.ndarray, q: np.ndarray, rejected_mask: np.ndarray, n_used: int,
               cfg: CombinationConfig) -> bool:
    """The rejected pairs, combined on their own (the same rules, recursively on a smaller
    set), keep as many pairs that agree as well as the kept ones do: two groups and no
    majority.  Only evaluated when the consistency test is on."""
    rejected = np.flatnonzero(rejected_mask)
    if not (cfg.max_reduced_chi2 > 0 and n_used >= 2 and rejected.size >= n_used):
        return False
    rival = combine_pairs(d[rejected], q[rejected], config=cfg)
    return bool(rival.n_pairs >= n_used and rival.reduced_chi2 <= cfg.max_reduced_chi2)


def fit_noise_model(errors_nm: np.ndarray, noise_scale: np.ndarray,
                    clip: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``E[err_kj^2] = f_j^2 + c_j^2 q_k^2`` to single-pair errors against the truth.

    Args:
        errors_nm: (m, 19) single-pair departure errors (estimate minus truth, nm).
        noise_scale: (m,) q of each pair.
        clip: errors beyond ``clip`` times the fitted sigma are dropped and the fit redone
            (caustics or blends the selection missed would otherwise set the floor).

    Returns:
        ``(c, f)``: (19,) noise coefficients and per-pair floors, nm.
    """
    e = np.asarray(errors_nm, dtype=np.float64).reshape(-1, N_TERMS)
    q = np.asarray(noise_scale, dtype=np.float64).reshape(-1)
    ok = np.all(np.isfinite(e), axis=1) & np.isfinite(q)
    e, q = e[ok], q[ok]
    c = np.zeros(N_TERMS)
    f = np.zeros(N_TERMS)
    if e.shape[0] < 3:
        raise ValueError("need at least 3 pairs to fit the noise model")
    a = np.stack([np.ones_like(q), q * q], axis=1)
    for j in range(N_TERMS):
        keep = np.ones(e.shape[0], bool)
        for _ in range(3):
            coef, *_ = np.linalg.lstsq(a[keep], e[keep, j] ** 2, rcond=None)
            f2, c2 = max(float(coef[0]), 0.0), max(float(coef[1]), 0.0)
            if f2 == 0.0 and c2 == 0.0:
                f2 = float(np.mean(e[keep, j] ** 2))
            s = np.sqrt(f2 + c2 * q * q)
            new = np.abs(e[:, j]) <= clip * s
            if np.array_equal(new, keep) or new.sum() < 3:
                break
            keep = new
        c[j], f[j] = np.sqrt(c2), np.sqrt(f2)
    return c, f
