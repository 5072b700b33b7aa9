"""Offline replay of a recorded bag: the wavefront estimator and the OFC solver, without DDS.

``cwfs-ros replay BAG --out DIR [--params FILE ...]`` reads the 8 image topics
``/aos/wfs/<corner>/<intra|extra>/image`` of a bag (:mod:`cwfs_ros.ros.bag`) in bag-timestamp
order and runs, in this process, exactly what the live graph runs on them:

* wavefront_node's path: the node's own :class:`~cwfs_ros.runtime.pipeline.WavefrontPipeline`
  (input guards, decoding, pairing, the stamp :class:`~cwfs_ros.runtime.corner_pool.CornerJob`
  or, for frames, the :class:`~cwfs_ros.frames.selection.CornerFrameJob`, visit assembly and
  timeouts), its jobs run inline by the functions the node's worker processes run
  (:func:`~cwfs_ros.runtime.pipeline.run_job`);
* ofc_node's path: the :class:`~cwfs_ros.ofc.control.OFCSolver` of
  :func:`~cwfs_ros.ofc.control.solver_from_params`, one ``step`` per vector (state kept
  between visits, not advanced for ``dry_run``);

with the parameters the nodes would get: ``config/params.yaml`` (also their declared
defaults), then each ``--params`` file (``ros__parameters`` keyed by node name or
``/**``, nested keys flattened to dotted names, as rcl reads them). All four corners are
estimated whatever the ``corners`` parameter says (a bag may come from several wavefront_node
processes). Receive times and the pairing / visit timeouts use the bag timestamps (receive
times, s), so a visit that timed out live times out here too; the live node also waits for its
workers, which replay cannot know (a visit within a few tens of ms of a timeout may differ).
The OFC starts from a zero state, as a freshly started ofc_node does.

Outputs in ``--out``:

* ``zernikes.csv``: one row per corner estimate: ``visit, stamp, corner, valid, status,
  Z4..Z22`` (nm; empty when not valid); ``stamp`` is ``sec.nanosec`` of the visit's image
  ``header.stamp``;
* ``dof.csv``: one row per visit's correction: ``visit, stamp, valid, status,
  wavefront_rms_nm, predicted_residual_rms_nm, n_modes_used, dry_run``, then the 50
  ``dof.<name>`` (this visit's correction) and 50 ``total.<name>`` (accumulated state), in the
  units of ``config/ofc/dof.yaml`` (um, or deg for the hexapod tilts);
* ``zernikes.png`` (Z4..Z22 per corner, one line per visit), ``dof.png`` (corrections and
  accumulated state per visit, by DoF group);
* ``summary.json``: counts, the parameters used and the comparison below.

If the bag also holds the live ``/aos/wfs/<corner>/wavefront`` and ``/aos/ofc/dof_correction``
messages, replay matches them by corner and stamp and reports the largest differences.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cwfs_ros import layout
from cwfs_ros.layout import CORNERS as _CORNERS
from cwfs_ros.layout import SIDES as _SIDES
from cwfs_ros.layout import absolute

__all__ = [
    "Comparison",
    "CornerRow",
    "DofRow",
    "ReplayResult",
    "add_replay_parser",
    "image_topic",
    "node_parameters",
    "params_overlay",
    "parse_remaps",
    "replay",
]



def image_topic(corner: str, side: str) -> str:
    """A half-chip's image topic as a bag records it (absolute name)."""
    return absolute(layout.image_topic(corner, side))


def corner_topic(corner: str) -> str:
    """A corner's wavefront topic as a bag records it (absolute name)."""
    return absolute(layout.corner_topic(corner))


IMAGE_TYPE = "sensor_msgs/msg/Image"
CORNER_TYPE = "cwfs_msgs/msg/CornerWavefront"
DOF_TOPIC = absolute(layout.CORRECTION_TOPIC)
DOF_TYPE = "cwfs_msgs/msg/DofCorrection"
SIM_TRUTH_TOPIC = absolute(layout.TRUTH_TOPIC)
JOINT_TOPIC = absolute(layout.JOINT_TOPIC)
JOINT_TYPE = "sensor_msgs/msg/JointState"


# ----------------------------------------------------------------------------- parameters
def node_parameters(node: str, params_files: Sequence[str | Path] = ()) -> dict[str, Any]:
    """A node's parameter values: config/params.yaml (whose values the nodes also declare as
    their defaults, :func:`cwfs_ros.ros.common.bundled_declarer`), then each file in order.

    A file section applies to the node when its key is the node's name (with or without the
    leading ``/``) or the ``/**`` wildcard; its ``ros__parameters`` are flattened to dotted
    names (``sensors.R00.intra.rot90``), later sections and files overriding earlier ones.
    Raises ConfigError for an unreadable file.
    """
    from cwfs_ros.errors import ConfigError, ParamsFileError
    from cwfs_ros.ros.params import default_params_file, read_params_file

    files = [default_params_file(), *map(Path, params_files)]
    out: dict[str, Any] = {}
    for f in files:
        try:
            sections = read_params_file(f)  # the launcher's reader: same rules, same errors
        except ParamsFileError as exc:
            raise ConfigError(str(exc)) from None
        for key, params in sections.items():
            if key.lstrip("/") in (node, "**"):
                out.update(params)
    return out


# ----------------------------------------------------------------------------- results
@dataclass
class CornerRow:
    """One corner estimate of one visit (Z4..Z22 in nm; NaN when not valid)."""

    visit: int
    stamp_ns: int
    corner: str
    valid: bool
    status: str
    zernikes_nm: list[float]


@dataclass
class DofRow:
    """One visit's OFC result: correction and accumulated state (dof.yaml units)."""

    visit: int
    stamp_ns: int
    valid: bool
    status: str
    wavefront_rms_nm: float
    predicted_residual_rms_nm: float
    n_modes_used: int
    dry_run: bool
    dof: list[float]
    dof_total: list[float]


@dataclass
class Comparison:
    """Replay against the live messages found in the bag (matched by corner and stamp).

    Differences are absolute: nm for the Zernikes, DoF units (um | deg) for the DoF. ``nan``
    when nothing could be compared.
    """

    corners_compared: int = 0
    corners_validity_mismatch: int = 0
    corners_not_live: int = 0
    live_corners_not_replayed: int = 0
    max_zernike_diff_nm: float = float("nan")
    dof_compared: int = 0
    dof_validity_mismatch: int = 0
    dof_not_live: int = 0
    live_dof_not_replayed: int = 0
    max_dof_diff: float = float("nan")
    max_dof_total_diff: float = float("nan")
    notes: list[str] = field(default_factory=list)

    def format(self) -> str:
        lines = [
            f"live comparison: {self.corners_compared} corner estimates, max |dZ| = "
            f"{self.max_zernike_diff_nm:.3g} nm, {self.corners_validity_mismatch} with a "
            f"different validity; {self.dof_compared} DoF corrections, max |d dof| = "
            f"{self.max_dof_diff:.3g}, max |d dof_total| = {self.max_dof_total_diff:.3g} "
            f"(um | deg), {self.dof_validity_mismatch} with a different validity"]
        if self.corners_not_live or self.dof_not_live:
            lines.append(f"  not in the bag's live results: {self.corners_not_live} corner "
                         f"estimates, {self.dof_not_live} corrections")
        if self.live_corners_not_replayed or self.live_dof_not_replayed:
            lines.append(f"  live results without a replayed counterpart: "
                         f"{self.live_corners_not_replayed} corner estimates, "
                         f"{self.live_dof_not_replayed} corrections")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


# Refused corrections named in the summary; the rest are in dof.csv.
_REFUSED_SHOWN = 5


@dataclass
class ReplayResult:
    """Everything a replay produced (see the module docstring for the files)."""

    bag: Path
    out_dir: Path
    images: int
    corners: list[CornerRow]
    dofs: list[DofRow]
    comparison: Comparison | None
    files: dict[str, Path]
    wavefront_params: dict[str, Any]
    ofc_params: dict[str, Any]
    rejections: list[str] = field(default_factory=list)

    def format(self) -> str:
        n_valid = sum(r.valid for r in self.corners)
        d_valid = sum(r.valid for r in self.dofs)
        lines = [f"replayed {self.bag}: {self.images} images, {len(self.corners)} corner "
                 f"estimates ({n_valid} valid), {len(self.dofs)} DoF corrections "
                 f"({d_valid} valid)"]
        if self.rejections:
            lines.append(f"  {len(self.rejections)} inputs rejected, e.g. {self.rejections[0]}")
        refused = [r for r in self.dofs if not r.valid]
        for r in refused[:_REFUSED_SHOWN]:
            lines.append(f"  correction of visit {r.visit} refused: {r.status}")
        if len(refused) > _REFUSED_SHOWN:
            lines.append(f"  ... and {len(refused) - _REFUSED_SHOWN} more refused (dof.csv)")
        lines.append(self.comparison.format() if self.comparison is not None
                     else "live comparison: no live CornerWavefront / DofCorrection in the bag")
        lines += [f"{k}: {v}" for k, v in self.files.items()]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- replay
class _Pipeline:
    """wavefront_node + ofc_node, minus the middleware (see the module docstring).

    The wavefront side is the node's own :class:`~cwfs_ros.runtime.pipeline.WavefrontPipeline`
    (guards, decoding, pairing, the stamp or frame job, conflicts, assembly, timeouts); the
    jobs run here inline (:func:`~cwfs_ros.runtime.pipeline.run_job`) instead of in worker
    processes, and what the node would publish is kept as rows.
    """

    def __init__(self, wf: dict[str, Any], ofc: dict[str, Any]) -> None:
        from cwfs_ros.runtime.pipeline import WavefrontPipeline

        # Every corner, whatever ``corners`` says: a bag may come from several processes.
        self.wf = WavefrontPipeline(wf.__getitem__, _CORNERS, assemble=True)
        self.settings = self.wf.settings
        self.fields = self.wf.fields
        from cwfs_ros.ofc.params import controller_from_params
        from cwfs_ros.ofc.rotator import RotatorHistory

        self.solver = controller_from_params(lambda n: ofc[n])
        self.dry_run = bool(ofc["dry_run"])
        self.ofc_params = ofc
        self.rotator = RotatorHistory(float(ofc["rotator_tolerance_s"]))
        self.corners: list[CornerRow] = []
        self.dofs: list[DofRow] = []
        self.rejections: list[str] = []
        self._visits: dict[int, int] = {}
        self._now_s = 0.0

    def _visit(self, stamp_ns: int) -> int:
        if stamp_ns not in self._visits:
            self._visits[stamp_ns] = len(self._visits) + 1
        return self._visits[stamp_ns]

    def warm_up(self) -> None:
        """Build each corner's estimator caches as the node's workers do at start."""
        from cwfs_ros.runtime.corner_pool import warm_corner

        for c in _CORNERS:
            warm_corner(c, self.fields[c]["intra"], self.fields[c]["extra"], self.settings,
                        frames=self.wf.frame_warm())

    # -- the wavefront_node path (WavefrontNode._on_image and what follows it)
    def image(self, msg: Any, corner: str, side: str, now_s: float, clock_ns: int) -> None:
        """One recorded image, received at ``now_s`` (bag time, s; ``clock_ns`` in ns)."""
        from cwfs_ros.runtime.pipeline import run_job

        self.expire(now_s)  # the node's 0.1 s timer would have run before this image
        refused = self.wf.refusal(msg, corner, side, clock_ns)
        if refused is not None:
            self.rejections.append(refused.message)
            rec = self.wf.refused_record(refused, now_s)  # pairs, naming its reason
            if rec is None:
                return
        else:
            rec, bad = self.wf.record(msg, corner, side, now_s)
            if bad is not None:
                self.rejections.append(bad.message)
        step = self.wf.add_record(rec)
        for r in step.dropped:
            self._unpaired(r)
        rej = step.rejection
        if rej is not None:
            self.rejections.append(rej.message)
            if rej.reason == "conflicting_images":
                unpaired, vec = self.wf.conflict(rej)
                if unpaired is not None:
                    self._unpaired(unpaired, count=False)
                if vec is not None:
                    self._vector(vec)
        if step.pair is not None:
            self._outcome(run_job(self.wf.job_for(step.pair)))

    def _unpaired(self, r: Any, assemble: bool = True, count: bool = True) -> None:
        if count:
            self.rejections.append(r.message)
        self._outcome(self.wf.unpaired_outcome(r), assemble=assemble)

    def _outcome(self, out: Any, assemble: bool = True) -> None:
        out, _ = self.wf.settle(out)
        self.corners.append(CornerRow(self._visit(out.stamp_ns), int(out.stamp_ns), out.corner,
                                      bool(out.valid), out.status,
                                      [float(v) for v in out.zernikes_nm]))
        if not assemble:
            return
        vec, rej = self.wf.assemble(out, self._now_s)
        if rej is not None:
            self.rejections.append(rej.message)
        if vec is not None:
            self._vector(vec)

    def _vector(self, vec: Any) -> None:
        for r in self.wf.close_missing(vec):
            self._unpaired(r, assemble=False)  # the vector already holds it as missing
        self._ofc(vec)

    def expire(self, now_s: float) -> None:
        self._now_s = now_s
        for r in self.wf.expire_pairs(now_s):
            self._unpaired(r)
        for vec in self.wf.expire_visits(now_s):
            self._vector(vec)

    # -- the ofc_node path
    def joints(self, msg: Any) -> None:
        """A recorded JointState: the camera rotator's angle, as ofc_node takes it."""
        from cwfs_ros.ofc.rotator import ROTATOR_JOINT
        from cwfs_ros.runtime.visits import stamp_to_ns

        if ROTATOR_JOINT in msg.name:
            i = list(msg.name).index(ROTATOR_JOINT)
            if i < len(msg.position):
                self.rotator.add(stamp_to_ns(msg.header.stamp), float(msg.position[i]))

    def _ofc(self, vec: Any) -> None:
        import numpy as np

        from cwfs_ros.ofc.params import rotator_angle_for, step_controller

        # The visit-order rules of ofc_node (OFCSolver.step); not the clock's: a bag's
        # stamps are in the past of any clock it is replayed by.
        stamp = int(vec.stamp_ns)
        angle, why = rotator_angle_for(self.ofc_params.__getitem__, self.rotator, stamp)
        out = step_controller(self.solver, np.asarray(vec.zernikes_nm, dtype=np.float64),
                              np.asarray(vec.corner_valid, dtype=bool),
                              uncertainty_nm=getattr(vec, "uncertainty_nm", None),
                              angle_deg=angle, angle_why=why, stamp_ns=stamp, now_ns=None,
                              dry_run=self.dry_run)
        self.dofs.append(DofRow(
            self._visit(vec.stamp_ns), int(vec.stamp_ns), bool(out.valid), out.status,
            float(out.wavefront_rms_nm), float(out.predicted_residual_rms_nm),
            int(max(0, min(out.n_modes_used, 65535))), self.dry_run,
            [float(v) for v in out.dof], [float(v) for v in out.dof_total]))


def _load_numeric_libraries(instrument: str) -> None:
    """Import what the estimates will use, so that a thread limit set now covers it."""
    from cwfs_ros.wfs import estimator  # noqa: F401 - numpy, scipy
    from cwfs_ros.wfs.instrument import load_instrument

    if load_instrument(instrument).mapping == "batoid":
        import batoid  # noqa: F401 - its OpenMP runtime


def _max_abs_diff(a: Iterable[float], b: Iterable[float]) -> float:
    import numpy as np

    x, y = np.asarray(list(a), dtype=np.float64), np.asarray(list(b), dtype=np.float64)
    if x.shape != y.shape:
        return float("inf")
    both = np.isfinite(x) & np.isfinite(y)
    if not np.array_equal(np.isfinite(x), np.isfinite(y)):
        return float("inf")  # NaN on one side only: not the same result
    return float(np.max(np.abs(x[both] - y[both]))) if both.any() else 0.0


def _nanmax(values: list[float]) -> float:
    return max(values) if values else float("nan")


def _compare(corners: list[CornerRow], dofs: list[DofRow], live_corners: dict[tuple, Any],
             live_dofs: dict[int, Any]) -> Comparison:
    from cwfs_ros.runtime.visits import stamp_to_ns, zernikes_by_noll

    cmp = Comparison()
    zdiffs: list[float] = []
    seen: set[tuple] = set()
    for r in corners:
        m = live_corners.get((r.corner, r.stamp_ns))
        if m is None:
            cmp.corners_not_live += 1
            continue
        seen.add((r.corner, r.stamp_ns))
        cmp.corners_compared += 1
        if bool(m.valid) != r.valid:
            cmp.corners_validity_mismatch += 1
            continue
        if r.valid:
            z = zernikes_by_noll(m.noll, m.zernikes_nm)
            zdiffs.append(float("inf") if z is None else _max_abs_diff(r.zernikes_nm, z))
    cmp.live_corners_not_replayed = len(set(live_corners) - seen)
    cmp.max_zernike_diff_nm = _nanmax(zdiffs)
    d1: list[float] = []
    d2: list[float] = []
    seen_d: set[int] = set()
    for r in dofs:
        m = live_dofs.get(r.stamp_ns)
        if m is None:
            cmp.dof_not_live += 1
            continue
        seen_d.add(r.stamp_ns)
        cmp.dof_compared += 1
        if bool(m.valid) != r.valid:
            cmp.dof_validity_mismatch += 1
        d1.append(_max_abs_diff(r.dof, m.dof))
        d2.append(_max_abs_diff(r.dof_total, m.dof_total))
    cmp.live_dof_not_replayed = len(set(live_dofs) - seen_d)
    cmp.max_dof_diff, cmp.max_dof_total_diff = _nanmax(d1), _nanmax(d2)
    if live_dofs:
        first = live_dofs[min(live_dofs)]
        before = [t - d for t, d in zip(first.dof_total, first.dof, strict=True)]
        if any(abs(v) > 0 for v in before):
            cmp.notes.append(
                "the live ofc_node had accumulated a DoF state before the bag's first "
                f"correction (at {stamp_to_ns(first.header.stamp)}); replay starts from zero, "
                "so dof_total (and, with ki > 0, dof) differ")
    return cmp


@dataclass
class _BagTopics:
    """The bag's topics replay reads, by role (the bag's names), and why any were left out."""

    images: dict[str, tuple[str, str]]  # topic -> (corner, side)
    live: dict[str, str]  # live wavefront topic -> corner
    dof: list[str]  # the live correction topic, if it can be compared
    joints: list[str]  # the joint-state topic, if it can be decoded
    notes: list[str]

    @property
    def read(self) -> list[str]:
        """Every topic to decode, in the order the roles are listed."""
        return [*self.images, *self.live, *self.dof, *self.joints]


def replay(bag_path: str | Path, out_dir: str | Path, *, params_files: Sequence[str | Path] = (),
           progress: bool = True, plots: bool = True, sim: bool | None = None,
           remap: dict[str, str] | None = None) -> ReplayResult:
    """Run the estimator and the OFC solver offline on every visit of a bag; write the outputs.

    ``sim``: layer config/sim.yaml under the ``params_files``, as ``bringup --sim`` does;
    ``None`` (default) decides from the bag: a bag holding ``/aos/sim/truth`` was recorded from
    the simulated loop.  ``remap``: bag topic -> the node's topic (``--remap FROM:=TO``), for a
    bag whose topics a camera driver named otherwise.

    Raises :class:`~cwfs_ros.ros.bag.BagError` for a bad bag (or one without image topics) and
    :class:`~cwfs_ros.errors.ConfigError` for bad parameters.
    """
    from cwfs_ros.ros.bag import open_bag
    from cwfs_ros.ros.launch import sim_params_file

    if sim is None:
        with open_bag(bag_path) as bag:
            sim = SIM_TRUTH_TOPIC in bag.topics
    params_files = [*([sim_params_file()] if sim else []), *params_files]
    wf = node_parameters("wavefront_node", params_files)
    ofc = node_parameters("ofc_node", params_files)
    out = Path(out_dir)
    with open_bag(bag_path) as bag:
        topics = _bag_topics(bag, remap or {}, sim)
        n_images = sum(bag.topics[t].count for t in topics.images)
        pipe = _Pipeline(wf, ofc)
        live_corners, live_dofs = _run_bag(bag, topics, pipe, n_images, progress)
    comparison = None
    if live_corners or live_dofs:
        comparison = _compare(pipe.corners, pipe.dofs, live_corners, live_dofs)
        comparison.notes[:0] = topics.notes
    files = _write_outputs(out, pipe, plots)
    result = ReplayResult(Path(bag_path), out, n_images, pipe.corners, pipe.dofs, comparison,
                          files, wf, ofc, pipe.rejections)
    _write_summary(files["summary"], result)
    return result


def _bag_topics(bag: Any, remap: dict[str, str], sim: bool) -> _BagTopics:
    """Find the image, live-output and joint topics in ``bag``; raise for a bag without
    decodable images (nothing to replay), note the live outputs that cannot be compared."""
    from cwfs_ros.ros.bag import BagError
    from cwfs_ros.ros.launch import sim_params_file

    bag_name = _bag_names(remap, bag.topics)
    images = {bag_name(image_topic(c, s)): (c, s) for c in _CORNERS for s in _SIDES
              if bag_name(image_topic(c, s)) in bag.topics}
    if not images:
        raise BagError(f"{bag.path}: no image topics (/aos/wfs/<corner>/<intra|extra>/image)"
                       " in the bag: nothing to replay")
    for t in images:
        if bag.topics[t].type != IMAGE_TYPE:
            raise BagError(f"{bag.path}: {t} holds {bag.topics[t].type}, not {IMAGE_TYPE}")
    bag.require_decodable(images)
    notes = ([f"{sim_params_file().name} applied under the --params files (the bag holds "
              f"{SIM_TRUTH_TOPIC}: a simulated run, as bringup --sim)"] if sim else [])
    live = {bag_name(corner_topic(c)): c for c in _CORNERS
            if bag_name(corner_topic(c)) in bag.topics}
    for t in list(live):
        if bag.topics[t].type != CORNER_TYPE or bag.decode_problem(t):
            notes.append(f"{t} ({bag.topics[t].type}) not compared: "
                         f"{bag.decode_problem(t) or 'not a ' + CORNER_TYPE}")
            del live[t]
    dof_topic = bag_name(DOF_TOPIC)
    has_dof = dof_topic in bag.topics
    if has_dof and (bag.topics[dof_topic].type != DOF_TYPE
                    or bag.decode_problem(dof_topic)):
        notes.append(f"{dof_topic} not compared: "
                     f"{bag.decode_problem(dof_topic) or 'not a ' + DOF_TYPE}")
        has_dof = False
    joint_topic = bag_name(JOINT_TOPIC)
    joints = [joint_topic] if (joint_topic in bag.topics and bag.topics[
        joint_topic].type == JOINT_TYPE and not bag.decode_problem(joint_topic)) else []
    return _BagTopics(images, live, [dof_topic] if has_dof else [], joints, notes)


def _run_bag(bag: Any, topics: _BagTopics, pipe: _Pipeline, n_images: int,
             progress: bool) -> tuple[dict[tuple, Any], dict[int, Any]]:
    """Feed the bag's messages to ``pipe`` in bag order; return the live corner estimates by
    ``(corner, stamp_ns)`` and the live corrections by stamp, to compare with."""
    from threadpoolctl import threadpool_limits
    from tqdm import tqdm

    from cwfs_ros.wfs.estimator import reset_caches
    from cwfs_ros.wfs.mapping import use_field_tile_store

    live_corners: dict[tuple, Any] = {}
    live_dofs: dict[int, Any] = {}
    # One BLAS/OpenMP thread, as in the node's worker processes (corner_pool._worker_init):
    # the sums then run in the same order and the estimates agree with the live ones to
    # the last bit (with two threads they differed by up to 1e-4 nm). The limit only
    # reaches libraries already loaded: load the estimator's (scipy, batoid) first.
    _load_numeric_libraries(pipe.settings.instrument)
    with threadpool_limits(1), tqdm(total=n_images, unit="img", desc="replay",
                                    disable=not progress, file=sys.stderr) as bar:
        # From the caches of a freshly started node's workers: a field tile serves a
        # tile's third field on, so what this process estimated before could move the
        # estimates by ~0.1 nm from the live ones (mapping.reset_field_tiles).
        reset_caches()
        try:
            _replay_messages(pipe, bag, topics, bar, live_corners, live_dofs)
        finally:
            use_field_tile_store(None)  # turned on by a frames warm-up: this run's only
    return live_corners, live_dofs


def _replay_messages(pipe: _Pipeline, bag: Any, topics: Any, bar: Any,
                     live_corners: dict[tuple, Any], live_dofs: dict[int, Any]) -> None:
    """Warm the pipeline up, then feed it the bag's messages in order, keeping the live
    outputs the bag holds."""
    from cwfs_ros.runtime.visits import stamp_to_ns

    pipe.warm_up()
    for m, msg in bag.decoded(topics.read):
        if m.topic in topics.images:
            pipe.image(msg, *topics.images[m.topic], m.timestamp_ns / 1e9, m.timestamp_ns)
            bar.update(1)
        elif m.topic in topics.joints:
            pipe.joints(msg)
        elif m.topic in topics.live:
            live_corners[(str(msg.corner) or topics.live[m.topic],
                          stamp_to_ns(msg.header.stamp))] = msg
        else:
            live_dofs[stamp_to_ns(msg.header.stamp)] = msg
    pipe.expire(float("inf"))  # the end of the bag: every timeout has passed


def _write_outputs(out: Path, pipe: _Pipeline, plots: bool) -> dict[str, Path]:
    """Write the CSVs (and plots) of a replay into ``out``; the files by role, the summary's
    path included (written last, from the result)."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"zernikes": out / "zernikes.csv", "dof": out / "dof.csv"}
    _write_zernikes(files["zernikes"], pipe.corners)
    _write_dofs(files["dof"], pipe.dofs)
    if plots:
        files["zernikes_plot"] = _plot_zernikes(out / "zernikes.png", pipe.corners)
        files["dof_plot"] = _plot_dofs(out / "dof.png", pipe.dofs)
    files["summary"] = out / "summary.json"
    return files


def _bag_names(remap: dict[str, str], bag_topics: Any) -> Any:
    """node topic -> the bag's name for it, from ``FROM:=TO`` remappings (bag -> node)."""
    from cwfs_ros.ros.bag import BagError

    inverse: dict[str, str] = {}
    for src, dst in remap.items():
        if src not in bag_topics:
            raise BagError(f"--remap {src}:={dst}: the bag has no topic {src} (it has: "
                           f"{', '.join(sorted(bag_topics)) or 'none'})")
        if dst in inverse:
            raise BagError(f"--remap: {inverse[dst]} and {src} both map to {dst}")
        inverse[dst] = src
    return lambda topic: inverse.get(topic, topic)


# ----------------------------------------------------------------------------- outputs
def _stamp(ns: int) -> str:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}"


def _num(v: float) -> str:
    # repr round-trips a float64 exactly: the CSV holds the very numbers that were computed
    return repr(float(v)) if v == v else ""


def _write_zernikes(path: Path, rows: list[CornerRow]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["visit", "stamp", "corner", "valid", "status",
                    *[f"Z{j}" for j in layout.NOLL]])
        for r in rows:
            w.writerow([r.visit, _stamp(r.stamp_ns), r.corner, int(r.valid), r.status,
                        *[_num(v) if r.valid else "" for v in r.zernikes_nm]])


def _dof_names() -> list[str]:
    from cwfs_ros.ofc.control import load_dof_spec

    return list(load_dof_spec().names)


def _write_dofs(path: Path, rows: list[DofRow]) -> None:
    names = _dof_names()
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["visit", "stamp", "valid", "status", "wavefront_rms_nm",
                    "predicted_residual_rms_nm", "n_modes_used", "dry_run",
                    *[f"dof.{n}" for n in names], *[f"total.{n}" for n in names]])
        for r in rows:
            w.writerow([r.visit, _stamp(r.stamp_ns), int(r.valid), r.status,
                        _num(r.wavefront_rms_nm), _num(r.predicted_residual_rms_nm),
                        r.n_modes_used, int(r.dry_run), *map(_num, r.dof),
                        *map(_num, r.dof_total)])


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, float) and obj != obj:
        return None
    if isinstance(obj, float) and obj in (float("inf"), float("-inf")):
        return str(obj)
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _write_summary(path: Path, r: ReplayResult) -> None:
    doc = {
        "bag": r.bag, "images": r.images,
        "corner_estimates": len(r.corners),
        "corner_estimates_valid": sum(x.valid for x in r.corners),
        "dof_corrections": len(r.dofs), "dof_corrections_valid": sum(x.valid for x in r.dofs),
        "rejections": r.rejections,
        "comparison": asdict(r.comparison) if r.comparison is not None else None,
        "wavefront_node_parameters": r.wavefront_params, "ofc_node_parameters": r.ofc_params,
        "files": r.files,
    }
    path.write_text(json.dumps(_json_safe(doc), indent=2) + "\n", encoding="utf-8")


def _figure(size: tuple[float, float]) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)  # an explicit Agg canvas: no pyplot, the caller's backend untouched
    return fig


def _visit_colours(n: int) -> list[Any]:
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    return [cmap(0.5 if n <= 1 else i / (n - 1)) for i in range(n)]


def _plot_zernikes(path: Path, rows: list[CornerRow]) -> Path:
    """Z4..Z22 per corner (2x2 panels), one line per visit; invalid estimates left out."""
    noll = list(layout.NOLL)
    visits = sorted({r.visit for r in rows})
    colours = dict(zip(visits, _visit_colours(len(visits)), strict=True))
    fig = _figure((12.0, 8.0))
    axes = fig.subplots(2, 2, sharex=True, sharey=True).ravel()
    for ax, c in zip(axes, _CORNERS, strict=True):
        mine = [r for r in rows if r.corner == c]
        for r in mine:
            if r.valid:
                ax.plot(noll, r.zernikes_nm, "o-", ms=3, lw=1, color=colours[r.visit],
                        label=f"visit {r.visit}")
        bad = sum(not r.valid for r in mine)
        ax.set_title(f"{c}: {len(mine) - bad} valid, {bad} invalid", fontsize=10)
        ax.axhline(0.0, color="0.7", lw=0.8)
        ax.grid(alpha=0.3)
        ax.set_xticks(noll)
    for ax in axes[2:]:
        ax.set_xlabel("Noll index")
    for ax in axes[::2]:
        ax.set_ylabel("Zernike coefficient (nm)")
    if 0 < len(visits) <= 12:
        axes[0].legend(fontsize=8, ncols=2)
    fig.suptitle("replayed corner wavefronts (total, design included)")
    fig.savefig(path)
    return path


def _plot_dofs(path: Path, rows: list[DofRow]) -> Path:
    """Per-visit correction (top) and accumulated state (bottom), by DoF group and unit."""
    names = _dof_names()
    groups = [("hexapod dz, dx, dy (um)", [0, 1, 2, 5, 6, 7]),
              ("hexapod rx, ry (deg)", [3, 4, 8, 9]),
              ("M1M3 bending (um)", list(range(10, 30))),
              ("M2 bending (um)", list(range(30, 50)))]
    visits = sorted({r.visit for r in rows})
    colours = dict(zip(visits, _visit_colours(len(visits)), strict=True))
    fig = _figure((16.0, 7.5))
    axes = fig.subplots(2, len(groups))
    for row, (attr, what) in enumerate((("dof", "correction"), ("dof_total", "state"))):
        for col, (title, idx) in enumerate(groups):
            ax = axes[row, col]
            x = list(range(len(idx)))
            for r in rows:
                if r.valid:
                    vals = getattr(r, attr)
                    ax.plot(x, [vals[i] for i in idx], "o-", ms=3, lw=1,
                            color=colours[r.visit], label=f"visit {r.visit}")
            ax.axhline(0.0, color="0.7", lw=0.8)
            ax.grid(alpha=0.3)
            ax.set_title(f"{what}: {title}", fontsize=10)
            ax.set_xticks(x)
            ax.set_xticklabels([names[i] for i in idx], rotation=90, fontsize=7)
    if 0 < len(visits) <= 12:
        axes[0, 0].legend(fontsize=8)
    bad = sum(not r.valid for r in rows)
    fig.suptitle(f"replayed DoF corrections: {len(rows) - bad} valid, {bad} refused")
    fig.savefig(path)
    return path


# ----------------------------------------------------------------------------- command line
def _abs_topic(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def parse_remaps(rules: Sequence[str]) -> dict[str, str]:
    """``FROM:=TO`` rules (as ``--ros-args -r``) to {bag topic: node topic}."""
    from cwfs_ros.errors import ConfigError

    out: dict[str, str] = {}
    for rule in rules:
        src, sep, dst = rule.partition(":=")
        if not sep or not src.strip() or not dst.strip():
            raise ConfigError(f"--remap {rule!r}: expected FROM:=TO, e.g. "
                              "/camera/wfs_r00_sw1/image_raw:=/aos/wfs/R00/intra/image")
        out[_abs_topic(src.strip())] = _abs_topic(dst.strip())
    return out


def params_overlay(rules: Sequence[str], params_files: Sequence[str | Path],
                   out_dir: Path) -> Path | None:
    """``-p NAME:=VALUE`` rules as a parameter file for the node that declares NAME
    (wavefront_node's ``sensors.<corner>.<side>.rot90/flip``, ofc_node's ``kp`` ...),
    checked like ``--ros-args -p`` (:func:`cwfs_ros.ros.params.check_overrides`)."""
    import yaml

    from cwfs_ros.errors import ConfigError
    from cwfs_ros.ros.params import check_overrides, parse_parameter_text, yaml_kind

    if not rules:
        return None
    declared = {n: {k: yaml_kind(v) for k, v in node_parameters(n, params_files).items()}
                for n in ("wavefront_node", "ofc_node")}
    argv = [a for r in rules for a in ("-p", r)]
    problems = check_overrides(argv, declared)
    if problems:
        raise ConfigError("; ".join(problems))
    body: dict[str, dict[str, Any]] = {}
    for rule in rules:
        name, _, text = rule.partition(":=")
        node = next(n for n, d in declared.items() if name in d)
        body.setdefault(node, {"ros__parameters": {}})["ros__parameters"][name] = (
            parse_parameter_text(text))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "params_overrides.yaml"
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    return path


def cmd_replay(args: argparse.Namespace) -> int:
    from cwfs_ros.errors import BagError, CliError, ConfigError

    try:
        remap = parse_remaps(args.remap)
        overlay = params_overlay(args.param, args.params, Path(args.out))
        result = replay(args.bag, args.out, params_files=[*args.params,
                                                          *([overlay] if overlay else [])],
                        progress=not args.no_progress, plots=not args.no_plots,
                        sim={"auto": None, "yes": True, "no": False}[args.sim], remap=remap)
    except (BagError, ConfigError) as exc:
        raise CliError(str(exc)) from None
    print(result.format())
    return 0


def add_replay_parser(subparsers: Any, cli_error: type[Exception] | None = None
                      ) -> argparse.ArgumentParser:
    """Register ``replay BAG --out DIR`` on an argparse subparsers object (sets ``func``).

    ``cli_error``: as for :func:`cwfs_ros.ros.bag.add_bag_parser`.
    """
    p = subparsers.add_parser(
        "replay", help="run the estimator and the OFC offline on a recorded bag",
        description="Pair the image topics of a bag into visits and run the wavefront "
                    "estimator and the OFC solver on them offline (no DDS), with the nodes' "
                    "parameters (config/params.yaml, then --params files). Writes "
                    "zernikes.csv, dof.csv, plots and summary.json, and compares with the live "
                    "results if the bag holds them.")
    p.add_argument("bag", metavar="BAG", help="bag directory (or .mcap / .db3 file)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output directory (created if needed)")
    p.add_argument("--params", action="append", default=[], metavar="FILE",
                   help="ROS parameter YAML overlaid on config/params.yaml (repeatable; "
                        "ros__parameters keyed by node name)")
    p.add_argument("--sim", choices=("auto", "yes", "no"), default="auto",
                   help="layer config/sim.yaml under the --params files, as bringup --sim "
                        "does; auto: when the bag holds /aos/sim/truth (default)")
    p.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                   help="read the bag's topic FROM as the node's TO (repeatable), e.g. "
                        "/cam/r00_sw1/image_raw:=/aos/wfs/R00/intra/image")
    p.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                   help="a wavefront_node or ofc_node parameter over the --params files "
                        "(repeatable), e.g. the orientation of a camera's stamps: "
                        "sensors.R00.intra.rot90:=2, sensors.R00.intra.flip:=lr "
                        "(docs/connecting-a-camera.md)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true", help="write the CSV files only")
    p.set_defaults(func=cmd_replay, cli_error=cli_error)
    return p
