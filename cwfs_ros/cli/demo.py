"""The closed active-optics loop, headless: the package's main job and the convergence benchmark.

``cwfs-ros demo`` runs the real ROS 2 graph that ``cwfs-ros bringup --sim`` runs, composed in
this process on its own rclpy Context:

    camera_sim_node --8 images--> wavefront_node --76-vector--> ofc_node --DofCorrection--+
          ^                                                                               |
          +-------------------------------------------------------------------------------+

plus a small monitor node (:class:`LoopMonitor`) that triggers one visit at a time on
``camera_sim_node/trigger`` and listens to every topic of the loop, so that each visit's
estimate can be scored against the simulator's truth (``/aos/sim/truth``). A visit is
triggered only once the previous visit's correction has been applied (or refused), as on the
telescope, where the next exposure starts after the mirrors have moved.

Isolation: unless ``visible=True``, DDS discovery is switched off
(``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``: nodes in this process still talk, nothing outside it
sees them), so a demo can never send its simulated corrections to a real telescope's
actuators on the same network, and two demos never cross-talk.

Figures of merit (the closed-loop issue's definitions), from the simulator's truth
(``SimTruth``): the corner figure is the true wavefront minus the design (intrinsic) wavefront,
as sqrt(sum over Z4..Z22 of the squared coefficients) per corner, averaged over the four
corners, in nm; the field figure is the same departure over the science field's 31
Gaussian-quadrature points (:mod:`cwfs_ros.sim.field_truth`), with the optical PSF FWHM it adds.
"""

from __future__ import annotations

import csv
import json
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cwfs_ros.errors import LoopError
from cwfs_ros.layout import (
    CORNERS,
    CORRECTION_TOPIC,
    N_DOF,
    N_ZK,
    SIDES,
    TRUTH_TOPIC,
    VECTOR_TOPIC,
    corner_topic,
    image_topic,
)
from cwfs_ros.ros.launch import DISCOVERY_ENV
from cwfs_ros.sim.perturbation import rigid_perturbation, wavefront_error_nm

__all__ = [
    "LoopConfig",
    "LoopRun",
    "VisitRecord",
    "rigid_perturbation",
    "run_closed_loop",
    "wavefront_error_nm",
    "write_report",
]

@dataclass
class LoopConfig:
    """What one closed-loop run simulates.

    Attributes:
        visits: number of visits (each: render, estimate, solve, apply).
        initial_dof: the telescope's starting state (50 DoF, ts_ofc order and units,
            DofCorrection signs).
        n_photons: photons per donut; the estimate's noise falls as 1/sqrt(n_photons) and
            the render time rises linearly (about 2.3 us per photon per donut here).
        render_seed: seed of the image noise and donut offsets.
        params_files: ROS parameter YAML files overlaid on config/params.yaml, in order
            (default: config/sim.yaml, the simulation's controller settings).
        parameters: further per-node overrides, ``{node: {name: value}}``, applied last.
        ros_args: extra ROS arguments for the nodes (e.g. ``("--log-level", "warn")``).
        visible: let other processes on the DDS domain see the graph (off by default).
        domain_id: DDS domain when visible (default: ``ROS_DOMAIN_ID`` or 0).
        visit_timeout_s: give up on a visit whose truth or correction does not arrive.
        keep_images: visits whose 8 donuts are kept for the report (1-based; -1 = the last).
        rotator_angle_deg: the camera rotator angle of every visit [deg].
    """

    visits: int = 8
    initial_dof: np.ndarray = field(default_factory=lambda: rigid_perturbation(1))
    n_photons: float = 5e5
    render_seed: int = 7
    params_files: Sequence[str | Path] | None = None
    parameters: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    ros_args: Sequence[str] = ()
    visible: bool = False
    domain_id: int | None = None
    visit_timeout_s: float = 180.0
    keep_images: tuple[int, ...] = (1, -1)
    rotator_angle_deg: float = 0.0


@dataclass
class VisitRecord:
    """Everything the loop saw of one visit (nm, DoF units, seconds)."""

    visit: int
    stamp_ns: int
    dof_state: np.ndarray            # true state the visit was rendered with (50)
    truth_nm: np.ndarray             # true total wavefront at the corner mid-points (76)
    intrinsic_nm: np.ndarray         # its design part (76)
    estimate_nm: np.ndarray          # the wavefront_node's 76-vector (NaN where invalid)
    corner_valid: np.ndarray         # (4,) bool
    corner_status: list[str]
    correction: np.ndarray           # the DofCorrection's dof (50)
    correction_valid: bool
    correction_status: str
    predicted_residual_nm: float     # ofc_node's own prediction (its rms convention)
    render_s: float                  # trigger -> last image received (ray tracing 8 donuts)
    estimate_s: float                # last image received -> 76-vector received
    solve_s: float                   # 76-vector received -> DofCorrection received
    corner_compute_ms: np.ndarray    # per-corner estimator time in its worker (4,)
    images: dict[tuple[str, str], np.ndarray] | None = None
    field_error_nm: float = float("nan")   # SimTruth field figure (GQ points, design removed)
    fwhm_arcsec: float = float("nan")      # SimTruth optical FWHM over the field
    rotator_angle_deg: float = 0.0         # the visit's camera rotator angle
    predicted_field_nm: float = float("nan")  # ofc_node's prediction of the field error

    @property
    def true_error_nm(self) -> float:
        """True wavefront error (design removed), the figure of merit."""
        return wavefront_error_nm(self.truth_nm, self.intrinsic_nm)

    @property
    def estimated_error_nm(self) -> float:
        """The same figure computed from the estimate (design removed)."""
        return wavefront_error_nm(self.estimate_nm, self.intrinsic_nm)

    @property
    def median_estimate_error_nm(self) -> float:
        """Median over the valid corners of :attr:`estimate_rms_error_nm`; NaN if none."""
        e = self.estimate_rms_error_nm
        e = e[np.isfinite(e)]
        return float(np.median(e)) if e.size else float("nan")

    @property
    def estimate_rms_error_nm(self) -> np.ndarray:
        """Per-corner RMS (mean over Z4..Z22) of estimate minus truth (4,) [nm]."""
        d = (self.estimate_nm - self.truth_nm).reshape(len(CORNERS), N_ZK)
        return np.sqrt(np.mean(d ** 2, axis=1))


@dataclass
class LoopRun:
    """The outcome of :func:`run_closed_loop`."""

    config: LoopConfig
    records: list[VisitRecord]
    startup_s: float
    wall_s: float
    camera_stats: dict[str, int]

    @property
    def true_error_nm(self) -> np.ndarray:
        """Per visit, the true wavefront error at the four corners [nm]."""
        return np.array([r.true_error_nm for r in self.records])

    @property
    def field_error_nm(self) -> np.ndarray:
        """The field figure per visit (SimTruth.field_wavefront_rms_nm) [nm]."""
        return np.array([r.field_error_nm for r in self.records])

    @property
    def fwhm_arcsec(self) -> np.ndarray:
        return np.array([r.fwhm_arcsec for r in self.records])

    def reduction(self, within: int = 5, figure: str = "corner") -> float:
        """First visit's error / the lowest error of visits 2..``within``.

        "Falls 5x within 5 visits" counts the first visit, so it allows 4 corrections: the
        5th visit is rendered after the 4th correction. ``figure``: ``"corner"`` or
        ``"field"``.
        """
        e = self.field_error_nm if figure == "field" else self.true_error_nm
        if len(e) < 2:
            return float("nan")
        return float(e[0] / np.min(e[1:within]))

    def summary(self) -> dict[str, Any]:
        e = self.true_error_nm
        return {
            "visits": len(self.records),
            "true_error_nm": [round(float(x), 2) for x in e],
            "true_field_error_nm": [round(float(x), 2) for x in self.field_error_nm],
            "fwhm_arcsec": [round(float(x), 4) for x in self.fwhm_arcsec],
            "rotator_angle_deg": self.config.rotator_angle_deg,
            "estimated_error_nm": [round(float(r.estimated_error_nm), 2) for r in self.records],
            "estimate_rms_error_nm": [round(r.median_estimate_error_nm, 2)
                                      for r in self.records],
            "corrections_valid": [bool(r.correction_valid) for r in self.records],
            "reduction_within_5": round(self.reduction(5), 2),
            "field_reduction_within_5": round(self.reduction(5, "field"), 2),
            "render_s": [round(r.render_s, 3) for r in self.records],
            "estimate_s": [round(r.estimate_s, 4) for r in self.records],
            "solve_s": [round(r.solve_s, 4) for r in self.records],
            "startup_s": round(self.startup_s, 2),
            "wall_s": round(self.wall_s, 2),
            "camera_stats": self.camera_stats,
        }


def _overlay(config: LoopConfig) -> dict[str, Any]:
    """The run's own parameters (written next to the report, so the run can be repeated)."""
    dof = np.asarray(config.initial_dof, dtype=np.float64).reshape(-1)
    if dof.shape != (N_DOF,) or not np.all(np.isfinite(dof)):
        raise ValueError(f"initial_dof must be {N_DOF} finite numbers")
    over: dict[str, dict[str, Any]] = {
        "camera_sim_node": {"visit_period_s": 0.0, "n_photons": float(config.n_photons),
                            "initial_dof": [float(x) for x in dof], "perturbation_seed": -1,
                            "render_seed": int(config.render_seed),
                            "rotator_angle_deg": float(config.rotator_angle_deg)},
        # A visit is only triggered once all four corners of the last one are in, so the
        # assembly timeout only matters for a corner that fails outright.
        "wavefront_node": {"visit_timeout_s": 30.0},
    }
    for node, values in config.parameters.items():
        over.setdefault(node, {}).update(dict(values))
    return {node: {"ros__parameters": values} for node, values in over.items()}


def run_closed_loop(config: LoopConfig, *, workdir: str | Path,
                    on_visit: Callable[[VisitRecord], None] | None = None,
                    on_status: Callable[[str], None] | None = None) -> LoopRun:
    """Run the closed loop for ``config.visits`` visits and return what happened.

    Args:
        config: the run.
        workdir: where the run's parameter overlay is written (``params_overlay.yaml``).
        on_visit: called with each finished :class:`VisitRecord` (progress display).
        on_status: called with short status lines during start-up.

    Raises:
        LoopError: a node could not start, the workers did not warm up, or a visit's truth
            or correction did not arrive within ``config.visit_timeout_s``.
    """
    say = on_status or (lambda _m: None)
    files = _params_files(config, Path(workdir))
    # rcl reads the discovery range when the context is initialised (in run_nodes, below);
    # the caller's environment is restored once the nodes exist.
    saved_env = os.environ.get(DISCOVERY_ENV)
    if not config.visible:
        os.environ[DISCOVERY_ENV] = "OFF"
    domain = config.domain_id
    if domain is None:
        domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)

    import rclpy

    ctx = rclpy.Context()
    t0 = time.monotonic()
    say("starting camera_sim_node, wavefront_node and ofc_node ...")
    th, started, ready, exit_code = _start_graph(config, files, ctx, domain)
    try:
        ready.wait(60)
        if not config.visible:
            _restore_env(DISCOVERY_ENV, saved_env)
        if "nodes" not in started:
            raise LoopError("the nodes did not start (see the error above)"
                            + (f", exit code {exit_code[0]}" if exit_code else ""))
        monitor = LoopMonitor(ctx)
        started["executor"].add_node(monitor.node)
        return _drive(config, monitor, started["nodes"], t0, on_visit, say)
    finally:
        ctx.try_shutdown()
        th.join(15)


def _start_graph(config: LoopConfig, files: list[Path], ctx: Any, domain: int
                 ) -> tuple[threading.Thread, dict[str, Any], threading.Event, list[int]]:
    """Start the three nodes in a thread on ``ctx``; return the thread, what it started (the
    nodes by name and their executor, once ``ready`` is set) and its exit code, once ended.
    ``ready`` is set also when a node failed to start."""
    from cwfs_ros.ros.launch import run_nodes

    started: dict[str, Any] = {}
    ready = threading.Event()
    exit_code: list[int] = []

    def on_ready(nodes, executor) -> None:
        started["nodes"] = {n.get_name(): n for n in nodes}
        started["executor"] = executor
        ready.set()

    def spin() -> None:
        exit_code.append(run_nodes(["camera_sim_node", "wavefront_node", "ofc_node"],
                                   params_files=files, ros_args=list(config.ros_args),
                                   context=ctx, domain_id=domain,
                                   on_ready=on_ready))
        ready.set()  # also when a node failed to start

    th = threading.Thread(target=spin, name="cwfs_demo_graph", daemon=True)
    th.start()
    return th, started, ready, exit_code


def _params_files(config: LoopConfig, workdir: Path) -> list[Path]:
    """The nodes' parameter files: the run's (default config/sim.yaml), then its own overlay,
    written into ``workdir`` so that the run can be repeated."""
    from cwfs_ros.ros.launch import sim_params_file

    workdir.mkdir(parents=True, exist_ok=True)
    overlay_path = workdir / "params_overlay.yaml"
    overlay_path.write_text(yaml.safe_dump(_overlay(config), sort_keys=False))
    return [*([sim_params_file()] if config.params_files is None
              else [Path(f) for f in config.params_files]), overlay_path]


def _restore_env(name: str, saved: str | None) -> None:
    """Put the environment variable ``name`` back as it was (unset when ``saved`` is None)."""
    if saved is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = saved


def _drive(config: LoopConfig, monitor: LoopMonitor, nodes: dict[str, Any], t0: float,
           on_visit: Callable[[VisitRecord], None] | None,
           say: Callable[[str], None]) -> LoopRun:
    """Wait for the started graph to be ready (service, warm workers, connections), then run
    the visits one at a time; ``t0`` is when the start began (start-up and wall times)."""
    cam, wf = nodes["camera_sim_node"], nodes["wavefront_node"]
    if not monitor.trigger.wait_for_service(timeout_sec=20):
        raise LoopError("camera_sim_node/trigger did not appear")
    say("warming up the per-corner estimator workers ...")
    _wait(lambda: wf.ready, 120, "wavefront_node workers to warm up")
    _wait(lambda: all(p.get_subscription_count() > 0 for p in cam.pubs.values()), 20,
          "wavefront_node to subscribe to the camera")
    _wait(monitor.connected, 20, "the monitor to connect")
    startup = time.monotonic() - t0
    keep = {k if k > 0 else config.visits + 1 + k for k in config.keep_images}
    records: list[VisitRecord] = []
    for k in range(1, config.visits + 1):
        rec = monitor.run_visit(cam, keep_images=k in keep, timeout_s=config.visit_timeout_s)
        records.append(rec)
        if on_visit is not None:
            on_visit(rec)
    return LoopRun(config=config, records=records, startup_s=startup,
                   wall_s=time.monotonic() - t0, camera_stats=dict(cam.stats))


def _wait(cond: Callable[[], bool], timeout: float, what: str) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return
        time.sleep(0.01)
    raise LoopError(f"timed out after {timeout:g} s waiting for {what}")


class LoopMonitor:
    """A node that drives the loop one visit at a time and keeps what it hears.

    Built lazily as a plain object wrapping an rclpy Node, so that importing this module
    does not import rclpy.
    """

    def __init__(self, context) -> None:
        import rclpy
        from cwfs_msgs.msg import CornerWavefront, DofCorrection, SimTruth, WavefrontVector
        from sensor_msgs.msg import Image
        from std_srvs.srv import Trigger

        from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS

        self._Trigger = Trigger
        self.node = rclpy.create_node("cwfs_demo_monitor", context=context)
        self._lock = threading.Lock()
        self._arrivals: dict[tuple[str, int], float] = {}
        self.truths: dict[int, Any] = {}
        self.vectors: dict[int, Any] = {}
        self.corrections: dict[int, Any] = {}
        self.corners: dict[tuple[int, str], Any] = {}
        self.images: dict[int, dict[tuple[str, str], Any]] = {}
        self.subs = [
            self.node.create_subscription(SimTruth, TRUTH_TOPIC,
                                          self._keeper("truth", self.truths), OUTPUT_QOS),
            self.node.create_subscription(WavefrontVector, VECTOR_TOPIC,
                                          self._keeper("vector", self.vectors), OUTPUT_QOS),
            self.node.create_subscription(DofCorrection, CORRECTION_TOPIC,
                                          self._keeper("dof", self.corrections), OUTPUT_QOS),
        ]
        for c in CORNERS:
            self.subs.append(self.node.create_subscription(
                CornerWavefront, corner_topic(c),
                lambda m, c=c: self._store_corner(c, m), OUTPUT_QOS))
            for s in SIDES:
                self.subs.append(self.node.create_subscription(
                    Image, image_topic(c, s),
                    lambda m, c=c, s=s: self._store_image(c, s, m), IMAGE_QOS))
        self.trigger = self.node.create_client(Trigger, "camera_sim_node/trigger")

    def connected(self) -> bool:
        return all(s.get_publisher_count() > 0 for s in self.subs)

    @staticmethod
    def _stamp(msg) -> int:
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)

    def _keeper(self, kind: str, store: dict[int, Any]) -> Callable[[Any], None]:
        def keep(msg) -> None:
            stamp = self._stamp(msg)
            with self._lock:
                store[stamp] = msg
                self._arrivals[(kind, stamp)] = time.monotonic()
        return keep

    def _store_corner(self, corner: str, msg) -> None:
        with self._lock:
            self.corners[(self._stamp(msg), corner)] = msg

    def _store_image(self, corner: str, side: str, msg) -> None:
        from cwfs_ros.ros.convert import image_record_from_msg

        rec = image_record_from_msg(msg, corner, side, time.monotonic())
        with self._lock:
            self.images.setdefault(rec.stamp_ns, {})[(corner, side)] = rec

    def run_visit(self, cam, *, keep_images: bool, timeout_s: float) -> VisitRecord:
        """Trigger one visit and wait for its truth, estimate, correction and its application."""
        with self._lock:
            n_truth = len(self.truths)
        handled = cam.stats["corrections_applied"] + cam.stats["corrections_ignored"]
        t_trigger = time.monotonic()
        fut = self.trigger.call_async(self._Trigger.Request())
        _wait(fut.done, 30, "the camera's trigger response")
        if not fut.result().success:
            raise LoopError(f"camera_sim_node refused the visit: {fut.result().message}")
        _wait(lambda: len(self.truths) > n_truth, timeout_s, "the visit's SimTruth")
        with self._lock:
            stamp = max(self.truths)
            truth = self.truths[stamp]
        _wait(lambda: stamp in self.corrections, timeout_s,
              f"the DofCorrection of the visit at stamp {stamp}")
        # The camera applies (or refuses) the correction in its own callback: wait for it, so
        # the next visit is rendered with the corrected state.
        _wait(lambda: cam.stats["corrections_applied"] + cam.stats["corrections_ignored"]
              > handled, 30, "the camera to apply the correction")
        with self._lock:
            vec = self.vectors.get(stamp)
            dof = self.corrections[stamp]
            t_truth = self._arrivals[("truth", stamp)]
            t_vec = self._arrivals.get(("vector", stamp), float("nan"))
            t_dof = self._arrivals[("dof", stamp)]
            corners = [self.corners.get((stamp, c)) for c in CORNERS]
            imgs = self.images.pop(stamp, {})
            # The images arrive before the truth (the camera publishes them first); the
            # estimate starts on the last of the 8.
            t_images = max((r.received for r in imgs.values()), default=t_truth)
            # Drop what is no longer needed (bounded memory over long runs).
            for old in [s for s in self.images if s < stamp]:
                del self.images[old]
        est, valid = _estimate_of(vec)
        return VisitRecord(
            visit=int(truth.visit), stamp_ns=stamp,
            dof_state=np.asarray(truth.dof_state, dtype=np.float64).copy(),
            truth_nm=np.asarray(truth.zernikes_nm, dtype=np.float64).copy(),
            intrinsic_nm=np.asarray(truth.intrinsic_nm, dtype=np.float64).copy(),
            estimate_nm=est, corner_valid=valid,
            corner_status=[m.status if m is not None else "not received" for m in corners],
            correction=np.asarray(dof.dof, dtype=np.float64).copy(),
            correction_valid=bool(dof.valid), correction_status=str(dof.status),
            predicted_residual_nm=float(dof.predicted_residual_rms_nm),
            render_s=t_images - t_trigger, estimate_s=t_vec - t_images, solve_s=t_dof - t_vec,
            corner_compute_ms=np.array([m.compute_ms if m is not None else np.nan
                                        for m in corners], dtype=np.float64),
            images=({k: r.image for k, r in imgs.items() if r.image is not None}
                    if keep_images else None),
            field_error_nm=float(truth.field_wavefront_rms_nm),
            fwhm_arcsec=float(truth.fwhm_arcsec),
            rotator_angle_deg=float(truth.rotator_angle_deg),
            predicted_field_nm=float(dof.predicted_field_rms_nm),
        )


def _estimate_of(vec: Any) -> tuple[np.ndarray, np.ndarray]:
    """A visit's estimated Zernikes (nm, NaN for the invalid corners) and the corner flags
    from its WavefrontVector (None: not received, every corner invalid)."""
    if vec is not None:
        est = np.asarray(vec.zernikes_nm, dtype=np.float64).copy()
        valid = np.asarray(vec.corner_valid, dtype=bool)
    else:
        est, valid = np.full(len(CORNERS) * N_ZK, np.nan), np.zeros(len(CORNERS), bool)
    for i, ok in enumerate(valid):
        if not ok:
            est[i * N_ZK:(i + 1) * N_ZK] = np.nan
    return est, valid


# ------------------------------------------------------------------------------ report
def write_report(run: LoopRun, out_dir: str | Path) -> dict[str, Path]:
    """Write the run's report: PNG figure, HTML page, per-visit CSV and a JSON summary."""
    from cwfs_ros.cli.plotting import plot_closed_loop

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"png": out / "closed_loop.png", "html": out / "report.html",
             "csv": out / "visits.csv", "json": out / "summary.json"}
    plot_closed_loop(run, paths["png"])
    with paths["csv"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["visit", "stamp_ns", "true_error_nm", "true_field_error_nm", "fwhm_arcsec",
                    "rotator_angle_deg", "estimated_error_nm",
                     "median_corner_estimate_rms_error_nm", "correction_valid",
                     "correction_status", "render_s", "estimate_s", "solve_s",
                     *[f"dof_state_{i}" for i in range(N_DOF)],
                     *[f"correction_{i}" for i in range(N_DOF)]])
        for r in run.records:
            w.writerow([r.visit, r.stamp_ns, f"{r.true_error_nm:.3f}",
                        f"{r.field_error_nm:.3f}", f"{r.fwhm_arcsec:.4f}",
                        f"{r.rotator_angle_deg:g}", f"{r.estimated_error_nm:.3f}",
                        f"{r.median_estimate_error_nm:.3f}", r.correction_valid,
                        r.correction_status, f"{r.render_s:.3f}", f"{r.estimate_s:.4f}",
                        f"{r.solve_s:.4f}", *[f"{x:.6g}" for x in r.dof_state],
                        *[f"{x:.6g}" for x in r.correction]])
    paths["json"].write_text(json.dumps(run.summary(), indent=2) + "\n")
    paths["html"].write_text(_html(run, paths["png"].name))
    return paths


def _html(run: LoopRun, png_name: str) -> str:
    rows = "\n".join(
        f"<tr><td>{r.visit}</td><td>{r.true_error_nm:.1f}</td>"
        f"<td>{r.field_error_nm:.1f}</td><td>{r.fwhm_arcsec:.3f}</td>"
        f"<td>{r.estimated_error_nm:.1f}</td>"
        f"<td>{r.median_estimate_error_nm:.1f}</td>"
        f"<td>{'yes' if r.correction_valid else 'no: ' + r.correction_status}</td>"
        f"<td>{r.render_s:.1f}</td><td>{1e3 * r.estimate_s:.0f}</td>"
        f"<td>{1e3 * r.solve_s:.0f}</td></tr>" for r in run.records)
    e, fe = run.true_error_nm, run.field_error_nm
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>cwfs_ros closed-loop demo</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto}}
td,th{{padding:2px 10px;text-align:right}}</style></head><body>
<h1>cwfs_ros closed-loop demo</h1>
<p>{len(run.records)} visits of the simulated Rubin/LSST telescope (batoid ray tracing,
{run.config.n_photons:g} photons per donut) through camera_sim_node, wavefront_node and
ofc_node. True wavefront error (design removed, mean over corners of
sqrt(&Sigma; Z4..Z22&sup2;)): {e[0]:.0f} nm at the first visit, {e[-1]:.0f} nm at the last,
a reduction of {run.reduction(5):.1f}&times; within {min(5, len(e))} visits. Over the science
field (31 Gaussian-quadrature points): {fe[0]:.0f} nm &rarr; {fe[-1]:.0f} nm, a reduction of
{run.reduction(5, "field"):.1f}&times; within {min(5, len(e))} visits. Camera rotator
{run.config.rotator_angle_deg:g}&deg;.</p>
<img src="{png_name}" style="width:100%">
<table><tr><th>visit</th><th>true corner error (nm)</th><th>true field error (nm)</th>
<th>optical FWHM (arcsec)</th><th>estimated error (nm)</th>
<th>median corner estimate RMS error (nm)</th><th>correction valid</th><th>render (s)</th>
<th>estimate (ms)</th><th>solve (ms)</th></tr>
{rows}
</table></body></html>
"""
