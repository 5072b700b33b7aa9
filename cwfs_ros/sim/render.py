"""Ray-traced donut images and true wavefront Zernikes for the LSST corner sensors.

The renderer is independent of any wavefront estimator. It does not use a pupil-to-image
mapping model. It traces photons through the full batoid model: random rays are drawn
uniformly over the entrance-pupil annulus and traced through the (perturbed, defocused)
telescope to the detector. Vignetted and failed rays are dropped, which is how vignetting
shows up. The surviving rays are binned into pixels.

Image frame
-----------
Stamps are ``image[row, col]`` with ``col`` increasing with the detector-frame x and ``row``
increasing with y: batoid traces to the detector's local frame, so a rotated camera
(``perturbed_telescope(..., rotator_angle_deg=a)``) is imaged in its own frame. For a
telescope whose camera is not rotated, those are batoid's global focal-plane x and y. In
batoid's LSST model a star at field angle (+theta_x, 0) images at
focal-plane +x (plate scale ~ +10.31 m/rad), so the stamp frame is the frame of the field
angles. ``np.histogram2d(y, x, ...)`` would give the same layout.

Timing
------
Measured with ``bench/bench_sim.py`` on this project's shared 2-core development machine,
batoid 0.9.0, 160x160 stamp, corner field, one wavelength. The ranges span idle to
moderately loaded. Batoid's trace is single-threaded here.

* 1e5 rays: 0.23-0.38 s; 3e5 rays: 0.7-0.9 s; 1e6 rays: 2.2-2.6 s per donut. That is
  ~2.3 µs per ray, of which batoid's trace is ~95 %. Ray generation and binning take ~0.1 s
  per 1e6 rays.
* ``true_zernikes_nm``: 40-150 ms with the default ``nx=128`` (within ~0.3 nm of
  ``nx=255``), and 0.17-0.38 s with ``nx=255``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import batoid
import numpy as np

from cwfs_ros.config import CornerGeometry, load_sensor_geometry
from cwfs_ros.sim.sampling import annulus_samples
from cwfs_ros.sim.telescope import defocused
from cwfs_ros.wfs.blur import FWHM_PER_SIGMA

__all__ = [
    "CornerSensor",
    "RenderSettings",
    "TracedRays",
    "camera_zernikes_nm",
    "corner_fields",
    "load_corner_geometry",
    "plate_scale_um_per_arcsec",
    "pupil_vignetting_fraction",
    "render_donut",
    "trace_pupil_rays",
    "true_zernikes_nm",
]

_ARCSEC = np.pi / 180.0 / 3600.0  # radians per arcsec
_CHUNK = 1_000_000  # rays traced per batoid call (bounds memory: ~100 B per ray)


# --------------------------------------------------------------------------------------
# Ray tracing
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TracedRays:
    """Rays traced from the entrance pupil to the detector.

    Attributes
    ----------
    pupil_x, pupil_y : (N,) ray positions on the entrance-pupil (stop) plane, metres,
        in batoid's global frame.
    x, y : (N,) ray positions on the detector, metres, in the detector's local frame.
    ok : (N,) bool; True for rays that reached the detector (not vignetted and not failed).
    chief_x, chief_y : position of the chief ray (pupil centre) on the detector, metres.
        The chief ray of an obscured telescope is formally vignetted by the central hole;
        its geometric position is used.
    """

    pupil_x: np.ndarray
    pupil_y: np.ndarray
    x: np.ndarray
    y: np.ndarray
    ok: np.ndarray
    chief_x: float
    chief_y: float


def _pupil_geometry(telescope: batoid.Optic) -> tuple[float, float]:
    """Return (outer radius [m], fractional obscuration) of the entrance-pupil annulus."""
    return 0.5 * float(telescope.pupilSize), float(telescope.pupilObscuration)


def _trace_chunk(
    optic: batoid.Optic, px: np.ndarray, py: np.ndarray, wl_m: float, thx: float, thy: float
) -> batoid.RayVector:
    rv = batoid.RayVector.fromStop(px, py, optic, wavelength=wl_m, theta_x=thx, theta_y=thy)
    return optic.trace(rv)


def _chief_position(
    optic: batoid.Optic, wl_m: float, thx: float, thy: float
) -> tuple[float, float] | None:
    out = _trace_chunk(optic, np.zeros(1), np.zeros(1), wl_m, thx, thy)
    if bool(out.failed[0]):
        return None
    return float(out.x[0]), float(out.y[0])


def trace_pupil_rays(
    telescope: batoid.Optic,
    field_deg: tuple[float, float],
    detector_offset_mm: float,
    *,
    wavelength_nm: float,
    n_rays: int,
    rng: np.random.Generator | None = None,
    sampling: str = "random",
) -> TracedRays:
    """Trace ``n_rays`` uniformly distributed rays over the entrance-pupil annulus to the detector.

    Parameters
    ----------
    telescope : in-focus telescope (e.g. :func:`~cwfs_ros.sim.telescope.perturbed_telescope`).
    field_deg : (theta_x, theta_y) field angle in degrees (batoid field frame, postel).
    detector_offset_mm : detector displacement in mm (negative = intra-focal), see
        :func:`~cwfs_ros.sim.telescope.defocused`.
    wavelength_nm : wavelength in nm.
    n_rays : number of rays drawn over the annulus (including those later vignetted).
    rng : random generator (a fresh default one if None).
    sampling : ``"random"``: independent uniform rays (their shot noise is that of
        ``n_rays`` photons).  ``"quasi"``: a scrambled Sobol sequence (scipy.stats.qmc),
        whose integration error falls almost as 1 / n_rays instead of 1 / sqrt(n_rays):
        with ``poisson=False`` in :func:`render_donut` an (almost) noise-free geometric
        image, as the paper's ZEMAX test images, without the moire of a regular grid.

    Returns
    -------
    TracedRays

    Notes
    -----
    Rays are drawn over the annulus ``obscuration * R <= r <= R`` with ``R = pupilSize / 2``.
    Off axis, a few rays just outside this annulus would still reach the detector. At the
    corner sensors they would add about 0.15 % more light; they are not traced.
    """
    rng = np.random.default_rng() if rng is None else rng
    n_rays = int(n_rays)
    if n_rays < 1:
        raise ValueError("n_rays must be >= 1")
    optic = defocused(telescope, detector_offset_mm)
    wl_m = float(wavelength_nm) * 1e-9
    thx, thy = (float(np.deg2rad(a)) for a in field_deg)
    r_out, eps = _pupil_geometry(optic)

    # Uniform over the annulus area.
    rho, phi = annulus_samples(rng, n_rays, eps, sampling)
    r = r_out * rho
    px = r * np.cos(phi)
    py = r * np.sin(phi)

    x = np.empty(n_rays)
    y = np.empty(n_rays)
    ok = np.empty(n_rays, dtype=bool)
    for lo in range(0, n_rays, _CHUNK):
        hi = min(lo + _CHUNK, n_rays)
        out = _trace_chunk(optic, px[lo:hi], py[lo:hi], wl_m, thx, thy)
        x[lo:hi] = out.x
        y[lo:hi] = out.y
        ok[lo:hi] = ~(out.vignetted | out.failed)

    chief = _chief_position(optic, wl_m, thx, thy)
    if chief is None:  # pragma: no cover - does not happen for LSST fields <= 1.75 deg
        chief = (float(np.mean(x[ok])), float(np.mean(y[ok]))) if ok.any() else (0.0, 0.0)
    return TracedRays(px, py, x, y, ok, chief[0], chief[1])


def plate_scale_um_per_arcsec(
    telescope: batoid.Optic,
    field_deg: tuple[float, float] = (0.0, 0.0),
    *,
    wavelength_nm: float = 622.0,
) -> float:
    """Return the local focal-plane plate scale in µm per arcsec, from the ray-traced model.

    It is ``sqrt(|det J|)``, where J is batoid's Jacobian d(x, y)/d(theta_x, theta_y) at the
    field point, i.e. the effective focal length (m/rad) converted to µm/arcsec. For LSST it
    is ~10.31 m/rad = ~50.0 µm/arcsec, i.e. 0.2 arcsec per 10 µm pixel.
    """
    thx, thy = (float(np.deg2rad(a)) for a in field_deg)
    jac = batoid.drdth(telescope, thx, thy, float(wavelength_nm) * 1e-9)
    focal_m = float(np.sqrt(abs(np.linalg.det(jac))))
    return focal_m * _ARCSEC * 1e6


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------


def _bin_to_stamp(xs_px: np.ndarray, ys_px: np.ndarray, npix: int, weights: float) -> np.ndarray:
    """Histogram continuous pixel coordinates (pixel i spans [i, i+1)) into (npix, npix)."""
    col = np.floor(xs_px).astype(np.int64)
    row = np.floor(ys_px).astype(np.int64)
    keep = (col >= 0) & (col < npix) & (row >= 0) & (row < npix)
    idx = row[keep] * npix + col[keep]
    counts = np.bincount(idx, minlength=npix * npix).astype(np.float64)
    return counts.reshape(npix, npix) * weights


@dataclass(frozen=True)
class RenderSettings:
    """How :func:`render_donut` renders a donut: the detector, the light and the noise.

    Attributes
    ----------
    wavelength_nm : monochromatic wavelength in nm.
    npix : stamp side in pixels.
    pixel_um : pixel pitch in µm.
    n_photons : expected number of photons (electrons) entering the **unvignetted** pupil
        annulus. Vignetted photons are lost, so the expected image sum is
        ``n_photons * (1 - vignetting fraction)``, minus any light falling off the stamp.
    n_rays : rays to trace; default ``min(n_photons, 2e6)``. Each ray carries
        ``n_photons / n_rays`` photons (so ray shot noise is below photon noise when
        n_rays >= n_photons).
    seeing_fwhm_arcsec : FWHM of a Gaussian atmospheric blur, in arcsec. It is applied as
        independent per-ray offsets on the detector, converted with the model's plate scale
        (:func:`plate_scale_um_per_arcsec`, ~50 µm/arcsec for LSST).
    sky_per_pixel : expected sky background in electrons per pixel, added before noise.
    read_noise_e : Gaussian read noise, sigma in electrons per pixel.
    offset_px : (dx, dy) shift of the donut within the stamp in pixels: +dx moves it towards
        larger column index, +dy towards larger row index.
    centre : reference point of the stamp. ``"chief"``: the chief ray's hit on the detector.
        ``"centroid"``: the mean position of the surviving rays, before seeing. A tuple
        ``(x_m, y_m)``: a fixed detector position in metres, in the detector's local frame.
        Use it to see image motion between telescopes.
    poisson : if False, return the expected (noise-free, ray-sampled) image plus sky, and
        skip Poisson noise (read noise is still added if ``read_noise_e > 0``).
    subtract_sky : subtract ``sky_per_pixel`` from the returned image (after the noise).
    sampling : pupil sampling of the rays, ``"random"`` or ``"quasi"`` (see
        :func:`trace_pupil_rays`); ``"quasi"`` with ``poisson=False`` renders the
        noise-free image.

    Raises ValueError for a stamp of no pixels, no photons or an unknown ``centre``.
    """

    wavelength_nm: float
    npix: int = 160
    pixel_um: float = 10.0
    n_photons: float = 1e6
    n_rays: int | None = None
    seeing_fwhm_arcsec: float = 0.0
    sky_per_pixel: float = 0.0
    read_noise_e: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    centre: str | tuple[float, float] = "chief"
    poisson: bool = True
    subtract_sky: bool = False
    sampling: str = "random"

    def __post_init__(self) -> None:
        if self.npix < 1:
            raise ValueError("npix must be >= 1")
        if self.n_photons <= 0:
            raise ValueError("n_photons must be > 0")
        if isinstance(self.centre, str) and self.centre not in ("chief", "centroid"):
            raise ValueError("centre must be 'chief', 'centroid' or an (x_m, y_m) tuple")

    def ray_count(self) -> int:
        """Rays to trace: ``n_rays``, or ``min(n_photons, 2e6)`` (at least one)."""
        if self.n_rays is None:
            return int(max(1, round(min(float(self.n_photons), 2e6))))
        return self.n_rays


def render_donut(
    telescope: batoid.Optic,
    field_deg: tuple[float, float],
    detector_offset_mm: float,
    settings: RenderSettings | None = None,
    *,
    rng: np.random.Generator | None = None,
    **options: Any,
) -> np.ndarray:
    """Ray-trace a defocused star image ("donut") on an LSST wavefront sensor.

    The steps: trace photons through the defocused telescope (:func:`trace_pupil_rays`),
    place the survivors on the stamp relative to its reference point, with seeing
    (:func:`_stamp_positions`), bin them into pixels, and add the sky and the detector's
    noise (:func:`_detector_noise`).

    Parameters
    ----------
    telescope : the in-focus (perturbed) telescope, e.g. from ``perturbed_telescope``.
    field_deg : (theta_x, theta_y) of the star in degrees (batoid field frame).
    detector_offset_mm : detector displacement in mm; negative = intra-focal (before focus),
        positive = extra-focal. LSST corner sensors use -1.5 / +1.5.
    settings : the detector, light and noise (:class:`RenderSettings`).
    rng : random generator for ray positions and noise (fresh default if None).
    **options : fields of :class:`RenderSettings` (``wavelength_nm``, ``npix``,
        ``n_photons``, ``offset_px`` ...), replacing those of ``settings``; without
        ``settings`` they make one (``wavelength_nm`` is then required).

    Returns
    -------
    numpy.ndarray
        float64 ``(npix, npix)`` image in electrons, indexed ``[row = y, col = x]`` in the
        detector (focal-plane) frame. The reference point lands at continuous pixel
        coordinates ``(x, y) = (npix / 2 + dx, npix / 2 + dy)``, where pixel i spans
        [i, i+1). For the default ``offset_px`` and an even ``npix`` that is the shared
        corner of the four central pixels. In pixel-centre convention it is
        ``(npix - 1) / 2 + offset``.
    """
    s = RenderSettings(**options) if settings is None else replace(settings, **options)
    rng = np.random.default_rng() if rng is None else rng
    n_rays = s.ray_count()
    rays = trace_pupil_rays(telescope, field_deg, detector_offset_mm,
                            wavelength_nm=s.wavelength_nm, n_rays=n_rays, rng=rng,
                            sampling=s.sampling)
    xs, ys = _stamp_positions(rays, telescope, field_deg, s, rng)
    image = _bin_to_stamp(xs, ys, s.npix, float(s.n_photons) / n_rays)
    return _detector_noise(image, s, rng)


def _stamp_positions(rays: TracedRays, telescope: batoid.Optic,
                     field_deg: tuple[float, float], s: RenderSettings,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (pixel i spans [i, i+1)) of the rays that reached the
    detector: relative to the stamp's reference point (``s.centre``), blurred by the seeing
    (independent Gaussian offsets per ray), and placed so that the reference point lands at
    ``npix / 2 + offset_px``.

    The seeing offsets are drawn for every traced ray, vignetted or not, and then masked:
    two renders with the same seed (a finite difference, ``+h`` and ``-h``) then give each
    pupil ray the same offset even where a step changes which rays are vignetted. Drawing
    them for the surviving rays only would shift every later ray's offset there, and the
    difference of the two images would carry seeing noise of the whole donut."""
    ok = rays.ok
    if not isinstance(s.centre, str):
        x0, y0 = _pair(s.centre)
    elif s.centre == "chief":
        x0, y0 = rays.chief_x, rays.chief_y
    else:
        x0, y0 = ((float(np.mean(rays.x[ok])), float(np.mean(rays.y[ok]))) if ok.any()
                  else (0.0, 0.0))
    pix_m = float(s.pixel_um) * 1e-6
    xs = (rays.x - x0) / pix_m
    ys = (rays.y - y0) / pix_m
    if s.seeing_fwhm_arcsec > 0:
        scale = plate_scale_um_per_arcsec(telescope, field_deg, wavelength_nm=s.wavelength_nm)
        sigma_px = s.seeing_fwhm_arcsec / FWHM_PER_SIGMA * scale / float(s.pixel_um)
        xs = xs + rng.normal(0.0, sigma_px, xs.size)
        ys = ys + rng.normal(0.0, sigma_px, ys.size)
    xs = xs[ok] + (0.5 * s.npix + float(s.offset_px[0]))
    ys = ys[ok] + (0.5 * s.npix + float(s.offset_px[1]))
    return xs, ys


def _detector_noise(image: np.ndarray, s: RenderSettings,
                    rng: np.random.Generator) -> np.ndarray:
    """The expected image plus sky, drawn as Poisson counts (``s.poisson``), plus Gaussian
    read noise, less the sky if ``s.subtract_sky``."""
    if s.sky_per_pixel:
        image += float(s.sky_per_pixel)
    if s.poisson:
        image = rng.poisson(image).astype(np.float64)
    if s.read_noise_e > 0:
        image += rng.normal(0.0, float(s.read_noise_e), image.shape)
    if s.subtract_sky and s.sky_per_pixel:
        image -= float(s.sky_per_pixel)
    return image


def pupil_vignetting_fraction(
    telescope: batoid.Optic,
    field_deg: tuple[float, float],
    detector_offset_mm: float = 0.0,
    wavelength_nm: float = 622.0,
    *,
    n_grid: int = 256,
) -> float:
    """Return the fraction of the entrance-pupil annulus that is vignetted at a field point.

    Parameters
    ----------
    telescope : in-focus telescope.
    field_deg : (theta_x, theta_y) in degrees.
    detector_offset_mm : detector displacement in mm. It barely matters: the vignetting comes
        from the mirrors and lenses.
    wavelength_nm : wavelength in nm.
    n_grid : the pupil is sampled on a deterministic ``n_grid x n_grid`` square grid,
        keeping the points inside the annulus (~0.49 n_grid^2 rays).

    Returns
    -------
    float
        Fraction in [0, 1] of annulus rays that do not reach the detector. About 0 on axis
        and about 0.075 at the LSST corner sensors.
    """
    optic = defocused(telescope, detector_offset_mm)
    r_out, eps = _pupil_geometry(optic)
    g = (np.arange(n_grid) + 0.5) / n_grid * 2.0 - 1.0
    gx, gy = np.meshgrid(g * r_out, g * r_out)
    rr = np.hypot(gx, gy)
    inside = (rr <= r_out) & (rr >= eps * r_out)
    px, py = gx[inside], gy[inside]
    thx, thy = (float(np.deg2rad(a)) for a in field_deg)
    out = _trace_chunk(optic, px, py, float(wavelength_nm) * 1e-9, thx, thy)
    ok = ~(out.vignetted | out.failed)
    return float(1.0 - np.mean(ok))


# --------------------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------------------


def true_zernikes_nm(
    telescope: batoid.Optic,
    field_deg: tuple[float, float],
    *,
    wavelength_nm: float,
    jmax: int = 22,
    eps: float = 0.61,
    nx: int = 128,
) -> np.ndarray:
    """Return the true wavefront annular Zernikes, Noll 4..jmax, in nm.

    Parameters
    ----------
    telescope : the **in-focus** telescope (detector at the nominal focal plane). Do not
        pass a ``defocused`` optic; its wavefront contains the sensor defocus itself
        (~ tens of µm of Z4).
    field_deg : (theta_x, theta_y) in degrees.
    wavelength_nm : wavelength in nm.
    jmax : highest Noll index.
    eps : annular obscuration ratio of the Zernike basis.
    nx : pupil sampling of :func:`batoid.zernike`.

    Returns
    -------
    numpy.ndarray
        ``(jmax - 3,)`` coefficients for Noll j = 4..jmax, in nm of wavefront (OPD). They are
        batoid's convention: the wavefront relative to the chief-ray reference sphere, pupil
        coordinates in batoid's global x/y, and the fit over the unvignetted pupil.
    """
    if jmax < 4:
        raise ValueError("jmax must be >= 4")
    thx, thy = (float(np.deg2rad(a)) for a in field_deg)
    wl_m = float(wavelength_nm) * 1e-9
    zk_waves = batoid.zernike(telescope, thx, thy, wl_m, jmax=jmax, eps=eps, nx=nx)
    return np.asarray(zk_waves[4 : jmax + 1], dtype=np.float64) * float(wavelength_nm)


def camera_zernikes_nm(
    telescope: batoid.Optic,
    field_camera_deg: tuple[float, float],
    rotator_angle_deg: float,
    *,
    wavelength_nm: float,
    nx: int = 128,
) -> np.ndarray:
    """True Z4..Z22 [nm] that a sensor of the rotated camera measures: the camera frame.

    Parameters
    ----------
    telescope : the in-focus telescope built with the same ``rotator_angle_deg``
        (:func:`~cwfs_ros.sim.telescope.perturbed_telescope`).
    field_camera_deg : the sensor's nominal (camera-frame) field point [deg].
    rotator_angle_deg : camera rotator angle [deg].

    Returns
    -------
    (19,) array [nm]: :func:`true_zernikes_nm` at the telescope field ``R(angle) f`` that the
    sensor sees, turned from the telescope pupil axes into the camera's
    (``zernike_rotation_matrix(angle).T``; :mod:`cwfs_ros.ofc.rotation`). At angle 0 it is
    :func:`true_zernikes_nm` at ``f``.
    """
    from cwfs_ros.ofc.rotation import telescope_field_deg, zernike_rotation_matrix

    a = np.deg2rad(float(rotator_angle_deg))
    g = telescope_field_deg(field_camera_deg, a)[0]
    z = true_zernikes_nm(telescope, (float(g[0]), float(g[1])), wavelength_nm=wavelength_nm,
                         nx=nx)
    return zernike_rotation_matrix(a).T @ z if a else z


# --------------------------------------------------------------------------------------
# Corner-sensor geometry
# --------------------------------------------------------------------------------------


# The corner-sensor geometry is read in one place (cwfs_ros.config); the simulator's name for it.
CornerSensor = CornerGeometry


def _pair(v: object) -> tuple[float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (2,):
        raise ValueError(f"expected a pair of numbers, got {v!r}")
    return float(a[0]), float(a[1])


def load_corner_geometry(path: str | Path | None = None) -> dict[str, CornerSensor]:
    """The corner-sensor geometry (default ``config/sensors/lsst_corners.yaml``).

    Returns
    -------
    dict
        Raft name -> :class:`CornerSensor`, in the file's order
        (:func:`cwfs_ros.config.load_sensor_geometry`).
    """
    return load_sensor_geometry(path)


def corner_fields(path: str | Path | None = None) -> dict[str, dict[str, tuple[float, float]]]:
    """Return ``{raft: {"extra": (thx, thy), "intra": (...), "mid": (...)}}`` in degrees."""
    return {
        name: {"extra": s.extra_field_deg, "intra": s.intra_field_deg, "mid": s.mid_field_deg}
        for name, s in load_corner_geometry(path).items()
    }
