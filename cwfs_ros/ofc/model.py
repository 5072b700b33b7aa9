"""The controller's optical model at a camera-rotator angle: what the corners and the field see.

The state ``x`` of the controller is the 50 DoF in the actuators' own convention (the one of
``DofCorrection``, batoid_rubin's ``LSSTBuilder``). The corner sensors rotate with the camera:
a sensor whose nominal field is ``f`` (camera frame) sees the telescope field ``R(θ) f`` and
reports Zernikes in the camera frame. So, per rotator angle ``θ``:

* ``zrot``: camera-frame Z4..Z22 -> telescope frame (:mod:`cwfs_ros.ofc.rotation`);
* ``dofrot``: actuator DoF -> the telescope-frame DoF of the sensitivity data;
* ``H = A_tel(R(θ) f_c) @ dofrot``: telescope-frame Zernikes at the corners per DoF unit;
* ``F = A_tel(gq) @ dofrot``: the same at the 31 Gaussian-quadrature field points;
* ``intrinsic_nm``: the design wavefront at ``R(θ) f_c``, telescope frame.

A measurement ``y_cam`` is compared with the model as ``zrot @ y_cam - intrinsic = H x``.

With the measurement model ``estimator`` the corner rows are what the wavefront estimator
reports rather than the true wavefront (``config/ofc/estimator_response_r.npz``, from
tools/make_estimator_response.py). Per corner, in the camera frame, the estimator reads
``z + (G - I) dz_4..22 + A dz_23..37 + b`` (``dz`` the change from the design), so in the
telescope frame

* ``H_c = Rz G Rzᵀ H_c(4..22) + Rz A Rz'ᵀ H_c(23..37)``, with ``Rz``, ``Rz'`` the camera ->
  telescope rotations of Z4..Z22 and Z23..Z37 and ``H_c(23..37)`` the bundled double
  Zernike's Z23..Z37 at the corner (whatever the source of Z4..Z22: ts_ofc's stops at Z28);
* ``intrinsic_c = design_c + Rz b``.

The field rows (``F``, the image quality the controller minimises) stay the true wavefront.

The sensitivity at any field point comes from a double Zernike, evaluated here as one matrix
product with the field-Zernike basis (galsim's ``DoubleZernike`` object per DoF takes 5 s for
the 31 points; this takes milliseconds). Sources: ``ts_ofc`` (Rubin's yaml) and ``bundled``
(this project's from batoid, ``config/ofc/sensitivity_dz_bundled.npy`` when present). At
``θ = 0`` the ``bundled`` corner rows are the bundled 76x50 matrix itself, so an unrotated
camera sees exactly the matrix the project ships.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import galsim
import numpy as np

from cwfs_ros import layout
from cwfs_ros.errors import ConfigError
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc import rotation
from cwfs_ros.ofc.field import gq_field_points_deg, gq_weights

__all__ = ["BUNDLED_DZ_FILENAME", "ESTIMATOR_RESPONSE_BAND", "ESTIMATOR_RESPONSE_FILENAME",
           "MEASUREMENT_MODELS",
           "RESPONSE_NOLL_HIGH", "EstimatorResponse", "ModelAtAngle", "OpticalModel",
           "double_zernike_at", "estimator_response"]

#: This project's double-Zernike sensitivity, (k_field, 38, 50) nm per DoF unit (Noll pupil
#: index 0..37: the controller's Z4..Z22 and the Z23..Z37 the estimator aliases into them),
#: wavefront sign, batoid_rubin DoF convention (tools/make_sensitivity.py).
BUNDLED_DZ_FILENAME = "sensitivity_dz_bundled.npy"

#: How the estimator reads the wavefront at each corner, camera frame (G, A, b; see
#: tools/make_estimator_response.py), in ``config/ofc``.
ESTIMATOR_RESPONSE_FILENAME = "estimator_response_r.npz"
ESTIMATOR_RESPONSE_BAND = "r"

#: The highest pupil Noll index of the estimator's response (aliasing from Z23..this).
RESPONSE_NOLL_HIGH = 37

#: What the controller compares a measurement with: ``design``, the true wavefront's
#: Z4-Z22; ``estimator``, the same as the estimator reads it (gain, aliasing and offset).
MEASUREMENT_MODELS = ("design", "estimator")


@dataclass(frozen=True)
class ModelAtAngle:
    """The optical model at one rotator angle (all arrays read-only).

    About 40 kB per angle: the field sensitivity is shared by every angle and turned into
    the actuators' DoF on use (:attr:`F`), so that the cache of every bin a night visits
    stays small.
    """

    angle_deg: float
    corner_fields_deg: np.ndarray  # (4, 2) telescope frame
    zrot: np.ndarray  # (19, 19) camera -> telescope Zernikes
    dofrot: np.ndarray  # (50, 50) actuator DoF -> telescope-frame DoF
    H: np.ndarray  # (76, 50) nm per DoF unit
    intrinsic_nm: np.ndarray  # (76,) telescope frame
    F_tel: np.ndarray  # (31 * 19, 50) nm per telescope-frame DoF unit at the GQ points
    field_weights: np.ndarray  # (31,)

    @property
    def F(self) -> np.ndarray:
        """(31 * 19, 50) nm per actuator DoF unit at the quadrature points (computed, ~1 ms)."""
        return self.F_tel @ self.dofrot

    def to_telescope(self, y_cam: np.ndarray) -> np.ndarray:
        """(76,) camera-frame corner Zernikes -> telescope frame."""
        return (y_cam.reshape(-1, layout.N_ZK) @ self.zrot.T).reshape(-1)


def double_zernike_at(dz: np.ndarray, fields_deg: np.ndarray,
                      noll: tuple[int, int] = (layout.NOLL_MIN, layout.NOLL_MAX)) -> np.ndarray:
    """Pupil Z_noll[0]..Z_noll[1] per DoF at field points: (n, nj, n_dof) from a (k, j, n_dof)
    double Zernike (default Z4..Z22, nj = 19).

    Same convention as galsim's ``DoubleZernike`` with the field annulus of ts_ofc's
    ``configurations/lsst.yaml`` (which :func:`cwfs_ros.ofc.control._eval_double_zernike`
    uses): the value is ``sum_k Z_k(field) dz[k, j]``.
    """
    cfg = C.load_optics_config()
    f = np.asarray(fields_deg, dtype=np.float64).reshape(-1, 2)
    basis = galsim.zernike.zernikeBasis(dz.shape[0] - 1, f[:, 0], f[:, 1],
                                        R_outer=cfg.field_outer_deg,
                                        R_inner=cfg.field_inner_deg)  # (k, n)
    if dz.shape[1] <= noll[1]:
        raise ConfigError(f"the double Zernike stops at pupil Noll {dz.shape[1] - 1}; "
                          f"Z{noll[1]} is needed")
    pupil = dz[:, noll[0]:noll[1] + 1, :]  # (k, nj, d)
    return np.einsum("kn,kjd->njd", basis, pupil)


@lru_cache(maxsize=2)
def _dz_nm(source: str) -> np.ndarray:
    """(k, j, 50) double-Zernike sensitivity of ``source`` in nm, wavefront sign, batoid_rubin
    DoF convention."""
    if source == "ts_ofc":
        path = C.ofc_config_dir() / C._TS_OFC_MATRIX  # noqa: SLF001 - one home for the path
        dz = C._yaml_array(path, 3)  # noqa: SLF001
        dz = -1000.0 * C.convert_dof_convention(dz, "ts_ofc", "batoid_rubin")
    elif source == "bundled":
        path = C.ofc_config_dir() / BUNDLED_DZ_FILENAME
        if not path.is_file():
            raise ConfigError(f"{path} is missing: the bundled sensitivity away from the "
                              "corners (rotated camera, field points) needs it")
        dz = np.load(path)
    else:
        raise ConfigError(f"matrix_source must be one of {C.MATRIX_SOURCES}, got {source!r}")
    if dz.ndim != 3 or dz.shape[1] <= layout.NOLL_MAX or dz.shape[2] != layout.N_DOF:
        raise ConfigError(f"{source} double Zernike must be (k, >22, 50), got {dz.shape}")
    dz = np.ascontiguousarray(dz, dtype=np.float64)
    dz.setflags(write=False)
    return dz


@lru_cache(maxsize=8)
def _intrinsic_dz_nm(band: str) -> np.ndarray:
    """(k, j, 1) double Zernike of the design wavefront of ``band`` in nm (ts_ofc's intrinsic
    yaml, as :func:`cwfs_ros.ofc.control.intrinsic_zernikes_nm` reads it)."""
    tag = "" if band == "ref" else band
    path = C.ofc_config_dir() / C._INTRINSIC_DIR / f"intrinsic_zk_{tag}_31_29.yaml"  # noqa: SLF001
    coef = C._yaml_array(path, 2) * C.band_wavelength_um(band) * 1000.0  # noqa: SLF001
    out = np.ascontiguousarray(coef[:, :, None])
    out.setflags(write=False)
    return out


def _bundled_dz_available() -> bool:
    return (C.ofc_config_dir() / BUNDLED_DZ_FILENAME).is_file()


@dataclass(frozen=True)
class EstimatorResponse:
    """How the estimator reads the wavefront at each corner, camera frame (read-only arrays):
    ``z_est = z + (G - I) dz_4..22 + A dz_23..37 + b``, ``dz`` the change from the design."""

    G: np.ndarray  # (4, 19, 19) read per true nm
    A: np.ndarray  # (4, 19, 15) read Z4..Z22 per true nm of Z23..Z37
    b_nm: np.ndarray  # (4, 19) reading of the design less the design [nm]


@lru_cache(maxsize=1)
def estimator_response() -> EstimatorResponse:
    """The shipped :class:`EstimatorResponse` (``config/ofc/estimator_response_r.npz``);
    ConfigError if missing or malformed."""
    path = C.ofc_config_dir() / ESTIMATOR_RESPONSE_FILENAME
    n_high = RESPONSE_NOLL_HIGH - layout.NOLL_MAX
    shapes = {"G": (layout.N_CORNERS, layout.N_ZK, layout.N_ZK),
              "A": (layout.N_CORNERS, layout.N_ZK, n_high), "b": (layout.N_CORNERS, layout.N_ZK)}
    try:
        with np.load(path) as f:
            arrays = {k: np.array(f[k], dtype=np.float64) for k in shapes}
    except (OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"{path}: the estimator's response is unreadable ({exc}); the "
                          "measurement model 'estimator' needs it "
                          "(tools/make_estimator_response.py)") from exc
    for k, shape in shapes.items():
        a = arrays[k]
        if a.shape != shape or not np.all(np.isfinite(a)):
            raise ConfigError(f"{path}: {k} must be finite of shape {shape}, got {a.shape}")
        a.setflags(write=False)
    return EstimatorResponse(arrays["G"], arrays["A"], arrays["b"])


def _as_estimator_reads(H: np.ndarray, intrinsic_nm: np.ndarray, high: np.ndarray,
                        theta_rad: float, zrot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, intrinsic) of the corners as the estimator reads them (the module docstring's
    formula): ``high`` (4, 15, 50) is Z23..Z37 per telescope-frame DoF unit at the corners."""
    resp = estimator_response()
    zrot_high = rotation.zernike_rotation_matrix(theta_rad, layout.NOLL_MAX + 1,
                                                 RESPONSE_NOLL_HIGH)
    h = H.reshape(layout.N_CORNERS, layout.N_ZK, -1)
    g_tel = zrot @ resp.G @ zrot.T  # (4, 19, 19)
    a_tel = zrot @ resp.A @ zrot_high.T  # (4, 19, 15)
    h_read = g_tel @ h + a_tel @ high
    intr = intrinsic_nm.reshape(layout.N_CORNERS, layout.N_ZK) + resp.b_nm @ zrot.T
    return h_read.reshape(H.shape), intr.reshape(-1)


class OpticalModel:
    """The controller's model of the telescope, cached per rotator-angle bin.

    Parameters
    ----------
    source : ``"bundled"`` or ``"ts_ofc"`` (the sensitivity data).
    band : band of the design wavefront subtracted (``u g r i z y ref``).
    measurement : :data:`MEASUREMENT_MODELS`: the corners' true wavefront (``design``) or
        what the estimator reads of it (``estimator``, the module docstring).
    angle_bin_deg : the rotator angle is rounded to this before the model is built; an
        angle's model is cached (``cache_size`` bins: every 0.25 deg bin of the rotator's
        whole range fits, about 40 kB each, 80 MB at most).
    """

    def __init__(self, source: str = "bundled", band: str = "r", *,
                 angle_bin_deg: float = 0.25, cache_size: int = 2048,
                 measurement: str = "design") -> None:
        if source not in C.MATRIX_SOURCES:
            raise ConfigError(f"matrix_source must be one of {C.MATRIX_SOURCES}, got {source!r}")
        if measurement not in MEASUREMENT_MODELS:
            raise ConfigError(f"measurement_model must be one of {MEASUREMENT_MODELS}, got "
                              f"{measurement!r}")
        self.measurement = measurement
        if measurement == "estimator":
            if band != ESTIMATOR_RESPONSE_BAND:
                raise ConfigError(f"measurement_model estimator: the estimator's response is "
                                  f"measured in band {ESTIMATOR_RESPONSE_BAND}, not {band!r}")
            estimator_response()  # a missing or malformed file fails here, at configure
            self._high_dz = _dz_nm("bundled")
        if not (np.isfinite(angle_bin_deg) and 0 < angle_bin_deg <= 5):
            raise ConfigError(f"angle_bin_deg must be in (0, 5], got {angle_bin_deg!r}")
        self.source = source
        self.band = band
        self.angle_bin_deg = float(angle_bin_deg)
        self.corner_fields_cam_deg = C.corner_mid_field_points_deg()
        # The data of the field and of rotated corners: the source's own double Zernike, or,
        # for a bundled matrix without one, ts_ofc's (stated in docs/closed-loop.md).
        self.field_source = source if (source == "ts_ofc" or _bundled_dz_available()) \
            else "ts_ofc"
        gq = gq_field_points_deg()
        self._F_tel = double_zernike_at(_dz_nm(self.field_source), gq).reshape(-1, layout.N_DOF)
        self._F_tel.setflags(write=False)
        self._weights = gq_weights()
        self._at = lru_cache(maxsize=cache_size)(self._build)

    def bin_angle_deg(self, angle_deg: float) -> float:
        """The angle the model of ``angle_deg`` is built at (its bin's centre)."""
        return round(float(angle_deg) / self.angle_bin_deg) * self.angle_bin_deg

    def at(self, angle_deg: float) -> ModelAtAngle:
        """The model at the rotator angle ``angle_deg`` (degrees), from the cache."""
        if not np.isfinite(angle_deg):
            raise ConfigError(f"rotator angle must be finite, got {angle_deg!r}")
        return self._at(self.bin_angle_deg(angle_deg))

    def _corner_matrix(self, fields_tel: np.ndarray, angle_deg: float) -> np.ndarray:
        if angle_deg == 0 and self.source == "bundled":
            return C.sensitivity_for_source("bundled").matrix_nm
        return double_zernike_at(_dz_nm(self.field_source), fields_tel).reshape(-1, layout.N_DOF)

    def _build(self, angle_deg: float) -> ModelAtAngle:
        theta = np.deg2rad(angle_deg)
        fields = rotation.telescope_field_deg(self.corner_fields_cam_deg, theta)
        zrot = rotation.zernike_rotation_matrix(theta)
        dofrot = rotation.dof_rotation_matrix(theta)
        H = self._corner_matrix(fields, angle_deg)
        intr = double_zernike_at(_intrinsic_dz_nm(self.band), fields).reshape(-1)
        if self.measurement == "estimator":
            high = double_zernike_at(self._high_dz, fields,
                                     (layout.NOLL_MAX + 1, RESPONSE_NOLL_HIGH))
            H, intr = _as_estimator_reads(H, intr, high, theta, zrot)
        H = H @ dofrot
        arrays = [np.ascontiguousarray(a, dtype=np.float64)
                  for a in (fields, zrot, dofrot, H, intr)]
        for a in arrays:
            a.setflags(write=False)
        return ModelAtAngle(float(angle_deg), *arrays, self._F_tel, self._weights)

