"""The project's double-Zernike sensitivity (config/ofc/sensitivity_dz_bundled.npy).

The committed file is loaded (generating it takes minutes: tools/make_sensitivity.py --dz) and
evaluated the way the controller evaluates ts_ofc's double Zernikes; the truth is the 76x50
corner matrix and a fresh batoid finite difference at a field point off the fit's grid.
"""

from __future__ import annotations

import batoid
import numpy as np
import pytest

from cwfs_ros import layout
from cwfs_ros.config import config_dir
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.model import double_zernike_at
from cwfs_ros.sim import perturbed_telescope

DZ_FILE = config_dir() / "ofc" / "sensitivity_dz_bundled.npy"
EPS = 2.558 / 4.18
# Columns that change steeply with the field where vignetting sets in (near the corners): a
# smooth double Zernike misses them by 10-20 % (config/ofc/sensitivity_dz_bundled.md).
STEEP = [28, 45, 46]  # M1M3 mode 19, M2 modes 16 and 17
STEPS = np.array([10.0, 100.0, 100.0, 0.005, 0.005, 10.0, 100.0, 100.0, 0.01, 0.01]
                 + [0.05] * 40)


@pytest.fixture(scope="module")
def dz() -> np.ndarray:
    return np.load(DZ_FILE, allow_pickle=False)


def _evaluate(dz: np.ndarray, fields: np.ndarray) -> np.ndarray:
    """(19 n, 50) with control's double-Zernike evaluator and ts_ofc's radii."""
    cfg = C.load_optics_config()
    out = np.stack([C._eval_double_zernike(dz[:, :, d], fields, cfg)
                    for d in range(layout.N_DOF)], axis=-1)
    return out.reshape(-1, layout.N_DOF)


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=0) / np.linalg.norm(b, axis=0)


def test_layout(dz):
    # pupil Noll 0..37: the controller's Z4..Z22, and Z23..Z37 for the estimator's aliasing
    assert dz.dtype == np.float64 and dz.ndim == 3 and dz.shape[1:] == (38, 50)
    assert not np.any(dz[0]) and not np.any(dz[:, :4])
    assert np.all(np.isfinite(dz))


def test_matches_the_corner_matrix_at_the_corners(dz):
    at = _evaluate(dz, C.corner_mid_field_points_deg())
    bundled = C.sensitivity_for_source("bundled").matrix_nm
    rel = _relative(at, bundled)
    print(f"\ncorners: per-DoF relative difference median {np.median(rel):.1e}, rigid max "
          f"{rel[:10].max():.1e}, bending max {rel[10:].max():.1e}")
    # the corner matrix is eps 0.61 and a 255 grid, the double Zernike eps 0.612, a 64 grid
    assert rel[:10].max() < 0.01
    assert np.median(rel) < 0.01
    assert np.delete(rel, STEEP).max() < 0.05 and rel[STEEP].max() < 0.3


def test_matches_batoid_off_the_fit_grid(dz):
    field = np.array([[0.6231, -1.3077]])  # r = 1.449 deg, between rings, no symmetry
    wl = 622.0
    thx, thy = np.deg2rad(field[0])

    def zk(dof):
        tel = perturbed_telescope(dof, "r")
        low = batoid.zernike(tel, thx, thy, wl * 1e-9, jmax=22, eps=EPS, nx=128)[4:23]
        high = batoid.zernike(tel, thx, thy, wl * 1e-9, jmax=37, eps=EPS, nx=128)[23:38]
        return np.r_[low, high] * wl

    fresh = np.empty((layout.N_ZK + 15, layout.N_DOF))
    for i in range(layout.N_DOF):
        d = np.zeros(layout.N_DOF)
        d[i] = STEPS[i]
        fresh[:, i] = (zk(d) - zk(-d)) / (2.0 * STEPS[i])
    rel = _relative(_evaluate(dz, field), fresh[:layout.N_ZK])
    print(f"\noff-grid field {field[0]}: per-DoF relative difference median "
          f"{np.median(rel):.1e}, rigid max {rel[:10].max():.1e}, max {rel.max():.1e}")
    assert rel[:10].max() < 0.005
    assert np.median(rel) < 0.005
    assert np.delete(rel, STEEP).max() < 0.1 and rel[STEEP].max() < 0.3
    # Z23..Z37 (the estimator's aliasing), weighed against each column's whole Z4..Z37: a
    # column with almost no Z23..Z37 may miss its little by a large fraction of it.
    high = double_zernike_at(dz, field, (23, 37))[0]
    err = np.linalg.norm(high - fresh[layout.N_ZK:], axis=0) / np.linalg.norm(fresh, axis=0)
    print(f"Z23-Z37: error per DoF / |column| median {np.median(err):.1e}, rigid max "
          f"{err[:10].max():.1e}, max {err.max():.1e}")
    assert err[:10].max() < 0.005
    assert np.median(err) < 0.005
    assert err.max() < 0.01
