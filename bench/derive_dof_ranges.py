"""Derive the DoF clip ranges of ``config/ofc/dof.yaml`` from ts_ofc's data, and check them.

ts_ofc builds its ``range-fwhm`` normalisation weights as ``w_i = r_i * f_i``:

* ``r_i`` the DoF's range: the hexapod strokes ``rb_stroke`` (µm, deg) for the rigid body;
  ``(force_range / 20) / max|actuator force per µm of mode|`` for bending modes
  (134 N for M1M3, 45 N for M2);
* ``f_i`` the DoF's PSF-FWHM sensitivity (arcsec per DoF unit): the field-averaged root sum
  square over Noll 4..28 of ``zernike_coefficient_um * c_j``, where ``c_j`` is the FWHM of
  a 1-µm Zernike (2 sqrt(2 ln 2) x the per-axis RMS wavefront slope over the 8.36 m,
  0.612-obscured pupil, in arcsec).

The bending-mode force tables ts_ofc uses are not in this repository, so the bending ranges
are recovered here as ``r_i = w_i / f_i``. The same inversion applied to the rigid body
gives the ts_ofc strokes for dz to 0.02 % (5900 / 8700 µm) and within ~12 % for dx/dy/rx/ry of
M2 and the camera translation, which validates the recipe (field average over ts_ofc's
Gaussian-quadrature field points, Gauss-Legendre ring weights). The camera tilt comes out at
0.013 deg instead of the 0.24 deg stroke: the weights file was evidently made with a smaller
camera tilt range, so dof.yaml keeps the stroke there.

Usage: ``python bench/derive_dof_ranges.py [--write]`` (``--write`` rewrites dof.yaml).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import galsim
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cwfs_ros.ofc import control  # noqa: E402

# ts_ofc BaseOFCData.rb_stroke: M2 dz, dx, dy [µm], rx, ry [deg]; camera the same.
RB_STROKE = np.array([5900.0, 6700.0, 6700.0, 0.12, 0.12, 8700.0, 7600.0, 7600.0, 0.24, 0.24])
JMAX = 28


def fwhm_per_um(jmin: int = 4, jmax: int = JMAX) -> np.ndarray:
    """FWHM (arcsec) contributed by 1 µm of each Noll j in [jmin, jmax]."""
    r_out = 8.36 / 2
    out = []
    for j in range(jmin, jmax + 1):
        coef = np.zeros(j + 1)
        coef[j] = 1.0
        z = galsim.zernike.Zernike(coef, R_outer=r_out, R_inner=0.612 * r_out)
        slope_rms = np.sqrt(np.sum(z.gradX.coef**2 + z.gradY.coef**2) / 2)  # µm / m
        out.append(2 * np.sqrt(2 * np.log(2)) * np.rad2deg(slope_rms * 1e-6) * 3600)
    return np.array(out)


def fwhm_sensitivity() -> np.ndarray:
    """Field-averaged FWHM sensitivity f_i (arcsec per DoF unit), (50,)."""
    cfg_dir = control.ofc_config_dir()
    gq = control._load_yaml(str(cfg_dir / "sample_points" / "lsst_gaussian_quadrature_points.yaml"))
    pts = np.array([gq[k] for k in sorted(gq)], dtype=float)[1:]  # (0, 0) has zero weight
    radius = np.hypot(pts[:, 0], pts[:, 1])
    nodes, ring_w = np.polynomial.legendre.leggauss(5)
    ring_r = np.sqrt((1 + nodes) / 2) * 1.75
    q = ring_w[np.argmin(np.abs(radius[:, None] - ring_r[None, :]), axis=1)]
    q /= q.sum()
    dz = np.asarray(control._load_yaml(str(cfg_dir / control._TS_OFC_MATRIX)))
    basis = galsim.zernike.zernikeBasis(dz.shape[0] - 1, pts[:, 0], pts[:, 1], R_outer=1.75)
    ev = np.einsum("kf,kjd->fjd", basis, dz)[:, 4 : JMAX + 1, :]  # µm, (n_pts, 25, 50)
    fw = ev * fwhm_per_um()[None, :, None]
    return np.sqrt(np.sum(np.sum(fw**2, axis=1) * q[:, None], axis=0))


def sig(x: float, n: int = 3) -> float:
    return float(f"{x:.{n}g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="rewrite config/ofc/dof.yaml")
    args = ap.parse_args()
    w = control.load_normalization_weights("range-fwhm")
    f = fwhm_sensitivity()
    r_derived = w / f
    names = (["M2_dz", "M2_dx", "M2_dy", "M2_rx", "M2_ry",
              "Cam_dz", "Cam_dx", "Cam_dy", "Cam_rx", "Cam_ry"]
             + [f"M1M3_B{i}" for i in range(1, 21)] + [f"M2_B{i}" for i in range(1, 21)])
    units = ["um", "um", "um", "deg", "deg"] * 2 + ["um"] * 40
    print(f"{'idx':>3} {'name':<9} {'unit':<4} {'w/f':>11} {'rb_stroke':>10}")
    for i in range(control.N_DOF):
        stroke = f"{RB_STROKE[i]:10.4g}" if i < 10 else ""
        print(f"{i:3d} {names[i]:<9} {units[i]:<4} {r_derived[i]:11.4g} {stroke}")
    if not args.write:
        return
    lines = [HEADER]
    for i in range(control.N_DOF):
        if i < 10:
            rng = RB_STROKE[i]
            note = f"ts_ofc rb_stroke; w/f gives {sig(r_derived[i])}"
        else:
            rng = sig(r_derived[i])
            note = "range-fwhm w / f"
        step = sig(0.1 * rng, 2)
        lines.append(f"  - {{index: {i}, name: {names[i]}, unit: {units[i]}, range: {rng:g}, "
                     f"max_step: {step:g}}}  # {note}")
    out = control.ofc_config_dir() / "dof.yaml"
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {out}")


HEADER = """\
# The 50 active-optics degrees of freedom, in ts_ofc order: the single source of truth for
# names, units, clip ranges and per-visit step limits (read by cwfs_ros.ofc.control).
#
#   index 0-4   M2 hexapod dz, dx, dy [um], rx, ry [deg]
#   index 5-9   camera hexapod dz, dx, dy [um], rx, ry [deg]
#   index 10-29 M1M3 bending modes 1-20 [um]
#   index 30-49 M2 bending modes 1-20 [um]
#
# range: symmetric clip limit of the accumulated commanded state, |x_i| <= range_i.
#   * rigid body (0-9): ts_ofc's hexapod strokes (BaseOFCData.rb_stroke: 5900, 6700, 6700 um,
#     0.12, 0.12 deg for M2; 8700, 7600, 7600 um, 0.24, 0.24 deg for the camera).
#   * bending (10-49): recovered from ts_ofc's normalization_weights/range-fwhm.yaml, whose
#     entries are w_i = range_i * fwhm_i, by dividing out fwhm_i (the field-averaged PSF-FWHM
#     sensitivity of the DoF, recomputed from the ts_ofc sensitivity matrix); ts_ofc's own
#     bending ranges come from actuator force limits (134 N M1M3, 45 N M2, / 20 modes) whose
#     force tables are not in this repository. The same inversion reproduces the dz strokes
#     to 0.02 % and the M1M3 modes 1-11 to <7 % of force limits computed from batoid_rubin's
#     legacy bend forces, but gives tiny ranges for the nearly invisible modes (M1M3 12, 15,
#     16, 20; M2 18-20): those are effectively frozen. See bench/derive_dof_ranges.py, which
#     generated this file.
# max_step: default largest |correction| per visit = 10 % of range (2 significant figures), so
#   a full-range excursion takes at least 10 visits. Tune per hardware.
# Note: the ts_ofc matrix yaml header says arcsec for rx/ry; its numbers are per degree.
dofs:"""


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
