"""State estimation pieces: the measurement noise and which state directions a visit observes.

Observability by a physical criterion
-------------------------------------
A direction of the DoF state is worth estimating when one visit's measurement says more about
it than was known beforehand. With the prior standard deviation ``σ0`` of each DoF (a fraction
of its stroke, :class:`cwfs_ros.ofc.kalman.KalmanSettings`) and the measurement noise
``σ_meas`` of each Zernike term (the estimator's reported uncertainty, plus a model floor),
the whitened sensitivity

    B = diag(1 / σ_meas) @ H @ diag(σ0)

is unit-free: a singular value ``s`` of ``B`` is the signal-to-noise ratio, in one visit, of a
state excursion of one prior standard deviation along its singular direction. It does not
depend on the units of the DoF (µm or degrees), nor on any normalisation weights: rescaling a
DoF rescales its ``σ0`` inversely. Directions with ``s < min_snr`` are *dropped*: the filter
does not update them (they keep their prior), so the estimator's small systematic errors can
never pile up along them over many visits (the creep of weakly observed bending modes), and the
correction never acts on them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cwfs_ros import layout
from cwfs_ros.errors import ConfigError

__all__ = ["MAX_UNCERTAINTY_NM", "Observability", "measurement_covariance", "observability"]

#: Uncertainties above this are taken as this [nm]: 1 mm of wavefront, no information.
MAX_UNCERTAINTY_NM = 1e6


def measurement_covariance(
    uncertainty_nm: np.ndarray | Sequence[float] | None,
    rows: np.ndarray,
    zrot: np.ndarray,
    *,
    default_nm: float,
    floor_nm: float,
) -> np.ndarray:
    """(m, m) noise covariance [nm²] of the used rows, in the telescope frame.

    Parameters
    ----------
    uncertainty_nm : (76,) 1-sigma per camera-frame term as the wavefront node reports it;
        entries that are 0, negative or not finite (not reported) take ``default_nm``.
        ``None``: every term takes ``default_nm``.
    rows : (76,) bools, the rows of the corners used.
    zrot : (19, 19) camera -> telescope Zernike rotation; a term's variance is rotated with
        its corner's block, so differing uncertainties within an ``m`` pair stay exact.
    default_nm : uncertainty of a term whose producer did not report one.
    floor_nm : added in quadrature to every term: what the estimator's noise model does not
        hold (sensitivity-model error, aliasing of higher terms).
    """
    n_rows = rows.size
    if uncertainty_nm is None:
        sig = np.full(n_rows, default_nm)
    else:
        sig = np.asarray(uncertainty_nm, dtype=np.float64).reshape(-1)
        if sig.size != n_rows:
            raise ConfigError(f"uncertainty_nm must have {n_rows} entries, got {sig.size}")
        sig = np.where(np.isfinite(sig) & (sig > 0), sig, default_nm)
    # A term reported as more uncertain than any wavefront the telescope makes carries no
    # weight either way; the cap keeps the covariance's factorisation finite.
    sig = np.minimum(sig, MAX_UNCERTAINTY_NM)
    var = sig**2 + floor_nm**2
    blocks = []
    for c in range(n_rows // layout.N_ZK):
        sl = slice(c * layout.N_ZK, (c + 1) * layout.N_ZK)
        if rows[sl].any():
            blocks.append(zrot @ np.diag(var[sl]) @ zrot.T)
    m = layout.N_ZK * len(blocks)
    cov = np.zeros((m, m))
    for k, b in enumerate(blocks):
        cov[k * layout.N_ZK:(k + 1) * layout.N_ZK, k * layout.N_ZK:(k + 1) * layout.N_ZK] = b
    return cov


@dataclass(frozen=True)
class Observability:
    """Which state directions one visit observes.

    Attributes
    ----------
    snr : (n,) singular values of the whitened sensitivity (one visit's SNR of a one-prior-
        sigma excursion), descending, zero-padded to the number of DoF in the mask.
    n_kept : directions with ``snr >= min_snr``.
    projector : (n, n) projector onto the kept directions in the masked DoF's units
        (``diag(σ0) V_k V_kᵀ diag(1/σ0)``); the filter's update is multiplied by it.
    dropped_dirs : (n - n_kept, n) dropped directions in prior-sigma units (unit norm).
    dof_visibility : (n,) per masked DoF, the norm of its unit prior-sigma vector inside the
        kept directions: 1 = fully observed, 0 = the corners cannot see it at all.
    """

    snr: np.ndarray
    n_kept: int
    projector: np.ndarray
    dropped_dirs: np.ndarray
    dof_visibility: np.ndarray

    def describe_dropped(self, names: Sequence[str], field_cost_nm: np.ndarray | None = None,
                         top: int = 3, limit: int = 4) -> str:
        """Short text of the dropped directions (largest field cost first), e.g.
        ``"+0.71*M1M3_B3 -0.70*M2_B5 (snr 0.42, 12 nm over the field)"``."""
        n = self.dropped_dirs.shape[0]
        if n == 0:
            return ""
        order = np.arange(n) if field_cost_nm is None else np.argsort(-field_cost_nm)
        parts = []
        for k in order[:limit]:
            v = self.dropped_dirs[k]
            idx = np.argsort(-np.abs(v))[:top]
            terms = " ".join(f"{v[i]:+.2f}*{names[i]}" for i in idx if abs(v[i]) >= 0.05)
            extra = "" if field_cost_nm is None else f", {field_cost_nm[k]:.3g} nm over the field"
            parts.append(f"{terms} (snr {self.snr[self.n_kept + k]:.2g}{extra})")
        more = f"; and {n - limit} more" if n > limit else ""
        return "; ".join(parts) + more


def observability(H: np.ndarray, cov: np.ndarray, prior_sigma: np.ndarray,
                  min_snr: float) -> Observability:
    """Whitened SVD of one visit's sensitivity (rows used, masked DoF).

    Parameters
    ----------
    H : (m, n) nm per DoF unit.
    cov : (m, m) measurement covariance, nm².
    prior_sigma : (n,) prior standard deviation of each DoF, DoF units.
    min_snr : directions seen below this SNR in one visit are dropped.
    """
    chol = np.linalg.cholesky(cov)
    B = np.linalg.solve(chol, H * prior_sigma[None, :])
    _, s, vt = np.linalg.svd(B, full_matrices=True)
    n = H.shape[1]
    snr = np.zeros(n)
    snr[:s.size] = s
    keep = snr >= min_snr
    n_kept = int(keep.sum())
    vk = vt[:n_kept].T  # (n, k), whitened coordinates
    proj_w = vk @ vk.T
    projector = (prior_sigma[:, None] * proj_w) / prior_sigma[None, :]
    visibility = np.sqrt(np.clip(np.diag(proj_w), 0.0, 1.0))
    return Observability(snr, n_kept, projector, vt[n_kept:], visibility)
