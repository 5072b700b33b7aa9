"""The Kalman filter's consistency test (inconsistent_measurement) on tampered vectors: away
from the nominal telescope, corners swapped, rotated, sign-flipped or emptied are data no
state within the strokes gives, and are refused, while the genuine measurement of the same
state is taken, with either matrix (the ts_ofc matrix against the bundled one's wavefronts:
a model mismatch). Near the nominal telescope such vectors are within what genuine data of
large aberrations needs (docs/reliability.md, "What a measurement may be")."""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros import layout
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc.kalman import KalmanOFC
from cwfs_ros.ofc.model import OpticalModel


def _tampered(z: np.ndarray, case: str, rng: np.random.Generator) -> np.ndarray:
    w = z.copy()
    if case == "R00<->R04":
        w[:19], w[19:38] = z[19:38], z[:19]
    elif case == "blocks rotated":
        w = z.reshape(4, 19)[[1, 2, 3, 0]].reshape(-1)
    elif case == "R00 sign":
        w[:19] = -z[:19]
    elif case == "R40 0.011-1 nm":
        w[38:57] = rng.uniform(0.011, 1.0, 19) * rng.choice([-1, 1], 19)
    return w


@pytest.mark.parametrize("source", ["bundled", "ts_ofc"])
def test_tampered_corners_away_from_nominal_are_inconsistent(source):
    sm = C.SensitivityMatrix.from_bundled()
    spec = C.load_dof_spec()
    intrinsic = C.intrinsic_vector_nm("r", sm.field_points_deg)
    rng = np.random.default_rng(21)
    unc = np.full(layout.N_MEAS, 15.0)
    for k in range(5):
        x = rng.uniform(-1, 1, 50) * spec.range * 0.1
        y = intrinsic + sm.matrix_nm @ x + rng.normal(0, 10.0, layout.N_MEAS)
        ctl = KalmanOFC(OpticalModel(source), max_abs_zernike_nm=None)
        res = ctl.step(y, uncertainty_nm=unc, stamp_ns=1, dry_run=True)
        assert res.valid, res.status
        for case in ("R00<->R04", "blocks rotated", "R00 sign", "R40 0.011-1 nm"):
            res = ctl.step(_tampered(y, case, rng), uncertainty_nm=unc, stamp_ns=2)
            assert not res.valid and res.reason == "inconsistent_measurement", (k, case,
                                                                                res.status)
            assert ctl.n_steps == 0 and not np.any(ctl.dof_total)
