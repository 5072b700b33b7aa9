"""The one home of the project's fixed layout: corners, sides, Zernike range, DoF, topic names.

Everything else imports these; no other module defines them.

* Corner wavefront sensors: the four LSST corner rafts, each split into an intra-focal and an
  extra-focal half-chip.
* Zernike terms: annular, Noll-indexed, Z4..Z22 (19 terms) in nm of OPD, in the focal-plane
  frame. The 76-vector is the 19 terms of each corner, corners in :data:`CORNERS` order.
* DoF: the 50 optical degrees of freedom in ts_ofc's order: M2 hexapod (dz, dx, dy in um; rx,
  ry in deg), camera hexapod (same), 20 M1M3 bending modes, 20 M2 bending modes (um).
* Topic names are relative (they follow the node's namespace and remappings); recorded bags
  and the offline replay use the same names with a leading slash (:func:`absolute`).
"""

from __future__ import annotations

__all__ = [
    "CLOCK_RESET_S", "CORNERS", "CORNER_SENSORS", "CORRECTION_TOPIC", "DOF_NAMES", "DOF_UNITS",
    "JOINT_TOPIC", "NOLL", "NOLL_MAX", "NOLL_MIN", "N_CORNERS", "N_DOF", "N_MEAS", "N_ZK",
    "SIDES", "TRUTH_TOPIC", "VECTOR_TOPIC", "absolute", "corner_topic", "image_topic",
]

CORNERS: tuple[str, ...] = ("R00", "R04", "R40", "R44")
# The corner sensors' names in the LSST focal plane (the sensitivity matrix's row order).
CORNER_SENSORS: tuple[str, ...] = tuple(f"{c}_SW0" for c in CORNERS)
SIDES: tuple[str, ...] = ("intra", "extra")
N_CORNERS = len(CORNERS)

NOLL_MIN = 4
NOLL_MAX = 22
NOLL: tuple[int, ...] = tuple(range(NOLL_MIN, NOLL_MAX + 1))
N_ZK = len(NOLL)  # 19
N_MEAS = N_CORNERS * N_ZK  # 76

N_DOF = 50
_RIGID = ("dz", "dx", "dy", "rx", "ry")
DOF_NAMES: tuple[str, ...] = (
    *(f"M2_{n}" for n in _RIGID),
    *(f"Cam_{n}" for n in _RIGID),
    *(f"M1M3_B{k}" for k in range(1, 21)),
    *(f"M2_B{k}" for k in range(1, 21)),
)
DOF_UNITS: tuple[str, ...] = ("um", "um", "um", "deg", "deg") * 2 + ("um",) * 40

# Visit timing: a stamp this far behind the newest visit, and older than every visit
# remembered, is a clock that went back, not a late image (visits come every ~30-40 s; no
# image is 10 minutes late). The pairing and the controller share it.
CLOCK_RESET_S = 600.0

VECTOR_TOPIC = "aos/wfs/wavefront"
CORRECTION_TOPIC = "aos/ofc/dof_correction"
TRUTH_TOPIC = "aos/sim/truth"
JOINT_TOPIC = "joint_states"


def image_topic(corner: str, side: str) -> str:
    """The image topic of one half-chip, e.g. ``aos/wfs/R00/intra/image``."""
    return f"aos/wfs/{corner}/{side}/image"


def corner_topic(corner: str) -> str:
    """The per-corner wavefront topic, e.g. ``aos/wfs/R00/wavefront``."""
    return f"aos/wfs/{corner}/wavefront"


def absolute(topic: str) -> str:
    """The fully qualified name of a topic in the root namespace (as bags record it)."""
    return topic if topic.startswith("/") else "/" + topic
