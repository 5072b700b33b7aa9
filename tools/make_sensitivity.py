#!/usr/bin/env python3
"""Compute the project's wavefront sensitivity matrices from the batoid simulator.

    .venv/bin/python tools/make_sensitivity.py          # writes config/ofc/sensitivity_bundled_r.*
    .venv/bin/python tools/make_sensitivity.py --check  # recompute and compare, write nothing
    .venv/bin/python tools/make_sensitivity.py --dz     # writes config/ofc/sensitivity_dz_bundled.*
    .venv/bin/python tools/make_sensitivity.py --dz --check

``--dz`` fits a double Zernike (see :func:`compute_dz`) so that the matrix can be evaluated at
any field point; the default is the 76x50 matrix at the four corners described below.

For each of the 50 DoF (ts_ofc order and units, batoid_rubin/OCS sign convention, the one of
``cwfs_msgs/DofCorrection``) the matrix column is the central finite difference

    A[:, i] = (Z(+h_i e_i) - Z(-h_i e_i)) / (2 h_i)

of the true wavefront Zernikes ``Z`` (``cwfs_ros.sim.true_zernikes_nm``: batoid.zernike of the
in-focus :func:`cwfs_ros.sim.perturbed_telescope`, annular Noll 4..22, eps 0.61, nm of OPD,
wavefront sign) at the mid-point of the SW0/SW1 half-chips of the four corner rafts
(``config/sensors/lsst_corners.yaml``, order R00, R04, R40, R44), r band (batoid
``LSST_r.yaml``) at 622 nm. Rows ``19 * corner + (j - 4)``. Units: nm per DoF unit (µm or
deg).

Bending modes use the legacy Zernike decomposition of batoid_rubin's bending modes (j <= 28,
``cwfs_ros/sim/data/bending``) without the high-order residual grids, so those columns are
approximate (see ``cwfs_ros/sim/telescope.py``).

The script also reports the linearity of each column (central difference with h and h/2) and
writes a provenance note, ``config/ofc/sensitivity_bundled_r.md``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cwfs_ros import layout  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ofc.model import RESPONSE_NOLL_HIGH  # noqa: E402
from cwfs_ros.sim import (  # noqa: E402
    DOF_NAMES,
    N_DOF,
    load_corner_geometry,
    perturbed_telescope,
    true_zernikes_nm,
)

BAND = "r"
WAVELENGTH_NM = 622.0
EPS = 0.61  # the estimator's annular obscuration (config/instruments/lsst.yaml)
NX = 255  # batoid.zernike pupil sampling
# Finite-difference half-steps per DoF (µm, deg): small enough to be linear, large enough to be
# far above the ~1e-3 nm numerical noise of batoid.zernike.
STEPS = np.array([10.0, 100.0, 100.0, 0.005, 0.005, 10.0, 100.0, 100.0, 0.01, 0.01]
                 + [0.05] * 40)
OUT_NPY = REPO / "config" / "ofc" / C.BUNDLED_MATRIX_FILENAME
OUT_NOTE = OUT_NPY.with_suffix(".md")

# Double-Zernike fit (--dz): galsim.zernike.DoubleZernike conventions, as
# cwfs_ros.ofc.control._eval_double_zernike evaluates ts_ofc's matrix.
DZ_NPY = REPO / "config" / "ofc" / "sensitivity_dz_bundled.npy"
DZ_NOTE = DZ_NPY.with_suffix(".md")
DZ_FIELD_RADIUS_DEG = 1.75  # uv_outer (uv_inner 0)
DZ_PUPIL_INNER_M, DZ_PUPIL_OUTER_M = 2.558, 4.18  # xy_inner, xy_outer
DZ_EPS = DZ_PUPIL_INNER_M / DZ_PUPIL_OUTER_M  # batoid.zernike's R_outer is pupilSize/2 = 4.18
DZ_KMAX = 28  # field Zernikes Noll 1..28: complete radial orders 0..6
# Field grid: the centre and rings at the five Gaussian-quadrature radii (where the controller
# evaluates the field), one between the outer two, and the field edge; the corners (1.706 deg,
# at any rotator angle) lie on the 1.708 ring. Near the edge vignetting sets in and some
# bending columns grow steeply (M1M3 mode 19: x15 from 1.25 to 1.75 deg), so the rings are
# denser there. 99 points.
DZ_RING_RADII_DEG = (0.379, 0.841, 1.237, 1.535, 1.64, 1.708, 1.75)
DZ_RING_POINTS = (6, 8, 12, 16, 16, 24, 16)
DZ_NX = 64  # batoid.zernike pupil grid (the fit, not the grid, limits the accuracy)
# Pupil terms of the double Zernike: Z4..Z37. The controller's model of the corners and the
# field uses Z4..Z22; Z23..Z37 are what the estimator aliases into them (the measurement
# model "estimator", tools/make_estimator_response.py).
DZ_JMAX = RESPONSE_NOLL_HIGH
DZ_NJ = DZ_JMAX - layout.NOLL_MIN + 1


def corner_fields() -> list[tuple[float, float]]:
    geo = load_corner_geometry()
    return [geo[c].mid_field_deg for c in layout.CORNERS]


def wavefront(dof: np.ndarray, fields: list[tuple[float, float]]) -> np.ndarray:
    tel = perturbed_telescope(dof, BAND)
    return np.concatenate([
        true_zernikes_nm(tel, f, wavelength_nm=WAVELENGTH_NM, jmax=22, eps=EPS, nx=NX)
        for f in fields
    ])


def column(i: int, h: float, fields: list[tuple[float, float]]) -> np.ndarray:
    d = np.zeros(N_DOF)
    d[i] = h
    return (wavefront(d, fields) - wavefront(-d, fields)) / (2.0 * h)


def compute(verbose: bool = True) -> tuple[np.ndarray, np.ndarray]:
    fields = corner_fields()
    a = np.zeros((layout.N_MEAS, N_DOF))
    nonlin = np.zeros(N_DOF)
    t0 = time.perf_counter()
    for i in range(N_DOF):
        a[:, i] = column(i, STEPS[i], fields)
        half = column(i, 0.5 * STEPS[i], fields)
        nonlin[i] = np.linalg.norm(a[:, i] - half) / max(np.linalg.norm(a[:, i]), 1e-300)
        if verbose:
            print(f"{i:2d} {DOF_NAMES[i]:9s} |A|={np.linalg.norm(a[:, i]):10.4g} nm/unit  "
                  f"nonlinearity(h vs h/2)={nonlin[i]:.1e}  [{time.perf_counter() - t0:5.1f} s]",
                  flush=True)
    return a, nonlin


def compare_ts_ofc(a: np.ndarray) -> list[str]:
    """Per-column correlation and norm ratio against ts_ofc (converted, at the same fields)."""
    ts = C.SensitivityMatrix.from_ts_ofc(fields_deg=C.corner_mid_field_points_deg()).matrix_nm
    lines = []
    for i in range(N_DOF):
        x, y = a[:, i], ts[:, i]
        corr = float(x @ y / np.sqrt((x @ x) * (y @ y)))
        ratio = float(np.linalg.norm(x) / np.linalg.norm(y))
        lines.append(f"| {i} | {DOF_NAMES[i]} | {corr:+.3f} | {ratio:.3f} |")
    return lines


def write_note(a: np.ndarray, nonlin: np.ndarray, table: list[str]) -> None:
    sha = hashlib.sha256(OUT_NPY.read_bytes()).hexdigest()
    import batoid

    fields = corner_fields()
    fld = ", ".join(f"{c} ({x:+.4f}, {y:+.4f})" for c, (x, y) in zip(layout.CORNERS, fields,
                                                                     strict=True))
    text = f"""# {OUT_NPY.name}: provenance

Made by `tools/make_sensitivity.py` (this project) on {_dt.date.today().isoformat()},
batoid {batoid.__version__}, numpy {np.__version__}, Python {platform.python_version()}.
Re-run the script to regenerate it; `--check` recomputes and compares without writing.

- **What:** wavefront sensitivity `A`, shape (76, 50), float64, **nm of wavefront (OPD) per
  DoF unit** (µm for translations and bending amplitudes, degrees for rx/ry), **wavefront
  sign** (`wavefront_change = A @ dof_change`), **batoid_rubin/OCS DoF convention** (the one
  of `cwfs_msgs/DofCorrection` and of `cwfs_ros.sim.perturbed_telescope`'s default).
- **Rows:** `19 * corner + (j - 4)`, Noll j = 4..22 annular Zernikes (eps {EPS}), corners in
  the order R00, R04, R40, R44, each at the mid-point of its SW0/SW1 half-chips
  (`config/sensors/lsst_corners.yaml`): {fld} deg.
- **How:** central finite differences of `cwfs_ros.sim.true_zernikes_nm` (batoid.zernike of the
  in-focus perturbed `LSST_{BAND}.yaml`, {WAVELENGTH_NM:g} nm, nx={NX}) under
  `cwfs_ros.sim.perturbed_telescope(dof, "{BAND}")`, half-steps: M2 dz 10 µm, dx/dy 100 µm,
  rx/ry 0.005 deg; camera dz 10 µm, dx/dy 100 µm, rx/ry 0.01 deg; bending modes 0.05 µm.
  The largest change between half-steps h and h/2 (nonlinearity) was {nonlin.max():.1e} of a
  column's norm.
- **Approximation:** the bending-mode columns (10-49) use batoid_rubin's *legacy* Zernike
  decomposition of the modes (j <= 28) without the high-order residual grids
  (`cwfs_ros/sim/data/bending/PROVENANCE.md`), so they are approximate; M1M3 modes 15-20 in
  particular differ from ts_ofc's (table below).
- sha256 `{sha}`

## Agreement with ts_ofc's matrix (converted to wavefront sign and batoid_rubin DoF
convention by `SensitivityMatrix.from_ts_ofc`, evaluated at the same mid-points)

| DoF | name | correlation | norm ratio bundled/ts_ofc |
|---|---|---|---|
""" + "\n".join(table) + "\n"
    OUT_NOTE.write_text(text, encoding="utf-8")


def dz_fields_deg() -> np.ndarray:
    """(99, 2) field points [deg] of the fit: the centre and :data:`DZ_RING_RADII_DEG`, every
    other ring turned by half a step."""
    pts = [(0.0, 0.0)]
    for k, (r, n) in enumerate(zip(DZ_RING_RADII_DEG, DZ_RING_POINTS, strict=True)):
        a = 2.0 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
        pts += list(zip(r * np.cos(a), r * np.sin(a), strict=True))
    return np.array(pts)


def dz_zernikes(dof: np.ndarray, fields: np.ndarray, nx: int = DZ_NX) -> np.ndarray:
    """(n_fields, 34) true Z4..Z37 [nm] on the 2.558..4.18 m annulus (telescope frame).

    Z4..Z22 come from a fit of Z1..Z22, as the 76x50 matrix's do, and Z23..Z37 from a fit
    of Z1..Z37: on a vignetted pupil the terms are not orthogonal, so adding terms to the
    fit moves the low ones (by about 1e-3 of a column), and the controller's Z4..Z22 stay
    those of the Z22 fit."""
    import batoid

    tel = perturbed_telescope(dof, BAND)
    out = np.empty((fields.shape[0], DZ_NJ))
    for k, (x, y) in enumerate(fields):
        for jmax, terms in ((layout.NOLL_MAX, slice(0, layout.N_ZK)),
                            (DZ_JMAX, slice(layout.N_ZK, None))):
            zk = batoid.zernike(tel, np.deg2rad(x), np.deg2rad(y), WAVELENGTH_NM * 1e-9,
                                jmax=jmax, eps=DZ_EPS, nx=nx)
            out[k, terms] = np.asarray(zk[layout.NOLL_MIN:])[terms] * WAVELENGTH_NM
    return out


def dz_columns(fields: np.ndarray, nx: int = DZ_NX, verbose: bool = True) -> np.ndarray:
    """(n_fields, 34, 50) central finite differences [nm per DoF unit] at ``fields``."""
    out = np.empty((fields.shape[0], DZ_NJ, N_DOF))
    t0 = time.perf_counter()
    for i in range(N_DOF):
        d = np.zeros(N_DOF)
        d[i] = STEPS[i]
        out[:, :, i] = (dz_zernikes(d, fields, nx) - dz_zernikes(-d, fields, nx)) / (2 * STEPS[i])
        if verbose:
            print(f"{i:2d} {DOF_NAMES[i]:9s} [{time.perf_counter() - t0:6.1f} s]", flush=True)
    return out


def fit_dz(fields: np.ndarray, values: np.ndarray, kmax: int = DZ_KMAX) -> np.ndarray:
    """Field-Zernike fit of ``values`` (n_fields, 34, 50) -> (kmax + 1, 38, 50) double-Zernike
    coefficients ``[k, j, d]`` (k = 0 and j = 0..3 zero).

    Per DoF, a least-squares fit with each field point weighted by 1 / |column there| (of
    Z4..Z22, the terms the controller models): the relative error is balanced over the
    field, so a column that grows steeply near the edge does not buy its edge values with the
    rest of the field (M1M3 mode 19 at the corners: 35 % instead of 67 % unweighted)."""
    import galsim

    basis = galsim.zernike.zernikeBasis(kmax, fields[:, 0], fields[:, 1],
                                        R_outer=DZ_FIELD_RADIUS_DEG)[1:]  # (kmax, n)
    out = np.zeros((kmax + 1, DZ_JMAX + 1, N_DOF))
    for d in range(N_DOF):
        w = 1.0 / np.maximum(np.linalg.norm(values[:, :layout.N_ZK, d], axis=1), 1e-12)
        coef, *_ = np.linalg.lstsq((basis * w).T, values[:, :, d] * w[:, None], rcond=None)
        out[1:, layout.NOLL_MIN:, d] = coef
    return out


def eval_dz(dz: np.ndarray, fields: np.ndarray) -> np.ndarray:
    """(n_fields, 34, 50) of a (k, 38, 50) double Zernike, with galsim.DoubleZernike."""
    import galsim

    out = np.empty((fields.shape[0], dz.shape[1] - layout.NOLL_MIN, N_DOF))
    for d in range(N_DOF):
        dzd = galsim.zernike.DoubleZernike(dz[:, :, d], uv_inner=0.0,
                                           uv_outer=DZ_FIELD_RADIUS_DEG,
                                           xy_inner=DZ_PUPIL_INNER_M, xy_outer=DZ_PUPIL_OUTER_M)
        for k, zk in enumerate(dzd(fields[:, 0], fields[:, 1])):
            out[k, :, d] = np.asarray(zk.coef)[layout.NOLL_MIN:dz.shape[1]]
    return out


def dz_checks(dz: np.ndarray, nx: int = DZ_NX) -> list[str]:
    """Figures of the fit: against the 76x50 bundled matrix at the corners, and against a
    fresh finite difference at off-grid field points."""
    lines = []
    corners = C.corner_mid_field_points_deg()
    at_corners = eval_dz(dz, corners)[:, :layout.N_ZK].reshape(-1, N_DOF)
    bundled = C.SensitivityMatrix.from_bundled().matrix_nm
    rel = np.linalg.norm(at_corners - bundled, axis=0) / np.linalg.norm(bundled, axis=0)
    worst = ", ".join(f"{DOF_NAMES[i]} {rel[i]:.2f}" for i in np.argsort(-rel)[:6])
    lines.append(f"corners vs sensitivity_bundled_r.npy: per-DoF relative difference median "
                 f"{np.median(rel):.2e}, rigid max {rel[:10].max():.2e}; worst: {worst}")
    rng = np.random.default_rng(2026)
    r = DZ_FIELD_RADIUS_DEG * np.sqrt(rng.uniform(0.0, 1.0, 3))
    a = rng.uniform(0.0, 2.0 * np.pi, 3)
    pts = np.c_[r * np.cos(a), r * np.sin(a)]
    fresh = dz_columns(pts, nx=nx, verbose=False)
    model = eval_dz(dz, pts)
    for k, p in enumerate(pts):
        for label, j in (("Z4-Z22", slice(0, layout.N_ZK)),
                         (f"Z23-Z{DZ_JMAX}", slice(layout.N_ZK, None))):
            rel = (np.linalg.norm(model[k, j] - fresh[k, j], axis=0)
                   / np.linalg.norm(fresh[k, j], axis=0))
            lines.append(f"off-grid field ({p[0]:+.4f}, {p[1]:+.4f}) deg vs a fresh finite "
                         f"difference, {label}: per-DoF relative difference median "
                         f"{np.median(rel):.2e}, max {rel.max():.2e} "
                         f"({DOF_NAMES[int(np.argmax(rel))]})")
    return lines


def write_dz_note(dz: np.ndarray, fields: np.ndarray, checks: list[str], wall_s: float,
                  nx: int) -> None:
    import batoid
    import galsim

    sha = hashlib.sha256(DZ_NPY.read_bytes()).hexdigest()
    text = f"""# {DZ_NPY.name}: provenance

Made by `tools/make_sensitivity.py --dz` (this project) on {_dt.date.today().isoformat()} in
{wall_s:.0f} s, batoid {batoid.__version__}, galsim {galsim.__version__}, numpy
{np.__version__}, Python {platform.python_version()}. Command:

    .venv/bin/python tools/make_sensitivity.py --dz          # regenerate
    .venv/bin/python tools/make_sensitivity.py --dz --check  # recompute and compare

- **What:** the wavefront sensitivity as a double Zernike: float64 array of shape
  {dz.shape}, index `[k, j, d]`: k the field Noll index (1..{dz.shape[0] - 1}; row 0 zero), j
  the pupil Noll index (4..{dz.shape[1] - 1}; 0..3 zero; the controller models 4..22, and
  23..{dz.shape[1] - 1} are what the estimator aliases into them), d the DoF. **nm of
  wavefront (OPD) per DoF unit** (µm, or degrees for rx/ry), **wavefront sign**
  (`wavefront_change = A @ dof_change`),
  **batoid_rubin/OCS DoF convention** (`cwfs_msgs/DofCorrection`, and
  `cwfs_ros.sim.perturbed_telescope`'s default), telescope frame (unrotated camera).
- **Evaluate** with `galsim.zernike.DoubleZernike(dz[:, :, d], uv_inner=0, uv_outer=
  {DZ_FIELD_RADIUS_DEG}, xy_inner={DZ_PUPIL_INNER_M}, xy_outer={DZ_PUPIL_OUTER_M})` at field
  points (deg, batoid field frame), as `cwfs_ros.ofc.control._eval_double_zernike` evaluates
  ts_ofc's matrix (`configurations/lsst.yaml` radii): its `.coef[4:23]` are nm per DoF unit.
- **How:** central finite differences (half-steps as `sensitivity_bundled_r.npy`: M2 dz 10 µm,
  dx/dy 100 µm, rx/ry 0.005 deg; camera dz 10 µm, dx/dy 100 µm, rx/ry 0.01 deg; bending
  0.05 µm) of batoid.zernike (r band, `LSST_r.yaml`, {WAVELENGTH_NM:g} nm, annular Noll
  4..{DZ_JMAX} with eps {DZ_EPS:.5f} = 2.558 / 4.18, nx={nx}) of the in-focus
  `perturbed_telescope(dof, "r")`, at {fields.shape[0]} field points (the centre and rings
  at {", ".join(f"{r:g}" for r in DZ_RING_RADII_DEG)} deg of
  {", ".join(str(n) for n in DZ_RING_POINTS)} points: the five Gaussian-quadrature radii, one
  between the outer two, the edge; the corners lie on the 1.708 ring), then a fit of field
  Zernikes Noll 1..{dz.shape[0] - 1} (radius {DZ_FIELD_RADIUS_DEG} deg) per pupil term and
  DoF, each field point weighted by 1 / |column there| (relative error balanced).
- **Limits:** near the field edge vignetting sets in and some bending columns change steeply
  with the field (M1M3 mode 19 grows 15x from 1.25 to 1.75 deg); a smooth double Zernike
  cannot follow that. The worst columns at the corners are listed below.
- **Approximation:** bending modes are the j <= 28 Zernike part of batoid_rubin's legacy modes
  (see `sensitivity_bundled_r.md`).
- **Checks** (`--dz --check` prints them again):
""" + "".join(f"  - {c}\n" for c in checks) + f"""- sha256 `{sha}`
"""
    DZ_NOTE.write_text(text, encoding="utf-8")


def main_dz(check: bool, nx: int) -> int:
    t0 = time.perf_counter()
    fields = dz_fields_deg()
    dz = fit_dz(fields, dz_columns(fields, nx=nx))
    wall = time.perf_counter() - t0
    if check:
        old = np.load(DZ_NPY)
        if old.shape != dz.shape:
            print(f"bundled shape {old.shape} != recomputed {dz.shape}")
            return 1
        err = np.abs(old - dz).max()
        print(f"max |bundled - recomputed| = {err:.3g} nm per DoF unit")
        print("\n".join(dz_checks(old, nx)))
        return 0 if err <= 1e-6 * np.abs(dz).max() else 1
    np.save(DZ_NPY, dz)
    checks = dz_checks(dz, nx)
    print("\n".join(checks))
    write_dz_note(dz, fields, checks, wall, nx)
    print(f"wrote {DZ_NPY} and {DZ_NOTE} ({wall:.0f} s)")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="recompute and compare with the bundled file; write nothing")
    ap.add_argument("--dz", action="store_true",
                    help="the double-Zernike matrix (config/ofc/sensitivity_dz_bundled.npy)")
    ap.add_argument("--nx", type=int, default=DZ_NX, help="pupil grid of --dz")
    args = ap.parse_args()
    if args.dz:
        return main_dz(args.check, args.nx)
    a, nonlin = compute()
    table = compare_ts_ofc(a)
    print("\n".join(table))
    if args.check:
        old = np.load(OUT_NPY)
        err = np.abs(old - a).max()
        print(f"max |bundled - recomputed| = {err:.3g} nm per DoF unit")
        return 0 if err <= 1e-6 * np.abs(a).max() else 1
    np.save(OUT_NPY, a)
    write_note(a, nonlin, table)
    print(f"wrote {OUT_NPY} and {OUT_NOTE}")
    return 0


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    raise SystemExit(main())
