"""Optical feedback control (OFC): four corner wavefronts in, 50 degree-of-freedom corrections out.

numpy, galsim and PyYAML only; no ROS imports. The data live in ``config/ofc/`` (copied from
lsst-ts/ts_ofc, GPL-3.0, see ``config/ofc/PROVENANCE.md``).

Measurement vector
------------------
One visit gives ``y``, 76 numbers in **nm**: ``y[19 * c + (j - 4)]`` is the annular-Zernike
coefficient of Noll index ``j`` (4..22) of the wavefront at corner ``c``, corners in the
order of :data:`CORNER_SENSORS` (R00_SW0, R04_SW0, R40_SW0, R44_SW0; field points from
``config/ofc/sample_points/lsst_points.yaml``, in degrees). Zernikes are galsim/Noll
normalised (each term has unit RMS) on the pupil annulus 2.558 m .. 4.18 m. A ``(4, 19)``
array is accepted too. The frame is batoid's: the field angles are used as batoid's
``(thx, thy)`` and the Zernikes are batoid's ``batoid.zernike`` coefficients (the ts_ofc
intrinsic yaml reproduces ``batoid.zernike(LSST_r, ...)`` at the corners to ~5 nm in every
term, same signs).

Degrees of freedom
------------------
``x`` has 50 entries in ts_ofc order and units (``config/ofc/dof.yaml``): 0-4 M2 hexapod dz,
dx, dy [µm], rx, ry [deg]; 5-9 camera hexapod, same; 10-29 M1M3 bending modes 1-20 [µm];
30-49 M2 bending modes 1-20 [µm]. (The header of the ts_ofc matrix yaml says arcsec for the
rotations; the numbers are per **degree**: a 0.005° M2 tilt in batoid gives the matrix's
coma to 0.3 %, and the ts_ofc strokes 0.12°/0.24° are in degrees.)

THE sign convention of this module
----------------------------------
``A`` is the **wavefront sensitivity**, in nm per DoF unit::

    wavefront_change_nm = A @ dof_change

ts_ofc stores the *negative* of this, in µm ("correction" convention); :class:`SensitivityMatrix`
converts at load time (``A = -1000 * S_ts_ofc``), so nothing downstream sees the ts_ofc sign.

DoF convention (which way is "+" for each DoF)
----------------------------------------------
The DoF of this module, of ``cwfs_msgs/DofCorrection`` and of the simulator
(:func:`cwfs_ros.sim.perturbed_telescope`, default ``convention="batoid_rubin"``) follow
batoid_rubin's ``LSSTBuilder``, i.e. the observatory coordinate system (OCS), which maps into
batoid's global frame as x -> -x, y -> y, z -> -z (``dof_convention="batoid_rubin"``).

ts_ofc's matrix, converted to wavefront sign, is instead the finite-difference sensitivity of
a *plain* batoid frame (``dof_convention="ts_ofc"``; ratio 0.996-1.00 for the rigid body,
1.05-1.09 for bending modes 1-2, correlation > 0.9999; see ``test/test_control.py``), where a
DoF vector is applied to ``batoid.Optic.fromYaml("LSST_r.yaml")`` as:

* M2 / camera ``(dz, dx, dy)``: ``withGloballyShiftedOptic(name, [dx, dy, dz] * 1e-6)``;
* M2 / camera ``(rx, ry)``: ``withLocallyRotatedOptic(name, RotX(rad(rx)) @ RotY(rad(ry)))``;
* bending: sag ``+sum_k dof_k * Z_k`` (batoid_rubin's legacy ``*_bend_zk`` tables) added to
  M1 and M3 (M1M3 modes) or M2 (M2 modes).

The two conventions differ only in the sign of DoF :data:`TS_OFC_FLIPPED_DOF` = (0, 1, 3, 5,
6, 8), i.e. dz, dx and rx of M2 and of the camera (the x -> -x, z -> -z frame flip; dy, ry and
the bending modes are unchanged). :meth:`SensitivityMatrix.from_ts_ofc` therefore negates those
six columns by default, so that ``A`` is in the batoid_rubin/OCS convention of
``DofCorrection``; pass ``dof_convention="ts_ofc"`` to keep ts_ofc's own columns. The same
conversion for DoF vectors and matrices is :func:`convert_dof_convention`.

Controller
----------
Each visit: ``r = y - y_intrinsic`` (the wavefront error caused by the current optical state
error); the state error is estimated as ``e = A⁺ r`` with a truncated-SVD (default, 12 modes as
ts_ofc) or Tikhonov pseudo-inverse computed in *normalised* DoF coordinates ``z = x / w``
(``w`` = ts_ofc's range x FWHM weights, so that µm, degrees and bending modes are comparable);
then the correction to ADD to the telescope this visit is::

    u = -(kp * e + ki * sum_visits(e))          (defaults kp = 0.18, ki = 0.022, as ts_ofc)

clipped per DoF to ``max_step`` and so that the accumulated state stays within ``±range``.
Because ``A @ u ≈ -kp * r`` for the observable part, applying ``u`` reduces the wavefront.

Dynamics: the commanded state accumulates ``u``, so ``kp`` alone already integrates (each
observable mode decays by ``1 - kp`` = 0.82 per visit, monotonically). ``ki`` adds a second
integrator: a mode's error then follows ``c+ = c - kp c - ki sum(c)``, poles
``0.899 ± 0.109i`` for the defaults, and a step disturbance is removed in ~7 visits but
overshoots by ~25 % of its size before settling. Any ``ki > 0`` overshoots a step (the steady
state needs ``sum(e) = 0``, so ``e`` must change sign); ``ki`` pays off against drifts.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import galsim
import numpy as np

from cwfs_ros.config import config_dir, load_sensor_geometry, load_yaml, sensor_file
from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.layout import (
    CLOCK_RESET_S,
    CORNER_SENSORS,
    CORNERS,
    N_CORNERS,
    N_DOF,
    N_ZK,
    NOLL_MAX,
    NOLL_MIN,
)

__all__ = [
    "BANDS",
    "BUNDLED_MATRIX_FILENAME",
    "CheckedVisit",
    "DOF_CONVENTIONS",
    "MATRIX_SOURCES",
    "TS_OFC_FLIPPED_DOF",
    "DofSpec",
    "Estimate",
    "OFCResult",
    "OFCSolver",
    "ObservabilityReport",
    "OpticsConfig",
    "Refusal",
    "SensitivityMatrix",
    "band_wavelength_um",
    "convert_dof_convention",
    "corner_field_points_deg",
    "corner_mid_field_points_deg",
    "intrinsic_vector_nm",
    "intrinsic_zernikes_nm",
    "load_dof_spec",
    "load_normalization_weights",
    "load_optics_config",
    "observability",
    "ofc_config_dir",
    "sensitivity_for_source",
    "solver_from_params",
]

BANDS: tuple[str, ...] = ("u", "g", "r", "i", "z", "y", "ref")
# The project's own matrix (tools/make_sensitivity.py): r band, rows at the corner mid-points.
BUNDLED_MATRIX_FILENAME = "sensitivity_bundled_r.npy"
# DoF conventions (see the module docstring): "batoid_rubin" = OCS = DofCorrection = simulator
# default; "ts_ofc" = the plain batoid frame of ts_ofc's matrix. They differ in the sign of
# M2/camera dz, dx, rx (same tuple as cwfs_ros.sim.TS_OFC_FLIPPED_DOF, kept here so that this
# module needs no batoid).
DOF_CONVENTIONS: tuple[str, ...] = ("batoid_rubin", "ts_ofc")
TS_OFC_FLIPPED_DOF: tuple[int, ...] = (0, 1, 3, 5, 6, 8)

_TS_OFC_MATRIX = "sensitivity_matrix/lsst_sensitivity_dz_31_29_50.yaml"
_INTRINSIC_DIR = "intrinsic_zernikes/lsst"
_UM_TO_NM = 1000.0
_RANK_RTOL = 1e-12  # singular values below this (relative) are treated as exactly zero


# --------------------------------------------------------------------------------------------
# configuration files
# --------------------------------------------------------------------------------------------
def ofc_config_dir() -> Path:
    """Directory holding the OFC data (``<config>/ofc``, see :func:`cwfs_ros.config.config_dir`)."""
    return config_dir() / "ofc"


def _dir(cfg_dir: str | Path | None) -> Path:
    return ofc_config_dir() if cfg_dir is None else Path(cfg_dir)


def _load_yaml(path: str) -> object:
    """An OFC data file, parsed (:func:`cwfs_ros.config.load_yaml`: cached, ConfigError).

    The callers only read it (into new arrays or dataclasses), so the cached parse is shared.
    """
    return load_yaml(path, "OFC data file", copy_=False)


def _yaml_array(path: Path, shape_ndim: int) -> np.ndarray:
    arr = np.asarray(_load_yaml(str(path)), dtype=np.float64)
    if arr.ndim != shape_ndim:
        raise ConfigError(f"{path}: expected a {shape_ndim}-d array, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class OpticsConfig:
    """Radii and wavelengths from ts_ofc's ``configurations/lsst.yaml``.

    Attributes
    ----------
    field_inner_deg, field_outer_deg : field annulus of the double Zernikes, degrees.
    pupil_inner_m, pupil_outer_m : pupil annulus of the Zernikes, metres.
    wavelengths_um : band -> wavelength in µm (``"ref"`` is 0.5 µm).
    """

    field_inner_deg: float
    field_outer_deg: float
    pupil_inner_m: float
    pupil_outer_m: float
    wavelengths_um: dict[str, float]


def load_optics_config(cfg_dir: str | Path | None = None) -> OpticsConfig:
    """Read ``configurations/lsst.yaml`` (field/pupil radii, band wavelengths)."""
    path = _dir(cfg_dir) / "configurations" / "lsst.yaml"
    raw = _load_yaml(str(path))
    try:
        return OpticsConfig(
            field_inner_deg=float(raw["field"]["radius_inner"]),
            field_outer_deg=float(raw["field"]["radius_outer"]),
            pupil_inner_m=float(raw["pupil"]["radius_inner"]),
            pupil_outer_m=float(raw["pupil"]["radius_outer"]),
            wavelengths_um={str(k): float(v) for k, v in raw["wavelengths"].items()},
        )
    except (KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: missing field/pupil/wavelengths entry ({exc})") from exc


def band_wavelength_um(band: str, cfg_dir: str | Path | None = None) -> float:
    """Wavelength (µm) that converts the intrinsic Zernikes of ``band`` from waves to µm.

    ts_ofc multiplies the intrinsic double Zernikes (stored in waves) by the band's effective
    wavelength. These are the wavelengths at which ts_ofc generated them with batoid and that
    ``configurations/lsst.yaml`` lists: u 0.365, g 0.480, r 0.622, i 0.754, z 0.869, y 0.971 µm,
    and 0.5 µm for the band-less reference file (``"ref"``). (ts_ofc's in-code default table
    has z 0.868 and y 0.973, a 0.1-0.2 % difference.)
    """
    waves = load_optics_config(cfg_dir).wavelengths_um
    if band not in BANDS or band not in waves:
        raise ConfigError(f"unknown band {band!r}; expected one of {BANDS}")
    return waves[band]


def corner_field_points_deg(
    sensors: Sequence[str] = CORNER_SENSORS, cfg_dir: str | Path | None = None
) -> np.ndarray:
    """Field points (deg) of the named sensors from ``sample_points/lsst_points.yaml``.

    Returns
    -------
    (n, 2) array of ``(field_x, field_y)`` in degrees. The default is the four extra-focal
    (SW0) corner halves, e.g. R00_SW0 = (-1.1903, -1.1903).
    """
    pts = _load_yaml(str(_dir(cfg_dir) / "sample_points" / "lsst_points.yaml"))
    try:
        return np.array([[float(v) for v in pts[s]] for s in sensors], dtype=np.float64)
    except KeyError as exc:
        raise ConfigError(f"unknown sensor {exc} in lsst_points.yaml") from exc


def corner_mid_field_points_deg(
    corners: Sequence[str] = CORNERS, sensors_yaml: str | Path | None = None
) -> np.ndarray:
    """Mid-points (deg) of the SW0/SW1 half-chips of the corner rafts.

    Read from ``config/sensors/lsst_corners.yaml`` (``mid_deg``, else the mean of the two
    half-chip field points). This is where the wavefront estimator reports its Zernikes and
    where the bundled sensitivity matrix is evaluated.

    Returns
    -------
    (n, 2) array of ``(field_x, field_y)`` in degrees, in the order of ``corners``.
    """
    geometry = load_sensor_geometry(sensors_yaml)
    missing = [c for c in corners if c not in geometry]
    if missing:
        raise ConfigError(f"{sensor_file(sensors_yaml)}: no field points for corner "
                          f"{', '.join(missing)}")
    return _as_fields(np.array([geometry[c].mid_field_deg for c in corners], dtype=np.float64))


def convert_dof_convention(values: np.ndarray | Sequence[float], from_convention: str,
                           to_convention: str, *, axis: int = -1) -> np.ndarray:
    """Express a DoF vector, or the DoF axis of a matrix, in another DoF convention.

    Parameters
    ----------
    values : (..., 50) DoF vector(s) or a (m, 50) sensitivity matrix (``axis=-1``).
    from_convention, to_convention : ``"batoid_rubin"`` or ``"ts_ofc"`` (see the module
        docstring). Between the two, entries :data:`TS_OFC_FLIPPED_DOF` change sign.
    axis : the axis of length 50.

    Returns
    -------
    A new float64 array (a copy even when the conventions are equal).
    """
    for c in (from_convention, to_convention):
        if c not in DOF_CONVENTIONS:
            raise ConfigError(f"unknown DoF convention {c!r}; expected one of {DOF_CONVENTIONS}")
    out = np.array(values, dtype=np.float64, copy=True)
    if out.shape[axis] != N_DOF:
        raise ConfigError(f"the DoF axis must have {N_DOF} entries, got shape {out.shape}")
    if from_convention != to_convention:
        idx = [slice(None)] * out.ndim
        idx[axis] = list(TS_OFC_FLIPPED_DOF)
        out[tuple(idx)] *= -1.0
        out += 0.0  # no -0.0
    return out


def load_normalization_weights(
    name: str = "range-fwhm", cfg_dir: str | Path | None = None
) -> np.ndarray:
    """ts_ofc's DoF normalisation weights ``w`` (50,), in DoF units per normalised unit.

    In ts_ofc (and here) the DoF vector is ``x = w * z``; the solver works in ``z``. For
    ``range-fwhm`` each ``w_i`` is the DoF's range times its field-averaged PSF-FWHM
    sensitivity, so a normalised unit of a DoF that is cheap (big range) and effective (big
    FWHM change) is large, and the minimum-norm solution prefers it.
    """
    folder = _dir(cfg_dir) / "normalization_weights"
    known = sorted(p.stem for p in folder.glob("*.yaml"))
    if name not in known:  # a name, never a path (the ofc_node parameter takes any string)
        raise ConfigError(f"unknown normalisation weights {name!r}: choose one of {known}")
    try:
        w = _yaml_array(folder / f"{name}.yaml", 1)
    except (TypeError, ValueError) as exc:  # not an array of numbers
        raise ConfigError(f"normalisation weights {name!r}: {exc}") from exc
    if w.shape != (N_DOF,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ConfigError(f"normalisation weights {name!r} must be 50 positive numbers")
    return w


@dataclass(frozen=True)
class DofSpec:
    """The 50 DoF: names, units, physical clip range and default per-visit step limit.

    Attributes
    ----------
    names, units : tuples of 50 strings (units ``um`` or ``deg``).
    range : (50,) symmetric clip limit of the accumulated state, ``|x_i| <= range_i``, DoF units.
    max_step : (50,) default largest ``|correction_i|`` per visit, DoF units.
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    range: np.ndarray
    max_step: np.ndarray

    def index(self, name: str) -> int:
        """Index of the DoF called ``name`` (e.g. ``"M2_dx"``, ``"M1M3_B3"``)."""
        try:
            return self.names.index(name)
        except ValueError as exc:
            raise ConfigError(f"unknown DoF name {name!r}") from exc


def load_dof_spec(path: str | Path | None = None) -> DofSpec:
    """Read ``config/ofc/dof.yaml`` (the single source of truth for the 50 DoF)."""
    p = Path(path) if path is not None else ofc_config_dir() / "dof.yaml"
    raw = _load_yaml(str(p))
    try:
        entries = sorted(raw["dofs"], key=lambda d: int(d["index"]))
        if [int(d["index"]) for d in entries] != list(range(N_DOF)):
            raise ConfigError(f"{p}: DoF indices must be exactly 0..49")
        spec = DofSpec(
            names=tuple(str(d["name"]) for d in entries),
            units=tuple(str(d["unit"]) for d in entries),
            range=np.array([float(d["range"]) for d in entries]),
            max_step=np.array([float(d["max_step"]) for d in entries]),
        )
    except (KeyError, TypeError) as exc:
        raise ConfigError(
            f"{p}: each DoF needs index, name, unit, range, max_step ({exc})"
        ) from exc
    if np.any(spec.range <= 0) or np.any(spec.max_step <= 0):
        raise ConfigError(f"{p}: range and max_step must be positive")
    return spec


# --------------------------------------------------------------------------------------------
# double-Zernike evaluation
# --------------------------------------------------------------------------------------------
def _as_fields(fields_deg: np.ndarray | Sequence[Sequence[float]] | None) -> np.ndarray:
    if fields_deg is None:
        return corner_field_points_deg()
    f = np.asarray(fields_deg, dtype=np.float64)
    if f.ndim == 1 and f.size == 2:
        f = f[None, :]
    if f.ndim != 2 or f.shape[1] != 2 or f.shape[0] < 1 or not np.all(np.isfinite(f)):
        raise ConfigError(f"field points must be a finite (n, 2) array in degrees, got {f.shape}")
    return f


def _eval_double_zernike(coef: np.ndarray, fields: np.ndarray, cfg: OpticsConfig) -> np.ndarray:
    """Pupil Zernikes Noll 4..22 of a (k, j) double-Zernike array at the field points."""
    dz = galsim.zernike.DoubleZernike(
        coef,
        uv_inner=cfg.field_inner_deg,
        uv_outer=cfg.field_outer_deg,
        xy_inner=cfg.pupil_inner_m,
        xy_outer=cfg.pupil_outer_m,
    )
    zks = dz(fields[:, 0], fields[:, 1])
    out = np.zeros((fields.shape[0], N_ZK))
    for i, zk in enumerate(zks):
        c = np.asarray(zk.coef)[NOLL_MIN : NOLL_MAX + 1]
        out[i, : c.size] = c
    return out


def intrinsic_zernikes_nm(
    band: str,
    fields_deg: np.ndarray | Sequence[Sequence[float]] | None = None,
    cfg_dir: str | Path | None = None,
) -> np.ndarray:
    """Design (intrinsic) wavefront of the nominal telescope, Noll 4..22, in nm.

    Parameters
    ----------
    band : ``u g r i z y`` or ``"ref"`` (the band-less 0.5 µm file).
    fields_deg : (n, 2) field points in degrees; default the four SW0 corners.

    Returns
    -------
    (n, 19) array in nm: the ts_ofc intrinsic double Zernikes (waves) evaluated with galsim
    and multiplied by :func:`band_wavelength_um` x 1000. Wavefront sign (as measured).
    """
    cfg = load_optics_config(cfg_dir)
    wl_um = band_wavelength_um(band, cfg_dir)
    tag = "" if band == "ref" else band
    path = _dir(cfg_dir) / _INTRINSIC_DIR / f"intrinsic_zk_{tag}_31_29.yaml"
    coef = _yaml_array(path, 2)
    return _eval_double_zernike(coef, _as_fields(fields_deg), cfg) * wl_um * _UM_TO_NM


def intrinsic_vector_nm(
    band: str,
    fields_deg: np.ndarray | Sequence[Sequence[float]] | None = None,
    cfg_dir: str | Path | None = None,
) -> np.ndarray:
    """:func:`intrinsic_zernikes_nm` flattened to the measurement layout (19 * n,), nm."""
    return intrinsic_zernikes_nm(band, fields_deg, cfg_dir).reshape(-1)


@dataclass(frozen=True)
class SensitivityMatrix:
    """Wavefront sensitivity ``A``: ``wavefront_change_nm = A @ dof_change``.

    Attributes
    ----------
    matrix_nm : (19 * n_fields, 50) nm of wavefront per DoF unit, row ``19 * f + (j - 4)``.
    field_points_deg : (n_fields, 2) field points in degrees, or ``None`` if unknown.
    source : where it came from (``"ts_ofc"``, ``"bundled"``, ``"npy:<path>"``).
    """

    matrix_nm: np.ndarray
    field_points_deg: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix_nm, dtype=np.float64)
        if m.ndim != 2 or m.shape[1] != N_DOF or m.shape[0] == 0 or m.shape[0] % N_ZK:
            raise ConfigError(
                f"sensitivity matrix must be (19 * n_fields, {N_DOF}), got {m.shape}"
            )
        if not np.all(np.isfinite(m)) or not np.any(m):
            raise ConfigError("sensitivity matrix must be finite and not all zero")
        m = m.copy()
        m.setflags(write=False)
        object.__setattr__(self, "matrix_nm", m)
        if self.field_points_deg is not None:
            fp = _as_fields(self.field_points_deg).copy()
            if fp.shape[0] != self.n_fields:
                raise ConfigError(f"{fp.shape[0]} field points for {self.n_fields} fields")
            fp.setflags(write=False)
            object.__setattr__(self, "field_points_deg", fp)

    @property
    def n_fields(self) -> int:
        """Number of field points (corners): rows / 19."""
        return self.matrix_nm.shape[0] // N_ZK

    def rows_for(self, field_valid: Sequence[bool] | np.ndarray) -> np.ndarray:
        """Boolean row mask (19 * n_fields,) selecting the rows of the valid fields."""
        v = np.asarray(field_valid, dtype=bool).reshape(-1)
        if v.shape != (self.n_fields,):
            raise ConfigError(f"field mask must have {self.n_fields} entries, got {v.size}")
        return np.repeat(v, N_ZK)

    @classmethod
    def from_ts_ofc(
        cls,
        fields_deg: np.ndarray | Sequence[Sequence[float]] | None = None,
        cfg_dir: str | Path | None = None,
        matrix_path: str | Path | None = None,
        dof_convention: str = "batoid_rubin",
    ) -> SensitivityMatrix:
        """Evaluate ts_ofc's double-Zernike sensitivity yaml at field points.

        Parameters
        ----------
        fields_deg : (n, 2) field points in degrees; default the four SW0 corners.
        cfg_dir : OFC config directory (default ``config/ofc``).
        matrix_path : the (31 field x 29 pupil x 50 DoF) yaml, default ts_ofc's r-band one.
        dof_convention : DoF convention of the result. ``"batoid_rubin"`` (default, the
            convention of ``DofCorrection`` and of the simulator) negates the columns
            :data:`TS_OFC_FLIPPED_DOF`; ``"ts_ofc"`` keeps ts_ofc's own columns (the plain
            batoid frame). See the module docstring.

        The yaml is in µm per DoF unit in ts_ofc's correction convention; the result is
        converted to this module's wavefront convention in nm (``A = -1000 * S``). ts_ofc uses
        the r-band matrix for every band; so does this.
        """
        cfg = load_optics_config(cfg_dir)
        path = Path(matrix_path) if matrix_path is not None else _dir(cfg_dir) / _TS_OFC_MATRIX
        dz = _yaml_array(path, 3)
        if dz.shape[2] != N_DOF or dz.shape[1] <= NOLL_MAX:
            raise ConfigError(f"{path}: expected (k, j>22, 50) double Zernikes, got {dz.shape}")
        fields = _as_fields(fields_deg)
        out = np.empty((fields.shape[0], N_ZK, N_DOF))
        for d in range(N_DOF):
            out[:, :, d] = _eval_double_zernike(dz[:, :, d], fields, cfg)
        matrix = -_UM_TO_NM * out.reshape(-1, N_DOF)
        matrix = convert_dof_convention(matrix, "ts_ofc", dof_convention)
        return cls(matrix, fields, "ts_ofc")

    @classmethod
    def from_npy(
        cls,
        path: str | Path,
        *,
        units: str = "nm",
        convention: str = "wavefront",
        fields_deg: np.ndarray | Sequence[Sequence[float]] | None = None,
        n_fields: int | None = None,
        dof_convention: str = "batoid_rubin",
    ) -> SensitivityMatrix:
        """Load a ``(19 * n_fields, 50)`` matrix from an ``.npy`` file.

        Parameters
        ----------
        units : ``"nm"`` or ``"um"`` of wavefront per DoF unit.
        convention : ``"wavefront"`` (this module's) or ``"ts_ofc"`` (negated, correction).
        fields_deg : optional field points to attach.
        n_fields : if given, the number of field points the file must hold.
        dof_convention : DoF convention the *file* is in (``"batoid_rubin"`` or ``"ts_ofc"``);
            the result is always converted to ``"batoid_rubin"``.
        """
        scale = {"nm": 1.0, "um": _UM_TO_NM}.get(units)
        sign = {"wavefront": 1.0, "ts_ofc": -1.0}.get(convention)
        if scale is None or sign is None:
            raise ConfigError(f"units must be nm|um and convention wavefront|ts_ofc, got "
                              f"{units!r}, {convention!r}")
        try:
            m = np.load(Path(path), allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot read sensitivity matrix {path}: {exc}") from exc
        if n_fields is not None and m.shape != (N_ZK * n_fields, N_DOF):
            raise ConfigError(f"{path}: expected shape ({N_ZK * n_fields}, {N_DOF}), "
                              f"got {m.shape}")
        fp = None if fields_deg is None else _as_fields(fields_deg)
        if m.ndim != 2 or m.shape[1] != N_DOF:
            raise ConfigError(f"{path}: expected shape (19 * n_fields, {N_DOF}), got {m.shape}")
        m = convert_dof_convention(m, dof_convention, "batoid_rubin")
        return cls(sign * scale * np.asarray(m, dtype=np.float64), fp, f"npy:{path}")

    @classmethod
    def from_bundled(
        cls, path: str | Path | None = None, cfg_dir: str | Path | None = None
    ) -> SensitivityMatrix:
        """Load the project's own matrix (``config/ofc/sensitivity_bundled_r.npy``).

        The file must be (76, 50), nm of wavefront per DoF unit in this module's wavefront
        sign and the batoid_rubin DoF convention, rows for the four corner mid-points
        (:func:`corner_mid_field_points_deg`) in :data:`CORNERS` order. It is made by
        ``tools/make_sensitivity.py`` from the simulator (see ``config/ofc/PROVENANCE.md``).
        """
        p = Path(path) if path is not None else _dir(cfg_dir) / BUNDLED_MATRIX_FILENAME
        sm = cls.from_npy(p, units="nm", convention="wavefront", n_fields=N_CORNERS,
                          fields_deg=corner_mid_field_points_deg())
        return cls(sm.matrix_nm, sm.field_points_deg, "bundled")

    @classmethod
    def load(cls, source: str = "ts_ofc", **kwargs: object) -> SensitivityMatrix:
        """``"ts_ofc"`` -> :meth:`from_ts_ofc`, ``"bundled"`` -> :meth:`from_bundled`.

        Both come back in the batoid_rubin DoF convention and wavefront sign.
        """
        if source == "ts_ofc":
            return cls.from_ts_ofc(**kwargs)  # type: ignore[arg-type]
        if source == "bundled":
            return cls.from_bundled(**kwargs)  # type: ignore[arg-type]
        raise ConfigError(f"unknown sensitivity source {source!r} (ts_ofc | bundled)")


# --------------------------------------------------------------------------------------------
# normalised pseudo-inverse
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Inverse:
    """Filtered SVD inverse of ``A_rows[:, dof] * w`` for one row/DoF selection."""

    u: np.ndarray  # (m, r)
    s: np.ndarray  # (r,)
    vt: np.ndarray  # (r, n)
    filt: np.ndarray  # (r,) 1/s for kept modes (tsvd) or s/(s^2+lam^2) (tikhonov), 0 otherwise
    n_modes: int
    condition: float  # largest singular value x largest filter gain (1 = perfect)


def _build_inverse(an: np.ndarray, method: str, n_modes: int, alpha: float) -> _Inverse:
    u, s, vt = np.linalg.svd(an, full_matrices=False)
    s0 = float(s[0]) if s.size else 0.0
    nonzero = s > _RANK_RTOL * s0 if s0 > 0 else np.zeros_like(s, dtype=bool)
    filt = np.zeros_like(s)
    if method == "tsvd":
        k = int(min(n_modes, int(nonzero.sum())))
        filt[:k] = 1.0 / s[:k]
        n_used = k
    else:  # tikhonov; alpha is relative to the largest singular value
        lam = alpha * s0
        filt[nonzero] = s[nonzero] / (s[nonzero] ** 2 + lam**2)
        n_used = int(np.sum(s > lam))
    cond = s0 * float(filt.max()) if n_used > 0 else np.inf
    return _Inverse(u, s, vt, filt, n_used, cond)


def _resolve_weights(weights: str | np.ndarray | Sequence[float], spec: DofSpec) -> np.ndarray:
    if isinstance(weights, str):
        if weights == "range":
            return spec.range.copy()
        if weights == "none":
            return np.ones(N_DOF)
        return load_normalization_weights(weights)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (N_DOF,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ConfigError("weights must be 50 positive finite numbers")
    return w


def _resolve_limit(
    value: str | float | np.ndarray | Sequence[float] | None, default: np.ndarray, what: str
) -> np.ndarray | None:
    if value is None:
        return None
    if isinstance(value, str):
        if value != "dof.yaml":
            raise ConfigError(f"{what}: use 'dof.yaml', None, a number or 50 numbers")
        return default.copy()
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (N_DOF,)).copy()
    if np.any(np.isnan(arr)) or np.any(arr < 0):
        raise ConfigError(f"{what} must be >= 0")
    return arr


# --------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CheckedVisit:
    """A visit's measurement that passed :meth:`OFCSolver.check_visit`."""

    y: np.ndarray  # (19 * n_fields,) total measured wavefront, nm
    corner_valid: np.ndarray  # (n_fields,) bools
    rows: np.ndarray  # (19 * n_fields,) bools: the rows of the corners used


@dataclass(frozen=True)
class Refusal(Problem):
    """Why a visit is refused (:class:`~cwfs_ros.errors.Problem`) and the corner flags seen."""

    corners: tuple[bool, ...] = ()


@dataclass(frozen=True)
class Estimate:
    """Gain-1 estimate of the optical-state error from one visit (no controller state).

    Attributes
    ----------
    dof_error : (50,) estimated DoF state error, DoF units (zeros when not valid).
    valid, status, reason : ``reason`` is ``"ok"`` or the refusal's tag, ``status`` the text
        for people, ``"ok"`` or ``"<tag>: <explanation>"``; tags are
        ``bad_shape``, ``non_finite``, ``corner_invalid``, ``no_valid_corners``,
        ``implausible_wavefront``, ``ill_conditioned``; :meth:`OFCSolver.step` adds
        ``no_stamp``, ``stale_visit``, ``future_stamp`` and ``non_finite_result``.
    wavefront_nm : (19 * n_fields,) measured minus intrinsic, NaN on dropped corners.
    wavefront_rms_nm : corner-averaged RMS wavefront of ``wavefront_nm``:
        ``sqrt(sum(r**2) / n_corners_used)`` (Zernikes have unit RMS, so this is the RMS of the
        Noll 4-22 wavefront over the pupil, averaged in quadrature over the corners).
    fit_residual_rms_nm : same RMS of ``r - A @ dof_error`` (what the kept modes cannot explain).
    n_modes_used : SVD modes kept (tsvd) or with ``s > alpha * s_max`` (tikhonov).
    condition : effective condition number of the inverse actually applied.
    corners_used : per-corner flags of the rows used.
    """

    dof_error: np.ndarray
    valid: bool
    status: str
    wavefront_nm: np.ndarray
    wavefront_rms_nm: float
    fit_residual_rms_nm: float
    n_modes_used: int
    condition: float
    corners_used: tuple[bool, ...]
    reason: str = "ok"


@dataclass(frozen=True)
class OFCResult:
    """What one controller step returns.

    Attributes
    ----------
    dof : (50,) correction to ADD to the telescope this visit, DoF units (zeros if not valid).
    dof_total : (50,) accumulated commanded state after adding ``dof``.
    valid, status : see :class:`Estimate`.
    wavefront_rms_nm : measured wavefront RMS with the intrinsic removed, nm (see Estimate).
    predicted_residual_rms_nm : RMS (same definition) of ``r + A @ dof``: the wavefront
        predicted after this visit's correction is applied.
    n_modes_used : SVD modes used by the estimate.
    dof_error : (50,) the estimate ``e`` the controller acted on.
    clipped : (50,) True where the step limit or the range clip changed the correction.
    condition : effective condition number of the inverse.
    corners_used : per-corner flags of the rows used.
    elapsed_s : wall time of the step.
    dof_uncertainty : (50,) 1-sigma of the estimated state after this visit (Kalman
        controller; zeros from the PI controller, which does not estimate it).
    field_rms_nm, predicted_field_rms_nm : estimated wavefront error averaged over the science
        field (Gaussian-quadrature points, design removed) before and after ``dof`` [nm];
        NaN from the PI controller.
    rotator_angle_deg : camera rotator angle the visit was solved at.
    dropped, n_dropped : the state directions too weakly observed to be corrected.
    reason : ``"ok"`` or the refusal's tag (:class:`Estimate`), as data: never parsed from
        ``status``.
    """

    dof: np.ndarray
    dof_total: np.ndarray
    valid: bool
    status: str
    wavefront_rms_nm: float
    predicted_residual_rms_nm: float
    n_modes_used: int
    dof_error: np.ndarray = field(default_factory=lambda: np.zeros(N_DOF))
    clipped: np.ndarray = field(default_factory=lambda: np.zeros(N_DOF, dtype=bool))
    condition: float = float("nan")
    corners_used: tuple[bool, ...] = ()
    elapsed_s: float = 0.0
    dof_uncertainty: np.ndarray = field(default_factory=lambda: np.zeros(N_DOF))
    field_rms_nm: float = float("nan")
    predicted_field_rms_nm: float = float("nan")
    rotator_angle_deg: float = 0.0
    dropped: str = ""
    n_dropped: int = 0
    reason: str = "ok"


def _rms(r: np.ndarray, n_corners: int) -> float:
    with np.errstate(over="ignore"):  # inf for absurd input, which is refused anyway
        return float(np.sqrt(np.sum(r**2) / n_corners)) if n_corners > 0 else float("nan")


# --------------------------------------------------------------------------------------------
# solver / controller
# --------------------------------------------------------------------------------------------
class OFCSolver:
    """Per-visit state estimator + PI controller for the 50 DoF.

    Parameters
    ----------
    sensitivity : the wavefront sensitivity; default ``SensitivityMatrix.from_ts_ofc()``
        at the four SW0 corners.
    band : band of the intrinsic wavefront to subtract (``u g r i z y ref``).
    intrinsic_nm : explicit intrinsic vector (19 * n_fields,), nm; overrides ``band``.
    method : ``"tsvd"`` (keep ``n_modes`` largest modes) or ``"tikhonov"``.
    n_modes : modes kept by the truncated SVD (ts_ofc uses 12).
    alpha : Tikhonov regulariser as a fraction of the largest normalised singular value.
    weights : DoF normalisation ``x = w * z``: ``"range-fwhm"`` (ts_ofc), ``"range"``
        (dof.yaml ranges), ``"none"`` or 50 numbers.
    kp, ki : proportional and integral gains (ts_ofc OIC: 0.18, 0.022). ``ki = 0`` gives a
        pure proportional step.
    dof_mask : 50 bools; False DoFs are excluded from the solve and never move.
    clip_range : ``"dof.yaml"`` (default), None (no clip), a number or 50 numbers (DoF units):
        the accumulated state is kept within ``±clip_range``.
    max_step : ``"dof.yaml"`` (default), None, a number or 50 numbers: per-visit step limit.
    max_integral : None or 50 numbers: clip of ``sum(e)`` (DoF units), as ts_ofc's
        ``max_integral``. Independently, a DoF whose correction is cut by the step limit or
        the range clip does not integrate that visit (conditional-integration anti-windup).
    allow_partial : if True, invalid corners' rows are dropped instead of refusing the visit.
    max_condition : refuse when the effective condition number of the (normalised) inverse
        exceeds this.
    max_abs_zernike_nm : refuse a visit whose used corners hold a Zernike term beyond this
        (nm; None: no limit). Finite but absurd values (a corrupted or misconfigured
        producer) would otherwise overflow the solve into a NaN state, or command the full
        step limit from a wavefront no estimator can measure.
    max_future_s : with ``step(..., stamp_ns=, now_ns=)``, refuse a visit stamped more than
        this ahead of ``now_ns`` (None: no limit): applied, it would make every later visit
        look stale (see :meth:`step`).
    dof_spec : DoF table (default ``config/ofc/dof.yaml``).
    """

    def __init__(
        self,
        sensitivity: SensitivityMatrix | None = None,
        *,
        band: str = "r",
        intrinsic_nm: np.ndarray | Sequence[float] | None = None,
        method: str = "tsvd",
        n_modes: int = 12,
        alpha: float = 1e-3,
        weights: str | np.ndarray | Sequence[float] = "range-fwhm",
        kp: float = 0.18,
        ki: float = 0.022,
        dof_mask: np.ndarray | Sequence[bool] | None = None,
        clip_range: str | float | np.ndarray | Sequence[float] | None = "dof.yaml",
        max_step: str | float | np.ndarray | Sequence[float] | None = "dof.yaml",
        max_integral: np.ndarray | Sequence[float] | None = None,
        allow_partial: bool = False,
        max_condition: float = 1e6,
        max_abs_zernike_nm: float | None = None,
        max_future_s: float | None = None,
        dof_spec: DofSpec | None = None,
    ) -> None:
        self.sensitivity = sensitivity if sensitivity is not None else (
            SensitivityMatrix.from_ts_ofc()
        )
        self.n_fields = self.sensitivity.n_fields
        self._set_solve(method, n_modes, alpha, kp, ki)
        self.allow_partial = bool(allow_partial)
        self.max_condition = float(max_condition)
        for name, v in (("max_abs_zernike_nm", max_abs_zernike_nm),
                        ("max_future_s", max_future_s)):
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ConfigError(f"{name} must be a positive number or None, got {v!r}")
        self.max_abs_zernike_nm = None if max_abs_zernike_nm is None else float(
            max_abs_zernike_nm)
        self.max_future_s = None if max_future_s is None else float(max_future_s)
        self.spec = dof_spec if dof_spec is not None else load_dof_spec()
        self.weights = _resolve_weights(weights, self.spec)
        self._set_dof_limits(dof_mask, clip_range, max_step, max_integral)
        self._set_intrinsic(band, intrinsic_nm)
        self._inverse_cache: dict[bytes, _Inverse] = {}
        self.dof_total = np.zeros(N_DOF)
        self.integral = np.zeros(N_DOF)
        self.n_steps = 0
        # Stamp (ns) of the last visit applied through step(stamp_ns=...); None before one.
        self.last_stamp_ns: int | None = None

    def _set_solve(self, method: str, n_modes: int, alpha: float, kp: float,
                   ki: float) -> None:
        """Check and keep the inverse's and the PI law's settings (a bad one raises here,
        not at the first visit)."""
        if method not in ("tsvd", "tikhonov"):
            raise ConfigError(f"method must be 'tsvd' or 'tikhonov', got {method!r}")
        if int(n_modes) < 1:
            raise ConfigError("n_modes must be >= 1")
        if not alpha > 0 and method == "tikhonov":
            raise ConfigError("alpha must be > 0 for tikhonov")
        if not (np.isfinite(kp) and np.isfinite(ki)) or kp < 0 or ki < 0:
            raise ConfigError("kp and ki must be finite and >= 0")
        self.method = method
        self.n_modes = int(n_modes)
        self.alpha = float(alpha)
        self.kp = float(kp)
        self.ki = float(ki)

    def _set_dof_limits(
        self,
        dof_mask: np.ndarray | Sequence[bool] | None,
        clip_range: str | float | np.ndarray | Sequence[float] | None,
        max_step: str | float | np.ndarray | Sequence[float] | None,
        max_integral: np.ndarray | Sequence[float] | None,
    ) -> None:
        """Resolve which DoFs move and how far (``self.spec`` must be set): a mask that
        excludes every DoF would make every visit a no-op, so it is refused."""
        mask = np.ones(N_DOF, dtype=bool) if dof_mask is None else np.asarray(dof_mask, bool)
        if mask.shape != (N_DOF,):
            raise ConfigError(f"dof_mask must have {N_DOF} entries, got {mask.size}")
        if not mask.any():
            raise ConfigError("dof_mask excludes every DoF")
        self.dof_mask = mask.copy()
        self.clip_range = _resolve_limit(clip_range, self.spec.range, "clip_range")
        self.max_step = _resolve_limit(max_step, self.spec.max_step, "max_step")
        self.max_integral = _resolve_limit(max_integral, np.full(N_DOF, np.inf), "max_integral")

    def _set_intrinsic(self, band: str,
                       intrinsic_nm: np.ndarray | Sequence[float] | None) -> None:
        """The intrinsic wavefront to subtract: an explicit vector, or the band's at the
        sensitivity's field points (``self.band`` is None for an explicit vector)."""
        n_rows = self.sensitivity.matrix_nm.shape[0]
        if intrinsic_nm is not None:
            intr = np.asarray(intrinsic_nm, dtype=np.float64).reshape(-1)
            if intr.shape != (n_rows,) or not np.all(np.isfinite(intr)):
                raise ConfigError(f"intrinsic_nm must be {n_rows} finite numbers")
        else:
            if self.sensitivity.field_points_deg is None:
                raise ConfigError("sensitivity has no field points: pass intrinsic_nm")
            intr = intrinsic_vector_nm(band, self.sensitivity.field_points_deg)
        self.intrinsic_nm = intr
        self.band = band if intrinsic_nm is None else None

    # ---------------------------------------------------------------- state
    def set_band(self, band: str) -> None:
        """Subtract the intrinsic wavefront of another band from now on (``u g r i z y ref``).

        The sensitivity matrix is kept: ts_ofc uses its r-band matrix for every band.
        """
        if self.sensitivity.field_points_deg is None:
            raise ConfigError("sensitivity has no field points: set intrinsic_nm instead")
        self.intrinsic_nm = intrinsic_vector_nm(band, self.sensitivity.field_points_deg)
        self.band = band

    def reset(self) -> None:
        """Forget the accumulated state and the integral (e.g. after the telescope is reset)."""
        self.dof_total = np.zeros(N_DOF)
        self.integral = np.zeros(N_DOF)
        self.n_steps = 0
        self.last_stamp_ns = None

    def state(self) -> tuple:
        """The controller state (accumulated DoFs, integral, steps, last visit stamp, and the
        ``ki`` the integral was accumulated with), to carry over into a rebuilt solver with
        :meth:`restore`."""
        return (self.dof_total.copy(), self.integral.copy(), self.n_steps, self.last_stamp_ns,
                self.ki)

    def restore(self, state: tuple) -> None:
        """Put back a :meth:`state`, bumpless across a change of ``ki``.

        The integral's contribution to a correction is ``ki * integral``; a solver rebuilt with
        another ``ki`` rescales the integral so that the contribution stays what it was, rather
        than jumping with the gain. With ``ki = 0`` there is no integral action, and the
        integral restarts from zero when it is turned on again.
        """
        dof_total, integral, self.n_steps, self.last_stamp_ns, ki = state
        self.dof_total = dof_total.copy()
        if self.ki == 0 or ki == 0:
            self.integral = np.zeros(N_DOF)
        else:
            self.integral = integral * (ki / self.ki)
            if self.max_integral is not None:
                self.integral = np.clip(self.integral, -self.max_integral, self.max_integral)

    def _inverse(self, rows: np.ndarray) -> _Inverse:
        key = np.packbits(rows).tobytes()
        inv = self._inverse_cache.get(key)
        if inv is None:
            an = self.sensitivity.matrix_nm[np.ix_(rows, self.dof_mask)]
            an = an * self.weights[self.dof_mask][None, :]
            inv = _build_inverse(an, self.method, self.n_modes, self.alpha)
            self._inverse_cache[key] = inv
        return inv

    # ---------------------------------------------------------------- estimate
    def check_visit(
        self,
        measured_nm: np.ndarray | Sequence[float],
        corner_valid: np.ndarray | Sequence[bool] | None = None,
        intrinsic_nm: np.ndarray | None = None,
    ) -> CheckedVisit | Refusal:
        """The input checks every controller applies before it solves anything.

        Shape, corner validity (``allow_partial``), finiteness, ``max_abs_zernike_nm`` and
        unfilled corners, against ``intrinsic_nm`` (default this solver's). Returns the
        flattened measurement with its corner and row masks, or the refusal.
        """
        intrinsic = self.intrinsic_nm if intrinsic_nm is None else intrinsic_nm
        parsed = self._parse_visit(measured_nm, corner_valid)
        if isinstance(parsed, Refusal):
            return parsed
        y, cv = parsed
        corners = tuple(bool(c) for c in cv)
        names = self._corner_names()
        if not cv.all() and not self.allow_partial:
            bad = ", ".join(n for n, ok in zip(names, cv, strict=True) if not ok)
            return Refusal("corner_invalid", f"{bad} flagged invalid and allow_partial is False",
                           corners)
        if not cv.any():
            return Refusal("no_valid_corners", "every corner is flagged invalid", corners)
        rows = self.sensitivity.rows_for(cv)
        bad_rows = rows & ~np.isfinite(y)
        if bad_rows.any():
            bad_c = sorted({names[i // N_ZK] for i in np.flatnonzero(bad_rows)})
            return Refusal("non_finite", f"NaN/inf in the wavefront of {', '.join(bad_c)} "
                           f"({int(bad_rows.sum())} values)", corners)
        problem = self._implausible(y, cv, rows, intrinsic)
        if problem is not None:
            return Refusal(problem.reason, problem.message, corners)
        return CheckedVisit(y, cv, rows)

    def _parse_visit(
        self,
        measured_nm: np.ndarray | Sequence[float],
        corner_valid: np.ndarray | Sequence[bool] | None,
    ) -> tuple[np.ndarray, np.ndarray] | Refusal:
        """The flattened measurement and the corner flags, or a ``bad_shape`` refusal: a
        message of the wrong size must be refused, not broadcast into the solve."""
        nf = self.n_fields
        n_rows = nf * N_ZK
        try:
            y = np.asarray(measured_nm, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            return Refusal("bad_shape", f"measured_nm is not a numeric array ({exc})")
        if y.size != n_rows or y.ndim not in (1, 2) or (y.ndim == 2 and y.shape != (nf, N_ZK)):
            return Refusal("bad_shape", f"expected {n_rows} values ({nf} corners x {N_ZK} "
                           f"Zernikes Z4..Z22), got shape {y.shape}")
        if corner_valid is None:
            return y.reshape(-1), np.ones(nf, dtype=bool)
        cv_raw = np.asarray(corner_valid)
        if cv_raw.size != nf:
            return Refusal("bad_shape", f"corner_valid must have {nf} entries, "
                           f"got shape {cv_raw.shape}")
        return y.reshape(-1), cv_raw.reshape(-1).astype(bool)

    def _implausible(self, y: np.ndarray, cv: np.ndarray, rows: np.ndarray,
                     intrinsic: np.ndarray) -> Problem | None:
        """Why finite values of the used corners are still no measurement, or None."""
        names = self._corner_names()
        if self.max_abs_zernike_nm is not None:
            big = rows & (np.abs(y) > self.max_abs_zernike_nm)
            if big.any():
                big_c = sorted({names[i // N_ZK] for i in np.flatnonzero(big)})
                return Problem("implausible_wavefront", f"|Z| up to {np.abs(y[big]).max():.4g} "
                               f"nm in {', '.join(big_c)}, beyond max_abs_zernike_nm "
                               f"{self.max_abs_zernike_nm:g}")
        # A measured total wavefront holds the design's (tens to hundreds of nm at the
        # corners): a valid-flagged corner of exact zeros is an unfilled field, not a
        # measurement, and solving it would correct a perfect telescope by minus its design.
        blank = [names[k] for k in range(self.n_fields)
                 if cv[k] and not np.any(y[k * N_ZK:(k + 1) * N_ZK])
                 and np.any(intrinsic[k * N_ZK:(k + 1) * N_ZK])]
        if blank:
            return Problem("implausible_wavefront", f"{', '.join(blank)} flagged valid but all "
                           f"{N_ZK} terms are exactly 0 (an unfilled corner: a measurement "
                           "holds the design wavefront)")
        return None

    def estimate(
        self,
        measured_nm: np.ndarray | Sequence[float],
        corner_valid: np.ndarray | Sequence[bool] | None = None,
    ) -> Estimate:
        """Gain-1 state-error estimate ``e = A⁺ (y - y_intrinsic)`` (leaves the state alone).

        Parameters
        ----------
        measured_nm : (19 * n_fields,) or (n_fields, 19) total measured wavefront, nm.
        corner_valid : (n_fields,) bools; default all True.
        """
        nf = self.n_fields
        nan_vec = np.full(nf * N_ZK, np.nan)
        checked = self.check_visit(measured_nm, corner_valid)
        if isinstance(checked, Refusal):
            return Estimate(np.zeros(N_DOF), False, checked.status, nan_vec, float("nan"),
                            float("nan"), 0, float("nan"), checked.corners, checked.reason)
        y, cv, rows = checked.y, checked.corner_valid, checked.rows
        corners = tuple(bool(c) for c in cv)

        def refuse(problem: Problem, r: np.ndarray, rms: float) -> Estimate:
            return Estimate(np.zeros(N_DOF), False, problem.status, r, rms, float("nan"), 0,
                            float("nan"), corners, problem.reason)

        r_full = np.where(rows, y - self.intrinsic_nm, np.nan)
        r = r_full[rows]
        n_used = int(cv.sum())
        rms = _rms(r, n_used)
        inv = self._inverse(rows)
        if inv.n_modes == 0 or not inv.condition <= self.max_condition:
            return refuse(Problem("ill_conditioned", f"effective condition number "
                                  f"{inv.condition:.3g} > max_condition "
                                  f"{self.max_condition:.3g} ({self.method}, {n_used} corners)"),
                          r_full, rms)
        # Overflow (values near the float64 maximum, with no plausibility limit set) gives
        # NaN/inf here, which step() refuses as non_finite_result: no warning needed.
        with np.errstate(over="ignore", invalid="ignore"):
            z = inv.vt.T @ (inv.filt * (inv.u.T @ r))
            e = np.zeros(N_DOF)
            e[self.dof_mask] = self.weights[self.dof_mask] * z
            fit_res = r - self.sensitivity.matrix_nm[rows] @ e
        return Estimate(e, True, "ok", r_full, rms, _rms(fit_res, n_used), inv.n_modes,
                        inv.condition, corners)

    def _corner_names(self) -> list[str]:
        if self.n_fields == N_CORNERS:
            return list(CORNERS)  # raft names: valid for SW0 and mid-point rows
        return [f"field{i}" for i in range(self.n_fields)]

    # ---------------------------------------------------------------- control step
    def visit_stamp_problem(self, stamp_ns: int | None, now_ns: int | None) -> Problem | None:
        """Why a visit of this stamp must not be applied, or None."""
        if stamp_ns is None:
            return None
        if stamp_ns <= 0:
            return Problem("no_stamp", "the visit's header.stamp is unset (0)" if stamp_ns == 0
                           else f"the visit's header.stamp is {stamp_ns} ns, before 1970")
        if self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns:
            what = "again" if stamp_ns == self.last_stamp_ns else "older than the last one"
            hint = ""
            if self.last_stamp_ns - stamp_ns > CLOCK_RESET_S * 1e9:
                # Deliberately not followed automatically (wavefront_node does restart its
                # visit history): a correction must not come from visits whose time went
                # backwards, an old bag played into the graph say, without an operator.
                hint = (f"; {(self.last_stamp_ns - stamp_ns) / 1e9:.0f} s back: if the "
                        "camera's clock was reset, reset the controller (ofc_node ~/reset)")
            return Problem("stale_visit", f"visit {stamp_ns} ns is {what} applied "
                           f"({self.last_stamp_ns} ns): not applied twice or out of order{hint}")
        if self.max_future_s is not None and now_ns is not None and now_ns > 0 and \
                stamp_ns > now_ns + self.max_future_s * 1e9:
            return Problem("future_stamp", f"visit {stamp_ns} ns is "
                           f"{(stamp_ns - now_ns) / 1e9:.4g} s ahead of the clock "
                           f"(max_future_s {self.max_future_s:g})")
        return None

    def step(
        self,
        measured_nm: np.ndarray | Sequence[float],
        corner_valid: np.ndarray | Sequence[bool] | None = None,
        *,
        stamp_ns: int | None = None,
        now_ns: int | None = None,
        dry_run: bool = False,
    ) -> OFCResult:
        """One visit: estimate, PI control law, step limit, range clip, accumulate.

        Parameters
        ----------
        measured_nm : (19 * n_fields,) or (n_fields, 19) total measured wavefront in nm
            (intrinsic included; it is subtracted here).
        corner_valid : (n_fields,) bools; default all True.
        stamp_ns : the visit's stamp. Given, a visit is refused when its stamp is unset (0),
            not newer than the last visit applied (a repeated or reordered message would
            otherwise be integrated twice, or an old correction applied after a newer
            one), or more than ``max_future_s`` ahead of ``now_ns`` (the clock's time, ns).
            :meth:`reset` forgets the last stamp.
        dry_run : compute the correction as usual but leave the state (accumulated DoFs,
            integral, step count, last stamp) as it was: the correction is not applied.

        Returns
        -------
        OFCResult. When not valid, ``dof`` is zero and neither the state nor the integral
        changes.
        """
        t0 = time.perf_counter()
        problem = self.visit_stamp_problem(stamp_ns, now_ns)
        est = (self.estimate(measured_nm, corner_valid) if problem is None else
               Estimate(np.zeros(N_DOF), False, problem.status,
                        np.full(self.n_fields * N_ZK, np.nan), float("nan"), float("nan"), 0,
                        float("nan"), (), problem.reason))
        if not est.valid:
            return self._unchanged(est, est.status, est.reason, t0)
        e = est.dof_error
        u, total, integral, clipped = self._control_law(e)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(total))
                and np.all(np.isfinite(integral))):
            # Never reached from finite, plausible input; kept so that no arithmetic accident
            # can leave a NaN in the state, which every later visit would inherit.
            return self._unchanged(
                est, "non_finite_result: the solve gave NaN/inf DoFs; state unchanged",
                "non_finite_result", t0)
        if not dry_run:
            self.integral = integral
            self.dof_total = total
            self.n_steps += 1
            if stamp_ns is not None:
                self.last_stamp_ns = int(stamp_ns)
        rows = self.sensitivity.rows_for(est.corners_used)
        r = est.wavefront_nm[rows]
        pred = r + self.sensitivity.matrix_nm[rows] @ u
        n_used = int(sum(est.corners_used))
        return OFCResult(u.copy(), total.copy(), True, "ok", est.wavefront_rms_nm,
                         _rms(pred, n_used), est.n_modes_used, e, clipped, est.condition,
                         est.corners_used, time.perf_counter() - t0)

    def _unchanged(self, est: Estimate, status: str, reason: str, t0: float) -> OFCResult:
        """The result of a visit not applied: zero correction, the state as it was."""
        return OFCResult(np.zeros(N_DOF), self.dof_total.copy(), False, status,
                         est.wavefront_rms_nm, float("nan"), est.n_modes_used, est.dof_error,
                         np.zeros(N_DOF, dtype=bool), est.condition, est.corners_used,
                         time.perf_counter() - t0, reason=reason)

    def _control_law(
        self, e: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """PI law, step limit, range clip and anti-windup for the state error ``e``.

        Returns the correction, the new accumulated state, the new integral and the DoFs
        whose correction was limited; the solver's state is left alone (``step`` applies
        them, unless a dry run or a non-finite result).
        """
        # Without integral action (ki = 0) nothing accumulates: an integral summed unused
        # would kick the loop by ki * sum(e) the moment ki is turned on.
        integral = self.integral + e if self.ki != 0 else self.integral.copy()
        if self.max_integral is not None:
            integral = np.clip(integral, -self.max_integral, self.max_integral)
        raw = -(self.kp * e + self.ki * integral)
        raw[~self.dof_mask] = 0.0
        u = raw
        clipped = np.zeros(N_DOF, dtype=bool)
        if self.max_step is not None:
            clipped |= np.abs(u) > self.max_step
            u = np.clip(u, -self.max_step, self.max_step)
        total = self.dof_total + u
        if self.clip_range is not None:
            clipped |= np.abs(total) > self.clip_range
            total = np.clip(total, -self.clip_range, self.clip_range)
        total[~self.dof_mask] = self.dof_total[~self.dof_mask]
        u = total - self.dof_total
        if self.max_step is not None and np.any(np.abs(u) > self.max_step):
            # The range clip moved a state that was out of range (range clipping switched on
            # again, or the ranges narrowed) back by more than a step: the step limit still
            # holds, and the state returns into range over several visits.
            clipped |= np.abs(u) > self.max_step
            u = np.clip(u, -self.max_step, self.max_step)
            total = self.dof_total + u
        # anti-windup: a DoF whose correction was limited does not integrate this visit
        integral[clipped] = self.integral[clipped]
        return u, total, integral, clipped


# --------------------------------------------------------------------------------------------
# a solver from the ofc_node's parameters
# --------------------------------------------------------------------------------------------
MATRIX_SOURCES: tuple[str, ...] = ("bundled", "ts_ofc")


@lru_cache(maxsize=4)
def sensitivity_for_source(source: str) -> SensitivityMatrix:
    """The 76x50 matrix of ``source`` at the corner mid-points (batoid_rubin DoF convention).

    ``"bundled"``: this project's matrix (:meth:`SensitivityMatrix.from_bundled`);
    ``"ts_ofc"``: Rubin's, evaluated at :func:`corner_mid_field_points_deg`. Cached: the
    ts_ofc one takes a double-Zernike evaluation.
    """
    if source == "bundled":
        return SensitivityMatrix.from_bundled()
    if source == "ts_ofc":
        return SensitivityMatrix.from_ts_ofc(fields_deg=corner_mid_field_points_deg())
    raise ConfigError(f"matrix_source must be one of {MATRIX_SOURCES}, got {source!r}")


# Ranges of ofc_node's numeric parameters, in one place: the node declares them in its
# ParameterDescriptors and solver_from_params checks them, so that the offline replay of a bag
# refuses the values the node refuses instead of running a solver no node could run.
OFC_PARAM_RANGES: dict[str, tuple[float, float]] = {
    "n_modes": (1, N_DOF),
    "alpha": (1e-9, 1.0),
    "kp": (0.0, 1.0),
    "ki": (0.0, 1.0),
    "max_step_scale": (0.0, 100.0),
    "max_condition": (1.0, 1e15),
    "max_abs_zernike_nm": (0.0, 1e7),
    "max_future_s": (0.0, 1e7),
}


def _ranged(get: Callable[[str], Any], name: str, integer: bool = False) -> float:
    """The parameter ``name`` checked as the node's descriptor checks it: a number (an integer
    for an integer parameter; never a bool or a string) within OFC_PARAM_RANGES."""
    v = get(name)
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, kinds):
        raise ConfigError(f"{name} must be {'an integer' if integer else 'a number'}, "
                          f"got {v!r}")
    lo, hi = OFC_PARAM_RANGES[name]
    if not lo <= v <= hi:  # NaN fails too
        raise ConfigError(f"{name} must be in [{lo:g}, {hi:g}], got {v!r}")
    return float(v)


def _flag(get: Callable[[str], Any], name: str) -> bool:
    v = get(name)
    if not isinstance(v, (bool, np.bool_)):
        raise ConfigError(f"{name} must be true or false, got {v!r}")
    return bool(v)


def solver_from_params(get: Callable[[str], Any]) -> OFCSolver:
    """An :class:`OFCSolver` from the ofc_node's parameter values, ``get(name) -> value``.

    The one place that turns the parameters of ``config/params.yaml`` (``band``,
    ``matrix_source``, ``method``, ``n_modes``, ``alpha``, ``weights``, ``kp``, ``ki``,
    ``dof_mask``, ``allow_partial``, ``max_step_scale``, ``clip_to_range``, ``max_condition``,
    ``max_abs_zernike_nm``, ``max_future_s``; 0 for either is no limit) into a solver, for
    the node and for the offline replay of a bag alike. Raises ConfigError naming the
    problem.
    """
    spec = load_dof_spec()
    band = str(get("band"))
    if band not in BANDS:
        raise ConfigError(f"band must be one of {BANDS}, got {band!r}")
    raw_mask = list(get("dof_mask"))
    if len(raw_mask) != N_DOF or not all(isinstance(b, (bool, np.bool_)) for b in raw_mask):
        raise ConfigError(f"dof_mask must hold {N_DOF} booleans, got {raw_mask!r}")
    mask = np.asarray(raw_mask, dtype=bool)
    scale = _ranged(get, "max_step_scale")
    return OFCSolver(
        sensitivity_for_source(str(get("matrix_source"))), band=band, method=str(get("method")),
        n_modes=int(_ranged(get, "n_modes", integer=True)), alpha=_ranged(get, "alpha"),
        weights=str(get("weights")), kp=_ranged(get, "kp"),
        ki=_ranged(get, "ki"), dof_mask=mask,
        clip_range="dof.yaml" if _flag(get, "clip_to_range") else None,
        max_step=spec.max_step * scale if scale > 0 else None,
        allow_partial=_flag(get, "allow_partial"),
        max_condition=_ranged(get, "max_condition"),
        max_abs_zernike_nm=_positive_or_none(_ranged(get, "max_abs_zernike_nm")),
        max_future_s=_positive_or_none(_ranged(get, "max_future_s")),
        dof_spec=spec)


def _positive_or_none(value: Any) -> float | None:
    """A parameter where 0 means "no limit"."""
    v = float(value)
    return v if v > 0 else None


# --------------------------------------------------------------------------------------------
# observability
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ObservabilityReport:
    """Singular spectrum and blind DoF combinations of the normalised, masked ``A``.

    Attributes
    ----------
    singular_values : (n_used,) singular values of ``A[rows][:, mask] * w[mask]``, nm per
        normalised unit, descending; zero-padded when there are fewer rows than DoFs.
    relative : ``singular_values / singular_values[0]``.
    dof_indices : (n_used,) indices of the DoFs included.
    weights : (n_used,) the normalisation ``w`` of those DoFs.
    vt : (n_used, n_used) right singular vectors (rows, unit norm in normalised units),
        in the order of ``singular_values``.
    rel_tol : threshold on ``relative`` below which a direction counts as unobservable.
    n_near_null : number of directions with ``relative < rel_tol`` (structural zeros included).
    """

    singular_values: np.ndarray
    relative: np.ndarray
    dof_indices: np.ndarray
    weights: np.ndarray
    vt: np.ndarray
    rel_tol: float
    n_near_null: int

    @property
    def null_directions_norm(self) -> np.ndarray:
        """(n_near_null, n_used) blind directions in normalised coordinates, unit norm."""
        return self.vt[self.relative < self.rel_tol]

    @property
    def null_directions_dof(self) -> np.ndarray:
        """(n_near_null, 50) blind directions in DoF units, ``x = w * z`` for unit-norm ``z``.

        Zero on the DoFs left out by the mask. Divide by the DoF ranges to compare entries of
        different units.
        """
        out = np.zeros((self.n_near_null, N_DOF))
        out[:, self.dof_indices] = self.null_directions_norm * self.weights[None, :]
        return out

    def describe(self, k: int, names: Sequence[str], top: int = 4) -> str:
        """Text of direction ``k`` (0 = most observable): its largest normalised components."""
        v = self.vt[k]
        order = np.argsort(-np.abs(v))[:top]
        terms = " ".join(f"{v[i]:+.2f}*{names[self.dof_indices[i]]}" for i in order)
        return f"s/s0={self.relative[k]:.2e}: {terms}"


def observability(
    sensitivity: SensitivityMatrix | None = None,
    *,
    weights: str | np.ndarray | Sequence[float] = "range-fwhm",
    dof_mask: np.ndarray | Sequence[bool] | None = None,
    corner_valid: np.ndarray | Sequence[bool] | None = None,
    rel_tol: float = 1e-6,
    dof_spec: DofSpec | None = None,
) -> ObservabilityReport:
    """Which DoF combinations the corner wavefronts cannot see.

    Parameters
    ----------
    sensitivity : default the ts_ofc matrix at the four SW0 corners.
    weights, dof_mask : as for :class:`OFCSolver`.
    corner_valid : corners whose rows are included (default all).
    rel_tol : singular values below ``rel_tol * s_max`` count as null.
    """
    sm = sensitivity if sensitivity is not None else SensitivityMatrix.from_ts_ofc()
    spec = dof_spec if dof_spec is not None else load_dof_spec()
    w = _resolve_weights(weights, spec)
    mask = np.ones(N_DOF, bool) if dof_mask is None else np.asarray(dof_mask, bool).reshape(-1)
    if mask.shape != (N_DOF,) or not mask.any():
        raise ConfigError("dof_mask must be 50 bools with at least one True")
    cv = np.ones(sm.n_fields, bool) if corner_valid is None else np.asarray(corner_valid, bool)
    rows = sm.rows_for(cv)
    if not rows.any():
        raise ConfigError("no corner selected")
    an = sm.matrix_nm[np.ix_(rows, mask)] * w[mask][None, :]
    _, s, vt = np.linalg.svd(an, full_matrices=True)
    n_used = int(mask.sum())
    s_full = np.zeros(n_used)
    s_full[: s.size] = s
    rel = s_full / s_full[0] if s_full[0] > 0 else np.zeros(n_used)
    return ObservabilityReport(s_full, rel, np.flatnonzero(mask), w[mask], vt, float(rel_tol),
                               int(np.sum(rel < rel_tol)))
