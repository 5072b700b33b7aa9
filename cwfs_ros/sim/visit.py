"""One simulated visit: the 8 corner-sensor donuts, rendered in parallel processes (no ROS).

Ray tracing dominates a simulated visit (about 2.3 us per photon per donut, single-threaded
in batoid, and it holds the GIL, so threads do not help). The 8 donuts of a visit are
independent, so they are spread over a small process pool. Each donut gets its own seed,
drawn up front by the caller, so the images are the same whatever the number of workers
(a test checks this): parallelism never changes a simulated result.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Hashable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass

import batoid
import numpy as np

from cwfs_ros.layout import SIDES
from cwfs_ros.sim.render import RenderSettings, render_donut

__all__ = ["DonutSpec", "FrameSpec", "FrameScene", "frame_specs", "make_render_pool",
           "render_frames", "render_visit"]


@dataclass(frozen=True)
class DonutSpec:
    """One donut of a visit.

    Attributes:
        key: the caller's name for it, e.g. ``("R00", "intra")``.
        field_deg: field angle (x, y) of the star [deg], telescope frame (batoid's global
            field; with a rotated camera, ``cwfs_ros.ofc.rotation.telescope_field_deg`` of
            the sensor's camera-frame field).
        detector_offset_mm: detector offset from focus [mm]; negative = intra-focal.
        offset_px: donut offset from the stamp centre (x, y) [px].
        seed: seed of this donut's photon sampling and noise.
    """

    key: Hashable
    field_deg: tuple[float, float]
    detector_offset_mm: float
    offset_px: tuple[float, float]
    seed: int


def _init_worker() -> None:
    # The pool is the parallelism: one BLAS/OpenMP thread per worker, not n x n.
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except Exception:  # noqa: BLE001, S110 - an optimisation only
        pass


def make_render_pool(n_workers: int) -> ProcessPoolExecutor | None:
    """A process pool for :func:`render_visit`, or ``None`` for ``n_workers <= 1``.

    ``n_workers = 0`` means one per CPU. Uses the fork server (spawn where unavailable):
    forking a process that runs DDS threads is unsafe.
    """
    n = int(n_workers) or (os.cpu_count() or 1)
    if n <= 1:
        return None
    method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    ctx = mp.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(["numpy", "batoid", "cwfs_ros.sim.render"])
    return ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_worker)


def _render_one(telescope: batoid.Optic, spec: DonutSpec, settings: RenderSettings
                ) -> np.ndarray:
    return render_donut(telescope, spec.field_deg, spec.detector_offset_mm, settings,
                        offset_px=spec.offset_px,
                        rng=np.random.default_rng(spec.seed)).astype(np.float32)


def render_visit(telescope: batoid.Optic, specs: Sequence[DonutSpec], *, wavelength_nm: float,
                 npix: int = 160, n_photons: float = 1e6, sky_per_pixel: float = 0.0,
                 seeing_fwhm_arcsec: float = 0.0, read_noise_e: float = 0.0,
                 executor: Executor | None = None) -> dict[Hashable, np.ndarray]:
    """Render every donut of ``specs`` (sky-subtracted float32 stamps, photo-electrons).

    Args:
        telescope: the in-focus, perturbed telescope (``perturbed_telescope``); it is sent
            to the workers by pickling (about 10 kB).
        specs: the donuts.
        wavelength_nm, npix, n_photons, sky_per_pixel, seeing_fwhm_arcsec, read_noise_e:
            as in :func:`cwfs_ros.sim.render.render_donut`.
        executor: a pool from :func:`make_render_pool`; ``None`` renders in this thread.

    Returns:
        ``{spec.key: image}``.
    """
    settings = RenderSettings(wavelength_nm=wavelength_nm, npix=int(npix),
                              n_photons=float(n_photons), sky_per_pixel=float(sky_per_pixel),
                              seeing_fwhm_arcsec=float(seeing_fwhm_arcsec),
                              read_noise_e=float(read_noise_e), poisson=True,
                              subtract_sky=True)
    if executor is None:
        return {s.key: _render_one(telescope, s, settings) for s in specs}
    futures = {s.key: executor.submit(_render_one, telescope, s, settings) for s in specs}
    return {k: f.result() for k, f in futures.items()}


@dataclass(frozen=True)
class FrameSpec:
    """One half-chip frame of a visit with several stars (donut-selection input).

    Attributes:
        key: the caller's name for it, e.g. ``("R00", "intra")``.
        field_ref_deg: the half-chip's field point [deg], imaged at the frame centre.
        detector_offset_mm: detector offset from focus [mm]; negative = intra-focal.
        shape_px: (rows, cols).
        n_stars: (min, max) isolated stars, log-uniform fluxes in ``flux_range``.
        flux_range: photons per isolated star.
        blend, faint: also inject a blended pair / a too-faint star.
        seed: seed of this frame's layout, photons and noise.
        rotator_angle_deg: camera rotator angle [deg] of the telescope the frame is rendered
            through; ``field_ref_deg`` is then the camera-frame (nominal) field.
    """

    key: Hashable
    field_ref_deg: tuple[float, float]
    detector_offset_mm: float
    shape_px: tuple[int, int]
    n_stars: tuple[int, int]
    flux_range: tuple[float, float]
    blend: bool
    faint: bool
    seed: int
    rotator_angle_deg: float = 0.0


@dataclass(frozen=True)
class FrameScene:
    """What every frame of a visit holds (camera_sim_node's frame parameters).

    Attributes:
        size_px: (rows, cols) of the frames of half-chips whose long side runs along the
            rows; the others' frames are turned by 90 degrees (:meth:`HalfChip.window`).
        n_stars, flux_range, blend, faint: as :class:`FrameSpec`.
    """

    size_px: tuple[int, int]
    n_stars: tuple[int, int]
    flux_range: tuple[float, float]
    blend: bool = True
    faint: bool = True


def frame_specs(corners: Sequence[str], scene: FrameScene, rng: np.random.Generator,
                rotator_angle_deg: float = 0.0, sensor_path: str | None = None
                ) -> list[FrameSpec]:
    """The two half-chip frames of each corner of a visit, keyed ``(corner, side)``: each a
    window of ``scene.size_px`` laid along its half-chip, as a camera reads a window out
    (R04 and R40 are R00's turned by 90 degrees; wavefront_node refuses a window across
    its half-chip), at the half-chip's field point and offset of the sensor file.  One seed
    per frame is drawn from ``rng``, in order."""
    from cwfs_ros.frames.field_position import load_half_chips

    halves = load_half_chips(sensor_path)
    specs = []
    for c in corners:
        for side in SIDES:
            h = halves[c][side]
            specs.append(FrameSpec((c, side), tuple(h.field_deg), float(h.detector_offset_mm),
                                   h.window(scene.size_px), scene.n_stars, scene.flux_range,
                                   scene.blend, scene.faint, int(rng.integers(2**62)),
                                   float(rotator_angle_deg)))
    return specs


def _render_frame(telescope: batoid.Optic, spec: FrameSpec, band: str, wavelength_nm: float,
                  sky_per_pixel: float, read_noise_e: float, seeing_fwhm_arcsec: float):
    from cwfs_ros.sim.frames import random_stars, render_frame

    rng = np.random.default_rng(spec.seed)
    stars = random_stars(rng, spec.shape_px, n_good=spec.n_stars, flux_range=spec.flux_range,
                         blend=spec.blend, faint=spec.faint,
                         detector_offset_mm=abs(spec.detector_offset_mm))
    return render_frame(telescope, stars, field_ref_deg=spec.field_ref_deg,
                        detector_offset_mm=spec.detector_offset_mm, shape_px=spec.shape_px,
                        band=band, wavelength_nm=wavelength_nm, sky_per_pixel=sky_per_pixel,
                        read_noise_e=read_noise_e, seeing_fwhm_arcsec=seeing_fwhm_arcsec,
                        rng=rng, rotator_angle_deg=spec.rotator_angle_deg)


def render_frames(telescope: batoid.Optic, specs: Sequence[FrameSpec], *, band: str,
                  wavelength_nm: float, sky_per_pixel: float = 50.0, read_noise_e: float = 0.0,
                  seeing_fwhm_arcsec: float = 0.0,
                  executor: Executor | None = None) -> dict[Hashable, object]:
    """Render every frame of ``specs`` (:class:`cwfs_ros.sim.frames.SimulatedFrame`, sky
    included: donut selection estimates and subtracts it), in parallel when given a pool."""
    args = (band, float(wavelength_nm), float(sky_per_pixel), float(read_noise_e),
            float(seeing_fwhm_arcsec))
    if executor is None:
        return {s.key: _render_frame(telescope, s, *args) for s in specs}
    futures = {s.key: executor.submit(_render_frame, telescope, s, *args) for s in specs}
    return {k: f.result() for k, f in futures.items()}
