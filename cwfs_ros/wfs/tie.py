"""Solvers of the transport-of-intensity equation (paper §2).

Both solvers take the compensated intra and extra images on the pupil and return the residual
wavefront as annular Zernike coefficients.  With intensities normalised to 1 on the pupil, the
first-order signal is (eqs. 1, 4)

    S = -(I_intra - I_extra) / (kappa_intra - kappa_extra) ~ laplacian(W) - delta_c dW/dn,

where ``kappa = C tr(A^-1) / 2`` is the local contrast per unit Laplacian of each image, with
C the paper's eq. (11) and ``A = d(x'_0, y'_0)/d(x, y)`` the unperturbed mapping (for the
paraxial case ``kappa = +/- C / r_d``).  The edge term ``delta_c`` is carried by the intensity
that spills beyond the pupil edge, which is why both solvers look a little beyond the pupil
mask ("boundary thickness").

* :class:`SeriesExpansion` ("exp", §2.2, Gureyev & Nugent 1996): project on the basis,
  ``F_j = integral(dI/dz Z_j)``, ``M_ji = integral(I grad Z_j . grad Z_i)``, ``W = M^-1 F``.
* :class:`IterativeFFT` ("fft", §2.1, Roddier & Roddier 1993): solve the Poisson equation by
  fast transform (eq. 8), impose a zero normal derivative outside the computation region
  (Neumann boundary), re-insert the measured signal inside, repeat; then fit Zernikes.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from cwfs_ros.wfs.zernike import ZernikeBasis

__all__ = ["SeriesExpansion", "IterativeFFT", "SOLVERS"]


class SeriesExpansion:
    """Series-expansion TIE solver on fixed pupil points (paper §2.2, eqs. 14-18).

    Args:
        basis: annular Zernikes Z1..Z_jmax at the computation points.
        pupil: boolean mask of the pupil on those points, where ``I = 1`` in ``M_ji``.
    """

    name = "exp"

    def __init__(self, basis: ZernikeBasis, pupil: np.ndarray) -> None:
        self.jmax = basis.jmax
        gx, gy = basis.dx[1:, pupil], basis.dy[1:, pupil]
        # M_ji over the pupil for j, i = 2..jmax (piston has no gradient and is not solved).
        m = gx.astype(float) @ gx.T.astype(float) + gy.astype(float) @ gy.T.astype(float)
        self._m_inv = np.linalg.inv(m)
        self._z = basis.z[1:]  # kept in the basis dtype: the signal is cast, not the basis

    def solve(self, d_intensity: np.ndarray, kappa: float) -> np.ndarray:
        """Residual wavefront Z1..Z_jmax (nm) from ``I_intra - I_extra`` on the points.

        ``F_j = -sum(S Z_j) = sum(dI Z_j) / kappa`` (``S = -dI / kappa`` carries the edge
        term), and by eq. (16) ``sum_i M_ji W_i = F_j``.
        """
        f = (self._z @ d_intensity.astype(self._z.dtype)).astype(float) / kappa
        out = np.zeros(self.jmax)
        out[1:] = self._m_inv @ f
        return out


class IterativeFFT:
    """Iterative fast-transform Poisson solver with Neumann boundary (paper §2.1, eq. 8).

    The Poisson equation is solved with a discrete cosine transform, whose eigenfunctions
    already satisfy a zero normal derivative at the grid edge; the Roddier iteration imposes
    the same condition at the edge of the computation region, where the measured signal
    ends: the wavefront slopes are zeroed outside it, the Laplacian is recomputed there, and
    the measured signal is re-inserted inside.  After ``inner_iterations`` passes the map is
    fitted with annular Zernikes over the pupil.

    The whole inner loop is linear in the measured signal and depends only on the geometry.
    :meth:`wavefront_map` runs it literally (and gives the 2-D wavefront the paper values
    the FFT method for); :meth:`solve` applies the same linear map as a precomputed matrix,
    built once per geometry by running the loop's adjoint for each Zernike output.  Both give
    the same coefficients to rounding (checked by
    ``test_estimator.py::test_fft_matrix_equals_literal_iteration``), and the outer loop then
    costs no more than with the series expansion.

    Args:
        shape: (n, n) grid of the pupil points.
        spacing: grid spacing in reduced pupil units.
        region: flat indices of the computation points in the grid.
        basis: Zernikes at the computation points.
        pupil: pupil mask on the computation points (the Zernike fit region).
        inner_iterations: number of Roddier iterations.
        dtype: storage of the precomputed matrix (float32 halves the memory traffic; the
            signal's own noise is far above its precision).
    """

    name = "fft"

    def __init__(self, shape: tuple[int, int], spacing: float, region: np.ndarray,
                 basis: ZernikeBasis, pupil: np.ndarray, inner_iterations: int = 6,
                 dtype: type = np.float32) -> None:
        self.shape = shape
        self._dtype = dtype
        self.jmax = basis.jmax
        self.region = region
        self.inner = int(inner_iterations)
        inside = np.zeros(shape[0] * shape[1], bool)
        inside[region] = True
        self._inside = inside.reshape(shape).astype(float)
        self._outside = 1.0 - self._inside
        ky = 2.0 * np.cos(np.pi * np.arange(shape[0]) / shape[0]) - 2.0
        kx = 2.0 * np.cos(np.pi * np.arange(shape[1]) / shape[1]) - 2.0
        eig = (ky[:, None] + kx[None, :]) / spacing**2
        eig[0, 0] = np.inf  # the mean of W is free (piston)
        self._inv_eig = 1.0 / eig
        self._inv_h2 = 1.0 / spacing**2
        # Least-squares Zernike fit of the recovered map over the pupil (piston included so
        # that the free mean of W does not leak into other terms).
        self._fit = np.linalg.pinv(basis.z[:, pupil].T)
        self._pupil_idx = region[pupil]
        self._matrix = self._adjoint_matrix()

    # -- the literal iteration --------------------------------------------------------------
    def _poisson(self, s: np.ndarray) -> np.ndarray:
        """Solve laplacian(W) = s (5-point stencil, Neumann edges) on the last two axes."""
        axes = (-2, -1)
        spec = sfft.dctn(s, type=2, norm="ortho", axes=axes, workers=1)
        spec *= self._inv_eig
        return sfft.idctn(spec, type=2, norm="ortho", axes=axes, workers=1, overwrite_x=True)

    def _boundary_laplacian(self, w: np.ndarray) -> np.ndarray:
        """Laplacian of ``w`` with its slopes zeroed inside-out, kept outside the region."""
        gx = np.diff(w, axis=-1, append=w[..., -1:]) * self._inside
        gy = np.diff(w, axis=-2, append=w[..., -1:, :]) * self._inside
        div = np.diff(gx, axis=-1, prepend=0.0) + np.diff(gy, axis=-2, prepend=0.0)
        return div * (self._outside * self._inv_h2)

    def wavefront_map(self, d_intensity: np.ndarray, kappa: float) -> np.ndarray:
        """Run the inner loop literally; return the wavefront map (nm) on the (n, n) grid."""
        measured = np.zeros(self.shape[0] * self.shape[1])
        measured[self.region] = -d_intensity / kappa
        measured = measured.reshape(self.shape)
        s = measured
        for _ in range(self.inner):
            # Forward differences for the gradient, backward for the divergence: their
            # composition is the 5-point Laplacian the cosine transform inverts.
            s = measured + self._boundary_laplacian(self._poisson(s))
        return self._poisson(s)

    def fit(self, wmap: np.ndarray) -> np.ndarray:
        """Annular Zernike coefficients Z1..Z_jmax (Z1 set to 0) of a wavefront map."""
        out = self._fit @ wmap.ravel()[self._pupil_idx]
        out[0] = 0.0
        return out

    # -- the same linear map, precomputed ------------------------------------------------------
    def _boundary_laplacian_adjoint(self, u: np.ndarray) -> np.ndarray:
        v = u * (self._outside * self._inv_h2)
        # Adjoint of the backward-difference divergence, then of the masked forward gradient.
        ax = v - np.concatenate([v[..., 1:], np.zeros_like(v[..., :1])], axis=-1)
        ay = v - np.concatenate([v[..., 1:, :], np.zeros_like(v[..., :1, :])], axis=-2)
        ax *= self._inside
        ay *= self._inside
        ax[..., -1] = 0.0  # the gradient's last column/row is identically zero
        ay[..., -1, :] = 0.0
        zx = np.zeros_like(ax[..., :1])
        zy = np.zeros_like(ay[..., :1, :])
        gtx = np.concatenate([zx, ax[..., :-1]], axis=-1) - ax
        gty = np.concatenate([zy, ay[..., :-1, :]], axis=-2) - ay
        return gtx + gty

    def _adjoint_matrix(self) -> np.ndarray:
        """Rows r_j with ``coefficient_j = r_j . measured_signal`` over the region points."""
        n = self.shape[0] * self.shape[1]
        seed = np.zeros((self.jmax, n))
        seed[:, self._pupil_idx] = self._fit
        # c = F P s_N with s_N = sum_k T^k m and T = B P (B the boundary Laplacian); the
        # Poisson operator P is symmetric, so the adjoint is sum_k (P B^T)^k P F^T.
        u = self._poisson(seed.reshape(self.jmax, *self.shape))
        acc = u.copy()
        for _ in range(self.inner):
            u = self._poisson(self._boundary_laplacian_adjoint(u))
            acc += u
        rows = acc.reshape(self.jmax, n)[:, self.region]
        rows[0] = 0.0
        return np.ascontiguousarray(rows, dtype=self._dtype)

    def solve(self, d_intensity: np.ndarray, kappa: float) -> np.ndarray:
        """Residual wavefront Z1..Z_jmax (nm) from ``I_intra - I_extra`` on the points."""
        return (self._matrix @ d_intensity.astype(self._dtype)).astype(float) / -kappa


def _region_neighbours(shape: tuple[int, int], region: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Positions in ``region`` of each region point's left, right, upper, lower neighbour.

    ``region.size`` where the neighbour is off the region (or off the grid).
    """
    nr, nc = shape
    m = region.size
    # A look-up table on the grid padded by one sample: every neighbour of a grid point is
    # then inside it (off-grid ones read the padding), so no bounds tests are needed
    # (0.9 -> 0.3 ms on a 150 x 150 grid's 9k region points).
    w = nc + 2
    lut = np.full((nr + 2) * w, m, dtype=np.intp)
    rows, cols = np.divmod(region, nc)
    p = (rows + 1) * w + cols + 1
    lut[p] = np.arange(m)
    return lut[p - 1], lut[p + 1], lut[p - w], lut[p + w]


def _flux_factors(i0: np.ndarray, mappings: tuple | None, kappa: float | None
                  ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """(cxx, cxy, cyx, cyy) float32 per point: the model intensity ``I`` times the factors
    of ``grad Z`` in the flux displacement ``I u`` whose divergence is the response (eq. 14).

    Paraxial (``mappings`` None) ``u = grad Z``: isotropic, no cross terms (None).  Off axis
    each image's samples move in the pupil by ``v = C A^-1 grad Z`` when the wavefront
    changes (A: that image's mapping Jacobian, anisotropic), and the difference image
    changes by ``div(I (v_intra - v_extra))``; the factors are summed over both images
    first (one pass over the (jmax, n) arrays instead of four).
    """
    f32 = np.float32
    if mappings is None:
        c = i0.astype(f32)
        return c, None, None, c
    m = i0.size
    axx, axy, ayx, ayy = (np.zeros(m) for _ in range(4))
    for mp, sign in zip(mappings, (1.0, -1.0), strict=True):
        c = (mp.c_px_per_nm * sign / kappa) / mp.det.astype(float)
        axx += c * mp.jyy
        axy -= c * mp.jxy
        ayx -= c * mp.jyx
        ayy += c * mp.jxx
    cxx, cxy, cyx, cyy = ((i0 * a).astype(f32) for a in (axx, axy, ayx, ayy))
    return cxx, cxy, cyx, cyy


def response_matrix(shape: tuple[int, int], spacing: float, region: np.ndarray,
                    basis: ZernikeBasis, pupil: np.ndarray, edge_sigma: float = 1.0,
                    mappings: tuple | None = None, kappa: float | None = None,
                    weight: np.ndarray | None = None) -> np.ndarray:
    """``B`` (jmax - 1, n) float32: the linearised TIE response of the difference image to
    Z2..Z_jmax, ``dI = -kappa * sum_i W_i B_i`` (eq. 14), on the computation points.

    ``B_i = div(I grad Z_i)`` (paraxial, ``mappings`` None), or off axis
    ``div(I (v_intra - v_extra))`` with each image's own pupil displacement
    ``v = C A^-1 grad Z_i`` (per ``kappa``).  ``I`` is the model of a compensated image: the
    pupil mask blurred by a Gaussian of ``edge_sigma`` grid samples (pixel and seeing blur of
    the edge).  Columns are zero where ``weight`` is (the estimator's guard band, where the
    difference image it solves from is zeroed).
    """
    from scipy.ndimage import gaussian_filter

    jmax = basis.jmax
    n = shape[0] * shape[1]
    grid = np.zeros(n)
    grid[region[pupil]] = 1.0
    model = gaussian_filter(grid.reshape(shape), edge_sigma) if edge_sigma > 0 else \
        grid.reshape(shape)
    i0 = model.ravel()[region]
    # Single precision for the (jmax, n) arrays: the lsq loop's fixed point is where
    # B dI = 0, which float32 rounding of B moves by ~1e-7 of the signal.
    m = region.size
    f32 = np.float32
    zx, zy = basis.dx[1:], basis.dy[1:]
    if zx.dtype != f32:
        zx, zy = zx.astype(f32), zy.astype(f32)
    cxx, cxy, cyx, cyy = _flux_factors(i0, mappings, kappa)
    # I u on the region, plus one zero column standing for every point off it (the
    # divergence below gathers neighbours on the region itself).
    nj = jmax - 1
    ux = np.zeros((nj, m + 1), f32)
    uy = np.zeros((nj, m + 1), f32)
    np.multiply(zx, cxx, out=ux[:, :m])
    np.multiply(zy, cyy, out=uy[:, :m])
    if cxy is not None:
        ux[:, :m] += zy * cxy
        uy[:, :m] += zx * cyx
    # div(I u) at the region points by central differences (np.gradient's interior
    # rule).
    left, right, up, down = _region_neighbours(shape, region)
    # (np.take: numpy's a[:, idx] is ~3x slower on these (jmax, n) arrays.)
    b = np.take(ux, right, axis=1)
    b -= np.take(ux, left, axis=1)
    b += np.take(uy, down, axis=1)
    b -= np.take(uy, up, axis=1)
    scale = f32(1.0 / (2.0 * spacing))
    if weight is None:
        b *= scale
    else:
        # The model of the signal actually used: the outer loop zeroes the difference
        # image where the estimator gives it no weight (the guard band where only one
        # image is transmitted), so the model response must be zero there too.  The
        # fixed point, B (w dI) = 0, is unchanged (w is 0 or 1); the Gram matrix is then
        # the true one: without the weight, modes with response in the guard band are
        # under-corrected 5x and the loop contracts at only 0.88 per iteration (docs/design.md).
        # One pass with the difference scale: w is 0 or 1, so the product is exact.
        b *= weight.astype(f32) * scale
    return b


class LeastSquares:
    """Least-squares TIE solver on the annular Zernike basis (beyond the paper).

    The linearised TIE (eq. 14) says a residual ``W = sum_i W_i Z_i`` changes the difference
    of the compensated images by ``dI = -kappa * sum_i W_i B_i`` with
    ``B_i = div(I grad Z_i)``.  The series expansion tests this equation against ``Z_j``
    (a Galerkin projection, ``M_ji = -<Z_j, B_i>``); this solver minimises ``|dI + kappa B W|^2``
    instead, i.e. tests against ``B_j``.  Both have the same noise-free fixed point in the
    outer loop (``dI = 0``), but with photon noise the least-squares weighting is the best
    linear unbiased estimate: it gives no weight to pixels where a term has no signal, such as
    the interior of the pupil for astigmatism, whose information is all at the edge.

    ``B`` is :func:`response_matrix`, zeroed with ``weight`` where the estimator zeroes the
    signal: a model with response there under-corrected the modes that have some, and
    their part of the loop converged at 0.88 per iteration, up to 27 nm short of the fixed
    point after the configured 14 (docs/accuracy.md).
    """

    name = "lsq"

    def __init__(self, shape: tuple[int, int], spacing: float, region: np.ndarray,
                 basis: ZernikeBasis, pupil: np.ndarray, edge_sigma: float = 1.0,
                 mappings: tuple | None = None, kappa: float | None = None,
                 weight: np.ndarray | None = None) -> None:
        self.jmax = basis.jmax
        b = response_matrix(shape, spacing, region, basis, pupil, edge_sigma, mappings, kappa,
                            weight)
        # W = -(B B^T)^-1 B dI / kappa: B dI in one float32 product per iteration, then the
        # small inverse in float64.  (B B^T)^-1 only sets how fast the loop reaches its
        # fixed point.  Folding the inverse into B once would cost a (jmax, jmax) x
        # (jmax, n) product per pair geometry for nothing per iteration.
        # The Gram matrix from the float32 B (single-precision BLAS, no float64 copy of B),
        # inverted in float64: its rounding, ~5e-8 of the largest element, moves the inverse
        # by ~6e-6 (condition ~5e4 at the corners), which again only sets the convergence
        # rate.
        gram = (b @ b.T).astype(np.float64)
        b.setflags(write=False)
        self._response = b
        self._gain = -np.linalg.inv(gram)

    def solve(self, d_intensity: np.ndarray, kappa: float) -> np.ndarray:
        """Residual wavefront Z1..Z_jmax (nm) from ``I_intra - I_extra`` on the points."""
        out = np.zeros(self.jmax)
        out[1:] = self._gain @ (self._response @ d_intensity.astype(np.float32)) / kappa
        return out


SOLVERS = {"exp": SeriesExpansion, "fft": IterativeFFT, "lsq": LeastSquares}
