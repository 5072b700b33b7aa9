"""The command line's defaults, exit codes, refusals, provenance and batch mode.

Each exit code is produced by the real command (a subprocess, as a user runs it) on the
bundled ZEMAX pairs: the F1.23 paraxial pair (0.25 wave of Z7 injected: Z7 near 190 nm)
and the FAM pairs of the LSST design at 1.5 mm.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_cli import EXTRA, GEOMETRY, INTRA, ROOT, run_cli

from cwfs_ros.wfs.io import read_image

FAM = ROOT / "test" / "data" / "zemax" / "FAM"
FAM_ARGS = ["--band", "g", "--wavelength", "500"]  # as the README's FAM runs
R22 = [FAM / "Image_intra_R22_S11.txt", FAM / "Image_extra_R22_S11.txt"]
R34 = [FAM / "Image_intra_R34_S12.txt", FAM / "Image_extra_R34_S12.txt"]
EXIT_FLAGGED = 3


def test_help_documents_every_exit_code():
    for argv in (["--help"], ["estimate", "--help"], ["batch", "--help"]):
        proc = run_cli(*argv)
        assert proc.returncode == 0
        text = proc.stdout
        assert "exit status:" in text, argv
        for code in ("0", "1", "2", "3", "130"):
            assert any(line.split()[:1] == [code] for line in text.splitlines()), (argv, code)


def test_lsq_is_the_default_solver_and_exp_fft_stay_selectable():
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--json")
    out = json.loads(proc.stdout)
    assert proc.returncode == 0 and out["solver"] == "lsq"
    assert 180.0 < out["zernikes_nm"][3] < 200.0  # the injected Z7
    for solver in ("exp", "fft"):
        proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--json", "--solver", solver)
        assert proc.returncode == 0 and json.loads(proc.stdout)["solver"] == solver
    import inspect

    from cwfs_ros.wfs import estimate_wavefront

    assert inspect.signature(estimate_wavefront).parameters["solver"].default == "lsq"


def test_result_repr_is_a_short_summary():
    from cwfs_ros.wfs import estimate_wavefront

    r = estimate_wavefront(read_image(INTRA), read_image(EXTRA), field_intra_deg=(0, 0),
                           field_extra_deg=(0, 0), instrument="paraxial",
                           defocal_offset_mm=1.0)
    text = repr(r)
    assert len(text) < 400 and "\n" not in text, text
    assert text.startswith("<WavefrontResult paraxial r 622 nm, lsq, field (0.0000, 0.0000)")
    assert f"Z4 {r.zernikes_nm[0]:.1f} nm" in text and "iterations" in text


def test_text_output_says_settled_and_swap_check():
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY)
    assert proc.returncode == 0
    assert ("inputs: field intra (0, 0) deg (command line), extra (0, 0) deg (command line); "
            "defocal offset 1 mm (command line)") in proc.stdout
    assert "converged" not in proc.stdout
    status = next(ln for ln in proc.stdout.splitlines() if ln.startswith("caustic:"))
    assert "settled: " in status and "swap check: off" in status
    assert "check plausible: pass" in proc.stdout and "check caustic: pass" in proc.stdout


def test_field_outside_the_field_of_view_is_refused():
    proc = run_cli("estimate", INTRA, EXTRA, "--instrument", "lsst", "--field-intra", "2.0",
                   "1.5", "--field-extra", "2.0", "1.5")
    assert proc.returncode == 2 and proc.stdout == ""
    assert "2.500 deg off axis, outside the field of view of lsst (2.1 deg" in proc.stderr
    # A field in arcseconds is named as such; a wavelength in micrometres too.
    proc = run_cli("estimate", INTRA, EXTRA, "--instrument", "lsst", "--field-intra", "-4517.6",
                   "-4285.1", "--field-extra", "-4285.1", "-4285.1")
    assert proc.returncode == 2 and proc.stdout == ""
    assert "outside the field of view of lsst" in proc.stderr
    assert "in arcseconds that is (-1.255, -1.19) deg" in proc.stderr, proc.stderr
    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--wavelength", "0.622")
    assert proc.returncode == 2 and proc.stdout == ""
    assert "outside 250-2500 nm (micrometres? 0.622 um = 622 nm)" in proc.stderr, proc.stderr



def test_a_field_at_the_edge_where_the_design_cannot_be_fitted_is_one_error_line():
    """2.05 deg off axis is inside LSST's 2.1 deg field of view, but its pupil is so
    vignetted that batoid cannot fit the design wavefront's 22 terms: exit 2, one line.
    (The FAM pair's 200-px stamps hold an LSST donut, so the field is what is refused.)"""
    proc = run_cli("estimate", *R22, "--instrument", "lsst", "--field-intra", "1.45",
                   "1.45", "--field-extra", "1.45", "1.45")
    assert proc.returncode == 2 and proc.stdout == "" and "Traceback" not in proc.stderr
    assert "the design wavefront cannot be fitted at field (1.45, 1.45) deg" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_a_whole_frame_given_to_estimate_names_the_frames_path(tmp_path: Path):
    frame = tmp_path / "frame.npy"
    np.save(frame, np.random.default_rng(0).poisson(30.0, (2000, 1000)).astype(float))
    proc = run_cli("estimate", frame, frame, "--field-intra", "-1.2", "-1.19",
                   "--field-extra", "-1.19", "-1.19")
    assert proc.returncode == 2 and proc.stdout == ""
    assert "a 2000x1000 image: estimate takes one donut per image" in proc.stderr, proc.stderr
    assert "input_mode frames" in proc.stderr


def test_lsst_admits_every_corner_sensor_and_the_fam_set():
    from cwfs_ros.wfs import load_instrument

    inst = load_instrument("lsst")
    corners = yaml.safe_load((ROOT / "config" / "sensors" / "lsst_corners.yaml").read_text())
    for c in corners["corners"].values():
        for side in ("intra", "extra"):
            inst.check_field(tuple(c[side]["field_deg"]))
    inst.check_field((0.706, 1.646))  # FAM R34_S12, 1.79 deg
    # The farthest pixel of a science raft: 1.5 and 2.5 raft pitches of 0.7056 deg.
    inst.check_field((1.5 * 0.7056, 2.5 * 0.7056))


def test_an_implausible_estimate_exits_3_and_prints_nothing():
    """FAM R22_S11, a pair near the axis, told a corner's field: its round donuts show no
    vignetting to refuse the field by, and the model's vignetted pupil reads tens of um."""
    wrong = ["--field-intra", "1.4", "-1.4", "--field-extra", "1.4", "-1.4"]
    proc = run_cli("estimate", *R22, *FAM_ARGS, *wrong)
    assert proc.returncode == EXIT_FLAGGED and proc.stdout == ""
    assert "flagged: plausible: largest departure from design" in proc.stderr
    assert "--allow-flagged" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("estimate", *R22, *FAM_ARGS, *wrong, "--allow-flagged", "--json")
    out = json.loads(proc.stdout)
    assert proc.returncode == 0 and "plausible" in out["flags"]
    assert {c["name"]: c["outcome"] for c in out["checks"]}["plausible"] == "fail"


def test_a_wrong_field_that_stays_plausible_warns_that_the_loop_has_not_settled():
    """FAM R34_S12 at its true field settles near its fixed point; told a field 0.55 deg
    away, the estimate is still plausible (no flag) but the loop keeps moving by nm, and the
    settled check says what to look at."""
    true = ["--field-intra", "0.706", "1.646", "--field-extra", "0.706", "1.646"]
    wrong = ["--field-intra", "1.176", "1.176", "--field-extra", "1.176", "1.176"]
    details = {}
    for name, field in (("true", true), ("wrong", wrong)):
        proc = run_cli("estimate", *R34, *FAM_ARGS, *field, "--json")
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out["flags"] == []
        details[name] = {c["name"]: c for c in out["checks"]}["settled"]["detail"]
    assert "WARNING" not in details["true"]
    assert details["wrong"].startswith("WARNING") and "field angles" in details["wrong"]
    assert {c["name"]: c for c in out["checks"]}["settled"]["warning"] is True


def test_batch_names_the_warnings_of_each_row(tmp_path: Path):
    """The R34 pair at its true field and told a wrong one: the table says which row's
    loop was still moving (``warnings``, ``last_update_nm``), not only ``settled``."""
    from astropy.table import Table

    table = tmp_path / "pairs.csv"
    rows = [f"{R34[0]},{R34[1]}," + f.replace(" ", ",")
            for f in ("0.706 1.646 0.706 1.646", "1.176 1.176 1.176 1.176")]
    table.write_text("intra,extra,field_intra_x,field_intra_y,field_extra_x,field_extra_y\n"
                     + "\n".join(rows) + "\n")
    proc = run_cli("batch", table, "--out", tmp_path / "out.ecsv", *FAM_ARGS, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = Table.read(tmp_path / "out.ecsv", format="ascii.ecsv")
    assert [str(w) for w in res["warnings"].filled("")] == ["", "settled"]
    assert res["last_update_nm"][1] > 1.0 > res["last_update_nm"][0]


def test_a_field_whose_vignetting_points_elsewhere_is_refused():
    """FAM R34_S12 given a field in another direction (its true one is (0.706, 1.646)):
    the donuts' vignetted lunes point the wrong way for it, refused before estimating."""
    for fx, fy in ((1.411, -1.411), (-0.706, 1.646), (1.646, 0.706)):
        wrong = ["--field-intra", str(fx), str(fy), "--field-extra", str(fx), str(fy)]
        proc = run_cli("estimate", *R34, *FAM_ARGS, *wrong)
        assert proc.returncode == 2 and proc.stdout == "", (fx, fy, proc.stderr)
        assert "looks turned or mirrored" in proc.stderr
        assert "that the field given is this image's" in proc.stderr


def test_a_caustic_estimate_exits_3():
    """The 1.5 mm FAM pair told 1.0 mm: the compensation folds."""
    proc = run_cli("estimate", *R22, *FAM_ARGS, "--field-intra", "0", "0", "--field-extra",
                   "0", "0", "--defocal-offset", "1.0")
    assert proc.returncode == EXIT_FLAGGED and proc.stdout == ""
    assert "flagged: caustic" in proc.stderr


@pytest.mark.parametrize("content, reason", [
    (b"\x89PNG\r\n\x1a\n" + bytes(64), "it is a PNG picture"),
    (b"1 2 3\n\x00\x01\x02\n", "binary data"),
    (b"one two\nthree four\n", "could not convert"),
    (b"1 2 3\n4 5\n6 7 8\n", "its rows differ in length: row 2 has 2 values, the rows before "
                            "it 3"),
])
def test_not_an_image_says_why(tmp_path: Path, content: bytes, reason: str):
    bad = tmp_path / "donut.png"
    bad.write_bytes(content)
    proc = run_cli("estimate", bad, EXTRA, *GEOMETRY)
    assert proc.returncode == 2 and proc.stdout == ""
    assert f"intra image {bad}: not an image: " in proc.stderr and reason in proc.stderr
    assert "codec" not in proc.stderr and "Traceback" not in proc.stderr


def test_json_carries_the_provenance_and_every_check():
    from cwfs_ros import __version__

    proc = run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--json")
    out = json.loads(proc.stdout)
    assert out["inputs"]["intra"]["path"] == str(INTRA)
    assert out["inputs"]["extra"]["sha256"] == hashlib.sha256(EXTRA.read_bytes()).hexdigest()
    assert (out["instrument"], out["band"], out["wavelength_nm"]) == ("paraxial", "r", 622.0)
    assert out["defocal_offset_mm"] == 1.0 and out["solver"] == "lsq"
    assert out["software"]["cwfs_ros"] == __version__ and "numpy" in out["software"]
    assert out["field_sources"] == {"intra": "command line", "extra": "command line"}
    checks = {c["name"]: c["outcome"] for c in out["checks"]}
    assert checks == {"field_of_view": "pass", "image_checks": "pass", "swap_check": "off",
                      "caustic": "pass", "plausible": "pass",
                      "settled": "yes" if out["converged"] else "no",
                      "text_images": "flipped"}
    assert out["flags"] == [] and out["swap_check"] == "off"
    assert not any(c["warning"] for c in out["checks"])
    assert out["inputs"]["intra"]["text_flipped"] is True


def _off_axis_pair(tmp_path: Path) -> tuple[list[Path], list[str]]:
    """A ray-traced pair of the perturbed LSST at (1, 1) deg as .npy files."""
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    dof = np.zeros(50)
    dof[[1, 2]] = (200.0, -150.0)  # M2 decentres (um): a wavefront with astigmatism and coma
    tel = perturbed_telescope(dof, band="r")
    rng = np.random.default_rng(3)
    paths = []
    for side, dz in (("intra", -1.5), ("extra", 1.5)):
        paths.append(tmp_path / f"{side}.npy")
        np.save(paths[-1], render_donut(tel, (1.0, 1.0), dz, wavelength_nm=622.0, npix=160,
                                        n_photons=1e6, rng=rng))
    return paths, ["--field-intra", "1", "1", "--field-extra", "1", "1"]


def test_text_images_are_said_to_be_flipped_and_a_refusal_names_the_flip(tmp_path: Path):
    """Arrays in the focal-plane frame written with numpy.savetxt: read with the ZEMAX
    row order (the default), both halves look mirrored and the refusal says that read as
    stored they pass; --no-text-flip estimates them as the .npy files, and says nothing."""
    (intra, extra), field = _off_axis_pair(tmp_path)
    texts = []
    for path in (intra, extra):
        texts.append(path.with_suffix(".txt"))
        np.savetxt(texts[-1], np.load(path))
    proc = run_cli("estimate", *texts, *field)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert "looks turned or mirrored" in proc.stderr
    assert "read as stored, the pair passes this check" in proc.stderr
    assert "--no-text-flip" in proc.stderr
    ref = json.loads(run_cli("estimate", intra, extra, *field, "--json").stdout)
    proc = run_cli("estimate", *texts, *field, "--no-text-flip", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    np.testing.assert_allclose(out["zernikes_nm"], ref["zernikes_nm"], atol=1e-6)
    assert {c["name"]: c["outcome"] for c in out["checks"]}["text_images"] == "as stored"
    assert out["inputs"]["intra"]["text_flipped"] is False
    # On axis no check can see the flip: text that does not look like a ZEMAX export,
    # flipped by default, is a WARNING (the ZEMAX pairs' is not: test above).
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    tel, rng, axis = perturbed_telescope(np.zeros(50), band="r"), np.random.default_rng(4), []
    for side, dz in (("intra", -1.5), ("extra", 1.5)):
        axis.append(tmp_path / f"axis_{side}.txt")
        np.savetxt(axis[-1], render_donut(tel, (0.0, 0.0), dz, wavelength_nm=622.0, npix=160,
                                          n_photons=5e5, rng=rng))
    proc = run_cli("estimate", *axis, "--field-intra", "0", "0", "--field-extra", "0", "0",
                   "--json")
    assert proc.returncode == 0, proc.stderr
    text = {c["name"]: c for c in json.loads(proc.stdout)["checks"]}["text_images"]
    assert text["warning"] and "do not look like a ZEMAX export" in text["detail"]


def test_a_wavelength_of_another_band_is_a_warning():
    """``--band u --wavelength 622``: the u filter traced at r's wavelength is estimated,
    with a WARNING check naming the band the wavelength belongs to (not a flag)."""
    proc = run_cli("estimate", *R22, "--band", "u", "--wavelength", "622", "--field-intra",
                   "0", "0", "--field-extra", "0", "0", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    band = {c["name"]: c for c in out["checks"]}["band"]
    assert band["outcome"] == "mismatch" and band["warning"] and not band["flags_estimate"]
    assert "nearer band r's effective wavelength (622 nm) than band u's" in band["detail"]
    proc = run_cli("estimate", *R22, *FAM_ARGS, "--field-intra", "0", "0", "--field-extra",
                   "0", "0", "--json")
    assert "band" not in {c["name"] for c in json.loads(proc.stdout)["checks"]}


def _fits_pair(tmp_path: Path, defocus: tuple[float, float] = (-1.0, 1.0)) -> list[Path]:
    from astropy.io import fits

    tmp_path.mkdir(exist_ok=True)
    out = []
    for side, src, dz in (("intra", INTRA, defocus[0]), ("extra", EXTRA, defocus[1])):
        hdu = fits.PrimaryHDU(read_image(src))
        hdu.header["FIELD_X"], hdu.header["FIELD_Y"], hdu.header["DEFOCUS"] = 0.0, 0.0, dz
        out.append(tmp_path / f"{side}.fits")
        hdu.writeto(out[-1])
    return out


def test_fits_headers_give_the_field_and_defocus(tmp_path: Path):
    pair = _fits_pair(tmp_path)
    proc = run_cli("estimate", *pair, "--instrument", "paraxial", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["defocal_offset_mm"] == 1.0 and out["field_intra_deg"] == [0.0, 0.0]
    assert out["field_sources"]["intra"] == "FITS header intra.fits"
    ref = json.loads(run_cli("estimate", INTRA, EXTRA, *GEOMETRY, "--json").stdout)
    np.testing.assert_allclose(out["zernikes_nm"], ref["zernikes_nm"], atol=1e-3)
    # Without header or option: said, not guessed.
    from astropy.io import fits

    bare = tmp_path / "bare.fits"
    fits.PrimaryHDU(read_image(INTRA)).writeto(bare)
    proc = run_cli("estimate", bare, pair[1], "--instrument", "paraxial")
    assert proc.returncode == 2 and "no field for the intra image" in proc.stderr


def test_unusable_geometry_is_one_error_line_before_any_work(tmp_path: Path):
    """A FITS keyword that is not a number, a defocal offset of 99 mm (a donut of 4000 px,
    whose pupil grid would take gigabytes), and a batch cell that is not a number: each is
    one error line (batch: that row's error, the others written)."""
    from astropy.io import fits

    hdu = fits.PrimaryHDU(read_image(INTRA))
    hdu.header["FIELD_X"], hdu.header["FIELD_Y"], hdu.header["DEFOCUS"] = 0.0, 0.0, "-1 mm"
    bad = tmp_path / "intra.fits"
    hdu.writeto(bad)
    proc = run_cli("estimate", bad, EXTRA, *GEOMETRY)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "DEFOCUS = '-1 mm' is not a number (mm)" in proc.stderr
    proc = run_cli("estimate", INTRA, EXTRA, "--instrument", "paraxial", "--defocal-offset",
                   "99", "--field-intra", "0", "0", "--field-extra", "0", "0", timeout=20)
    assert proc.returncode == 2 and "cannot hold a donut of radius 40" in proc.stderr
    table = tmp_path / "pairs.csv"
    table.write_text("intra,extra,field_intra_x,field_intra_y,field_extra_x,field_extra_y\n"
                     f"{INTRA},{EXTRA},abc,0,0,0\n{INTRA},{EXTRA},0,0,0,0\n")
    proc = run_cli("batch", table, "--out", tmp_path / "out.csv", "--instrument", "paraxial",
                   timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    from astropy.table import Table

    res = Table.read(tmp_path / "out.csv", format="ascii.csv")
    assert list(res["status"]) == ["error", "ok"]
    assert "column field_intra_x: 'abc' is not a number" in res["error"][0]
    # A misspelt optional column is kept as the user's own, and said not to be read.
    table.write_text("intra,extra,field_intra_x,field_intra_y,field_extra_x,field_extra_y,"
                     f"defocal_ofset_mm\n{INTRA},{EXTRA},0,0,0,0,1.0\n")
    proc = run_cli("batch", table, "--out", tmp_path / "out.csv", "--instrument", "paraxial",
                   timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert ("column 'defocal_ofset_mm' is not read (did you mean 'defocal_offset_mm'?)"
            in proc.stderr + proc.stdout)
    # FIELD_X without FIELD_Y: said so.
    hdu = fits.PrimaryHDU(read_image(INTRA))
    hdu.header["FIELD_X"] = 0.0
    half = tmp_path / "half.fits"
    hdu.writeto(half)
    proc = run_cli("estimate", half, EXTRA, "--instrument", "paraxial")
    assert proc.returncode == 2 and "has FIELD_X but not FIELD_Y" in proc.stderr


def test_fits_defocus_of_the_wrong_sign_is_refused(tmp_path: Path):
    pair = _fits_pair(tmp_path, defocus=(1.0, -1.0))
    proc = run_cli("estimate", *pair, "--instrument", "paraxial")
    assert proc.returncode == 2 and "are intra and extra exchanged?" in proc.stderr


def test_fits_defocus_out_of_range_names_the_header(tmp_path: Path):
    """DEFOCUS written in um (-1000 for -1 mm): the error names the file and the keyword,
    and --defocal-offset overrides the header."""
    pair = _fits_pair(tmp_path, defocus=(-1000.0, 1000.0))
    proc = run_cli("estimate", *pair, "--instrument", "paraxial")
    assert proc.returncode == 2 and proc.stdout == ""
    assert f"intra image {pair[0]}: its FITS header: DEFOCUS must be in (0, 100) mm" in proc.stderr
    assert "micrometres? 1000 um = 1 mm" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("estimate", *pair, "--instrument", "paraxial", "--defocal-offset", "1.0")
    assert proc.returncode == 0, proc.stderr
    assert "defocal offset 1 mm (command line; the FITS header says 1000 mm)" in proc.stdout
    # In metres: a donut of a tenth of a pixel, said so (the geometry cannot be built).
    pair = _fits_pair(tmp_path / "m", defocus=(-0.001, 0.001))
    proc = run_cli("estimate", *pair, "--instrument", "paraxial")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "gives a donut of radius 0.0 px" in proc.stderr
    assert "metres? 0.001 m = 1 mm" in proc.stderr
    # Two headers that disagree: one error line, naming both values and how to give one.
    pair = _fits_pair(tmp_path / "d", defocus=(-1.0, 1.5))
    proc = run_cli("estimate", *pair, "--instrument", "paraxial")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "the FITS headers disagree on the defocal offset: [1.0, 1.5] mm" in proc.stderr
    assert "estimate --defocal-offset, batch column defocal_offset_mm" in proc.stderr


def test_batch_writes_a_table_of_results(tmp_path: Path):
    from astropy.table import Table

    png = tmp_path / "x.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    table = tmp_path / "pairs.csv"
    rows = [f"{INTRA},{EXTRA},0,0,0,0,1.0", f"{png},{EXTRA},0,0,0,0,1.0",
            f"{INTRA},{EXTRA},0,0,0,0,0.5"]
    table.write_text("intra,extra,field_intra_x,field_intra_y,field_extra_x,field_extra_y,"
                     "defocal_offset_mm\n" + "\n".join(rows) + "\n")
    for name in ("out.ecsv", "out.csv"):
        proc = run_cli("batch", table, "--out", tmp_path / name, "--instrument", "paraxial",
                       timeout=120)
        assert proc.returncode == 2, proc.stderr  # one row is not an image
        assert "3 pairs: 1 ok, 1 flagged, 1 errors" in proc.stdout
        res = Table.read(tmp_path / name,
                         format="ascii.ecsv" if name.endswith("ecsv") else "ascii.csv")
        assert list(res["status"]) == ["ok", "error", "flagged"]
        assert 0 <= res["last_update_nm"][0] < 1.0 and np.isnan(res["last_update_nm"][1])
        # The row that was not estimated has empty cells, not "no caustic, not settled".
        for name in ("caustic", "settled", "iterations"):
            assert np.ma.is_masked(res[name][1]) and not np.ma.is_masked(res[name][0]), name
        assert 180.0 < res["Z7_nm"][0] < 200.0
        assert "not an image" in res["error"][1]
        assert np.isnan(res["Z7_nm"][2]) and "caustic" in res["flags"][2]
    assert str(res["solver"][0]) == "lsq"
    ecsv = Table.read(tmp_path / "out.ecsv", format="ascii.ecsv")
    assert str(ecsv["Z7_nm"].unit) == "nm" and "cwfs_ros" in ecsv.meta["software"]
    # --allow-flagged: the flagged row's numbers are written, and it exits 0 for them.
    table.write_text("intra,extra,field_intra_x,field_intra_y,field_extra_x,field_extra_y,"
                     "defocal_offset_mm\n" + rows[2] + "\n")
    proc = run_cli("batch", table, "--out", tmp_path / "f.ecsv", "--instrument", "paraxial")
    assert proc.returncode == EXIT_FLAGGED
    proc = run_cli("batch", table, "--out", tmp_path / "f.ecsv", "--instrument", "paraxial",
                   "--allow-flagged")
    res = Table.read(tmp_path / "f.ecsv", format="ascii.ecsv")
    assert proc.returncode == 0 and np.isfinite(res["Z7_nm"][0])
