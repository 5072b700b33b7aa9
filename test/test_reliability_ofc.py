"""ofc_node's input guards: physical plausibility, no measurement, uncertainty, one
measurement one correction, the minimum visit period, queue drops and other publishers.

The bounds are checked against the sensitivity matrix and dof.yaml read here with numpy
(not through the module under test); the node runs over real DDS (conftest fixtures).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from cwfs_ros.ofc import control as C
from cwfs_ros.ofc import plausibility as P

T = 1_750_000_000_000_000_000
SEC = 1_000_000_000
VISIT = 40 * SEC


@pytest.fixture(scope="module")
def bounds() -> P.PlausibilityBounds:
    return P.physical_bounds("r", "bundled", 300.0)


def _genuine(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """A vector some telescope state within the strokes gives (linear model)."""
    a = C.SensitivityMatrix.from_bundled().matrix_nm
    rng_ = C.load_dof_spec().range
    x = rng.uniform(-1, 1, 50) * rng_ * scale
    return C.intrinsic_vector_nm("r", C.SensitivityMatrix.from_bundled().field_points_deg) \
        + a @ x


def test_bounds_are_design_plus_reach_plus_margin(bounds):
    a = C.SensitivityMatrix.from_bundled().matrix_nm
    spec = C.load_dof_spec()
    # The largest |A_i x| over the box is at a vertex: x_j = range_j sign(A_ij).
    vertex = np.abs(a @ (spec.range[None, :] * np.sign(a)).T).diagonal().reshape(4, 19).copy()
    # The rotator mixes each azimuthal (cos, sin) pair of a corner: both terms are bounded by
    # the pair's norm. Noll pairs among Z4..Z22 (Noll's table): 5-6, 7-8, 9-10, 12-13, 14-15,
    # 16-17, 18-19, 20-21.
    for j, k in ((5, 6), (7, 8), (9, 10), (12, 13), (14, 15), (16, 17), (18, 19), (20, 21)):
        h = np.hypot(vertex[:, j - 4], vertex[:, k - 4])
        vertex[:, j - 4] = vertex[:, k - 4] = h
    np.testing.assert_allclose(bounds.reach_nm, vertex.reshape(-1), rtol=1e-12)
    assert np.all(bounds.bound_nm() >= bounds.reach_nm + 300.0)
    u = np.full(76, 10.0)
    np.testing.assert_allclose(bounds.bound_nm(u, 5.0) - bounds.bound_nm(), 50.0)


def test_every_state_within_the_strokes_is_plausible(bounds):
    rng = np.random.default_rng(1)
    for _ in range(200):
        z = _genuine(rng)
        assert P.check_vector(z, np.ones(4, bool), bounds).ok


def test_19999_nm_everywhere_is_implausible(bounds):
    for sign in (1.0, -1.0):
        v = P.check_vector(np.full(76, 19999.0 * sign), np.ones(4, bool), bounds)
        assert not v.ok and v.reason == "implausible_wavefront" and "R00" in v.message
    # ... and one corner out of range is enough; an invalid corner is not judged.
    z = _genuine(np.random.default_rng(2))
    z[19 + 18] = 5000.0  # R04 Z22: no DoF within its stroke gives that
    assert P.check_vector(z, np.ones(4, bool), bounds).reason == "implausible_wavefront"
    assert P.check_vector(z, np.array([True, False, True, True]), bounds).ok


@pytest.mark.parametrize("fill", [1e-30, 5e-324, 0.0])
def test_a_valid_corner_with_no_measurement_is_refused(bounds, fill):
    z = _genuine(np.random.default_rng(3))
    z[38:57] = fill
    if fill == 0.0:
        z[40] = 1e-9  # zeros plus 1e-9: not "all exactly zero"
    v = P.check_vector(z, np.ones(4, bool), bounds)
    assert not v.ok and v.reason == "no_measurement" and "R40" in v.message


def test_uncertainty_required_only_from_a_producer_that_reports_it(bounds):
    z = _genuine(np.random.default_rng(4))
    ones = np.ones(4, bool)
    assert P.check_vector(z, ones, bounds, uncertainty_nm=np.zeros(76),
                          n_pairs=np.zeros(4)).ok  # nothing reported (hand-built vectors)
    unc = np.full(76, 8.0)
    pairs = np.array([1, 1, 1, 1])
    assert P.check_vector(z, ones, bounds, uncertainty_nm=unc, n_pairs=pairs).ok
    unc[19:38] = 0.0
    v = P.check_vector(z, ones, bounds, uncertainty_nm=unc, n_pairs=pairs)
    assert v.reason == "no_uncertainty" and "R04" in v.message
    v = P.check_vector(z, ones, bounds, uncertainty_nm=np.full(76, 8.0),
                       n_pairs=np.array([1, 1, 0, 1]))
    assert v.reason == "no_uncertainty" and "R40" in v.message


def test_visit_guard_repeats_and_period():
    g = P.VisitGuard(min_period_s=2.0)
    z = np.arange(76.0)
    ones = np.ones(4, bool)
    assert g.check(T, z, ones).ok
    g.integrated(T, z, ones)
    assert g.check(T + VISIT, z, ones).reason == "repeated_measurement"
    assert g.check(T + VISIT, z + 1e-9, ones).reason == "repeated_measurement"
    z2 = z + np.random.default_rng(0).normal(0, 5.0, 76)  # a new measurement
    assert g.check(T + 1_000_000, z2, ones).reason == "too_soon"  # 1 ms later
    assert g.check(T + 2 * SEC + 1, z2, ones).ok


# ------------------------------------------------------------------ the node over DDS
rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.ofc_node import OfcNode  # noqa: E402


def _vector(stamp: int, z: np.ndarray, unc=None, pairs=None) -> WavefrontVector:
    m = WavefrontVector()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
    m.zernikes_nm = np.asarray(z, dtype=float)
    m.corner_valid = [True] * 4
    m.corners = ["R00", "R04", "R40", "R44"]
    if unc is not None:
        m.uncertainty_nm = np.asarray(unc, dtype=float)
    if pairs is not None:
        m.n_pairs = list(pairs)
    return m


def _ofc_and_tester(ros_context, spin):
    """An ofc_node without a rotator (rotator_angle_source fixed) and a tester's publisher of
    vectors and recorder of corrections, discovered."""
    from conftest import wait_for

    ofc = spin(OfcNode(context=ros_context, parameter_overrides=[
        Parameter("rotator_angle_source", value="fixed")]))
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    out: list[DofCorrection] = []
    tester.create_subscription(DofCorrection, "aos/ofc/dof_correction", out.append, OUTPUT_QOS)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    return ofc, pub, out


def test_node_integrates_a_restamped_flood_once(ros_context, spin):
    """30 re-stamped copies of one vector 1 ms apart, then 30 distinct vectors 1 ms apart:
    one correction is integrated; the rest get none and are counted."""
    from conftest import wait_for

    ofc, pub, out = _ofc_and_tester(ros_context, spin)
    rng = np.random.default_rng(5)
    z = _genuine(rng, 1e-3)
    for k in range(30):
        pub.publish(_vector(T + k * 1_000_000, z))
        time.sleep(0.01)  # within the subscription's queue
    for k in range(30):
        pub.publish(_vector(T + (100 + k) * 1_000_000, z + rng.normal(0, 1.0, 76)))
        time.sleep(0.01)
    wait_for(lambda: sum(ofc.guard_counts.counts.values()) >= 59, 10, "the guards' counts")
    time.sleep(0.3)
    valid = [m for m in out if m.valid]
    assert len(valid) == 1 and stamp_to_ns(valid[0].header.stamp) == T
    assert len(out) == 1  # no refusal published for a repeat or a visit too soon
    assert ofc.guard_counts.counts["repeated_measurement"] == 29
    assert ofc.guard_counts.counts["too_soon"] == 30
    assert ofc.solver.n_steps == 1
    kv = {x.key: x.value for x in ofc.diagnostics().values}
    assert kv["guard.too_soon"] == "30" and kv["guard.repeated_measurement"] == "29"


def test_node_refuses_implausible_and_unmeasured_corners(ros_context, spin):
    from conftest import wait_for

    ofc, pub, out = _ofc_and_tester(ros_context, spin)
    rng = np.random.default_rng(6)
    cases = []
    cases.append((np.full(76, 19999.0), None, None, "implausible_wavefront"))
    for fill in (1e-30, 5e-324):
        z = _genuine(rng, 1e-3)
        z[:19] = fill
        cases.append((z, None, None, "no_measurement"))
    z = _genuine(rng, 1e-3)
    unc = np.full(76, 9.0)
    unc[57:] = 0.0
    cases.append((z, unc, [1, 1, 1, 1], "no_uncertainty"))
    cases.append((_genuine(rng, 1e-3), np.full(76, 9.0), [1, 3, 1, 1], ""))
    for k, (z, u, p, reason) in enumerate(cases):
        stamp = T + (k + 1) * VISIT
        pub.publish(_vector(stamp, z, u, p))
        wait_for(lambda s=stamp: any(stamp_to_ns(m.header.stamp) == s for m in out), 5,
                 f"answer to case {k}")
        (m,) = [m for m in out if stamp_to_ns(m.header.stamp) == stamp]
        if reason:
            assert not m.valid and m.status.startswith(reason), (reason, m.status)
            assert np.all(np.asarray(m.dof) == 0.0)
        else:
            assert m.valid, m.status
    assert ofc.solver.n_steps == 1


def test_node_counts_what_its_queue_dropped(ros_context, spin):
    """A burst far beyond the subscription's depth while the node's executor is busy: the
    vectors never taken are counted from the sequence numbers (DDS reports none)."""
    from conftest import wait_for

    ofc = spin(OfcNode(context=ros_context, parameter_overrides=[
        Parameter("min_visit_period_s", value=0.0),
        Parameter("rotator_angle_source", value="fixed")]))
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE))
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    rng = np.random.default_rng(7)
    z = _genuine(rng, 1e-3)
    taken = []
    orig = ofc._on_vector

    def slow(msg):  # a busy controller: 20 ms a visit
        taken.append(stamp_to_ns(msg.header.stamp))
        time.sleep(0.02)
        orig(msg)

    ofc._on_vector = slow
    # The count starts at the first message taken (a reader that joins late sees a writer's
    # numbers from where it is): one visit, taken, then the burst.
    pub.publish(_vector(T, z))
    wait_for(lambda: len(taken) == 1, 10, "the first visit taken")
    n = 150
    for k in range(1, n + 1):
        pub.publish(_vector(T + k * VISIT, z + rng.normal(0, 1.0, 76)))
    wait_for(lambda: len(taken) - 1 + ofc.queue_gaps.dropped >= n, 20, "all accounted for")
    time.sleep(0.5)
    assert ofc.queue_gaps.dropped > 0
    assert len(taken) - 1 + ofc.queue_gaps.dropped == n  # each one taken or counted
    kv = {x.key: x.value for x in ofc.diagnostics().values}
    assert kv["queue_dropped"].split()[0] == str(ofc.queue_gaps.dropped)


def test_node_names_another_publisher_on_its_correction_topic(ros_context, spin):
    from conftest import wait_for

    ofc = spin(OfcNode(context=ros_context))
    assert {x.key: x.value for x in ofc.diagnostics().values}["foreign_publishers"] == "none"
    impostor = spin(rclpy.create_node("impostor", context=ros_context))
    impostor.create_publisher(DofCorrection, "aos/ofc/dof_correction", OUTPUT_QOS)

    def named():
        st = ofc.diagnostics()
        return "impostor" in {x.key: x.value for x in st.values}["foreign_publishers"]

    wait_for(named, 10, "the other publisher named")
    st = ofc.diagnostics()
    assert st.level == st.WARN and "impostor" in st.message


def test_frame_id_parameter_length_is_limited(ros_context, spin):
    ofc = spin(OfcNode(context=ros_context))
    (res,) = ofc.set_parameters([Parameter("frame_id", value="x" * 1_000_000)])
    assert not res.successful and "at most 256" in res.reason
    for bad in ("bad/id\\n", "/telescope", "tele scope", "a//b", ""):
        (res,) = ofc.set_parameters([Parameter("frame_id", value=bad)])
        assert not res.successful and "is not a frame name" in res.reason, (bad, res.reason)
    assert ofc.frame_id == "telescope"
    (res,) = ofc.set_parameters([Parameter("frame_id", value="telescope_2")])
    assert res.successful
    (res,) = ofc.set_parameters([Parameter("frame_id", value="lsst/telescope_2")])
    assert res.successful
