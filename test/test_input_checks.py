"""Input checks: saturated (or clipped) donuts and exchanged intra/extra pairs are rejected.

Images are ray-traced by the simulator (batoid, independent of the estimator's mapping
model); what a case holds (saturated at a known level, exchanged, genuine) is known by
construction, and the expected pixel counts are counted here with numpy.  The false-positive
and detection rates over many more realisations are measured by
``bench/bench_input_checks.py`` (README of :mod:`cwfs_ros.wfs.checks`).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.ndimage import gaussian_filter

from cwfs_ros.config import config_dir
from cwfs_ros.errors import (
    ConfigError,
    ImageError,
    MisorientedImageError,
    SaturatedImageError,
    SwappedImagesError,
)
from cwfs_ros.runtime.corner_pool import synthetic_donut
from cwfs_ros.wfs import estimate_wavefront, load_instrument
from cwfs_ros.wfs.donuts import prepare_donut
from cwfs_ros.wfs.io import read_image

CORNERS = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())["corners"]
ZEMAX = Path(__file__).parent / "data" / "zemax"
RAYS = 100_000


def _fields(corner: str) -> tuple[tuple[float, float], tuple[float, float]]:
    g = CORNERS[corner]
    return tuple(g["intra"]["field_deg"]), tuple(g["extra"]["field_deg"])


@lru_cache(maxsize=8)
def _expected(corner: str, perturbed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Ray-traced intra/extra images of one corner, unit flux, ray noise smoothed away.

    ``perturbed``: M2 and camera hexapods moved (280-560 nm rms of wavefront at the
    corners), donuts off centre by up to 1.5 px (the corner donuts reach within 9 px of a
    160-px stamp's edge, and the stamp checks need room).
    """
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    dof = np.zeros(50)
    if perturbed:
        dof[[0, 1, 2, 3, 6, 7]] = [8.0, 120.0, -90.0, 0.003, -100.0, 80.0]
    tel = perturbed_telescope(dof, band="r")
    rng = np.random.default_rng([*corner.encode(), int(perturbed)])
    fi, fe = _fields(corner) if corner in CORNERS else ((0.0, 0.0), (0.0, 0.0))
    out = []
    for f, dz in ((fi, -1.5), (fe, 1.5)):
        im = render_donut(tel, f, dz, wavelength_nm=622.0, npix=160, n_photons=RAYS,
                          n_rays=RAYS, poisson=False, rng=rng,
                          offset_px=tuple(rng.uniform(-1.5, 1.5, 2)) if perturbed else (0, 0))
        out.append(gaussian_filter(im, 0.7) / RAYS)
    return out[0], out[1]


def _noisy(expect: np.ndarray, photons: float, sky: float, rng: np.random.Generator,
           integer: bool = False) -> np.ndarray:
    raw = rng.poisson(expect * photons + sky)
    return raw.astype(np.uint16) if integer else raw.astype(np.float64) - sky


def _estimate(intra: np.ndarray, extra: np.ndarray, corner: str = "R00", **kw):
    fi, fe = _fields(corner) if corner in CORNERS else ((0.0, 0.0), (0.0, 0.0))
    return estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                              solver="lsq", **kw)


# -- saturation ---------------------------------------------------------------------------

def test_full_well_with_configured_level_names_side_level_and_count() -> None:
    """A bright star on a 16-bit ADC: raw counts clipped at 65535, level given."""
    e_in, e_ex = _expected("R00", False)
    rng = np.random.default_rng(1)
    raw = np.minimum(rng.poisson(e_in / e_in.max() * 65535 * 1.3 + 1000.0), 65535)
    intra = raw.astype(np.uint16)
    extra = (rng.poisson(e_ex / e_ex.max() * 30000 + 1000.0)).astype(np.uint16)
    n_sat = int(np.count_nonzero(intra == 65535))
    assert n_sat > 100  # the construction saturates a good part of the donut
    with pytest.raises(SaturatedImageError) as err:
        _estimate(intra, extra, saturation_level=65535)
    msg = str(err.value)
    assert err.value.reason == "saturated"
    assert msg.startswith("intra ") and "65535" in msg and f"{n_sat} pixel" in msg
    # A level at the extra donut's brightest pixel: that one side is named.
    faint = (rng.poisson(e_in / e_in.max() * 20000 + 1000.0)).astype(np.uint16)
    assert faint.max() < extra.max()
    with pytest.raises(SaturatedImageError, match=r"^extra donut is saturated: 1 pixel"):
        _estimate(faint, extra, saturation_level=float(extra.max()))


def test_configured_level_from_the_instrument_file(tmp_path: Path) -> None:
    e_in, e_ex = _expected("R00", False)
    rng = np.random.default_rng(2)
    intra, extra = _noisy(e_in, 1e6, 10, rng), _noisy(e_ex, 1e6, 10, rng)
    level = float(np.percentile(intra, 99.9))  # 26 px of a genuine (unclipped) donut above
    data = yaml.safe_load((config_dir() / "instruments" / "lsst.yaml").read_text())
    data["saturation_level"] = level
    path = tmp_path / "lsst_sat.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(SaturatedImageError) as err:
        _estimate(intra, extra, instrument=str(path))
    assert f"{int(np.count_nonzero(intra >= level))} pixel(s)" in str(err.value)
    _estimate(intra, extra)  # without the level the same genuine pair is fine
    data["saturation_level"] = "high"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="saturation_level"):
        load_instrument(str(path))


@pytest.mark.parametrize("percentile", [50, 60, 75, 90, 99])
@pytest.mark.parametrize("kind", ["float64", "float32", "integer"])
def test_clipped_donut_is_rejected_without_a_level(percentile: float, kind: str) -> None:
    """np.minimum(img, percentile): a flat-topped donut, the estimator given no level."""
    e_in, e_ex = _expected("R00", False)
    rng = np.random.default_rng(3)
    intra, extra = _noisy(e_in, 1e5, 10, rng), _noisy(e_ex, 1e5, 10, rng)
    level = np.percentile(intra, percentile)
    clipped = np.minimum(intra, level)
    if kind == "float32":
        clipped = clipped.astype(np.float32)
    elif kind == "integer":
        clipped = np.round(clipped).astype(np.int32)
    n_top = int(np.count_nonzero(clipped == clipped.max()))
    with pytest.raises(SaturatedImageError) as err:
        _estimate(clipped, extra)
    assert err.value.reason == "saturated"
    assert str(err.value).startswith("intra donut is saturated or clipped")
    assert f"{n_top} pixels" in str(err.value)


def test_full_well_is_found_without_a_level_too() -> None:
    e_in, e_ex = _expected("R44", True)
    rng = np.random.default_rng(4)
    extra = np.minimum(rng.poisson(e_ex / e_ex.max() * 65535 * 2.0 + 800.0), 65535)
    intra = rng.poisson(e_in / e_in.max() * 30000 + 800.0)
    with pytest.raises(SaturatedImageError, match="extra donut .* level 65535"):
        _estimate(intra.astype(np.uint16), extra.astype(np.uint16), corner="R44")


@pytest.mark.parametrize("photons", [1e4, 1e5, 1e6, 1e7])
def test_genuine_donuts_are_not_saturated(photons: float) -> None:
    """Poisson donuts, float (sky subtracted) and raw uint16, several seeds: all accepted."""
    e_in, e_ex = _expected("R04", True)
    rng = np.random.default_rng(int(photons))
    fi, fe = _fields("R04")
    for seed in range(6):
        sky = (0.0, 10.0, 50.0)[seed % 3]
        integer = seed >= 3
        intra = _noisy(e_in, photons, sky, rng, integer)
        extra = _noisy(e_ex, photons, sky, rng, integer)
        try:
            r = estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                                   solver="lsq", outer_iterations=2)
        except ImageError as exc:
            # At 1e4 photons the stamp checks may find the donut too faint or its border
            # too bright (noise); a saturated or swapped verdict would be wrong.
            assert exc.reason in ("flat_or_empty", "donut_cut_by_edge") and photons <= 1e4, exc
            continue
        assert r.iterations == 2


def test_zemax_and_fam_images_are_not_saturated() -> None:
    files = [f for f in sorted(ZEMAX.glob("*/*.txt"))
             if f.parent.name != "reference-outputs" and not f.name.startswith(("zn_", "ccd"))]
    assert len(files) == 12
    for f in files:
        img = read_image(f)
        prepare_donut(img, name="intra", outer_radius_px=0.42 * min(img.shape), margin_px=3.0)


def test_noise_free_flat_top_is_left_to_the_configured_level() -> None:
    """A noise-free model image may be flat by construction (a uniformly lit pupil): only
    a configured level can call it saturated (the plateau test needs noise to tell)."""
    d = synthetic_donut(160, 60.0, 0.61)
    fi, fe = _fields("R00")
    r = estimate_wavefront(d, d, field_intra_deg=fi, field_extra_deg=fe, outer_iterations=1,
                           swap_check=False)
    assert r.iterations == 1
    with pytest.raises(SaturatedImageError):
        estimate_wavefront(d, d, field_intra_deg=fi, field_extra_deg=fe, swap_check=False,
                           saturation_level=float(d.max()))


# -- swapped intra/extra -------------------------------------------------------------------

@pytest.mark.parametrize("corner", ["R00", "R04", "R40", "R44"])
def test_swapped_pairs_at_the_corners_are_rejected(corner: str) -> None:
    e_in, e_ex = _expected(corner, True)
    rng = np.random.default_rng(5)
    for photons, sky in ((1e5, 10.0), (1e5, 50.0), (1e6, 10.0)):
        intra, extra = _noisy(e_in, photons, sky, rng), _noisy(e_ex, photons, sky, rng)
        r = _estimate(intra, extra, corner=corner)  # the right order is accepted...
        assert r.iterations >= 1
        with pytest.raises(SwappedImagesError) as err:  # ... the exchanged one is not
            _estimate(extra, intra, corner=corner)
        assert err.value.reason == "swapped"
        assert "intra and extra images look exchanged" in str(err.value)
        pref = re.search(r"preference ([-+]\d+\.\d+)", str(err.value))
        assert pref is not None and float(pref.group(1)) < -0.5


@pytest.mark.parametrize(("corner", "opposite"), [("R00", "R44"), ("R04", "R40")])
def test_the_opposite_corners_images_are_refused_as_swapped_naming_that_cause(
        corner: str, opposite: str) -> None:
    """The diagonally opposite corner's images are this corner's turned by 180 degrees,
    which the swap check cannot tell from an exchanged pair: its message names the cause."""
    e_in, e_ex = _expected(opposite, True)
    rng = np.random.default_rng(6)
    intra, extra = _noisy(e_in, 1e6, 10.0, rng), _noisy(e_ex, 1e6, 10.0, rng)
    with pytest.raises(SwappedImagesError) as err:
        _estimate(intra, extra, corner=corner)
    assert "diagonally opposite corner" in str(err.value)


def test_correct_pairs_are_accepted_at_every_corner() -> None:
    """The false-positive side, over corners, both telescopes, photon counts and seeds."""
    rng = np.random.default_rng(6)
    n = 0
    for corner in CORNERS:
        for perturbed in (False, True):
            e_in, e_ex = _expected(corner, perturbed)
            for photons in (1e4, 3e4, 1e5, 1e6):
                for sky in (10.0, 50.0):
                    intra, extra = _noisy(e_in, photons, sky, rng), _noisy(e_ex, photons, sky,
                                                                           rng)
                    try:
                        _estimate(intra, extra, corner=corner, outer_iterations=1)
                    except ImageError as exc:  # too faint: see above
                        assert exc.reason in ("flat_or_empty", "donut_cut_by_edge") and \
                            photons <= 3e4, exc
                        continue
                    n += 1
    assert n >= 40  # of 64; the others too faint for the stamp checks


def test_swap_check_abstains_on_axis_and_can_be_disabled() -> None:
    """On axis nothing is vignetted: the pupil footprints of the two sides are the same
    annulus and the check cannot tell (it must not guess)."""
    e_in, e_ex = _expected("axis", False)
    rng = np.random.default_rng(7)
    intra, extra = _noisy(e_in, 1e6, 10, rng), _noisy(e_ex, 1e6, 10, rng)
    _estimate(extra, intra, corner="axis", outer_iterations=1)  # not rejected
    e_in, e_ex = _expected("R40", False)
    intra, extra = _noisy(e_in, 1e6, 10, rng), _noisy(e_ex, 1e6, 10, rng)
    _estimate(extra, intra, corner="R40", outer_iterations=1, swap_check=False)


# -- one half turned or mirrored -----------------------------------------------------------

# The mirror about each corner's diagonal leaves its vignetted lunes where they were: the
# orientation the check cannot tell there (numpy.rot90 quarter turns, then the mirror).
DIAGONAL_MIRROR = {"R00": (3, "lr"), "R44": (3, "lr"), "R04": (1, "lr"), "R40": (1, "lr")}


def _inverse(o):
    from cwfs_ros.wfs.orientation import Orientation

    return o if o.flip == "lr" else Orientation((4 - o.rot90) % 4, "none")


@pytest.mark.parametrize("corner", ["R00", "R04", "R40", "R44"])
def test_one_half_turned_or_mirrored_is_rejected_naming_the_turn_back(corner: str) -> None:
    """Each half in each of the seven wrong orientations of the square: rejected
    ``misoriented``, the message naming the turn that brings it back; the mirror about the
    corner's diagonal, which leaves its vignetting as it was, is not tested (no guess)."""
    from cwfs_ros.wfs.checks import WRONG_ORIENTATIONS
    from cwfs_ros.wfs.orientation import orient_image

    e_in, e_ex = _expected(corner, True)
    rng = np.random.default_rng(11)
    intra, extra = _noisy(e_in, 1e6, 10.0, rng), _noisy(e_ex, 1e6, 10.0, rng)
    assert _estimate(intra, extra, corner=corner, outer_iterations=1).iterations == 1
    for o in WRONG_ORIENTATIONS:
        for side in ("intra", "extra"):
            a = orient_image(intra, o) if side == "intra" else intra
            b = orient_image(extra, o) if side == "extra" else extra
            if (o.rot90, o.flip) == DIAGONAL_MIRROR[corner]:
                _estimate(a, b, corner=corner, outer_iterations=1)  # cannot be told
                continue
            with pytest.raises(MisorientedImageError) as err:
                _estimate(a, b, corner=corner, outer_iterations=1)
            back = _inverse(o)
            turn = f"rot90 {back.rot90}" + (" then flip lr" if back.flip == "lr" else "")
            assert err.value.reason == "misoriented"
            assert f"the {side} image looks turned or mirrored" in str(err.value), err.value
            named = re.search(r"best after (.*?) \(numpy", str(err.value)).group(1)
            # The turn back is named; with it at most its mirror about the diagonal, which
            # fits the corner's symmetric lune equally.
            turns = named.split(", or equally after ")
            assert turn in turns and len(turns) <= 2, (o, named)


def test_orientation_check_abstains_on_axis_and_can_be_disabled() -> None:
    from cwfs_ros.wfs.orientation import Orientation, orient_image

    rng = np.random.default_rng(12)
    e_in, e_ex = _expected("axis", False)
    intra, extra = _noisy(e_in, 1e6, 10, rng), _noisy(e_ex, 1e6, 10, rng)
    _estimate(intra, orient_image(extra, Orientation(1)), corner="axis", outer_iterations=1)
    e_in, e_ex = _expected("R00", False)
    intra, extra = _noisy(e_in, 1e6, 10, rng), _noisy(e_ex, 1e6, 10, rng)
    turned = orient_image(extra, Orientation(0, "lr"))
    with pytest.raises(MisorientedImageError):
        _estimate(intra, turned, corner="R00", outer_iterations=1)
    _estimate(intra, turned, corner="R00", outer_iterations=1, orientation_check=False)


def test_input_check_parameters_are_validated() -> None:
    e_in, e_ex = _expected("R00", False)
    for bad in ({"swap_threshold": 2.0}, {"plateau_min_pixels": -1}, {"swap_check": "yes"},
                {"plateau_min_fraction": "x"}, {"orientation_check": 1},
                {"orientation_threshold": -0.1}, {"orientation_min_significance": -1.0}):
        with pytest.raises(ConfigError, match="input_checks"):
            _estimate(e_in, e_ex, **bad)
    with pytest.raises(ConfigError, match="saturation_level"):
        _estimate(e_in, e_ex, saturation_level=float("nan"))


def test_donut_centroid_takes_all_the_light_of_an_aberrated_donut() -> None:
    """Microns of coma throw light beyond the unaberrated radius plus the 10-px spill; the
    centroid (which aligns the compensation) must still be that of all the light, as a
    plain flux-weighted mean over the (noise-free) stamp gives it."""
    n, r_out = 256, 60.0
    yy, xx = np.mgrid[:n, :n].astype(float)
    r = np.hypot(xx - 128.0, yy - 128.0)
    # A smooth (not flat-topped, which the saturation test would refuse) ring ...
    shade = 100.0 * (1.0 + 0.2 * r / r_out) * (1.0 + 0.1 * (xx - 128.0) / r_out)
    img = np.where((r <= r_out) & (r >= 0.6 * r_out), shade, 0.0)
    # ... and a faint crescent 12-22 px outside it on one side (2.5 % of the flux).
    tail = (r > r_out + 12) & (r <= r_out + 22) & (xx > 150)
    img[tail] = 0.025 * img.sum() / tail.sum()
    truth = ((img * xx).sum() / img.sum(), (img * yy).sum() / img.sum())
    d = prepare_donut(img, name="intra", outer_radius_px=r_out, margin_px=3.0)
    assert abs(d.centroid_xy[0] - truth[0]) < 0.01 and abs(d.centroid_xy[1] - truth[1]) < 0.01
    assert truth[0] - 128.0 > 1.0  # the tail moves the centroid: the check has teeth
    assert abs(d.flux - img.sum()) / img.sum() < 1e-9


# -- a donut larger than the geometry gives --------------------------------------------------

def test_a_stamp_upsampled_twice_is_refused_as_larger_than_expected() -> None:
    """Each pixel of R00's stamps repeated 2 x 2 (a 320-px stamp at half the pixel size):
    the donut is twice the radius the instrument and defocus give, its "sky" is measured on
    the donut, and the refusal says where the light is rather than only "no flux"."""
    e_in, e_ex = _expected("R00", True)
    rng = np.random.default_rng(5)
    up = [np.kron(_noisy(e, 1e6, 50, rng), np.ones((2, 2))) / 4 for e in (e_in, e_ex)]
    with pytest.raises(ImageError) as err:
        _estimate(*up)
    msg = str(err.value)
    assert msg.startswith("intra image has no flux above its background")
    share = int(re.search(r"\((\d+)% of its light lies beyond the donut's expected radius",
                          msg).group(1))
    assert share > 80 and "resampled" in msg
    # A stamp of sky alone is refused without that reason: its light is nowhere.
    sky = rng.normal(0.0, 7.0, e_in.shape)
    with pytest.raises(ImageError) as err:
        _estimate(sky, _noisy(e_ex, 1e6, 50, rng))
    assert "expected radius" not in str(err.value), str(err.value)


@pytest.mark.parametrize("size", [150, 151])
def test_turned_footprints_spectra_are_the_turned_images_transforms(size: int) -> None:
    """The footprints' turned-back spectra, made from two transforms with frequencies
    reversed, are the transforms of the footprints turned by orient_image (even and odd
    windows), and their squared differences are the images'."""
    from scipy import fft as sfft

    from cwfs_ros.wfs.checks import WRONG_ORIENTATIONS, _inverse, _shift_bases, _turned_back
    from cwfs_ros.wfs.orientation import orient_image

    rng = np.random.default_rng(size)
    units = gaussian_filter(rng.random((2, size, size)), (0, 3, 3)).astype(np.float32)
    spectra = np.conj(sfft.rfft2(units))
    rows, cols = _shift_bases(size, 4)
    out, _, diff_sq = _turned_back(units, spectra, rows.astype(np.complex64),
                                   cols.astype(np.complex64))
    for s in range(2):
        for k, o in enumerate(WRONG_ORIENTATIONS):
            back = orient_image(units[s], _inverse(o))
            want = np.conj(sfft.rfft2(back))
            assert np.abs(out[s, k] - want).max() <= 1e-6 * np.abs(want).max(), (s, o)
            assert diff_sq[s, k] == pytest.approx(float(np.sum((back - units[s]) ** 2)),
                                                  rel=1e-5)
