"""Benchmark the photon-tracing simulator (cwfs_ros.sim).

Usage::

    .venv/bin/python bench/bench_sim.py [--repeat 3] [--ofc-senm PATH]

Prints the wall time per 160x160 donut for 1e5, 3e5 and 1e6 rays at a corner field, and the
time of ``true_zernikes_nm``.

With ``--ofc-senm`` (the ts_ofc sensitivity matrix evaluated at the four SW0 corners, a
76x50 ``.npy`` in µm per DoF unit, rows ``19*corner + (j-4)``), it also compares the
simulator's own finite-difference wavefront sensitivity with that matrix, column by column.
It prints the correlation and norm ratio against ``-senM``. The notes say ts_ofc stores the
negative of the wavefront sensitivity. ``--convention ts_ofc`` makes the rigid-body columns
match too (see ``cwfs_ros.sim.telescope``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cwfs_ros.sim import (
    CONVENTIONS,
    DOF_NAMES,
    N_DOF,
    corner_fields,
    load_lsst,
    perturbed_telescope,
    render_donut,
    true_zernikes_nm,
)

WL = 622.0


def _best(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench(repeat: int) -> None:
    tel = load_lsst("r")
    fld = corner_fields()["R44"]["intra"]
    rng = np.random.default_rng(0)
    render_donut(tel, fld, -1.5, wavelength_nm=WL, n_photons=1e3, rng=rng)  # warm caches
    print(f"render_donut, 160x160, field {fld}, -1.5 mm, best of {repeat}:")
    for n in (1e5, 3e5, 1e6):
        dt = _best(
            lambda n=n: render_donut(tel, fld, -1.5, wavelength_nm=WL, n_photons=n, rng=rng),
            repeat,
        )
        print(f"  {n:9.0e} rays: {dt:6.3f} s  ({dt / n * 1e6:.2f} µs/ray)")
    for nx in (64, 128, 255):
        dt = _best(lambda nx=nx: true_zernikes_nm(tel, fld, wavelength_nm=WL, nx=nx), repeat)
        print(f"true_zernikes_nm(nx={nx:3d}): {dt * 1e3:7.1f} ms")
    dof = np.zeros(N_DOF)
    dof[[1, 12, 33]] = [100.0, 0.05, 0.05]
    t0 = time.perf_counter()
    perturbed_telescope(dof)
    print(f"perturbed_telescope (uncached): {(time.perf_counter() - t0) * 1e3:.1f} ms")


def compare_ofc(path: str, convention: str) -> None:
    sen = np.load(path)
    fields = [corner_fields()[c]["extra"] for c in ("R00", "R04", "R40", "R44")]

    def zk(tel):
        return np.concatenate([true_zernikes_nm(tel, f, wavelength_nm=WL) * 1e-3 for f in fields])

    z0 = zk(load_lsst("r"))
    steps = np.array([10, 100, 100, 0.01, 0.01] * 2 + [0.1] * 40, dtype=float)
    print(f"\nconvention={convention!r}")
    print("DoF  name        corr(sim, -senM)  |sim|/|senM|")
    for i in range(N_DOF):
        d = np.zeros(N_DOF)
        d[i] = steps[i]
        a = (zk(perturbed_telescope(d, convention=convention)) - z0) / steps[i]
        b = -sen[:, i]
        c = a @ b / np.sqrt((a @ a) * (b @ b))
        ratio = np.linalg.norm(a) / np.linalg.norm(b)
        print(f"{i:3d}  {DOF_NAMES[i]:10s}  {c:+8.3f}          {ratio:6.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ofc-senm", default=None, help="76x50 .npy corner sensitivity matrix")
    ap.add_argument("--convention", default="batoid_rubin", choices=CONVENTIONS)
    args = ap.parse_args()
    bench(args.repeat)
    if args.ofc_senm:
        compare_ofc(args.ofc_senm, args.convention)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
