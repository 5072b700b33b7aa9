"""Optical feedback control: from corner wavefronts to corrections of the 50 DoF.

Split as ts_ofc splits it: the science field and its figure of merit (:mod:`.field`), state
estimation (:mod:`.estimation`) and controllers (:mod:`.controller`). The sensitivity data
still live in :mod:`cwfs_ros.ofc.control`.
"""

from cwfs_ros.ofc.field import (
    FIELD_RADIUS_DEG,
    field_rms_nm,
    gq_field_points_deg,
    gq_weights,
)

__all__ = [
    "FIELD_RADIUS_DEG",
    "field_rms_nm",
    "gq_field_points_deg",
    "gq_weights",
]
