"""One exposure, one stamp: conflicting images; bounded pending memory; frame_id; uncertainty
carried from the corners into the visit vector (no ROS: cwfs_ros.runtime.visits)."""

from __future__ import annotations

import numpy as np

from cwfs_ros.runtime.visits import (
    CornerEntry,
    ImageRecord,
    PairingBuffer,
    VisitAssembler,
)

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def rec(side: str, value: float, stamp: int = T0, corner: str = "R00", t: float = 0.0,
        shape=(4, 4)) -> ImageRecord:
    return ImageRecord(corner, side, stamp, np.full(shape, float(value)), received=t)


def test_an_identical_copy_is_a_duplicate_a_different_image_a_conflict_while_waiting():
    pb = PairingBuffer(tolerance_ns=MS)
    assert pb.add(rec("intra", 1.0)) == (None, None)
    _, r = pb.add(rec("intra", 1.0))
    assert r.reason == "duplicate"
    # Another exposure under the same stamp (0.5 ms off: the same visit).
    pair, r = pb.add(rec("intra", 2.0, T0 + MS // 2))
    assert pair is None and r.reason == "conflicting_images"
    # The corner's visit is closed: neither image is paired with a later partner.
    for v in (1.0, 2.0):
        pair, r = pb.add(rec("extra", v))
        assert pair is None and r.reason == "late" and "conflicting_images" in r.message
    assert pb.pending_count() == 0


def test_chimeric_pair_is_reported_when_the_other_exposure_arrives():
    """Intra of exposure A and extra of exposure B paired (equal stamps): the arrival of
    A's extra or B's intra is a conflict, never a silent duplicate."""
    pb = PairingBuffer(tolerance_ns=MS)
    pb.add(rec("intra", 1.0))
    pair, _ = pb.add(rec("extra", 20.0))
    assert pair is not None
    for side, v in (("extra", 10.0), ("intra", 2.0)):
        pair, r = pb.add(rec(side, v))
        assert pair is None and r.reason == "conflicting_images"
    assert pb.was_paired("R00", T0)
    _, r = pb.add(rec("intra", 1.0))  # a re-sent copy of what was paired
    assert r.reason == "duplicate"


def test_assembler_invalidates_a_corner_of_a_pending_visit():
    asm = VisitAssembler(tolerance_ns=MS)
    z = np.arange(19.0) + 100.0
    asm.add(CornerEntry("R00", T0, z, True, "ok"), 0.0)
    done, vec = asm.invalidate("R00", T0, "conflicting_images: two exposures")
    assert done and vec is None
    for c in ("R04", "R40"):
        asm.add(CornerEntry(c, T0, z, True, "ok"), 0.0)
    vec, _ = asm.add(CornerEntry("R44", T0, z, True, "ok"), 0.0)
    assert vec.corner_valid == (False, True, True, True)
    assert vec.statuses[0].startswith("conflicting_images")
    # Once emitted, too late: False.
    assert asm.invalidate("R04", T0, "x") == (False, None)


def test_pending_images_are_bounded_oldest_first():
    pb = PairingBuffer(tolerance_ns=0)
    for k in range(5):
        pb.add(rec("intra", k, T0 + k * 1000 * MS, t=float(k), shape=(100, 100)))
    assert pb.pending_bytes() == 5 * 100 * 100 * 8
    r = pb.drop_oldest()
    assert r.reason == "memory_limit" and r.stamp_ns == T0
    assert pb.pending_bytes() == 4 * 100 * 100 * 8
    # Its visit is closed: the late partner is not paired.
    pair, r2 = pb.add(rec("extra", 0, T0, t=9.0, shape=(100, 100)))
    assert pair is None and r2.reason == "late"


def test_vector_carries_uncertainty_and_pair_counts_of_valid_corners():
    asm = VisitAssembler(tolerance_ns=MS)
    z = np.arange(19.0)
    unc = np.full(19, 7.0)
    vec = None
    for k, c in enumerate(("R00", "R04", "R40", "R44")):
        valid = c != "R40"
        u = unc.copy()
        if c == "R44":
            u[3] = np.nan  # unknown for one term: 0 = not reported
        vec, _ = asm.add(CornerEntry(c, T0, z, valid, "ok" if valid else "bad: x", u, k + 1),
                         0.0)
    assert vec.n_pairs == (1, 2, 0, 4)
    u = vec.uncertainty_nm.reshape(4, 19)
    assert np.all(u[0] == 7.0) and np.all(u[2] == 0.0) and u[3, 3] == 0.0 and u[3, 4] == 7.0


def test_a_message_identity_sees_one_changed_byte_and_the_layout():
    from types import SimpleNamespace

    from cwfs_ros.runtime.visits import message_digest

    data = bytearray(np.arange(4000 * 2000 // 4, dtype="<f4").tobytes())

    def msg(d, encoding="32FC1", width=1000):  # 4-byte pixels
        return SimpleNamespace(encoding=encoding, height=len(d) // (4 * width), width=width,
                               step=4 * width, is_bigendian=0, data=d)

    a = message_digest(msg(data))
    assert len(a) == 16 and message_digest(msg(bytearray(data))) == a
    changed = bytearray(data)
    changed[len(changed) // 2 + 3] ^= 1  # one bit of one pixel in the middle of the frame
    assert message_digest(msg(changed)) != a
    assert message_digest(msg(data, encoding="32SC1")) != a  # the same bytes
    assert message_digest(msg(data, width=500)) != a
