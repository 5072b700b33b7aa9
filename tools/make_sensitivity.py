#!/usr/bin/env python3
"""Compute the bundled 76x50 wavefront sensitivity matrix from the batoid simulator.

    .venv/bin/python tools/make_sensitivity.py          # writes config/ofc/sensitivity_bundled_r.*
    .venv/bin/python tools/make_sensitivity.py --check  # recompute and compare, write nothing

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

from cwfs_ros.core import control as C  # noqa: E402
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


def corner_fields() -> list[tuple[float, float]]:
    geo = load_corner_geometry()
    return [geo[c].mid_field_deg for c in C.CORNER_NAMES]


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
    a = np.zeros((C.N_MEAS, N_DOF))
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
    fld = ", ".join(f"{c} ({x:+.4f}, {y:+.4f})" for c, (x, y) in zip(C.CORNER_NAMES, fields,
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="recompute and compare with the bundled file; write nothing")
    args = ap.parse_args()
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
    raise SystemExit(main())
