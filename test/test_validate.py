"""``cwfs-ros validate``: a fast subset of the paper's figures with independent expectations.

Expected values come from closed forms (inner products of Zernikes on an annulus), from the
injected amplitudes, or from a second model (a mirror-perturbed batoid telescope), never
from the code under test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_fig4_annular_identity_and_standard_cross_talk() -> None:
    from cwfs_ros.validation.paper import fig4_orthogonality

    eps = 0.61
    (verdict,), data = fig4_orthogonality(eps)
    g_std, g_ann = data["standard"], data["annular"]
    assert np.abs(g_ann - np.eye(22)).max() < 1e-6
    # Closed forms for circle Zernikes averaged over eps <= r <= 1, with <r^2> = (1+eps^2)/2:
    # Z1.Z4 = sqrt(3) <2r^2 - 1> = sqrt(3) eps^2; Z2.Z2 = <4 r^2 cos^2> = 1 + eps^2.
    assert g_std[0, 3] == pytest.approx(np.sqrt(3.0) * eps**2, abs=1e-9)
    assert g_std[1, 1] == pytest.approx(1.0 + eps**2, abs=1e-9)
    assert g_std[0, 0] == pytest.approx(1.0, abs=1e-12)
    assert verdict.passed


def test_deflected_rays_match_a_mirror_perturbed_telescope() -> None:
    """Rays tilted by -grad W trace like a telescope whose batoid wavefront gained +W."""
    import batoid
    from galsim.zernike import Zernike

    from cwfs_ros.sim.telescope import load_lsst
    from cwfs_ros.validation.common import trace_deflected

    tel = load_lsst("r")
    field, wl = (1.19, 1.19), 622.0
    coef = np.zeros(8)
    coef[7] = 1e-7  # 100 nm of Z7 sag on M1
    tel_m1 = tel.withSurface("M1", batoid.Sum([tel["M1"].surface,
                                               batoid.Zernike(coef, R_outer=4.18,
                                                              R_inner=2.558)]))
    th = np.deg2rad(field)
    dz = (batoid.zernike(tel_m1, *th, wl * 1e-9, jmax=22, eps=0.61, nx=128)
          - batoid.zernike(tel, *th, wl * 1e-9, jmax=22, eps=0.61, nx=128)) * wl
    w_coef = np.zeros(23)
    w_coef[4:] = dz[4:]  # tip/tilt moves the whole image: compared centroid-relative
    w = Zernike(w_coef * 1e-9, R_outer=4.18, R_inner=0.61 * 4.18)

    def grad(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return w.gradX(x, y) * 1e9, w.gradY(x, y) * 1e9  # nm per metre, as galsim's

    kw = dict(wavelength_nm=wl, n_rays=20000)
    xa, ya, oka, _ = trace_deflected(tel, field, -1.5, rng=np.random.default_rng(4),
                                     gradient=grad, **kw)
    xb, yb, okb, _ = trace_deflected(tel_m1, field, -1.5, rng=np.random.default_rng(4), **kw)
    xc, yc, okc, _ = trace_deflected(tel, field, -1.5, rng=np.random.default_rng(4), **kw)
    ok = oka & okb & okc

    def rel(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.stack([x[ok] - x[ok].mean(), y[ok] - y[ok].mean()])

    shift = np.sqrt(np.mean(np.sum((rel(xc, yc) - rel(xb, yb)) ** 2, axis=0)))
    resid = np.sqrt(np.mean(np.sum((rel(xa, ya) - rel(xb, yb)) ** 2, axis=0)))
    assert abs(dz[7]) > 150.0  # the probe is a real coma
    assert shift > 1e-6  # > 1 um of ray shift to reproduce ...
    assert resid < 0.02 * shift  # ... and reproduced to 2 %


def test_linearity_slope_on_small_paraxial_steps() -> None:
    from cwfs_ros.sim.paraxial import render_paraxial_pair
    from cwfs_ros.wfs import estimate_wavefront, load_instrument

    inst = load_instrument("paraxial")
    amps = np.array([100.0, 200.0, 300.0])
    got = []
    for a in amps:
        i, e = render_paraxial_pair(inst, {7: a}, npix=120, n_photons=2e6,
                                    rng=np.random.default_rng(7))
        r = estimate_wavefront(i, e, field_intra_deg=(0, 0), field_extra_deg=(0, 0),
                               instrument=inst)
        got.append(r.zernikes_nm[3])
    slope = np.polyfit(amps, got, 1)[0]
    assert slope == pytest.approx(1.0, abs=0.05)


def test_geometric_limit_is_found_on_the_ray_map() -> None:
    from cwfs_ros.sim.telescope import perturbed_telescope
    from cwfs_ros.validation.common import fold_fraction

    assert fold_fraction(perturbed_telescope(None), (1.185, 1.185), -1.0, 622.0) == 0.0
    dof = np.zeros(50)
    dof[3] = 0.08  # M2 rx: ~7 um of Z5 at the corner, far past the 1 mm limit
    assert fold_fraction(perturbed_telescope(dof), (1.185, 1.185), -1.0, 622.0) > 0.05


def test_faint_limit_crossing_interpolates_in_log_log() -> None:
    from cwfs_ros.validation.beyond import _crossing

    n = np.array([1e3, 1e4, 1e5])
    err = np.array([100.0, 30.0, 5.0])
    # Between (1e3, 100) and (1e4, 30) on a log-log line: 1e3 * 10^(ln 0.5 / ln 0.3).
    assert _crossing(n, err, 50.0) == pytest.approx(1e3 * 10 ** (np.log(0.5) / np.log(0.3)))
    assert _crossing(n, err, 1.0) is None
    assert _crossing(n, err, 200.0) == 1e3


def test_cli_writes_the_report_and_exits_zero(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", "cwfs_ros.cli", "validate", "--quick",
                           "--only", "fig4", "--out", str(tmp_path)], capture_output=True,
                          text=True, timeout=120, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "Fig. 4 orthogonality PASS" in proc.stdout.replace("  ", " ").replace("  ", " ")
    report = (tmp_path / "report.md").read_text()
    assert "fig4_orthogonality.png" in report and "PASS" in report
    assert (tmp_path / "fig4_orthogonality.png").stat().st_size > 10_000
    res = json.loads((tmp_path / "results.json").read_text())
    (v,) = res["sections"]["fig4"]["verdicts"]
    assert v["numbers"]["annular_max_dev"] < 1e-6 and v["numbers"]["standard_max_offdiag"] > 0.6
    assert res["meta"]["quick"] is True


def test_cli_rejects_an_unknown_section(tmp_path: Path) -> None:
    from cwfs_ros.cli.main import main

    assert main(["validate", "--only", "fig8", "--out", str(tmp_path)]) == 2


def test_noise_free_deflected_donut_traces_exactly_n_rays() -> None:
    """Fig. 10's noise-free images: exactly n quasi-random rays (no Poisson draw), and two
    scrambles of one atmosphere-deflected donut agree far better than random rays do."""
    from cwfs_ros.sim.telescope import load_lsst
    from cwfs_ros.validation.common import render_deflected

    tel = load_lsst("r")

    def tilt(x, y, t):  # a uniform 1 um/m OPD gradient (nm per m): a pure image shift
        return np.full_like(x, 1000.0), np.zeros_like(y)

    kw = dict(wavelength_nm=622.0, npix=160, n_photons=2**16, gradient=tilt)
    q = [render_deflected(tel, (0.0, 0.0), 1.5, rng=np.random.default_rng(s), noise_free=True,
                          **kw) for s in (1, 2)]
    r = [render_deflected(tel, (0.0, 0.0), 1.5, rng=np.random.default_rng(s), **kw)
         for s in (1, 2)]
    # On axis the donut is inside the stamp: every ray lands but the odd one grazing the
    # central obscuration's edge.
    assert all(2**16 - 10 <= a.sum() <= 2**16 for a in q)
    assert r[0].sum() != 2**16 or r[1].sum() != 2**16  # Poisson-drawn photon numbers
    lit = q[0] > 0.2 * q[0].max()
    assert np.std((q[0] - q[1])[lit]) < 0.5 * np.std((r[0] - r[1])[lit])
