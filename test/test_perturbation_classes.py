"""The perturbation classes of the closed-loop issue (cwfs_ros.sim.perturbation)."""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros.ofc.control import load_dof_spec
from cwfs_ros.sim.perturbation import (
    random_perturbation,
    stroke_perturbation,
    stroke_usage,
    true_error_of_state_nm,
)

SEEDS = range(40)


def _hexapods(dof):
    return dof[0:5], dof[5:10]


def test_rigid_class_spans_the_hexapod_strokes():
    decentres, tilts = [], []
    for seed in SEEDS:
        dof = stroke_perturbation("rigid", seed)
        assert np.all(dof[10:] == 0)
        for h in _hexapods(dof):
            decentres.append(h[1:3])
            tilts.append(h[3:5] * 3600.0)  # arcsec
            assert abs(h[0]) <= 25.0
    d, t = np.array(decentres), np.array(tilts)
    assert np.hypot(*d.T).max() <= 1000.0 and np.hypot(*t.T).max() <= 30.0
    # sizes fill the stroke and directions cover every quadrant
    assert np.hypot(*d.T).max() > 900.0 and np.hypot(*d.T).min() < 200.0
    assert np.hypot(*t.T).max() > 27.0 and np.hypot(*t.T).min() < 6.0
    for v in (d, t):
        quadrants = {(bool(x > 0), bool(y > 0)) for x, y in v}
        assert len(quadrants) == 4


def test_bending_class_stays_within_three_tenths_of_each_range():
    rng = load_dof_spec().range[10:]
    frac = np.array([stroke_perturbation("bending", s)[10:] / rng for s in SEEDS])
    assert np.all(np.abs(frac) <= 0.3) and np.abs(frac).max() > 0.29
    assert np.all(np.array([stroke_perturbation("bending", s)[:10] for s in SEEDS]) == 0)
    # every mode is excited, with both signs
    assert np.all(frac.max(axis=0) > 0.05) and np.all(frac.min(axis=0) < -0.05)


def test_mixed_class_is_both_and_within_strokes():
    for seed in range(10):
        dof = stroke_perturbation("mixed", seed)
        assert np.any(dof[:10]) and np.any(dof[10:])
        assert max(stroke_usage(dof).values()) <= 1.0 + 1e-12


@pytest.mark.parametrize("kind", ["rigid", "bending", "mixed"])
def test_classes_scale_to_a_target_corner_error(kind):
    raw = stroke_perturbation(kind, 5)
    dof = stroke_perturbation(kind, 5, target_nm=500.0)
    ratio = dof[raw != 0] / raw[raw != 0]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)  # the same draw, rescaled
    assert true_error_of_state_nm(dof) == pytest.approx(500.0, rel=0.03)
    with pytest.raises(ValueError, match="one of"):
        stroke_perturbation("twist", 1)
    with pytest.raises(ValueError, match="> 0"):
        stroke_perturbation(kind, 1, target_nm=0.0)


def test_old_random_perturbation_is_unchanged():
    """Its callers (the demo, bench seeds) keep their states."""
    dof = random_perturbation("rigid", 3)
    from cwfs_ros.sim.perturbation import RIGID_SCALE

    np.testing.assert_array_equal(dof[:10],
                                  np.random.default_rng(3).normal(0.0, 1.0, 10) * RIGID_SCALE)
