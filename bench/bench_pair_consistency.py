#!/usr/bin/env python
"""The pairs-agree test of the frame combination on synthetic corners (no images).

Draws corners of 4 star pairs from the shipped noise model of ``config/selection.yaml``
(``--solver``), each pair's departure from design a normal draw of its own sigma
(``cwfs_ros.frames.combination.pair_sigma_nm``) at a noise scale q log-uniform in
[``--q-min``, ``--q-max``] (the frames of bench_frames.py: median 0.0037), and reports:

  clean         corners refused (``CombinedEstimate.consistent`` false): false alarms
  spoilt alike  two pairs moved by the same normal draw times 3-10 of their sigma (a
                shared cause): refused, and passed while their combination is more than
                3 sigma (rms over the terms, sigma of the median pair) off the truth
  spoilt apart  the same with one draw each

Usage: .venv/bin/python bench/bench_pair_consistency.py [--corners 2000] [--solver lsq]
"""

from __future__ import annotations

import argparse

import numpy as np

from cwfs_ros.frames.combination import combine_pairs, pair_sigma_nm
from cwfs_ros.frames.selection import load_selection_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corners", type=int, default=2000)
    ap.add_argument("--solver", default="lsq")
    ap.add_argument("--q-min", type=float, default=0.002)
    ap.add_argument("--q-max", type=float, default=0.008)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    comb = load_selection_config(solver=a.solver).combination
    rng = np.random.default_rng(a.seed)
    counts = {name: [0, 0] for name in ("clean", "spoilt alike", "spoilt apart")}
    for _ in range(a.corners):
        q = np.exp(rng.uniform(np.log(a.q_min), np.log(a.q_max), 4))
        sig = pair_sigma_nm(q, comb)
        clean = rng.normal(size=sig.shape) * sig
        bad = rng.choice(4, 2, replace=False)
        scale = rng.uniform(3.0, 10.0)
        unit = pair_sigma_nm(np.array([np.median(q)]), comb)[0]
        for name, draws in (("clean", 0), ("spoilt alike", 1), ("spoilt apart", 2)):
            d = clean.copy()
            if draws:
                d[bad] += rng.normal(size=(draws, sig.shape[1])) * scale * sig[bad]
            r = combine_pairs(d, q, config=comb)
            off = float(np.sqrt(np.mean((r.zernikes_nm / unit) ** 2)))
            counts[name][0] += not r.consistent
            counts[name][1] += bool(r.consistent and off > 3.0)
    print(f"{a.corners} synthetic 4-pair corners, {a.solver} noise model, q in "
          f"[{a.q_min:g}, {a.q_max:g}], max_reduced_chi2 {comb.max_reduced_chi2:g}:")
    for name, (refused, wrong) in counts.items():
        print(f"  {name:13s} refused {refused:5d}   passed > 3 sigma off {wrong:5d}")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
