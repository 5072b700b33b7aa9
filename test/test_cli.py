"""The ``cwfs-ros`` command line, run as a subprocess on the bundled ZEMAX example pair.

Known answer: the F1.23 paraxial pair carries 0.25 wave of Z7 injected in ZEMAX, so the
estimate of Z7 lies near 190 nm (the published reference output gives ~189 nm).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cwfs_ros.wfs.io import read_image

ROOT = Path(__file__).resolve().parents[1]
PAIR_DIR = ROOT / "test" / "data" / "zemax" / "F1.23_1mm_v61"
INTRA, EXTRA = PAIR_DIR / "z7_0.25_intra.txt", PAIR_DIR / "z7_0.25_extra.txt"
GEOMETRY = ["--instrument", "paraxial", "--defocal-offset", "1.0",
            "--field-intra", "0", "0", "--field-extra", "0", "0"]


def run_cli(*args: str | Path, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "cwfs_ros.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)


def estimate_json(intra: Path, extra: Path, *extra_args: str | Path) -> dict:
    proc = run_cli("estimate", intra, extra, *GEOMETRY, "--json", *extra_args)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)  # stdout holds the JSON document and nothing else


@pytest.fixture(scope="module")
def text_result(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """The text pair through the CLI, with --json and --plot together."""
    png = tmp_path_factory.mktemp("plot") / "result.png"
    return estimate_json(INTRA, EXTRA, "--plot", png), png


def test_json_output_known_z7(text_result: tuple[dict, Path]) -> None:
    out, _ = text_result
    assert out["noll"] == list(range(4, 23))
    assert len(out["zernikes_nm"]) == 19 and len(out["intrinsic_nm"]) == 19
    assert 180.0 < out["zernikes_nm"][3] < 200.0  # Z7: the injected 0.25 wave
    others = np.delete(np.asarray(out["zernikes_nm"]), 3)
    assert np.abs(others).max() < 20.0
    # lsq is the default solver of the CLI (exp, the paper's, stays selectable).
    assert out["instrument"] == "paraxial" and out["solver"] == "lsq"
    assert not out["caustic"] and out["iterations"] >= 1


def test_plot_is_a_reasonable_png(text_result: tuple[dict, Path]) -> None:
    import matplotlib.image as mpimg

    _, png = text_result
    assert png.is_file() and png.stat().st_size > 10_000
    img = mpimg.imread(png)
    h, w = img.shape[:2]
    assert 400 <= h <= 3000 and 600 <= w <= 4000
    assert img.std() > 0.05  # not a blank canvas


def test_human_output_table_and_status() -> None:
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--iterations", "3")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:1] == ["Noll"])
    rows = [line.split() for line in lines[header + 1:header + 20]]
    assert [int(r[0]) for r in rows] == list(range(4, 23))
    assert 150.0 < float(rows[3][1]) < 220.0  # Z7, after only 3 outer iterations
    status = lines[header + 20]
    assert "caustic: no" in status and "iterations: 3" in status and "wall time" in status


@pytest.mark.parametrize("fmt", ["npy", "fits"])
def test_npy_and_fits_round_trip(fmt: str, tmp_path: Path,
                                 text_result: tuple[dict, Path]) -> None:
    """The pair, flipped into the focal-plane frame on reading, written back out as .npy or
    FITS: the CLI reads those unflipped and gives the same Zernikes as from the text files."""
    paths = []
    for side, src in (("intra", INTRA), ("extra", EXTRA)):
        data = read_image(src)
        dest = tmp_path / f"{side}.{fmt}"
        if fmt == "npy":
            np.save(dest, data)
        else:
            from astropy.io import fits

            fits.PrimaryHDU(data.astype(np.float32)).writeto(dest)
        paths.append(dest)
    out = estimate_json(*paths)
    ref, _ = text_result
    tol = 1e-6 if fmt == "npy" else 0.05  # FITS stored as float32
    np.testing.assert_allclose(out["zernikes_nm"], ref["zernikes_nm"], atol=tol)


def test_non_finite_image_is_a_clean_error(tmp_path: Path) -> None:
    bad = read_image(INTRA)
    bad[60, 60] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    np.save(tmp_path / "good.npy", read_image(EXTRA))
    proc = run_cli("estimate", tmp_path / "bad.npy", tmp_path / "good.npy", *GEOMETRY)
    assert proc.returncode == 2
    assert proc.stderr.startswith("cwfs-ros estimate: error:")
    assert "non-finite" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stdout == ""


def test_missing_file_is_a_clean_error(tmp_path: Path) -> None:
    proc = run_cli("estimate", tmp_path / "nope.npy", EXTRA, *GEOMETRY)
    assert proc.returncode == 2
    assert "cwfs-ros estimate: error:" in proc.stderr and "nope.npy" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_bad_config_is_a_clean_error() -> None:
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY[2:], "--instrument", "no_such_scope")
    assert proc.returncode == 2
    assert "unknown instrument" in proc.stderr and "Traceback" not in proc.stderr


def test_bad_seeing_is_a_clean_error() -> None:
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--seeing", "-1")
    assert proc.returncode == 2
    assert "seeing_fwhm_arcsec must be in [0, 10]" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_bogus_solver_rejected_by_argparse() -> None:
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--solver", "bogus")
    assert proc.returncode == 2
    assert "invalid choice: 'bogus'" in proc.stderr and "usage:" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_version_and_missing_command() -> None:
    from cwfs_ros import __version__

    proc = run_cli("--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"cwfs-ros {__version__}"
    assert run_cli().returncode == 2


def test_plot_result_without_iterations(tmp_path: Path) -> None:
    """A result that hit caustic before any iteration (no history, no compensated images)
    still plots, from the preprocessed stamps it carries."""
    from cwfs_ros.cli.plotting import plot_result

    stamp = SimpleNamespace(image=read_image(INTRA))
    result = SimpleNamespace(
        noll=np.arange(4, 23), zernikes_nm=np.zeros(19), intrinsic_nm=np.zeros(19),
        history_nm=np.zeros((0, 22)), caustic=True, converged=False, iterations=0,
        wall_time_s=0.1, instrument="paraxial", band="r", wavelength_nm=622.0, solver="exp",
        field_deg=(0.0, 0.0), masks={}, compensated={}, inputs={"intra": stamp},
    )
    out = plot_result(result, tmp_path / "empty.png")
    assert out == tmp_path / "empty.png" and out.stat().st_size > 0


def test_pair_demo_recentres_a_donut_that_its_chief_ray_puts_off_the_stamp(tmp_path: Path
                                                                          ) -> None:
    """Seed 14 draws 2 um of wavefront (M2 decentred by 390 um), which moves the donut off
    the stamp centred on its chief ray: the pair is rendered again centred on its light,
    as a pipeline cuts stamps, and estimated."""
    proc = run_cli("pair-demo", "--out", tmp_path, "--seed", "14")
    assert proc.returncode == 0, proc.stderr
    assert "donut is cut by the stamp edge" in proc.stdout
    assert "rendered again, each stamp centred on its donut's light" in proc.stdout
    rms = float(next(ln for ln in proc.stdout.splitlines()
                     if ln.startswith("RMS error")).split()[2])
    assert rms < 40.0, proc.stdout


def test_pair_demo_ray_traces_estimates_and_reports(tmp_path: Path) -> None:
    """A perturbed LSST pair, its estimate against truth, a figure."""
    proc = run_cli("pair-demo", "--out", tmp_path, "--photons", "4e5", "--seed", "2")
    assert proc.returncode == 0, proc.stderr
    png = tmp_path / "demo_estimate.png"
    assert f"report: {png.resolve()}" in proc.stdout
    assert png.stat().st_size > 10_000
    saved = np.load(tmp_path / "demo_pair.npz")
    assert saved["intra"].shape == (160, 160) and saved["truth_nm"].shape == (19,)
    # The perturbation with its units; lsq, the default solver.
    pert = next(ln for ln in proc.stdout.splitlines() if ln.startswith("perturbation:"))
    assert pert.count(" um,") == 6 and pert.count(" deg") == 4, pert
    assert "solver lsq" in proc.stdout
    rms_line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RMS error"))
    # Several hundred nm of wavefront, recovered to tens of nm at this photon count.
    assert float(rms_line.split()[2]) < 40.0
    assert np.sqrt(np.sum(saved["truth_nm"] ** 2)) > 150.0
    # One table (estimate, truth, error, design), and the command that estimates the saved
    # images again, which gives the same estimate.
    assert proc.stdout.count("Noll") == 1, proc.stdout
    again = next(ln for ln in proc.stdout.splitlines() if ln.startswith("the same pair again"))
    argv = again.split(": ", 1)[1].split()
    assert argv[:2] == ["cwfs-ros", "estimate"], again
    rerun = run_cli(*argv[1:], "--json")
    assert rerun.returncode == 0, rerun.stderr
    table = {int(ln.split()[0]): float(ln.split()[1]) for ln in proc.stdout.splitlines()
             if ln.split() and ln.split()[0].isdigit() and len(ln.split()) == 5}
    got = json.loads(rerun.stdout)
    z = dict(zip(got["noll"], got["zernikes_nm"], strict=True))
    assert set(table) == set(range(4, 23))
    assert all(abs(z[j] - table[j]) < 0.051 for j in table), (z, table)


@pytest.mark.ros
def test_demo_runs_the_closed_loop_and_writes_its_report(tmp_path: Path) -> None:
    """The README's main job, small: 3 visits of the real graph, the report, the verdict."""
    proc = run_cli("demo", "--out", tmp_path, "--visits", "3", "--photons", "2e5",
                   "--wavefront-error", "500", timeout=240)
    assert proc.returncode == 0, proc.stderr
    html = tmp_path / "report.html"
    assert f"report: {html.resolve()}" in proc.stdout
    assert (tmp_path / "closed_loop.png").stat().st_size > 50_000
    summary = json.loads((tmp_path / "summary.json").read_text())
    e = summary["true_error_nm"]
    assert len(e) == 3 and all(summary["corrections_valid"])
    # The start is the asked-for 500 nm (scaled perturbation), and the loop closes on it.
    assert abs(e[0] - 500.0) < 25.0, e
    assert e[2] < e[0] / 3.0, e
    rows = (tmp_path / "visits.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("visit,")
    assert "<img src=\"closed_loop.png\"" in html.read_text()


def test_demo_rejects_bad_arguments(tmp_path: Path) -> None:
    proc = run_cli("demo", "--out", tmp_path, "--wavefront-error", "-3")
    assert proc.returncode == 2
    assert "--wavefront-error must be > 0" in proc.stderr
    proc = run_cli("demo", "--out", tmp_path, "--params", tmp_path / "missing.yaml")
    assert proc.returncode == 2 and "no such file" in proc.stderr
    proc = run_cli("demo", "--out", tmp_path, "--seeing", "20")
    assert proc.returncode == 2 and "--seeing must be in [0, 10]" in proc.stderr
