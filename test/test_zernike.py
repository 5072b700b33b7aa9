"""Annular Zernikes: orthonormality, closed forms, derivatives, GalSim agreement."""

from __future__ import annotations

import numpy as np
import pytest
from galsim.zernike import Zernike, zernikeBasis

from cwfs_ros.wfs.zernike import noll_to_nm, zernike_basis

EPS = 0.61


def _polar_quadrature(n_r: int = 64, n_t: int = 128, eps: float = EPS):
    """Gauss-Legendre in r^2 times uniform in theta: exact for polynomials of modest order."""
    u, w = np.polynomial.legendre.leggauss(n_r)
    r2 = eps**2 + (1 - eps**2) * (u + 1) / 2
    theta = np.arange(n_t) * 2 * np.pi / n_t
    rr, tt = np.meshgrid(np.sqrt(r2), theta, indexing="ij")
    weights = np.repeat(w[:, None] / w.sum() / n_t, n_t, axis=1)  # mean over the annulus
    return (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), weights.ravel()


@pytest.mark.parametrize("jmax", [22, 37])
def test_orthonormal_on_annulus(jmax: int) -> None:
    x, y, w = _polar_quadrature()
    b = zernike_basis(x, y, jmax=jmax, eps=EPS)
    gram = (b.z * w) @ b.z.T
    assert np.abs(gram - np.eye(jmax)).max() < 1e-10


def test_mahajan_closed_forms() -> None:
    """Annular defocus and spherical aberration from Mahajan (1981), independent of GalSim."""
    rng = np.random.default_rng(0)
    r = rng.uniform(EPS, 1, 50)
    t = rng.uniform(0, 2 * np.pi, 50)
    b = zernike_basis(r * np.cos(t), r * np.sin(t), jmax=11, eps=EPS)
    e2 = EPS**2
    z4 = np.sqrt(3) * (2 * r**2 - 1 - e2) / (1 - e2)
    z11 = np.sqrt(5) * (6 * r**4 - 6 * (1 + e2) * r**2 + 1 + 4 * e2 + e2**2) / (1 - e2) ** 2
    z6 = np.sqrt(6) * r**2 * np.cos(2 * t) / np.sqrt(1 + e2 + e2**2)
    np.testing.assert_allclose(b.z[3], z4, atol=1e-12)
    np.testing.assert_allclose(b.z[10], z11, atol=1e-12)
    np.testing.assert_allclose(b.z[5], z6, atol=1e-12)


def test_agrees_with_galsim_basis() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-1, 1, (2, 200))
    b = zernike_basis(x, y, jmax=37, eps=EPS)
    ref = zernikeBasis(37, x, y, R_outer=1.0, R_inner=EPS)[1:]
    np.testing.assert_allclose(b.z, ref, atol=1e-10)


def test_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.9, 0.9, (2, 40))
    c = rng.normal(size=30)
    h = 1e-5
    b = zernike_basis(x, y, jmax=30, eps=EPS)
    wx, wy, wxx, wxy, wyy = b.derivative_fields(c)

    def w(px, py):
        return zernike_basis(px, py, jmax=30, eps=EPS).wavefront(c)

    np.testing.assert_allclose(wx, (w(x + h, y) - w(x - h, y)) / (2 * h), rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(wy, (w(x, y + h) - w(x, y - h)) / (2 * h), rtol=1e-6, atol=1e-5)
    h = 1e-4
    np.testing.assert_allclose(wxx, (w(x + h, y) - 2 * w(x, y) + w(x - h, y)) / h**2,
                               rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(wyy, (w(x, y + h) - 2 * w(x, y) + w(x, y - h)) / h**2,
                               rtol=1e-4, atol=1e-2)
    cross = (w(x + h, y + h) - w(x + h, y - h) - w(x - h, y + h) + w(x - h, y - h)) / (4 * h * h)
    np.testing.assert_allclose(wxy, cross, rtol=1e-4, atol=1e-2)
    # Per-term arrays agree with the fused derivative fields.
    np.testing.assert_allclose(c @ b.dx, wx, atol=1e-9)
    np.testing.assert_allclose(c @ b.dxy, wxy, atol=1e-8)


def test_gradient_matches_galsim() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1, 1, (2, 100))
    c = np.concatenate([[0.0], rng.normal(size=22)])
    z = Zernike(c, R_outer=1.0, R_inner=EPS)
    d = zernike_basis(x, y, jmax=22, eps=EPS).derivative_fields(c[1:])
    np.testing.assert_allclose(d[0], z.gradX(x, y), atol=1e-9)
    np.testing.assert_allclose(d[1], z.gradY(x, y), atol=1e-9)


def test_noll_indices() -> None:
    assert [noll_to_nm(j) for j in (1, 4, 5, 6, 7, 8, 11, 22)] == [
        (0, 0), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (4, 0), (6, 0)]
    with pytest.raises(ValueError):
        noll_to_nm(0)
    with pytest.raises(ValueError):
        zernike_basis(np.zeros(1), np.zeros(1), jmax=22, eps=1.2)
