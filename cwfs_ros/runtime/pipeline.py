"""The wavefront side of the loop, decided in one place: image -> pair -> job -> visit (no ROS).

:class:`WavefrontPipeline` holds what wavefront_node decides about its inputs, and nothing
about how they arrive or where results go: which images are refused (a bad or future stamp, a
``frame_id`` naming another corner or side), the decoding and the pairing (with the memory
bound on waiting images), which job a pair becomes (a stamp :class:`CornerJob`, a frame
:class:`~cwfs_ros.frames.selection.CornerFrameJob`, or at once an invalid
:class:`CornerOutcome`), how a corner's outcome is settled (a conflict found after pairing
makes it invalid) and assembled into a :class:`VisitVector`, and what the timeouts expire.

Its methods *return* what to do; the caller does it. The live node
(:mod:`cwfs_ros.ros.wavefront_node`) sends the jobs to its worker processes, publishes and
counts; the offline replay (:mod:`cwfs_ros.cli.replay`) runs the same jobs inline with
:func:`run_job` and feeds the outcomes back. One set of rules thus serves both, and a
replayed bag gives the numbers the live graph published (frames included).

The pipeline is not thread-safe: the node calls it under its own lock. Times: ``now`` is in
seconds on the caller's clock (monotonic for the node, the bag's receive times for a replay);
``clock_ns`` is the time the future-stamp guard compares with (the node's ROS clock, the
bag's receive stamp).
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cwfs_ros.config import tile_store_dir
from cwfs_ros.errors import ConfigError, Problem
from cwfs_ros.layout import CORNERS, SIDES
from cwfs_ros.runtime.corner_pool import (
    CornerJob,
    CornerOutcome,
    FrameFiles,
    invalid_outcome,
    run_corner_job,
    run_frame_job,
)
from cwfs_ros.runtime.images import full_scale, full_scale_message
from cwfs_ros.runtime.visits import (
    CornerEntry,
    ImageRecord,
    PairingBuffer,
    PairReady,
    Rejection,
    VisitAssembler,
    VisitVector,
    corner_entry_from_outcome,
    image_record_from_msg,
    load_corner_fields,
    stamp_to_ns,
)
from cwfs_ros.wfs.orientation import Orientation
from cwfs_ros.wfs.settings import EstimatorSettings, validate_settings

__all__ = [
    "PAIRED_REFUSALS",
    "SETTINGS_PARAMS",
    "ImageStep",
    "WavefrontPipeline",
    "frame_id_problem",
    "run_job",
    "served_corners",
    "stamp_problem",
]

Getter = Callable[[str], Any]
# The estimator settings' parameters; all but the seeing invalidate the workers' caches.
SETTINGS_PARAMS = ("instrument", "band", "solver", "outer_iterations", "pad_px",
                   "seeing_fwhm_arcsec")
# Conflicts found after pairing that are remembered (oldest forgotten first).
_MAX_CONFLICTS = 256
# Refusals at the door whose image still pairs (:meth:`WavefrontPipeline.refused_record`).
PAIRED_REFUSALS = frozenset({"frame_mismatch", "too_large", "untrusted_source"})


def stamp_problem(stamp: Any) -> Problem | None:
    """Why a header stamp (``sec``, ``nanosec``) cannot be used, or None.

    builtin_interfaces/Time requires ``nanosec`` below 1e9, but nothing enforces it: such a
    stamp names a time that does not round-trip (the excess carries into ``sec``, which can
    overflow its int32), so an output stamped with it would be refused at publication or go
    out with another visit's stamp. A negative ``sec`` is before 1970: no exposure's time.
    """
    if int(stamp.nanosec) >= 1_000_000_000:
        return Problem("bad_stamp", f"nanosec {int(stamp.nanosec)} is not below 1e9 "
                       "(builtin_interfaces/Time)")
    if int(stamp.sec) < 0:
        return Problem("bad_stamp", f"sec {int(stamp.sec)} is before 1970: no exposure's "
                       "time (a clock or a driver that sets its stamps wrongly)")
    return None


_CORNER_RE = re.compile(r"(?<![0-9A-Za-z])R(00|04|40|44)(?![0-9])", re.IGNORECASE)
# LSST names the corner wavefront half-chips SW0 (extra-focal) and SW1 (intra-focal).
_SIDE_WORDS = {"intra": "intra", "extra": "extra", "sw0": "extra", "sw1": "intra"}
_SIDE_RE = re.compile(r"(?<![0-9A-Za-z])(intra|extra|sw0|sw1)(?![0-9A-Za-z])", re.IGNORECASE)


def frame_id_problem(frame_id: str, corner: str, side: str) -> str | None:
    """Why an image's ``frame_id`` contradicts its topic's corner and side, or None.

    An empty frame_id, or one naming no corner and no side (``focal_plane``), says nothing
    and is taken. One naming a corner (``R00`` .. ``R44``, as a word) must name the topic's
    corner only; one naming a side (``intra``/``extra``, or LSST's ``SW1``/``SW0``) must name
    the topic's side only.
    """
    if not frame_id:
        return None
    corners = {"R" + m.group(1) for m in _CORNER_RE.finditer(frame_id)}
    if corners and corners != {corner}:
        return (f"frame_id {frame_id[:80]!r} names {', '.join(sorted(corners))}, not the "
                f"topic's corner {corner}")
    sides = {_SIDE_WORDS[m.group(1).lower()] for m in _SIDE_RE.finditer(frame_id)}
    if sides and sides != {side}:
        return (f"frame_id {frame_id[:80]!r} names the {', '.join(sorted(sides))} side, not "
                f"the topic's {side}")
    return None


def served_corners(names: Iterable[str]) -> tuple[str, ...]:
    """The ``corners`` parameter as distinct known names in layout order (ConfigError if not)."""
    corners = list(names)
    bad = [c for c in corners if c not in CORNERS] or ([] if corners else ["(none)"])
    if bad or len(set(corners)) != len(corners):
        raise ConfigError(f"parameter corners must be distinct names among {CORNERS}, "
                          f"got {corners}")
    return tuple(c for c in CORNERS if c in corners)


def run_job(job: Any) -> CornerOutcome:
    """Run a job of :meth:`WavefrontPipeline.job_for` in this process (what a worker runs)."""
    if isinstance(job, CornerOutcome):
        return job
    if isinstance(job, CornerJob):
        return run_corner_job(job)
    return run_frame_job(job)


@dataclass
class ImageStep:
    """What adding one image record to the pairing gave.

    Attributes:
        pair: a pair ready for :meth:`WavefrontPipeline.job_for`, or None.
        dropped: older waiting images dropped for the memory bound (``memory_limit``); each
            is reported and its corner published invalid
            (:meth:`WavefrontPipeline.unpaired_outcome`).
        rejection: the pairing's refusal of this image (``duplicate``, ``late``,
            ``conflicting_images`` ...), or None; a conflict also goes to
            :meth:`WavefrontPipeline.conflict`.
    """

    pair: PairReady | None = None
    dropped: list[Rejection] = field(default_factory=list)
    rejection: Rejection | None = None


class WavefrontPipeline:
    """wavefront_node's decisions (see the module docstring), from its parameters.

    Args:
        get: ``get(name) -> value`` of wavefront_node's parameters (the node's current
            values, or a replay's resolved YAML); read again where the node reads a
            parameter per image (``input_mode``, ``max_pending_mb`` ...).
        corners: the corners served (pairing); see :func:`served_corners`.
        assemble: build the 76-vector here (the node's ``assemble``).

    Raises ConfigError for a sensor file lacking a served corner, bad estimator settings or
    a bad selection file (the workers read it per frame visit: refused at start instead).
    """

    def __init__(self, get: Getter, corners: Iterable[str], *, assemble: bool = True) -> None:
        from cwfs_ros.frames.selection import load_selection_config

        self._get = get
        self.corners = served_corners(corners)
        self.fields = load_corner_fields(get("sensor_config") or None)
        missing = [c for c in self.corners if c not in self.fields]
        if missing:
            raise ConfigError(f"no field points for corners {missing} in the sensor config")
        self.settings = EstimatorSettings.from_params(get)
        validate_settings(self.settings)
        load_selection_config(get("selection_config") or None, solver=self.settings.solver)
        self.orientations = {(c, s): self._orientation(c, s)
                             for c in self.corners for s in SIDES}
        tol_ns, timeout_s = self._tolerance_ns(), float(get("visit_timeout_s"))
        self.pairing = PairingBuffer(self.corners, tolerance_ns=tol_ns, timeout_s=timeout_s)
        self.assembler = (VisitAssembler(tolerance_ns=tol_ns, timeout_s=timeout_s)
                          if assemble else None)
        # (corner, visit stamp) of visits whose corner had conflicting images after pairing:
        # their estimate is made invalid (bounded, oldest forgotten first).
        self._conflicts: OrderedDict[tuple[str, int], str] = OrderedDict()
        # (corner, side) -> (the node's clock then, ns; the latest refusal of an image's
        # stamp there), until an image of that side is taken: named by its partner's
        # unpaired outcome if it came after that partner's exposure.
        self._door_refused: dict[tuple[str, str], tuple[int, Rejection]] = {}

    def _orientation(self, corner: str, side: str) -> Orientation:
        return Orientation(int(self._get(f"sensors.{corner}.{side}.rot90")),
                           str(self._get(f"sensors.{corner}.{side}.flip")))

    def frame_warm(self) -> FrameFiles | None:
        """What the workers' warm-up builds for frames (:attr:`warms_frames`), or None."""
        if not self.warms_frames:
            return None
        return FrameFiles(str(self._get("sensor_config") or ""),
                          str(self._get("selection_config") or ""),
                          tile_store_dir(str(self._get("tile_store"))))

    @property
    def warms_frames(self) -> bool:
        """Whether the workers' warm-up builds the half-chips' field tiles: with
        ``input_mode: frames`` (a camera that sends frames), so that the first frames visit
        costs what any other does; stamps and ``auto`` warm the stamp path only (the tiles
        are then built as frames need them, ~1.2 s each on the first visits)."""
        return str(self._get("input_mode")) == "frames"

    def _tolerance_ns(self) -> int:
        return int(round(float(self._get("pairing_tolerance_s")) * 1e9))

    def apply(self, names: set[str]) -> str:
        """Take changed parameters ``names`` (their new values through ``get``). Returns
        ``"rewarm"`` when the workers' caches no longer fit the settings (or frames now need
        their tiles), ``"seeing"`` when
        only the seeing changed (the caches stay valid: the blur reference is cached per
        seeing), ``""`` otherwise."""
        if "pairing_tolerance_s" in names:
            self.pairing.tolerance_ns = self._tolerance_ns()
            if self.assembler is not None:
                self.assembler.tolerance_ns = self.pairing.tolerance_ns
        if "visit_timeout_s" in names:
            self.pairing.timeout_s = float(self._get("visit_timeout_s"))
            if self.assembler is not None:
                self.assembler.timeout_s = self.pairing.timeout_s
        for c, s in self.orientations:
            if any(n.startswith(f"sensors.{c}.{s}.") for n in names):
                self.orientations[(c, s)] = self._orientation(c, s)
        if not names & set(SETTINGS_PARAMS):
            return "rewarm" if "input_mode" in names and self.warms_frames else ""
        self.settings = EstimatorSettings.from_params(self._get)
        return "rewarm" if names & (set(SETTINGS_PARAMS) - {"seeing_fwhm_arcsec"}) else "seeing"

    # ------------------------------------------------------------------ images
    def refusal(self, msg: Any, corner: str, side: str, clock_ns: int) -> Rejection | None:
        """The refusal of an Image message before decoding, or None (:meth:`_door_refusal`).
        A refusal of the stamp is kept until an image of that side pairs, so that its
        partner, dropped ``unpaired``, says what became of it (:meth:`unpaired_outcome`)."""
        rej = self._door_refusal(msg, corner, side, clock_ns)
        if rej is not None and rej.reason not in PAIRED_REFUSALS:
            self._door_refused[(corner, side)] = (int(clock_ns), rej)
        return rej

    def _door_refusal(self, msg: Any, corner: str, side: str, clock_ns: int
                      ) -> Rejection | None:
        """The refusal of an Image message before decoding, or None: a stamp no output could
        carry (``bad_stamp``), a stamp of 0 (``no_stamp``: a camera that never set it; every
        such image would claim one visit), one more than ``max_future_s`` ahead of
        ``clock_ns`` (``future_stamp``; not checked while ``clock_ns`` is 0), a pair of such
        images too large for ``max_pending_mb`` (``too_large``, :meth:`size_problem`: judged
        on height and width, before the digest and the decoding that would cost seconds and
        gigabytes), a ``frame_id`` naming another corner or side (``frame_mismatch``,
        :func:`frame_id_problem`)."""
        where = f"{side} image of {corner}"
        bad = stamp_problem(msg.header.stamp)
        if bad is not None:
            return Rejection("bad_stamp", f"{where}: {bad}", corner, side, 0)
        t = stamp_to_ns(msg.header.stamp)
        if t == 0:
            return Rejection("no_stamp", f"{where}: header.stamp is 0 (never set): an image "
                             "needs its exposure time to be paired and assembled", corner,
                             side, 0)
        ahead = float(self._get("max_future_s"))
        if ahead > 0 and clock_ns > 0 and t > clock_ns + ahead * 1e9:
            return Rejection("future_stamp", f"{where}: stamped "
                             f"{(t - clock_ns) / 1e9:.4g} s ahead of the clock (max_future_s "
                             f"{ahead:g})", corner, side, t)
        big = self.size_problem(msg)
        if big is not None:
            return Rejection("too_large", f"{where}: {big}", corner, side, t)
        bad_id = frame_id_problem(str(msg.header.frame_id), corner, side)
        if bad_id is not None:
            return Rejection("frame_mismatch", f"{where}: {bad_id}", corner, side, t)
        return None

    def size_problem(self, msg: Any) -> str | None:
        """Why an image is too large to be taken, from its ``height`` and ``width`` alone,
        or None: its pair at 8 bytes a pixel (2 x rows x cols x 8 B: float64, the widest
        type an image decodes to) must fit within ``max_pending_mb``. One image of the pair
        waits for the other in that memory, and the pair then goes to a worker; a larger
        pair could never be estimated, and its decoding alone would take the process
        gigabytes beyond the limit (an 8192 x 8192 image: 537 MB as float64)."""
        try:
            rows, cols = int(msg.height), int(msg.width)
        except (TypeError, ValueError):
            return None  # the decoder names it
        image_mb = rows * cols * 8 / 1e6
        limit_mb = float(self._get("max_pending_mb"))
        if 2 * image_mb <= limit_mb:
            return None
        return (f"{rows} x {cols} px is {image_mb:.0f} MB as float64, a pair "
                f"{2 * image_mb:.0f} MB, beyond max_pending_mb {limit_mb:g}: refused before "
                "decoding")

    @staticmethod
    def refused_record(rej: Rejection, received_s: float) -> ImageRecord | None:
        """The pairing record of an image refused at the door (:meth:`refusal`), or None.

        An image refused for what it is (:data:`PAIRED_REFUSALS`) still pairs, as an
        undecodable one does, so that its corner's result names the refusal at once instead
        of its partner timing out ``unpaired``. Refusals of the stamp itself do not pair:
        their stamp names no visit (0, malformed) or one far ahead that would close visits
        still to come.
        """
        if rej.reason not in PAIRED_REFUSALS:
            return None
        where = f"{rej.side} image of {rej.corner}: "
        detail = rej.message[len(where):] if rej.message.startswith(where) else rej.message
        return ImageRecord(rej.corner, rej.side, rej.stamp_ns, error=f"{rej.reason}: {detail}",
                           reason=rej.reason, received=float(received_s))

    def record(self, msg: Any, corner: str, side: str, received_s: float
               ) -> tuple[ImageRecord, Rejection | None]:
        """Decode an Image message (no state of the pipeline's: the caller may run it outside
        its lock). An undecodable one still pairs, so that its corner's result names the
        problem; the Rejection reports it. A stamp with pixels at its integer type's full
        scale is ``saturated``; a frame's only make their own star saturated (detection)."""
        rec = image_record_from_msg(msg, corner, side, received_s, full_scale_ok=True)
        if not rec.error and rec.full_scale_px and not self.is_frame_pair(rec.image, rec.image):
            rec.error = f"saturated: {full_scale_message(rec.full_scale_px, rec.encoding)}"
            rec.reason, rec.image = "saturated", None
        if not rec.error:
            return rec, None
        return rec, Rejection(rec.reason, f"{side} image of {corner}: {rec.error}", corner,
                              side, rec.stamp_ns)

    def add_record(self, rec: ImageRecord) -> ImageStep:
        """Pair a record; then drop the oldest waiting images while they hold more than
        ``max_pending_mb``."""
        self._door_refused.pop((rec.corner, rec.side), None)  # that side's latest image came
        pair, rej = self.pairing.add(rec)
        limit = float(self._get("max_pending_mb")) * 1e6
        dropped = []
        while self.pairing.pending_bytes() > limit:
            r = self.pairing.drop_oldest()
            if r is None:
                break
            dropped.append(r)
        return ImageStep(pair, dropped, rej)

    def conflict(self, rej: Rejection) -> tuple[Rejection | None, VisitVector | None]:
        """Two different images for one corner, side and stamp: the corner's visit is invalid.

        Found while the first image waited, the pairing closed the visit: returns the
        Rejection whose corner is to be published invalid now (its cause already counted).
        Found after pairing, it is remembered: the estimate in flight is made invalid by
        :meth:`settle`, or, already assembled, the corner is made invalid in its visit; a
        visit that this completes is returned.
        """
        c, t = rej.corner, rej.stamp_ns
        if not self.pairing.was_paired(c, t):
            return Rejection("conflicting_images", rej.message, c, rej.side, t), None
        self._conflicts[(c, t)] = rej.message
        while len(self._conflicts) > _MAX_CONFLICTS:
            self._conflicts.popitem(last=False)
        if self.assembler is None:
            return None, None
        _, vec = self.assembler.invalidate(c, t, f"conflicting_images: {rej.message}")
        return None, vec

    # ------------------------------------------------------------------ jobs
    def is_frame_pair(self, intra: np.ndarray, extra: np.ndarray) -> bool:
        """Frames (several stars, detection needed) or stamps (one donut each)?"""
        mode = str(self._get("input_mode"))
        if mode != "auto":
            return mode == "frames"
        side = int(self._get("frame_min_side_px"))
        return max(*np.shape(intra), *np.shape(extra)) >= side

    def job_for(self, pair: PairReady) -> Any:
        """What a pair becomes: a :class:`CornerJob` (stamps), a
        :class:`~cwfs_ros.frames.selection.CornerFrameJob` (frames), or, for a pair with an
        undecodable image, its invalid :class:`CornerOutcome` (its cause already reported)."""
        c = pair.corner
        fi, fe = self.fields[c]["intra"], self.fields[c]["extra"]
        if pair.error is not None:
            return invalid_outcome(c, pair.stamp_ns, pair.reason, pair.error, fi, fe,
                                   self.settings.solver)
        if self.is_frame_pair(pair.intra.image, pair.extra.image):
            from cwfs_ros.frames.selection import CornerFrameJob

            return CornerFrameJob(c, pair.stamp_ns, pair.intra.image, pair.extra.image,
                                  self.settings,
                                  sensor_config=str(self._get("sensor_config")),
                                  selection_config=str(self._get("selection_config")),
                                  full_scale=_full_scale_of(pair))
        return CornerJob(c, pair.stamp_ns, pair.intra.image, pair.extra.image, fi, fe,
                         self.settings, self.orientations[(c, "intra")],
                         self.orientations[(c, "extra")], hint=self._stamp_hint(pair))

    def _stamp_hint(self, pair: PairReady) -> str:
        """For images of a frame's size taken as stamps (``input_mode: stamps``): what to
        change if they hold several stars ("" otherwise)."""
        shape = np.shape(pair.intra.image)
        if max(*shape, *np.shape(pair.extra.image)) < int(self._get("frame_min_side_px")):
            return ""
        return (f"{shape[0]}x{shape[1]} images taken as one-donut stamps because input_mode "
                f"is {self._get('input_mode')}: frames with several stars need input_mode "
                f"frames")

    # ------------------------------------------------------------------ outcomes
    def _conflict_of(self, corner: str, stamp_ns: int) -> str | None:
        tol = self.pairing.tolerance_ns
        for (c, t), m in self._conflicts.items():
            if c == corner and abs(t - stamp_ns) <= tol:
                return m
        return None

    def settle(self, out: CornerOutcome) -> tuple[CornerOutcome, bool]:
        """The outcome to publish and whether it replaced ``out``: a valid estimate of a
        visit whose corner had conflicting images becomes invalid (``conflicting_images``,
        already counted when found)."""
        conflict = self._conflict_of(out.corner, out.stamp_ns) if out.valid else None
        if conflict is None:
            return out, False
        f = self.fields[out.corner]
        return invalid_outcome(out.corner, out.stamp_ns, "conflicting_images", conflict,
                               f["intra"], f["extra"], out.solver), True

    def unpaired_outcome(self, r: Rejection) -> CornerOutcome:
        """The invalid outcome of a half visit dropped unpaired (its corner says why, and what
        became of the other side's latest image if its stamp was refused)."""
        f = self.fields[r.corner]
        other = "extra" if r.side == "intra" else "intra"
        clock_ns, refused = self._door_refused.get((r.corner, other), (0, None))
        # Only a refusal after this half's exposure can be its partner's (an older one
        # belongs to an earlier visit; without a clock, 0, nothing can be said).
        exposed_ns = r.stamp_ns - self.pairing.tolerance_ns
        if refused is not None and exposed_ns > 0 and clock_ns >= exposed_ns:
            message = (f"{r.message}; the latest {other} image of {r.corner} was refused: "
                       f"{refused.reason}: {refused.message}")
        else:
            message = r.message
        return invalid_outcome(r.corner, r.stamp_ns, r.reason, message, f["intra"],
                               f["extra"], self.settings.solver)

    def assemble(self, entry: CornerEntry | CornerOutcome, now: float
                 ) -> tuple[VisitVector | None, Rejection | None]:
        """Add a corner (an entry, or this process's outcome) to its visit: the vector it
        completes, and the assembler's refusal. Nothing without an assembler."""
        if self.assembler is None:
            return None, None
        if isinstance(entry, CornerOutcome):
            entry = corner_entry_from_outcome(entry)
        return self.assembler.add(entry, now)

    def close_missing(self, vec: VisitVector) -> list[Rejection]:
        """A vector about to go out: close the served corners it holds as missing, so that
        a late image is reported as late instead of starting a new visit. The returned half
        visits are to be published invalid, not assembled again."""
        out: list[Rejection] = []
        for c, st in zip(vec.corners, vec.statuses, strict=True):
            if c in self.corners and st.startswith("missing"):
                out += self.pairing.close(c, vec.stamp_ns, "visit published without it")
        return out

    def expire_pairs(self, now: float) -> list[Rejection]:
        """Half visits whose partner did not come within the timeout (publish them invalid
        and assemble them, before :meth:`expire_visits`)."""
        return self.pairing.expire(now)

    def expire_visits(self, now: float) -> list[VisitVector]:
        """Visits due at ``now`` (the missing corners invalid)."""
        return ([] if self.assembler is None
                else self.assembler.expire(now, why_missing=self.pairing.why_missing))


def _full_scale_of(pair: PairReady) -> float | None:
    """The lower full scale of the pair's integer images (None: floats): a frame's pixels at
    it are saturated whatever the configured level."""
    tops = [full_scale(r.encoding) for r in (pair.intra, pair.extra) if r.encoding]
    tops = [t for t in tops if t is not None]
    return min(tops) if tops else None
