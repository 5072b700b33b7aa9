"""ofc_node over DDS: what a measurement may be (docs/reliability.md). A re-sent
measurement with a jitter far below the noise, a corner replayed inside new data, corners
copied into one another, uncertainties and pair counts no estimate has, and visits closer
than the survey cadence (the default minimum period, 15 s): no valid correction from any;
genuine visits a cadence apart are integrated.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from cwfs_ros.errors import ConfigError
from cwfs_ros.ofc import control as C

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import DofCorrection, WavefrontVector  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from cwfs_ros.ros.common import OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.ofc_node import OfcNode  # noqa: E402

T = 1_750_000_000_000_000_000
SEC = 1_000_000_000
VISIT = 40 * SEC


def _state_vector(rng: np.random.Generator) -> np.ndarray:
    sm = C.SensitivityMatrix.from_bundled()
    x = rng.uniform(-1, 1, 50) * C.load_dof_spec().range * 0.01
    return C.intrinsic_vector_nm("r", sm.field_points_deg) + sm.matrix_nm @ x


def _vector(stamp: int, z: np.ndarray, unc: np.ndarray, pairs=(1, 1, 1, 1)) -> WavefrontVector:
    m = WavefrontVector()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
    m.zernikes_nm = np.asarray(z, dtype=float)
    m.corner_valid = [True] * 4
    m.corners = ["R00", "R04", "R40", "R44"]
    m.uncertainty_nm = np.asarray(unc, dtype=float)
    m.n_pairs = list(pairs)
    return m


def _tester(ros_context, spin) -> tuple:
    """A tester node's publisher of vectors and the list of corrections it records."""
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    out: list[DofCorrection] = []
    tester.create_subscription(DofCorrection, "aos/ofc/dof_correction", out.append, OUTPUT_QOS)
    return pub, out


def _answer(out: list[DofCorrection], stamp: int) -> DofCorrection:
    """The one correction published for ``stamp``, waited for."""
    from conftest import wait_for

    wait_for(lambda: any(stamp_to_ns(m.header.stamp) == stamp for m in out), 5,
             f"the answer to {stamp}")
    (m,) = [m for m in out if stamp_to_ns(m.header.stamp) == stamp]
    return m


def test_node_refuses_what_no_measurement_is(ros_context, spin):
    from conftest import wait_for

    ofc = spin(OfcNode(context=ros_context, parameter_overrides=[
        Parameter("rotator_angle_source", value="fixed")]))
    pub, out = _tester(ros_context, spin)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    rng = np.random.default_rng(11)
    truth = _state_vector(rng)
    unc = np.full(76, 12.0)

    def measured() -> np.ndarray:
        return truth + rng.normal(0, 8.0, 76)

    first = measured()
    pub.publish(_vector(T, first, unc))
    assert _answer(out, T).valid
    # The same measurement re-sent with 1e-9 nm of noise every 20 s, past the period, and one
    # corner of it inside otherwise new data: nothing integrated, no correction published.
    silent = []
    for k in range(1, 4):
        silent.append(T + k * 20 * SEC)
        pub.publish(_vector(silent[-1], first + rng.normal(0, 1e-9, 76), unc))
        time.sleep(0.05)
    mixed = measured()
    mixed[57:] = first[57:] + rng.normal(0, 1e-9, 19)
    silent.append(T + 80 * SEC)
    pub.publish(_vector(silent[-1], mixed, unc))
    wait_for(lambda: ofc.guard_counts.counts.get("repeated_measurement", 0) == 4, 5,
             "four repeats counted")
    # A genuine visit 5 s after an integrated one is too soon under the default period
    # (15 s); 20 s later it is integrated.
    s_ok = T + 100 * SEC
    pub.publish(_vector(s_ok, measured(), unc))
    assert _answer(out, s_ok).valid
    silent.append(s_ok + 5 * SEC)
    pub.publish(_vector(silent[-1], measured(), unc))
    wait_for(lambda: ofc.guard_counts.counts.get("too_soon", 0) == 1, 5, "too soon counted")
    s_ok2 = s_ok + 20 * SEC
    pub.publish(_vector(s_ok2, measured(), unc))
    assert _answer(out, s_ok2).valid
    # Refused with a published reason: corners copied into one another, and claims no
    # estimate makes (the +5000 nm would be within the bound 5 x 1e4 nm would widen).
    cases = []
    z = measured()
    z[19:38] = z[:19]
    cases.append((z, unc, (1, 1, 1, 1), "copied_corner"))
    z = measured()
    z = np.tile(z[:19], 4) + rng.normal(0, 1e-9, 76)
    cases.append((z, unc, (1, 1, 1, 1), "copied_corner"))
    z = measured()
    z[:19] += 5000.0
    cases.append((z, np.full(76, 1e4), (1, 1, 1, 1), "implausible_uncertainty"))
    cases.append((measured(), np.full(76, 5e-324), (1, 1, 1, 1), "implausible_uncertainty"))
    cases.append((measured(), unc, (1, 65535, 1, 1), "implausible_uncertainty"))
    for k, (z, u, p, reason) in enumerate(cases):
        stamp = s_ok2 + (k + 1) * VISIT
        pub.publish(_vector(stamp, z, u, p))
        m = _answer(out, stamp)
        assert not m.valid and m.status.startswith(reason), (k, reason, m.status)
        assert not np.any(np.asarray(m.dof))
    time.sleep(0.3)
    assert not any(stamp_to_ns(m.header.stamp) in silent for m in out)
    assert [m.valid for m in out].count(True) == 3
    assert ofc.solver.n_steps == 3
    kv = {x.key: x.value for x in ofc.diagnostics().values}
    assert kv["guard.repeated_measurement"] == "4" and kv["guard.too_soon"] == "1"
    assert kv["min_visit_period_s"] == "15.0"


def test_uncertainty_limits_must_leave_room(ros_context, spin):
    """The limits are read-only guards; a node started with limits that would refuse every
    reported one-sigma does not configure."""
    ofc = spin(OfcNode(context=ros_context))
    (res,) = ofc.set_parameters([Parameter("max_uncertainty_nm", value=500.0)])
    assert not res.successful and "read-only" in res.reason
    assert ofc.get_parameter("max_uncertainty_nm").value == 2000.0
    with pytest.raises(ConfigError, match="min_uncertainty_nm"):
        OfcNode(context=ros_context, parameter_overrides=[
            Parameter("min_uncertainty_nm", value=900.0),
            Parameter("max_uncertainty_nm", value=500.0)])


def test_a_lifecycle_cycle_keeps_what_was_integrated(ros_context, spin, tmp_path):
    """Deactivate, clean up, configure and activate (any process can ask for them): the
    measurement integrated before the cycle, re-sent under a new stamp, is still a repeat."""
    from conftest import wait_for
    from rclpy.lifecycle import TransitionCallbackReturn

    ofc = spin(OfcNode(context=ros_context, parameter_overrides=[
        Parameter("rotator_angle_source", value="fixed"),
        Parameter("state_file", value=str(tmp_path / "ofc.state.json"))]))
    pub, out = _tester(ros_context, spin)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    rng = np.random.default_rng(5)
    a = _state_vector(rng) + rng.normal(0, 8.0, 76)
    unc = np.full(76, 12.0)
    pub.publish(_vector(T, a, unc))
    assert _answer(out, T).valid
    for step in (ofc.trigger_deactivate, ofc.trigger_cleanup, ofc.trigger_configure,
                 ofc.trigger_activate):
        assert step() == TransitionCallbackReturn.SUCCESS
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery again")
    pub.publish(_vector(T + VISIT, a, unc))
    wait_for(lambda: ofc.guard_counts.counts.get("repeated_measurement", 0) == 1, 5,
             "the repeat counted")
    assert not any(stamp_to_ns(m.header.stamp) == T + VISIT and m.valid for m in out)


def test_a_restarted_node_still_refuses_a_measurement_it_integrated(ros_context, spin,
                                                                    tmp_path):
    """The state file holds the integrated visits: the same measurement under a new stamp,
    sent to the node that restarts from the file, is a repeat; a new one is integrated."""
    from conftest import wait_for

    state = str(tmp_path / "ofc.state.json")
    over = [Parameter("rotator_angle_source", value="fixed"),
            Parameter("state_file", value=state)]
    pub, out = _tester(ros_context, spin)

    rng = np.random.default_rng(8)
    truth = _state_vector(rng)
    a = truth + rng.normal(0, 8.0, 76)
    unc = np.full(76, 12.0)
    first = spin(OfcNode(context=ros_context, parameter_overrides=over))
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery")
    pub.publish(_vector(T, a, unc))
    assert _answer(out, T).valid
    first.trigger_deactivate()
    first.trigger_cleanup()  # its subscription gone: the file is all the next one has
    wait_for(lambda: pub.get_subscription_count() == 0, 10, "the node gone")
    second = spin(OfcNode(context=ros_context, parameter_overrides=over))
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "discovery again")
    pub.publish(_vector(T + VISIT, a, unc))
    wait_for(lambda: second.guard_counts.counts.get("repeated_measurement", 0) == 1, 5,
             "the repeat counted")
    pub.publish(_vector(T + 2 * VISIT, truth + rng.normal(0, 8.0, 76), unc))
    assert _answer(out, T + 2 * VISIT).valid
    assert not any(stamp_to_ns(m.header.stamp) == T + VISIT and m.valid for m in out)
