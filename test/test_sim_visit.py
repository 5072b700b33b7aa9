"""Parallel visit rendering and random perturbations of the simulator (no ROS)."""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros.core.control import load_dof_spec
from cwfs_ros.sim import load_corner_geometry, perturbed_telescope
from cwfs_ros.sim.perturbation import RIGID_SCALE, random_perturbation, true_error_of_state_nm
from cwfs_ros.sim.visit import DonutSpec, make_render_pool, render_visit


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
