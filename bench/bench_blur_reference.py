#!/usr/bin/env python
"""Cost of the blur reference (cwfs_ros.wfs.blur) per new pair geometry, with the vignetting
edges traced ray by ray and from the fitted aperture positions (mapping.pupil_transmission).

Random pairs of corner-sensor fields (both halves, all four corners, within 0.05 deg of each
half's centre), as stars at new fields on the sky.  For each pair the blur reference is
computed both ways, in alternating order, and the two outputs must be identical (the
script stops otherwise).  The first ``--fill`` pairs build the field tiles a running node
has after a few visits and are not counted; the medians of the rest are printed.

  .venv/bin/python bench/bench_blur_reference.py [--pairs 200] [--fill 100]
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from cwfs_ros.sim.render import corner_fields  # noqa: E402
from cwfs_ros.wfs import load_instrument  # noqa: E402
from cwfs_ros.wfs import mapping as mp  # noqa: E402
from cwfs_ros.wfs.blur import blur_reference, image_blur_sigma_px  # noqa: E402
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry  # noqa: E402

WL = 622.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--fill", type=int, default=100)
    ap.add_argument("--seeing", type=float, default=0.7, help="arcsec FWHM")
    a = ap.parse_args()
    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    blur = image_blur_sigma_px(a.seeing, algo.smooth_sigma_px, inst.pixel_size_um,
                               inst.focal_length_m)
    rng = np.random.default_rng(11)
    fields = corner_fields()

    def traced(side: str, field: tuple[float, float], x: np.ndarray,
               y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
        return mp._annulus(inst, x, y) & mp._trace_defocused(inst, "r", WL, field, side,
                                                             1.5, x, y)[3]

    times: dict[str, list[float]] = {"traced": [], "fitted": []}
    for k in range(a.pairs):
        corner = ("R00", "R04", "R40", "R44")[k % 4]
        fi = tuple(np.add(fields[corner]["intra"], rng.uniform(-0.05, 0.05, 2)))
        fe = tuple(np.add(fields[corner]["extra"], rng.uniform(-0.05, 0.05, 2)))
        g = pair_geometry(inst, "r", WL, fi, fe, 1.5, algo)
        args = ((g.mapping_intra, g.mapping_extra), g.x, g.y, g.spacing, g.obscuration,
                g.weight, (160, 160), blur)
        ways = {"traced": (partial(traced, "intra", fi), partial(traced, "extra", fe)),
                "fitted": g.transmissions}
        order = ("traced", "fitted") if k % 2 else ("fitted", "traced")
        out = {}
        for way in order:
            t0 = time.perf_counter()
            out[way] = blur_reference(*args, transmissions=ways[way], grid=(g.shape, g.region))
            if k >= a.fill:
                times[way].append(time.perf_counter() - t0)
        if not np.array_equal(out["traced"], out["fitted"]):
            raise SystemExit(f"pair {k}: the fitted edges changed the blur reference")
    med = {w: 1e3 * float(np.median(t)) for w, t in times.items()}
    print(f"blur reference per new pair geometry, median of {len(times['traced'])} random "
          f"corner pairs ({a.seeing}\" seeing): edges traced {med['traced']:.1f} ms, "
          f"fitted {med['fitted']:.1f} ms; outputs identical for all {a.pairs} pairs")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
