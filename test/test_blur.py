"""The blur's edge signal (cwfs_ros.wfs.blur) and the seeing input of the estimator.

The truth here comes from outside the code under test: donuts of the nominal (design)
telescope ray-traced by batoid, blurred by a Gaussian of a known seeing, whose wavefront
departure from design is zero by construction; the annulus' area; the plate scale of the
instrument file.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from cwfs_ros.errors import ConfigError
from cwfs_ros.sim.render import corner_fields, plate_scale_um_per_arcsec, render_donut
from cwfs_ros.sim.telescope import perturbed_telescope
from cwfs_ros.wfs import estimate_wavefront, load_instrument
from cwfs_ros.wfs.blur import FWHM_PER_SIGMA, design_donut, seeing_sigma_px
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
from cwfs_ros.wfs.settings import EstimatorSettings, validate_settings

WL = 622.0


def test_seeing_sigma_from_the_instrument_plate_scale():
    # LSST: 10 um pixels at 10.312 m: 0.2000 arcsec/px; FWHM = 2.3548 sigma.
    assert FWHM_PER_SIGMA == pytest.approx(2.35482, rel=1e-5)
    sigma = seeing_sigma_px(1.0, 10.0, 10.312)
    assert sigma == pytest.approx(1.0 / 2.35482 / (10e-6 / 10.312 * 206264.806), rel=1e-5)
    assert 2.10 < sigma < 2.13
    assert seeing_sigma_px(0.0, 10.0, 10.312) == 0.0


def test_design_donut_holds_the_annulus_and_its_outer_edge_where_batoid_puts_it():
    inst = load_instrument("lsst")
    g = pair_geometry(inst, "r", WL, (0.0, 0.0), (0.0, 0.0), 1.5, load_algorithm("lsq"))
    sub = 3
    img = design_donut(g.mapping_intra, g.x, g.y, g.spacing, inst.obscuration, (160, 160),
                       (79.5, 79.5), sub=sub)
    # Flux: one unit per sub-point inside the annulus; on axis nothing is vignetted, so the
    # total is the annulus area over a sub-cell's area (to the staircase of the sub-grid).
    expected = np.pi * (1.0 - inst.obscuration ** 2) / (g.spacing / sub) ** 2
    assert img.sum() == pytest.approx(expected, rel=2e-3)
    # The outer edge where batoid's ray-traced design donut has it: the radius holding
    # 99 % of the light, compared on the two images.
    tel = perturbed_telescope(np.zeros(50), band="r")
    traced = render_donut(tel, (0.0, 0.0), -1.5, wavelength_nm=WL, npix=160,
                          n_photons=2.0 ** 20,
                          poisson=False, sampling="quasi")

    def r99(im: np.ndarray) -> float:
        yy, xx = np.indices(im.shape)
        cx, cy = (im * xx).sum() / im.sum(), (im * yy).sum() / im.sum()
        r = np.hypot(xx - cx, yy - cy).ravel()
        order = np.argsort(r)
        return float(r[order][np.searchsorted(np.cumsum(im.ravel()[order]) / im.sum(), 0.99)])

    assert abs(r99(img) - r99(traced)) <= 0.5


def test_design_donut_vignetting_edges_follow_the_traced_rays():
    """At a corner field ~8 % of the pupil is vignetted.  The share of the light that the
    design donut keeps must be batoid's: the fraction of quasi-random pupil rays that reach
    the detector (to 5e-4; cells dropped whole at the grid's staircase miss by 1.3e-3)."""
    field = tuple(corner_fields()["R00"]["intra"])
    inst = load_instrument("lsst")
    g = pair_geometry(inst, "r", WL, field, field, 1.5, load_algorithm("lsq"))
    sub = 3
    img = design_donut(g.mapping_intra, g.x, g.y, g.spacing, inst.obscuration, (160, 160),
                       (79.5, 79.5), g.transmissions[0], (g.shape, g.region), sub=sub)
    kept = img.sum() / (np.pi * (1.0 - inst.obscuration ** 2) / (g.spacing / sub) ** 2)
    n = 2.0 ** 20
    tel = perturbed_telescope(np.zeros(50), band="r")
    traced = render_donut(tel, field, -1.5, wavelength_nm=WL, npix=160, n_photons=n,
                          poisson=False, sampling="quasi").sum() / n
    assert 0.85 < traced < 0.97  # vignetted, as the corners are
    assert kept == pytest.approx(traced, abs=5e-4)


@pytest.mark.parametrize("corner, side, offset_deg, tile_deg",
                         [("R00", "intra", (0.05, -0.04), 0.0),
                          ("R44", "extra", (-0.03, 0.06), 0.0),
                          ("R04", "intra", (0.02, 0.03), 0.125),
                          ("R40", "extra", (-0.04, -0.01), 0.125)])
def test_pupil_transmission_at_the_vignetting_edges_is_batoids(corner, side, offset_deg,
                                                               tile_deg):
    """The blur reference asks which sub-points of the cells on a vignetting edge reach the
    detector.  The answer (from ray positions fitted over the pupil, mapping._PupilApertures,
    at the field or interpolated over a field tile) must be that of batoid's own trace of
    those rays through its LSST model, point for point, there and at random pupil points."""
    import batoid

    from cwfs_ros.wfs.blur import _boundary
    from cwfs_ros.wfs.mapping import pupil_transmission

    inst = load_instrument("lsst")
    field = tuple(np.add(corner_fields()[corner][side], offset_deg))
    g = pair_geometry(inst, "r", WL, field, field, 1.5, load_algorithm("lsq"))
    m = g.mapping_intra if side == "intra" else g.mapping_extra
    r = np.hypot(g.x, g.y)
    annulus = (r <= 1.0) & (r >= inst.obscuration)
    cells = np.flatnonzero(_boundary((g.shape, g.region), m.transmitted,
                                     annulus & ~m.transmitted))
    assert cells.size > 200  # a corner field: long vignetting edges
    offs = (np.arange(3) - 1.0) / 3.0 * g.spacing
    dx, dy = (a.ravel() for a in np.meshgrid(offs, offs))
    rng = np.random.default_rng(3)
    x = np.concatenate([(g.x[cells, None] + dx).ravel(), rng.uniform(-1, 1, 2000)])
    y = np.concatenate([(g.y[cells, None] + dy).ravel(), rng.uniform(-1, 1, 2000)])
    kw = dict(defocus_mm=1.5, band="r", wavelength_nm=WL, tile_deg=tile_deg)
    if tile_deg:
        # A tile serves from its third field on (the first two are traced, as a map tile's).
        for k in (1, 2):
            pupil_transmission(inst, side, x[:10], y[:10], field_deg=(field[0] + 0.001 * k,
                                                                       field[1]), **kw)
    got = pupil_transmission(inst, side, x, y, field_deg=field, **kw)
    assert not tile_deg or _tile_served(inst, side, field, tile_deg)
    tel = batoid.Optic.fromYaml("LSST_r.yaml")
    big_r = tel.pupilSize / 2.0
    rays = tel.trace(batoid.RayVector.fromStop(x * big_r, y * big_r, optic=tel,
                                               wavelength=WL * 1e-9,
                                               theta_x=np.deg2rad(field[0]),
                                               theta_y=np.deg2rad(field[1])))
    r = np.hypot(x, y)
    truth = ~rays.vignetted & ~rays.failed & (r <= 1.0) & (r >= inst.obscuration)
    assert 0.05 < 1.0 - truth[:cells.size * 9].mean() < 0.95  # both states on the edges
    assert np.array_equal(got, truth)


def _tile_served(inst, side: str, field: tuple[float, float], tile_deg: float) -> bool:
    from cwfs_ros.wfs import mapping

    tile = mapping.tile_of(field, tile_deg)
    return any(key[1] == side and key[5] == tile and entry is not None
               for key, entry in mapping._PUPIL_TILE_CACHE.items())


@pytest.fixture(scope="module")
def seeing_pair():
    """Noise-free design donuts at the R00 SW0 corner field, blurred by 1" of seeing."""
    field = tuple(corner_fields()["R00"]["extra"])
    tel = perturbed_telescope(np.zeros(50), band="r")
    imgs = []
    for dz in (-1.5, 1.5):
        sharp = render_donut(tel, field, dz, wavelength_nm=WL, npix=160, n_photons=2.0 ** 20,
                             poisson=False, sampling="quasi")
        sigma_px = 1.0 / FWHM_PER_SIGMA * plate_scale_um_per_arcsec(tel, field,
                                                                    wavelength_nm=WL) / 10.0
        imgs.append(gaussian_filter(sharp, sigma_px, mode="constant"))
    return field, imgs


def _departure_rms(field, imgs, **kw) -> float:
    r = estimate_wavefront(*imgs, field_intra_deg=field, field_extra_deg=field, solver="lsq",
                           wavelength_nm=WL, **kw)
    return float(np.sqrt(np.mean((r.zernikes_nm - r.intrinsic_nm) ** 2)))


def test_blur_reference_removes_what_seeing_makes_lsq_read(seeing_pair):
    """The design telescope has no departure from design.  Without the reference, lsq read
    ~10 nm rms of it out of the seeing's edge signal at this field (README, Accuracy)."""
    field, imgs = seeing_pair
    without = _departure_rms(field, imgs, seeing_fwhm_arcsec=1.0, blur_reference=False)
    told = _departure_rms(field, imgs, seeing_fwhm_arcsec=1.0)
    assert without > 6.0
    assert told < 2.5
    # Not told the seeing (0), the estimator makes no such correction.
    untold = _departure_rms(field, imgs, seeing_fwhm_arcsec=0.0)
    assert untold == pytest.approx(without, abs=1e-9)


def test_seeing_is_validated():
    img = np.zeros((160, 160))
    with pytest.raises(ConfigError, match="seeing_fwhm_arcsec"):
        estimate_wavefront(img, img, field_intra_deg=(0, 0), field_extra_deg=(0, 0),
                           seeing_fwhm_arcsec=-0.5)
    with pytest.raises(ConfigError, match="seeing_fwhm_arcsec"):
        estimate_wavefront(img, img, field_intra_deg=(0, 0), field_extra_deg=(0, 0),
                           seeing_fwhm_arcsec=float("nan"))
    with pytest.raises(ConfigError, match="seeing_fwhm_arcsec"):
        validate_settings(EstimatorSettings(solver="lsq", seeing_fwhm_arcsec=12.0))
    settings = EstimatorSettings.from_params({"instrument": "lsst", "band": "r",
                                              "solver": "lsq", "outer_iterations": 0,
                                              "pad_px": 0, "seeing_fwhm_arcsec": 0.8}.get)
    assert settings.estimator_kwargs()["seeing_fwhm_arcsec"] == 0.8
