"""Annular Zernike polynomials (Noll ordering, Mahajan's annular form) with derivatives.

The estimator needs, at fixed pupil points, the values of every basis term and its first and
second derivatives: the series-expansion solver projects the signal on ``Z_j`` and uses
``grad Z_j`` (paper §2.2, ``F_j`` and ``M_ji``), and the compensation needs the gradient and
Hessian of the current wavefront (§2.1, eqs. 9-12) at every outer iteration.

The polynomials come from GalSim (``galsim.zernike``), which implements Mahajan's annular
Zernikes in Noll order and exposes each as a polynomial in x and y (its ``_coef_array_xy``).
This module keeps them in that monomial form: a wavefront's derivatives are then exact
monomial coefficient shifts, and the gradient and Hessian fields at all points come from one
small matrix product with the cached monomials, instead of five products with full basis
arrays.  That is what makes the outer loop fast.

Normalisation: orthonormal over the annulus ``eps <= r <= 1`` in the sense
``(1/A) * integral(Z_i Z_j dA) = delta_ij`` (Noll's convention).  Coordinates are reduced pupil
coordinates (pupil radius = 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
from galsim.zernike import Zernike

__all__ = ["ZernikeBasis", "zernike_basis", "noll_to_nm", "xy_coefficients", "annulus_quadrature",
           "gram_matrix", "gram_summary"]


def noll_to_nm(j: int) -> tuple[int, int]:
    """Return the radial order n and signed azimuthal order m of Noll index ``j`` (j >= 1).

    Noll's convention: even j carries cos(m theta) (m > 0), odd j carries sin (m < 0).
    """
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    k = j - n * (n + 1) // 2 - 1
    ms = [m for m in range(n % 2, n + 1, 2) for _ in ((0,) if m == 0 else (0, 1))]
    m = ms[k]
    return n, (m if (m == 0 or j % 2 == 0) else -m)


def _order(jmax: int) -> int:
    return noll_to_nm(jmax)[0]


def _exponents(order: int) -> np.ndarray:
    """(a, b) exponents of the monomials x^a y^b with a + b <= order."""
    return np.array([(a, d - a) for d in range(order + 1) for a in range(d + 1)])


@lru_cache(maxsize=32)
def xy_coefficients(jmax: int, eps: float) -> np.ndarray:
    """Monomial coefficients of Z_1..Z_jmax: shape (jmax, n_monomials), see ``_exponents``."""
    order = _order(jmax)
    exps = _exponents(order)
    out = np.zeros((jmax, len(exps)))
    for j in range(1, jmax + 1):
        coef = np.zeros(j + 1)
        coef[j] = 1.0
        arr = Zernike(coef, R_outer=1.0, R_inner=eps)._coef_array_xy  # arr[a, b]: x^a y^b
        for k, (a, b) in enumerate(exps):
            if a < arr.shape[0] and b < arr.shape[1]:
                out[j - 1, k] = arr[a, b]
    out.setflags(write=False)
    return out


@lru_cache(maxsize=8)
def _derivative_operators(order: int) -> np.ndarray:
    """Matrices mapping monomial coefficients to those of d/dx, d/dy, d2/dx2, d2/dxdy, d2/dy2.

    Shape (5, n_mono, n_mono), used as ``c @ D[k]`` on a row vector of coefficients.
    """
    exps = _exponents(order)
    index = {tuple(e): k for k, e in enumerate(exps)}
    dx = np.zeros((len(exps), len(exps)))
    dy = np.zeros_like(dx)
    for k, (a, b) in enumerate(exps):
        if a > 0:
            dx[k, index[(a - 1, b)]] = a
        if b > 0:
            dy[k, index[(a, b - 1)]] = b
    ops = np.stack([dx, dy, dx @ dx, dx @ dy, dy @ dy])
    ops.setflags(write=False)
    return ops


# The cached arrays of a ZernikeBasis that hold one value (or row) per point.
_POINT_ARRAYS = ("z", "dx", "dy", "dxx", "dxy", "dyy")


@dataclass(frozen=True)
class ZernikeBasis:
    """Annular Zernikes Z_1..Z_jmax at fixed pupil points, with fast derivative fields.

    Attributes:
        jmax, eps: highest Noll index and obscuration ratio.
        monomials: x^a y^b at the points, shape (n_mono, npoints).
        coeffs_xy: monomial coefficients of each Zernike, shape (jmax, n_mono).
        z: Z_j at the points, shape (jmax, npoints); row j-1 is Noll j.
    """

    jmax: int
    eps: float
    monomials: np.ndarray = field(repr=False)
    coeffs_xy: np.ndarray = field(repr=False)
    # A subset's source: (its parent's arrays at the points that had been evaluated, by
    # name; the subset's point indices). Each is taken from there on first use: the
    # least-squares estimator of a new star pair reads only the monomials, dx and dy, and
    # the other arrays' points would be gathered for nothing.
    _parent: tuple[dict[str, np.ndarray], np.ndarray] | None = field(default=None, repr=False,
                                                                     compare=False)

    @property
    def npoints(self) -> int:
        return self.monomials.shape[1]

    def _from_parent(self, name: str) -> np.ndarray | None:
        if self._parent is not None:
            arrays, index = self._parent
            if name in arrays:
                return np.take(arrays[name], index, axis=1)
        return None

    @cached_property
    def z(self) -> np.ndarray:
        got = self._from_parent("z")
        return got if got is not None else np.ascontiguousarray(self.coeffs_xy @ self.monomials)

    @cached_property
    def _ops(self) -> np.ndarray:
        return _derivative_operators(_order(self.jmax))

    def _term_derivative(self, k: int, name: str) -> np.ndarray:
        got = self._from_parent(name)
        if got is not None:
            return got
        # In the basis dtype, as z: the small factor is cast, never the big monomial array
        # (a float64 product would upcast it and double the arrays every solver set-up reads).
        return (self.coeffs_xy @ self._ops[k]).astype(self.monomials.dtype) @ self.monomials

    # Per-term derivative arrays (jmax, npoints), built on first use (solver set-up, tests).
    @cached_property
    def dx(self) -> np.ndarray:
        return self._term_derivative(0, "dx")

    @cached_property
    def dy(self) -> np.ndarray:
        return self._term_derivative(1, "dy")

    @cached_property
    def dxx(self) -> np.ndarray:
        return self._term_derivative(2, "dxx")

    @cached_property
    def dxy(self) -> np.ndarray:
        return self._term_derivative(3, "dxy")

    @cached_property
    def dyy(self) -> np.ndarray:
        return self._term_derivative(4, "dyy")

    def subset(self, index: np.ndarray) -> ZernikeBasis:
        """The basis at ``points[index]``, sharing this basis' polynomial coefficients.

        The arrays at the points already built here (``z``, the derivatives) are indexed on
        first use, not rebuilt: a basis built once on a fixed pupil grid then serves every
        field's computation region on it.
        """
        built = {k: v for k, v in self.__dict__.items() if k in _POINT_ARRAYS}
        # np.take along the point axis: the same values as a[:, index], ~3x faster (numpy's
        # mixed slice/array indexing is slow for (k, n) arrays).
        return ZernikeBasis(self.jmax, self.eps, np.take(self.monomials, index, axis=1),
                            self.coeffs_xy, _parent=(built, index))

    def wavefront(self, coeffs: np.ndarray) -> np.ndarray:
        """W at the points for Noll coefficients ``coeffs`` (Z1.., at most jmax long)."""
        c = np.asarray(coeffs, float)[: self.jmax]
        return c @ self.z[: c.size]

    def derivative_fields(self, coeffs: np.ndarray) -> np.ndarray:
        """``[W_x, W_y, W_xx, W_xy, W_yy]`` at the points, shape (5, npoints).

        One (5 x n_mono) @ (n_mono x npoints) product: the cost does not grow with jmax.
        """
        c = np.asarray(coeffs, float)[: self.jmax]
        mono = c @ self.coeffs_xy[: c.size]
        # Cast the small (5 x n_mono) factor, never the big monomial array.
        return (mono @ self._ops).astype(self.monomials.dtype) @ self.monomials


def zernike_basis(x: np.ndarray, y: np.ndarray, jmax: int = 22, eps: float = 0.61,
                  dtype: type = np.float64) -> ZernikeBasis:
    """Annular Zernikes 1..jmax (with derivatives on demand) at reduced pupil points (x, y).

    Args:
        x, y: reduced pupil coordinates (pupil radius 1), equal shapes; flattened.
        jmax: highest Noll index (any value >= 1; 22 by default, 37 and beyond supported).
        eps: obscuration ratio of the annulus (inner/outer radius); 0 gives circle Zernikes.
        dtype: floating type of the cached arrays.
    """
    if int(jmax) != jmax or jmax < 1:
        raise ValueError(f"jmax must be an integer >= 1, got {jmax}")
    if not 0.0 <= eps < 1.0:
        raise ValueError(f"obscuration eps must be in [0, 1), got {eps}")
    jmax = int(jmax)
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    exps = _exponents(_order(jmax))
    maxp = int(exps.max())
    xp = np.vstack([np.ones_like(x)] + [x**p for p in range(1, maxp + 1)])
    yp = np.vstack([np.ones_like(y)] + [y**p for p in range(1, maxp + 1)])
    mono = np.ascontiguousarray(xp[exps[:, 0]] * yp[exps[:, 1]], dtype=dtype)
    coeffs = np.asarray(xy_coefficients(jmax, float(eps)), dtype=dtype)
    basis = ZernikeBasis(jmax, float(eps), mono, coeffs)
    _ = basis.z  # evaluated now: a full basis' callers read it
    return basis


def annulus_quadrature(eps: float, n_radial: int = 24,
                       n_azimuth: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points and weights integrating polynomials exactly over the annulus ``eps <= r <= 1``.

    Gauss-Legendre in ``r`` (with the ``r dr`` measure) times a uniform rule in azimuth,
    normalised so the weights sum to 1 (area average, Noll's normalisation).  With the
    defaults it is exact for the radial and azimuthal orders of Z1..Z_231.
    """
    t, wt = np.polynomial.legendre.leggauss(n_radial)
    r = 0.5 * (1 - eps) * t + 0.5 * (1 + eps)
    wr = wt * r
    th = 2 * np.pi * np.arange(n_azimuth) / n_azimuth
    rr, tt = np.meshgrid(r, th, indexing="ij")
    w = np.repeat(wr, n_azimuth) / n_azimuth
    return (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), w / w.sum()


def gram_matrix(basis: ZernikeBasis, mask: np.ndarray | None = None,
                weights: np.ndarray | None = None, j_min: int = 4,
                j_max: int = 22) -> np.ndarray:
    """Gram matrix ``<Z_i, Z_j>`` of Noll terms j_min..j_max over a (vignetted) pupil.

    Paper §3.3: annular Zernikes are orthonormal on the full annulus (the matrix is the
    identity there) and stop being so on a vignetted pupil.  The inner product is the area
    average over the points selected by ``mask`` (all points if None), with quadrature
    ``weights`` if given (else equal weights: a uniform grid).
    """
    z = basis.z[j_min - 1:j_max].astype(float)
    w = np.ones(basis.npoints) if weights is None else np.asarray(weights, float)
    if mask is not None:
        w = np.where(mask, w, 0.0)
    return (z * w) @ z.T / w.sum()


def gram_summary(gram: np.ndarray) -> tuple[float, float]:
    """Largest |off-diagonal| element and condition number of a Gram matrix."""
    off = gram - np.diag(np.diag(gram))
    return float(np.abs(off).max()), float(np.linalg.cond(gram))
