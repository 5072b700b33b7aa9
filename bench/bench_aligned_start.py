#!/usr/bin/env python
"""What the closed loop does to a telescope that is already aligned.

From the nominal state (every DoF 0), the shipped Kalman controller (config/params.yaml) is
run against batoid's telescope for ``--visits`` visits, measurements drawn from the
estimator's noise model (the true corner wavefront plus ``--noise`` nm per term, as
bench_closed_loop_model.py), over ``--seeds`` noise seeds. The first correction fits the
first visit's noise with the large prior of a start (``prior_fraction`` 0.2 of each stroke),
so the loop goes from 0 to its floor; later visits average. A smaller ``prior_fraction``
(for a telescope known to be aligned) is run beside it.

Usage: .venv/bin/python bench/bench_aligned_start.py [--visits 10] [--seeds 5] [--noise 15]
"""

from __future__ import annotations

import argparse

import numpy as np

from cwfs_ros import layout
from cwfs_ros.ofc.kalman import KalmanOFC, KalmanSettings
from cwfs_ros.ofc.model import OpticalModel
from cwfs_ros.validation.loop_model import TruthModel, run_model_loop


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--visits", type=int, default=10)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--noise", type=float, default=15.0, help="nm per term")
    ap.add_argument("--priors", type=float, nargs="+", default=[0.2, 0.02],
                    help="prior_fraction values (0.2 is the shipped default)")
    a = ap.parse_args()
    truth = TruthModel()
    model = OpticalModel("bundled")
    for prior in a.priors:
        rows = []
        for seed in range(a.seeds):
            ctl = KalmanOFC(model, settings=KalmanSettings(prior_fraction=prior))
            tr = run_model_loop(ctl, np.zeros(layout.N_DOF), a.visits, truth=truth,
                                noise_nm=a.noise, seed=seed)
            rows.append(tr.field_nm)
        f = np.array(rows)
        print(f"prior_fraction {prior:g}: field error (nm) per visit, mean over {a.seeds} "
              "seeds: " + " ".join(f"{x:.1f}" for x in f.mean(axis=0))
              + f"; max over seeds at visit 2 {f[:, 1].max():.1f}, mean of visits "
              f"{min(6, a.visits)}-{a.visits} {f[:, 5:].mean():.1f}", flush=True)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    main()
