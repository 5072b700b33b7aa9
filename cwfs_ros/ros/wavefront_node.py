"""wavefront_node: donut image pairs in, per-corner wavefronts and the visit's 76-vector out.

Topics (relative names; in the root namespace they are the ones below)
---------------------------------------------------------------------
in   ``/aos/wfs/<corner>/<side>/image``  sensor_msgs/Image, side ``intra`` | ``extra``, one
     subscription per served corner and side (:func:`~.common.image_qos`, reliable unless
     ``image_reliability`` says best_effort). ``header.stamp`` is the
     exposure time; the intra and extra images of a visit carry equal stamps.
out  ``/aos/wfs/<corner>/wavefront``     cwfs_msgs/CornerWavefront, as soon as that corner's
     pair is estimated (valid=false with a status naming the problem otherwise).
in   ``/aos/wfs/<corner>/wavefront``     for corners served by *other* processes, when
     ``assemble`` is true: the vector is assembled from CornerWavefront messages wherever
     they were produced.
out  ``/aos/wfs/wavefront``              cwfs_msgs/WavefrontVector, when the four corners of a
     visit are in, or after ``visit_timeout_s`` with the missing corners marked invalid.
out  ``/diagnostics``                    state, counts of rejected inputs and the last reason,
     pending memory, messages lost, and any other publisher on the topics this node owns.

Input guards (docs/reliability.md): an image stamped 0, or more than ``max_future_s`` ahead
of the node's clock, whose pair could not fit within ``max_pending_mb``, or whose
``header.frame_id`` names another corner or side than its topic's, is refused (``no_stamp``,
``future_stamp``, ``too_large``, ``frame_mismatch``), as are the images of a topic while it
has more than ``max_image_publishers`` publishers, now or since they were last trusted
(``untrusted_source``, :class:`~cwfs_ros.ros.common.PublisherTrust`; every
image topic with several publishers is named on /diagnostics); images waiting for their
partners hold at most ``max_pending_mb`` (the oldest is dropped first, ``memory_limit``);
two different images for one corner, side and stamp make that corner invalid
(``conflicting_images``, see :mod:`cwfs_ros.runtime.visits`). Rejections are logged at most
once per ``log_throttle_s`` per reason, and all of them counted.

Every output carries the visit's image ``header.stamp``. The estimates run in worker processes
(:class:`cwfs_ros.runtime.corner_pool.CornerPool`), one corner per worker, warmed up at start.
What happens to an image, a pair, an outcome and a timeout is decided by
:class:`cwfs_ros.runtime.pipeline.WavefrontPipeline`, which the offline replay runs too; the
pairing and assembly rules are in :mod:`cwfs_ros.runtime.visits`.

A managed (lifecycle) node: the workers and topics exist from configure to cleanup; only an
active node processes images (docs/ros.md, Managed nodes). /diagnostics is published in
every state.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future

from cwfs_msgs.msg import CornerWavefront, WavefrontVector
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.layout import CORNERS, SIDES, VECTOR_TOPIC, corner_topic, image_topic
from cwfs_ros.ros.common import (
    DIAGNOSTICS_QOS,
    ERROR,
    MAX_STRING_PARAM_LEN,
    OK,
    OUTPUT_QOS,
    WARN,
    ManagedNode,
    PublisherTrust,
    QosEventMonitor,
    RejectionCounter,
    SequenceGaps,
    bundled_declarer,
    describe,
    diagnostic_status,
    endpoint_label,
    image_qos,
    refresh_foreign,
    result,
    stamp_to_ns,
    string_param_problem,
)
from cwfs_ros.ros.convert import (
    corner_entry_from_msg,
    corner_wavefront_msg,
    wavefront_vector_msg,
)
from cwfs_ros.runtime.corner_pool import (
    CornerJob,
    CornerOutcome,
    CornerPool,
    FrameFiles,
    frames_nbytes,
)
from cwfs_ros.runtime.memory import prefault_heap
from cwfs_ros.runtime.pipeline import SETTINGS_PARAMS as _SETTINGS_PARAMS
from cwfs_ros.runtime.pipeline import (
    WavefrontPipeline,
    served_corners,
    stamp_problem,
)
from cwfs_ros.runtime.visits import (
    CornerEntry,
    PairReady,
    Rejection,
    VisitVector,
    checked_entry,
)
from cwfs_ros.runtime.workload import WorkloadMonitor
from cwfs_ros.wfs.blur import MAX_SEEING_FWHM_ARCSEC
from cwfs_ros.wfs.orientation import FLIPS
from cwfs_ros.wfs.settings import EstimatorSettings, validate_settings

__all__ = ["WavefrontNode", "main"]

NODE_NAME = "wavefront_node"
_SOLVERS = ("exp", "fft", "lsq")
_INPUT_MODES = ("auto", "stamps", "frames")
_WARM_ATTEMPTS = 2  # a corner's warm-up is retried once (a worker killed while warming)




class WavefrontNode(ManagedNode):
    """Pairs images, estimates corners in parallel processes, publishes the wavefronts.

    A lifecycle (managed) node. ``autostart`` (default) configures and activates it at once,
    as ``cwfs-ros bringup`` does; with ``autostart=False`` it starts unconfigured, with its
    parameters declared and /diagnostics published. ``configure`` reads the parameters,
    starts and warms the worker processes and creates the topics; ``activate`` starts taking
    images; ``deactivate`` stops: images that arrive are counted, logged and reported on
    /diagnostics as ``inactive`` but not processed; ``cleanup`` stops the workers.

    Keyword arguments go to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``,
    ``cli_args``, ``namespace`` ...).
    """

    def __init__(self, node_name: str = NODE_NAME, *, autostart: bool = True,
                 **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.RLock()
        self.pool: CornerPool | None = None
        self._subs: list = []
        self._image_subs: dict = {}  # (corner, side) -> its image subscription
        self._image_trust: dict = {}  # (corner, side) -> PublisherTrust of its topic
        self.pub_corner: dict = {}
        self.pub_vector = None
        self._expiry_timer = None
        # Counts warm-ups over the node's life (not reset on configure), so that a late
        # answer of a pool released by cleanup is never taken for the new pool's.
        self._warm_generation = 0
        # Heap mapped at the first frames warm-up (_prefault_heap, runtime.memory): 0 where
        # the process returns freed memory (glibc's defaults) or serves stamps.
        self._heap_prefault_mb = 0.0
        self._declare_parameters()
        self._cb_images = MutuallyExclusiveCallbackGroup()
        self._cb_timers = MutuallyExclusiveCallbackGroup()
        self._cb_remote = ReentrantCallbackGroup()
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self._diag_timer = self.create_timer(self._param("diagnostics_period_s"),
                                             self.publish_diagnostics,
                                             callback_group=self._cb_timers)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        if autostart:
            self.start()

    def _configure_resources(self) -> None:
        """configure: parameters read and checked, worker pool started, topics created."""
        p = self._param
        self._read_configuration()
        self.rejected = RejectionCounter()
        self.stats = {"images": 0, "pairs": 0, "corners_valid": 0, "corners_invalid": 0,
                      "visits_published": 0, "visits_incomplete": 0, "frame_pairs": 0}
        self.last_compute_ms: dict[str, float] = {}
        # Per-corner job costs, the workers' cache counts and the visit-timeout promise.
        self.workload = WorkloadMonitor()
        self._rebalancing = False
        self.last_status: dict[str, str] = {}
        # (monotonic time, what was missing) of the last visit published incomplete: WARN on
        # /diagnostics for a minute, as a producer that stopped is not an input rejected.
        self.last_incomplete: tuple[float, str] | None = None
        self.foreign: list[str] = []
        # Images never taken (the queue overflowed), per topic, from sequence numbers.
        self.image_gaps = {(c, s): SequenceGaps() for c in self.corners for s in SIDES}
        # The publishers of each image topic from the ROS graph (refreshed with /diagnostics,
        # and when an image comes while more than one is matched).
        self.image_publishers: dict[tuple[str, str], list[str]] = {}

        img_qos = image_qos(str(p("image_reliability")))  # raises before any worker starts
        # Worker processes, warmed up in the background.
        self.pool = CornerPool(self.corners, p("workers"))
        self._warm: dict[str, dict] = {}
        self._start_warm_up()
        self._create_topics(img_qos)
        self.get_logger().info(
            f"serving corners {', '.join(self.corners)} with {self.pool.n_workers} worker "
            f"process(es) (affinity {self.pool.affinity}); assemble={self.assemble}; "
            f"settings {self.settings}")

    def _read_configuration(self) -> None:
        """The corners and the pipeline: fields, estimator settings, orientations, pairing
        and assembly (ConfigError if bad)."""
        p = self._param
        self.corners = served_corners(p("corners"))
        self.assemble = bool(p("assemble"))
        self.pipeline = WavefrontPipeline(p, self.corners, assemble=self.assemble)
        self.frame_id = p("frame_id")
        bad = string_param_problem("frame_id", self.frame_id)
        if bad is not None:
            raise ConfigError(f"parameter {bad}")

    # The pipeline's state, as the node has always exposed it.
    @property
    def settings(self) -> EstimatorSettings:
        return self.pipeline.settings

    @property
    def fields(self) -> dict:
        return self.pipeline.fields

    @property
    def orientations(self) -> dict:
        return self.pipeline.orientations

    @property
    def pairing(self):
        return self.pipeline.pairing

    @property
    def assembler(self):
        return self.pipeline.assembler

    def _create_topics(self, img_qos) -> None:
        # Managed publishers: nothing goes out unless the node is active.
        self.pub_corner = {c: self.create_lifecycle_publisher(CornerWavefront, corner_topic(c),
                                                              OUTPUT_QOS)
                           for c in self.corners}
        self.pub_vector = (self.create_lifecycle_publisher(WavefrontVector, VECTOR_TOPIC,
                                                           OUTPUT_QOS)
                           if self.assemble else None)
        self._subs = []
        self._image_subs = {}
        self._image_trust = {}
        self.qos_events = QosEventMonitor(self.get_logger())
        for c in self.corners:
            for s in SIDES:
                topic = image_topic(c, s)
                cb = self._image_callback(c, s)
                # Two arguments: rclpy passes the message info (its sequence numbers).
                sub = self.create_subscription(
                    Image, topic, lambda msg, info, cb=cb: cb(msg, info), img_qos,
                    callback_group=self._cb_images,
                    event_callbacks=self.qos_events.subscription_callbacks(topic))
                self._subs.append(sub)
                self._image_subs[(c, s)] = sub
                trust = PublisherTrust(self, topic, int(self._param("max_image_publishers")),
                                       at_most=True)
                trust.attach(sub, callback_group=self._cb_timers)
                self._image_trust[(c, s)] = trust
        if self.assemble:
            for c in CORNERS:
                if c not in self.corners:
                    self._subs.append(self.create_subscription(
                        CornerWavefront, corner_topic(c), self._remote_corner_callback(c),
                        OUTPUT_QOS, callback_group=self._cb_remote))
        self._expiry_timer = self.create_timer(0.1, self._expire,
                                               callback_group=self._cb_timers)

    def _release_resources(self) -> None:
        """cleanup / shutdown: the topics, the timeout timer and the worker processes."""
        for trust in self._image_trust.values():
            trust.detach()  # its event handle before the subscription
        self._image_trust = {}
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []
        self._image_subs = {}
        if self._expiry_timer is not None:
            self.destroy_timer(self._expiry_timer)
            self._expiry_timer = None
        for pub in [*self.pub_corner.values(), self.pub_vector]:
            if pub is not None:
                self.destroy_lifecycle_publisher(pub)
        self.pub_corner, self.pub_vector = {}, None
        self._release_processes()

    def _release_processes(self) -> None:
        pool, self.pool = self.pool, None
        if pool is not None:
            pool.shutdown(wait=False)

    def _inactive_effect(self) -> str:
        return "images are not processed (counted as rejected.inactive)"

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        """Declare every parameter, defaults from config/params.yaml, by concern."""
        d = bundled_declarer(self, "wavefront_node")
        self._declare_estimator_parameters(d)
        self._declare_visit_parameters(d)
        self._declare_input_parameters(d)
        d("diagnostics_period_s", describe("Period of /diagnostics [s].",
                                                read_only=True, fp_range=(0.05, 60.0)))
        self._declare_orientation_parameters(d)
        self._declare_guard_parameters(d)

    @staticmethod
    def _declare_estimator_parameters(d) -> None:
        """The optical model and the estimator's settings."""
        d("instrument", describe(
            "Instrument model: a config/instruments/<name>.yaml name or a path to one. Set "
            "at start only, as the other files the node reads: a path given through the "
            "parameter services could load any file as the optical model.", read_only=True))
        d("band", describe("Filter band of the optical model.",
                                constraints="u | g | r | i | z | y"))
        d("solver", describe("TIE solver: exp (series expansion), fft, lsq.",
                                    constraints=" | ".join(_SOLVERS)))
        d("outer_iterations", describe(
            "Outer compensation iterations; 0 = the value of config/algorithm.yaml.",
            int_range=(0, 100)))
        d("pad_px", describe(
            "Background padding [px] added around each stamp before estimation (border "
            "median), for stamps cut so tight that the estimator rejects the donut as touching "
            "the edge; 0 = none (160 px corner stamps need none).",
            int_range=(0, 256)))
        d("seeing_fwhm_arcsec", describe(
            "Atmospheric seeing of the images [arcsec FWHM], e.g. from the seeing monitor: the "
            "lsq and exp solvers take the blur's edge signal out of the difference image "
            "(docs/accuracy.md, Seeing); 0 = not given: no such correction.",
            fp_range=(0.0, MAX_SEEING_FWHM_ARCSEC)))

    @staticmethod
    def _declare_visit_parameters(d) -> None:
        """Pairing and visit assembly: timing, workers, the corners served, outputs' frame."""
        d("pairing_tolerance_s", describe(
            "Intra/extra (and corner) stamps closer than this [s] belong to the same visit.",
            fp_range=(0.0, 10.0)))
        d("visit_timeout_s", describe(
            "How long [s] an image waits for its partner, and a visit for its four corners, "
            "before it is dropped / published with the missing corners invalid (checked "
            "every 0.1 s).",
            fp_range=(0.05, 600.0)))
        d("workers", describe(
            "Worker processes for the corner estimates; 0 = min(#corners, #CPUs).",
            read_only=True, int_range=(0, 64)))
        d("corners", describe(
            "Corners served by this instance (subset of R00 R04 R40 R44).", read_only=True))
        d("assemble", describe(
            "Assemble and publish the 76-vector here, subscribing to the CornerWavefront "
            "topics of the corners served elsewhere.", read_only=True))
        d("sensor_config", describe(
            "Corner field-point YAML; empty = config/sensors/lsst_corners.yaml.",
            read_only=True))
        d("frame_id", describe("frame_id of the published messages."))

    @staticmethod
    def _declare_input_parameters(d) -> None:
        """What the images are (stamps or frames), donut selection and image QoS."""
        d("input_mode", describe(
            "What the images are: stamps (one donut each, oriented by sensors.*), frames (a "
            "half-chip each with several stars: detection, per-star field, pairing and "
            "combination, oriented by the frames section of sensor_config), or auto (frames "
            "when a side is >= frame_min_side_px).", constraints="auto | stamps | frames"))
        d("frame_min_side_px", describe(
            "With input_mode auto, an image with a side of at least this many pixels is a "
            "frame [px].", int_range=(16, 8192)))
        d("selection_config", describe(
            "Donut selection YAML for frames; empty = config/selection.yaml.",
            read_only=True))
        d("tile_store", describe(
            "Directory where the workers keep the half-chips' field tiles across starts, so "
            "that a restart (or a replay) with input_mode frames reads them instead of "
            "tracing them again: auto = $ROS_HOME/cwfs_ros/tiles, empty = none. A tile is "
            "read only when it was built by the same code and library versions.",
            read_only=True))
        d("image_reliability", describe(
            "QoS reliability of the image subscriptions: reliable (a lost image loses the "
            "corner's visit) or best_effort (needed to hear a camera that publishes with "
            "sensor_data QoS: a reliable subscription never matches a best-effort "
            "publisher).", constraints="reliable | best_effort", read_only=True))

    @staticmethod
    def _declare_orientation_parameters(d) -> None:
        """Each half-chip's rotation and flip into the focal-plane frame."""
        for c in CORNERS:
            for s in SIDES:
                d(f"sensors.{c}.{s}.rot90", describe(
                    f"Quarter turns (numpy.rot90, counter-clockwise) that bring the {c} {s} "
                    "image into the focal-plane frame; applied before the flip.",
                    int_range=(0, 3)))
                d(f"sensors.{c}.{s}.flip", describe(
                    f"Flip of the {c} {s} image after the rotation: none, lr (x -> -x) or "
                    "ud (y -> -y).", constraints=" | ".join(FLIPS)))

    @staticmethod
    def _declare_guard_parameters(d) -> None:
        """The input guards' parameters (docs/reliability.md)."""
        d("max_pending_mb", describe(
            "Memory [MB] the decoded images waiting for their partners may hold; beyond it "
            "the oldest is dropped first, counted and reported (memory_limit).",
            fp_range=(1.0, 65536.0)))
        d("max_future_s", describe(
            "Refuse an image stamped more than this ahead of the node's clock [s] "
            "(future_stamp); 0 = no limit. An image is stamped at its exposure and arrives "
            "after it (readout: 2 s for LSSTCam), so only the offset between the camera's "
            "clock and this host's puts it ahead: below 1 ms with PTP, a few ms with NTP on "
            "a LAN (100 ms at worst). 1 s leaves a margin of 10x the worst NTP offset and "
            "refuses any clock that is wrong by more.", fp_range=(0.0, 1e6)))
        d("max_image_publishers", describe(
            "Refuse the images of an image topic while it has more than this many "
            "publishers, now or since they were last trusted (untrusted_source; 0 = no "
            "check). One camera publishes each topic: another publisher (an "
            "impostor, one that sends a visit and leaves, a stray bag replay) can mix its "
            "exposures into a visit, which no check of the pixels can tell. Every topic "
            "with more than one publisher is named on /diagnostics (WARN) either way.",
            read_only=True, int_range=(0, 64)))
        d("log_throttle_s", describe(
            "At most one log line per rejection reason per this period [s]; every rejection "
            "is counted on /diagnostics; 0 = a line each.", fp_range=(0.0, 3600.0)))

    def _validate_parameters(self, params: Sequence[Parameter]) -> SetParametersResult:
        new = {p.name: p.value for p in params}

        def get(n):
            return new[n] if n in new else self._param(n)

        if any(n in new for n in _SETTINGS_PARAMS):
            if get("solver") not in _SOLVERS:
                return result(False, f"solver must be one of {_SOLVERS}, got {get('solver')!r}")
            try:
                validate_settings(EstimatorSettings.from_params(get))
            except ConfigError as exc:
                return result(False, str(exc))
            except Exception as exc:  # noqa: BLE001 - a bad value is refused, never raised
                return result(False, f"{type(exc).__name__}: {exc}")
        if "input_mode" in new and new["input_mode"] not in _INPUT_MODES:
            return result(False, f"input_mode must be one of {_INPUT_MODES}, got "
                                 f"{new['input_mode']!r}")
        for n, v in new.items():
            if n.startswith("sensors.") and n.endswith(".flip") and v not in FLIPS:
                return result(False, f"{n} must be one of {FLIPS}, got {v!r}")
            bad = string_param_problem(n, v, MAX_STRING_PARAM_LEN)
            if bad is not None:
                return result(False, bad)
        return result(True)

    def _apply_parameters(self, params: Sequence[Parameter]) -> None:
        names = {p.name for p in params}
        with self._lock:
            if self.pool is None:
                return  # unconfigured: the values are read on configure
            if "frame_id" in names:
                self.frame_id = self._param("frame_id")
            change = self.pipeline.apply(names)
            if change == "rewarm":
                self.get_logger().info(f"estimator settings now {self.settings}; re-warming")
                self._start_warm_up()
            elif change == "seeing":
                # The seeing may follow the seeing monitor visit by visit: the workers'
                # caches stay valid (the blur reference is cached per seeing).
                self.get_logger().info(f"seeing now {self.settings.seeing_fwhm_arcsec:g}"
                                       " arcsec FWHM")

    # ------------------------------------------------------------------ warm-up
    def _start_warm_up(self) -> None:
        with self._lock:
            self._warm_generation += 1
            gen = self._warm_generation
            self._warm = {}
        t0 = time.monotonic()
        frames = self.pipeline.frame_warm()
        if frames is not None and not self._heap_prefault_mb:
            self._prefault_heap(frames)
        for c in self.corners:
            self._warm_corner(c, gen, t0, attempt=1)

    def _prefault_heap(self, frames: FrameFiles) -> None:
        """Map heap pages for one visit's frames now (runtime.memory), where the process
        keeps its freed heap (the cwfs-ros entry points set that up): the served half-chips
        as float32 (256 MB for four whole LSST corners), at most ``max_pending_mb``. The
        first visit's 32 MB takes then reuse them instead of faulting pages in."""
        visit_bytes = sum(frames_nbytes(frames, self.corners).values())
        mb = min(float(self._param("max_pending_mb")), visit_bytes / 1e6)
        if prefault_heap(int(mb * 1e6)):
            self._heap_prefault_mb = mb

    def _warm_corner(self, corner: str, gen: int, t0: float, attempt: int) -> None:
        (f,) = self.pool.warm_up({corner: (self.fields[corner]["intra"],
                                           self.fields[corner]["extra"])}, self.settings,
                                 frames=self.pipeline.frame_warm())
        f.add_done_callback(lambda f: self._warm_done(f, corner, gen, t0, attempt))

    def _warm_done(self, f: Future, corner: str, gen: int, t0: float, attempt: int) -> None:
        try:
            info = f.result()
        except BaseException as exc:  # noqa: BLE001
            info = {"corner": corner, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        cancelled = f.cancelled()  # the pool is shutting down: nothing to retry
        if not info.get("ok") and attempt < _WARM_ATTEMPTS and not cancelled:
            # A worker that died during its warm-up (killed, out of memory) is restarted by
            # the next job it is given: warm it again rather than report ERROR for good.
            with self._lock:
                current = gen == self._warm_generation
            if current:
                self.get_logger().warning(f"warm-up of {corner} failed ({info.get('error')}); "
                                          f"retrying ({attempt + 1}/{_WARM_ATTEMPTS})")
                try:
                    self._warm_corner(corner, gen, t0, attempt + 1)
                    return
                except Exception as exc:  # noqa: BLE001 - e.g. the pool is shut down
                    info = {"corner": corner, "ok": False,
                            "error": f"{type(exc).__name__}: {exc}"}
        with self._lock:
            if gen != self._warm_generation:
                return
            self._warm[corner] = info
            done = len(self._warm) == len(self.corners)
            tiles = sum(int(w.get("tiles", 0)) for w in self._warm.values())
            loaded = sum(int(w.get("tiles_loaded", 0)) for w in self._warm.values())
            self.workload.record_warm(int(info.get("pid", 0)), info.get("caches"))
        if not info.get("ok"):
            self.get_logger().error(f"warm-up of {corner} failed: {info.get('error')}")
        if info.get("tile_store"):  # a rejected tile or failed write: rebuilt, next start slow
            self.get_logger().warning(f"tile store of {corner}'s worker: {info['tile_store']}")
        if done:
            self.get_logger().info(
                f"workers warm after {time.monotonic() - t0:.2f} s"
                + (f" ({tiles} field tiles of the half-chips made, {loaded} of them read "
                   f"from the tile store)" if tiles else ""))

    @property
    def ready(self) -> bool:
        """All served corners have warm worker caches."""
        with self._lock:
            return len(self._warm) == len(self.corners) and all(
                w.get("ok") for w in self._warm.values())

    # ------------------------------------------------------------------ images
    def _publisher_count(self, corner: str, side: str) -> int | None:
        """Publishers matched on the image topic (the subscription's own count: no graph
        query), or None without a subscription."""
        sub = self._image_subs.get((corner, side))
        return None if sub is None else int(sub.get_publisher_count())

    def _image_callback(self, corner: str, side: str):
        def cb(msg: Image, info=None) -> None:
            try:
                gap = (self.image_gaps[(corner, side)].note(
                    info, self._publisher_count(corner, side)) if info is not None else 0)
                if gap:
                    self._reject(Rejection(
                        "queue_dropped", f"{gap} {side} image(s) of {corner} never taken: "
                        "the queue overflowed (a burst faster than the node takes them)",
                        corner, side), warn=True)
                if not self.is_active:
                    self._ignore_inactive(f"{side} image of {corner}", corner, side)
                    return
                self._on_image(msg, corner, side)
            except Exception as exc:  # noqa: BLE001 - never let a message kill the node
                self._reject(Rejection("internal_error", f"{corner} {side} image: "
                                       f"{type(exc).__name__}: {exc}", corner, side))
        return cb

    def _ignore_inactive(self, what: str, corner: str = "", side: str = "") -> None:
        """An input that came while the node is not active: counted, logged, not used."""
        state = self.lifecycle_state
        self._reject(Rejection("inactive", f"{what} not processed: the node is {state} "
                               f"(activate: cwfs-ros lifecycle set {self.get_name()} activate)",
                               corner, side), warn=True)

    def _on_image(self, msg: Image, corner: str, side: str) -> None:
        """An image through the pipeline's guards, decoding and pairing; a pair to its job."""
        refused = (self.pipeline.refusal(msg, corner, side, self.get_clock().now().nanoseconds)
                   or self._source_refusal(msg, corner, side))
        if refused is not None:
            self._reject(refused, warn=True)
            # Refused for what it is, it still pairs: its corner's result names the reason.
            rec = self.pipeline.refused_record(refused, time.monotonic())
            if rec is None:
                return
        else:
            # Decoded outside the lock: a frame takes a while, and the timers wait on the lock.
            rec, bad = self.pipeline.record(msg, corner, side, time.monotonic())
            if bad is not None:
                self._reject(bad, warn=True)
        with self._lock:
            self.stats["images"] += 1
            step = self.pipeline.add_record(rec)
        for r in step.dropped:
            self._publish_unpaired(r)
        if step.rejection is not None:
            self._reject(step.rejection, warn=True)
            if step.rejection.reason == "conflicting_images":
                self._on_conflict(step.rejection)
        if step.pair is not None:
            self._process_pair(step.pair)

    def image_source_problem(self, corner: str, side: str) -> str | None:
        """Why an image of that corner and side taken now would be ``untrusted_source``, or
        None (:meth:`_source_refusal`)."""
        trust = self._image_trust.get((corner, side))
        return None if trust is None else trust.problem()

    def _source_refusal(self, msg: Image, corner: str, side: str) -> Rejection | None:
        """``untrusted_source`` while the image's topic has more than ``max_image_publishers``
        publishers, now or since they were last trusted (:class:`PublisherTrust`: a camera
        that publishes one visit and leaves before its images are taken is still counted;
        fewer are fine: a camera that sent its last visit and left; 0 = no check), naming
        them (docs/reliability.md, Who may act)."""
        why = self.image_source_problem(corner, side)
        if why is None:
            return None
        return Rejection("untrusted_source", f"{side} image of {corner}: {why}: which camera "
                         "took it cannot be told", corner, side, stamp_to_ns(msg.header.stamp))

    def _refresh_image_publishers(self) -> dict[tuple[str, str], list[str]]:
        """The publishers of each served image topic, from the ROS graph (~0.1 ms a topic):
        ``namespace/node (gid ...)`` labels (:func:`.common.endpoint_label`)."""
        out: dict[tuple[str, str], list[str]] = {}
        for c, s in list(self._image_subs):
            try:
                infos = self.get_publishers_info_by_topic(
                    self.resolve_topic_name(image_topic(c, s)))
            except Exception:  # noqa: BLE001 - a graph query must not break an image
                continue
            out[(c, s)] = [endpoint_label(i) for i in infos]
        with self._lock:
            self.image_publishers = out
        return out

    def _on_conflict(self, rej: Rejection) -> None:
        """Two different images for one corner, side and stamp: the corner's visit is
        invalid (:meth:`WavefrontPipeline.conflict` says how)."""
        with self._lock:
            unpaired, vec = self.pipeline.conflict(rej)
        if unpaired is not None:
            self._publish_unpaired(unpaired, count=False)
        if vec is not None:
            self._publish_vector(vec)

    def _process_pair(self, pair: PairReady) -> None:
        """The pair's job on the corner's worker (or its invalid outcome at once)."""
        with self._lock:
            self.stats["pairs"] += 1
            job = self.pipeline.job_for(pair)
        if isinstance(job, CornerOutcome):
            self._publish_outcome(job, count=False)
            return
        if isinstance(job, CornerJob):
            fut = self.pool.submit(job)
        else:
            with self._lock:
                self.stats["frame_pairs"] += 1
            fut = self.pool.submit_frames(job)
        fut.add_done_callback(self._on_future)

    def _on_future(self, f: Future) -> None:
        if not self.is_active:  # deactivated while it ran: its managed publisher is off
            self._ignore_inactive("an estimate finished after deactivation")
            return
        try:
            self._publish_outcome(f.result())
        except Exception as exc:  # noqa: BLE001
            self._publish_failed(exc)

    def _publish_unpaired(self, r: Rejection, assemble: bool = True,
                          count: bool = True) -> None:
        """Report a half visit dropped unpaired (the pairing timeout, or its visit published
        without it), and say so on the corner's topic. A failure to publish is reported, not
        raised, so that it does not stop the others of the same pass. ``count``: False when
        ``r`` was already counted."""
        if count:
            self._reject(r, warn=True)
        try:
            with self._lock:
                out = self.pipeline.unpaired_outcome(r)
            self._publish_outcome(out, count=False, assemble=assemble)
        except Exception as exc:  # noqa: BLE001
            self._publish_failed(exc)

    def _publish_failed(self, exc: BaseException) -> None:
        """A corner result that could not be published: counted and reported like any
        rejection (the log alone would leave /diagnostics saying all is well)."""
        self.get_logger().error(f"publishing a corner result failed: {exc}")
        self._reject(Rejection("publish_failed", f"a corner result could not be published: "
                               f"{type(exc).__name__}: {exc}"))

    def _publish_outcome(self, out: CornerOutcome, count: bool = True,
                         assemble: bool = True) -> None:
        """Publish a corner's result (and assemble it, unless ``assemble`` is False: its visit
        was already published). ``count``: count an invalid one as a rejection (False when
        its cause was already counted, e.g. a decoding error).

        The message's frame_id is the ``frame_id`` parameter, never the images' own: the
        Zernikes are in the focal-plane frame whatever frame the camera names its images in.
        """
        c = out.corner
        with self._lock:
            out, replaced = self.pipeline.settle(out)
            count = count and not replaced
            self.stats["corners_valid" if out.valid else "corners_invalid"] += 1
            self.last_compute_ms[c] = out.compute_ms
            self.workload.record(c, out.compute_ms, out.worker_pid, out.caches)
            self.last_status[c] = out.status
        if not out.valid and count:
            self._reject(Rejection(out.reason or "invalid", f"{c}: {out.status}", c, "",
                                   out.stamp_ns), warn=True)
        fi, fe = self.fields[c]["intra"], self.fields[c]["extra"]
        msg = corner_wavefront_msg(out, field_intra_deg=fi, field_extra_deg=fe,
                                   frame_id=self.frame_id)
        self.pub_corner[c].publish(msg)
        if self.assembler is not None and assemble:
            self._assemble(out)
        self._maybe_rebalance()

    # ------------------------------------------------------------------ workers
    def _maybe_rebalance(self) -> None:
        """Move corners between workers when their measured costs say a busier worker would
        be relieved by a fifth or more (:meth:`WorkloadMonitor.proposal`). A moved corner is
        warmed on its new worker first, and served there from the job after that."""
        with self._lock:
            pool = self.pool
            if self._rebalancing or pool is None or not self.ready:
                return
            new = self.workload.proposal(pool.affinity, pool.n_workers)
            if new is None:
                return
            self._rebalancing = True
            gen, old = self._warm_generation, dict(pool.affinity)
        moved = {c: i for c, i in new.items() if old[c] != i}
        futures = [pool.warm_up({c: (self.fields[c]["intra"], self.fields[c]["extra"])},
                                self.settings, frames=self.pipeline.frame_warm(), slot=i)[0]
                   for c, i in moved.items()]
        left = [len(futures)]

        def done(_f: Future) -> None:
            with self._lock:
                left[0] -= 1
                if left[0]:
                    return
                ok = all(not f.cancelled() and f.exception() is None and f.result().get("ok")
                         for f in futures)
                if ok and self.pool is pool and gen == self._warm_generation:
                    pool.assign(new)
                self._rebalancing = False
            costs = self.workload.costs_s(new)
            self.get_logger().info(
                ("corners reassigned by measured cost (p90 " if ok else
                 "corner reassignment abandoned (a warm-up failed; p90 ")
                + ", ".join(f"{c} {costs.get(c, float('nan')):.2f} s" for c in sorted(new))
                + f"): {old} -> {new}")

        for f in futures:
            f.add_done_callback(done)

    # ------------------------------------------------------------------ assembly
    def _remote_corner_callback(self, corner: str):
        """The callback of another producer's ``corner`` topic: a message must be about the
        corner of the topic it came on.  One claiming another corner (a misconfigured or
        wrongly remapped producer) would fill that corner's slot, possibly one this node
        serves itself, with a wavefront measured elsewhere: it is rejected."""
        def on_msg(msg: CornerWavefront) -> None:
            if not self.is_active:
                self._ignore_inactive(f"a CornerWavefront of {corner}", corner)
                return
            try:
                bad = stamp_problem(msg.header.stamp)
                if bad is not None:
                    self._reject(Rejection("bad_stamp", f"a CornerWavefront of {corner}: {bad}",
                                           corner, "", 0), warn=True)
                    return
                if msg.corner != corner:
                    self._reject(Rejection(
                        "corner_mismatch", f"a CornerWavefront on {corner}'s topic claims corner "
                        f"{msg.corner!r}: not assembled", corner, "",
                        stamp_to_ns(msg.header.stamp)), warn=True)
                    return
                entry = corner_entry_from_msg(msg)
                checked = checked_entry(entry)
                if msg.valid and not checked.valid:
                    # Assembled as invalid (its corner is then left out of the solve), and
                    # reported: a producer sending unusable results flagged valid is broken.
                    self._reject(Rejection("bad_corner_wavefront", f"a CornerWavefront of "
                                           f"{corner} flagged valid: {checked.status}", corner,
                                           "", entry.stamp_ns), warn=True)
                self._assemble(checked)
            except Exception as exc:  # noqa: BLE001 - a message must never crash the node
                self._reject(Rejection("bad_corner_wavefront", f"{type(exc).__name__}: {exc}"))
        return on_msg

    def _assemble(self, entry: CornerEntry | CornerOutcome) -> None:
        with self._lock:
            vec, rej = self.pipeline.assemble(entry, time.monotonic())
        if rej is not None:
            self._reject(rej, warn=True)
        if vec is not None:
            self._publish_vector(vec)

    def _publish_vector(self, vec: VisitVector) -> None:
        with self._lock:
            self.stats["visits_published"] += 1
            if not vec.complete:
                self.stats["visits_incomplete"] += 1
            # Local corners that never produced a pair for this visit: closed, so that a
            # late image is reported as late instead of starting a new visit.
            closures = self.pipeline.close_missing(vec)
        for r in closures:
            # The vector already holds the corner as missing: not assembled again.
            self._publish_unpaired(r, assemble=False)
        if not vec.complete:
            with self._lock:
                self.last_incomplete = (time.monotonic(), f"visit {vec.stamp_ns}: {vec.status}")
            self.get_logger().warning(f"visit {vec.stamp_ns} published incomplete: {vec.status}")
        self.pub_vector.publish(wavefront_vector_msg(vec, self.frame_id))

    def _expire(self) -> None:
        if not self.is_active:
            return  # paused: what waits is timed out once active again, never dropped unsaid
        try:
            self._expire_now()
        except Exception as exc:  # noqa: BLE001 - a timer callback must not kill the node
            self._reject(Rejection("internal_error", f"visit timeout handling: "
                                   f"{type(exc).__name__}: {exc}"), warn=True)

    def _expire_now(self) -> None:
        now = time.monotonic()
        with self._lock:
            unpaired = self.pipeline.expire_pairs(now)
        for r in unpaired:
            self._publish_unpaired(r)
        with self._lock:
            due = self.pipeline.expire_visits(now)
        for vec in due:
            self._publish_vector(vec)

    # ------------------------------------------------------------------ diagnostics
    def _reject(self, rej: Rejection, warn: bool = False) -> None:
        self.rejected.add(rej.reason, rej.message)
        if warn:
            due, n = self.rejected.log_due(rej.reason, float(self._param("log_throttle_s")))
            if due:
                more = f" (+{n} more of this reason not logged)" if n else ""
                self.get_logger().warning(f"rejected ({rej.reason}): {rej.message}{more}")

    def diagnostics(self):
        name = f"{self.get_name()}: wavefront estimation"
        unconfigured = self.lifecycle_status(name, "cwfs_corner_sensors")
        if unconfigured is not None:
            return unconfigured
        lifecycle = self.lifecycle_state
        with self._lock:
            pool = self.pool
            if pool is None:  # released while this ran
                return self.lifecycle_status(name, "cwfs_corner_sensors")
            warm = dict(self._warm)
            stats = dict(self.stats)
            pending_images = self.pairing.pending_count()
            pending_visits = self.assembler.pending_count() if self.assembler else 0
            compute = dict(self.last_compute_ms)
            last = dict(self.last_status)
            incomplete = self.last_incomplete
            pending_mb = self.pairing.pending_bytes() / 1e6
            promise, promise_s = self.workload.promise(
                pool.affinity, pool.queued(), float(self._param("visit_timeout_s")))
        self.foreign = refresh_foreign(self, self._owned_topics())
        shared = {k: v for k, v in self._refresh_image_publishers().items() if len(v) > 1}
        level, state, message = self._health(warm, lifecycle, incomplete, promise, shared)
        values = [("state", state), ("lifecycle", lifecycle),
                  ("corners", " ".join(self.corners)),
                  ("workers", pool.n_workers), ("worker_restarts", pool.restarts),
                  ("worker_rewarms", pool.rewarms),
                  ("frame_transport", f"shared memory {pool.frames_shared}, "
                                      f"pipe {pool.frames_piped}"),
                  ("heap_prefault_mb", f"{self._heap_prefault_mb:g}"),
                  ("assemble", self.assemble), ("settings", str(self.settings)),
                  *stats.items(), ("pending_images", pending_images),
                  ("pending_visits", pending_visits), ("pending_mb", f"{pending_mb:.1f}"),
                  ("max_pending_mb", self._param("max_pending_mb")),
                  ("foreign_publishers", "; ".join(self.foreign) or "none")]
        values += [(f"queue_dropped.{c}.{s}", g.describe())
                   for (c, s), g in sorted(self.image_gaps.items()) if g.dropped or not g.exact]
        values += [(f"publishers.{c}.{s}", f"{len(v)}: {', '.join(v)}")
                   for (c, s), v in sorted(shared.items())]
        values += [(f"compute_ms.{c}", f"{v:.1f}") for c, v in sorted(compute.items())]
        values += self._workload_values(pool, promise_s)
        values += [(f"status.{c}", v) for c, v in sorted(last.items())]
        values += [(f"warm_s.{c}", f"{w.get('total_s', 0.0):.2f}") for c, w in
                   sorted(warm.items())]
        values += self.rejected.key_values()
        values += self.qos_events.key_values()
        return diagnostic_status(name, level, message, values,
                                 hardware_id="cwfs_corner_sensors")

    def _workload_values(self, pool: CornerPool, promise_s: float) -> list[tuple[str, str]]:
        """The workers' assignment, queues, costs and caches, for /diagnostics."""
        with self._lock:
            costs = self.workload.costs_s(pool.affinity)
            values = [("affinity", " ".join(f"{c}:{i}" for c, i in sorted(pool.affinity.items()))),
                      ("visit_timeout_s", f"{float(self._param('visit_timeout_s')):g}"),
                      ("visit_time_p90_s", f"{promise_s:.2f}" if promise_s == promise_s
                       else "not yet measured")]
            values += [(f"queued.worker{i}", str(n)) for i, n in sorted(pool.queued().items())]
            values += [(f"cost_p90_s.{c}", f"{v:.2f}") for c, v in sorted(costs.items())]
            values += self.workload.cache_values()
            values += [(f"warm_tiles.{c}", f"{int(w.get('tiles', 0))} in "
                        f"{float(w.get('tiles_s', 0.0)):.1f} s "
                        f"({int(w.get('tiles_loaded', 0))} from the tile store)") for c, w in
                       sorted(self._warm.items()) if w.get("tiles")]
            values += [(f"tile_store.{c}", str(w["tile_store"])) for c, w in
                       sorted(self._warm.items()) if w.get("tile_store")]
        return values

    def _health(self, warm: dict[str, dict], lifecycle: str,
                incomplete: tuple[float, str] | None,
                promise: Problem | None = None,
                shared: dict[tuple[str, str], list[str]] | None = None
                ) -> tuple[bytes, str, str]:
        """(level, state, message) of /diagnostics: the worst condition first. ``shared``:
        image topics with more than one publisher, and who they are."""
        failed = [w for w in warm.values() if not w.get("ok")]
        if failed:
            level, state = ERROR, "error"
            message = "warm-up failed: " + "; ".join(f"{w['corner']}: {w.get('error')}"
                                                      for w in failed)
        elif lifecycle != "active":
            level, state = WARN, "ready" if len(warm) == len(self.corners) else "warming"
            message = f"{lifecycle}: {self._inactive_effect()}"
        elif len(warm) < len(self.corners):
            level, state = WARN, "warming"
            message = f"warming up workers ({len(warm)}/{len(self.corners)} corners ready)"
        elif self.qos_events.problem() is not None:
            level, state = ERROR, "ready"
            message = f"QoS: {self.qos_events.problem()}"
        elif shared:
            (c, s), names = sorted(shared.items())[0]
            what = ("its images are refused (untrusted_source)"
                    if int(self._param("max_image_publishers")) > 0 else "its images are taken")
            level, state = WARN, "ready"
            message = (f"ready; {len(names)} publishers on the {image_topic(c, s)} image topic "
                       f"({', '.join(names)}): {what}")
        elif self.foreign:
            level, state = WARN, "ready"
            message = f"ready; another publisher on a topic of this node: {self.foreign[0]}"
        elif promise is not None:
            level, state = WARN, "ready"
            message = f"ready; {promise.status}"
        elif self.rejected.recent(10.0):
            level, state = WARN, "ready"
            message = f"ready; recently rejected input: {self.rejected.last_message}"
        elif incomplete is not None and time.monotonic() - incomplete[0] < 60.0:
            level, state = WARN, "ready"
            message = f"ready; a recent visit was published incomplete: {incomplete[1]}"
        else:
            level, state, message = OK, "ready", "ready"
        return level, state, message

    def _owned_topics(self) -> list[str]:
        out = [corner_topic(c) for c in self.corners]
        return out + [VECTOR_TOPIC] if self.assemble else out



def main(args: list[str] | None = None) -> int:
    """``wavefront_node [--ros-args ...]``: run this node alone (parameters: config/params.yaml)."""
    from cwfs_ros.ros.launch import run_node_main

    return run_node_main(NODE_NAME, args)


if __name__ == "__main__":
    raise SystemExit(main())
