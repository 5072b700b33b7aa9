#!/usr/bin/env python
"""Field-tiled vignetting against the direct ray trace, at random corner star fields.

The batoid mapping decides the vignetting of a map tile's swept band from interpolated ray
positions on the apertures (cwfs_ros.wfs.mapping._ApertureEdges).  This checks, at
``--fields`` random star fields per corner and side (within 0.06 deg of the half-chip
centre, on the estimator's own lsq pupil grid), that the tiled mask equals the mask of a
direct trace of every pupil point, and prints how many points differ, how many rays the
tiled path still traced per star, and the time per side of the edge model.

Usage: .venv/bin/python bench/bench_vignetting_tiles.py [--fields 25] [--seed 5]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.fft as sfft  # noqa: E402

from cwfs_ros.frames.field_position import load_half_chips  # noqa: E402
from cwfs_ros.wfs import load_instrument  # noqa: E402
from cwfs_ros.wfs import mapping as mp  # noqa: E402
from cwfs_ros.wfs.estimator import _pupil_grid, load_algorithm  # noqa: E402

BAND = "r"


def pupil_points(inst, algo) -> tuple[np.ndarray, np.ndarray]:
    """The candidate points of the estimator's pupil grid (as pair_geometry builds it)."""
    r_d = inst.donut_radius_px(inst.defocal_offset_mm)
    spacing = 1.0 / (r_d * algo.oversample)
    extent = 1.08 + (algo.boundary_px + 3) / r_d
    n = sfft.next_fast_len(2 * int(np.ceil(extent / spacing)) + 1, real=True)
    _, x, y, _ = _pupil_grid(n, spacing, extent, inst.obscuration, algo.jmax)
    return x, y


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fields", type=int, default=25, help="fields per corner and side")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    wl = inst.wavelength_nm(BAND, None)
    x, y = pupil_points(inst, algo)
    kw = dict(defocus_mm=inst.defocal_offset_mm, band=BAND, wavelength_nm=wl)
    rng = np.random.default_rng(a.seed)
    real_trace = mp._trace_defocused
    traced: list[int] = []

    def counting(*args):
        traced.append(args[-1].size)
        return real_trace(*args)

    n_fields = n_diff = n_vignetted = 0
    rays: list[int] = []
    served: list[bool] = []
    for corner, halves in load_half_chips().items():
        for side, half in halves.items():
            f0 = np.asarray(half.field_deg, float)
            for _ in range(a.fields):
                # Three fields of the same tile first: the tile is built at the third.
                for _ in range(3):
                    fld = tuple(float(v) for v in f0 + rng.uniform(-0.06, 0.06, 2))
                    mp.nominal_mapping(inst, side, x, y, field_deg=fld,
                                       tile_deg=algo.map_tile_deg, **kw)
                fld = tuple(float(v) for v in f0 + rng.uniform(-0.06, 0.06, 2))
                mp._trace_defocused = counting
                traced.clear()
                builds = mp.map_tile_builds
                tiled = mp.nominal_mapping(inst, side, x, y, field_deg=fld,
                                           tile_deg=algo.map_tile_deg, **kw)
                mp._trace_defocused = real_trace
                # Served by a built tile: no build now, and no trace of the fit subset
                # (the direct path's first call).
                served.append(mp.map_tile_builds == builds
                              and all(k < x.size // 3 for k in traced))
                direct = mp.nominal_mapping(inst, side, x, y, field_deg=fld, **kw)
                n_fields += 1
                n_diff += int((tiled.transmitted != direct.transmitted).sum())
                n_vignetted += int((~direct.transmitted).sum())
                rays.append(sum(traced))
        print(f"{corner}: done", flush=True)
    rays_arr = np.array(rays)[np.array(served)]
    print(f"{n_fields} fields: {n_diff} mask points differ from the direct trace "
          f"({n_vignetted} vignetted or outside the annulus in all)")
    print(f"{rays_arr.size} fields served by a built tile (the others started a tile or "
          f"fell in one not built yet): rays traced per star median "
          f"{np.median(rays_arr):.0f}, mean {rays_arr.mean():.2f}, max {rays_arr.max()}")
    # Time of the edge model alone, per side, on the tiles built above.
    tiles = [e for e in mp._MAP_TILE_CACHE.values() if e is not None and e[3] is not None]
    mono = mp._tile_monomials(np.array(0.3), np.array(-0.2))
    t0 = time.perf_counter()
    for e in tiles:
        e[3].transmitted(mono)
    ms = (time.perf_counter() - t0) / max(len(tiles), 1) * 1e3
    sweep = np.median([e[2].size for e in tiles])
    print(f"edge model: {ms:.2f} ms per side ({len(tiles)} tiles, median swept band "
          f"{sweep:.0f} points)")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
