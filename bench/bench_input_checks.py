#!/usr/bin/env python
"""Detection and false-positive rates of the input checks (saturation, swapped intra/extra).

Ray-traces corner-sensor pairs once (batoid, r band; the nominal telescope and random M2 /
camera rigid-body perturbations of 200-900 nm mean wavefront at the corners, donuts off
centre by up to 3 px), then draws many noisy realisations of them: the traced image (rays
binned, lightly smoothed to remove ray noise) scaled to N photons plus sky, Poisson noise,
sky subtracted (float) or raw counts rounded into uint16 (integer).

  saturation  genuine donuts 1e4-1e7 photons, float and uint16: rejected as saturated?
              (false positives); clipped at a percentile, at a full well (uint16 65535,
              level given and not): rejected?  Also the ZEMAX/FAM test images.
  swap        correct pairs at the four corners: rejected as swapped? (false positives);
              the same pairs exchanged: rejected? (detection); and a field-radius scan.
  orientation correct pairs at the four corners: rejected as misoriented? (false positives);
              one half turned by a quarter turn or mirrored (the seven wrong orientations
              of the square, each half in turn): rejected as misoriented? (detection).
  wrap        the decoder's wrap test at the converter's depth (runtime/images.py): genuine
              raw counts of a 10-, 12-, 14- or 16-bit ADC in 16UC1 (bias 1-10 % of the range,
              peak at 50-99 % of it): refused? (false positives); the same counts 1.05-3x
              past the range, wrapped (with the bias and without one): refused as wrapped?
              and clipped: refused as what, by the decoder and then by the estimator?

Usage: .venv/bin/python bench/bench_input_checks.py [saturation] [swap] [orientation] [wrap]
       [--seeds N]
       [--perturbations K] [--rays R]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from scipy.ndimage import gaussian_filter  # noqa: E402

from cwfs_ros.config import config_dir  # noqa: E402
from cwfs_ros.errors import ImageError  # noqa: E402
from cwfs_ros.sim.render import render_donut, true_zernikes_nm  # noqa: E402
from cwfs_ros.sim.telescope import perturbed_telescope  # noqa: E402
from cwfs_ros.wfs import estimate_wavefront, load_instrument  # noqa: E402
from cwfs_ros.wfs.checks import swap_score  # noqa: E402
from cwfs_ros.wfs.donuts import prepare_donut  # noqa: E402
from cwfs_ros.wfs.io import read_image  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SCALE = np.array([8, 150, 150, 0.005, 0.005, 8, 150, 150, 0.005, 0.005])
CORNERS = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())[
    "corners"]


def telescopes(k: int, rng: np.random.Generator,
               span_nm: tuple[float, float] = (200.0, 900.0)) -> list:
    """The nominal telescope (unless the span excludes it) and perturbed ones, ``k`` in
    all, with a mean wavefront at the corners within ``span_nm``."""
    lo, hi = span_nm
    out = [perturbed_telescope(np.zeros(50), band="r")] if lo <= 200.0 else []
    mids = [tuple(c["mid_deg"]) for c in CORNERS.values()]
    scale = SCALE * max(1.0, hi / 900.0)  # larger draws for a span of larger errors
    while len(out) < k:
        dof = np.zeros(50)
        dof[:10] = rng.normal(0, 1, 10) * scale
        tel = perturbed_telescope(dof, band="r")
        tot = np.mean([np.sqrt(np.sum(true_zernikes_nm(tel, m, wavelength_nm=622.0) ** 2))
                       for m in mids])
        if lo <= tot <= hi:
            out.append(tel)
    return out


def traced_pairs(tels: list, fields: list[tuple[str, tuple, tuple]], rays: int,
                 rng: np.random.Generator) -> list[dict]:
    """Expected images (rays binned, 1-px smoothed, unit total flux) of each pair."""
    pairs = []
    for tel in tels:
        for name, fi, fe in fields:
            ims = []
            for f, dz in ((fi, -1.5), (fe, 1.5)):
                im = render_donut(tel, f, dz, wavelength_nm=622.0, npix=160, n_photons=rays,
                                  n_rays=rays, poisson=False, rng=rng,
                                  offset_px=tuple(rng.uniform(-3, 3, 2)))
                # Smoothing removes the ray noise so that high photon counts are realistic.
                im = gaussian_filter(im, 0.7)
                ims.append(im / rays)
            pairs.append({"name": name, "fi": fi, "fe": fe, "intra": ims[0], "extra": ims[1]})
    return pairs


def noisy(expect: np.ndarray, photons: float, sky: float, integer: bool,
          rng: np.random.Generator) -> np.ndarray:
    """A Poisson realisation: float sky-subtracted, or raw counts as uint16."""
    raw = rng.poisson(expect * photons + sky).astype(np.float64)
    if integer:
        return np.clip(raw, 0, 65535).astype(np.uint16)
    return raw - sky


def outcome(intra: np.ndarray, extra: np.ndarray, fi: tuple, fe: tuple, **kw) -> str:
    """'' if accepted, else the ImageError reason (one outer iteration: the checks run first)."""
    try:
        estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                           solver="lsq", outer_iterations=1, **kw)
    except ImageError as exc:
        return exc.reason
    return ""


def realisations(pairs: list[dict], photon_levels: tuple[float, ...], seeds: int,
                 rng: np.random.Generator):
    """``(pair, photons, sky, intra, extra)``: ``seeds`` noisy float pairs of each pair at
    each photon count and sky (10, 50 e-/px)."""
    for p in pairs:
        for photons in photon_levels:
            for sky in (10.0, 50.0):
                for _ in range(seeds):
                    yield (p, photons, sky, noisy(p["intra"], photons, sky, False, rng),
                           noisy(p["extra"], photons, sky, False, rng))


def corner_fields() -> list[tuple[str, tuple, tuple]]:
    return [(n, tuple(c["intra"]["field_deg"]), tuple(c["extra"]["field_deg"]))
            for n, c in CORNERS.items()]


def zemax_saturation_refusals() -> tuple[int, int]:
    """The noise-free ZEMAX/FAM model donuts of test/data/zemax: (refused as saturated,
    images)."""
    n_img = hits = 0
    for f in sorted((REPO / "test" / "data" / "zemax").glob("*/*.txt")):
        if f.name.startswith(("zn_", "ccd")) or f.parent.name == "reference-outputs":
            continue
        img = read_image(f)
        try:
            prepare_donut(img, name="intra", outer_radius_px=0.42 * min(img.shape),
                          margin_px=3.0)
        except ImageError as exc:
            hits += exc.reason == "saturated"
        n_img += 1
    return hits, n_img


def bench_saturation(pairs: list[dict], seeds: int, rng: np.random.Generator) -> None:
    print("\n== saturation: genuine donuts (false positives) — rejected as saturated / total")
    fp = defaultdict(lambda: [0, 0])
    other = defaultdict(int)
    for p in pairs:
        for photons in (1e4, 1e5, 1e6, 1e7):
            for sky in (0.0, 10.0, 50.0):
                for integer in (False, True):
                    key = (photons, sky, "uint16" if integer else "float")
                    for _ in range(seeds):
                        a = noisy(p["intra"], photons, sky, integer, rng)
                        b = noisy(p["extra"], photons, sky, integer, rng)
                        r = outcome(a, b, p["fi"], p["fe"], swap_check=False)
                        fp[key][0] += r == "saturated"
                        fp[key][1] += 1
                        if r and r != "saturated":
                            other[(key, r)] += 1
    for key in sorted(fp):
        n_sat, n = fp[key]
        rej = {r: c for (k, r), c in other.items() if k == key}
        print(f"  {key[0]:7.0e} photons, sky {key[1]:4.0f}, {key[2]:6s}: {n_sat}/{n}"
              + (f"   (other rejections: {rej})" if rej else ""))
    hits, n_img = zemax_saturation_refusals()
    print(f"  ZEMAX/FAM test images (test/data/zemax): {hits}/{n_img} rejected as saturated")

    print("\n== saturation: damaged donuts (detection) — rejected as saturated / total")
    det = defaultdict(lambda: [0, 0])
    for p in pairs:
        for photons in (1e5, 1e6):
            for _ in range(seeds):
                a = noisy(p["intra"], photons, 10.0, False, rng)
                b = noisy(p["extra"], photons, 10.0, False, rng)
                for pct in (50, 60, 70, 80, 90, 95, 99, 99.5):
                    c = np.minimum(a, np.percentile(a, pct))
                    for enc, img in (("float", c), ("float32", c.astype(np.float32)),
                                     ("int", np.round(c))):
                        key = (f"clip at percentile {pct}", enc)
                        det[key][0] += outcome(img, b, p["fi"], p["fe"]) == "saturated"
                        det[key][1] += 1
        # A bright star on a 16-bit ADC: raw counts clipped at 65535, with and without the
        # level configured.
        for peak_over in (1.05, 1.5, 3.0):
            for _ in range(seeds):
                raw = p["intra"] / p["intra"].max() * 65535 * peak_over + 1000.0
                a = np.minimum(rng.poisson(raw), 65535).astype(np.uint16)
                b = np.minimum(rng.poisson(p["extra"] / p["extra"].max() * 30000 + 1000.0),
                               65535).astype(np.uint16)
                for level in (None, 65535.0):
                    key = (f"uint16 full well, peak x{peak_over}", f"level {level}")
                    det[key][0] += outcome(a, b, p["fi"], p["fe"],
                                           saturation_level=level) == "saturated"
                    det[key][1] += 1
    for key in sorted(det):
        print(f"  {key[0]:34s} {key[1]:13s}: {det[key][0]}/{det[key][1]}")


def decode_reason(counts: np.ndarray) -> str:
    """'' if the decoder takes raw 16UC1 counts, else its reason."""
    from cwfs_ros.runtime.images import ImageDecodeError, decode_checked

    x = np.ascontiguousarray(counts, dtype="<u2")
    try:
        decode_checked(x.tobytes(), height=x.shape[0], width=x.shape[1], encoding="16UC1",
                       step=2 * x.shape[1])
    except ImageDecodeError as exc:
        return exc.reason
    return ""


def bench_wrap(pairs: list[dict], seeds: int, rng: np.random.Generator) -> None:
    print("\n== wrap at the converter's depth: raw counts of a k-bit ADC in 16UC1, Poisson "
          "(peak photons at the given fraction of the range), bias + read noise 5 ADU")
    genuine = defaultdict(lambda: defaultdict(int))
    damaged = defaultdict(lambda: defaultdict(int))

    def raw(shape: np.ndarray, peak: float, bias: float) -> np.ndarray:
        return np.round(rng.poisson(shape * peak) + bias + rng.normal(0, 5, shape.shape))

    for p in pairs:
        for side in ("intra", "extra"):
            shape = p[side] / p[side].max()
            for bits in (10, 12, 14, 16):
                top = float(2 ** bits)
                for _ in range(seeds):
                    bias = rng.uniform(0.01, 0.10) * top
                    counts = np.clip(raw(shape, rng.uniform(0.5, 0.99) * top - bias, bias),
                                     0, top - 1)
                    genuine[bits][decode_reason(counts) or "taken"] += 1
                    past = raw(shape, rng.uniform(1.05, 3.0) * top - bias, bias)
                    damaged[(bits, "wrapped")][decode_reason(np.mod(past, top)) or "taken"] += 1
                    damaged[(bits, "clipped")][
                        decode_reason(np.clip(past, 0, top - 1)) or "taken"] += 1
                    # No bias: the background within its noise of 0 (the wrap test at the
                    # converter's depth abstains; the type's own range is still judged).
                    past0 = np.clip(raw(shape, rng.uniform(1.05, 3.0) * top, 0.0), 0, None)
                    damaged[(bits, "wrapped, no bias")][
                        decode_reason(np.mod(past0, top)) or "taken"] += 1
    for bits in sorted(genuine):
        print(f"  genuine {bits:2d}-bit counts: {dict(genuine[bits])}")
    for key in sorted(damaged):
        print(f"  {key[0]:2d}-bit counts 1.05-3x past the range, {key[1]}: "
              f"{dict(damaged[key])}")
    # What the estimator makes of the pairs the decoder takes: clipped (its plateau test)
    # and wrapped without a bias.
    est = defaultdict(lambda: defaultdict(int))
    for p in pairs:
        for bits in (10, 12, 14):
            top = float(2 ** bits)
            for kind in ("clipped", "wrapped, no bias"):
                imgs = []
                for side in ("intra", "extra"):
                    shape = p[side] / p[side].max()
                    over = rng.uniform(1.05, 3.0) * top
                    if kind == "clipped":
                        bias = rng.uniform(0.01, 0.10) * top
                        imgs.append(np.clip(raw(shape, over - bias, bias), 0, top - 1))
                    else:
                        imgs.append(np.mod(np.clip(raw(shape, over, 0.0), 0, None), top))
                if any(decode_reason(im) for im in imgs):
                    continue
                est[(bits, kind)][outcome(imgs[0], imgs[1], p["fi"], p["fe"]) or "valid"] += 1
    for key in sorted(est):
        print(f"  estimator on the {key[0]:2d}-bit {key[1]} pairs the decoder takes: "
              f"{dict(est[key])}")


def scores(intra: np.ndarray, extra: np.ndarray, fi: tuple, fe: tuple) -> np.ndarray:
    """(vignetting, footprint) preferences of the swap check for a pair (as the estimator)."""
    from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry

    g = pair_geometry(load_instrument("lsst"), "r", 622.0, fi, fe, 1.5, load_algorithm("lsq"))
    d = [prepare_donut(im, name=s, outer_radius_px=g.outer_radius_px, margin_px=3.0)
         for im, s in ((intra, "intra"), (extra, "extra"))]
    s = swap_score(d[0].image, d[1].image, d[0].centroid_xy, d[1].centroid_xy,
                   (d[0].noise, d[1].noise), g.footprints)
    return np.array(s.preference)


def bench_swap(pairs: list[dict], scan: list[dict], seeds: int,
               rng: np.random.Generator) -> None:
    print("\n== swap: correct pairs rejected as swapped (false positives) / exchanged pairs "
          "rejected as swapped (detection); pairs the stamp checks rejected are not counted."
          "\n   pf, pv: range of the footprint and vignetting-only preferences (+1 = given "
          "order, -1 = exchanged; reject: pf < -0.5 and pv < 0.25)")
    for label, items in (("corners", pairs), ("field scan", scan)):
        res = defaultdict(lambda: [0, 0, 0, 0])
        prefs = defaultdict(lambda: ([], []))
        for p, photons, sky, a, b in realisations(items, (1e4, 3e4, 1e5, 1e6), seeds, rng):
            group = p["name"] if label == "field scan" else "4 corners"
            ok = outcome(a, b, p["fi"], p["fe"])
            if ok not in ("", "swapped"):
                continue  # too faint etc.: never reaches the swap check
            sw = outcome(b, a, p["fi"], p["fe"])
            r = res[(group, photons, sky)]
            if sw in ("", "swapped"):
                prefs[(group, photons, sky)][0].append(scores(a, b, p["fi"], p["fe"]))
                prefs[(group, photons, sky)][1].append(scores(b, a, p["fi"], p["fe"]))
            r[0] += ok == "swapped"
            r[1] += 1
            r[2] += sw == "swapped"
            r[3] += sw in ("", "swapped")
        print(f"  {label}:")
        for key in sorted(res, key=lambda k: (str(k[0]), k[1], k[2])):
            f, n, d, m = res[key]
            ok, sw = (np.array(v).reshape(-1, 2) for v in prefs[key])

            def rng_(a: np.ndarray, j: int) -> str:
                return f"{a[:, j].min():+.2f}..{a[:, j].max():+.2f}" if a.size else "-"

            print(f"    {key[0]:>10s} {key[1]:7.0e} photons, sky {key[2]:3.0f}: "
                  f"false positives {f:3d}/{n:3d} (pf {rng_(ok, 1)}, pv {rng_(ok, 0)})   "
                  f"detected {d:3d}/{m:3d} (pf {rng_(sw, 1)}, pv {rng_(sw, 0)})")


def bench_orientation(pairs: list[dict], seeds: int, rng: np.random.Generator) -> None:
    from cwfs_ros.wfs.checks import WRONG_ORIENTATIONS
    from cwfs_ros.wfs.orientation import orient_image

    print("\n== orientation: correct pairs rejected as misoriented (false positives) / one "
          "half turned or mirrored rejected as misoriented (detection), per orientation "
          "(numpy.rot90 quarter turns, then a left-right mirror); pairs the stamp checks "
          "rejected are not counted. The mirrors about a corner's diagonal (rot90 1 or 3, "
          "then lr) leave two of the four corners' lunes unchanged")
    res = defaultdict(lambda: [0, 0])
    det = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for p, photons, sky, a, b in realisations(pairs, (3e4, 1e5, 1e6), seeds, rng):
        ok = outcome(a, b, p["fi"], p["fe"])
        if ok not in ("", "misoriented"):
            continue  # too faint, cut etc.: never reaches the check
        r = res[(photons, sky)]
        r[0] += ok == "misoriented"
        r[1] += 1
        for o in WRONG_ORIENTATIONS:
            for side in ("intra", "extra"):
                got = outcome(orient_image(a, o) if side == "intra" else a,
                              orient_image(b, o) if side == "extra" else b, p["fi"], p["fe"])
                d = det[(photons, sky)][(o.rot90, o.flip)]
                d[0] += got == "misoriented"
                d[1] += 1
    for key in sorted(res):
        f, n = res[key]
        rates = "  ".join(f"{k[0]}{'+lr' if k[1] == 'lr' else ''}: {d:3d}/{m:3d}"
                          for k, (d, m) in sorted(det[key].items(), key=lambda kv: kv[0][::-1]))
        print(f"  {key[0]:7.0e} photons, sky {key[1]:3.0f}: false positives {f:3d}/{n:3d}; "
              f"detected {rates}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", default=["saturation", "swap"])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--perturbations", type=int, default=5, help="telescopes incl. nominal")
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--span-nm", type=float, nargs=2, default=(200.0, 900.0),
                    metavar=("LO", "HI"),
                    help="mean wavefront at the corners of the perturbed telescopes (nm)")
    a = ap.parse_args()
    rng = np.random.default_rng(2027)
    t0 = time.perf_counter()
    tels = telescopes(a.perturbations, rng, tuple(a.span_nm))
    pairs = traced_pairs(tels, corner_fields(), a.rays, rng)
    print(f"traced {len(pairs)} corner pairs ({a.rays} rays each; telescopes of "
          f"{a.span_nm[0]:g}-{a.span_nm[1]:g} nm at the corners) in "
          f"{time.perf_counter() - t0:.0f} s")
    if "saturation" in a.sections:
        bench_saturation(pairs, a.seeds, rng)
    if "swap" in a.sections:
        scan_fields = [(f"r={r:.2f}", (-r / np.sqrt(2), r / np.sqrt(2)),
                        (-r / np.sqrt(2), r / np.sqrt(2))) for r in (0.0, 0.8, 1.0, 1.2, 1.4)]
        scan = traced_pairs(tels[:3], scan_fields, a.rays, rng)
        bench_swap(pairs, scan, a.seeds, rng)
    if "orientation" in a.sections:
        bench_orientation(pairs, a.seeds, rng)
    if "wrap" in a.sections:
        bench_wrap(pairs, a.seeds * 6, rng)
    print(f"(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()  # one BLAS thread, as the cwfs-ros command sets it
    main()
