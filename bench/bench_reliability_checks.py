#!/usr/bin/env python
"""False refusals and detection of the reliability checks, on genuine ray-traced data.

  decode        genuine corner donuts (bench_input_checks' traced pairs: nominal and
                perturbed telescopes, 1e4-1e7 photons, sky 0/10/50) as the node receives
                them (32FC1, 64FC1, raw 16UC1 counts with a 1000 ADU bias, both byte
                orders declared right; raw counts at 50-98 % of the full scale): refused
                by the decoder (byte_order, wrapped, saturated, bad_scale)? Then the same
                pixels with the byte order declared wrong, and raw counts past 65535
                wrapped: detected?
  plateau       genuine donuts on a background of exactly 0 (no sky, raw photon counts):
                refused as saturated by the plateau test that now applies to them?
  plausibility  true wavefronts (batoid) of telescope states drawn uniformly within the DoF
                strokes (x 0.3 and x 1), and of the box vertices that maximise each term of
                R00 under the linear model: refused by ofc_node's physical bounds?

Usage: .venv/bin/python bench/bench_reliability_checks.py [decode] [plateau] [plausibility]
       [--seeds N] [--perturbations K] [--states S]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_input_checks as BIC  # noqa: E402

from cwfs_ros.runtime.images import ImageDecodeError, decode_checked  # noqa: E402


def _decode(a: np.ndarray, dtype: str, big: bool, declared_big: bool) -> str:
    arr = np.ascontiguousarray(a.astype(np.dtype(dtype).newbyteorder(">" if big else "<")))
    enc = {"f4": "32FC1", "f8": "64FC1", "u2": "16UC1"}[dtype]
    try:
        decode_checked(arr.tobytes(), height=arr.shape[0], width=arr.shape[1], encoding=enc,
                       step=arr.shape[1] * arr.dtype.itemsize, is_bigendian=declared_big)
    except ImageDecodeError as exc:
        return exc.reason
    return ""


def bench_decode(pairs: list[dict], seeds: int, rng: np.random.Generator) -> None:
    print("\n== decode: genuine donuts, byte order declared right -> refused / total")
    genuine: Counter = Counter()
    total: Counter = Counter()
    reasons: Counter = Counter()
    det: Counter = Counter()
    det_n: Counter = Counter()
    for p in pairs:
        for side in ("intra", "extra"):
            for photons in (1e4, 1e5, 1e6, 1e7):
                for sky in (0.0, 10.0, 50.0):
                    for _ in range(seeds):
                        raw = rng.poisson(p[side] * photons + sky).astype(np.float64)
                        cases = {"f4": raw - sky, "f8": raw - sky,
                                 "u2": np.clip(raw + 1000.0, 0, 65535)}
                        for dt, img in cases.items():
                            for big in (False, True):
                                r = _decode(img, dt, big, big)
                                total[dt] += 1
                                genuine[dt] += r != ""
                                if r:
                                    reasons[(dt, r)] += 1
                            r = _decode(img, dt, True, False)
                            det_n[("byte_order", dt)] += 1
                            det[("byte_order", dt)] += r == "byte_order"
                        # Genuine bright raw counts, 50-98 % of the full scale at the peak.
                        scale = 65535 * rng.uniform(0.5, 0.98) / max(p[side].max(), 1e-12)
                        br = np.minimum(rng.poisson(p[side] * scale + 1000.0), 65534)
                        r = _decode(br.astype(float), "u2", False, False)
                        total["u2 bright"] += 1
                        genuine["u2 bright"] += r != ""
                        if r:
                            reasons[("u2 bright", r)] += 1
                        # Raw counts past the 16-bit full scale, wrapped.
                        scale = 65535 * rng.uniform(1.05, 3.0) / max(p[side].max(), 1e-12)
                        wr = (rng.poisson(p[side] * scale + 1000.0) % 65536).astype(float)
                        det_n[("wrapped", "u2")] += 1
                        r = _decode(wr, "u2", False, False)
                        det[("wrapped", "u2")] += r != ""
                        if r != "wrapped":
                            reasons[("wrapped u2 damaged", r or "accepted")] += 1
    for dt in sorted(total):
        print(f"  {dt}: {genuine[dt]}/{total[dt]} refused"
              + (f"  {dict((r, c) for (d, r), c in reasons.items() if d == dt)}"
                 if genuine[dt] else ""))
    print("== decode: damaged -> refused / total")
    for key in sorted(det_n):
        print(f"  {key[0]:10s} {key[1]}: {det[key]}/{det_n[key]}")
    other = {r: c for (d, r), c in reasons.items() if d == "wrapped u2 damaged"}
    if other:
        print(f"  (wrapped images refused for another reason or accepted: {other})")


def bench_plateau(pairs: list[dict], seeds: int, rng: np.random.Generator) -> None:
    print("\n== plateau: genuine donuts on a zero background -> refused as saturated / total")
    for photons in (1e4, 1e5, 1e6, 1e7):
        n = sat = 0
        other: Counter = Counter()
        for p in pairs:
            for _ in range(seeds):
                a = rng.poisson(p["intra"] * photons).astype(np.float64)
                b = rng.poisson(p["extra"] * photons).astype(np.float64)
                r = BIC.outcome(a, b, p["fi"], p["fe"], swap_check=False)
                n += 1
                sat += r == "saturated"
                if r and r != "saturated":
                    other[r] += 1
        print(f"  {photons:7.0e} photons: {sat}/{n}" + (f"  (other: {dict(other)})"
                                                      if other else ""))
    hits, n_img = BIC.zemax_saturation_refusals()
    print(f"  ZEMAX/FAM model images (test/data/zemax, noise-free): {hits}/{n_img} refused "
          "as saturated")


def bench_plausibility(states: int, rng: np.random.Generator) -> None:
    import yaml

    from cwfs_ros.config import config_dir
    from cwfs_ros.ofc import control as C
    from cwfs_ros.ofc import plausibility as P
    from cwfs_ros.sim.render import true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope

    geo = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())
    mids = [tuple(c["mid_deg"]) for c in geo["corners"].values()]
    spec = C.load_dof_spec()
    sm = C.SensitivityMatrix.from_bundled()
    bounds = P.physical_bounds("r", "bundled", 300.0)
    print("\n== plausibility: true wavefronts of states within the strokes -> refused / total")

    def judge(x: np.ndarray) -> tuple[str, float]:
        tel = perturbed_telescope(x, "r")
        z = np.concatenate([true_zernikes_nm(tel, m, wavelength_nm=622.0) for m in mids])
        v = P.check_vector(z, np.ones(4, bool), bounds)
        return ("" if v.ok else v.reason), float(np.max(np.abs(z) / bounds.bound_nm()))

    for scale in (0.3, 1.0):
        bad, worst = 0, 0.0
        for _ in range(states):
            r, w = judge(rng.uniform(-1.0, 1.0, 50) * spec.range * scale)
            bad += r != ""
            worst = max(worst, w)
        print(f"  uniform x {scale:g} of the strokes: {bad}/{states} refused; largest "
              f"|term| / bound {worst:.3f}")
    bad, worst = 0, 0.0
    a = sm.matrix_nm
    for i in range(19):
        for sign in (1.0, -1.0):
            r, w = judge(sign * spec.range * np.sign(a[i]))
            bad += r != ""
            worst = max(worst, w)
    print(f"  R00 box vertices maximising each term (38 states): {bad}/38 refused; largest "
          f"|term| / bound {worst:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", default=["decode", "plateau", "plausibility"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--perturbations", type=int, default=3, help="telescopes incl. nominal")
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--states", type=int, default=100)
    a = ap.parse_args()
    rng = np.random.default_rng(2026)
    t0 = time.time()
    pairs: list[dict] = []
    if {"decode", "plateau"} & set(a.sections):
        tels = BIC.telescopes(a.perturbations, rng)
        pairs = BIC.traced_pairs(tels, BIC.corner_fields(), a.rays, rng)
        print(f"traced {len(pairs)} pairs in {time.time() - t0:.0f} s")
    if "decode" in a.sections:
        bench_decode(pairs, a.seeds, rng)
    if "plateau" in a.sections:
        bench_plateau(pairs, a.seeds, rng)
    if "plausibility" in a.sections:
        bench_plausibility(a.states, rng)
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
