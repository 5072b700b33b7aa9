"""Pairing of intra/extra images and assembly of the 76-vector (cwfs_ros.runtime.visits).

Pure Python: the state machines are driven with explicit times, no middleware.
"""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros.layout import CORNERS, NOLL
from cwfs_ros.runtime.visits import (
    CornerEntry,
    ImageRecord,
    PairingBuffer,
    VisitAssembler,
    load_corner_fields,
    zernikes_by_noll,
)

T0 = 1_700_000_000_000_000_000  # a stamp in ns
MS = 1_000_000


def img(corner, side, stamp, t=0.0, error=None):
    return ImageRecord(corner, side, stamp, None if error else np.zeros((2, 2)), error,
                       received=t)


def zk(c: int) -> np.ndarray:
    return np.arange(19, dtype=float) + 100 * c


# ------------------------------------------------------------------ pairing
def test_pairs_intra_and_extra_with_equal_stamps_in_either_order():
    pb = PairingBuffer(tolerance_ns=0)
    assert pb.add(img("R00", "intra", T0)) == (None, None)
    pair, rej = pb.add(img("R00", "extra", T0))
    assert rej is None and pair.corner == "R00" and pair.stamp_ns == T0
    assert (pair.intra.side, pair.extra.side) == ("intra", "extra")
    assert pb.add(img("R44", "extra", T0 + 5)) == (None, None)
    pair, _ = pb.add(img("R44", "intra", T0 + 5))
    assert pair.corner == "R44" and pair.intra.side == "intra"
    assert pb.pending_count() == 0


def test_corners_and_visits_do_not_cross_pair():
    pb = PairingBuffer(tolerance_ns=0)
    pb.add(img("R00", "intra", T0))
    assert pb.add(img("R04", "extra", T0)) == (None, None)  # other corner
    assert pb.add(img("R00", "extra", T0 + 1)) == (None, None)  # other visit (tolerance 0)
    assert pb.pending_count() == 3
    pair, _ = pb.add(img("R00", "extra", T0))
    assert pair.stamp_ns == T0 and pair.extra.stamp_ns == T0


def test_tolerance_pairs_the_closest_partner():
    pb = PairingBuffer(tolerance_ns=2 * MS)
    pb.add(img("R40", "extra", T0 - 2 * MS))
    pb.add(img("R40", "extra", T0 + 5 * MS))  # too far: another visit
    pair, _ = pb.add(img("R40", "intra", T0))
    assert pair.extra.stamp_ns == T0 - 2 * MS and pair.stamp_ns == T0  # the intra's stamp
    assert pb.pending_count() == 1


def test_interleaved_visits_pair_correctly():
    pb = PairingBuffer(tolerance_ns=0)
    for k in range(3):
        pb.add(img("R00", "intra", T0 + k * 1000 * MS))
    stamps = []
    for k in (2, 0, 1):
        pair, _ = pb.add(img("R00", "extra", T0 + k * 1000 * MS))
        stamps.append(pair.stamp_ns)
    assert stamps == [T0 + 2000 * MS, T0, T0 + 1000 * MS]


def test_duplicate_pending_and_duplicate_after_pairing():
    pb = PairingBuffer(tolerance_ns=MS)
    pb.add(img("R00", "intra", T0))
    _, rej = pb.add(img("R00", "intra", T0 + MS // 2))
    assert rej.reason == "duplicate" and "already waiting" in rej.message
    pb.add(img("R00", "extra", T0))
    for side in ("intra", "extra"):
        pair, rej = pb.add(img("R00", side, T0))
        assert pair is None and rej.reason == "duplicate" and "already paired" in rej.message
        assert rej.corner == "R00" and rej.side == side and rej.stamp_ns == T0
    assert pb.pending_count() == 0


def test_unpaired_images_expire_after_the_timeout_and_late_partners_are_rejected():
    pb = PairingBuffer(tolerance_ns=0, timeout_s=2.0)
    pb.add(img("R04", "intra", T0, t=10.0))
    assert pb.expire(11.9) == []
    (rej,) = pb.expire(12.1)
    assert rej.reason == "unpaired" and rej.corner == "R04" and rej.side == "intra"
    assert "no extra image" in rej.message and "timeout 2 s" in rej.message
    assert pb.pending_count() == 0
    pair, rej = pb.add(img("R04", "extra", T0, t=12.5))
    assert pair is None and rej.reason == "late"


def test_close_from_outside_drops_waiting_images_and_marks_later_ones_late():
    pb = PairingBuffer(tolerance_ns=0)
    pb.add(img("R40", "extra", T0))
    (rej,) = pb.close("R40", T0, "visit published without it")
    assert rej.reason == "unpaired" and "visit published without it" in rej.message
    _, rej = pb.add(img("R40", "intra", T0))
    assert rej.reason == "late" and "closed" in rej.message
    assert pb.close("R40", T0 + 1, "x") == []  # nothing waiting: just remembered
    assert pb.add(img("R40", "intra", T0 + 1))[1].reason == "late"


def test_images_older_than_the_tracked_history_are_late():
    pb = PairingBuffer(tolerance_ns=0, history=3)
    for k in range(1, 5):
        pb.add(img("R00", "intra", T0 + k))
        pb.add(img("R00", "extra", T0 + k))
    _, rej = pb.add(img("R00", "intra", T0))  # before every remembered visit
    assert rej.reason == "late" and "older than every visit" in rej.message


def test_a_clock_that_went_back_restarts_the_history_instead_of_locking_out():
    """A camera or simulator restarted with its clock a day back: its images are older than
    every visit remembered, but far beyond any lateness (CLOCK_RESET_S behind the newest
    visit): the corner's history is cleared with a clock_jump notice and they pair again.
    Before, every later image was refused as late until the stamps caught up (a day)."""
    sec, day = 1_000_000_000, 86_400_000_000_000
    pb = PairingBuffer(tolerance_ns=MS, history=3)
    for k in range(1, 5):
        pb.add(img("R00", "intra", T0 + k * 30 * sec))
        pb.add(img("R00", "extra", T0 + k * 30 * sec))
    # A minute late: still refused as late (within CLOCK_RESET_S).
    _, rej = pb.add(img("R00", "intra", T0 + 30 * sec - 60 * sec))
    assert rej.reason == "late"
    back = T0 - day
    pair, notice = pb.add(img("R00", "intra", back))
    # The newest visit was T0 + 120 s: 86,520 s after this image.
    assert pair is None and notice.reason == "clock_jump" and "86520 s" in notice.message
    pair, rej = pb.add(img("R00", "extra", back))
    assert rej is None and pair.stamp_ns == back
    for k in range(1, 5):  # and the following visits pair as usual
        pb.add(img("R00", "intra", back + k * 30 * sec))
        pair, rej = pb.add(img("R00", "extra", back + k * 30 * sec))
        assert rej is None and pair is not None

    va = VisitAssembler(tolerance_ns=MS, history=2)
    for k in range(1, 4):
        for c in CORNERS:
            va.add(CornerEntry(c, T0 + k * 30 * sec, zk(0), True, "ok"), 1.0)
    _, rej = va.add(CornerEntry("R00", T0 - 60 * sec, zk(0), True, "ok"), 1.0)
    assert rej.reason == "late"
    vec, notice = va.add(CornerEntry("R00", back, zk(0), True, "ok"), 1.0)
    assert vec is None and notice.reason == "clock_jump"
    for c in CORNERS[1:]:
        vec, rej = va.add(CornerEntry(c, back, zk(0), True, "ok"), 1.0)
    assert rej is None and vec.complete and vec.stamp_ns == back


def test_unknown_corner_and_side_are_rejected():
    pb = PairingBuffer(corners=("R00",))
    assert pb.add(img("R44", "intra", T0))[1].reason == "unknown_corner"
    assert pb.add(img("R00", "focus", T0))[1].reason == "unknown_side"


def test_a_pair_with_an_undecodable_image_still_forms_and_names_the_problem():
    pb = PairingBuffer()
    bad = img("R00", "intra", T0, error="unsupported_encoding: encoding 'rgb8' ...")
    bad.reason = "unsupported_encoding"
    pb.add(bad)
    pair, _ = pb.add(img("R00", "extra", T0))
    # The pair's reason leads the corner's status; the side's text does not repeat it.
    assert pair.reason == "unsupported_encoding"
    assert pair.error == "intra image: encoding 'rgb8' ..."
    # Two images wrong for different reasons: the second keeps its own tag.
    pb.add(bad := img("R04", "intra", T0, error="unsupported_encoding: encoding 'rgb8' ..."))
    bad.reason = "unsupported_encoding"
    other = img("R04", "extra", T0, error="bad_step: step 3 is less than the row size")
    other.reason = "bad_step"
    pair, _ = pb.add(other)
    assert pair.error == ("intra image: encoding 'rgb8' ...; "
                          "extra image: bad_step: step 3 is less than the row size")


# ------------------------------------------------------------------ assembly
def test_four_corners_make_a_complete_vector_in_layout_order():
    va = VisitAssembler(tolerance_ns=0)
    for c in ("R44", "R00", "R40"):  # arrival order does not matter
        assert va.add(CornerEntry(c, T0, zk(CORNERS.index(c)), True, "ok"), 1.0) == (None, None)
    vec, rej = va.add(CornerEntry("R04", T0, zk(1), True, "ok"), 1.1)
    assert rej is None and vec.complete and vec.stamp_ns == T0
    assert vec.corners == ("R00", "R04", "R40", "R44") and vec.status == "ok"
    assert vec.corner_valid == (True,) * 4
    np.testing.assert_array_equal(vec.zernikes_nm, np.concatenate([zk(i) for i in range(4)]))
    # layout: [19*c + (j-4)]
    assert vec.zernikes_nm[19 * 2 + (7 - 4)] == zk(2)[3]
    assert va.pending_count() == 0


def test_invalid_corner_is_nan_and_named_in_the_status():
    va = VisitAssembler()
    for c in CORNERS:
        ok = c != "R40"
        vec, _ = va.add(CornerEntry(c, T0, zk(0) if ok else None, ok,
                                    "ok" if ok else "non_finite: intra image has 3 NaN"), 0.0)
    assert vec.complete and vec.corner_valid == (True, True, False, True)
    assert np.all(np.isnan(vec.zernikes_nm[38:57]))
    assert np.all(np.isfinite(np.delete(vec.zernikes_nm, np.s_[38:57])))
    assert "R40 non_finite: intra image has 3 NaN" in vec.status
    assert vec.statuses[2].startswith("non_finite")


def test_timeout_publishes_with_missing_corners_invalid_then_late_is_rejected():
    va = VisitAssembler(tolerance_ns=0, timeout_s=2.0)
    va.add(CornerEntry("R00", T0, zk(0), True, "ok"), 10.0)
    va.add(CornerEntry("R44", T0, zk(3), True, "ok"), 10.5)
    assert va.expire(12.0) == []
    (vec,) = va.expire(12.01)
    assert not vec.complete and vec.corner_valid == (True, False, False, True)
    assert vec.statuses[1].startswith("missing") and "R04 missing" in vec.status
    vec2, rej = va.add(CornerEntry("R04", T0, zk(1), True, "ok"), 12.2)
    assert vec2 is None and rej.reason == "late" and "already" not in rej.message
    assert va.pending_count() == 0


def test_a_missing_corner_says_what_became_of_its_images():
    """A visit published at its timeout says, per missing corner, whether one half came
    without the other, the pair was still being estimated, or nothing came: the vector's
    status then agrees with the ``unpaired`` corner published later."""
    pb = PairingBuffer(tolerance_ns=0, timeout_s=5.0)
    va = VisitAssembler(tolerance_ns=0, timeout_s=2.0)
    pb.add(img("R44", "intra", T0, t=10.0))  # its extra image is late
    pb.add(img("R40", "intra", T0, t=10.0))
    pair, _ = pb.add(img("R40", "extra", T0, t=10.1))  # paired; its estimate is slow
    assert pair is not None
    va.add(CornerEntry("R00", T0, zk(0), True, "ok"), 10.5)
    (vec,) = va.expire(12.6, why_missing=pb.why_missing)
    st = dict(zip(CORNERS, vec.statuses, strict=True))
    assert st["R00"] == "ok"
    assert st["R44"] == ("missing: no wavefront within the 2 s visit timeout (its intra image "
                         "came, its extra image had not)")
    assert st["R40"].endswith("(its images were paired, but its estimate had not come back)")
    assert st["R04"].endswith("(none of its images had come)")
    assert "R44 missing: no wavefront within the 2 s visit timeout (its intra" in vec.status


def test_duplicate_corner_in_a_visit_is_rejected():
    va = VisitAssembler()
    va.add(CornerEntry("R00", T0, zk(0), True, "ok"), 0.0)
    _, rej = va.add(CornerEntry("R00", T0, zk(0), True, "ok"), 0.1)
    assert rej.reason == "duplicate"


def test_concurrent_visits_are_kept_apart_and_expire_in_stamp_order():
    va = VisitAssembler(tolerance_ns=0, timeout_s=1.0)
    for k in (1, 0):
        va.add(CornerEntry("R00", T0 + k, zk(0), True, "ok"), 0.0)
    assert va.pending_count() == 2
    vecs = va.expire(5.0)
    assert [v.stamp_ns for v in vecs] == [T0, T0 + 1]


def test_a_valid_entry_without_19_finite_values_is_downgraded():
    va = VisitAssembler()
    bad = {"R00": np.arange(18.0), "R04": np.full(19, np.nan), "R40": None}
    for c in CORNERS:
        z = bad.get(c, zk(3))
        vec, _ = va.add(CornerEntry(c, T0, z, True, "ok"), 0.0)
    assert vec.corner_valid == (False, False, False, True)
    assert all(s.startswith("bad_corner_wavefront") for s in vec.statuses[:3])


def test_unknown_corner_entry_rejected():
    _, rej = VisitAssembler().add(CornerEntry("R22", T0, zk(0), True, "ok"), 0.0)
    assert rej.reason == "unknown_corner"


def test_zernikes_by_noll_reorders_and_checks_completeness():
    noll = list(reversed(NOLL))
    vals = [float(j) for j in noll]
    np.testing.assert_array_equal(zernikes_by_noll(noll, vals), np.arange(4.0, 23.0))
    assert zernikes_by_noll(NOLL[:-1], vals[:-1]) is None
    assert zernikes_by_noll(NOLL, vals[:-1]) is None
    # extra terms (e.g. Z23+) are ignored
    z = zernikes_by_noll([*NOLL, 23], [*range(19), 99.0])
    np.testing.assert_array_equal(z, np.arange(19.0))


def test_corner_fields_come_from_config():
    f = load_corner_fields()
    assert set(f) == set(CORNERS)
    assert f["R00"]["extra"] == pytest.approx((-1.1902777777777778, -1.1902777777777778))
    assert f["R04"]["intra"] == pytest.approx((-1.1903333333333332, 1.2549166666666665))
