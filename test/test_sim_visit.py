"""Parallel visit rendering and random perturbations of the simulator (no ROS)."""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros.ofc.control import load_dof_spec
from cwfs_ros.sim import load_corner_geometry, perturbed_telescope
from cwfs_ros.sim.perturbation import RIGID_SCALE, random_perturbation, true_error_of_state_nm
from cwfs_ros.sim.visit import DonutSpec, FrameSpec, make_render_pool, render_frames, render_visit


def _specs() -> list[DonutSpec]:
    g = load_corner_geometry()["R04"]
    return [DonutSpec(("R04", "intra"), g.intra_field_deg, g.intra_offset_mm, (1.5, -2.0), 11),
            DonutSpec(("R04", "extra"), g.extra_field_deg, g.extra_offset_mm, (0.0, 0.5), 12)]


def test_render_visit_does_not_depend_on_the_number_of_workers():
    tel = perturbed_telescope(np.zeros(50), "r")
    kw = dict(wavelength_nm=622.0, npix=160, n_photons=2e4, sky_per_pixel=5.0)
    serial = render_visit(tel, _specs(), **kw)
    pool = make_render_pool(2)
    assert pool is not None
    try:
        parallel = render_visit(tel, _specs(), executor=pool, **kw)
    finally:
        pool.shutdown()
    assert set(serial) == {("R04", "intra"), ("R04", "extra")}
    for k in serial:
        assert serial[k].dtype == np.float32 and serial[k].shape == (160, 160)
        np.testing.assert_array_equal(serial[k], parallel[k])
    # Different seeds give different noise: the two donuts are not copies of one another.
    assert not np.array_equal(serial[("R04", "intra")], serial[("R04", "extra")])
    # Photons are conserved to Poisson accuracy (sky subtracted, ~8 % vignetted at a corner).
    total = float(serial[("R04", "intra")].sum())
    assert 0.8 * 2e4 < total < 1.02 * 2e4


def test_frames_are_blurred_by_the_seeing():
    """The seeing reaches frames (it once reached only stamps).

    With 1 arcsec FWHM (sigma = 2.12 px at 0.2 arcsec/px) light crosses the donut's edges.
    The share found beyond the sharp donut's pixels grown by one (its edges ~1-1.5 px out)
    is, per unit edge length, sigma (phi(t) - t (1 - Phi(t))) with t = d / sigma: 0.29 px
    at d = 1.5 px and 0.42 px at 1 px; times the edge length (2 pi (61 + 37) px) over the
    donut's area (pi (61^2 - 37^2) px^2), 2.4-3.5 %.  Without seeing, none is there.
    """
    g = load_corner_geometry()["R04"]
    spec = FrameSpec(("R04", "intra"), g.intra_field_deg, g.intra_offset_mm, (300, 300),
                     (1, 1), (2e5, 2e5), False, False, 5)
    tel = perturbed_telescope(np.zeros(50), "r")
    kw = dict(band="r", wavelength_nm=622.0, sky_per_pixel=0.0)
    sharp = render_frames(tel, [spec], **kw)[spec.key]
    blurred = render_frames(tel, [spec], seeing_fwhm_arcsec=1.0, **kw)[spec.key]
    assert [s.x for s in sharp.stars] == [s.x for s in blurred.stars]  # same star field
    # The sharp donut's own pixels, slightly grown: ray-traced light never leaves them.
    from scipy.ndimage import binary_dilation
    lit = binary_dilation(sharp.image > 0, iterations=1)
    assert sharp.image[~lit].sum() == 0.0
    outside = blurred.image[~lit].sum() / blurred.image.sum()
    assert 0.018 < outside < 0.045


def test_render_pool_of_one_is_in_thread():
    assert make_render_pool(1) is None


@pytest.mark.parametrize("kind", ["rigid", "bending"])
def test_random_perturbation_kinds_and_target(kind):
    dof = random_perturbation(kind, seed=3, target_nm=400.0)
    assert dof.shape == (50,)
    if kind == "rigid":
        assert np.all(dof[10:] == 0) and np.all(dof[:10] != 0)
        # The pattern is normal(0, 1) x RIGID_SCALE, only rescaled.
        pattern = np.random.default_rng(3).normal(0.0, 1.0, 10) * RIGID_SCALE
        ratio = dof[:10] / pattern
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)
    else:
        assert np.all(dof[:10] == 0) and np.all(dof[10:] != 0)
        assert np.max(np.abs(dof[10:]) / load_dof_spec().range[10:]) < 1.0
    assert true_error_of_state_nm(dof) == pytest.approx(400.0, rel=0.03)
    with pytest.raises(ValueError, match="one of"):
        random_perturbation("twist", 1)


def test_true_error_of_state_is_batoids_departure_at_the_corners(repo_root):
    """The figure of merit, recomputed here from batoid alone: a 25 um camera piston moves the
    detector 25 um towards M1 (batoid_rubin's sign), and the error is the mean over the four
    corner mid-fields of the rms-summed Z4..Z22 change of batoid's wavefront (622 nm, the
    r band; the annular basis of the 0.61 obscuration)."""
    import batoid
    import yaml

    nominal = batoid.Optic.fromYaml("LSST_r.yaml")
    moved = nominal.withGloballyShiftedOptic("LSSTCamera", np.array([0.0, 0.0, -25e-6]))
    with open(repo_root / "config" / "sensors" / "lsst_corners.yaml", encoding="utf-8") as f:
        corners = yaml.safe_load(f)["corners"]
    per_corner = []
    for c in corners.values():
        thx, thy = np.deg2rad(c["mid_deg"])
        dz = [batoid.zernike(t, thx, thy, 622e-9, jmax=22, eps=0.61, nx=128)[4:23] * 622.0
              for t in (moved, nominal)]
        per_corner.append(np.sqrt(np.sum((dz[0] - dz[1]) ** 2)))
    expected = float(np.mean(per_corner))
    assert expected > 100.0  # a 25 um piston is several hundred nm of defocus
    dof = np.zeros(50)
    dof[5] = 25.0
    assert true_error_of_state_nm(dof) == pytest.approx(expected, rel=1e-9)
    # Half the piston, half the error (defocus is linear in it at this size).
    assert true_error_of_state_nm(dof / 2) == pytest.approx(expected / 2, rel=0.02)
