"""Off-axis geometry: ray-traced mappings, vignetting, the split corner sensor.

Truth comes from batoid (``batoid.zernike`` of the perturbed model, through the simulator),
never from the estimator's own mapping.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cwfs_ros.config import config_dir
from cwfs_ros.wfs import estimate_wavefront, load_instrument
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
from cwfs_ros.wfs.mapping import design_zernikes_nm, nominal_mapping, poly10_tables
from cwfs_ros.wfs.zernike import annulus_quadrature, gram_matrix, gram_summary, zernike_basis

CORNERS = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())["corners"]


def _fields(corner: str) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
    g = CORNERS[corner]
    return (tuple(g["intra"]["field_deg"]), tuple(g["extra"]["field_deg"]),
            tuple(g["mid_deg"]))


def test_corner_geometry_masks_and_mapping() -> None:
    fi, fe, _ = _fields("R00")
    g = pair_geometry(load_instrument("lsst"), "r", 622.0, fi, fe, 1.5, load_algorithm("exp"))
    r = np.hypot(g.x, g.y)
    annulus = (r <= 1) & (r >= 0.61)
    for mask in (g.mask_intra, g.mask_extra):
        vignetted = 1 - mask.sum() / annulus.sum()
        assert 0.03 < vignetted < 0.15  # paper §3.3: about 8-10% at the corners
    np.testing.assert_array_equal(g.mask_common, g.mask_intra & g.mask_extra)
    # The halves see different pupils; the signal is not used where only one is lit.
    only_one = g.mask_intra ^ g.mask_extra
    assert only_one.sum() > 50 and np.all(g.weight[only_one] == 0)
    assert np.all(g.weight[g.mask_common][::50] >= 0)
    # The ray-hit fit is far better than the paper's 1% of a pixel.
    assert g.mapping_intra.fit_rms_px < 0.01 and g.mapping_extra.fit_rms_px < 0.01
    # Off axis the donut is distorted: the mapping is not the paraxial one.
    r_d = load_instrument("lsst").donut_radius_px(1.5)
    edge = np.argmin(np.abs(r - 1.0) + np.abs(g.y))
    assert abs(g.mapping_intra.x_px[edge] - r_d * g.x[edge]) > 0.5


def test_design_wavefront_matches_batoid() -> None:
    """The design part added back equals batoid's own wavefront of the nominal telescope."""
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    _, _, mid = _fields("R44")
    ours = design_zernikes_nm(load_instrument("lsst"), "r", 622.0, mid, 22)[3:22]
    ref = true_zernikes_nm(perturbed_telescope(np.zeros(50), band="r"), mid, wavelength_nm=622.0)
    assert np.abs(ours - ref).max() < 1.5
    assert np.abs(ref).max() > 50  # the corners carry large design aberrations


@pytest.mark.parametrize("corner,dof_index,value",
                         [("R00", None, 0.0), ("R00", 1, 300.0), ("R44", 5, 20.0)])
def test_split_corner_pair(corner: str, dof_index: int | None, value: float) -> None:
    """Intra at SW1, extra at SW0, truth at the mid-point (paper §3.4).

    The unperturbed case is the null test: no aberration is invented from the split pupils
    and the design (an estimator that returned the design alone would pass it).  The
    perturbed ones must recover the departure: M2 dx 300 um is 89 nm rms at R00, camera dz
    20 um 73 nm at R44 (measured 10 and 7 nm of error).
    """
    from cwfs_ros.sim.render import render_donut, true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    fi, fe, mid = _fields(corner)
    dof = np.zeros(50)
    if dof_index is not None:
        dof[dof_index] = value  # camera dz: ~320 nm of defocus
    tel = perturbed_telescope(dof, band="r")
    truth = true_zernikes_nm(tel, mid, wavelength_nm=622.0)
    rng = np.random.default_rng(3)
    intra, extra = (render_donut(tel, f, dz, wavelength_nm=622.0, npix=160, n_photons=3e6,
                                 rng=rng, poisson=False, offset_px=(1.5, -2.0))
                    for f, dz in ((fi, -1.5), (fe, 1.5)))
    r = estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe)
    assert r.field_deg == pytest.approx(mid)
    assert float(np.sqrt(np.mean((r.zernikes_nm - truth) ** 2))) < 20.0
    if dof_index is not None:  # the departure to recover is well above the bound
        assert float(np.sqrt(np.mean((r.intrinsic_nm - truth) ** 2))) > 60.0


@pytest.fixture(scope="module")
def noisy_split_pair():
    """A perturbed telescope's R00 split pair with photon noise (1e6 photons, sky)."""
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    fi, fe, _ = _fields("R00")
    dof = np.zeros(50)
    dof[:10] = [6.0, 120.0, -90.0, 0.004, -0.003, -5.0, 100.0, 80.0, -0.003, 0.004]
    tel = perturbed_telescope(dof, band="r")
    rng = np.random.default_rng(17)
    intra, extra = (render_donut(tel, f, dz, wavelength_nm=622.0, npix=160, n_photons=1e6,
                                 sky_per_pixel=50.0, rng=rng, offset_px=(1.0, -2.0))
                    for f, dz in ((fi, -1.5), (fe, 1.5)))
    return intra, extra, fi, fe


def test_split_pair_outer_loop_reaches_its_fixed_point(noisy_split_pair) -> None:
    """The configured 14 outer iterations end at the loop's fixed point (what 60 iterations
    give) on a split pair; before the lsq model carried the guard band's zero weight, slow
    modes left estimates up to 27 nm short of it.  A warm start from a nearby departure
    (another star's) reaches the same point in fewer iterations."""
    intra, extra, fi, fe = noisy_split_pair
    kw = dict(field_intra_deg=fi, field_extra_deg=fe, solver="lsq")
    ref = estimate_wavefront(intra, extra, outer_iterations=60, **kw)
    assert ref.converged
    cold = estimate_wavefront(intra, extra, **kw)
    assert np.abs(cold.zernikes_nm - ref.zernikes_nm).max() < 0.1
    start = ref.departure_all_nm + np.r_[0, 0, 0, np.random.default_rng(2).normal(0, 20, 19)]
    warm = estimate_wavefront(intra, extra, initial_nm=start, **kw)
    assert warm.converged and warm.iterations <= 6
    assert np.abs(warm.zernikes_nm - ref.zernikes_nm).max() < 0.1


# -- the paper's poly10 mapping (§3.3) and the Gram matrix on vignetted pupils -------------

DATA = Path(__file__).resolve().parent / "data" / "zemax"
POLY10_DIR = config_dir() / "instruments" / "poly10" / "lsst"


def _ring(n: int = 61) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(-1, 1, n)
    xx, yy = np.meshgrid(g, g)
    r = np.hypot(xx, yy)
    keep = (r <= 1) & (r >= 0.61)
    return xx[keep], yy[keep]


def _position_difference(field_poly: tuple[float, float], side: str) -> tuple[float, float]:
    """rms and max |poly10 - batoid| image position (px) at (1.185, 1.185), 1 mm, 770 nm."""
    x, y = _ring()
    mb = nominal_mapping(load_instrument("lsst"), side, x, y, defocus_mm=1.0, band="r",
                         wavelength_nm=770.0, field_deg=(1.185, 1.185))
    mp = nominal_mapping(load_instrument("lsst_poly10"), side, x, y, defocus_mm=1.0,
                         field_deg=field_poly)
    both = mb.transmitted & mp.transmitted
    dx, dy = mp.x_px - mb.x_px, mp.y_px - mb.y_px
    dx -= dx[both].mean()  # the two models use different reference points
    dy -= dy[both].mean()
    d = np.hypot(dx, dy)[both]
    return float(np.sqrt(np.mean(d**2))), float(d.max())


@pytest.mark.parametrize("side", ["intra", "extra"])
def test_poly10_mapping_agrees_with_batoid(side: str) -> None:
    """The paper's ZEMAX tables and batoid's ray trace put the rays within ~1 px (§3.3).

    Both describe LSST at the same field (the tables an older ZEMAX design); the same tables
    rotated to the opposite or mirrored field disagree by several pixels, which pins the
    orientation of the tables' frame.
    """
    rms, worst = _position_difference((1.185, 1.185), side)
    assert rms < 0.8 and worst < 1.8
    for wrong in ((-1.185, -1.185), (1.185, -1.185)):
        rms_w, worst_w = _position_difference(wrong, side)
        assert rms_w > 1.1 and worst_w > 2.5


def test_poly10_tables_read_as_written() -> None:
    """At a tabulated field and the reference defocus the coefficients are the file's row."""
    raw_in = np.loadtxt(POLY10_DIR / "offAxis_cxin_poly10.txt")
    raw_ex = np.loadtxt(POLY10_DIR / "offAxis_cyex_poly10.txt")
    row = 4  # field 1.185 deg on the diagonal
    tab = poly10_tables("poly10/lsst")
    fr = float(np.hypot(raw_in[row, 1], raw_in[row, 2]))
    cx_in, _ = tab.coefficients("intra", fr, 1e3 * raw_in[row, 0])
    _, cy_ex = tab.coefficients("extra", fr, 1e3 * raw_ex[row, 0])
    np.testing.assert_allclose(cx_in, raw_in[row, 3:], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cy_ex, raw_ex[row, 3:], rtol=1e-12, atol=1e-15)
    # Halfway to focus the image is half the size: linear in the offset (straight rays).
    cx_half, _ = tab.coefficients("intra", fr, 0.5e3 * raw_in[row, 0])
    raw_ex_x = np.loadtxt(POLY10_DIR / "offAxis_cxex_poly10.txt")
    np.testing.assert_allclose(cx_half, 0.75 * raw_in[row, 3:] + 0.25 * raw_ex_x[row, 3:],
                               atol=1e-12)


def test_poly10_vignetting_is_the_papers_circles() -> None:
    """At (1.185, 1.185) the transmitted pupil is the annulus cut by mask_migrate's circles."""
    mask = np.loadtxt(POLY10_DIR / "mask_migrate.txt")
    _, ca, ra, cb, rb = mask[4]  # field 1.185 deg on the diagonal
    u = np.array([1.0, 1.0]) / np.sqrt(2.0)
    x, y = _ring(81)
    da = np.hypot(x - ca * u[0], y - ca * u[1])
    db = np.hypot(x - cb * u[0], y - cb * u[1])
    expect = (da <= ra) & (db >= rb)
    m = nominal_mapping(load_instrument("lsst_poly10"), "intra", x, y, defocus_mm=1.0,
                        field_deg=(1.185, 1.185))
    r = np.hypot(x, y)
    clear = (np.abs(da - ra) > 1e-9) & (np.abs(db - rb) > 1e-9) & (np.abs(r - 1) > 1e-9)
    np.testing.assert_array_equal(m.transmitted[clear], expect[clear])
    assert 0.05 < 1 - expect.mean() < 0.15  # about 10% vignetted (paper §3.3)


def test_lsst_ne_sn25_with_the_papers_tables() -> None:
    """The off-axis ZEMAX pair agrees with the original code once the mapping is like for like.

    With batoid's (newer) design the pair is ~95 nm off in Z5; with the paper's tables of the
    design that made it, every term is within 13 nm of the original code's output (the
    benchmark target is 10 nm; the reference's own two solvers differ by 9.9 nm).
    """
    from cwfs_ros.wfs.io import read_image

    intra = read_image(DATA / "LSST_NE_SN25" / "z11_0.25_intra.txt")
    extra = read_image(DATA / "LSST_NE_SN25" / "z11_0.25_extra.txt")
    ref = np.loadtxt(DATA / "reference-outputs" / "LSST_NE_SN25_z11_0.25_exp.txt")
    r = estimate_wavefront(intra, extra, field_intra_deg=(1.185, 1.185),
                           field_extra_deg=(1.185, 1.185), instrument="lsst_poly10",
                           solver="exp")
    assert not r.caustic
    assert np.all(r.intrinsic_nm == 0)  # poly10: no design wavefront is added back
    assert np.abs(r.zernikes_nm - ref).max() < 13.0
    assert r.zernikes_nm[11 - 4] == pytest.approx(-192.8, abs=12.0)


def test_gram_matrix_full_annulus_and_vignetted() -> None:
    """Annular Zernikes are orthonormal on the annulus, not on a vignetted pupil (§3.3)."""
    x, y, w = annulus_quadrature(0.61)
    basis = zernike_basis(x, y, jmax=22, eps=0.61)
    off, cond = gram_summary(gram_matrix(basis, weights=w))
    assert off < 1e-6 and cond < 1 + 1e-6
    # The paper's vignetting at (1.185, 1.185): ~10% of the annulus lost.
    mask = nominal_mapping(load_instrument("lsst_poly10"), "intra", x, y, defocus_mm=1.0,
                           field_deg=(1.185, 1.185)).transmitted
    off_v, cond_v = gram_summary(gram_matrix(basis, mask=mask, weights=w))
    assert off_v > 0.05 and cond_v > 1.5
    # The estimator's common pupil at the FAM edge field is worse than at the corners.
    inst = load_instrument("lsst")
    fam = pair_geometry(inst, "g", 500.0, (0.70555556, 1.64583333), (0.70555556, 1.64583333),
                        1.5, load_algorithm("exp"))
    off_f, cond_f = gram_summary(np.asarray(fam.gram_common)[3:22, 3:22])
    assert off_f > 0.15 and cond_f > 3.0


def test_orthonormal_feedback_converges_to_the_same_estimate() -> None:
    """Truncating the feedback in the vignetted-pupil orthonormal basis changes the path only.

    The series expansion's Galerkin solve is invariant to a change of basis within
    Z1..Z22, so its converged estimate cannot change (README: measured identical on FAM).
    On a vignetted off-axis pair with 0.25 wave of Z11 to find (LSST_NE_SN25, 1.185 deg, the
    paper's tables of its design), so that the estimate is not the design alone.
    """
    from cwfs_ros.wfs.io import read_image

    intra = read_image(DATA / "LSST_NE_SN25" / "z11_0.25_intra.txt")
    extra = read_image(DATA / "LSST_NE_SN25" / "z11_0.25_extra.txt")
    kw = dict(field_intra_deg=(1.185, 1.185), field_extra_deg=(1.185, 1.185),
              instrument="lsst_poly10", solver="exp")
    a = estimate_wavefront(intra, extra, **kw)
    b = estimate_wavefront(intra, extra, feedback_basis="orthonormal", **kw)
    assert a.zernikes_nm[11 - 4] < -150.0  # the injected coma is found
    # The two bases take different paths (0.7 nm apart at the 4th iteration)...
    assert np.abs(a.history_nm[3] - b.history_nm[3]).max() > 0.1
    # ...to the same estimate.
    np.testing.assert_allclose(a.zernikes_nm, b.zernikes_nm, atol=0.5)


def test_fam_edge_field_bound() -> None:
    """The heavily vignetted FAM edge field R34_S12 (1.79 deg) against the ZEMAX truth.

    Bounds a little looser than the benchmark targets (every field <= 10 nm rms, every term
    <= 25 nm).  Without the rim registration this field was 13-17 nm rms with terms up to
    40 nm (the vignetting edges of the ZEMAX images differ from batoid's by about a pixel).
    """
    from cwfs_ros.wfs.io import read_image

    intra = read_image(DATA / "FAM" / "Image_intra_R34_S12.txt")
    extra = read_image(DATA / "FAM" / "Image_extra_R34_S12.txt")
    truth = np.loadtxt(DATA / "FAM" / "zn_R34_S12.txt")[3:22] * 500.0
    f = (0.70555556, 1.64583333)
    errors = {}
    for solver in ("exp", "lsq"):
        for register in (True, False):
            r = estimate_wavefront(intra, extra, field_intra_deg=f, field_extra_deg=f,
                                   band="g", wavelength_nm=500.0, solver=solver,
                                   register_rim=register)
            e = r.zernikes_nm - truth
            errors[solver, register] = (float(np.sqrt(np.mean(e**2))), float(np.abs(e).max()))
        rms, worst = errors[solver, True]
        assert rms < 11.0 and worst < 30.0
        assert errors[solver, False][0] > 1.5 * rms  # the registration is what fixes it


def test_rim_registration_with_a_wrong_vignetting_model() -> None:
    """Images from a telescope whose filter aperture is 1.3% larger than the model's.

    Ray-traced truth (batoid.zernike of the telescope that made the images): the
    estimator's vignetting model is off by about a pixel along the filter's cut, as at the
    FAM edge fields; registering the pupils on the primary's rim removes most of the error.
    """
    import batoid
    import yaml as _yaml

    from cwfs_ros.sim.render import render_donut

    cfg = _yaml.safe_load((Path(batoid.datadir) / "LSST" / "LSST_g.yaml").read_text())

    def set_radius(node: object, names: tuple[str, ...], radius: float) -> None:
        if isinstance(node, dict):
            if node.get("name") in names:
                node["obscuration"]["radius"] = radius
            for v in node.values():
                set_radius(v, names, radius)
        elif isinstance(node, list):
            for v in node:
                set_radius(v, names, radius)

    set_radius(cfg, ("Filter_entrance", "Filter_exit"), 0.38)  # batoid's LSST: 0.375 m
    tel = batoid.parse.parse_optic(cfg["opticalSystem"])
    f = (0.70555556, 1.64583333)
    rng = np.random.default_rng(2)
    imgs = [render_donut(tel, f, dz, wavelength_nm=500.0, npix=200, n_photons=1e6,
                         rng=rng, poisson=False) for dz in (-1.5, 1.5)]
    truth = batoid.zernike(tel, *np.deg2rad(f), 500e-9, jmax=22, eps=0.61, nx=128)[4:23] * 500
    rms = {}
    for register in (True, False):
        r = estimate_wavefront(*imgs, field_intra_deg=f, field_extra_deg=f, band="g",
                               wavelength_nm=500.0, solver="lsq", register_rim=register)
        rms[register] = float(np.sqrt(np.mean((r.zernikes_nm - truth) ** 2)))
    assert rms[True] < 15.0
    assert rms[False] > 2.0 * rms[True]


def test_poly10_and_feedback_configuration_errors() -> None:
    from cwfs_ros.errors import ConfigError
    from cwfs_ros.wfs.instrument import Instrument

    base = load_instrument("lsst_poly10")
    with pytest.raises(ConfigError, match="mapping_tables"):
        base.with_overrides(mapping_tables=None)
    with pytest.raises(ConfigError, match="cannot read poly10"):
        poly10_tables("/nonexistent/poly10")
    with pytest.raises(ConfigError, match="feedback_basis"):
        load_algorithm("exp", feedback_basis="gram")
    assert isinstance(base, Instrument) and base.mapping == "poly10"


@pytest.mark.parametrize("folder,instrument", [("F1.23_1mm_v61", "paraxial"),
                                               ("LSST_C_SN26", "lsst_analytic")])
def test_rim_registration_leaves_unvignetted_pairs_alone(folder: str, instrument: str) -> None:
    """On axis the centroid alignment is already right: registering changes < 3 nm."""
    from cwfs_ros.wfs.io import read_image

    intra = read_image(DATA / folder / "z7_0.25_intra.txt")
    extra = read_image(DATA / folder / "z7_0.25_extra.txt")
    kw = dict(field_intra_deg=(0, 0), field_extra_deg=(0, 0), instrument=instrument,
              defocal_offset_mm=1.0, solver="exp")
    a = estimate_wavefront(intra, extra, **kw)
    b = estimate_wavefront(intra, extra, register_rim=False, **kw)
    assert np.abs(a.zernikes_nm - b.zernikes_nm).max() < 3.0
    g = pair_geometry(load_instrument(instrument), "r", 622.0, (0.0, 0.0), (0.0, 0.0), 1.0,
                      load_algorithm("exp"))
    assert g.rim_index is not None and g.rim_index.size > 1000  # the whole rim is trusted
