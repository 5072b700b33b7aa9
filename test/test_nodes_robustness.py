"""The nodes over real DDS with bad inputs, timeouts, runtime parameters and the reset service.

Each test has its own rclpy Context and DDS domain (conftest fixtures). The wavefront node
serves one corner (R00) with one worker here, to keep the warm-up short.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import CornerWavefront, DofCorrection, WavefrontVector  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from cwfs_ros.ofc import control as C  # noqa: E402
from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.ros.ofc_node import OfcNode  # noqa: E402
from cwfs_ros.ros.wavefront_node import WavefrontNode  # noqa: E402
from cwfs_ros.runtime.corner_pool import synthetic_donut  # noqa: E402

# Visit stamps in the past of any clock running the tests (ofc_node refuses a visit stamped
# more than max_future_s ahead of its clock).
T = 1_750_000_000_000_000_000
SEC = 1_000_000_000
VISIT = 40 * SEC  # a survey visit's period (ofc_node refuses visits closer than 2 s)


from conftest import of, wait_for  # noqa: E402


def raw_image(stamp, *, h=160, w=160, encoding="32FC1", step=None, data=None):
    m = Image(height=h, width=w, encoding=encoding, step=step if step is not None else w * 4)
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
    m.data = data if data is not None else b"\0" * (m.step * h)
    return m


def test_wavefront_node_never_crashes_on_bad_input(ros_context, spin):
    # The timeout leaves room for DDS: reliable delivery is in order, so one retransmitted
    # fragment of an earlier 100-kB image holds up the next ones on that topic (a 0.6-s
    # timeout once turned the truncated extra image of one visit into "unpaired").
    wf = spin(WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("visit_timeout_s", value=3.0), Parameter("diagnostics_period_s", value=0.2)]))
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = {s: tester.create_publisher(Image, f"aos/wfs/R00/{s}/image", IMAGE_QOS)
           for s in ("intra", "extra")}
    corner, vector, diag = [], [], []
    tester.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront", corner.append,
                               OUTPUT_QOS)
    tester.create_subscription(WavefrontVector, "aos/wfs/wavefront", vector.append, OUTPUT_QOS)
    tester.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 10)
    wait_for(lambda: wf.ready, 60, "warm-up")
    wait_for(lambda: all(p.get_subscription_count() for p in pub.values()), 10, "discovery")

    donut = synthetic_donut(160, 60.0, 0.61)
    good = lambda s: image_msg(donut, s)  # noqa: E731
    nan = donut.copy()
    nan[80, 20:25] = np.nan
    cases = {  # stamp -> (intra, extra, expected status prefix)
        T + 1 * SEC: (raw_image(T, h=1, w=1), raw_image(T, h=1, w=1), "stamp_too_small"),
        T + 2 * SEC: (image_msg(nan, 0), good(0), "non_finite"),
        T + 3 * SEC: (raw_image(0, encoding="rgb8", step=480), good(0), "unsupported_encoding"),
        T + 4 * SEC: (good(0), raw_image(0, step=100), "bad_step"),
        T + 5 * SEC: (good(0), raw_image(0, data=b"\0" * 1000), "truncated_data"),
        T + 6 * SEC: (image_msg(np.zeros((160, 160)), 0), good(0), "flat_or_empty"),
        T + 7 * SEC: (good(0), raw_image(0, encoding="16UC1", data=b"\1" * (160 * 320 + 1),
                                         step=320), "excess_data"),
    }
    for stamp, (intra, extra, _) in cases.items():
        for side, m in (("intra", intra), ("extra", extra)):
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
            pub[side].publish(m)
    unpaired = T + 8 * SEC
    pub["intra"].publish(good(unpaired))
    wait_for(lambda: all(of(corner, s) for s in [*cases, unpaired]), 20, "all corner results")
    for stamp, (_, _, prefix) in cases.items():
        (m,) = of(corner, stamp)
        assert not m.valid and m.status.startswith(prefix), (prefix, m.status)
        assert m.corner == "R00" and np.all(np.isnan(m.zernikes_nm))
    (m,) = of(corner, unpaired)
    assert not m.valid and m.status.startswith("unpaired") and "no extra image" in m.status

    # duplicate (visit already paired) and late (partner already expired) images
    pub["intra"].publish(raw_image(T + 1 * SEC, h=1, w=1))
    pub["extra"].publish(good(unpaired))
    # the vector of each visit times out with R04, R40, R44 missing (served nowhere)
    wait_for(lambda: of(vector, unpaired), 10, "timed-out vector")
    v = of(vector, T + 4 * SEC)[0]
    assert list(v.corner_valid) == [False] * 4
    assert "R00 bad_step" in v.status and "R44 missing" in v.status

    def counts():
        for arr in reversed(list(diag)):
            for st in arr.status:
                if st.name.startswith("wavefront_node"):
                    return {kv.key: kv.value for kv in st.values}
        return {}

    wait_for(lambda: counts().get("rejected.late") == "1"
             and counts().get("rejected.duplicate") == "1"
             and counts().get("visits_incomplete") == str(len(cases) + 1), 5,
             "late + duplicate + incomplete visits counted")
    kv = counts()
    for reason in ("stamp_too_small", "non_finite", "unsupported_encoding", "bad_step",
                   "truncated_data", "flat_or_empty", "excess_data", "unpaired"):
        assert int(kv.get(f"rejected.{reason}", 0)) >= 1, (reason, kv)
    assert kv["state"] == "ready" and kv["corners_invalid"] == str(len(cases) + 1)
    assert int(kv["visits_incomplete"]) == len(cases) + 1
    assert len(corner) == len(cases) + 1  # one result per visit, none for the rejected ones

    # ---- runtime parameters: invalid updates are rejected with a reason
    for name, value, words in [
        ("solver", "bogus", "solver must be one of"),
        ("band", "q", "unknown band"),
        ("instrument", "lsst", "read-only"),  # a file the node reads: set at start only
        ("pairing_tolerance_s", 0.5, "read-only"),  # a safety guard: set at start only
        ("outer_iterations", 1000, "out of range"),
        ("workers", 3, "read-only"),
        ("corners", ["R04"], "read-only"),
        ("sensors.R00.intra.flip", "diagonal", "flip"),
        ("visit_timeout_s", "soon", "type"),
        ("seeing_fwhm_arcsec", -0.5, "out of range"),
    ]:
        (res,) = wf.set_parameters([Parameter(name, value=value)])
        assert not res.successful and words in res.reason, (name, res.reason)
    (res,) = wf.set_parameters([Parameter("band", value="g")])
    assert res.successful and wf.settings.band == "g"
    wait_for(lambda: wf.ready, 30, "re-warm after the band change")
    (res,) = wf.set_parameters([Parameter("sensors.R00.extra.rot90", value=2)])
    assert res.successful and wf.orientations[("R00", "extra")].rot90 == 2
    # The seeing reaches the estimator's settings, without a re-warm (the node stays ready).
    (res,) = wf.set_parameters([Parameter("seeing_fwhm_arcsec", value=0.8)])
    assert res.successful and wf.settings.seeing_fwhm_arcsec == 0.8 and wf.ready


def test_ofc_node_control_reset_dry_run_and_parameters(ros_context, spin):
    # ts_ofc's scheme, so that OFCSolver is the reference; no rotator on this bench
    ofc = spin(OfcNode(context=ros_context, parameter_overrides=[
        Parameter("diagnostics_period_s", value=0.2), Parameter("controller", value="pid"),
        Parameter("rotator_angle_source", value="fixed")]))
    tester = spin(rclpy.create_node("tester", context=ros_context))
    pub = tester.create_publisher(WavefrontVector, "aos/wfs/wavefront", OUTPUT_QOS)
    out: list[DofCorrection] = []
    tester.create_subscription(DofCorrection, "aos/ofc/dof_correction", out.append, OUTPUT_QOS)
    reset = tester.create_client(Trigger, "ofc_node/reset")
    wait_for(lambda: pub.get_subscription_count() > 0 and reset.service_is_ready(), 10,
             "discovery")

    sm = C.SensitivityMatrix.from_bundled()
    ref = C.OFCSolver(sm, band="r")
    x = np.zeros(50)
    x[[0, 5, 9]] = [15.0, -20.0, 0.004]
    y = ref.intrinsic_nm + sm.matrix_nm @ x

    rng = np.random.default_rng(0)

    def send(stamp, z=None, valid=(True,) * 4, corners=("R00", "R04", "R40", "R44")):
        # Each visit its own measurement, with a measurement's noise (a vector within photon
        # noise of one integrated is a repeat, refused), the visits VISIT apart (closer ones
        # are refused as too soon).
        z = y + rng.normal(0.0, 1.0, y.shape) if z is None else z
        m = WavefrontVector()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
        m.zernikes_nm = np.asarray(z, dtype=float)
        m.corner_valid = list(valid)
        m.corners = list(corners)
        seen = len(of(out, stamp))  # a stamp sent again gets a second correction
        pub.publish(m)
        wait_for(lambda: len(of(out, stamp)) > seen, 5, f"correction {stamp}")
        return of(out, stamp)[-1]

    d1 = send(T + 1 * VISIT, z=y)
    expected = ref.step(y)
    assert d1.valid and d1.status == "ok"
    np.testing.assert_allclose(d1.dof, expected.dof, rtol=1e-9, atol=1e-12)
    assert d1.wavefront_rms_nm == pytest.approx(expected.wavefront_rms_nm)
    assert d1.predicted_residual_rms_nm == pytest.approx(expected.predicted_residual_rms_nm)
    d2 = send(T + 2 * VISIT)
    np.testing.assert_allclose(d2.dof_total, np.asarray(d1.dof) + np.asarray(d2.dof))

    # dry run: computed and flagged, the state does not advance
    assert ofc.set_parameters([Parameter("dry_run", value=True)])[0].successful
    z3 = y + rng.normal(0.0, 1.0, y.shape)
    d3 = send(T + 3 * VISIT, z=z3)
    d4 = send(T + 4 * VISIT, z=z3 + rng.normal(0.0, 1e-6, y.shape))  # dry runs: not integrated
    assert d3.dry_run and d4.dry_run and d3.valid
    np.testing.assert_allclose(d3.dof, d4.dof, rtol=1e-7, atol=1e-9)  # 1e-6 nm apart
    np.testing.assert_allclose(d4.dof_total, np.asarray(d2.dof_total) + np.asarray(d4.dof))
    assert ofc.set_parameters([Parameter("dry_run", value=False)])[0].successful

    # refusals: invalid corner, NaN in a valid corner, bad layout
    bad = send(T + 5 * VISIT, valid=(True, True, False, True))
    assert not bad.valid and bad.status.startswith("corner_invalid") and "R40" in bad.status
    z = y + rng.normal(0.0, 1.0, y.shape)  # a new measurement (y itself was visit 1's)
    z[3] = np.nan
    assert send(T + 6 * VISIT, z=z).status.startswith("non_finite")
    lay = send(T + 7 * VISIT, corners=("R04", "R00", "R40", "R44"))
    assert not lay.valid and lay.status.startswith("bad_layout")
    np.testing.assert_allclose(lay.dof_total, d2.dof_total)  # refusals leave the state alone
    # allow_partial is a safety guard: read-only, set at start only
    (res,) = ofc.set_parameters([Parameter("allow_partial", value=True)])
    assert not res.successful and "read-only" in res.reason, res.reason
    assert send(T + 8 * VISIT).valid

    # visit order: a repeated, older or unset stamp is never applied, nor one far ahead of
    # the clock; nor a finite but absurd wavefront (it overflowed the solve into a NaN state)
    before = ofc.solver.state()
    again = send(T + 8 * VISIT)
    assert not again.valid and again.status.startswith("stale_visit") and "again" in again.status
    older = send(T + 4 * VISIT)
    assert not older.valid and older.status.startswith("stale_visit"), older.status
    unset = send(0)
    assert not unset.valid and unset.status.startswith("no_stamp")
    ahead = send(time.time_ns() + 3600 * SEC)
    assert not ahead.valid and ahead.status.startswith("future_stamp"), ahead.status
    huge = send(T + 10 * VISIT, z=np.full(76, 1.7e308))
    assert not huge.valid and huge.status.startswith("implausible_wavefront"), huge.status
    after = ofc.solver.state()
    np.testing.assert_array_equal(after[0], before[0])  # none of them moved the state
    assert after[2:] == before[2:] and np.all(np.isfinite(after[0]))
    assert send(T + 11 * VISIT).valid  # and the loop goes on
    tags = dict(ofc.refused.key_values())
    for tag in ("stale_visit", "no_stamp", "future_stamp", "implausible_wavefront"):
        assert any(tag in k for k in tags), (tag, tags)

    # reset service
    fut = reset.call_async(Trigger.Request())
    wait_for(fut.done, 5, "reset response")
    assert fut.result().success and "cleared" in fut.result().message
    assert np.all(ofc.solver.dof_total == 0) and ofc.solver.n_steps == 0

    # runtime parameters
    for name, value, words in [
        ("dof_mask", [True] * 49, "50"),
        ("dof_mask", [False] * 50, "excludes every DoF"),
        ("matrix_source", "ts_ofc", "read-only"),  # a safety guard: set at start only
        ("measurement_model", "estimator", "read-only"),
        ("method", "pinv", "method"),
        ("band", "q", "band"),
        ("n_modes", 0, "out of range"),
        ("kp", 1.5, "out of range"),
        ("kp", -0.1, "out of range"),
        ("ki", -0.01, "out of range"),
        ("weights", "nonsense", "unknown normalisation weights"),
        ("weights", "../ofc/dof", "unknown normalisation weights"),  # a name, not a path
    ]:
        (res,) = ofc.set_parameters([Parameter(name, value=value)])
        assert not res.successful and words in res.reason, (name, res.reason)
    before = ofc.solver
    assert ofc.set_parameters([Parameter("kp", value=0.3)])[0].successful
    assert ofc.solver is not before and ofc.solver.kp == 0.3  # rebuilt, state kept
    d9 = send(T + 9 * VISIT)
    assert d9.valid
    assert d9.predicted_residual_rms_nm < d9.wavefront_rms_nm


def _corner_msg(c: str, stamp: int, z, valid: bool = True) -> CornerWavefront:
    """A CornerWavefront of corner ``c`` at ``stamp`` (ns) holding Z4..Z22 = ``z``."""
    m = CornerWavefront(corner=c, valid=valid, status="ok" if valid else "x: remote bad")
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, SEC)
    m.noll = list(range(4, 23))
    m.zernikes_nm = [float(v) for v in z]
    return m


def _expire_until_published(wf: WavefrontNode, vectors: list) -> None:
    """Run the node's visit-timeout pass (its 0.1 s timer, called directly) until a vector
    is published, for at most 10 s."""
    deadline = time.monotonic() + 10
    while not vectors and time.monotonic() < deadline:
        wf._expire()
        time.sleep(0.05)


def test_vector_assembled_from_local_and_remote_corner_wavefronts(ros_context, spin):
    """One instance serves R00; R04, R40, R44 come as CornerWavefront from 'elsewhere'."""
    wf = spin(WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("visit_timeout_s", value=5.0)]))
    tester = spin(rclpy.create_node("remote", context=ros_context))
    img = {s: tester.create_publisher(Image, f"aos/wfs/R00/{s}/image", IMAGE_QOS)
           for s in ("intra", "extra")}
    remote = {c: tester.create_publisher(CornerWavefront, f"aos/wfs/{c}/wavefront", OUTPUT_QOS)
              for c in ("R04", "R40", "R44")}
    vectors: list[WavefrontVector] = []
    tester.create_subscription(WavefrontVector, "aos/wfs/wavefront", vectors.append, OUTPUT_QOS)
    wait_for(lambda: wf.ready, 60, "warm-up")
    wait_for(lambda: all(p.get_subscription_count() for p in [*img.values(),
                                                              *remote.values()]), 10,
             "discovery")

    donut = synthetic_donut(160, 60.0, 0.61)
    # A producer on R04's topic that claims R44 (a wrong remapping), and one claiming R00,
    # the corner this node serves: neither may fill that slot.
    remote["R04"].publish(_corner_msg("R44", T, np.full(19, 7777.0)))
    remote["R04"].publish(_corner_msg("R00", T, np.full(19, 8888.0)))
    wait_for(lambda: wf.rejected.counts["corner_mismatch"] == 2, 10, "both mismatches")
    for k, stamp in enumerate((T, T + SEC)):
        for c, pub in remote.items():
            z = np.arange(19.0) + 100 * ("R00", "R04", "R40", "R44").index(c)
            if k == 1 and c == "R40":
                z[3] = np.nan  # flagged valid but unusable
            pub.publish(_corner_msg(c, stamp, z))
        for pub in img.values():
            pub.publish(image_msg(donut, stamp))
    wait_for(lambda: of(vectors, T + SEC), 20, "both vectors")
    (v,) = of(vectors, T)
    assert list(v.corner_valid) == [True] * 4 and v.status == "ok"
    z = np.asarray(v.zernikes_nm)
    for i in (1, 2, 3):
        np.testing.assert_array_equal(z[19 * i:19 * i + 19], np.arange(19.0) + 100 * i)
    assert np.all(np.isfinite(z[:19]))  # R00 estimated locally
    assert not np.any(np.isin(z, (7777.0, 8888.0)))
    (v2,) = of(vectors, T + SEC)
    assert list(v2.corner_valid) == [True, True, False, True]
    assert "R40 bad_corner_wavefront" in v2.status
    # ...and the producer's fault is reported, not only absorbed into the vector.
    assert wf.rejected.counts["bad_corner_wavefront"] == 1, dict(wf.rejected.counts)
    assert "flagged valid" in wf.rejected.last_message


def test_wavefront_node_refuses_to_start_with_a_missing_selection_file(ros_context, tmp_path):
    """The frame path's selection file (detection limits, the fitted noise model) is read by
    the workers at every visit; a mistyped path stops the node at start, naming the file,
    instead of making every frame visit invalid or falling back to built-in numbers."""
    from cwfs_ros.errors import ConfigError

    missing = tmp_path / "no_such_selection.yaml"
    with pytest.raises(ConfigError, match="no_such_selection.yaml"):
        WavefrontNode(context=ros_context, parameter_overrides=[
            Parameter("selection_config", value=str(missing)),
            Parameter("corners", value=["R00"]),
            Parameter("workers", value=1)])


def test_a_failing_visit_timeout_pass_is_reported_not_raised(ros_context):
    """The 0.1 s timer that times visits out runs outside any message callback: if it ever
    raised (a defect), rclpy would stop the node's executor.  Fault injected: the pairing
    buffer's expiry raises; the pass must be counted as an internal error, named, and the
    next pass must run again normally."""
    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1)])
    try:
        real = wf.pairing.expire

        def broken(now):
            raise RuntimeError("injected")

        wf.pairing.expire = broken
        wf._expire()
        assert wf.rejected.counts["internal_error"] == 1
        assert "injected" in wf.rejected.last_message
        wf.pairing.expire = real
        wf._expire()
        assert wf.rejected.counts["internal_error"] == 1
    finally:
        wf.destroy_node()


def _capture(pub) -> list:
    """Every message ``pub`` publishes (the node's own publisher, wrapped in place)."""
    got: list = []
    real = pub.publish

    def publish(msg):
        real(msg)
        got.append(msg)

    pub.publish = publish
    return got


def test_incomplete_visits_and_unusable_stamps_are_reported(ros_context):
    """Callbacks called directly (no DDS needed): a visit published without the corners other
    producers should have sent puts /diagnostics at WARN; an image or remote corner whose
    stamp no output could carry (nanosec >= 1e9) is refused as bad_stamp before pairing,
    with nothing published and nothing raised."""
    from diagnostic_msgs.msg import DiagnosticStatus

    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("visit_timeout_s", value=0.5)])
    try:
        corners, vectors = _capture(wf.pub_corner["R00"]), _capture(wf.pub_vector)
        wait_for(lambda: wf.ready, 60, "warm-up")
        donut = synthetic_donut(160, 60.0, 0.61)
        for s in ("intra", "extra"):
            m = image_msg(donut, T)
            m.header.frame_id = f"camera_R00_{s}"  # the camera's own frame names
            wf._image_callback("R00", s)(m)
        wait_for(lambda: len(corners) == 1, 30, "R00's estimate")
        assert corners[0].valid, corners[0].status
        # The Zernikes are in the focal-plane frame, not the camera's: the node's frame_id.
        assert corners[0].header.frame_id == wf.frame_id == "focal_plane"
        _expire_until_published(wf, vectors)
        (v,) = vectors
        assert list(v.corner_valid) == [True, False, False, False]
        assert not wf.rejected.counts  # nothing was rejected: the others just never came
        d = wf.diagnostics()
        assert d.level == DiagnosticStatus.WARN and "incomplete" in d.message, d.message

        bad = image_msg(donut, T + SEC)
        bad.header.stamp.sec, bad.header.stamp.nanosec = 2**31 - 1, 2**32 - 1
        wf._image_callback("R00", "intra")(bad)
        remote = _corner_msg("R04", 0, np.ones(19))
        remote.header.stamp.nanosec = 1_000_000_000
        wf._remote_corner_callback("R04")(remote)
        assert wf.rejected.counts["bad_stamp"] == 2, dict(wf.rejected.counts)
        assert "nanosec" in wf.rejected.last_message
        assert wf.pairing.pending_count() == 0 and len(corners) == 1 and len(vectors) == 1
    finally:
        wf.destroy_node()


def test_a_worker_lost_during_warm_up_is_warmed_again(ros_context, monkeypatch):
    """A worker that dies while warming up (killed, out of memory) is restarted by the next
    job: the node warms the corner again instead of reporting ERROR for good."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from cwfs_ros.runtime.corner_pool import CornerPool

    real = CornerPool.warm_up
    failed: list[str] = []

    def first_attempt_dies(self, fields, settings, stamp_px=0, **kwargs):
        fresh = [c for c in fields if c not in failed]
        if fresh:
            failed.extend(fresh)
            f: Future = Future()
            f.set_exception(BrokenProcessPool("a child process terminated abruptly"))
            return [f for _ in fresh]
        return real(self, fields, settings, stamp_px, **kwargs)

    monkeypatch.setattr(CornerPool, "warm_up", first_attempt_dies)
    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1)])
    try:
        wait_for(lambda: wf.ready, 60, "the warm-up, retried")
        assert failed == ["R00"]
        assert "error" not in wf.diagnostics().message
    finally:
        wf.destroy_node()


def test_ofc_node_refuses_a_vector_whose_stamp_no_correction_could_carry(ros_context):
    """nanosec >= 1e9: refused before the step (a step whose correction then failed to
    publish would leave the controller state ahead of the telescope), counted, not raised."""
    ofc = OfcNode(context=ros_context, parameter_overrides=[
        Parameter("rotator_angle_source", value="fixed")])
    try:
        sent = _capture(ofc.pub)
        m = WavefrontVector()
        m.header.stamp.sec, m.header.stamp.nanosec = 2**31 - 1, 2**32 - 1
        m.zernikes_nm = np.asarray(ofc.solver.intrinsic_nm, dtype=float)
        m.corner_valid = [True] * 4
        m.corners = ["R00", "R04", "R40", "R44"]
        ofc._on_vector(m)
        assert ofc.refused.counts["bad_stamp"] == 1 and "nanosec" in ofc.last_status
        assert ofc.solver.n_steps == 0 and not sent
        m.header.stamp.sec, m.header.stamp.nanosec = -5, 0  # before 1970: no visit's time
        ofc._on_vector(m)
        assert ofc.refused.counts["bad_stamp"] == 2 and "sec -5 is before 1970" in ofc.last_status
        assert ofc.solver.n_steps == 0 and not sent
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(T, SEC)
        ofc._on_vector(m)  # the same vector, properly stamped, is applied
        assert ofc.solver.n_steps == 1 and len(sent) == 1 and sent[0].valid
    finally:
        ofc.destroy_node()


def test_a_half_visit_closed_by_the_visit_timeout_is_published_on_its_corner(ros_context):
    """A visit started by a remote corner times out while R00's intra image still waits for
    its extra: the image is dropped as unpaired, and R00's topic says so (as when the
    pairing timeout drops it), instead of carrying nothing for that visit."""
    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("visit_timeout_s", value=1.0)])
    try:
        corners, vectors = _capture(wf.pub_corner["R00"]), _capture(wf.pub_vector)
        wait_for(lambda: wf.ready, 60, "warm-up")
        # Only the visit timeout may drop the waiting image here, not its own pairing
        # timeout (the same 1 s by default, half a second later), whatever the machine's pace.
        wf.pairing.timeout_s = 60.0
        wf._remote_corner_callback("R04")(_corner_msg("R04", T, np.ones(19)))
        time.sleep(0.5)
        wf._image_callback("R00", "intra")(image_msg(synthetic_donut(160, 60.0, 0.61), T))
        _expire_until_published(wf, vectors)
        (v,) = vectors
        assert list(v.corner_valid) == [False, True, False, False]
        (m,) = corners
        assert not m.valid and m.status.startswith("unpaired"), m.status
        assert stamp_to_ns(m.header.stamp) == T
        assert dict(wf.rejected.counts) == {"unpaired": 1}
    finally:
        wf.destroy_node()


def test_a_worker_killed_while_warming_up_is_restarted_and_warmed(ros_context):
    """The real fault: the worker process SIGKILLed in the middle of its warm-up. The warm-up
    fails with BrokenProcessPool, the retry restarts the worker, and the node gets ready."""
    import os
    import signal

    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1)])
    try:
        pids: list[int] = []

        def worker_started() -> bool:
            ex = wf.pool._slots[0]
            procs = getattr(ex, "_processes", None) or {}
            pids.extend(procs)
            return bool(pids)

        wait_for(worker_started, 30, "the worker process")
        assert not wf.ready  # the warm-up (seconds) is still running
        os.kill(pids[0], signal.SIGKILL)
        wait_for(lambda: wf.ready, 90, "the warm-up, retried on a restarted worker")
        assert wf.pool.restarts == 1
        assert "error" not in wf.diagnostics().message
    finally:
        wf.destroy_node()
