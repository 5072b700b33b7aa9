"""ofc_node: the visit's 76-vector in, the 50-DoF active-optics correction out.

Topics and services (relative names; in the root namespace they are the ones below)
----------------------------------------------------------------------------------
in   ``/aos/wfs/wavefront``     cwfs_msgs/WavefrontVector (total wavefront, intrinsic included)
out  ``/aos/ofc/dof_correction`` cwfs_msgs/DofCorrection, one per vector, same header.stamp
in   ``/joint_states``          sensor_msgs/JointState: joint ``camera_rotator``, position [rad]
                                (``rotator_angle_source: topic``)
out  ``/diagnostics``           state, refusal counts and the last reason
srv  ``~/reset``                std_srvs/Trigger: forget the accumulated state (and its file)

A managed (lifecycle) node: the topics, the service and the controller exist from configure
to cleanup; only an active node integrates visits and publishes corrections (docs/ros.md,
Managed nodes). /diagnostics is published in every state.

Per visit, ``controller: kalman`` (default, :class:`cwfs_ros.ofc.kalman.KalmanOFC`): rotate the
camera-frame Zernikes into the telescope frame at the visit's rotator angle, subtract the
design, update a Kalman filter of the DoF state weighted by the corners' reported
uncertainties (directions the corners barely see are dropped and reported), and apply the
correction that minimises the predicted wavefront error over the whole science field within
the step limits and strokes. ``controller: pid`` is ts_ofc's scheme
(:class:`cwfs_ros.ofc.control.OFCSolver`: range-fwhm weights, truncated SVD, PI gains), kept
for comparison; it has no rotator model and refuses a rotated camera. The state is written
atomically to ``state_file`` after every applied visit and read back at start (by default
under ``$ROS_HOME``, :func:`cwfs_ros.ros.params.state_file_path`), so a restarted node
continues and refuses visits it already applied.

The DoF convention is batoid_rubin's (OCS), the one of
``DofCorrection``; both matrix sources are converted to it. A vector with an invalid corner is
refused (valid=false + status) unless ``allow_partial``; so is a vector with a Zernike term
beyond ``max_abs_zernike_nm``, one whose stamp is unset, not newer than the last visit applied
(a repeated or reordered message) or more than ``max_future_s`` ahead of the clock. With
``dry_run`` the correction is computed and published (``dry_run=true``) but the controller
state does not advance, since the correction is not applied.

Input guards (docs/reliability.md), before the solver: a vector with a corner that is a copy
of the same corner of a recently integrated visit (closer than photon noise allows:
``repeated_measurement``) or stamped less than ``min_visit_period_s`` after the last
integrated visit (``too_soon``) is counted and logged (throttled) but gets no DofCorrection,
so that a flood is not passed on; a valid corner beyond the physical bounds of
:mod:`cwfs_ros.ofc.plausibility` (``implausible_wavefront``), with no measurement in it
(``no_measurement``), without the uncertainty its producer reports for the others
(``no_uncertainty``), claiming an uncertainty or pair count no estimate has
(``implausible_uncertainty``), or two corners that are one estimate (``copied_corner``) is
refused like any other refusal. Vectors the subscription queue
dropped are counted from the publishers' sequence numbers; other publishers on the
correction topic are named on /diagnostics. A vector is acted on only while its topic has
exactly ``vector_publishers`` publishers (:class:`~cwfs_ros.ros.common.PublisherTrust`; else
``untrusted_source``, no correction, ERROR on /diagnostics).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np
from cwfs_msgs.msg import DofCorrection, WavefrontVector
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.layout import CORRECTION_TOPIC, JOINT_TOPIC, VECTOR_TOPIC
from cwfs_ros.ofc import control as C
from cwfs_ros.ofc import plausibility as P
from cwfs_ros.ofc.kalman import KALMAN_PARAM_RANGES, KalmanOFC
from cwfs_ros.ofc.model import MEASUREMENT_MODELS
from cwfs_ros.ofc.params import (
    CONTROLLERS,
    controller_from_params,
    refusal,
    restore_record,
    rotator_angle_for,
    state_record,
    step_controller,
)
from cwfs_ros.ofc.persistence import load_state, save_state
from cwfs_ros.ofc.rotator import ROTATOR_JOINT, RotatorHistory
from cwfs_ros.ros.common import (
    DIAGNOSTICS_QOS,
    ERROR,
    OK,
    OUTPUT_QOS,
    WARN,
    ManagedNode,
    PublisherTrust,
    RejectionCounter,
    SequenceGaps,
    bundled_declarer,
    describe,
    diagnostic_status,
    refresh_foreign,
    result,
    stamp_to_ns,
    string_param_problem,
)
from cwfs_ros.ros.convert import dof_correction_msg, vector_from_msg
from cwfs_ros.ros.params import state_file_path
from cwfs_ros.runtime.pipeline import stamp_problem

__all__ = ["OfcNode", "build_solver", "main"]

NODE_NAME = "ofc_node"
MATRIX_SOURCES = C.MATRIX_SOURCES
_SOLVER_PARAMS = ("controller", "band", "matrix_source", "method", "n_modes", "alpha", "weights",
                  "kp", "ki", "dof_mask", "allow_partial", "max_step_scale", "clip_to_range",
                  "max_condition", "max_abs_zernike_nm", "max_future_s", "angle_bin_deg",
                  "measurement_model",
                  *KALMAN_PARAM_RANGES)


# The matrix of a source and the controller of a parameter set live in the core, where the
# offline replay of a bag (cwfs_ros.cli.replay) builds the very same controller.
sensitivity = C.sensitivity_for_source
build_solver = controller_from_params


class OfcNode(ManagedNode):
    """Optical feedback controller node, a lifecycle (managed) node.

    ``autostart`` (default) configures and activates it at once, as ``cwfs-ros bringup``
    does; with ``autostart=False`` it starts unconfigured, with its parameters declared and
    /diagnostics published, and waits for ``configure`` (controller built, state file read,
    topics and ``~/reset`` created) and ``activate``. An inactive node integrates no visit
    and publishes no DofCorrection at all: it counts and logs what it ignores. Keyword
    arguments go to :class:`rclpy.node.Node`.
    """

    def __init__(self, node_name: str = NODE_NAME, *, autostart: bool = True,
                 **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.RLock()
        self.solver: C.OFCSolver | None = None
        self.pub = self.sub = self.sub_joints = self.srv = None
        self._declare_parameters()
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self._diag_timer = self.create_timer(self._param("diagnostics_period_s"),
                                             self.publish_diagnostics)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        if autostart:
            self.start()

    def _configure_resources(self) -> None:
        """configure: the controller, the input guards, the state file and the topics."""
        with self._lock:
            self.solver = build_solver(self._param)
            # ConfigError for limits that would refuse every measurement. Like every guard
            # parameter, the claims' limits are read-only: built once per configure.
            self.claims = self._claims()
            self.dry_run = bool(self._param("dry_run"))
            self.frame_id = str(self._param("frame_id"))
            self._warm(self.solver)
            self._init_guards()
            self.refused = RejectionCounter()
            self.stats = {"vectors": 0, "corrections_valid": 0, "corrections_refused": 0,
                          "resets": 0, "rotator_samples": 0, "rotator_samples_ignored": 0,
                          "state_saves_failed": 0, "vectors_inactive": 0,
                          "vectors_untrusted": 0}
            self.last_status = "none yet"
            self.last_ms = float("nan")
            self.last_result: C.OFCResult | None = None
            self.rotator = RotatorHistory(float(self._param("rotator_tolerance_s")))
            self.state_file = state_file_path(str(self._param("state_file")),
                                              self.get_namespace(), self.get_name())
            self.state_problem: Problem | None = None
            self.save_problem: Problem | None = None
            self._load_state()
        # A managed publisher: whatever path reaches it, nothing goes out unless active.
        self.pub = self.create_lifecycle_publisher(DofCorrection, CORRECTION_TOPIC, OUTPUT_QOS)
        self.trust = PublisherTrust(self, VECTOR_TOPIC, int(self._param("vector_publishers")))
        self.sub = self.create_subscription(WavefrontVector, VECTOR_TOPIC,
                                            self._on_vector_info, OUTPUT_QOS)
        self.trust.attach(self.sub)
        # Joint states come at the rotator's rate: a deeper queue than the outputs', so that a
        # burst around a visit is not lost; reliable, as robot_state_publisher's are.
        self.sub_joints = self.create_subscription(JointState, JOINT_TOPIC, self._on_joints,
                                                   100)
        self.srv = self.create_service(Trigger, "~/reset", self._on_reset)
        self.get_logger().info(
            f"OFC configured: controller {self._param('controller')}, matrix "
            f"{self._param('matrix_source')}, measurement model "
            f"{self._param('measurement_model')}, band {self.solver.band}, rotator "
            f"{self._param('rotator_angle_source')}, allow_partial "
            f"{self.solver.allow_partial}, dry_run {self.dry_run}, state_file "
            f"{self.state_file or '(none)'}")

    def _release_resources(self) -> None:
        """cleanup / shutdown: the topics, the service and the controller (its state is in
        the state file after every applied visit, and read again on configure)."""
        trust = getattr(self, "trust", None)
        if trust is not None:
            trust.detach()  # its event handle before the subscription
        for sub in (self.sub, self.sub_joints):
            if sub is not None:
                self.destroy_subscription(sub)
        if self.srv is not None:
            self.destroy_service(self.srv)
        if self.pub is not None:
            self.destroy_lifecycle_publisher(self.pub)
        self.pub = self.sub = self.sub_joints = self.srv = None
        with self._lock:
            self.solver = None

    def _inactive_effect(self) -> str:
        return "vectors are not integrated and no DofCorrection is published"

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        d = bundled_declarer(self, "ofc_node")
        d("controller", describe(
            "kalman: uncertainty-weighted Kalman filter with the field-optimal correction; "
            "pid: ts_ofc's scheme (range-fwhm weights, truncated SVD, kp/ki), for comparison.",
            constraints=" | ".join(CONTROLLERS)))
        self._declare_kalman(d)
        self._declare_rotator_and_state(d)
        d("band", describe("Band whose intrinsic (design) wavefront is subtracted.",
                                constraints="u | g | r | i | z | y | ref"))
        d("matrix_source", describe(
            "Sensitivity matrix: bundled (this project's, from the batoid simulator) or "
            "ts_ofc (Rubin's, converted to the DofCorrection DoF convention).",
            constraints=" | ".join(MATRIX_SOURCES)))
        d("method", describe("Pseudo-inverse: tsvd (truncated SVD) or tikhonov.",
                                     constraints="tsvd | tikhonov"))
        d("n_modes", describe("Singular modes kept by the truncated SVD.",
                                  int_range=C.OFC_PARAM_RANGES["n_modes"]))
        d("alpha", describe(
            "Tikhonov regulariser, as a fraction of the largest normalised singular value.",
            fp_range=C.OFC_PARAM_RANGES["alpha"]))
        d("weights", describe(
            "DoF normalisation weights: range-fwhm (ts_ofc), range (dof.yaml) or none.",
            constraints="range-fwhm | range | none"))
        d("kp", describe("Proportional gain.", fp_range=C.OFC_PARAM_RANGES["kp"]))
        d("ki", describe("Integral gain (0 = pure P controller).",
                         fp_range=C.OFC_PARAM_RANGES["ki"]))
        d("dof_mask", describe(
            "50 booleans: False DoFs are not used and never move (order of dof.yaml)."))
        d("allow_partial", describe(
            "Use the valid corners only when some are invalid (else refuse the visit)."))
        d("max_step_scale", describe(
            "Per-visit step limit as a multiple of dof.yaml's max_step (0 = no limit).",
            fp_range=C.OFC_PARAM_RANGES["max_step_scale"]))
        d("clip_to_range", describe(
            "Keep the accumulated DoF state within dof.yaml's ranges."))
        d("max_condition", describe(
            "Refuse when the effective condition number of the inverse exceeds this.",
            fp_range=C.OFC_PARAM_RANGES["max_condition"]))
        d("max_abs_zernike_nm", describe(
            "Refuse a visit whose used corners hold a Zernike term beyond this [nm] "
            "(0 = no limit): finite but absurd input is refused, not solved.",
            fp_range=C.OFC_PARAM_RANGES["max_abs_zernike_nm"]))
        d("max_future_s", describe(
            "Refuse a visit stamped more than this ahead of the node's clock [s] (0 = no "
            "limit). Visits not newer than the last applied one are always refused.",
            fp_range=C.OFC_PARAM_RANGES["max_future_s"]))
        d("dry_run", describe(
            "Compute and publish corrections flagged dry_run, without advancing the state."))
        d("frame_id", describe("frame_id of DofCorrection."))
        d("diagnostics_period_s", describe("Period of /diagnostics [s].", read_only=True,
                                                fp_range=(0.05, 60.0)))
        _declare_guard_parameters(d)

    def _declare_kalman(self, d) -> None:
        text = {
            "prior_fraction": "Prior 1-sigma of each DoF after start or ~/reset, x its stroke.",
            "drift_fraction": "1-sigma drift of the state per visit, x the prior sigma.",
            "correction_error": "1-sigma error of an applied correction, x its size (the "
                                "sensitivity model is not the telescope).",
            "min_snr": "State directions one visit sees below this signal-to-noise ratio are "
                       "dropped (not updated, not corrected) and reported.",
            "gain": "Fraction of the field-optimal correction applied per visit.",
            "default_uncertainty_nm": "1-sigma per Zernike term of a corner that reports none "
                                      "[nm].",
            "model_floor_nm": "Added in quadrature to every term's uncertainty [nm].",
            "nis_limit": "Normalised innovation squared per term above which the filter's "
                         "covariance is inflated (the telescope moved).",
            "field_regularization_nm": "Pull of the correction towards the nominal state, nm "
                                       "of field RMS per prior sigma.",
            "max_inconsistency": "Chi-square per term, against every state the DoF strokes "
                                 "allow, above which a visit is refused as inconsistent.",
        }
        for name, what in text.items():
            d(name, describe(f"(kalman) {what}", fp_range=KALMAN_PARAM_RANGES[name]))
        d("angle_bin_deg", describe(
            "(kalman) The model is built per rotator-angle bin of this width [deg] and cached.",
            fp_range=(0.01, 5.0)))
        d("measurement_model", describe(
            "(kalman) design: the corners' Zernikes are compared with the true wavefront's; "
            "estimator: with the wavefront as the estimator reads it (gain, aliasing of "
            "Z23-Z37 and offset, config/ofc/estimator_response_r.npz; band r only). pid "
            "ignores it.",
            constraints=" | ".join(MEASUREMENT_MODELS)))

    def _declare_rotator_and_state(self, d) -> None:
        d("rotator_angle_source", describe(
            "topic: the camera_rotator joint on joint_states at each visit's stamp; fixed: "
            "rotator_angle_deg (a bench without a rotator).", constraints="topic | fixed"))
        d("rotator_angle_deg", describe("Rotator angle with rotator_angle_source fixed [deg].",
                                        fp_range=(-360.0, 360.0)))
        d("rotator_tolerance_s", describe(
            "A visit with no rotator sample within this of its stamp is refused [s].",
            read_only=True, fp_range=(0.001, 3600.0)))
        d("state_file", describe(
            "File the controller state is written to after every applied visit and read at "
            "start; 'auto' = $ROS_HOME/cwfs_ros/<namespace>/<node name>.state.json "
            "($ROS_HOME: ~/.ros), so that a restarted node continues and refuses visits it "
            "already applied; '' = none (a restart forgets them); ~/reset clears it.",
            read_only=True))

    def _validate_parameters(self, params: Sequence[Parameter]) -> SetParametersResult:
        new = {p.name: p.value for p in params}
        src = new.get("rotator_angle_source")
        if src is not None and src not in ("topic", "fixed"):
            return result(False, f"rotator_angle_source must be topic or fixed, got {src!r}")
        for n, v in new.items():
            bad = string_param_problem(n, v)
            if bad is not None:
                return result(False, bad)
        if not any(n in new for n in _SOLVER_PARAMS):
            return result(True)

        def get(n):
            return new[n] if n in new else self._param(n)

        try:
            build_solver(get)
        except (ConfigError, ValueError, TypeError) as exc:
            return result(False, str(exc))
        except Exception as exc:  # noqa: BLE001 - a bad value is refused, never raised
            # (e.g. a weights file that is not YAML: the parser's own error)
            return result(False, f"{type(exc).__name__}: {exc}")
        return result(True)

    def _apply_parameters(self, params: Sequence[Parameter]) -> None:
        names = {p.name for p in params}
        with self._lock:
            if self.solver is None:
                return  # unconfigured: the values are read on configure
            self.dry_run = bool(self._param("dry_run"))
            self.frame_id = str(self._param("frame_id"))
            if names & set(_SOLVER_PARAMS):
                old, new = self.solver, build_solver(self._param)
                kept = restore_record(new, state_record(old))
                self._warm(new)
                self.solver = new
                self.get_logger().info(f"controller rebuilt for {sorted(names)}; kept {kept}")

    # ------------------------------------------------------------------ input guards
    def _init_guards(self) -> None:
        """State of the input guards (docs/reliability.md)."""
        bad = string_param_problem("frame_id", self.frame_id)
        if bad is not None:
            raise ConfigError(f"parameter {bad}")
        old = getattr(self, "guard", None)
        self.guard = P.VisitGuard(self._param("min_visit_period_s"),
                                  copies=self._copy_rule())
        self.guard.refuse_repeats = bool(self._param("refuse_repeats"))
        if old is not None:  # a lifecycle cycle: what was integrated stays integrated
            self.guard.carry_over(old)
        self.queue_gaps = SequenceGaps()
        self.guard_counts = RejectionCounter()
        self._bounds: P.PlausibilityBounds | None = None
        self._plausibility_bounds()  # now, so that the first visit is fast
        self.foreign: list[str] = []
        self.untrusted = RejectionCounter()

    def _on_vector_info(self, msg: WavefrontVector, info) -> None:
        """The subscription's callback: count what the queue dropped, then handle it (or,
        inactive, count and log it as ignored: no state change, no output)."""
        gap = self.queue_gaps.note(info)
        if gap:
            self.guard_counts.add("queue_dropped", f"{gap} vector(s) dropped by the "
                                  "subscription queue (its depth was exceeded)")
            self._log_guard("queue_dropped", f"{gap} vector(s) dropped by the subscription "
                            f"queue before visit {msg.header.stamp.sec}; "
                            f"{self.queue_gaps.dropped} in all")
        if not self.is_active:
            self._ignore_inactive(msg)
            return
        why = self.trust.problem()
        if why is not None:
            self._refuse_untrusted(msg, why)
            return
        self._on_vector(msg)

    def _refuse_untrusted(self, msg: WavefrontVector, why: str) -> None:
        """A vector whose topic has other publishers than expected: not integrated, no
        correction published (an answer per message would pass an impostor's flood on),
        counted, logged (throttled) and ERROR on /diagnostics for a minute."""
        text = (f"visit {msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}: not "
                f"integrated, no correction published: untrusted_source: {why}")
        with self._lock:
            self.stats["vectors"] += 1
            self.stats["vectors_untrusted"] += 1
        self.untrusted.add("untrusted_source", text)
        self.guard_counts.add("untrusted_source", text)
        self._log_guard("untrusted_source", text)

    def _ignore_inactive(self, msg: WavefrontVector) -> None:
        state = self.lifecycle_state
        with self._lock:
            self.stats["vectors_inactive"] += 1
        self.guard_counts.add("inactive", f"visit {msg.header.stamp.sec}: ignored, the node is "
                              f"{state}")
        self._log_guard("inactive", f"{state}: visit {msg.header.stamp.sec}."
                        f"{msg.header.stamp.nanosec:09d} ignored: not integrated, no correction "
                        f"published (activate: cwfs-ros lifecycle set {self.get_name()} "
                        "activate)")

    def _log_guard(self, reason: str, text: str) -> None:
        due, n = self.guard_counts.log_due(reason, float(self._param("log_throttle_s")))
        if due:
            more = f" (+{n} more not logged)" if n else ""
            self.get_logger().warning(text + more)

    def _plausibility_bounds(self) -> P.PlausibilityBounds:
        band, src = str(self._param("band")), str(self._param("matrix_source"))
        margin = float(self._param("plausibility_margin_nm"))
        b = self._bounds
        if b is None or (b.band, b.source, b.margin_nm) != (band, src, margin):
            b = self._bounds = P.physical_bounds(band, src, margin)
        return b

    def _copy_rule(self) -> P.CopyRule:
        return P.CopyRule(float(self._param("repeat_fraction")),
                          float(self._param("repeat_floor_nm")),
                          float(self._param("default_uncertainty_nm")))

    def _claims(self) -> P.Claims:
        return P.Claims(float(self._param("min_uncertainty_nm")),
                        float(self._param("max_uncertainty_nm")), int(self._param("max_pairs")))

    def _guard_vector(self, msg: WavefrontVector, stamp: int) -> tuple[Problem, bool] | None:
        """Why the vector is refused before the solver, or None; with whether to publish the
        refusal (False for a repeat or a visit too soon: answering a flood message by
        message would pass it on)."""
        z, valid, problem = vector_from_msg(msg)
        if problem is not None:
            return None  # the solver path names a layout problem
        unc = np.asarray(msg.uncertainty_nm, dtype=np.float64)
        with self._lock:
            # A visit not newer than the last applied one is named as such (published), before
            # the repeat rule would refuse its measurement silently.
            stale = self.solver.visit_stamp_problem(stamp, None)
            if stale is not None:
                return stale, True
            rate = self.guard.check(stamp, z, valid, unc)
        if not rate.ok:
            self.guard_counts.add(rate.reason, rate.message)
            self._log_guard(rate.reason, f"visit {stamp}: not integrated, no correction "
                            f"published: {rate.status}")
            return Problem(rate.reason, rate.message), False
        v = P.check_vector(z, valid, self._plausibility_bounds(), uncertainty_nm=unc,
                           n_pairs=np.asarray(list(msg.n_pairs)),
                           n_sigma=float(self._param("plausibility_n_sigma")),
                           min_corner_rms_nm=float(self._param("min_corner_rms_nm")),
                           claims=self.claims, copies=self.guard.copies)
        return (Problem(v.reason, v.message), True) if not v.ok else None

    def _note_integrated(self, visit: tuple | None, out: C.OFCResult, dry: bool) -> None:
        """Remember an applied visit ``(stamp, z, valid, uncertainty)`` for the repeat
        rule."""
        if visit is not None and out.valid and not dry:
            with self._lock:
                self.guard.integrated(*visit)

    def _guard_values(self) -> list[tuple[str, str]]:
        self.foreign = refresh_foreign(self, [CORRECTION_TOPIC])
        n_pub = len(self.get_publishers_info_by_topic(self.sub.topic_name))
        values = [(f"guard.{k}", str(v)) for k, v in sorted(self.guard_counts.counts.items())]
        values += [("queue_dropped", str(self.queue_gaps.dropped)
                    + ("" if n_pub <= 1 else f" (estimate: {n_pub} publishers)")),
                   ("min_visit_period_s", str(self.guard.min_period_s)),
                   ("foreign_publishers", "; ".join(self.foreign) or "none")]
        return values + self.trust.key_values("vector_publishers")

    # ------------------------------------------------------------------ control
    def _on_vector(self, msg: WavefrontVector) -> None:
        bad = stamp_problem(msg.header.stamp)
        if bad is not None:
            # No DofCorrection can carry this stamp: refused, counted and logged, and the
            # controller state is not touched (a step whose correction could not be
            # published would leave the state ahead of the telescope).
            with self._lock:
                self.stats["vectors"] += 1
            self._account(f"{msg.header.stamp.sec}.{msg.header.stamp.nanosec}",
                          self._refusal(bad))
            return
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            guard = self._guard_vector(msg, stamp)
        except Exception as exc:  # noqa: BLE001 - a message must never crash the node
            guard = (Problem("internal_error", f"input guard: {type(exc).__name__}: {exc}"), True)
        if guard is not None:
            with self._lock:
                self.stats["vectors"] += 1
            if guard[1]:
                self._publish(stamp, self._refusal(guard[0]), self.dry_run)
            return
        visit = None
        try:
            z, valid, problem = vector_from_msg(msg)
            visit = (stamp, z, valid, np.asarray(msg.uncertainty_nm, dtype=np.float64))
            with self._lock:
                self.stats["vectors"] += 1
                dry = self.dry_run
                now = self.get_clock().now().nanoseconds
                if problem is None:
                    problem = self.state_problem
                if problem is None:
                    # stale or ahead of the clock: said before the rotator is asked (a visit
                    # stamped ahead has no rotator sample either, and that is not its fault)
                    problem = self.solver.visit_stamp_problem(stamp, now)
                angle, why = rotator_angle_for(self._param, self.rotator, stamp)
                before = state_record(self.solver) if self.state_file else None
                out = self._refusal(problem) if problem is not None else step_controller(
                    self.solver, z, valid, uncertainty_nm=visit[3], angle_deg=angle,
                    angle_why=why, stamp_ns=stamp, now_ns=now, dry_run=dry)
                if out.valid and not dry:
                    out = self._persist(out, before, visit)
                self._log_observability_change(out)
                self.last_result = out
        except Exception as exc:  # noqa: BLE001 - a message must never crash the node
            out = self._refusal(Problem("internal_error", f"{type(exc).__name__}: {exc}"))
            dry = self.dry_run
        self._publish(stamp, out, dry)
        self._note_integrated(visit, out, dry)

    # ------------------------------------------------------------------ rotator and state
    def _on_joints(self, msg: JointState) -> None:
        try:
            if ROTATOR_JOINT not in msg.name:
                return
            i = list(msg.name).index(ROTATOR_JOINT)
            bad = stamp_problem(msg.header.stamp)
            why = bad if bad is not None else (
                "no position for camera_rotator" if i >= len(msg.position) else
                self.rotator.add(stamp_to_ns(msg.header.stamp), float(msg.position[i]),
                                 now_ns=self.get_clock().now().nanoseconds,
                                 max_future_s=self.solver.max_future_s))
        except Exception as exc:  # noqa: BLE001 - a message must never crash the node
            why = f"{type(exc).__name__}: {exc}"
        with self._lock:
            self.stats["rotator_samples_ignored" if why else "rotator_samples"] += 1
        if why:
            self.refused.add("rotator_sample_ignored", why)
            self.get_logger().warning(f"rotator sample ignored: {why}",
                                      throttle_duration_sec=10.0)

    def _warm(self, s: C.OFCSolver) -> None:
        """Build what the first visit needs now, so that it is as fast as any other, and say
        which DoF of the mask the corners cannot see at all."""
        self.unseen_dof = ""
        if isinstance(s, KalmanOFC):
            s.warm(0.0)
            obs = s.observability_report()
            names = [s.spec.names[i] for i in np.flatnonzero(s.dof_mask)]
            unseen = [n for n, v in zip(names, obs.dof_visibility, strict=True) if v < 0.1]
            self.unseen_dof = ", ".join(unseen)
            self.get_logger().info(
                f"the four corners observe {obs.n_kept} of {len(names)} state directions "
                f"(min_snr {s.settings.min_snr:g})" + (
                    f"; not seen at all (less than 10 % of the DoF in the kept directions), "
                    f"drop them from dof_mask to stop carrying them: {self.unseen_dof}"
                    if unseen else ""))
        else:
            s.estimate(s.intrinsic_nm)

    def _log_observability_change(self, out: C.OFCResult) -> None:
        last = self.last_result
        if out.valid and (last is None or not last.valid or last.n_dropped != out.n_dropped):
            self.get_logger().info(
                f"{out.n_modes_used} state directions kept, {out.n_dropped} dropped (seen "
                f"below min_snr this visit){': ' + out.dropped if out.dropped else ''}")

    def _load_state(self) -> None:
        if not self.state_file:
            return
        try:
            rec = load_state(self.state_file)
            if rec is None:
                self.get_logger().info(f"no controller state at {self.state_file}: starting "
                                       "from the prior")
                return
            what = restore_record(self.solver, rec)
            n_seen = self.guard.restore(rec.get("integrated"))
            self.get_logger().info(f"controller state restored from {self.state_file}: {what}, "
                                   f"last visit {self.solver.last_stamp_ns} ns, {n_seen} "
                                   "integrated visit(s) for the repeat rule")
        except (ConfigError, ValueError, TypeError, OverflowError) as exc:
            self.solver.reset()  # nothing of a refused file stays in the controller
            # Never act from a state that may be wrong: refuse visits until an operator looks
            # (~/reset starts from the prior and overwrites the file).
            self.state_problem = Problem("state_file_unreadable", str(exc))
            self.get_logger().error(f"{exc}; every visit is refused until ~/reset")

    def _save_state(self, visit: tuple | None = None) -> None:
        """Write the controller state and the integrated visits (``visit``, being applied,
        last) to the state file (OSError if it cannot)."""
        save_state(self.state_file, {**state_record(self.solver),
                                     "integrated": self.guard.record(visit)})

    def _persist(self, out: C.OFCResult, before: dict | None, visit: tuple) -> C.OFCResult:
        """Write the state of an applied visit before its correction is published.

        Saved first, then published: a crash in between loses one correction (the next
        visit's measurement shows it was never applied, and the filter takes that in) rather
        than applying one twice after a restart. The file also holds the integrated visits,
        ``visit`` (stamp, Zernikes, corner validity, uncertainty) included, so that a
        restarted node still refuses their measurements under new stamps. A state that cannot
        be written is not
        applied at all: the controller goes back to ``before`` and the visit is refused, so
        that the file never falls behind what the telescope was told.
        """
        if not self.state_file or before is None:
            return out
        try:
            self._save_state(visit)
            self.save_problem = None
            return out
        except OSError as exc:
            restore_record(self.solver, before)
            self.stats["state_saves_failed"] += 1
            self.save_problem = Problem("state_not_saved", f"{self.state_file}: {exc}")
            self.get_logger().error(f"{self.save_problem}; the visit is not applied",
                                    throttle_duration_sec=10.0)
            return self._refusal(Problem("state_not_saved", f"{self.save_problem.message}; "
                                         "correction withheld (state unchanged)"))

    def _refusal(self, problem: Problem) -> C.OFCResult:
        return refusal(self.solver, problem)

    def _publish(self, stamp: int, out: C.OFCResult, dry: bool) -> None:
        self._account(str(stamp), out)
        msg = dof_correction_msg(
            stamp_ns=stamp, frame_id=self.frame_id, dof=out.dof, dof_total=out.dof_total,
            valid=out.valid, status=out.status, wavefront_rms_nm=out.wavefront_rms_nm,
            predicted_residual_rms_nm=out.predicted_residual_rms_nm, dry_run=dry,
            n_modes_used=out.n_modes_used)
        msg.dof_uncertainty = [float(v) for v in out.dof_uncertainty]
        msg.field_rms_nm = float(out.field_rms_nm)
        msg.predicted_field_rms_nm = float(out.predicted_field_rms_nm)
        msg.rotator_angle_deg = float(out.rotator_angle_deg)
        msg.n_dropped = int(min(out.n_dropped, 65535))
        msg.dropped = out.dropped
        self.pub.publish(msg)

    def _account(self, visit: str, out: C.OFCResult) -> None:
        """Count a visit's result for /diagnostics, and log a refusal with its reason."""
        with self._lock:
            if out.valid:
                self.stats["corrections_valid"] += 1
            else:
                self.stats["corrections_refused"] += 1
            self.last_status = out.status
            self.last_ms = out.elapsed_s * 1e3
        if not out.valid:
            self.refused.add(out.reason, out.status)
            self.get_logger().warning(f"visit {visit}: correction refused: {out.status}")

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        with self._lock:
            n = self.solver.n_steps
            self.solver.reset()
            self.rotator.clear()  # a bad rotator sample must not outlive a reset either
            self.stats["resets"] += 1
            self.state_problem = None
            saved = ""
            if self.state_file:
                try:
                    self._save_state()
                    saved = f"; {self.state_file} holds the cleared state"
                    self.save_problem = None
                except OSError as exc:
                    saved = f"; {self.state_file} NOT updated: {exc}"
                    self.save_problem = Problem("state_not_saved", f"{self.state_file}: {exc}")
        response.success = self.save_problem is None
        response.message = f"controller state cleared (it had accumulated {n} visit(s)){saved}"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self):
        name = f"{self.get_name()}: optical feedback control"
        unconfigured = self.lifecycle_status(name, "aos_ofc")
        if unconfigured is not None:
            return unconfigured
        lifecycle = self.lifecycle_state
        with self._lock:
            stats = dict(self.stats)
            s = self.solver
            if s is None:  # released while this ran
                return self.lifecycle_status(name, "aos_ofc")
            values = [("state", "ready"), ("lifecycle", lifecycle),
                      ("controller", self._param("controller")),
                      ("matrix_source", self._param("matrix_source")),
                      ("measurement_model", self._param("measurement_model")),
                      ("method", s.method), ("n_modes", s.n_modes), ("kp", s.kp), ("ki", s.ki),
                      ("band", s.band), ("allow_partial", s.allow_partial),
                      ("rotator_angle_source", self._param("rotator_angle_source")),
                      ("dof_not_seen", self.unseen_dof or "none"),
                      *self._last_values(),
                      ("dry_run", self.dry_run), ("n_steps", s.n_steps),
                      ("dof_total_norm", f"{np.linalg.norm(s.dof_total):.4g}"),
                      *stats.items(), ("last_status", self.last_status),
                      ("last_step_ms", f"{self.last_ms:.2f}")]
        values += self.refused.key_values()
        values += self._guard_values()
        excess = self.trust.excess()
        if self.state_problem is not None or self.save_problem is not None:
            level, message = ERROR, str(self.state_problem or self.save_problem)
        elif self.untrusted.recent(60.0):
            level, message = ERROR, f"refused a vector: {self.untrusted.last_message}"
        elif excess:
            level, message = ERROR, excess
        elif lifecycle != "active":
            level, message = WARN, f"{lifecycle}: {self._inactive_effect()}"
        elif self.foreign:
            level, message = WARN, f"another publisher on the correction topic: {self.foreign[0]}"
        elif self.refused.recent(10.0):
            level, message = WARN, f"recently refused a visit: {self.refused.last_message}"
        else:
            level, message = OK, "ready"
        return diagnostic_status(name, level, message, values, hardware_id="aos_ofc")

    def _last_values(self) -> list[tuple[str, object]]:
        r = self.last_result
        if r is None or not r.valid:
            return []
        return [("rotator_angle_deg", f"{r.rotator_angle_deg:.3f}"),
                ("field_rms_nm", f"{r.field_rms_nm:.1f}"),
                ("predicted_field_rms_nm", f"{r.predicted_field_rms_nm:.1f}"),
                ("directions_kept", r.n_modes_used), ("directions_dropped", r.n_dropped),
                ("dropped", r.dropped)]



def _declare_guard_parameters(d) -> None:
    """The input guards' parameters (docs/reliability.md)."""
    d("min_visit_period_s", describe(
        "Refuse, without a correction, a visit stamped less than this after the last one "
        "integrated [s]; 0 = off. Survey exposures are at least a 15 s snap plus the 2 s "
        "readout apart, visits ~34-40 s.", fp_range=(0.0, 3600.0)))
    d("refuse_repeats", describe(
        "Refuse, without a correction, a vector with a corner that is a copy of the same "
        "corner of a recently integrated visit (closer than photon noise allows: "
        "repeat_fraction, repeat_floor_nm); false only for benchmarks that replay one "
        "visit's images."))
    d("repeat_fraction", describe(
        "Two estimates closer (rms over a corner's 19 terms) than this x their reported "
        "one-sigma are one measurement sent twice (repeated visits, copied corners).",
        fp_range=(0.0, 0.5)))
    d("repeat_floor_nm", describe(
        "Two estimates closer than this [nm] (rms over a corner's 19 terms) are one "
        "measurement whatever their reported one-sigma.", fp_range=(0.0, 100.0)))
    d("min_uncertainty_nm", describe(
        "A valid corner claiming a per-term one-sigma below this [nm] is refused "
        "(implausible_uncertainty): no estimate knows a term that well.",
        fp_range=(0.0, 1e3)))
    d("max_uncertainty_nm", describe(
        "A valid corner claiming a per-term one-sigma above this [nm] is refused "
        "(implausible_uncertainty): it carries no measurement, and would widen its "
        "plausibility bound by plausibility_n_sigma times as much.", fp_range=(1.0, 1e6)))
    d("max_pairs", describe(
        "A valid corner claiming more donut pairs is refused (implausible_uncertainty); "
        "config/selection.yaml max_pairs.", int_range=(1, 65535)))
    d("plausibility_margin_nm", describe(
        "Added to each term's physical bound (design + most the DoF strokes can add) [nm]: "
        "what the linear 50-DoF model and the estimator leave out.", fp_range=(0.0, 1e6)))
    d("plausibility_n_sigma", describe(
        "Multiple of the reported per-term uncertainty added to each bound.",
        fp_range=(0.0, 100.0)))
    d("min_corner_rms_nm", describe(
        "A valid corner whose 19 terms have a smaller rms carries no measurement [nm].",
        fp_range=(0.0, 100.0)))
    d("log_throttle_s", describe(
        "At most one log line per guard reason per this period [s] (all are counted); "
        "0 = a line each.", fp_range=(0.0, 3600.0)))
    d("vector_publishers", describe(
        "Act on a WavefrontVector only while its topic has exactly this many publishers "
        "(whatever their names; else untrusted_source: not integrated, ERROR on "
        "/diagnostics); 0 = any number.", int_range=(0, 64)))


def main(args: list[str] | None = None) -> int:
    """``ofc_node [--ros-args ...]``: run this node alone (parameters: config/params.yaml)."""
    from cwfs_ros.ros.launch import run_node_main

    return run_node_main(NODE_NAME, args)


if __name__ == "__main__":
    raise SystemExit(main())
