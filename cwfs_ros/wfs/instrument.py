"""Instrument geometry, loaded from ``config/instruments/<name>.yaml``.

Adding a telescope is a matter of adding a YAML file with the fields of :class:`Instrument`.
Every number lives in that file; the code derives the rest (pupil radius, donut radius, the
paper's C of eq. 11 and the focus offset of eq. 5).
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cwfs_ros.config import config_dir
from cwfs_ros.errors import ConfigError

__all__ = ["Instrument", "load_instrument", "available_instruments", "MAPPINGS",
           "WAVELENGTH_RANGE_NM", "checked_wavelength_nm", "MAX_DEFOCAL_OFFSET_MM",
           "MIN_DONUT_RADIUS_PX"]

MAPPINGS = ("paraxial", "fastbeam", "batoid", "poly10")


# Wavelengths a curvature sensor works in (nm): near UV to near IR. Outside, the value is in
# another unit (0.622 is um, 6.22e-7 is m) or a typo.
WAVELENGTH_RANGE_NM = (250.0, 2500.0)
#: The estimate takes a |defocal offset| in (0, this) mm.
MAX_DEFOCAL_OFFSET_MM = 100.0
#: The smallest donut (outer radius, px) the estimator takes: its pupil grid has one sample
#: per pixel, and a smaller donut resolves too few for Z4..Z22 (below ~8 px the geometry
#: cannot be built at all).
MIN_DONUT_RADIUS_PX = 10.0


def checked_wavelength_nm(value: float) -> float:
    """``value`` (nm) if within :data:`WAVELENGTH_RANGE_NM`, else ConfigError naming the
    unit it looks like."""
    lo, hi = WAVELENGTH_RANGE_NM
    v = float(value)
    if lo <= v <= hi:
        return v
    hint = ""
    if 0 < v < 1e-4:
        hint = f" (metres? {v:g} m = {v * 1e9:g} nm)"
    elif 0 < v < 10:
        hint = f" (micrometres? {v:g} um = {v * 1e3:g} nm)"
    raise ConfigError(f"wavelength_nm {value!r} is outside {lo:g}-{hi:g} nm{hint}")


@dataclass(frozen=True)
class Instrument:
    """Geometry of a curvature-wavefront-sensing telescope.

    Attributes:
        name: identifier (the YAML file's stem).
        focal_length_m: effective focal length f.
        aperture_diameter_m: entrance-pupil diameter 2R.
        obscuration: central obscuration ratio (inner/outer radius), the annular Zernike eps.
        defocal_offset_mm: |detector offset| l of the intra/extra images from focus.
        pixel_size_um: detector pixel pitch.
        stamp_size_px: default stamp side for rendering and cropping.
        mapping: pupil-to-image model: ``paraxial`` (eqs. 9-10), ``fastbeam`` (§3.2),
            ``batoid`` (ray-traced, any field; §3.3) or ``poly10`` (the paper's own §3.3
            tables of 10th-order polynomials fitted to ZEMAX ray hits, with its vignetting
            circles).
        batoid_optic: batoid YAML template with a ``{band}`` placeholder (batoid mapping only).
        mapping_tables: directory of the poly10 tables (``offAxis_c{x,y}{in,ex}_poly10.txt``
            and ``mask_migrate.txt``), relative to ``config/instruments`` unless absolute
            (poly10 mapping only).
        default_band: band used when the caller gives none.
        band_wavelength_nm: effective wavelength per band.
        saturation_level: pixel value of the stamps as given to the estimator (e.g. e- or
            ADU) at or above which the detector saturates; None (null) when unknown.
        field_radius_deg: radius of the field of view: a star farther from the axis is
            refused (:meth:`check_field`) as a wrong input, not estimated.
    """

    name: str
    focal_length_m: float
    aperture_diameter_m: float
    obscuration: float
    defocal_offset_mm: float
    pixel_size_um: float
    stamp_size_px: int
    mapping: str = "paraxial"
    batoid_optic: str | None = None
    mapping_tables: str | None = None
    default_band: str = "r"
    band_wavelength_nm: dict[str, float] = field(default_factory=dict)
    description: str = ""
    saturation_level: float | None = None
    field_radius_deg: float = 5.0

    def __post_init__(self) -> None:
        problems = []
        for name in ("focal_length_m", "aperture_diameter_m", "defocal_offset_mm",
                     "pixel_size_um"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0:
                problems.append(f"{name} must be a positive number, got {v!r}")
        if not isinstance(self.obscuration, (int, float)) or not 0 <= self.obscuration < 1:
            problems.append(f"obscuration must be in [0, 1), got {self.obscuration!r}")
        if not isinstance(self.stamp_size_px, int) or self.stamp_size_px < 8:
            problems.append(f"stamp_size_px must be an integer >= 8, got {self.stamp_size_px!r}")
        if self.mapping not in MAPPINGS:
            problems.append(f"mapping must be one of {MAPPINGS}, got {self.mapping!r}")
        if self.mapping == "batoid" and not self.batoid_optic:
            problems.append("mapping 'batoid' needs batoid_optic (e.g. 'LSST_{band}.yaml')")
        if self.mapping == "poly10" and not self.mapping_tables:
            problems.append("mapping 'poly10' needs mapping_tables (e.g. 'poly10/lsst')")
        sat = self.saturation_level
        if sat is not None and (isinstance(sat, bool) or not isinstance(sat, (int, float))
                                or not np.isfinite(sat)):
            problems.append(f"saturation_level must be a number or null, got {sat!r}")
        r = self.field_radius_deg
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 < r <= 5.0:
            problems.append(f"field_radius_deg must be in (0, 5], got {r!r}")
        if not isinstance(self.band_wavelength_nm, dict) or not all(
            isinstance(v, (int, float)) and v > 0 for v in self.band_wavelength_nm.values()
        ):
            problems.append("band_wavelength_nm must map band names to positive numbers")
        if problems:
            raise ConfigError(f"instrument {self.name!r}: " + "; ".join(problems))

    def __hash__(self) -> int:  # the dict field is not hashable; instruments key caches
        # Kept once made: an instrument keys ~10 cache look-ups per pair geometry. Its fields
        # are frozen, and its band table, which keys caches as they do, is not to be changed
        # after it is made either.
        cached = self.__dict__.get("_hash")
        if cached is None:
            cached = hash(tuple((f.name, getattr(self, f.name)) for f in fields(self)
                                if f.name != "band_wavelength_nm")
                          + tuple(sorted(self.band_wavelength_nm.items())))
            object.__setattr__(self, "_hash", cached)
        return cached

    def __getstate__(self) -> dict:
        # Not the kept hash: string hashes differ between processes.
        return {k: v for k, v in self.__dict__.items() if k != "_hash"}

    # -- derived geometry ------------------------------------------------------------------
    @property
    def pupil_radius_m(self) -> float:
        return self.aperture_diameter_m / 2.0

    @property
    def f_number(self) -> float:
        return self.focal_length_m / self.aperture_diameter_m

    def donut_radius_px(self, defocal_offset_mm: float | None = None) -> float:
        """Paraxial radius of a defocused pupil image, l R / f, in pixels (paper §3.2)."""
        l_m = (defocal_offset_mm or self.defocal_offset_mm) * 1e-3
        return l_m * self.pupil_radius_m / self.focal_length_m / (self.pixel_size_um * 1e-6)

    def check_field(self, field_deg: tuple[float, float], what: str = "field") -> None:
        """Refuse a field (x, y) in degrees beyond :attr:`field_radius_deg` (ConfigError)."""
        r = float(np.hypot(*field_deg))
        if not r <= self.field_radius_deg:
            # Far beyond any telescope's field: another unit (arcsec reads as 3600x).
            unit = (f"; in arcseconds that is ({field_deg[0] / 3600:.4g}, "
                    f"{field_deg[1] / 3600:.4g}) deg" if r > 60.0 else "")
            raise ConfigError(
                f"{what} ({field_deg[0]:g}, {field_deg[1]:g}) deg is {r:.3f} deg off axis, "
                f"outside the field of view of {self.name} ({self.field_radius_deg:g} deg "
                f"radius, field_radius_deg of its instrument file){unit}")

    def checked_defocal_offset_mm(self, value: Any, what: str = "defocal_offset_mm"
                                  ) -> float:
        """``value`` (mm) if it is a defocal offset this instrument can sense at: within
        (0, :data:`MAX_DEFOCAL_OFFSET_MM`) and giving a donut of at least
        :data:`MIN_DONUT_RADIUS_PX`; else ConfigError naming ``what`` and the unit it looks
        like."""
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{what} must be a number (mm), got {value!r}") from None
        if not np.isfinite(v) or not 0 < v < MAX_DEFOCAL_OFFSET_MM:
            hint = ""
            if v < 0:
                hint = " (the offset's size: intra and extra are told by the images' roles)"
            elif (np.isfinite(v) and v < MAX_DEFOCAL_OFFSET_MM * 1e3
                  and self.donut_radius_px(v * 1e-3) >= MIN_DONUT_RADIUS_PX):
                hint = f" (micrometres? {v:g} um = {v * 1e-3:g} mm)"
            raise ConfigError(f"{what} must be in (0, {MAX_DEFOCAL_OFFSET_MM:g}) mm, got "
                              f"{value!r}{hint}")
        radius = self.donut_radius_px(v)
        if radius < MIN_DONUT_RADIUS_PX:
            hint = (f" (metres? {v:g} m = {v * 1e3:g} mm)"
                    if self.donut_radius_px(v * 1e3) >= MIN_DONUT_RADIUS_PX and v < 0.1 else "")
            raise ConfigError(
                f"{what} {v:g} mm gives a donut of radius {radius:.1f} px on {self.name}: "
                f"curvature sensing needs the pupil resolved, a radius of at least "
                f"{MIN_DONUT_RADIUS_PX:g} px ({MIN_DONUT_RADIUS_PX / radius * v:.3g} mm){hint}")
        return v

    def wavelength_nm(self, band: str | None, wavelength_nm: float | None = None) -> float:
        """The wavelength to use: the caller's, else the band's effective wavelength."""
        if wavelength_nm is not None:
            return checked_wavelength_nm(wavelength_nm)
        band = band or self.default_band
        try:
            return float(self.band_wavelength_nm[band])
        except KeyError:
            raise ConfigError(
                f"instrument {self.name!r} has no band {band!r}; "
                f"known: {sorted(self.band_wavelength_nm)}"
            ) from None

    def with_overrides(self, **kw: Any) -> Instrument:
        """A copy with some fields replaced (validated again)."""
        return replace(self, **kw)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Instrument:
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read instrument file {path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"instrument file {path} must hold a mapping, got {type(data)}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"instrument file {path}: unknown fields {unknown}")
        required = {f.name for f in fields(cls)
                    if f.default is MISSING and f.default_factory is MISSING}
        data.setdefault("name", path.stem)
        missing = sorted(required - set(data))
        if missing:
            raise ConfigError(f"instrument file {path}: missing fields {missing}")
        try:
            return cls(**data)
        except TypeError as exc:
            raise ConfigError(f"instrument file {path}: {exc}") from exc


def available_instruments() -> list[str]:
    return sorted(p.stem for p in (config_dir() / "instruments").glob("*.yaml"))


@lru_cache(maxsize=32)
def _load_cached(path: str, mtime: float) -> Instrument:
    return Instrument.from_yaml(path)


def load_instrument(name_or_path: str | Path | Instrument) -> Instrument:
    """Load an instrument by name (``config/instruments/<name>.yaml``) or from a YAML path."""
    if isinstance(name_or_path, Instrument):
        return name_or_path
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = config_dir() / "instruments" / f"{name_or_path}.yaml"
    try:
        # (is_file and stat raise OSError for a name the file system refuses, e.g. longer
        # than 255 bytes: a bad parameter value, not a crash.)
        found = p.is_file()
        key = (str(p.resolve()), p.stat().st_mtime) if found else None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"unknown instrument {str(name_or_path)[:80]!r}: {exc}") from exc
    if key is None:
        raise ConfigError(
            f"unknown instrument {str(name_or_path)!r}: no file {p}; "
            f"available: {available_instruments()}"
        )
    return _load_cached(*key)
