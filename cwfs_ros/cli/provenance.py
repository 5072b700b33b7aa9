"""One pair from files to a judged, documented estimate: what ``cwfs-ros estimate`` and
``cwfs-ros batch`` run (ROS-free).

* :func:`read_pair_image` reads an image file, or says why it is not an image ("a PNG
  file", "binary data", ...), and the geometry its FITS header records (:data:`FITS_KEYS`).
* :func:`assess` lists every check of an estimate with its outcome.  Three of them flag the
  estimate as unusable: ``caustic`` (the compensation folded; the numbers are the last good
  iteration's), ``plausible`` (a departure from design beyond what the telescope can hold
  at this defocus, see :func:`plausible_limit_nm`) and ``swap`` when it could only have
  raised.  The others are informational (``settled``, ``swap_check`` ...).
* :func:`provenance` is the JSON record: inputs (path, size, SHA-256), instrument, band,
  wavelength, defocal offset, solver, seeing, field sources, software versions and checks.

FITS header keywords (in the HDU holding the image, else the primary header), read when
present; a command-line value wins over the header:

``FIELD_X``, ``FIELD_Y``  field angle of the star (x, y) in degrees, focal-plane frame;
``DEFOCUS``               signed detector offset from focus in mm: negative intra-focal,
                          positive extra-focal (its magnitude is the defocal offset; a sign
                          that contradicts the image's role is refused: swapped files).
"""

from __future__ import annotations

import hashlib
import math
import platform
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.errors import ConfigError, CwfsError

__all__ = [
    "FITS_KEYS",
    "Check",
    "format_geometry",
    "last_update_nm",
    "PairInput",
    "assess",
    "plausible_limit_nm",
    "provenance",
    "read_pair_image",
    "run_pair",
    "software_versions",
]

FITS_KEYS = {"field_x": "FIELD_X", "field_y": "FIELD_Y", "defocus": "DEFOCUS"}
# How estimate and batch take what a FITS header may lack (named in the messages of both).
FIELD_OPTIONS = {role: f"estimate --field-{role} X Y, batch columns field_{role}_x/_y"
                 for role in ("intra", "extra")}
DEFOCUS_OPTION = "estimate --defocal-offset, batch column defocal_offset_mm"
# A number as the ZEMAX exports write them (1.234E+000): their text images are stored
# upside down, and any other text is more likely an array written as it stands.
_ZEMAX_NUMBER = re.compile(rb"\d\.\d+E[+-]\d{3}(?!\d)")
# The fraction of the sensor's own defocus (as Z4) a departure from design may reach.
PLAUSIBLE_FRACTION = 0.5
# An outer loop still moving by more than this (nm rms) at its iteration limit is not near a
# fixed point: on a consistent pair the last update is ~0.05 nm, the solver's tolerance;
# a wrong field angle, defocus or exchanged images leave it at ~10 nm.
UNSETTLED_WARN_NM = 1.0
_MAGIC = ((b"\x89PNG", "a PNG picture"), (b"\xff\xd8\xff", "a JPEG picture"),
          (b"GIF8", "a GIF picture"), (b"II*\x00", "a TIFF picture"),
          (b"MM\x00*", "a TIFF picture"), (b"%PDF", "a PDF document"),
          (b"PK\x03\x04", "a ZIP archive"), (b"\x1f\x8b", "gzip-compressed data"))


@dataclass
class PairInput:
    """An image read from a file, with what its header says about its geometry."""

    path: Path
    image: np.ndarray
    field_deg: tuple[float, float] | None = None
    defocus_mm: float | None = None
    #: A text image whose rows were reversed on reading (the ZEMAX set's storage order).
    text_flipped: bool = False
    #: A text image whose numbers are not written as the ZEMAX exports write them.
    text_not_zemax: bool = False
    #: A text image read as stored (``--no-text-flip``).
    text_as_stored: bool = False

    def describe(self) -> dict[str, Any]:
        data = self.path.read_bytes()
        return {"path": str(self.path), "bytes": len(data),
                "sha256": hashlib.sha256(data).hexdigest(), "shape": list(self.image.shape),
                "text_flipped": self.text_flipped}


def _not_an_image(path: Path, role: str, reason: str) -> Exception:
    from cwfs_ros.errors import ImageError

    return ImageError(f"{role} image {path}: not an image: {reason} (give .npy, FITS or a "
                      "text table of numbers)")


def _head(path: Path, n: int = 4096) -> bytes:
    """The first ``n`` bytes of a file (what the text tests read)."""
    with open(path, "rb") as f:
        return f.read(n)


def _sniff(path: Path) -> str | None:
    """Why a file meant as a text image is not one (None when it may be)."""
    head = _head(path)
    for magic, what in _MAGIC:
        if head.startswith(magic):
            return f"it is {what}"
    if b"\x00" in head:
        return "it holds binary data, not text"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not merely a character cut at the 4 kB boundary
            return f"it is not text (byte 0x{head[exc.start]:02x} at offset {exc.start})"
    return None


def _fits_geometry(path: Path) -> tuple[tuple[float, float] | None, float | None]:
    from astropy.io import fits

    with fits.open(path) as hdul:
        hdus = [h for h in hdul if h.data is not None and getattr(h.data, "ndim", 0) == 2]
        headers = [h.header for h in hdus[:1]] + [hdul[0].header]

    def key(k: str) -> float | None:
        for h in headers:
            if k in h:
                v = h[k]
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    return float(v)
                raise ConfigError(f"{path}: its FITS header's {k} = {v!r} is not a number "
                                  f"({'degrees' if k != FITS_KEYS['defocus'] else 'mm'}); "
                                  "mend the header")
        return None

    fx, fy, dz = (key(FITS_KEYS[k]) for k in ("field_x", "field_y", "defocus"))
    if (fx is None) != (fy is None):
        have, lack = ((FITS_KEYS["field_x"], FITS_KEYS["field_y"]) if fy is None
                      else (FITS_KEYS["field_y"], FITS_KEYS["field_x"]))
        raise ConfigError(f"{path}: its FITS header has {have} but not {lack}: give both, "
                          "or the field on the command line")
    fld = (fx, fy) if fx is not None and fy is not None else None
    return fld, dz


def read_pair_image(path: str | Path, role: str, *, text_flip: bool = True) -> PairInput:
    """The image of ``role`` (intra / extra) and its FITS geometry; ImageError "not an
    image: <reason>" for a file that holds none."""
    from cwfs_ros.errors import ImageError
    from cwfs_ros.wfs.io import read_image

    p = Path(path)
    if not p.exists():
        raise ImageError(f"{role} image {path}: no such file")
    if not p.is_file():
        raise ImageError(f"{role} image {path}: not a regular file")
    name = p.name.lower()
    is_fits = name.endswith((".fits", ".fit", ".fits.gz", ".fz"))
    if not is_fits and not name.endswith(".npy"):
        reason = _sniff(p)
        if reason:
            raise _not_an_image(p, role, reason)
    try:
        image = read_image(p, text_flip=text_flip)
    except ImageError as exc:
        reason = str(exc).split(": ", 1)[-1] if str(exc).startswith(("cannot", str(p))) else exc
        raise _not_an_image(p, role, str(reason)) from None
    fld, dz = _fits_geometry(p) if is_fits else (None, None)
    if dz is not None and dz != 0 and (dz < 0) != (role == "intra"):
        raise ImageError(f"{role} image {path}: its FITS header says {FITS_KEYS['defocus']} "
                         f"= {dz:g} mm, an {'intra' if dz < 0 else 'extra'}-focal image "
                         "(are intra and extra exchanged?)")
    text = not is_fits and not name.endswith(".npy")
    return PairInput(p, image, fld, None if dz is None else abs(dz),
                     text_flipped=text and text_flip, text_as_stored=text and not text_flip,
                     text_not_zemax=text and not _ZEMAX_NUMBER.search(_head(p)))


def _header_defocus(pi: PairInput, role: str, inst: Any) -> float:
    """The FITS header's |DEFOCUS| if the instrument can sense at it; else ConfigError
    naming the file and the keyword (with the unit it looks like)."""
    try:
        return inst.checked_defocal_offset_mm(pi.defocus_mm, FITS_KEYS["defocus"])
    except ConfigError as exc:
        raise ConfigError(f"{role} image {pi.path}: its FITS header: {exc}; give the offset "
                          f"in mm ({DEFOCUS_OPTION}) or mend the header") from None


# ------------------------------------------------------------------------------ checks
@dataclass
class Check:
    """One check of an estimate: ``outcome`` is pass / fail / off / a word of the check's
    own (swap: confirmed / inconclusive); ``flags`` a fail that makes it unusable;
    ``warning`` an outcome to look into before using the numbers, which does not flag them
    (the detail starts with WARNING)."""

    name: str
    outcome: str
    detail: str
    flags: bool = field(default=False)
    warning: bool = field(default=False)

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "outcome": self.outcome, "detail": self.detail,
                "flags_estimate": self.flags, "warning": self.warning}


def plausible_limit_nm(inst: Any, defocal_offset_mm: float) -> float:
    """The largest departure from design (any of Z4..Z22, nm) taken as real.

    A detector ``l`` mm from focus sees a defocus of ``Z4 = l / (16 sqrt(3) N^2)`` (Noll
    normalisation, f-number N): 35.6 um for LSST at 1.5 mm.  A departure of half that would
    move the focus halfway to the sensor and change the donut's size by half; the telescope
    is not operated there and the estimator's mapping does not hold there, so such a number
    is a wrong input (field, defocus, instrument) rather than a wavefront.
    """
    z4_nm = defocal_offset_mm * 1e6 / (16.0 * math.sqrt(3.0) * inst.f_number ** 2)
    return PLAUSIBLE_FRACTION * z4_nm


def assess(result: Any, inst: Any, defocal_offset_mm: float) -> list[Check]:
    """Every check of an estimate, in the order the estimate met them."""
    r = math.hypot(*result.field_deg)
    limit = plausible_limit_nm(inst, defocal_offset_mm)
    dep = np.asarray(result.zernikes_nm) - np.asarray(result.intrinsic_nm)
    worst = int(np.argmax(np.abs(dep)))
    last = last_update_nm(result)
    return [
        Check("field_of_view", "pass", f"field {r:.3f} deg off axis, within "
              f"{inst.field_radius_deg:g} deg"),
        Check("image_checks", "pass", "finite, not flat, not cut, large enough, not "
              "saturated (each would have refused the pair)"),
        _swap(result.swap_check, inst.name),
        Check("caustic", "fail" if result.caustic else "pass",
              "the compensation folded into caustic: the numbers are the last good "
              "iteration's" if result.caustic else "no caustic", flags=bool(result.caustic)),
        Check("plausible", "fail" if abs(dep[worst]) > limit else "pass",
              f"largest departure from design Z{int(result.noll[worst])} = "
              f"{dep[worst]:.0f} nm, limit {limit:.0f} nm (half the sensor's own defocus)",
              flags=bool(abs(dep[worst]) > limit)),
        _settled(result, last),
    ]


def _swap(outcome: str, instrument: str) -> Check:
    """The swap check's outcome, and for ``off`` what then goes unseen."""
    if outcome != "off":
        return Check("swap_check", outcome, "intra/extra told apart by the vignetting, and "
                     "each image's orientation checked against it")
    where = (" (for LSST within about 1.3 deg of the axis)" if instrument.startswith("lsst")
             else "")
    return Check("swap_check", "off", "the vignetting at this field is too weak to tell intra "
                 f"from extra or a turned image{where}, or the check is disabled: exchanged, "
                 "turned or mirrored images are not detected here")


def last_update_nm(result: Any) -> float:
    """The outer loop's last update (nm rms over Z4..Z_jmax), NaN if it made none."""
    return float(result.residual_rms_nm[-1]) if len(result.residual_rms_nm) else float("nan")


def _settled(result: Any, last_nm: float) -> Check:
    """Whether the outer loop stopped moving: ``no`` by a fraction of a nm is a loop that ran
    out of iterations near its fixed point; by more than :data:`UNSETTLED_WARN_NM` the model
    does not fit the images, and the detail says so."""
    what = f"last update {last_nm:.3g} nm after {result.iterations} iterations"
    if result.converged:
        return Check("settled", "yes", f"{what} (below the solver's tolerance)")
    if last_nm > UNSETTLED_WARN_NM:
        return Check("settled", "no", f"WARNING: {what}, still moving by more than "
                     f"{UNSETTLED_WARN_NM:g} nm: the model does not fit these images. Check "
                     "the field angles, the defocal offset and which image is intra-focal; "
                     "do not use these numbers until it settles", warning=True)
    return Check("settled", "no", f"{what}: near its fixed point, not an error")


def software_versions() -> dict[str, str]:
    from importlib import metadata

    from cwfs_ros import __version__

    out = {"cwfs_ros": __version__, "python": platform.python_version()}
    for dist in ("numpy", "scipy", "batoid", "astropy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return out


def provenance(inputs: dict[str, PairInput], *, instrument: Any, defocal_offset_mm: float,
               seeing_fwhm_arcsec: float, field_sources: dict[str, str],
               checks: list[Check]) -> dict[str, Any]:
    """The record that makes an estimate reproducible (the ``--json`` additions)."""
    return {
        "inputs": {role: pi.describe() for role, pi in inputs.items()},
        "instrument_file": instrument.name,
        "defocal_offset_mm": defocal_offset_mm,
        "seeing_fwhm_arcsec": seeing_fwhm_arcsec,
        "field_sources": field_sources,
        "software": software_versions(),
        "checks": [c.as_dict() for c in checks],
        "flags": [c.name for c in checks if c.flags],
    }


@dataclass
class PairRun:
    """An estimate with its checks and its record (:func:`run_pair`)."""

    result: Any
    inputs: dict[str, PairInput]
    checks: list[Check]
    record: dict[str, Any]

    @property
    def flags(self) -> list[Check]:
        return [c for c in self.checks if c.flags]


def _geometry(inputs: dict[str, PairInput], fields: dict[str, Any],
              defocal_offset_mm: float | None, inst: Any
              ) -> tuple[dict[str, tuple[float, float]], dict[str, str], float]:
    got, sources = {}, {}
    for role, pi in inputs.items():
        if fields.get(role) is not None:
            got[role], sources[role] = tuple(float(v) for v in fields[role]), "command line"
        elif pi.field_deg is not None:
            got[role], sources[role] = pi.field_deg, f"FITS header {pi.path.name}"
        else:
            raise ConfigError(f"no field for the {role} image: give it "
                              f"({FIELD_OPTIONS[role]}), or {FITS_KEYS['field_x']}/"
                              f"{FITS_KEYS['field_y']} (deg) in its FITS header")
    if defocal_offset_mm is not None:
        return got, sources, float(defocal_offset_mm)
    # The headers' values are used: a wrong one is named with its file.
    headers = {_header_defocus(pi, role, inst) for role, pi in inputs.items()
               if pi.defocus_mm is not None}
    if len(headers) > 1:
        raise ConfigError(f"the FITS headers disagree on the defocal offset: {sorted(headers)}"
                          f" mm; give it ({DEFOCUS_OPTION})")
    return got, sources, headers.pop() if headers else inst.defocal_offset_mm


# An image this many stamp sizes across is taken for a frame in the estimate's messages.
FRAME_FACTOR = 4


def _frame_hint(inputs: dict[str, Any], inst: Any) -> str:
    """For an image far larger than a donut stamp (a whole frame): what takes frames."""
    rows, cols = (max(np.shape(inputs[s].image)[k] for s in inputs) for k in (0, 1))
    if max(rows, cols) < FRAME_FACTOR * inst.stamp_size_px:
        return ""
    return (f"a {rows}x{cols} image: estimate takes one donut per image, cut out as a stamp "
            f"(about {inst.stamp_size_px} px for {inst.name}); frames with several stars go "
            "to wavefront_node with input_mode frames, or to "
            "cwfs_ros.frames.estimate_corner_frames")


def _text_hint(exc: Exception, inputs: dict[str, PairInput],
               estimate: Callable[[np.ndarray, np.ndarray], Any]) -> str:
    """For a pair of text images read with their rows reversed and refused as turned,
    mirrored or exchanged: whether the same images read as stored pass (one more estimate,
    on this failure path only)."""
    from cwfs_ros.errors import MisorientedImageError, SwappedImagesError

    flipped = [s for s in inputs if inputs[s].text_flipped]
    if not flipped or not isinstance(exc, (MisorientedImageError, SwappedImagesError)):
        return ""
    try:
        estimate(*(inputs[s].image[::-1] if inputs[s].text_flipped else inputs[s].image
                   for s in ("intra", "extra")))
    except CwfsError:
        return ""
    return (f"the text image{'s were' if len(flipped) > 1 else ' was'} read with the rows "
            "reversed, as the ZEMAX set stores them; read as stored, the pair passes this "
            "check: text written from arrays already in the focal-plane frame [row=y, "
            "col=x] (numpy savetxt, say) is read so with --no-text-flip, while ZEMAX images "
            "point to a wrong field")


def _input_notes(inputs: dict[str, PairInput], inst: Any, band: str,
                 wavelength_nm: float | None) -> list[Check]:
    """Checks on how the inputs were read: text images' row order, and a wavelength given
    that lies nearer another band's effective wavelength than the band's (a WARNING: the
    optics are the band's filter, traced at that wavelength)."""
    out = []
    flipped = [s for s in inputs if inputs[s].text_flipped]
    stored = [s for s in inputs if inputs[s].text_as_stored]
    if stored:
        out.append(Check("text_images", "as stored", f"{' and '.join(stored)} read from text "
                         "as stored (--no-text-flip): row 0 is the smallest y"))
    if flipped:
        what = (f"{' and '.join(flipped)} read from text with the rows reversed, as the ZEMAX "
                "set stores them (--no-text-flip reads them as stored)")
        odd = [s for s in flipped if inputs[s].text_not_zemax]
        if odd:
            what = (f"WARNING: {what}, but {' and '.join(odd)} "
                    f"do{'es' if len(odd) == 1 else ''} not look like a ZEMAX export "
                    "(numbers such as 1.234E+000): text written from an array in the "
                    "focal-plane frame [row=y, col=x] (numpy savetxt, say) is upside down so, "
                    "and on axis nothing else can tell")
        out.append(Check("text_images", "flipped", what, warning=bool(odd)))
    if wavelength_nm is not None and band in inst.band_wavelength_nm:
        effective = inst.band_wavelength_nm
        nearest = min(effective, key=lambda b: abs(effective[b] - float(wavelength_nm)))
        if nearest != band:
            out.append(Check(
                "band", "mismatch", f"WARNING: {float(wavelength_nm):g} nm is nearer band "
                f"{nearest}'s effective wavelength ({effective[nearest]:g} nm) than band "
                f"{band}'s ({effective[band]:g} nm); the optics are band {band}'s, traced at "
                f"{float(wavelength_nm):g} nm. Check --band", warning=True))
    return out


def run_pair(intra: str | Path, extra: str | Path, *, field_intra: Any = None,
             field_extra: Any = None, instrument: str = "lsst", band: str | None = None,
             wavelength_nm: float | None = None, defocal_offset_mm: float | None = None,
             solver: str = "lsq", seeing_fwhm_arcsec: float = 0.0, text_flip: bool = True,
             **algorithm: Any) -> PairRun:
    """Read a pair of files, estimate, check and record (errors: the core's CwfsError)."""
    from cwfs_ros.wfs import estimate_wavefront, load_instrument

    inst = load_instrument(instrument)
    inputs = {"intra": read_pair_image(intra, "intra", text_flip=text_flip),
              "extra": read_pair_image(extra, "extra", text_flip=text_flip)}
    fields, sources, defocus = _geometry(inputs, {"intra": field_intra, "extra": field_extra},
                                         defocal_offset_mm, inst)
    band = band or inst.default_band
    estimate = partial(estimate_wavefront, field_intra_deg=fields["intra"],
                       field_extra_deg=fields["extra"], instrument=inst, band=band,
                       wavelength_nm=wavelength_nm, defocal_offset_mm=defocus, solver=solver,
                       seeing_fwhm_arcsec=seeing_fwhm_arcsec, **algorithm)
    try:
        result = estimate(inputs["intra"].image, inputs["extra"].image)
    except CwfsError as exc:
        hint = _frame_hint(inputs, inst) or _text_hint(exc, inputs, estimate)
        if not hint or isinstance(exc, ConfigError):
            raise
        raise type(exc)(f"{exc} ({hint})") from exc
    checks = assess(result, inst, defocus)
    checks += _input_notes(inputs, inst, band, wavelength_nm)
    record = provenance(inputs, instrument=inst, defocal_offset_mm=defocus,
                        seeing_fwhm_arcsec=seeing_fwhm_arcsec, field_sources=sources,
                        checks=checks)
    record["field_intra_deg"], record["field_extra_deg"] = fields["intra"], fields["extra"]
    record["defocal_offset_source"] = _defocus_source(inputs, defocal_offset_mm, inst)
    return PairRun(result, inputs, checks, record)


def _defocus_source(inputs: dict[str, PairInput], given_mm: float | None, inst: Any) -> str:
    if given_mm is not None:
        other = sorted({f"{pi.defocus_mm:g}" for pi in inputs.values()
                        if pi.defocus_mm is not None and pi.defocus_mm != float(given_mm)})
        return ("command line" + (f"; the FITS header says {', '.join(other)} mm"
                                  if other else ""))
    headers = [pi.path.name for pi in inputs.values() if pi.defocus_mm is not None]
    return f"FITS header {', '.join(headers)}" if headers else f"instrument {inst.name}"


def format_geometry(record: dict[str, Any]) -> str:
    """One line: each field and the defocal offset used, with where each came from."""
    def field(role: str) -> str:
        x, y = record[f"field_{role}_deg"]
        return f"{role} ({x:g}, {y:g}) deg ({record['field_sources'][role]})"

    return (f"inputs: field {field('intra')}, {field('extra')}; defocal offset "
            f"{record['defocal_offset_mm']:g} mm ({record['defocal_offset_source']})")
