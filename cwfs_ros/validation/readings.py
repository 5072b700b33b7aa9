"""The estimator's reading of a corner: a noise-free split pair, rendered by batoid's ray
trace and read by the shipped estimator.

A reading differs from the corner's true wavefront by the estimator's own error (its gain,
the aliasing of terms beyond Z22, its reading of the design): the measurement model
``estimator`` (``cwfs_ros.ofc.model``) is fitted to such readings, and the benchmarks and
tests that check it compare against them. Everything that would add noise to a difference
of two readings is switched off or shared: no Poisson noise, quasi-random pupil sampling,
and every donut drawn from ``default_rng(seed)``, so that two states read with one seed see
the same pupil points and the same seeing offsets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ReadingSettings", "corner_fields_deg", "corner_pair", "corner_reading_nm"]


@dataclass(frozen=True)
class ReadingSettings:
    """How a noise-free corner pair is rendered and read.

    Attributes:
        n_rays: rays per donut (a power of 2 keeps the Sobol sequence balanced).
        seed: every donut of the pair uses ``default_rng(seed)``.
        wavelength_nm: rendering wavelength (r band: 622 nm).
        seeing_arcsec: seeing FWHM of the render, and the seeing the estimator is told.
        defocus_mm: detector offsets of the intra and extra halves.
        npix: stamp side [px].
    """

    n_rays: int = 2**20
    seed: int = 1
    wavelength_nm: float = 622.0
    seeing_arcsec: float = 0.7
    defocus_mm: tuple[float, float] = (-1.5, 1.5)
    npix: int = 160


def corner_fields_deg(corner: str) -> tuple[tuple[float, float], tuple[float, float],
                                            tuple[float, float]]:
    """(intra, extra, mid-point) field of ``corner``'s halves [deg], camera frame."""
    from cwfs_ros.frames.field_position import load_half_chips

    h = load_half_chips()[corner]
    return (tuple(h["intra"].field_deg), tuple(h["extra"].field_deg),
            tuple(h["intra"].mid_deg))


def corner_pair(tel: Any, corner: str, settings: ReadingSettings = ReadingSettings(),
                angle_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The (intra, extra) stamps of ``corner`` for the batoid telescope ``tel``, noise-free.

    ``angle_deg`` is the rotator angle ``tel`` was built with: the stars are then at the
    telescope fields the turned halves see, and the stamps are in the camera frame.
    """
    from cwfs_ros.ofc.rotation import telescope_field_deg
    from cwfs_ros.sim.render import RenderSettings, render_donut

    s = RenderSettings(wavelength_nm=settings.wavelength_nm, npix=settings.npix,
                       n_photons=1e6, n_rays=settings.n_rays,
                       seeing_fwhm_arcsec=settings.seeing_arcsec, poisson=False,
                       sampling="quasi")
    theta = np.deg2rad(angle_deg)
    fi, fe, _ = corner_fields_deg(corner)
    intra, extra = (render_donut(tel, tuple(telescope_field_deg(f, theta)[0]), dz, s,
                                 rng=np.random.default_rng(settings.seed))
                    for f, dz in zip((fi, fe), settings.defocus_mm, strict=True))
    return intra, extra


def corner_reading_nm(tel: Any, corner: str, settings: ReadingSettings = ReadingSettings(),
                      angle_deg: float = 0.0, **estimator_kw: Any) -> np.ndarray:
    """(19,) the estimator's camera-frame Z4-Z22 [nm] at ``corner``, read from
    :func:`corner_pair`.

    The estimator is the shipped one (``lsq``, told the render's seeing); ``estimator_kw``
    overrides its settings (a wider fit, say).
    """
    from cwfs_ros.wfs import estimate_wavefront

    fi, fe, _ = corner_fields_deg(corner)
    kw = dict(solver="lsq", seeing_fwhm_arcsec=settings.seeing_arcsec) | estimator_kw
    r = estimate_wavefront(*corner_pair(tel, corner, settings, angle_deg),
                           field_intra_deg=fi, field_extra_deg=fe, **kw)
    return np.asarray(r.zernikes_nm)
