"""Ray-traced corner half-chip frames with several stars (no estimator code involved).

A real corner half-sensor image holds several stars, not one neat stamp.  This module
renders such a frame: each star is a donut ray-traced through the (perturbed, defocused)
telescope at *its own* field angle (:func:`cwfs_ros.sim.render.render_donut`), placed where its
chief ray lands on the frame, plus a sky background and Poisson noise.  Optionally the layout
includes a blended pair, a too-faint star, a star cut by the frame edge, a saturated star.

Truth: the list of injected stars (pixel position of the chief ray, field angle, flux, flags).
Field angles are found by tracing chief rays through the *nominal* defocused design
(:func:`star_field_deg`: Newton iterations on the traced landing point), independently of
the estimator's own pixel-to-field model (:mod:`cwfs_ros.frames.field_position`).  A star is
placed at the pixel where the nominal design images its chief ray, with the perturbed
telescope's donut drawn around that point (``centre="chief"``): the frame is taken as
astrometrically registered, so perturbation-induced pointing shifts do not move stars.

Photon statistics: a star of expected flux F gets N ~ Poisson(F) photons, each traced as one
ray (``n_rays = N``, ``poisson=False``), so its image is an exact Poisson realisation without
a second noise draw; sky is Poisson too.  Cost ~2.3 µs per photon (see ``render.py``).

Frame layout: ``[row=y, col=x]`` in the focal-plane orientation, pixel-centre convention
(pixel (i, j) centred at x = i, y = j), reference field's chief ray at ``reference_px``
(default the frame centre).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import batoid
import numpy as np

from cwfs_ros.sim.render import RenderSettings, render_donut
from cwfs_ros.sim.telescope import defocused, load_lsst, perturbed_telescope

__all__ = ["StarSpec", "InjectedStar", "SimulatedFrame", "star_field_deg", "random_stars",
           "render_frame", "donut_outer_radius_px"]

FLAGS = ("blend", "faint", "edge", "saturated")


@dataclass(frozen=True)
class StarSpec:
    """A star to inject: chief-ray pixel (x=col, y=row), expected photons, flags."""

    x: float
    y: float
    flux: float
    flags: tuple[str, ...] = ()


@dataclass(frozen=True)
class InjectedStar:
    """Truth for one injected star.

    Attributes:
        x, y: chief-ray pixel (col, row), pixel-centre convention.
        field_deg: the star's field angle (deg), batoid field frame (the telescope frame;
            with a rotated camera, ``R(angle)`` times the camera-frame field).
        flux: expected photons entering the unvignetted pupil; ``photons`` the drawn number.
        flags: any of :data:`FLAGS`.
    """

    x: float
    y: float
    field_deg: tuple[float, float]
    flux: float
    photons: int
    flags: tuple[str, ...] = ()


@dataclass(frozen=True)
class SimulatedFrame:
    """A rendered half-chip frame and its truth.

    Attributes:
        image: (rows, cols) float32 frame in electrons, sky included.
        stars: the injected stars.
        sky_per_pixel: expected sky (e-/px).
        field_ref_deg, reference_px: the reference field and where its chief ray lands.
        detector_offset_mm: -1.5 (intra) or +1.5 (extra) for LSST.
    """

    image: np.ndarray = field(repr=False)
    stars: tuple[InjectedStar, ...]
    sky_per_pixel: float
    field_ref_deg: tuple[float, float]
    reference_px: tuple[float, float]
    detector_offset_mm: float


def donut_outer_radius_px(detector_offset_mm: float = 1.5, f_number: float = 1.234,
                          pixel_um: float = 10.0) -> float:
    """Outer radius of a donut (px): ``l tan(asin(1 / 2N))`` (used only for layouts)."""
    return abs(detector_offset_mm) * 1e3 * np.tan(np.arcsin(0.5 / f_number)) / pixel_um


def _chief_hit(optic: batoid.Optic, field_deg: tuple[float, float], wl_m: float
               ) -> np.ndarray:
    rv = batoid.RayVector.fromStop(np.zeros(1), np.zeros(1), optic=optic, wavelength=wl_m,
                                   theta_x=np.deg2rad(field_deg[0]),
                                   theta_y=np.deg2rad(field_deg[1]))
    out = optic.trace(rv)
    return np.array([out.x[0], out.y[0]])


def star_field_deg(x: float, y: float, *, field_ref_deg: tuple[float, float],
                   reference_px: tuple[float, float], detector_offset_mm: float,
                   band: str = "r", wavelength_nm: float = 622.0, pixel_um: float = 10.0,
                   optic: batoid.Optic | None = None) -> tuple[float, float]:
    """Field (deg) whose chief ray, traced through the defocused design, lands on pixel
    (x, y), the reference field's chief ray landing on ``reference_px``.

    Newton iterations on the traced landing point, with a finite-difference Jacobian;
    converged to < 1e-4 px.
    """
    opt = defocused(optic or load_lsst(band), detector_offset_mm)
    wl = wavelength_nm * 1e-9
    pix = pixel_um * 1e-6
    target = _chief_hit(opt, field_ref_deg, wl) + pix * np.array(
        [x - reference_px[0], y - reference_px[1]])
    th = np.array(field_ref_deg, dtype=float) + np.rad2deg(
        (target - _chief_hit(opt, field_ref_deg, wl)) / 10.31)
    h = 1e-4  # deg
    for _ in range(6):
        p0 = _chief_hit(opt, tuple(th), wl)
        jx = (_chief_hit(opt, (th[0] + h, th[1]), wl) - p0) / h
        jy = (_chief_hit(opt, (th[0], th[1] + h), wl) - p0) / h
        step = np.linalg.solve(np.stack([jx, jy], axis=1), target - p0)
        th = th + step
        if np.abs(step).max() < 1e-9:
            break
    return float(th[0]), float(th[1])


def random_stars(rng: np.random.Generator, shape_px: tuple[int, int], *,
                 n_good: int | tuple[int, int] = (3, 6),
                 flux_range: tuple[float, float] = (2e5, 1e6),
                 blend: bool = True, faint: bool = True, edge: bool = False,
                 saturated: bool = False, faint_flux: float = 1.2e4,
                 saturated_flux: float | None = None, stamp_px: int = 160,
                 detector_offset_mm: float = 1.5, max_tries: int = 2000) -> list[StarSpec]:
    """A random star layout for one frame.

    Good stars are isolated (no other star within ``stamp_px / 2 + 2 R + 40`` px, so their
    stamps hold no other light) and their stamps fit in the frame with 12 px to spare; their
    fluxes are log-uniform in ``flux_range``.  A blend is two stars 0.5-1.5 donut radii apart
    (their footprints overlap), a faint star has ``faint_flux`` photons, an edge star is
    centred 0.3 radius inside an edge, a saturated star has ``saturated_flux`` photons.

    Args:
        rng: random generator.
        shape_px: (rows, cols).
        n_good: number of good stars, or an inclusive (min, max) range.
    """
    r = donut_outer_radius_px(detector_offset_mm)
    sep = stamp_px / 2 + 2 * r + 40.0
    margin = stamp_px / 2 + 12.0
    n = n_good if isinstance(n_good, int) else int(rng.integers(n_good[0], n_good[1] + 1))
    layout = _Layout(rng, shape_px, max_tries)
    lo, hi = np.log(flux_range[0]), np.log(flux_range[1])
    if blend:
        x, y = layout.spot(sep + 1.5 * r, margin + 1.5 * r)
        phi = rng.uniform(0, 2 * np.pi)
        s = rng.uniform(0.5, 1.5) * r
        layout.placed.append(StarSpec(x, y, float(np.exp(rng.uniform(lo, hi))), ("blend",)))
        layout.placed.append(StarSpec(x + s * np.cos(phi), y + s * np.sin(phi),
                                      float(np.exp(rng.uniform(lo, hi))), ("blend",)))
    if edge:
        layout.edge_star(0.3 * r, margin, sep, (lo, hi))
    if saturated:
        x, y = layout.spot(sep, margin)
        layout.placed.append(StarSpec(x, y, float(saturated_flux or 20 * flux_range[1]),
                                      ("saturated",)))
    if faint:
        x, y = layout.spot(sep, margin)
        layout.placed.append(StarSpec(x, y, float(faint_flux), ("faint",)))
    for _ in range(n):
        x, y = layout.spot(sep, margin)
        layout.placed.append(StarSpec(x, y, float(np.exp(rng.uniform(lo, hi)))))
    return layout.placed


@dataclass
class _Layout:
    """Stars placed so far on a frame of ``shape_px`` (rows, cols), and where a new one fits."""

    rng: np.random.Generator
    shape_px: tuple[int, int]
    max_tries: int
    placed: list[StarSpec] = field(default_factory=list)

    def free(self, x: float, y: float, d: float) -> bool:
        """No star placed within ``d`` px of (x, y)."""
        return all(np.hypot(x - s.x, y - s.y) >= d for s in self.placed)

    def spot(self, d: float, m: float) -> tuple[float, float]:
        """A uniform random position at least ``m`` px inside the frame and ``d`` px from
        every star placed; ValueError after ``max_tries`` misses."""
        rows, cols = self.shape_px
        for _ in range(self.max_tries):
            x, y = self.rng.uniform(m, cols - 1 - m), self.rng.uniform(m, rows - 1 - m)
            if self.free(x, y, d):
                return float(x), float(y)
        raise ValueError(f"cannot place a star {d:.0f} px from the others in a "
                         f"{cols}x{rows} frame; use fewer stars or a larger frame")

    def edge_star(self, inset: float, margin: float, sep: float,
                  log_flux: tuple[float, float]) -> None:
        """Place a star ``inset`` px inside a random edge, ``sep`` px from the others (none
        if no such spot turns up in ``max_tries``)."""
        rows, cols = self.shape_px
        side = int(self.rng.integers(4))
        for _ in range(self.max_tries):
            t = self.rng.uniform(margin, (cols if side < 2 else rows) - 1 - margin)
            e = inset
            x, y = {0: (t, e), 1: (t, rows - 1 - e), 2: (e, t), 3: (cols - 1 - e, t)}[side]
            if self.free(x, y, sep):
                self.placed.append(StarSpec(float(x), float(y),
                                            float(np.exp(self.rng.uniform(*log_flux))),
                                            ("edge",)))
                return


def render_frame(telescope: batoid.Optic, stars: Sequence[StarSpec], *,
                 field_ref_deg: tuple[float, float], detector_offset_mm: float,
                 shape_px: tuple[int, int] = (2000, 1000),
                 reference_px: tuple[float, float] | None = None, band: str = "r",
                 wavelength_nm: float = 622.0, sky_per_pixel: float = 50.0,
                 read_noise_e: float = 0.0, full_well_e: float | None = None,
                 render_px: int = 200, pixel_um: float = 10.0,
                 seeing_fwhm_arcsec: float = 0.0,
                 rng: np.random.Generator | None = None,
                 rotator_angle_deg: float = 0.0) -> SimulatedFrame:
    """Render a half-chip frame with the given stars.

    Args:
        telescope: the in-focus (perturbed) telescope; donuts are traced through it.
        stars: chief-ray pixel positions and fluxes (:func:`random_stars`).
        field_ref_deg: the half-chip's field point, imaged at ``reference_px``.
        detector_offset_mm: -1.5 intra, +1.5 extra.
        shape_px: (rows, cols).
        reference_px: (col, row); default the frame centre.
        band, wavelength_nm: design model band (for star fields) and wavelength.
        sky_per_pixel: expected sky (e-/px), Poisson.
        read_noise_e: Gaussian read noise (e-).
        full_well_e: pixels are clipped at this level (saturation), if given.
        render_px: side of the region each donut is rendered into (px).
        pixel_um: pixel pitch.
        seeing_fwhm_arcsec: FWHM of a Gaussian atmospheric blur of every star (each photon
            is displaced at random, as in :func:`~cwfs_ros.sim.render.render_donut`); 0 =
            none, which draws no seeing offsets (the random stream of a frame without seeing).
        rng: random generator.
        rotator_angle_deg: camera rotator angle [deg]; ``telescope`` must be built with the
            same angle. ``field_ref_deg`` is then the camera-frame (nominal) field of the
            half-chip, and star fields are found through the rotated design.

    Returns:
        A :class:`SimulatedFrame`.
    """
    rng = rng or np.random.default_rng()
    rows, cols = shape_px
    ref = reference_px if reference_px is not None else ((cols - 1) / 2.0, (rows - 1) / 2.0)
    img = np.zeros((rows, cols), dtype=np.float64)
    design, ref_field = _design_frame(band, field_ref_deg, rotator_angle_deg)
    settings = RenderSettings(wavelength_nm=wavelength_nm, npix=render_px, pixel_um=pixel_um,
                              centre="chief", poisson=False,
                              seeing_fwhm_arcsec=seeing_fwhm_arcsec)
    truth = []
    for s in stars:
        fld = star_field_deg(s.x, s.y, field_ref_deg=ref_field, reference_px=ref,
                             detector_offset_mm=detector_offset_mm, band=band,
                             wavelength_nm=wavelength_nm, pixel_um=pixel_um, optic=design)
        n = int(rng.poisson(s.flux))
        if n > 0:
            _add_star(img, telescope, fld, detector_offset_mm, (s.x, s.y), n, settings, rng)
        truth.append(InjectedStar(float(s.x), float(s.y), fld, float(s.flux), n,
                                  tuple(s.flags)))
    if sky_per_pixel > 0:
        img += rng.poisson(float(sky_per_pixel), img.shape)
    if read_noise_e > 0:
        img += rng.normal(0.0, float(read_noise_e), img.shape)
    if full_well_e is not None:
        np.minimum(img, float(full_well_e), out=img)
    return SimulatedFrame(img.astype(np.float32), tuple(truth), float(sky_per_pixel),
                          (float(field_ref_deg[0]), float(field_ref_deg[1])),
                          (float(ref[0]), float(ref[1])), float(detector_offset_mm))


def _design_frame(band: str, field_ref_deg: tuple[float, float], rotator_angle_deg: float
                  ) -> tuple[batoid.Optic, tuple[float, float]]:
    """(design telescope, reference field) through which star fields are found: the
    nominal design, or with a rotated camera the rotated design and the reference field in
    the telescope's frame."""
    if not rotator_angle_deg:
        return load_lsst(band), field_ref_deg
    from cwfs_ros.ofc.rotation import telescope_field_deg

    design = perturbed_telescope(None, band, rotator_angle_deg=rotator_angle_deg)
    g = telescope_field_deg(field_ref_deg, np.deg2rad(rotator_angle_deg))[0]
    return design, (float(g[0]), float(g[1]))


def _add_star(img: np.ndarray, telescope: batoid.Optic, field_deg: tuple[float, float],
              detector_offset_mm: float, xy_px: tuple[float, float], n_photons: int,
              settings: RenderSettings, rng: np.random.Generator) -> None:
    """Add one star's ``n_photons`` (one ray each, noise-free binning) to ``img``, its chief
    ray at pixel ``xy_px`` (col, row; pixel-centre convention), clipped at the frame."""
    rows, cols = img.shape
    render_px = settings.npix
    # Stamp origin so that the chief ray lands at xy_px: render_donut puts it at
    # (render_px - 1) / 2 + offset in pixel-centre coordinates.
    c = (render_px - 1) / 2.0
    x0, y0 = int(np.floor(xy_px[0] - c)), int(np.floor(xy_px[1] - c))
    off = (xy_px[0] - c - x0, xy_px[1] - c - y0)
    st = render_donut(telescope, field_deg, detector_offset_mm, settings, n_photons=n_photons,
                      n_rays=n_photons, offset_px=off, rng=rng)
    ya, yb = max(y0, 0), min(y0 + render_px, rows)
    xa, xb = max(x0, 0), min(x0 + render_px, cols)
    if ya < yb and xa < xb:
        img[ya:yb, xa:xb] += st[ya - y0:yb - y0, xa - x0:xb - x0]
