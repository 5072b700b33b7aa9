"""Field angle of a pixel on a corner half-chip frame, from the optical model.

The off-axis correction of the estimator (paper §3.3-3.4) depends steeply on each star's
field angle: the mapping, vignetting and design wavefront it removes are those of the field
it is told.  With several stars per half-chip the field of each star must come from its own
pixel position, not from the half-chip's nominal field point.

Geometry (``config/sensors/lsst_corners.yaml``, keys ``frame`` and ``frames``): each
half-chip has a nominal field point ``field_deg`` whose chief ray lands on the frame's
reference pixel (the frame centre unless ``reference_px`` says otherwise), a frame size and
an orientation (the ``rot90``/``flip`` that bring the frame as read out into the focal-plane
frame of the field angles, ``[row=y, col=x]``, as :func:`cwfs_ros.wfs.orientation.orient_image`
applies them).  Pixel pitch comes from the instrument (``pixel_size_um``).  The plate scale
and distortion come from the optical model only (one source of truth): chief rays are
traced through the defocused design telescope on a grid of fields covering the frame, and a
cubic polynomial field(pixel) is fitted to them (residual < 1e-3 px across a 2k x 4k
half-chip).  Non-ray-traced instruments fall back to the paraxial plate scale
``1 / focal_length``.

A donut's flux centroid is not its chief ray: vignetting at the corner removes part of the
pupil on one side, which moves the centroid by a few pixels.  The model also holds that
offset at the reference field (traced the same way), and :meth:`FieldModel.field_of_centroid`
removes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.config import load_sensor_geometry, load_yaml, sensor_file
from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import SIDES as _SIDES
from cwfs_ros.wfs.instrument import Instrument, load_instrument
from cwfs_ros.wfs.mapping import defocused_telescope
from cwfs_ros.wfs.orientation import Orientation

__all__ = ["HalfChip", "FieldModel", "load_half_chips", "field_model"]



@dataclass(frozen=True)
class HalfChip:
    """One half of a corner wavefront sensor, as ``config/sensors/lsst_corners.yaml`` says.

    Attributes:
        corner: raft name (``R00`` ...).
        side: ``"intra"`` or ``"extra"``.
        sensor: detector name (``SW1`` / ``SW0``).
        field_deg: nominal field point (deg) whose chief ray lands on the reference pixel.
        detector_offset_mm: detector offset from focus (mm; intra negative).
        shape_px: (rows, cols) of the frame in the focal-plane orientation.
        orientation: rotation/flip from the frame as read out to the focal-plane frame.
        reference_px: (col, row) of the reference pixel in the focal-plane orientation,
            pixel-centre convention; ``None`` = the frame centre.
        mid_deg: the corner's reference (mid-point) field, deg.
    """

    corner: str
    side: str
    sensor: str
    field_deg: tuple[float, float]
    detector_offset_mm: float
    shape_px: tuple[int, int]
    orientation: Orientation
    reference_px: tuple[float, float] | None
    mid_deg: tuple[float, float]

    def crosswise(self, shape_px: tuple[int, int]) -> bool:
        """Whether a window of ``shape_px`` (rows, cols) has its long side across this
        half-chip's long side: not a window of it as read out (a transposed or turned
        readout)."""
        (rows, cols), (half_rows, half_cols) = shape_px, self.shape_px
        return (half_rows > half_cols and rows < cols) or (half_rows < half_cols and rows > cols)

    def window(self, shape_px: tuple[int, int]) -> tuple[int, int]:
        """A window of ``shape_px`` (rows, cols) laid along this half-chip: turned by 90
        degrees when it lies across it, so one frame size serves the half-chips of every
        corner (R04 and R40 are R00's turned by 90 degrees)."""
        return (shape_px[1], shape_px[0]) if self.crosswise(shape_px) else tuple(shape_px)

    def reference(self, shape_px: tuple[int, int] | None = None) -> tuple[float, float]:
        """Reference pixel (col, row) for a frame of ``shape_px`` (default: the configured)."""
        if self.reference_px is not None:
            return self.reference_px
        rows, cols = shape_px or self.shape_px
        return (cols - 1) / 2.0, (rows - 1) / 2.0


def _pair(v: object, what: str) -> tuple[float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{what} must be two finite numbers, got {v!r}")
    return float(a[0]), float(a[1])


def load_half_chips(path: str | Path | None = None) -> dict[str, dict[str, HalfChip]]:
    """Read every corner's two half-chips from the sensor YAML.

    Returns:
        ``{corner: {"intra": HalfChip, "extra": HalfChip}}`` in the file's order.

    Raises:
        ConfigError naming the missing or bad key.
    """
    p = sensor_file(path)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError as exc:
        raise ConfigError(f"cannot read sensor file {p}: {exc.strerror or exc}") from exc
    # Parsing the YAML costs ~12 ms, a tenth of a corner's budget: every visit's corner job
    # reads it, so the parsed file is kept per (path, modification time).  The caller gets
    # its own outer dicts; HalfChip is frozen.
    parsed = _parse_half_chips(str(p.resolve()), mtime)
    return {corner: dict(halves) for corner, halves in parsed.items()}


@lru_cache(maxsize=8)
def _parse_half_chips(path: str, mtime_ns: int) -> dict[str, dict[str, HalfChip]]:
    p = Path(path)
    geometry = load_sensor_geometry(p)  # the corners' field points and offsets
    cfg = load_yaml(p, "sensor file", copy_=False)  # the frames' geometry
    try:
        default_frame = cfg.get("frame", {}) or {}
        per_frame = cfg.get("frames", {}) or {}
        out: dict[str, dict[str, HalfChip]] = {}
        for corner, g in geometry.items():
            halves = {}
            for side in _SIDES:
                fr = {**default_frame, **((per_frame.get(corner) or {}).get(side) or {})}
                rows, cols = int(fr.get("rows", 4000)), int(fr.get("cols", 2000))
                ref = fr.get("reference_px")
                ref_px = None if ref is None else _pair(ref, f"{corner}.{side}.reference_px")
                orient = Orientation(int(fr.get("rot90", 0)), str(fr.get("flip", "none")))
                halves[side] = HalfChip(
                    corner=corner, side=side,
                    sensor=g.intra_sensor if side == "intra" else g.extra_sensor,
                    field_deg=g.field_deg(side),
                    detector_offset_mm=g.intra_offset_mm if side == "intra" else g.extra_offset_mm,
                    shape_px=(rows, cols), orientation=orient, reference_px=ref_px,
                    mid_deg=g.mid_field_deg)
            out[str(corner)] = halves
    except (KeyError, TypeError, AttributeError, ValueError) as exc:
        raise ConfigError(f"sensor file {p}: bad or missing key ({exc})") from exc
    return out


@dataclass(frozen=True)
class FieldModel:
    """Pixel -> field angle on one half-chip frame (focal-plane orientation).

    Attributes:
        field_deg: the reference field (deg), imaged (chief ray) at ``reference_px``.
        reference_px: (col, row), pixel-centre convention.
        coeffs: (2, 10) cubic polynomial coefficients: field offset (deg) from ``field_deg``
            as a function of (u, v) = pixel offset / 1000 from the reference pixel.
        centroid_offset_px: flux centroid minus chief-ray position of a donut at the
            reference field (px), from the traced design.
        scale_arcsec_per_px: local plate scale sqrt(|det J|), arcsec per pixel.
        fit_rms_px: rms of the polynomial fit, in pixels (the forward trace is exact).
    """

    field_deg: tuple[float, float]
    reference_px: tuple[float, float]
    coeffs: np.ndarray
    centroid_offset_px: tuple[float, float]
    scale_arcsec_per_px: float
    fit_rms_px: float

    def field_of_pixel(self, x: float | np.ndarray, y: float | np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Field (deg) of the chief ray landing at pixel (x=col, y=row)."""
        u = (np.asarray(x, dtype=np.float64) - self.reference_px[0]) / 1000.0
        v = (np.asarray(y, dtype=np.float64) - self.reference_px[1]) / 1000.0
        terms = _cubic_terms(u, v)
        fx = self.field_deg[0] + np.tensordot(self.coeffs[0], terms, axes=1)
        fy = self.field_deg[1] + np.tensordot(self.coeffs[1], terms, axes=1)
        return fx, fy

    def field_of_centroid(self, x: float, y: float) -> tuple[float, float]:
        """Field (deg) of a star whose donut's flux centroid is at pixel (x, y)."""
        fx, fy = self.field_of_pixel(x - self.centroid_offset_px[0],
                                     y - self.centroid_offset_px[1])
        return float(fx), float(fy)


def _cubic_terms(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, v = np.broadcast_arrays(u, v)
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v,
                     u ** 3, u * u * v, u * v * v, v ** 3])


def _trace(optic, px: np.ndarray, py: np.ndarray, wl_m: float, thx_deg: float, thy_deg: float):
    import batoid

    rv = batoid.RayVector.fromStop(px, py, optic=optic, wavelength=wl_m,
                                   theta_x=np.deg2rad(thx_deg), theta_y=np.deg2rad(thy_deg))
    return optic.trace(rv)


@lru_cache(maxsize=64)
def field_model(inst: Instrument, band: str, field_deg: tuple[float, float],
                detector_offset_mm: float, shape_px: tuple[int, int],
                reference_px: tuple[float, float], wavelength_nm: float | None = None
                ) -> FieldModel:
    """Build (and cache) the pixel -> field model of one half-chip frame.

    Args:
        inst: instrument (pixel pitch; batoid design for ray-traced instruments).
        band: optical band of the design model.
        field_deg: reference field (deg).
        detector_offset_mm: detector offset from focus (mm; intra negative).
        shape_px: (rows, cols) of the frame: the fit covers it with 10 % to spare.
        reference_px: (col, row) where the reference field's chief ray lands.
        wavelength_nm: default the band's effective wavelength.

    Cost: 26 single-ray traces plus 2000 pupil rays, a few ms.
    """
    pix_m = inst.pixel_size_um * 1e-6
    ref = (float(reference_px[0]), float(reference_px[1]))
    rows, cols = shape_px
    if inst.mapping != "batoid" or not inst.batoid_optic:
        # Paraxial plate scale: 1 px = pixel / f radians, no distortion.
        k = np.rad2deg(pix_m / inst.focal_length_m) * 1000.0  # deg per 1000 px
        coeffs = np.zeros((2, 10))
        coeffs[0, 1] = coeffs[1, 2] = k
        return FieldModel(tuple(map(float, field_deg)), ref, coeffs, (0.0, 0.0),
                          k / 1000.0 * 3600.0, 0.0)
    wl_m = inst.wavelength_nm(band, wavelength_nm) * 1e-9
    optic = defocused_telescope(inst.batoid_optic, band, float(detector_offset_mm) * 1e-3)
    # Field grid covering the frame: half-extent in degrees from the paraxial scale.
    deg_per_px = np.rad2deg(pix_m / inst.focal_length_m)
    hx, hy = 0.55 * cols * deg_per_px, 0.55 * rows * deg_per_px
    g = np.linspace(-1.0, 1.0, 5)
    tx, ty = np.meshgrid(field_deg[0] + g * hx, field_deg[1] + g * hy)
    tx, ty = tx.ravel(), ty.ravel()
    coeffs, scale, fit_rms = _fit_pixel_to_field(optic, wl_m, pix_m, field_deg, tx, ty)
    cen = _centroid_offset_px(optic, wl_m, pix_m, field_deg)
    coeffs.setflags(write=False)
    return FieldModel((float(field_deg[0]), float(field_deg[1])), ref, coeffs, cen, scale,
                      fit_rms)


def _fit_pixel_to_field(optic: Any, wl_m: float, pix_m: float,
                        field_deg: tuple[float, float], tx: np.ndarray, ty: np.ndarray
                        ) -> tuple[np.ndarray, float, float]:
    """(coefficients, arcsec per px, fit rms px) of the cubic from pixel offsets (in units of
    1000 px) to field offsets (deg), fitted to the chief rays of the fields ``tx, ty`` traced
    through the defocused design, relative to the reference field's chief ray."""
    zero = np.zeros(1)
    c0 = _trace(optic, zero, zero, wl_m, field_deg[0], field_deg[1])
    x0, y0 = float(c0.x[0]), float(c0.y[0])
    hits = np.empty((tx.size, 2))
    for i, (a, b) in enumerate(zip(tx, ty, strict=True)):
        o = _trace(optic, zero, zero, wl_m, a, b)
        hits[i] = ((o.x[0] - x0) / pix_m, (o.y[0] - y0) / pix_m)
    u, v = hits[:, 0] / 1000.0, hits[:, 1] / 1000.0
    design = _cubic_terms(u, v).T
    targets = np.stack([tx - field_deg[0], ty - field_deg[1]], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, targets, rcond=None)
    coeffs = coeffs.T
    # Fit quality in pixels: field residual over the local scale.
    resid_deg = design @ coeffs.T - targets
    jac = coeffs[:, 1:3] / 1000.0  # deg per px at the reference
    scale = float(np.sqrt(abs(np.linalg.det(jac)))) * 3600.0
    return coeffs, scale, float(np.sqrt(np.mean(resid_deg ** 2)) * 3600.0 / scale)


def _centroid_offset_px(optic: Any, wl_m: float, pix_m: float,
                        field_deg: tuple[float, float]) -> tuple[float, float]:
    """(dx, dy) px of the donut's flux centroid from its chief ray: a 64 x 64 grid of rays
    over the pupil annulus, vignetted as the trace says (§3.3: off axis the vignetted donut
    is not centred on the chief ray)."""
    zero = np.zeros(1)
    r_out = 0.5 * optic.pupilSize
    eps = optic.pupilObscuration
    n = 64
    s = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    gx, gy = np.meshgrid(s * r_out, s * r_out)
    rr = np.hypot(gx, gy)
    keep = (rr <= r_out) & (rr >= eps * r_out)
    o = _trace(optic, gx[keep], gy[keep], wl_m, field_deg[0], field_deg[1])
    ok = ~(o.vignetted | o.failed)
    chief = _trace(optic, zero, zero, wl_m, field_deg[0], field_deg[1])
    return (float((o.x[ok].mean() - chief.x[0]) / pix_m),
            float((o.y[ok].mean() - chief.y[0]) / pix_m))


def half_chip_model(half: HalfChip, instrument: str | Instrument = "lsst", band: str = "r",
                    shape_px: tuple[int, int] | None = None) -> FieldModel:
    """The :class:`FieldModel` of a configured half-chip, for a frame of ``shape_px``
    (focal-plane orientation; default the configured size)."""
    inst = load_instrument(instrument)
    shp = tuple(int(v) for v in (shape_px or half.shape_px))
    return field_model(inst, band, half.field_deg, half.detector_offset_mm, shp,
                       half.reference(shp))


__all__ += ["half_chip_model", "corner_star_fields"]


def corner_star_fields(halves: dict[str, HalfChip], instrument: str | Instrument = "lsst",
                       band: str = "r", step_px: float = 250.0
                       ) -> tuple[dict[str, list[tuple[float, float]]],
                                  list[tuple[float, float]]]:
    """Where a corner's stars can be: the fields (deg) of a grid of pixels over each
    configured half-chip (every ``step_px`` and its edges, 0.5 mm beyond them for the donut
    centroid offsets), and the mid-points of every intra/extra pair of those.

    A field tile is 0.125 deg, ~2250 px: a grid finer than that touches every tile a star
    of the half-chip can fall in (:func:`cwfs_ros.wfs.estimator.warm_star_fields`).
    """
    inst = load_instrument(instrument) if isinstance(instrument, str) else instrument
    side_fields: dict[str, list[tuple[float, float]]] = {}
    margin_px = 500.0 / float(inst.pixel_size_um)
    for side, half in halves.items():
        model = half_chip_model(half, inst, band)
        rows, cols = half.shape_px
        cx = np.linspace(-margin_px, cols + margin_px, int(np.ceil(cols / step_px)) + 3)
        cy = np.linspace(-margin_px, rows + margin_px, int(np.ceil(rows / step_px)) + 3)
        gx, gy = np.meshgrid(cx, cy)
        fx, fy = model.field_of_pixel(gx.ravel(), gy.ravel())
        side_fields[side] = [(float(a), float(b)) for a, b in zip(fx, fy, strict=True)]
    intra = np.array(side_fields.get("intra", []))
    extra = np.array(side_fields.get("extra", []))
    mids: list[tuple[float, float]] = []
    if intra.size and extra.size:
        m = 0.5 * (intra[:, None, :] + extra[None, :, :])
        mids = [(float(a), float(b)) for a, b in m.reshape(-1, 2)]
    return side_fields, mids
