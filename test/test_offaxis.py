"""Off-axis geometry: ray-traced mappings, vignetting, the split corner sensor.

Truth comes from batoid (``batoid.zernike`` of the perturbed model, through the simulator),
never from the estimator's own mapping.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cwfs_ros.core import estimate_wavefront, load_instrument
from cwfs_ros.core.estimator import load_algorithm, pair_geometry
from cwfs_ros.core.mapping import design_zernikes_nm
from cwfs_ros.paths import config_dir

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


@pytest.mark.parametrize("corner,dof_index,value", [("R00", None, 0.0), ("R44", 5, 20.0)])
def test_split_corner_pair(corner: str, dof_index: int | None, value: float) -> None:
    """Intra at SW1, extra at SW0, truth at the mid-point (paper §3.4)."""
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
