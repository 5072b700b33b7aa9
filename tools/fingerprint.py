"""SHA-256 fingerprints of the numerical outputs of the estimator, the frames path and the
renderer, so that a change meant to keep behaviour can show that it did, bit for bit.

Run: ``python tools/fingerprint.py [section ...]`` (sections: estimate, refusals, blur, frames,
render; all by default; 20-30 s); compare the printed lines before and after the change.
Every float output is hashed as little-endian float64, every status or message as UTF-8
text, in a fixed order.  Timings and process ids are left out.
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ZEMAX = ROOT / "test" / "data" / "zemax"


class Digest:
    """A SHA-256 over a stream of arrays and strings, each tagged by its kind and shape."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def array(self, value: Any) -> None:
        a = np.ascontiguousarray(np.asarray(value, dtype="<f8"))
        self._h.update(f"a{a.shape}".encode())
        self._h.update(a.tobytes())

    def text(self, value: Any) -> None:
        self._h.update(f"s{value!s}\0".encode())

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def _pair(folder: str, stem_intra: str, stem_extra: str) -> tuple[np.ndarray, np.ndarray]:
    from cwfs_ros.wfs.io import read_image

    return (read_image(ZEMAX / folder / stem_intra), read_image(ZEMAX / folder / stem_extra))


# (name, intra, extra, estimate_wavefront keywords)
_ZEMAX_CASES: list[tuple[str, str, str, str, dict[str, Any]]] = [
    ("paraxial", "F1.23_1mm_v61", "z7_0.25_intra.txt", "z7_0.25_extra.txt",
     dict(instrument="paraxial", defocal_offset_mm=1.0, field_intra_deg=(0, 0),
          field_extra_deg=(0, 0))),
    ("lsst_c", "LSST_C_SN26", "z7_0.25_intra.txt", "z7_0.25_extra.txt",
     dict(instrument="lsst_analytic", defocal_offset_mm=1.0, field_intra_deg=(0, 0),
          field_extra_deg=(0, 0))),
    ("lsst_ne", "LSST_NE_SN25", "z11_0.25_intra.txt", "z11_0.25_extra.txt",
     dict(instrument="lsst_analytic", defocal_offset_mm=1.0, field_intra_deg=(0, 0),
          field_extra_deg=(0, 0))),
    ("fam_r22", "FAM", "Image_intra_R22_S11.txt", "Image_extra_R22_S11.txt",
     dict(band="g", wavelength_nm=500.0, field_intra_deg=(0, 0), field_extra_deg=(0, 0))),
    ("fam_r13", "FAM", "Image_intra_R13_S11.txt", "Image_extra_R13_S11.txt",
     dict(band="g", wavelength_nm=500.0, field_intra_deg=(-0.70555556, 0.70555556),
          field_extra_deg=(-0.70555556, 0.70555556))),
    # The blur reference (design donuts) runs only with a seeing.
    ("fam_r13_seeing", "FAM", "Image_intra_R13_S11.txt", "Image_extra_R13_S11.txt",
     dict(band="g", wavelength_nm=500.0, field_intra_deg=(-0.70555556, 0.70555556),
          field_extra_deg=(-0.70555556, 0.70555556), seeing_fwhm_arcsec=0.8)),
]


def _result(d: Digest, r: Any) -> None:
    """Every number and flag of a WavefrontResult (not its timings)."""
    for name in ("zernikes_nm", "zernikes_all_nm", "intrinsic_nm", "history_nm",
                 "residual_rms_nm", "departure_all_nm", "field_deg"):
        d.array(getattr(r, name))
    for name in ("caustic", "converged", "iterations", "swap_check", "solver", "instrument",
                 "band", "wavelength_nm"):
        d.text(getattr(r, name))
    for key in sorted(r.masks):
        d.array(r.masks[key])
    for key in sorted(r.compensated):
        d.array(r.compensated[key])
    for key in sorted(r.inputs):
        don = r.inputs[key]
        d.array(don.image)
        d.array(don.centroid_xy)
        d.array(don.noise)


def estimator_fingerprints() -> Iterable[tuple[str, str]]:
    """estimate_wavefront on the ZEMAX pairs with every solver, cold and warm started."""
    from cwfs_ros.core import estimate_wavefront

    for name, folder, si, se, kw in _ZEMAX_CASES:
        intra, extra = _pair(folder, si, se)
        for solver in ("exp", "fft", "lsq"):
            d = Digest()
            r = estimate_wavefront(intra, extra, solver=solver, **kw)
            _result(d, r)
            if name == "fam_r13":
                warm = estimate_wavefront(intra, extra, solver=solver,
                                          initial_nm=r.departure_all_nm, **kw)
                _result(d, warm)
            yield f"estimate {name} {solver}", d.hexdigest()


def _rejections() -> Iterable[tuple[str, str]]:
    """The refusals of bad inputs: their class, reason and message."""
    from cwfs_ros.core import estimate_wavefront

    intra, extra = _pair("LSST_C_SN26", "z7_0.25_intra.txt", "z7_0.25_extra.txt")
    kw = dict(instrument="lsst_analytic", defocal_offset_mm=1.0, field_intra_deg=(0, 0),
              field_extra_deg=(0, 0))
    rng = np.random.default_rng(5)
    cut = intra.copy()
    cut[:, : intra.shape[1] // 2] = 0.0
    nan = intra.copy()
    nan[3, 3] = np.nan
    cases: list[tuple[str, Callable[[], Any]]] = [
        ("noise", lambda: estimate_wavefront(rng.normal(0, 1, intra.shape), extra, **kw)),
        ("cut", lambda: estimate_wavefront(cut, extra, **kw)),
        ("nan", lambda: estimate_wavefront(nan, extra, **kw)),
        ("flat", lambda: estimate_wavefront(np.ones_like(intra), extra, **kw)),
        ("shape", lambda: estimate_wavefront(intra[:-2], extra, **kw)),
        ("small", lambda: estimate_wavefront(intra[40:-40, 40:-40], extra[40:-40, 40:-40],
                                             **kw)),
        ("saturated", lambda: estimate_wavefront(intra, extra,
                                                 saturation_level=0.5 * intra.max(), **kw)),
        ("plateau", lambda: estimate_wavefront(np.minimum(intra, 0.5 * intra.max()),
                                               extra, **kw)),
        ("swapped", lambda: estimate_wavefront(*_pair("FAM", "Image_extra_R13_S11.txt",
                                                      "Image_intra_R13_S11.txt"),
                                               band="g", wavelength_nm=500.0,
                                               field_intra_deg=(-0.70555556, 0.70555556),
                                               field_extra_deg=(-0.70555556, 0.70555556))),
        ("bad_gain", lambda: estimate_wavefront(intra, extra, feedback_gain=2.0, **kw)),
        ("bad_field", lambda: estimate_wavefront(intra, extra, **{**kw,
                                                 "field_intra_deg": (9, 0)})),
    ]
    d = Digest()
    for name, call in cases:
        try:
            r = call()
        except Exception as exc:  # noqa: BLE001 - the refusal is the output
            d.text(f"{name} {type(exc).__name__} {getattr(exc, 'reason', '')} {exc}")
        else:
            d.text(f"{name} accepted")
            _result(d, r)
    yield "estimate refusals", d.hexdigest()


def blur_fingerprints() -> Iterable[tuple[str, str]]:
    """design_donut and blur_reference at an on-axis and a vignetted corner field."""
    from cwfs_ros.sim.render import corner_fields
    from cwfs_ros.wfs.blur import design_donut
    from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
    from cwfs_ros.wfs.instrument import load_instrument

    inst = load_instrument("lsst")
    corner = tuple(float(v) for v in corner_fields()["R00"]["intra"])
    for name, field in (("axis", (0.0, 0.0)), ("corner", corner)):
        d = Digest()
        g = pair_geometry(inst, "r", 622.0, field, field, 1.5, load_algorithm("lsq"))
        d.array(design_donut(g.mapping_intra, g.x, g.y, g.spacing, inst.obscuration,
                             (160, 160), (79.5, 79.5), sub=3))
        d.array(design_donut(g.mapping_intra, g.x, g.y, g.spacing, inst.obscuration,
                             (160, 160), (80.2, 78.9), g.transmissions[0],
                             (g.shape, g.region), sub=3))
        d.array(g.blur_reference(1.7, (160, 160)))
        yield f"blur {name}", d.hexdigest()


def frames_fingerprints() -> Iterable[tuple[str, str]]:
    """The frames path (detection, pairing, estimates, combination) on two small
    simulated half-chip frames, as in test/test_selection.py, with exp and lsq."""
    from cwfs_ros.frames.combination import CombinationConfig, combine_pairs
    from cwfs_ros.frames.detection import DetectionConfig
    from cwfs_ros.frames.field_position import load_half_chips
    from cwfs_ros.frames.selection import SelectionConfig, estimate_corner_frames
    from cwfs_ros.sim.frames import StarSpec, render_frame
    from cwfs_ros.sim.telescope import perturbed_telescope
    from cwfs_ros.wfs.settings import EstimatorSettings

    dof = np.zeros(50)
    dof[:10] = [10.0, 120.0, -80.0, 0.003, -0.002, -6.0, 90.0, 60.0, -0.002, 0.004]
    tel = perturbed_telescope(dof, band="r")
    halves = load_half_chips()["R00"]
    shape = (1000, 900)
    stars = {
        "intra": [StarSpec(200.0, 200.0, 1.6e5), StarSpec(690.0, 215.0, 1.0e5),
                  StarSpec(210.0, 640.0, 1.2e5), StarSpec(275.0, 680.0, 1.2e5),
                  StarSpec(690.0, 600.0, 1.0e4), StarSpec(470.0, 985.0, 1.0e5),
                  StarSpec(470.0, 420.0, 4.5e5)],
        "extra": [StarSpec(230.0, 260.0, 1.4e5), StarSpec(640.0, 700.0, 1.1e5),
                  StarSpec(500.0, 450.0, 0.9e5)],
    }
    frames = {}
    for seed, side in ((7, "intra"), (8, "extra")):
        h = halves[side]
        frames[side] = render_frame(tel, stars[side], field_ref_deg=h.field_deg,
                                    detector_offset_mm=h.detector_offset_mm, shape_px=shape,
                                    sky_per_pixel=20.0, full_well_e=90.0,
                                    rng=np.random.default_rng(seed)).image
    d = Digest()
    d.array(frames["intra"])
    d.array(frames["extra"])
    yield "frames images", d.hexdigest()
    detection = DetectionConfig(saturation_level=90.0)
    for solver in ("exp", "lsq"):
        for name, comb in (("default", CombinationConfig()),
                           ("strict", CombinationConfig(max_reduced_chi2=1e-9))):
            cfg = SelectionConfig(detection=detection, combination=comb)
            res = estimate_corner_frames(frames["intra"], frames["extra"], corner="R00",
                                         settings=EstimatorSettings(solver=solver), config=cfg)
            yield f"frames {solver} {name}", _corner_digest(res)
    # A half without a usable donut; a short loop with a seeing; pairs that all fail.
    sky = np.random.default_rng(9).poisson(20.0, shape).astype(float)
    cfg = SelectionConfig(detection=detection)
    for name, (fi, fe), settings in (
            ("no_donuts", (frames["intra"], sky), EstimatorSettings(solver="lsq")),
            ("exp_short_seeing", (frames["intra"], frames["extra"]),
             EstimatorSettings(solver="exp", outer_iterations=2, seeing_fwhm_arcsec=0.7)),
            ("failing_pairs", (frames["intra"], frames["extra"]),
             EstimatorSettings(solver="lsq", seeing_fwhm_arcsec=99.0))):
        try:
            res = estimate_corner_frames(fi, fe, corner="R00", settings=settings, config=cfg)
        except Exception as exc:  # noqa: BLE001 - the refusal is the output
            d = Digest()
            d.text(f"{type(exc).__name__} {exc}")
            yield f"frames {name} (raised)", d.hexdigest()
        else:
            yield f"frames {name}", _corner_digest(res)
    # The combination alone, on planted outliers (test_selection.py's cases).
    d = Digest()
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n = 2 + seed % 5
        dep = np.linspace(-40, 40, 19) + rng.normal(0, 5.0, (n, 19))
        dep[seed % n] += rng.normal(0, 60.0, 19) * (seed % 3 > 0)
        q = np.exp(rng.uniform(np.log(0.002), np.log(0.008), n))
        if seed % 7 == 0:
            q[0] = np.nan
        for cfg in (CombinationConfig(), CombinationConfig(noise_coefficient_nm=1000.0,
                                                           pair_floor_nm=0.0,
                                                           max_reduced_chi2=4.0)):
            r = combine_pairs(dep, q, design_ref_nm=np.full(19, 3.0), config=cfg)
            for v in (r.zernikes_nm, r.uncertainty_nm, r.used, r.term_used, r.reduced_chi2):
                d.array(v)
            for v in (r.n_pairs, r.consistent, r.fallback, r.ambiguous):
                d.text(v)
    yield "combine_pairs", d.hexdigest()


def _corner_digest(res: Any) -> str:
    d = Digest()
    for v in (res.zernikes_nm, res.uncertainty_nm, res.field_deg, res.reduced_chi2):
        d.array(v)
    for v in (res.valid, res.status, res.reason, res.n_pairs, res.summary()):
        d.text(v)
    for p in res.pairs:
        for v in (p.intra_xy, p.extra_xy, p.field_intra_deg, p.field_extra_deg,
                  p.field_mid_deg, p.snr_intra, p.snr_extra, p.noise_scale, p.zernikes_nm,
                  p.intrinsic_nm):
            d.array(v)
        for v in (p.index, p.status, p.message, p.used, p.iterations, p.swap_check,
                  p.warm_start, p.converged):
            d.text(v)
    for side in sorted(res.detections):
        for det in res.detections[side]:
            d.text(det)
    return d.hexdigest()


def render_fingerprints() -> Iterable[tuple[str, str]]:
    """render_donut with its options, a few seeds each."""
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    dof = np.zeros(50)
    dof[[1, 2, 5]] = [400.0, -250.0, 20.0]
    tel = perturbed_telescope(dof, band="r")
    # (field, options); a fixed centre is a detector position (m): on axis, near the chief ray.
    variants: list[tuple[tuple[float, float], dict[str, Any]]] = [
        ((0.0, 0.0), dict()),
        ((1.19, -1.19), dict(seeing_fwhm_arcsec=0.8, sky_per_pixel=20.0, read_noise_e=3.0,
                             offset_px=(2.5, -1.5), subtract_sky=True)),
        ((1.19, -1.19), dict(centre="centroid", npix=120, pixel_um=12.0, n_rays=50_000)),
        ((0.0, 0.0), dict(centre=(1e-4, -2e-4), poisson=False, sampling="quasi",
                          n_rays=65536)),
    ]
    for seed in (1, 2, 3):
        d = Digest()
        for field, kw in variants:
            img = render_donut(tel, field, -1.5 if seed % 2 else 1.5, wavelength_nm=622.0,
                               n_photons=1e5, rng=np.random.default_rng(seed), **kw)
            if img.sum() <= 0:
                raise RuntimeError(f"render variant {kw} left the stamp empty")
            d.array(img)
        yield f"render seed {seed}", d.hexdigest()
    yield "render visit and paper pair", _render_callers(tel)
    yield "random star layouts", _star_layouts()


def _star_layouts() -> str:
    """random_stars with every kind of star, a few seeds."""
    from cwfs_ros.sim.frames import random_stars

    d = Digest()
    for seed in range(6):
        rng = np.random.default_rng(seed)
        stars = random_stars(rng, (2000, 1000), n_good=(2, 5), blend=seed % 2 == 0,
                             faint=seed % 3 == 0, edge=seed % 2 == 1, saturated=seed > 2)
        for st in stars:
            d.text(st)
        d.array(rng.random(3))  # the stream left after the layout
    return d.hexdigest()


def _render_callers(tel: Any) -> str:
    """render_donut as the visit renderer and the paper's validation call it."""
    from cwfs_ros.sim.visit import DonutSpec, render_visit
    from cwfs_ros.validation.common import SPLIT
    from cwfs_ros.validation.paper import lsst_pair

    d = Digest()
    for photons in (None, 2e5):
        for img in lsst_pair(tel, (1.1, 1.2), (1.2, 1.1), SPLIT, 622.0, photons,
                             np.random.default_rng(4), rays=2**16):
            d.array(img)
    specs = [DonutSpec(("R00", s), (1.19 * s, -1.1), 1.5 * s, (0.3, -0.7), 11 + i)
             for i, s in enumerate((-1, 1))]
    out = render_visit(tel, specs, wavelength_nm=622.0, n_photons=1e5, sky_per_pixel=20.0,
                       seeing_fwhm_arcsec=0.6, read_noise_e=2.0)
    for key in sorted(out):
        d.array(out[key])
    return d.hexdigest()


def main(argv: list[str]) -> int:
    """Print ``<case>  <sha256>`` per case, and one over all of them."""
    sections = {"estimate": estimator_fingerprints, "refusals": _rejections,
                "blur": blur_fingerprints,
                "frames": frames_fingerprints, "render": render_fingerprints}
    chosen = argv or list(sections)
    total = hashlib.sha256()
    for key in chosen:
        for name, digest in sections[key]():
            print(f"{name:32s} {digest}", flush=True)
            total.update(f"{name} {digest}\n".encode())
    print(f"{'ALL (' + ','.join(chosen) + ')':32s} {total.hexdigest()}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
