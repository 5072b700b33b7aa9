#!/usr/bin/env python
"""Time per corner on fixed rendered frames, for A/B comparisons on a noisy machine.

Renders ``--trials`` + ``--warm-trials`` corner frame pairs once (as bench_frames.py does,
same seeds) into ``--cache`` (npz).  The field tiles of R00's half-chips are made first as
wavefront_node's frames warm-up makes them (every star field of the half-chips, read from
``--tile-store`` after the first run), then the ``--warm-trials`` frames (trials after the
timed ones) are processed; then ``--reps`` passes over the ``--trials`` frames are timed,
with the pair-geometry cache cleared before each corner.  Their stars are not those of the
warm-up, so every pair is at a new star field, as every visit on the sky.  Prints the median
for the 4-pair corners, the machine reference (bench_frames.MachineReference, timed after
each corner) and their ratio.
``--no-tile-warm-up`` leaves the tiles to the warm-up trials alone: a tile then serves a
field only after its first few fields, which keep the direct trace (~5 ms a side).

Two checkouts compared on the same frames, alternately (the machine's speed drifts):

  for i in 1 2 3; do
    PYTHONPATH=/path/to/old .venv/bin/python bench/bench_frames_timing.py --tag old
    .venv/bin/python bench/bench_frames_timing.py --tag new
  done
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_frames as bf  # noqa: E402

from cwfs_ros.frames.field_position import load_half_chips  # noqa: E402
from cwfs_ros.frames.selection import estimate_corner_frames, load_selection_config  # noqa: E402
from cwfs_ros.wfs.estimator import pair_geometry  # noqa: E402
from cwfs_ros.wfs.settings import EstimatorSettings  # noqa: E402


def frames(cache: Path, trials: range, seed: int) -> list[dict[str, np.ndarray]]:
    """The trials' (intra, extra) frames, rendered on first use with bench_frames.py's
    scene (its default arguments)."""
    cache.mkdir(parents=True, exist_ok=True)
    halves = load_half_chips()["R00"]
    scene = bf.parser().parse_args(["--seed", str(seed)])
    out = []
    for k in trials:
        path = cache / f"trial{k:02d}.npz"
        if not path.exists():
            _, _, rendered = bf.render_trial(k, scene, halves)
            np.savez(path, **{side: f.image for side, f in rendered.items()})
            print(f"rendered trial {k}", flush=True)
        with np.load(path) as z:
            out.append({"intra": z["intra"], "extra": z["extra"]})
    return out


def warm_half_chip_tiles(settings: EstimatorSettings, store: Path) -> int:
    """The field tiles of every star field of R00's half-chips, as wavefront_node's frames
    warm-up makes them in its worker (runtime.corner_pool); returns the tiles made."""
    from cwfs_ros.frames.field_position import corner_star_fields
    from cwfs_ros.wfs.estimator import load_algorithm, warm_star_fields
    from cwfs_ros.wfs.instrument import load_instrument
    from cwfs_ros.wfs.mapping import use_field_tile_store

    use_field_tile_store(store)
    inst = load_instrument(settings.instrument)
    side_fields, mids = corner_star_fields(load_half_chips()["R00"], inst, settings.band)
    return warm_star_fields(inst, settings.band, inst.wavelength_nm(settings.band, None),
                            load_algorithm(settings.solver), side_fields, mids)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("out/bench_frames_cache"))
    ap.add_argument("--trials", type=int, default=12)
    ap.add_argument("--warm-trials", type=int, default=12)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--seed", type=int, default=20261126)
    ap.add_argument("--tag", default="")
    ap.add_argument("--tile-store", type=Path, default=Path("out/bench_frames_tiles"))
    ap.add_argument("--no-tile-warm-up", action="store_true")
    ap.add_argument("--estimator-seeing", type=float, default=0.0,
                    help="seeing (arcsec FWHM) the estimator is told: > 0 adds the blur "
                         "reference of each new pair geometry (cwfs_ros.wfs.blur)")
    a = ap.parse_args()
    data = frames(a.cache, range(a.trials), a.seed)
    warm_up = frames(a.cache, range(a.trials, a.trials + a.warm_trials), a.seed)
    settings = EstimatorSettings(solver="lsq", seeing_fwhm_arcsec=a.estimator_seeing)
    cfg = load_selection_config(solver="lsq", max_pairs=4)
    kw = dict(corner="R00", settings=settings, config=cfg)
    rows, refs = [], []
    ref = bf.MachineReference()
    with threadpool_limits(1):
        if not a.no_tile_warm_up:
            warm_half_chip_tiles(settings, a.tile_store)
        for d in warm_up:  # caches used: the steady state of a running node
            estimate_corner_frames(d["intra"], d["extra"], **kw)
        for _ in range(a.reps):
            for d in data:
                pair_geometry.cache_clear()
                r = estimate_corner_frames(d["intra"], d["extra"], **kw)
                if len(r.pairs) == 4:
                    rows.append([r.timing_ms[k] for k in ("total", "detect", "estimate")])
                # The reference between the corners: a slow spell of this shared machine
                # then weighs on both sides of the ratio.
                refs.append(ref.time_ms())
    t = np.median(np.array(rows), axis=0) if rows else np.full(3, np.nan)
    ref_ms = float(np.median(refs))
    print(f"{a.tag or 'this checkout'}: 4-pair corners at new star fields, median of "
          f"{len(rows)}: total {t[0]:.0f} ms (detection {t[1]:.0f}, pairs {t[2]:.0f}); "
          f"machine reference {ref_ms:.1f} ms (median of {len(refs)}, one after each "
          f"corner); ratio {t[0] / ref_ms:.2f}", flush=True)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
