"""Message <-> numpy conversion for the cwfs_ros nodes.

Only field copying lives here; decoding rules are in :mod:`cwfs_ros.runtime.images` and the
visit logic in :mod:`cwfs_ros.runtime.visits`, both free of ROS.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from cwfs_msgs.msg import CornerWavefront, DofCorrection, WavefrontVector
from sensor_msgs.msg import Image

from cwfs_ros.errors import Problem
from cwfs_ros.layout import CORNERS, NOLL
from cwfs_ros.ros.common import ns_to_stamp, stamp_to_ns
from cwfs_ros.runtime.corner_pool import CornerOutcome
from cwfs_ros.runtime.images import ENCODINGS
from cwfs_ros.runtime.visits import CornerEntry, ImageRecord, VisitVector, zernikes_by_noll
from cwfs_ros.runtime.visits import image_record_from_msg as core_image_record

__all__ = [
    "corner_entry_from_msg",
    "corner_wavefront_msg",
    "dof_correction_msg",
    "image_msg",
    "image_record_from_msg",
    "vector_from_msg",
    "wavefront_vector_msg",
]

_NUMPY_TYPE = {"u1": np.uint8, "i1": np.int8, "u2": np.uint16, "i2": np.int16,
               "i4": np.int32, "f4": np.float32, "f8": np.float64}


def image_record_from_msg(msg: Image, corner: str, side: str, received: float) -> ImageRecord:
    """Decode an Image message into an :class:`ImageRecord` (never raises).

    A message that cannot be decoded gives a record with ``image=None`` and ``error`` naming
    the problem; it still takes part in pairing so that the corner's result reports it. The
    rules are :func:`cwfs_ros.runtime.visits.image_record_from_msg`, which the offline replay of a
    bag (:mod:`cwfs_ros.cli.replay`) uses too.
    """
    return core_image_record(msg, corner, side, received)


def image_msg(array: np.ndarray, stamp_ns: int, *, encoding: str = "32FC1",
              frame_id: str = "", big_endian: bool = False) -> Image:
    """An Image message from a 2-D array (used by tests, the bench and the camera simulator)."""
    base = ENCODINGS[encoding]
    dt = np.dtype(_NUMPY_TYPE[base]).newbyteorder(">" if big_endian else "<")
    a = np.ascontiguousarray(np.asarray(array).astype(dt))
    m = Image(height=int(a.shape[0]), width=int(a.shape[1]), encoding=encoding,
              is_bigendian=int(big_endian), step=int(a.shape[1] * dt.itemsize))
    m.header.stamp = ns_to_stamp(stamp_ns)
    m.header.frame_id = frame_id
    m.data = a.tobytes()
    return m


def corner_wavefront_msg(out: CornerOutcome, *, field_intra_deg: Sequence[float],
                         field_extra_deg: Sequence[float], frame_id: str) -> CornerWavefront:
    """CornerWavefront from a worker's :class:`CornerOutcome` (or an invalid stand-in)."""
    m = CornerWavefront()
    m.header.stamp = ns_to_stamp(out.stamp_ns)
    m.header.frame_id = frame_id
    m.corner = out.corner
    m.field_deg = np.asarray(out.field_deg, dtype=np.float64)
    m.field_intra_deg = np.asarray(field_intra_deg, dtype=np.float64)
    m.field_extra_deg = np.asarray(field_extra_deg, dtype=np.float64)
    m.noll = [int(j) for j in out.noll]
    m.zernikes_nm = [float(v) for v in out.zernikes_nm]
    # NaN = unknown (an invalid result, or no noise model); a stamp pair gives the noise
    # model's, frames the scatter of their pairs.
    unc = out.uncertainty_nm
    m.uncertainty_nm = ([float(v) for v in unc] if unc is not None and len(unc) == len(out.noll)
                        else [float("nan")] * len(out.noll))
    m.n_pairs = int(max(0, min(out.n_pairs, 65535)))
    m.caustic = bool(out.caustic)
    m.valid = bool(out.valid)
    m.status = out.status
    m.solver = out.solver
    m.iterations = int(max(0, min(out.iterations, 65535)))
    m.compute_ms = float(out.compute_ms)
    return m


def corner_entry_from_msg(m: CornerWavefront) -> CornerEntry:
    """What the assembler needs from a CornerWavefront (any producer, local or remote)."""
    z = zernikes_by_noll(m.noll, m.zernikes_nm)
    valid = bool(m.valid)
    status = m.status or ("ok" if valid else "invalid (no status given)")
    if valid and z is None:
        valid = False
        status = ("bad_corner_wavefront: flagged valid but noll/zernikes_nm do not hold "
                  f"Z4..Z22 (noll={list(m.noll)}, {len(m.zernikes_nm)} values)")
    unc = np.asarray(m.uncertainty_nm, dtype=np.float64).reshape(-1)
    unc_z = zernikes_by_noll(m.noll, unc) if unc.size == len(m.noll) else None
    return CornerEntry(m.corner, stamp_to_ns(m.header.stamp), z, valid, status, unc_z,
                       int(m.n_pairs))


def wavefront_vector_msg(v: VisitVector, frame_id: str) -> WavefrontVector:
    m = WavefrontVector()
    m.header.stamp = ns_to_stamp(v.stamp_ns)
    m.header.frame_id = frame_id
    m.zernikes_nm = np.asarray(v.zernikes_nm, dtype=np.float64)
    m.corner_valid = [bool(b) for b in v.corner_valid]
    m.corners = list(v.corners)
    m.status = v.status
    m.uncertainty_nm = np.asarray(v.uncertainty_nm, dtype=np.float64)
    m.n_pairs = [int(n) for n in v.n_pairs]
    return m


def vector_from_msg(m: WavefrontVector) -> tuple[np.ndarray, np.ndarray, Problem | None]:
    """(zernikes (76,), corner_valid (4,), problem) from a WavefrontVector.

    ``problem`` is None when the layout is the documented one; otherwise it names the issue
    (the corners field must read R00, R04, R40, R44; an empty field is taken as that order).
    """
    z = np.asarray(m.zernikes_nm, dtype=np.float64).reshape(-1)
    valid = np.asarray(list(m.corner_valid), dtype=bool).reshape(-1)
    names = [str(c) for c in m.corners]
    problem = None
    if z.shape != (len(CORNERS) * len(NOLL),) or valid.shape != (len(CORNERS),):
        problem = Problem("bad_layout", f"expected {len(CORNERS) * len(NOLL)} Zernikes and "
                          f"{len(CORNERS)} validity flags, got {z.size} and {valid.size}")
    elif any(names) and names != list(CORNERS):
        problem = Problem("bad_layout",
                          f"corners must be {list(CORNERS)} in this order, got {names}")
    return z, valid, problem


def dof_correction_msg(*, stamp_ns: int, frame_id: str, dof: np.ndarray, dof_total: np.ndarray,
                       valid: bool, status: str, wavefront_rms_nm: float,
                       predicted_residual_rms_nm: float, dry_run: bool,
                       n_modes_used: int) -> DofCorrection:
    m = DofCorrection()
    m.header.stamp = ns_to_stamp(stamp_ns)
    m.header.frame_id = frame_id
    m.dof = np.asarray(dof, dtype=np.float64)
    m.dof_total = np.asarray(dof_total, dtype=np.float64)
    m.valid = bool(valid)
    m.status = status
    m.wavefront_rms_nm = float(wavefront_rms_nm)
    m.predicted_residual_rms_nm = float(predicted_residual_rms_nm)
    m.dry_run = bool(dry_run)
    m.n_modes_used = int(max(0, min(n_modes_used, 65535)))
    return m
