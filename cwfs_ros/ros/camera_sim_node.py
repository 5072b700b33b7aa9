"""camera_sim_node: a ray-traced Rubin/LSST corner-sensor camera that obeys the OFC.

Topics and services (relative names; in the root namespace they are the ones below)
----------------------------------------------------------------------------------
out  ``/aos/wfs/<corner>/<intra|extra>/image``  sensor_msgs/Image 32FC1, the 8 stamps of a
     visit (4 corners x intra (SW1, detector -1.5 mm) / extra (SW0, +1.5 mm)), all with the
     same ``header.stamp``
out  ``/aos/sim/truth``          cwfs_msgs/SimTruth, same stamp: DoF state, true total and
     intrinsic Zernikes at the corner mid points in the camera frame (layout of
     WavefrontVector), visit number, rotator angle, and the corner and field figures
     (``cwfs_ros.sim.field_truth``: field wavefront error, optical FWHM)
out  ``/joint_states``           sensor_msgs/JointState, joint ``camera_rotator``, position
     [rad] = ``rotator_angle_deg`` of the visit, stamped with the visit's stamp and published
     before its images
in   ``/aos/ofc/dof_correction`` cwfs_msgs/DofCorrection: a valid, non-dry-run correction is
     added to the DoF state (used from the next rendered visit), only if its stamp is a visit
     this node published and has not corrected yet, and each |step| is within dof.yaml's
     max_step x ``correction_max_step_scale`` (``not_our_visit``, ``already_corrected``,
     ``step_limit``), and only while the topic has exactly ``correction_publishers``
     publishers (``untrusted_source``, ERROR on /diagnostics): nothing else on the topic can
     move the telescope
out  ``/diagnostics``            state, visits rendered/skipped, corrections applied/ignored,
     other publishers on its image and truth topics
srv  ``~/trigger``               std_srvs/Trigger: render one visit now (the only way when
     ``visit_period_s`` is 0)

The telescope is :func:`cwfs_ros.sim.perturbed_telescope` at the current 50-DoF state (ts_ofc
order and units, the batoid_rubin sign convention of ``DofCorrection``) with the camera rotated
by ``rotator_angle_deg`` (batoid_rubin's ``with_rtp``; read at the start of each visit): each
corner sensor's donuts are traced at the telescope field ``R(angle) f`` of its nominal field
``f`` and imaged in the rotated camera's own frame (:mod:`cwfs_ros.ofc.rotation`). Each visit is
rendered by :func:`cwfs_ros.sim.render_donut` (photon tracing, random sub-stamp offsets,
Poisson noise, sky subtracted) in a background thread, so the executor is never blocked;
visits never overlap, and a period that falls while a visit is still rendering is skipped
(logged and counted).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from cwfs_msgs.msg import DofCorrection, SimTruth
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image, JointState
from std_srvs.srv import Trigger

from cwfs_ros.layout import CORNERS, CORRECTION_TOPIC, N_DOF, SIDES, TRUTH_TOPIC, image_topic
from cwfs_ros.ofc.rotation import telescope_field_deg
from cwfs_ros.ros.common import (
    DIAGNOSTICS_QOS,
    ERROR,
    IMAGE_QOS,
    OK,
    OUTPUT_QOS,
    WARN,
    NodeBasics,
    PublisherTrust,
    RejectionCounter,
    bundled_declarer,
    describe,
    diagnostic_status,
    ns_to_stamp,
    refresh_foreign,
    result,
    stamp_to_ns,
)
from cwfs_ros.ros.convert import image_msg
from cwfs_ros.runtime.corner_pool import guard_pool_workers
from cwfs_ros.runtime.pipeline import served_corners
from cwfs_ros.sim.field_truth import field_truth
from cwfs_ros.sim.perturbation import RIGID_SCALE, wavefront_error_nm
from cwfs_ros.sim.telescope import BANDS
from cwfs_ros.sim.visit import (
    DonutSpec,
    FrameScene,
    frame_specs,
    make_render_pool,
    render_frames,
    render_visit,
)
from cwfs_ros.wfs.blur import MAX_SEEING_FWHM_ARCSEC

__all__ = ["CameraSimNode", "N_DOF", "RIGID_SCALE", "SIDES", "main"]

NODE_NAME = "camera_sim_node"
JOINT_STATES_TOPIC = "joint_states"
ROTATOR_JOINT = "camera_rotator"
# ``declare(name, descriptor)`` of :func:`~cwfs_ros.ros.common.bundled_declarer`.
Declare = Callable[[str, ParameterDescriptor], Any]
ROTATOR_RANGE_DEG = (-270.0, 270.0)


def band_wavelength_nm(band: str) -> float:
    """Effective wavelength of ``band`` from config/instruments/lsst.yaml (as ts_wep uses)."""
    from cwfs_ros.wfs.instrument import load_instrument

    return float(load_instrument("lsst").wavelength_nm(band))


class CameraSimNode(NodeBasics, Node):
    """Simulated corner-sensor camera with a 50-DoF telescope state driven by DofCorrection."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.RLock()
        self._declare_parameters()
        self._init_optics()
        # Its workers end with this process, even one killed outright (docs/reliability.md).
        self._pool = guard_pool_workers(make_render_pool(int(self._param("render_workers"))))
        self.stats = {"visits_rendered": 0, "visits_skipped": 0, "visits_failed": 0,
                      "corrections_applied": 0, "corrections_ignored": 0}
        self.ignored = RejectionCounter()
        self._init_correction_guard()
        self.visit = 0
        self.last_render_s = float("nan")
        self.last_status = "no visit yet"
        self.last_frame_stars: dict = {}
        self.last_true_error_nm = float("nan")
        self.last_field_error_nm = float("nan")
        self.last_fwhm_arcsec = float("nan")
        self.last_rotator_angle_deg = float(self._param("rotator_angle_deg"))
        self._busy = False
        self._last_exposure_ns = 0  # the stamp of the last visit (render thread only)
        self._closing = False
        self._thread: threading.Thread | None = None
        period = self._init_interfaces()
        p = self._param
        self.get_logger().info(
            f"camera simulator ready: band {self.band} ({self.wavelength_nm:g} nm), "
            f"{p('npix')} px stamps, {p('n_photons'):.3g} photons, "
            + (f"a visit every {period:g} s" if period > 0 else "visits on ~/trigger only")
            + f", apply_corrections {p('apply_corrections')}, "
            f"|dof| {np.linalg.norm(self._dof):.4g}")

    def _init_optics(self) -> None:
        """The band, wavelength, starting telescope state, random streams and corner
        geometry from the parameters; a bad value raises here, before any visit."""
        p = self._param
        self.band = str(p("band"))
        if self.band not in BANDS:
            raise ValueError(f"band must be one of {BANDS}, got {self.band!r}")
        wl = float(p("wavelength_nm"))
        self.wavelength_nm = wl if wl > 0 else band_wavelength_nm(self.band)
        self.frame_id = str(p("frame_id"))
        self.corners = served_corners(p("corners"))

        dof = np.asarray(list(p("initial_dof")), dtype=np.float64).reshape(-1)
        if dof.shape != (N_DOF,) or not np.all(np.isfinite(dof)):
            raise ValueError(f"initial_dof must be {N_DOF} finite numbers, got {dof.size}")
        seed = int(p("perturbation_seed"))
        if seed >= 0:
            prng = np.random.default_rng(seed)
            dof[:10] += prng.normal(0.0, 1.0, 10) * float(p("perturbation_scale")) * RIGID_SCALE
        self._dof = dof
        rseed = int(p("render_seed"))
        self._rng = np.random.default_rng(None if rseed < 0 else rseed)
        self._act_rng = np.random.default_rng(None if rseed < 0 else rseed + 1)

        from cwfs_ros import sim

        self._sim = sim
        self.geometry = sim.load_corner_geometry()
        missing = [c for c in CORNERS if c not in self.geometry]
        if missing:
            raise ValueError(f"corner geometry lacks {missing}")
        # The design (intrinsic) wavefront at the corner mid points, camera frame: fixed for
        # the band and the rotator angle (cached per angle).
        self._intrinsic_by_angle: dict[float, np.ndarray] = {}
        self.intrinsic_nm = self._intrinsic(0.0)

    def _init_interfaces(self) -> float:
        """Publishers, the correction subscription, ~/trigger and the timers, created last
        (nothing arrives before the state exists); returns the visit period [s]."""
        self.pubs = {(c, s): self.create_publisher(Image, image_topic(c, s),
                                                   IMAGE_QOS)
                     for c in self.corners for s in SIDES}
        self.pub_truth = self.create_publisher(SimTruth, TRUTH_TOPIC, OUTPUT_QOS)
        # Reliable, keep-last 10, volatile: the ROS convention for joint_states, and a
        # controller matches each visit's stamp against the angles it has received.
        self.pub_joint = self.create_publisher(JointState, JOINT_STATES_TOPIC, OUTPUT_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self.trust = PublisherTrust(self, CORRECTION_TOPIC,
                                    int(self._param("correction_publishers")))
        self.sub = self.create_subscription(DofCorrection, CORRECTION_TOPIC,
                                            self._on_correction, OUTPUT_QOS)
        self.trust.attach(self.sub)
        self.srv = self.create_service(Trigger, "~/trigger", self._on_trigger)
        period = float(self._param("visit_period_s"))
        self._visit_timer = (self.create_timer(period, self._on_period) if period > 0 else None)
        self._diag_timer = self.create_timer(float(self._param("diagnostics_period_s")),
                                             self.publish_diagnostics)
        self.add_on_set_parameters_callback(self._validate_parameters)
        return period

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        """Declare every parameter, defaults from config/params.yaml, by concern."""
        d = bundled_declarer(self, "camera_sim_node")
        _declare_optics_parameters(d)
        _declare_image_parameters(d)
        _declare_frame_parameters(d)
        _declare_runtime_parameters(d)

    def _validate_parameters(self, params: Sequence[Parameter]) -> SetParametersResult:
        for prm in params:
            if prm.name == "actuator_noise" and not (0.0 <= float(prm.value) <= 10.0):
                return result(False, "actuator_noise must be in [0, 10]")
            lo, hi = ROTATOR_RANGE_DEG
            if prm.name == "rotator_angle_deg" and not (lo <= float(prm.value) <= hi):
                return result(False, f"rotator_angle_deg must be in [{lo:g}, {hi:g}]")
        return result(True)

    # ------------------------------------------------------------------ state
    @property
    def dof_state(self) -> np.ndarray:
        """A copy of the current 50-DoF telescope state."""
        with self._lock:
            return self._dof.copy()

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._busy

    def _truth_vector(self, telescope, angle_deg: float) -> np.ndarray:
        """True Zernikes at the corner mid points, camera frame (what the sensors measure)."""
        return np.concatenate([
            self._sim.camera_zernikes_nm(telescope, self.geometry[c].mid_field_deg, angle_deg,
                                         wavelength_nm=self.wavelength_nm)
            for c in CORNERS])

    def _intrinsic(self, angle_deg: float) -> np.ndarray:
        with self._lock:
            cached = self._intrinsic_by_angle.get(angle_deg)
        if cached is None:
            nominal = self._sim.perturbed_telescope(np.zeros(N_DOF), self.band,
                                                    rotator_angle_deg=angle_deg)
            cached = self._truth_vector(nominal, angle_deg)
            with self._lock:
                if len(self._intrinsic_by_angle) > 64:
                    self._intrinsic_by_angle.clear()
                self._intrinsic_by_angle[angle_deg] = cached
        return cached

    # ------------------------------------------------------------------ corrections
    def _on_correction(self, msg: DofCorrection) -> None:
        dof = np.asarray(msg.dof, dtype=np.float64).reshape(-1)
        reason = None
        untrusted = self.trust.problem()
        if untrusted is not None:
            reason = ("untrusted_source", f"correction {stamp_to_ns(msg.header.stamp)} ns not "
                      f"applied: {untrusted}")
        elif not msg.valid:
            reason = ("invalid", f"correction flagged invalid: {msg.status or 'no status'}")
        elif msg.dry_run:
            reason = ("dry_run", "correction is a dry run")
        elif dof.shape != (N_DOF,) or not np.all(np.isfinite(dof)):
            reason = ("bad_dof", f"dof must be {N_DOF} finite numbers")
        elif not bool(self._param("apply_corrections")):
            reason = ("not_applied", "apply_corrections is false")
        else:
            reason = self._correction_problem(msg, dof)
        if reason is not None:
            with self._lock:
                self.stats["corrections_ignored"] += 1
            self.ignored.add(*reason)
            if reason[0] == "untrusted_source":
                self.untrusted.add(*reason)
            due, n = self.ignored.log_due(reason[0], 5.0)
            text = (f"ignored DofCorrection ({reason[0]}: {reason[1]})"
                    + (f" (+{n} more not logged)" if n else ""))
            if due and reason[0] == "untrusted_source":
                self.get_logger().error(text)
            elif due:
                self.get_logger().info(text)
            return
        noise = float(self._param("actuator_noise"))
        with self._lock:
            step = dof if noise <= 0 else dof * (1.0 + noise * self._act_rng.normal(size=N_DOF))
            self._dof = self._dof + step
            self._visits_published[stamp_to_ns(msg.header.stamp)] = True  # corrected
            self.stats["corrections_applied"] += 1
            norm = float(np.linalg.norm(self._dof))
        self.get_logger().info(f"applied DofCorrection: |step| {np.linalg.norm(step):.4g}, "
                               f"|dof| {norm:.4g}")

    # ------------------------------------------------------------------ who may act
    def _init_correction_guard(self) -> None:
        """Which corrections may move the telescope: one per visit this node published,
        within the step limits. Without DDS Security anyone can publish on the correction
        topic; the stamp and the step are what the application can check."""
        from cwfs_ros.ofc.control import load_dof_spec

        # stamp (ns) of each visit published -> corrected yet; the last 64 visits.
        self._visits_published: OrderedDict[int, bool] = OrderedDict()
        scale = float(self._param("correction_max_step_scale"))
        self._max_step = load_dof_spec().max_step * scale if scale > 0 else None
        self.foreign: list[str] = []
        self.untrusted = RejectionCounter()

    def _note_published(self, stamp_ns: int) -> None:
        with self._lock:
            self._visits_published[int(stamp_ns)] = False
            while len(self._visits_published) > 64:
                self._visits_published.popitem(last=False)

    def _correction_problem(self, msg: DofCorrection, dof: np.ndarray) -> tuple[str, str] | None:
        """Why a valid correction must not be applied, or None (called before applying)."""
        stamp = stamp_to_ns(msg.header.stamp)
        with self._lock:
            done = self._visits_published.get(stamp)
        if done is None:
            return ("not_our_visit", f"stamp {stamp} ns is not a visit this simulator "
                    "published (recently): an outside publisher or a stale correction")
        if done:
            return ("already_corrected", f"visit {stamp} ns was already corrected once")
        if self._max_step is not None:
            over = np.abs(dof) > self._max_step * (1.0 + 1e-9)
            if np.any(over):
                i = int(np.argmax(np.abs(dof) / self._max_step))
                return ("step_limit", f"DoF {i} step {dof[i]:.6g} is beyond its limit "
                        f"{self._max_step[i]:.6g} ({int(over.sum())} DoF over)")
        return None

    # ------------------------------------------------------------------ visits
    def request_visit(self) -> tuple[bool, str]:
        """Start rendering a visit in the background unless one is in progress."""
        with self._lock:
            if self._closing:
                return False, "shutting down"
            if self._busy:
                self.stats["visits_skipped"] += 1
                return False, f"visit {self.visit} is still rendering; request skipped"
            self._busy = True
            self.visit += 1
            visit = self.visit
            dof = self._dof.copy()
            angle = float(self._param("rotator_angle_deg"))
            self._thread = threading.Thread(target=self._render_visit, args=(visit, dof, angle),
                                            name=f"camera_sim_visit_{visit}", daemon=True)
            self._thread.start()
        return True, f"visit {visit} started"

    def _on_period(self) -> None:
        ok, message = self.request_visit()
        if not ok:
            # Every skip is counted (visits_skipped on /diagnostics); the log says it once a
            # minute, not at every period of a free-running simulator slower than its period.
            self.get_logger().warning(
                f"skipped a visit period: {message} (visit_period_s is shorter than a render; "
                "each skip is counted as visits_skipped on /diagnostics)",
                throttle_duration_sec=60.0)

    def _on_trigger(self, request: Trigger.Request, response: Trigger.Response):
        response.success, response.message = self.request_visit()
        return response

    def _publish_rotator(self, stamp_ns: int, angle_deg: float) -> None:
        msg = JointState()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = self.frame_id
        msg.name = [ROTATOR_JOINT]
        msg.position = [float(np.deg2rad(angle_deg))]
        self.pub_joint.publish(msg)

    def _truth_msg(self, tel, visit: int, dof: np.ndarray, angle_deg: float,
                   stamp_ns: int) -> SimTruth:
        truth = SimTruth()
        truth.header.stamp = ns_to_stamp(stamp_ns)
        truth.header.frame_id = self.frame_id
        truth.dof_state = np.asarray(dof, dtype=np.float64)
        truth.zernikes_nm = self._truth_vector(tel, angle_deg)
        truth.intrinsic_nm = np.asarray(self._intrinsic(angle_deg), dtype=np.float64)
        truth.visit = int(visit)
        truth.band = self.band
        truth.rotator_angle_deg = float(angle_deg)
        truth.corner_wavefront_rms_nm = wavefront_error_nm(truth.zernikes_nm,
                                                           truth.intrinsic_nm)
        field = field_truth(tel, self.band, wavelength_nm=self.wavelength_nm)
        truth.field_wavefront_rms_nm = field.field_wavefront_rms_nm
        truth.fwhm_arcsec = field.fwhm_arcsec
        return truth

    def _exposure_stamp_ns(self) -> int | None:
        """The visit's exposure time: now, or, within ``readout_s`` of the last exposure, once
        that has passed (None when the node closes meanwhile). Runs in the render thread."""
        readout_ns = int(float(self._param("readout_s")) * 1e9)
        while not self._closing:
            now = self.get_clock().now().nanoseconds
            wait_ns = self._last_exposure_ns + readout_ns - now
            if wait_ns <= 0:
                self._last_exposure_ns = now
                return now
            time.sleep(min(wait_ns / 1e9, 0.1))
        return None

    def _render_visit(self, visit: int, dof: np.ndarray, angle_deg: float = 0.0) -> None:
        t0 = time.monotonic()
        released = False
        try:
            stamp_ns = self._exposure_stamp_ns()
            if stamp_ns is None:
                return  # shutting down
            self._publish_rotator(stamp_ns, angle_deg)  # before the visit's images
            p = self._param
            npix, n_photons = int(p("npix")), float(p("n_photons"))
            sky, off_max = float(p("sky_per_pixel")), float(p("offset_px_max"))
            tel = self._sim.perturbed_telescope(dof, self.band, rotator_angle_deg=angle_deg)
            if bool(p("frames")):
                images = self._render_frames(tel, angle_deg)
            else:
                images = self._render_stamps(tel, npix, n_photons, sky, off_max, angle_deg)
            if self._closing:
                return
            truth = self._truth_msg(tel, visit, dof, angle_deg, stamp_ns)
            msgs = {k: image_msg(v.astype(np.float32), stamp_ns, encoding="32FC1",
                                 frame_id=self.frame_id) for k, v in images.items()}
            if self._closing:
                return
            self._note_published(stamp_ns)
            for k, m in msgs.items():
                self.pubs[k].publish(m)
            dt = time.monotonic() - t0
            wfe = truth.corner_wavefront_rms_nm
            with self._lock:
                # The truth, the visit's last message, goes out under the lock that a
                # trigger takes, and the node is ready before the lock is let go: a driver
                # that triggers on the truth waits for that, and is never refused.
                self.pub_truth.publish(truth)
                self.stats["visits_rendered"] += 1
                self.last_render_s = dt
                self.last_status = f"visit {visit} published"
                self.last_true_error_nm = wfe
                self.last_field_error_nm = truth.field_wavefront_rms_nm
                self.last_fwhm_arcsec = truth.fwhm_arcsec
                self.last_rotator_angle_deg = angle_deg
                self._busy = False
                released = True
            self.get_logger().info(
                f"visit {visit} published (rendered in {dt:.1f} s, rotator {angle_deg:g} deg, "
                f"true wavefront error {wfe:.1f} nm at the corners, "
                f"{truth.field_wavefront_rms_nm:.1f} nm over the field, optical FWHM "
                f"{truth.fwhm_arcsec:.3f} arcsec, |dof| {np.linalg.norm(dof):.4g})")
        except Exception as exc:  # noqa: BLE001 - a failed visit must not kill the node
            with self._lock:
                self.stats["visits_failed"] += 1
                self.last_status = f"visit {visit} failed: {type(exc).__name__}: {exc}"
            if not self._closing:
                self.get_logger().error(self.last_status)
        finally:
            if not released:
                with self._lock:
                    self._busy = False

    def _render_stamps(self, tel, npix: int, n_photons: float, sky: float,
                       off_max: float, angle_deg: float = 0.0) -> dict:
        """The one-donut stamps of a visit, two per corner of ``corners`` (sky subtracted), at
        the telescope fields the rotated corners see."""
        p = self._param
        # Offsets and per-donut seeds are drawn here, in a fixed order, so the images do
        # not depend on how many render workers there are.
        specs = []
        for c in self.corners:
            g = self.geometry[c]
            for side, field, dz in (("intra", g.intra_field_deg, g.intra_offset_mm),
                                    ("extra", g.extra_field_deg, g.extra_offset_mm)):
                offset = (tuple(float(x) for x in self._rng.uniform(-off_max, off_max, 2))
                          if off_max > 0 else (0.0, 0.0))
                g = telescope_field_deg(field, np.deg2rad(angle_deg))[0]
                specs.append(DonutSpec((c, side), (float(g[0]), float(g[1])), float(dz),
                                       offset, int(self._rng.integers(2**62))))
        return render_visit(tel, specs, wavelength_nm=self.wavelength_nm, npix=npix,
                            n_photons=n_photons, sky_per_pixel=sky,
                            seeing_fwhm_arcsec=float(p("seeing_fwhm_arcsec")),
                            read_noise_e=float(p("read_noise_e")), executor=self._pool)

    def _render_frames(self, tel, angle_deg: float = 0.0) -> dict:
        """The half-chip frames of a visit, two per corner of ``corners``, several stars each
        (sky included)."""
        p = self._param
        scene = FrameScene((int(p("frame_rows")), int(p("frame_cols"))),
                           (int(p("frame_stars_min")),
                            max(int(p("frame_stars_min")), int(p("frame_stars_max")))),
                           (float(p("frame_flux_min")),
                            max(float(p("frame_flux_min")), float(p("frame_flux_max")))),
                           bool(p("frame_blend")), bool(p("frame_faint")))
        specs = frame_specs(self.corners, scene, self._rng, angle_deg)
        frames = render_frames(tel, specs, band=self.band, wavelength_nm=self.wavelength_nm,
                               sky_per_pixel=float(p("sky_per_pixel")),
                               read_noise_e=float(p("read_noise_e")),
                               seeing_fwhm_arcsec=float(p("seeing_fwhm_arcsec")),
                               executor=self._pool)
        with self._lock:
            self.last_frame_stars = {k: len(f.stars) for k, f in frames.items()}
        return {k: f.image for k, f in frames.items()}

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self):
        with self._lock:
            stats = dict(self.stats)
            values = [("state", "rendering" if self._busy else "idle"),
                      ("visit", self.visit), *stats.items(), ("band", self.band),
                      ("wavelength_nm", f"{self.wavelength_nm:g}"),
                      ("apply_corrections", self._param("apply_corrections")),
                      ("actuator_noise", self._param("actuator_noise")),
                      ("dof_norm", f"{np.linalg.norm(self._dof):.4g}"),
                      ("last_render_s", f"{self.last_render_s:.2f}"),
                      ("true_wavefront_error_nm", f"{self.last_true_error_nm:.1f}"),
                      ("true_field_wavefront_error_nm", f"{self.last_field_error_nm:.1f}"),
                      ("true_fwhm_arcsec", f"{self.last_fwhm_arcsec:.3f}"),
                      ("rotator_angle_deg", f"{self.last_rotator_angle_deg:g}"),
                      ("last_status", self.last_status)]
            failed = stats["visits_failed"] > 0 and "failed" in self.last_status
        values += self.ignored.key_values()
        self.foreign = refresh_foreign(self, [*(image_topic(c, s)
                                                   for c in self.corners for s in SIDES),
                                                 TRUTH_TOPIC])
        values.append(("foreign_publishers", "; ".join(self.foreign) or "none"))
        values += self.trust.key_values("correction_publishers")
        excess = self.trust.excess()
        if self.untrusted.recent(60.0):
            level, message = ERROR, f"untrusted_source: {self.untrusted.last_message}"
        elif excess:
            level, message = ERROR, excess
        elif failed:
            level, message = WARN, self.last_status
        elif self.foreign:
            level, message = WARN, f"another publisher on a topic of this node: {self.foreign[0]}"
        elif self.ignored.recent(10.0):
            level, message = WARN, f"recently ignored a correction: {self.ignored.last_message}"
        else:
            level, message = OK, "rendering" if values[0][1] == "rendering" else "idle"
        return diagnostic_status(f"{self.get_name()}: camera simulator", level, message,
                                 values, hardware_id="aos_camera_sim")

    def destroy_node(self) -> None:
        with self._lock:
            self._closing = True
            th = self._thread
        if th is not None and th.is_alive():
            th.join(timeout=1.0)  # a donut in progress finishes on its own (daemon thread)
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self.trust.detach()  # its event handle before the subscription
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """``camera_sim_node [--ros-args ...]``: run this node alone (config/params.yaml)."""
    from cwfs_ros.ros.launch import run_node_main

    return run_node_main(NODE_NAME, args)


if __name__ == "__main__":
    raise SystemExit(main())


def _declare_optics_parameters(d: Declare) -> None:
    """The telescope's starting state and the optical model (read-only)."""
    ro = {"read_only": True}
    d("initial_dof", describe(
        "Initial telescope state: 50 DoF, ts_ofc order and units [um | deg], batoid_rubin "
        "(DofCorrection) signs.", **ro))
    d("perturbation_seed", describe(
        "Seed of a random rigid-body perturbation added to DoF 0-9 at start (-1 = none).",
        int_range=(-1, 2**31 - 1), **ro))
    d("perturbation_scale", describe(
        "Scale of that perturbation: normal(0,1) x scale x [8, 150, 150, 0.005, 0.005] "
        "[um, um, um, deg, deg] per hexapod.", fp_range=(0.0, 100.0), **ro))
    d("band", describe("Filter band of the optical model.",
                       constraints="u | g | r | i | z | y", **ro))
    d("wavelength_nm", describe(
        "Monochromatic wavelength [nm]; 0 = the band's effective wavelength (r: 622).",
        fp_range=(0.0, 2000.0), **ro))


def _declare_image_parameters(d: Declare) -> None:
    """Visit cadence and what each stamp holds: photons, sky, offsets, blur, noise."""
    ro = {"read_only": True}
    d("corners", describe(
        "Corners whose images are rendered and published (a subset of R00 R04 R40 R44, as "
        "wavefront_node's corners); SimTruth always covers all four.", **ro))
    d("visit_period_s", describe(
        "Visit cadence [s]; 0 = only on a ~/trigger call. A period that falls while the "
        "previous visit still renders is skipped.", fp_range=(0.0, 3600.0), **ro))
    d("readout_s", describe(
        "Shortest time between two visits' exposures [s]: a visit requested sooner (a "
        "trigger right after a correction) is exposed once this has passed since the last "
        "one, as a camera exposes no faster than it reads out. ofc_node's "
        "min_visit_period_s must not exceed it (config/sim.yaml).",
        fp_range=(0.0, 60.0), **ro))
    d("n_photons", describe(
        "Expected photons per donut (unvignetted pupil).", fp_range=(1.0, 1e9), **ro))
    d("sky_per_pixel", describe(
        "Sky background [e-/px], added before Poisson noise and subtracted after.",
        fp_range=(0.0, 1e6), **ro))
    d("offset_px_max", describe(
        "Random donut offset in each axis, uniform in +-offset_px_max [px].",
        fp_range=(0.0, 1000.0), **ro))
    d("npix", describe("Stamp side [px].", int_range=(16, 4096), **ro))
    d("seeing_fwhm_arcsec", describe(
        "Gaussian seeing blur FWHM [arcsec] of every donut, stamps and frames; 0 = none.",
        fp_range=(0.0, MAX_SEEING_FWHM_ARCSEC), **ro))
    d("read_noise_e", describe(
        "Gaussian read noise per pixel [e-]; 0 = none.", fp_range=(0.0, 1000.0), **ro))


def _declare_frame_parameters(d: Declare) -> None:
    """The half-chip frames mode: frame size and the stars it holds."""
    ro = {"read_only": True}
    d("frames", describe(
        "Publish half-chip frames with several stars (random positions and brightness, "
        "a blended pair, a too-faint star) instead of one-donut stamps; wavefront_node "
        "then selects, pairs and combines the donuts.", **ro))
    d("frame_rows", describe(
        "Frame rows [px] (frames mode), focal-plane orientation, of the half-chips whose "
        "long side runs along the rows (R00, R44); the frames of those turned by 90 degrees "
        "(R04, R40) are frame_cols rows by frame_rows columns, along their half-chip as a "
        "window is read out.", int_range=(200, 8192), **ro))
    d("frame_cols", describe("Frame columns [px] (frames mode); see frame_rows.",
                             int_range=(200, 8192), **ro))
    d("frame_stars_min", describe("Fewest isolated stars per frame.",
                                  int_range=(0, 50), **ro))
    d("frame_stars_max", describe("Most isolated stars per frame.",
                                  int_range=(0, 50), **ro))
    d("frame_flux_min", describe("Photons of the faintest isolated star.",
                                 fp_range=(1.0, 1e9), **ro))
    d("frame_flux_max", describe("Photons of the brightest isolated star.",
                                 fp_range=(1.0, 1e9), **ro))
    d("frame_blend", describe("Add a blended pair to each frame.", **ro))
    d("frame_faint", describe("Add a too-faint star to each frame.", **ro))


def _declare_runtime_parameters(d: Declare) -> None:
    """Rendering workers, the rotator, how corrections are applied, seeds and outputs."""
    ro = {"read_only": True}
    d("render_workers", describe(
        "Processes that ray-trace a visit's 8 donuts in parallel (0 = one per CPU, "
        "1 = in the node's render thread). The images do not depend on it.",
        int_range=(0, 64), **ro))
    d("rotator_angle_deg", describe(
        "Camera rotator angle [deg] (batoid_rubin's with_rtp: the camera turned by "
        "RotZ(angle) before the DoF are applied), read at the start of each visit and "
        "published on joint_states as joint camera_rotator [rad].",
        fp_range=ROTATOR_RANGE_DEG))
    d("apply_corrections", describe(
        "Apply valid, non-dry-run DofCorrections to the state (false = observe only)."))
    d("actuator_noise", describe(
        "Relative actuator error: each applied DoF is scaled by (1 + actuator_noise x "
        "normal(0,1)).", fp_range=(0.0, 10.0)))
    d("render_seed", describe(
        "Seed of the image noise, offsets and actuator noise (-1 = fresh entropy).",
        int_range=(-1, 2**31 - 2), **ro))
    d("frame_id", describe("frame_id of the images and SimTruth.", **ro))
    d("diagnostics_period_s", describe("Period of /diagnostics [s].", read_only=True,
                                       fp_range=(0.05, 60.0)))
    d("correction_max_step_scale", describe(
        "Largest |step| of a correction applied, as a multiple of dof.yaml's max_step "
        "(ofc_node's own limit is max_step_scale x the same); beyond it the correction "
        "is ignored (step_limit); 0 = no limit.", fp_range=(0.0, 100.0), **ro))
    d("correction_publishers", describe(
        "Apply a DofCorrection only while its topic has exactly this many publishers "
        "(ofc_node; whatever their names), else ignore it (untrusted_source, ERROR on "
        "/diagnostics); 0 = any number.", int_range=(0, 64), **ro))
