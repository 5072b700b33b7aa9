#!/usr/bin/env python3
"""Measure how the wavefront estimator reads the wavefront at each corner sensor.

    .venv/bin/python tools/make_estimator_response.py [--workers 2]
        # writes config/ofc/estimator_response_r.npz and .md

The estimator fits Z4-Z22 to a split donut pair. It does not report the true Z4-Z22 of the
wavefront: terms beyond Z22 are partly read into Z4-Z22 (aliasing), each term of Z4-Z22 is
read with a gain near but not equal to 1, and the design wavefront itself is read with an
offset. Linearised about the design, per corner c, in the camera frame:

    z_est = z + (G_c - I) dz_4..22 + A_c dz_23..37 + b_c

with ``dz`` the true wavefront's change from the design at the corner's mid-point (batoid,
annular Noll, eps 0.61, nm of OPD), ``G_c`` (19 x 19), ``A_c`` (19 x 15) and ``b_c`` (19,)
the estimator's reading of the design less the true design. The controller's measurement
model with ``--measurement_model estimator`` (``cwfs_ros.ofc.model``) is built from them.

How. Each of Z4..Z37 is stepped by itself as a pure annular Zernike sag on M1 (a sag of s
gives about 1.94 s of wavefront, with a few per cent of cross-talk into other terms, which
the fit below removes). For each step ``±S`` each corner's split pair is rendered noise-free
(quasi-random pupil, no Poisson noise, 0.7 arcsec seeing, ``N_RAYS`` rays, the same random
numbers for ``+S`` and ``-S``) and estimated with the shipped solver (lsq, Z4-Z22); batoid
gives the true Z4..Z37 at the mid-point of the pair. With ``X`` (34 x 34) the true changes
and ``Y`` (19 x 34) the read ones, ``[G A] = Y X^-1``. ``b`` is the mean over
``NOMINAL_SEEDS`` renders of the design. At rotator angle 0 the camera frame is batoid's
global frame; an unperturbed telescope is symmetric under the camera's rotation, so the
camera-frame response holds at every angle.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cwfs_ros import layout  # noqa: E402
from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ofc.model import (  # noqa: E402
    ESTIMATOR_RESPONSE_BAND,
    ESTIMATOR_RESPONSE_FILENAME,
    RESPONSE_NOLL_HIGH,
)

BAND = ESTIMATOR_RESPONSE_BAND
WAVELENGTH_NM = 622.0
SEEING_ARCSEC = 0.7
N_RAYS = 2**20  # per donut; a power of 2 keeps the Sobol sequence balanced
NOMINAL_SEEDS = (1, 2, 3)
STEP_NM = 50.0  # wavefront of each Zernike step (sag = STEP_NM / 1.94)
M1_WAVEFRONT_PER_SAG = 1.94  # nm of wavefront per nm of M1 sag near the pupil
TRUTH_NX = 128  # batoid.zernike pupil grid
OUT_NPZ = C.ofc_config_dir() / ESTIMATOR_RESPONSE_FILENAME
OUT_NOTE = OUT_NPZ.with_suffix(".md")
NOLL_ALL = tuple(range(layout.NOLL_MIN, RESPONSE_NOLL_HIGH + 1))  # 4..37


def m1_zernike_telescope(noll: int, sag_m: float):
    """The design telescope with ``sag_m`` [m] of annular Noll ``noll`` (eps 0.61, the
    estimator's) added to M1's sag."""
    from cwfs_ros.sim import perturbed_telescope
    from cwfs_ros.validation.common import EPS, R_PUPIL_M, with_m1_zernike_sag

    tel = perturbed_telescope(np.zeros(layout.N_DOF), BAND)
    return tel if sag_m == 0.0 else with_m1_zernike_sag(tel, noll, sag_m, EPS * R_PUPIL_M)


def read_and_truth(corner: str, noll: int, sag_m: float, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(19,) the estimator's Z4-Z22 and (34,) batoid's Z4-Z37 [nm] at ``corner`` for the
    telescope with ``sag_m`` of Z_noll on M1 (noise-free render, ``default_rng(seed)``)."""
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.validation.readings import (
        ReadingSettings,
        corner_fields_deg,
        corner_reading_nm,
    )

    tel = m1_zernike_telescope(noll, sag_m)
    settings = ReadingSettings(n_rays=N_RAYS, seed=seed, wavelength_nm=WAVELENGTH_NM,
                               seeing_arcsec=SEEING_ARCSEC)
    est = corner_reading_nm(tel, corner, settings)
    truth = true_zernikes_nm(tel, corner_fields_deg(corner)[2], wavelength_nm=WAVELENGTH_NM,
                             jmax=RESPONSE_NOLL_HIGH, nx=TRUTH_NX)
    return est, np.asarray(truth)


def step_job(corner: str, noll: int) -> tuple[str, int, np.ndarray, np.ndarray]:
    """(corner, noll, d_read (19,), d_true (34,)): the change between ``+S`` and ``-S``."""
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    sag = STEP_NM / M1_WAVEFRONT_PER_SAG * 1e-9
    ep, tp = read_and_truth(corner, noll, +sag, 1)
    em, tm = read_and_truth(corner, noll, -sag, 1)
    return corner, noll, ep - em, tp - tm


def nominal_job(corner: str, seed: int) -> tuple[str, int, np.ndarray, np.ndarray]:
    """(corner, seed, read (19,), true (34,)) of the design telescope."""
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    est, truth = read_and_truth(corner, 4, 0.0, seed)
    return corner, seed, est, truth


def measure(workers: int) -> dict[str, np.ndarray]:
    """G (4, 19, 19), A (4, 19, 15), b (4, 19) and the raw steps, all corners."""
    nc, nk = layout.N_CORNERS, len(NOLL_ALL)
    d_read, d_true = np.zeros((nc, nk, layout.N_ZK)), np.zeros((nc, nk, nk))
    reads, truths = np.zeros((nc, len(NOMINAL_SEEDS), layout.N_ZK)), np.zeros((nc, nk))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        steps = [pool.submit(step_job, c, k) for c in layout.CORNERS for k in NOLL_ALL]
        noms = [pool.submit(nominal_job, c, s) for c in layout.CORNERS for s in NOMINAL_SEEDS]
        for n, f in enumerate(steps):
            c, k, dr, dt = f.result()
            ci, ki = layout.CORNERS.index(c), k - layout.NOLL_MIN
            d_read[ci, ki], d_true[ci, ki] = dr, dt
            print(f"{c} Z{k:2d}: read/true {dr[ki] / dt[ki] if ki < layout.N_ZK else 0:+.3f} "
                  f"[{n + 1}/{len(steps)}, {time.perf_counter() - t0:.0f} s]", flush=True)
        for f in noms:
            c, s, est, truth = f.result()
            ci = layout.CORNERS.index(c)
            reads[ci, NOMINAL_SEEDS.index(s)], truths[ci] = est, truth
    # Y = M X with X[:, k] the true change of step k: M = Y X^-1 per corner.
    m = np.einsum("ckj,ckl->cjl", d_read, np.linalg.inv(d_true))
    return dict(G=m[:, :, :layout.N_ZK], A=m[:, :, layout.N_ZK:],
                b=reads.mean(axis=1) - truths[:, :layout.N_ZK],
                design_true_nm=truths, design_read_nm=reads, step_read_nm=d_read,
                step_true_nm=d_true, wall_s=np.array(time.perf_counter() - t0))


def summary(r: dict[str, np.ndarray]) -> list[str]:
    """One line per corner: diag(G) range, the largest off-diagonal of G and of A, |b|."""
    lines = []
    for ci, c in enumerate(layout.CORNERS):
        g, a, b = r["G"][ci], r["A"][ci], r["b"][ci]
        off = g - np.diag(np.diag(g))
        i, j = np.unravel_index(np.argmax(np.abs(off)), off.shape)
        p, q = np.unravel_index(np.argmax(np.abs(a)), a.shape)
        spread = r["design_read_nm"][ci].std(axis=0, ddof=1)
        lines.append(
            f"{c}: diag(G) {np.diag(g).min():.2f}..{np.diag(g).max():.2f}, largest off-"
            f"diagonal Z{i + 4}<-Z{j + 4} {off[i, j]:+.2f}, largest A Z{p + 4}<-Z{q + 23} "
            f"{a[p, q]:+.1f}, |b| {np.linalg.norm(b):.1f} nm (seed-to-seed spread of the "
            f"design reading {np.sqrt((spread**2).sum()):.1f} nm rss)")
    return lines


def write_note(r: dict[str, np.ndarray], lines: list[str]) -> None:
    import batoid

    sha = hashlib.sha256(OUT_NPZ.read_bytes()).hexdigest()
    text = f"""# {OUT_NPZ.name}: provenance

Made by `tools/make_estimator_response.py` (this project) on
{_dt.date.today().isoformat()} in {float(r["wall_s"]):.0f} s, batoid {batoid.__version__},
numpy {np.__version__}, Python {platform.python_version()}. Command:

    .venv/bin/python tools/make_estimator_response.py --workers 2

- **What:** how the shipped estimator (lsq solver, Z4-Z22, 0.7 arcsec seeing) reads the
  wavefront at each corner, linearised about the design, camera frame, corners in
  `{", ".join(layout.CORNERS)}` order: `z_est = z + (G - I) dz_4..22 + A dz_23..37 + b`.
  `G` (4, 19, 19) and `A` (4, 19, 15) are dimensionless (nm read per nm of true wavefront),
  `b` (4, 19) nm: the estimator's reading of the design less batoid's design wavefront.
  Rows and columns are annular Noll (eps 0.61) Z4..Z22 (rows) and Z4..Z22 / Z23..Z37
  (columns), nm of OPD, wavefront sign.
- **How:** each of Z4..Z37 stepped by ±{STEP_NM:g} nm of wavefront as a pure Zernike sag
  on M1; each corner's split pair rendered noise-free ({N_RAYS} quasi-random rays per donut,
  the same random numbers for + and -) and estimated; batoid.zernike (nx {TRUTH_NX}) gives
  the true change at the pair's mid-point; `[G A] = Y X^-1`. `b` is the mean of
  {len(NOMINAL_SEEDS)} renders of the design (seeds {NOMINAL_SEEDS}).
- **Also stored:** `design_true_nm` (4, 34), `design_read_nm` (4, {len(NOMINAL_SEEDS)}, 19),
  `step_read_nm` (4, 34, 19), `step_true_nm` (4, 34, 34): the raw steps.
- **Figures:**
""" + "".join(f"  - {x}\n" for x in lines) + f"""- sha256 `{sha}`
"""
    OUT_NOTE.write_text(text, encoding="utf-8")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2, help="rendering processes")
    ap.add_argument("--out", type=Path, default=OUT_NPZ,
                    help="where to write (the provenance note only for the default)")
    args = ap.parse_args()
    r = measure(args.workers)
    lines = summary(r)
    print("\n".join(lines))
    np.savez(args.out, **r)
    if args.out == OUT_NPZ:
        write_note(r, lines)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    raise SystemExit(main())
