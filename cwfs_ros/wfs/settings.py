"""The estimator's settings besides the images, shared by the live node and the replay.

One frozen, picklable dataclass (:class:`EstimatorSettings`) goes to every corner job, stamp
or frame, so the worker processes, the node and the offline replay estimate alike.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cwfs_ros.errors import ConfigError
from cwfs_ros.wfs.blur import check_seeing
from cwfs_ros.wfs.estimator import load_algorithm
from cwfs_ros.wfs.instrument import load_instrument

__all__ = ["EstimatorSettings", "validate_settings"]


@dataclass(frozen=True)
class EstimatorSettings:
    """What the estimator needs besides the images (all picklable, hashable).

    Attributes:
        instrument: ``config/instruments`` name or path.
        band: filter band (``u g r i z y``).
        solver: TIE solver (``exp``, ``fft``, ``lsq``).
        outer_iterations: outer-loop iterations; 0 means the ``config/algorithm.yaml`` value.
        pad_px: pixels of background padding added around each stamp before estimation
            (see :func:`cwfs_ros.wfs.orientation.pad_stamp`).
        seeing_fwhm_arcsec: atmospheric seeing of the images (FWHM, arcsec), whose blur the
            lsq and exp solvers take out of the signal (:mod:`cwfs_ros.wfs.blur`).
    """

    instrument: str = "lsst"
    band: str = "r"
    solver: str = "lsq"  # as estimate_wavefront and wavefront_node: best under photon noise
    outer_iterations: int = 0
    pad_px: int = 0
    seeing_fwhm_arcsec: float = 0.0

    @classmethod
    def from_params(cls, get: Callable[[str], Any]) -> EstimatorSettings:
        """The settings of wavefront_node's parameters, ``get(name) -> value``.

        The one mapping from parameter names to settings, for the node and for the offline
        replay of a bag (:mod:`cwfs_ros.cli.replay`) alike.
        """
        return cls(instrument=str(get("instrument")), band=str(get("band")),
                   solver=str(get("solver")), outer_iterations=int(get("outer_iterations")),
                   pad_px=int(get("pad_px")),
                   seeing_fwhm_arcsec=float(get("seeing_fwhm_arcsec")))

    def estimator_kwargs(self) -> dict:
        kw: dict = {"instrument": self.instrument, "band": self.band, "solver": self.solver,
                    "seeing_fwhm_arcsec": float(self.seeing_fwhm_arcsec)}
        if self.outer_iterations > 0:
            kw["outer_iterations"] = int(self.outer_iterations)
        return kw


def validate_settings(settings: EstimatorSettings) -> None:
    """Raise ConfigError naming the problem if the settings cannot work (cheap; no batoid)."""
    inst = load_instrument(settings.instrument)
    if inst.mapping == "batoid" and settings.band not in inst.band_wavelength_nm:
        raise ConfigError(f"unknown band {settings.band!r} for instrument {inst.name!r}; "
                          f"known: {sorted(inst.band_wavelength_nm)}")
    load_algorithm(settings.solver, **({"outer_iterations": settings.outer_iterations}
                                       if settings.outer_iterations > 0 else {}))
    if not 0 <= settings.pad_px <= 256:
        raise ConfigError(f"pad_px must be in 0..256, got {settings.pad_px}")
    check_seeing(settings.seeing_fwhm_arcsec)
