"""Pupil-to-image mappings: where a ray from reduced pupil point (x, y) lands on a defocused image.

The outer loop of the paper (§2.1) compensates images by remapping flux through

    x'(x, y) = x'_0(x, y) + C dW/dx,     y'(x, y) = y'_0(x, y) + C dW/dy          (eqs. 9-10)

with Jacobian ``J = det(d(x', y')/d(x, y))`` (eq. 12).  ``x'_0`` is the mapping of the
unperturbed system and is what differs between models:

* ``paraxial``: ``x'_0 = +/- r_d x`` (eqs. 9-10 as written; r_d = l R / f in pixels).
* ``fastbeam``: ``x'_0 = +/- r_d F(x, y) x`` with ``F = f / sqrt(f^2 - r^2 R^2)``, the paper's
  §3.2 correction for an f/1.23 beam (eq. 13 with the aplanatic mask scale ``m``).
* ``batoid``: ``x'_0`` from rays traced through the defocused design telescope at the star's
  field angle (§3.3): includes fast-beam projection, off-axis distortion and the design
  aberrations of that field point.  A smooth polynomial fitted to the ray hits supplies the
  Jacobian.  Vignetting comes from the same trace.

All positions are in pixels, in the focal-plane frame of the field angles (``[row=y, col=x]``
images), relative to a reference point (the chief ray for batoid, the pupil centre's image
otherwise); the estimator aligns images by centroid, so the reference point drops out.

Intra-focal images are upright (``x'_0 ~ +r_d x``), extra-focal images inverted
(``x'_0 ~ -r_d x``); no image is ever rotated: the mapping carries the inversion.

Sign of the wavefront term: ``C`` is the ray displacement per unit wavefront slope.  A ray
leaving the pupil with OPD slope ``dW/dU`` is deflected by ``-dW/dU`` radians toward the focus
(wavefront ahead of the reference sphere at the edge = positive OPD = focus pushed beyond),
and travels ``f -/+ l`` to the intra/extra plane: ``C = -(f -/+ l) / R`` (m per unit slope per
unit reduced pupil coordinate), the same sign on both sides of focus.  The sign agrees with
batoid's OPD convention; ``test_estimator`` pins it with ray-traced perturbations.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from .errors import ConfigError
from .instrument import Instrument
from .zernike import zernike_basis

__all__ = ["ImageMapping", "nominal_mapping", "design_zernikes_nm", "SIDES"]

SIDES = ("intra", "extra")

# Radial order of the polynomial fitted to ray hits.  The paper uses 10th order (§3.3); with
# LSST at 1.5 mm that left Z4 and Z7 biased by up to 13 nm on noise-free ray-traced pairs,
# while 12 and above converge (14 and 16 agree to 0.01 nm).
_FIT_ORDER = 14


@dataclass(frozen=True)
class ImageMapping:
    """The unperturbed pupil-to-image mapping of one defocused image, at fixed pupil points.

    Attributes:
        x_px, y_px: image position of each pupil point, pixels from the reference point.
        jxx, jxy, jyx, jyy: Jacobian entries ``dx'/dx, dx'/dy, dy'/dx, dy'/dy`` in pixels per
            unit reduced pupil coordinate.
        transmitted: True where the pupil point lies in the unvignetted annulus.
        c_px_per_nm: displacement (pixels) per nm of wavefront per unit reduced pupil
            coordinate of slope: the paper's C (eq. 11) in these units.
        fit_rms_px: rms residual of the ray-hit fit (0 for analytic models).
    """

    side: str
    x_px: np.ndarray
    y_px: np.ndarray
    jxx: np.ndarray
    jxy: np.ndarray
    jyx: np.ndarray
    jyy: np.ndarray
    transmitted: np.ndarray
    c_px_per_nm: float
    fit_rms_px: float = 0.0

    @property
    def det(self) -> np.ndarray:
        return self.jxx * self.jyy - self.jxy * self.jyx

    @cached_property
    def transmitted_index(self) -> np.ndarray:
        """Indices of the transmitted points (cached: the caustic check runs every iteration)."""
        return np.flatnonzero(self.transmitted)

    @cached_property
    def inv_det_transmitted(self) -> np.ndarray:
        """``1 / J_0`` on the transmitted points."""
        return 1.0 / self.det[self.transmitted_index]


def _side_sign(side: str) -> float:
    if side not in SIDES:
        raise ValueError(f"side must be 'intra' or 'extra', got {side!r}")
    return 1.0 if side == "intra" else -1.0


def _c_px_per_nm(inst: Instrument, side: str, defocus_mm: float) -> float:
    """The paper's C (eq. 11): ray displacement per unit wavefront slope, in px per nm."""
    l_m = defocus_mm * 1e-3
    f = inst.focal_length_m
    dist = f - l_m if side == "intra" else f + l_m
    return -dist / inst.pupil_radius_m / (inst.pixel_size_um * 1e-6) * 1e-9


def _annulus(inst: Instrument, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    r2 = x * x + y * y
    return (r2 <= 1.0) & (r2 >= inst.obscuration**2)


def _paraxial(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray):
    s = _side_sign(side) * inst.donut_radius_px(defocus_mm)
    one = np.full_like(x, s)
    zero = np.zeros_like(x)
    return s * x, s * y, one, zero, zero, one.copy()


def _fastbeam(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray):
    """Paper §3.2: x' = F(x, y) x with F = m sqrt(f^2-R^2)/sqrt(f^2-r^2 R^2), m = f/sqrt(f^2-R^2).

    (For an aplanatic beam the unaberrated image radius is R' = l R / sqrt(f^2 - R^2), so the
    mask scale m = R' f / (l R) = f / sqrt(f^2 - R^2) and F reduces to f / sqrt(f^2 - r^2 R^2).)
    """
    s = _side_sign(side) * inst.donut_radius_px(defocus_mm)
    f, big_r = inst.focal_length_m, inst.pupil_radius_m
    r2 = x * x + y * y
    den = f * f - r2 * big_r * big_r
    if np.any(den <= 0):
        raise ConfigError("fast-beam mapping undefined: pupil point beyond the f-number limit")
    fxy = f / np.sqrt(den)
    g = big_r * big_r / den  # the R^2 / (f^2 - r^2 R^2) factor of the Jacobian terms
    jxx = s * fxy * (1 + x * x * g)
    jyy = s * fxy * (1 + y * y * g)
    jxy = s * fxy * x * y * g
    return s * fxy * x, s * fxy * y, jxx, jxy, jxy.copy(), jyy


@lru_cache(maxsize=8)
def _batoid_telescope(template: str, band: str):
    import batoid  # imported lazily: only the batoid mapping needs it

    try:
        return batoid.Optic.fromYaml(template.format(band=band))
    except Exception as exc:  # batoid raises several types for a missing file
        raise ConfigError(
            f"cannot load batoid optic {template.format(band=band)!r}: {exc}"
        ) from exc


def _trace_defocused(inst: Instrument, band: str, wavelength_nm: float,
                     field_deg: tuple[float, float], side: str, defocus_mm: float,
                     x: np.ndarray, y: np.ndarray):
    """Trace rays from reduced pupil points to the shifted detector. Returns hits in pixels."""
    import batoid

    tel = _batoid_telescope(inst.batoid_optic, band)
    dz = (-1.0 if side == "intra" else 1.0) * defocus_mm * 1e-3  # intra: detector before focus
    tel = tel.withGloballyShiftedOptic("Detector", [0.0, 0.0, dz])
    big_r = tel.pupilSize / 2.0
    thx, thy = np.deg2rad(field_deg[0]), np.deg2rad(field_deg[1])
    xs = np.concatenate([[0.0], x]) * big_r
    ys = np.concatenate([[0.0], y]) * big_r
    rv = batoid.RayVector.fromStop(xs, ys, optic=tel, wavelength=wavelength_nm * 1e-9,
                                   theta_x=thx, theta_y=thy)
    out = tel.trace(rv)
    pix = inst.pixel_size_um * 1e-6
    hx = (out.x[1:] - out.x[0]) / pix  # relative to the chief ray
    hy = (out.y[1:] - out.y[0]) / pix
    ok = ~out.failed[1:]
    transmitted = ok & ~out.vignetted[1:]
    return hx, hy, ok, transmitted


def _batoid(inst: Instrument, side: str, defocus_mm: float, x: np.ndarray, y: np.ndarray,
            band: str, wavelength_nm: float, field_deg: tuple[float, float]):
    hx, hy, ok, transmitted = _trace_defocused(inst, band, wavelength_nm, field_deg, side,
                                               defocus_mm, x, y)
    # Smooth fit over every traced point (the computation region extends a little beyond the
    # pupil; rays there are traced through the same surfaces, so the fit interpolates).
    rmax = float(np.sqrt((x * x + y * y).max())) * 1.0001
    jfit = (_FIT_ORDER + 1) * (_FIT_ORDER + 2) // 2
    basis = zernike_basis(x / rmax, y / rmax, jmax=jfit, eps=0.0)
    # 120 smooth terms need far fewer than the ~15k traced points: fit on a regular subset
    # (both coordinates in one solve), then evaluate everywhere.
    fit_idx = np.flatnonzero(ok)[::3]
    coef, *_ = np.linalg.lstsq(basis.z[:, fit_idx].T.astype(float),
                               np.stack([hx[fit_idx], hy[fit_idx]], axis=1), rcond=None)
    cx, cy = coef[:, 0], coef[:, 1]
    fx, fy = cx @ basis.z, cy @ basis.z
    rms = float(np.sqrt(np.mean((fx - hx)[ok] ** 2 + (fy - hy)[ok] ** 2)))
    # Derivatives of the fitted polynomials w.r.t. the reduced pupil coordinates.
    jxx, jxy = cx @ basis.dx / rmax, cx @ basis.dy / rmax
    jyx, jyy = cy @ basis.dx / rmax, cy @ basis.dy / rmax
    return (fx, fy, jxx, jxy, jyx, jyy), transmitted, rms


def nominal_mapping(inst: Instrument, side: str, x: np.ndarray, y: np.ndarray, *,
                    defocus_mm: float, band: str | None = None,
                    wavelength_nm: float | None = None,
                    field_deg: tuple[float, float] = (0.0, 0.0)) -> ImageMapping:
    """The unperturbed mapping of ``inst`` for one image side at pupil points (x, y).

    Args:
        inst: the instrument; its ``mapping`` field selects the model.
        side: ``"intra"`` (detector at -defocus) or ``"extra"`` (+defocus).
        x, y: reduced pupil coordinates (1-D arrays).
        defocus_mm: |detector offset| l.
        band, wavelength_nm: optical band and wavelength (batoid model only).
        field_deg: field angle (x, y) of the star in degrees (batoid model only).
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    rms = 0.0
    if inst.mapping == "paraxial":
        parts = _paraxial(inst, side, defocus_mm, x, y)
        transmitted = _annulus(inst, x, y)
    elif inst.mapping == "fastbeam":
        parts = _fastbeam(inst, side, defocus_mm, x, y)
        transmitted = _annulus(inst, x, y)
    else:
        band = band or inst.default_band
        wl = inst.wavelength_nm(band, wavelength_nm)
        parts, transmitted, rms = _batoid(inst, side, defocus_mm, x, y, band, wl,
                                          (float(field_deg[0]), float(field_deg[1])))
        transmitted = transmitted & _annulus(inst, x, y)
    return ImageMapping(side, *parts, transmitted=transmitted,
                        c_px_per_nm=_c_px_per_nm(inst, side, defocus_mm), fit_rms_px=rms)


@lru_cache(maxsize=256)
def design_zernikes_nm(inst: Instrument, band: str, wavelength_nm: float,
                       field_deg: tuple[float, float], jmax: int) -> np.ndarray:
    """Design (intrinsic) wavefront Z1..Z_jmax in nm at a field point; zeros if not ray-traced.

    Uses ``batoid.zernike``: the annular Zernike fit (the instrument's obscuration) of the
    in-focus design telescope's wavefront over the *unvignetted* rays, on a 128x128 pupil
    grid.  The Gaussian-quadrature variant (``zernikeGQ``) integrates over the full annulus
    including vignetted rays; at the FAM edge fields it is 8 nm rms further from the ZEMAX
    truth (1.8 nm with this one), and it disagrees with the simulator's truth by up to 7 nm
    at the corner sensors.
    """
    out = np.zeros(jmax)
    if inst.mapping != "batoid":
        return out
    import batoid

    tel = _batoid_telescope(inst.batoid_optic, band)
    wl = wavelength_nm * 1e-9
    z = batoid.zernike(tel, np.deg2rad(field_deg[0]), np.deg2rad(field_deg[1]), wl,
                       jmax=jmax, eps=inst.obscuration, nx=128)
    out[:] = z[1:] * wavelength_nm
    out.setflags(write=False)
    return out
