"""Run the per-corner wavefront estimates in parallel worker processes (no ROS imports).

The estimator is numpy code that holds the GIL most of the time, so the four corners of a
visit run in separate *processes*. :class:`CornerPool` keeps ``n_workers`` single-process
executors ("slots") and pins every corner to one slot (round robin), so that the geometry cache
of :func:`cwfs_ros.wfs.estimator.pair_geometry` (~0.3-1 s to build per corner, ~25 ms per
estimate once built) stays warm in the worker that serves the corner. :meth:`CornerPool.warm_up`
builds those caches at start by estimating a synthetic donut pair per corner.

Workers are started with the ``forkserver`` method (``spawn`` where it is unavailable): the
parent may be a ROS process with middleware threads, which must not be ``fork()``-ed. The fork
server pre-imports the estimator, so a worker is ready in well under a second.

What crosses the process boundary is a small picklable dataclass: a :class:`CornerJob` in,
a :class:`CornerOutcome` out; a frames job's two frames travel in shared memory
(:mod:`.shared_frames`). A job never raises in the worker: bad images and configuration
come back as an invalid outcome whose ``status`` names the problem.
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cwfs_ros.errors import ConfigError, CwfsError
from cwfs_ros.layout import NOLL as _NOLL
from cwfs_ros.runtime.shared_frames import FrameBlocks, SharedFrameJob
from cwfs_ros.wfs.orientation import Orientation, orient_image, pad_stamp
from cwfs_ros.wfs.settings import EstimatorSettings

__all__ = [
    "CornerJob",
    "CornerOutcome",
    "CornerPool",
    "FrameFiles",
    "frames_nbytes",
    "invalid_outcome",
    "frame_outcome",
    "run_corner_job",
    "run_frame_job",
    "synthetic_donut",
    "warm_corner",
    "worker_cache_counts",
]



@dataclass(frozen=True)
class CornerJob:
    """One corner's pair for one visit, as decoded from the two image messages."""

    corner: str
    stamp_ns: int
    intra: np.ndarray
    extra: np.ndarray
    field_intra_deg: tuple[float, float]
    field_extra_deg: tuple[float, float]
    settings: EstimatorSettings
    orient_intra: Orientation = Orientation()
    orient_extra: Orientation = Orientation()
    hint: str = ""  # a frame-sized image in stamps mode: what to change if it is refused


@dataclass(frozen=True)
class CornerOutcome:
    """Result of a :class:`CornerJob` (what a ``CornerWavefront`` carries).

    Attributes:
        zernikes_nm: (19,) Z4..Z22 in nm (NaN when not valid).
        status: ``"ok"`` or ``"<tag>: <explanation>"``.
        reason: the tag alone (``""`` when valid), for counting.
        field_deg: field of the estimate (mid-point of the two half-chips), degrees.
        compute_ms: wall time spent in the worker, ms.
        uncertainty_nm: (19,) one-sigma per term in nm, or ``None`` when not estimated;
            a stamp pair gives the calibrated noise model's (:func:`stamp_uncertainty_nm`),
            frames the pairs' combination's.
        n_pairs: donut pairs combined (1 for a stamp pair; 0 when none was usable).
        caches: the worker's geometry caches after the job (:func:`worker_cache_counts`).
    """

    corner: str
    stamp_ns: int
    valid: bool
    status: str
    reason: str
    zernikes_nm: np.ndarray
    field_deg: tuple[float, float]
    caustic: bool = False
    converged: bool = False
    iterations: int = 0
    compute_ms: float = 0.0
    solver: str = ""
    worker_pid: int = 0
    noll: tuple[int, ...] = field(default=_NOLL)
    uncertainty_nm: np.ndarray | None = None
    n_pairs: int = 1
    caches: dict[str, tuple[int, int, int, int]] = field(default_factory=dict)


def worker_cache_counts() -> dict[str, tuple[int, int, int, int]]:
    """(hits, builds, held, size) of this process's geometry caches since it started: the
    field tiles (``map``, ``pupil``, ``design``: :func:`cwfs_ros.wfs.mapping.field_tile_stats`)
    and ``pair_geometry`` (one per pair of star fields: stamps at the configured fields hit
    it every visit; frames, whose stars move, build one per pair from the tiles)."""
    from cwfs_ros.wfs.estimator import pair_geometry
    from cwfs_ros.wfs.mapping import field_tile_stats

    out = {k: (t.hits, t.builds, t.held, t.size) for k, t in field_tile_stats().items()}
    info = pair_geometry.cache_info()
    out["pair_geometry"] = (info.hits, info.misses, info.currsize, int(info.maxsize or 0))
    return out


def _with_caches(out: CornerOutcome) -> CornerOutcome:
    try:
        return replace(out, caches=worker_cache_counts())
    except Exception:  # noqa: BLE001 - the counts are a report; the outcome matters
        return out


def _mid(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    return (0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1]))


def invalid_outcome(corner: str, stamp_ns: int, reason: str, message: str,
                    field_intra: tuple[float, float], field_extra: tuple[float, float],
                    solver: str = "", compute_ms: float = 0.0) -> CornerOutcome:
    """An invalid outcome whose status is ``"<reason>: <message>"``."""
    status = message if message.startswith(reason + ":") else f"{reason}: {message}"
    return CornerOutcome(corner, int(stamp_ns), False, status, reason,
                         np.full(len(_NOLL), np.nan), _mid(field_intra, field_extra),
                         solver=solver, compute_ms=compute_ms, worker_pid=os.getpid(), n_pairs=0)


def _shapes(job: CornerJob) -> str:
    out = []
    for side, a in (("intra", job.intra), ("extra", job.extra)):
        shp = np.shape(a)
        out.append(f"{side} {shp[1]}x{shp[0]}" if len(shp) == 2 else f"{side} {shp}")
    return ", ".join(out)


def run_corner_job(job: CornerJob) -> CornerOutcome:
    """Estimate one corner (runs in a worker process; never raises)."""
    return _with_caches(_estimate_corner(job))


def _estimate_corner(job: CornerJob) -> CornerOutcome:
    from cwfs_ros.wfs.estimator import estimate_wavefront

    t0 = time.perf_counter()
    s = job.settings

    def fail(reason: str, message: str) -> CornerOutcome:
        return invalid_outcome(job.corner, job.stamp_ns, reason, message, job.field_intra_deg,
                               job.field_extra_deg, s.solver,
                               (time.perf_counter() - t0) * 1e3)

    try:
        intra = pad_stamp(orient_image(np.asarray(job.intra, dtype=np.float64),
                                       job.orient_intra), s.pad_px)
        extra = pad_stamp(orient_image(np.asarray(job.extra, dtype=np.float64),
                                       job.orient_extra), s.pad_px)
        res = estimate_wavefront(intra, extra, field_intra_deg=job.field_intra_deg,
                                 field_extra_deg=job.field_extra_deg,
                                 **s.estimator_kwargs())
    except CwfsError as exc:
        reason = getattr(exc, "reason", None) or ("config" if isinstance(exc, ConfigError)
                                                  else "bad_image")
        msg = str(exc)
        if s.pad_px > 0 and not isinstance(exc, ConfigError):
            msg += (f" (received stamps {_shapes(job)} px, padded by {s.pad_px} px on each "
                    "side)")
        if job.hint and not isinstance(exc, ConfigError):
            # The cause is the mode, not the image: said first, the estimator's refusal after.
            return fail("frame_as_stamp", f"{job.hint} (as a stamp: {reason}: {msg})")
        return fail(str(reason), msg)
    except Exception as exc:  # noqa: BLE001 - a worker must report, not die
        return fail("internal_error", f"{type(exc).__name__}: {exc}")
    z = np.asarray(res.zernikes_nm, dtype=np.float64)
    ms = (time.perf_counter() - t0) * 1e3
    if res.iterations < 1:
        return fail("caustic", "the compensation folded into caustic at the first outer "
                    "iteration: no estimate (defocus too small for this wavefront?)")
    if z.shape != (len(_NOLL),) or not np.all(np.isfinite(z)):
        return fail("non_finite_estimate", "the estimator returned NaN/Inf Zernikes")
    return CornerOutcome(job.corner, int(job.stamp_ns), True, "ok", "", z,
                         tuple(float(v) for v in res.field_deg), bool(res.caustic),
                         bool(res.converged), int(res.iterations), ms, res.solver,
                         os.getpid(), uncertainty_nm=stamp_uncertainty_nm(res, s.solver),
                         n_pairs=1)


def stamp_uncertainty_nm(res: Any, solver: str) -> np.ndarray | None:
    """(19,) one-sigma of a single stamp pair's terms (nm), from the donuts' S/N and the
    noise model that the frame combination uses (``combination`` of config/selection.yaml,
    fitted on simulations): ``sqrt((c_j q)^2 + f_j^2)``. None when it cannot be had."""
    from cwfs_ros.frames.combination import pair_noise_scale, pair_sigma_nm

    try:
        cfg = _combination_config(solver)
        q = pair_noise_scale(float(res.inputs["intra"].snr), float(res.inputs["extra"].snr))
        sig = pair_sigma_nm(np.array([q]), cfg)[0]
    except Exception:  # noqa: BLE001 - an uncertainty must not cost the estimate
        return None
    return sig if sig.shape == (len(_NOLL),) and np.all(np.isfinite(sig)) else None


@functools.lru_cache(maxsize=4)
def _combination_config(solver: str) -> Any:
    from cwfs_ros.frames.selection import load_selection_config

    return load_selection_config(None, solver=solver).combination


def frame_outcome(res: Any) -> CornerOutcome:
    """A :class:`CornerOutcome` from a :class:`~cwfs_ros.frames.selection.CornerFrameResult`."""
    z = np.asarray(res.zernikes_nm, dtype=np.float64)
    unc = np.asarray(res.uncertainty_nm, dtype=np.float64)
    ms = float(res.timing_ms.get("total", 0.0))
    if not res.valid:  # the summary: its reason first, then what was dropped and noted
        return CornerOutcome(res.corner, int(res.stamp_ns), False, res.summary(), res.reason,
                             np.full(len(_NOLL), np.nan), tuple(res.field_deg),
                             caustic=bool(res.caustic), compute_ms=ms, solver=res.solver,
                             worker_pid=res.worker_pid, uncertainty_nm=None,
                             n_pairs=int(res.n_pairs))
    if z.shape != (len(_NOLL),) or not np.all(np.isfinite(z)):
        return invalid_outcome(res.corner, res.stamp_ns, "non_finite_estimate",
                               "the frame combination returned NaN/Inf Zernikes",
                               tuple(res.field_deg), tuple(res.field_deg), res.solver, ms)
    return CornerOutcome(res.corner, int(res.stamp_ns), True, res.summary(), "", z,
                         tuple(float(v) for v in res.field_deg), bool(res.caustic),
                         bool(res.converged), int(res.iterations), ms, res.solver,
                         res.worker_pid,
                         uncertainty_nm=unc, n_pairs=int(res.n_pairs))


def frames_nbytes(frames: FrameFiles, corners: Sequence[str]) -> dict[str, int]:
    """Bytes of each of ``corners``' two whole half-chips (from the sensor file of
    ``frames``) as float32, what 8- and 16-bit and 32FC1 cameras decode to
    (:func:`.images.decoded_dtype`); ``{}`` where the sensor file cannot be read (the
    workers' warm-up reports that)."""
    from cwfs_ros.frames.field_position import load_half_chips

    try:
        halves = load_half_chips(frames.sensor_config or None)
    except (CwfsError, OSError):
        return {}
    itemsize = np.dtype(np.float32).itemsize
    return {c: sum(int(np.prod(h.shape_px)) for h in halves[c].values()) * itemsize
            for c in corners if c in halves}


def run_frame_job(job: Any) -> CornerOutcome:
    """Estimate one corner from its two frames (runs in a worker process; never raises).

    ``job`` is a :class:`~cwfs_ros.frames.selection.CornerFrameJob`, or a
    :class:`.shared_frames.SharedFrameJob` whose frames are read from shared memory first.
    """
    from cwfs_ros.frames.selection import run_corner_frame_job

    if isinstance(job, SharedFrameJob):
        try:
            job = job.load()
        except OSError as exc:
            nan_field = (float("nan"), float("nan"))
            return invalid_outcome(job.corner, job.stamp_ns, "internal_error",
                                   f"the frames could not be read from shared memory "
                                   f"({type(exc).__name__}: {exc})", nan_field, nan_field,
                                   job.job.settings.solver)
    return _with_caches(frame_outcome(run_corner_frame_job(job)))


def synthetic_donut(stamp_px: int, radius_px: float, obscuration: float) -> np.ndarray:
    """A flat annulus in a square stamp: enough to build and exercise the estimator caches."""
    n = int(stamp_px)
    yy, xx = np.mgrid[0:n, 0:n] - (n - 1) / 2.0
    r = np.hypot(xx, yy)
    img = ((r <= radius_px) & (r >= obscuration * radius_px)).astype(np.float64) * 100.0
    return img + 1.0


@dataclass(frozen=True)
class FrameFiles:
    """The files a frames job reads: wavefront_node's ``sensor_config`` and
    ``selection_config`` ("" = the bundled ones); and the directory of the field-tile store
    the warm-up turns on for the worker's life (``tile_store``, resolved; "" = none)."""

    sensor_config: str = ""
    selection_config: str = ""
    tile_store: str = ""  # the directory of the field-tile store ("" = none)


def warm_corner(corner: str, field_intra_deg: tuple[float, float],
                field_extra_deg: tuple[float, float], settings: EstimatorSettings,
                stamp_px: int = 0, frames: FrameFiles | None = None) -> dict:
    """Build the estimator caches of one corner in this (worker) process.

    Estimates a synthetic annulus pair once: that builds the pair geometry (the slow part) and
    runs every code path of an estimate. The result of that estimate is irrelevant; errors are
    reported, not raised. With ``frames``, also builds the field tiles of every star field
    the corner's two half-chips can hold and reads the selection file
    (:func:`_warm_frames`), so that the first frames visit costs what any other does.
    """
    from cwfs_ros.wfs.estimator import estimate_wavefront, load_algorithm, pair_geometry
    from cwfs_ros.wfs.instrument import load_instrument

    t0 = time.perf_counter()
    try:
        inst = load_instrument(settings.instrument)
        n = int(stamp_px) if stamp_px else int(inst.stamp_size_px)
        algo = load_algorithm(settings.solver, **({"outer_iterations": settings.outer_iterations}
                                                   if settings.outer_iterations > 0 else {}))
        geom = pair_geometry(inst, settings.band, inst.wavelength_nm(settings.band, None),
                             tuple(field_intra_deg), tuple(field_extra_deg),
                             inst.defocal_offset_mm, algo)
        img = synthetic_donut(n + 2 * settings.pad_px, 0.92 * geom.outer_radius_px,
                              inst.obscuration)
        t1 = time.perf_counter()
        try:
            estimate_wavefront(img, img, field_intra_deg=field_intra_deg,
                               field_extra_deg=field_extra_deg, **settings.estimator_kwargs())
        except CwfsError:
            pass  # the synthetic pair may be rejected; the caches are built regardless
        t2 = time.perf_counter()
        tiles, loaded = _warm_frames(corner, inst, settings, algo, frames) if frames else (0, 0)
        return {"corner": corner, "ok": True, "pid": os.getpid(),
                "geometry_s": t1 - t0, "tiles": tiles, "tiles_loaded": loaded,
                "tile_store": _tile_store_report(),
                "tiles_s": time.perf_counter() - t2,
                "total_s": time.perf_counter() - t0, "error": "",
                "caches": worker_cache_counts()}
    except Exception as exc:  # noqa: BLE001
        return {"corner": corner, "ok": False, "pid": os.getpid(),
                "geometry_s": 0.0, "total_s": time.perf_counter() - t0,
                "error": f"{type(exc).__name__}: {exc}"}


def _tile_store_report() -> str:
    """This worker's tile-store problems in one line ("" = none, or no store)."""
    from cwfs_ros.wfs.tile_store import active_tile_store

    store = active_tile_store()
    return store.report() if store is not None else ""


def _warm_frames(corner: str, inst: Any, settings: EstimatorSettings, algo: Any,
                 files: FrameFiles) -> tuple[int, int]:
    """Make the field tiles of every star field of the corner's half-chips (and read the
    selection file): (tiles made, of which read from the tile store). A tile is traced in
    ~1.2 s (map tiles; 9 per LSST corner), or read from the store in milliseconds."""
    from cwfs_ros.frames.field_position import corner_star_fields, load_half_chips
    from cwfs_ros.frames.selection import load_selection_config
    from cwfs_ros.wfs.estimator import warm_star_fields
    from cwfs_ros.wfs.mapping import field_tile_stats, use_field_tile_store

    use_field_tile_store(files.tile_store or None)  # for this worker's life
    load_selection_config(files.selection_config or None, solver=settings.solver)
    halves = load_half_chips(files.sensor_config or None)[corner]
    side_fields, mids = corner_star_fields(halves, inst, settings.band)
    loaded = sum(t.loaded for t in field_tile_stats().values())
    made = warm_star_fields(inst, settings.band, inst.wavelength_nm(settings.band, None),
                            algo, side_fields, mids)
    return made, sum(t.loaded for t in field_tile_stats().values()) - loaded


def _worker_init(owner_pid: int = 0) -> None:
    """Worker start-up: one BLAS/OpenMP thread per worker (the pool is the parallelism; n
    workers x n BLAS threads would oversubscribe the cores), and :func:`die_with_owner`."""
    die_with_owner(owner_pid)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # every thread pool, whatever the environment says


# How often a worker checks that the process owning its pool is alive [s].
OWNER_POLL_S = 0.5
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_owner(owner_pid: int) -> None:
    """Make this worker process end with the process that owns its pool (run in the worker).

    A node killed outright (SIGKILL, the OOM killer) runs no clean-up, and its workers would
    live on holding their memory. Two guards: ``PR_SET_PDEATHSIG`` (Linux) sends SIGKILL when
    the worker's parent dies (the fork server, which exits with the node); a daemon thread
    exits the worker once ``owner_pid`` is gone, polled every :data:`OWNER_POLL_S` s (the
    parent of a fork-server worker is not the node). SIGINT is ignored: Ctrl-C reaches the
    whole process group, and the node, not each worker, shuts the pool down (without the
    workers' KeyboardInterrupt tracebacks).
    """
    import signal

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except (ValueError, OSError):  # not the main thread: leave it
        pass
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except Exception:  # noqa: BLE001, S110 - not Linux: the watchdog alone
        pass
    if owner_pid > 0:
        threading.Thread(target=_watch_owner, args=(int(owner_pid),), daemon=True,
                         name="owner_watchdog").start()


def _watch_owner(owner_pid: int) -> None:
    while True:
        time.sleep(OWNER_POLL_S)
        try:
            os.kill(owner_pid, 0)
        except ProcessLookupError:
            os._exit(0)
        except OSError:  # EPERM: the pid exists (reused by another user's process)
            os._exit(0)


def guard_pool_workers(pool: Any) -> Any:
    """Give an existing ``ProcessPoolExecutor`` (whose workers are not started yet) the
    :func:`die_with_owner` start-up, chained before its own initializer. Returns ``pool``.

    For pools built elsewhere (the camera simulator's render pool); relies on CPython's
    ``_initializer`` / ``_initargs`` attributes and leaves a pool without them unchanged.
    """
    if pool is None or not hasattr(pool, "_initializer"):
        return pool
    pool._initargs = (os.getpid(), pool._initializer, tuple(pool._initargs or ()))
    pool._initializer = _chained_init
    return pool


def _chained_init(owner_pid: int, inner: Callable | None, args: tuple) -> None:
    die_with_owner(owner_pid)
    if inner is not None:
        inner(*args)


def _mp_context(method: str | None) -> mp.context.BaseContext:
    methods = mp.get_all_start_methods()
    name = method or ("forkserver" if "forkserver" in methods else "spawn")
    if name not in methods:
        raise ConfigError(f"start method {name!r} not available here ({methods})")
    ctx = mp.get_context(name)
    if name == "forkserver":
        # Only effective before the fork server starts (once per process); harmless after.
        ctx.set_forkserver_preload(["numpy", "scipy.ndimage", "cwfs_ros.wfs.estimator",
                                    "cwfs_ros.runtime.corner_pool", "batoid"])
    return ctx


class CornerPool:
    """Per-corner-affine process pool.

    Args:
        corners: the corners this pool serves; corner ``corners[i]`` runs in slot
            ``i % n_workers``.
        n_workers: worker processes (``0`` = ``min(len(corners), os.cpu_count())``).
        start_method: multiprocessing start method (default ``forkserver``, else ``spawn``).
    """

    def __init__(self, corners: Sequence[str], n_workers: int = 0,
                 start_method: str | None = None) -> None:
        if not corners:
            raise ConfigError("CornerPool needs at least one corner")
        self.corners = tuple(corners)
        n = int(n_workers) or min(len(self.corners), os.cpu_count() or 1)
        self.n_workers = max(1, min(n, len(self.corners)))
        self._ctx = _mp_context(start_method)
        self._lock = threading.Lock()
        self._slots: list[ProcessPoolExecutor | None] = [None] * self.n_workers
        self.affinity = {c: i % self.n_workers for i, c in enumerate(self.corners)}
        self._queued = [0] * self.n_workers  # jobs submitted to each slot and not finished
        self.restarts = 0
        self._closed = False
        # A frames job's frames in shared memory: one idle block kept per served corner.
        self._blocks = FrameBlocks(keep=len(self.corners))
        # Frames jobs sent through shared memory and through the pipe (no block could be
        # made: /dev/shm short of room, or no shared memory): /diagnostics frame_transport.
        self.frames_shared = 0
        self.frames_piped = 0
        # Each corner's last warm-up (warm_corner's arguments after the corner): a worker
        # restarted after a crash is warmed again before its first job.
        self._warm_args: dict[str, tuple] = {}
        self._cold: set[int] = set()  # slots restarted and not yet warmed again
        self.rewarms = 0

    def _slot(self, i: int) -> ProcessPoolExecutor:
        with self._lock:
            if self._closed:
                raise RuntimeError("CornerPool is shut down")
            ex = self._slots[i]
            if ex is not None:
                return ex
            ex = ProcessPoolExecutor(max_workers=1, mp_context=self._ctx,
                                     initializer=_worker_init, initargs=(os.getpid(),))
            self._slots[i] = ex
            rewarm = [(c, self._warm_args[c]) for c, k in self.affinity.items()
                      if k == i and c in self._warm_args] if i in self._cold else []
            self._cold.discard(i)
        self._rewarm(i, ex, rewarm)
        return ex

    def _rewarm(self, i: int, ex: ProcessPoolExecutor, corners: list[tuple[str, tuple]]
                ) -> None:
        """Queue the warm-up of ``corners`` on slot ``i``'s new worker ahead of any job (the
        slot is made again as soon as its worker's death is seen): a
        worker restarted after a crash would otherwise build its caches (and trace field
        tiles, without the tile store the warm-up turns on) inside its first visits, miss
        the visit timeout and skew the measured costs the corners are balanced by."""
        for corner, args in corners:
            try:
                f = ex.submit(warm_corner, corner, *args)
            except BrokenProcessPool:
                return  # the next job restarts the slot again
            with self._lock:
                self._queued[i] += 1
                self.rewarms += 1
            f.add_done_callback(lambda _f: self._finished(i))

    def _restart(self, i: int, broken: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._slots[i] is broken:
                self._slots[i] = None
                self.restarts += 1
                self._cold.add(i)
        broken.shutdown(wait=False, cancel_futures=True)
        # The new worker now, warmed while the next visit is still on its way.
        try:
            self._slot(i)
        except (RuntimeError, OSError):
            pass  # shut down meanwhile, or no process now: the next job starts one

    def _submit_on(self, corner: str, fn: Callable, *args, slot: int | None = None
                   ) -> tuple[Future, ProcessPoolExecutor]:
        """``fn(*args)`` on the corner's worker (or on ``slot``): its future, and the executor
        that runs it (the one to restart if it breaks: by then the slot may hold a newer,
        healthy one)."""
        i = self.affinity[corner] if slot is None else int(slot)
        ex = self._slot(i)
        try:
            f = ex.submit(fn, *args)
        except BrokenProcessPool:
            self._restart(i, ex)
            ex = self._slot(i)
            f = ex.submit(fn, *args)
        with self._lock:
            self._queued[i] += 1
        f.add_done_callback(lambda _f: self._finished(i))
        return f, ex

    def _finished(self, i: int) -> None:
        with self._lock:
            self._queued[i] = max(0, self._queued[i] - 1)

    def queued(self) -> dict[int, int]:
        """Jobs (estimates and warm-ups) submitted to each worker and not yet finished."""
        with self._lock:
            return dict(enumerate(self._queued))

    def assign(self, affinity: dict[str, int]) -> None:
        """Serve each corner from the given worker from the next job on (every served corner
        must be given a worker of this pool)."""
        if set(affinity) != set(self.corners) or not all(
                0 <= int(i) < self.n_workers for i in affinity.values()):
            raise ConfigError(f"an assignment of {sorted(self.corners)} to workers "
                              f"0..{self.n_workers - 1} was expected, got {affinity}")
        with self._lock:
            self.affinity = {c: int(i) for c, i in affinity.items()}

    def submit(self, job: CornerJob) -> Future:
        """Queue a job on its corner's worker. The future's result is a CornerOutcome.

        If the worker process dies, the future resolves to an invalid outcome
        (``worker_crashed``) and the slot is restarted for the next job.
        """
        return self._guarded(job.corner, job.stamp_ns, run_corner_job, job,
                             (job.field_intra_deg, job.field_extra_deg), job.settings.solver)

    def submit_frames(self, job: Any) -> Future:
        """Queue a :class:`~cwfs_ros.frames.selection.CornerFrameJob` (two full half-chip
        frames) on its corner's worker; the future's result is a :class:`CornerOutcome`
        carrying the combination of every usable donut pair (``n_pairs``,
        ``uncertainty_nm``). A dead worker gives ``worker_crashed``, as for :meth:`submit`.

        The frames go to the worker through shared memory (:mod:`.shared_frames`), released
        when the future is done; through the pipe where no block can be made.
        """
        nan_field = (float("nan"), float("nan"))
        shared = self._blocks.share(job)
        with self._lock:
            if shared is None:
                self.frames_piped += 1
            else:
                self.frames_shared += 1
        try:
            fut = self._guarded(job.corner, job.stamp_ns, run_frame_job,
                                job if shared is None else shared[0], (nan_field, nan_field),
                                job.settings.solver)
        except BaseException:
            if shared is not None:
                self._blocks.give_back(shared[1])
            raise
        if shared is not None:  # the worker has copied the frames out once the job is done
            fut.add_done_callback(lambda _f, shm=shared[1]: self._blocks.give_back(shm))
        return fut

    def _guarded(self, corner: str, stamp_ns: int, fn: Callable, job: Any,
                 fields: tuple[tuple[float, float], tuple[float, float]],
                 solver: str) -> Future:
        """Run ``fn(job)`` on the corner's worker; a future of its CornerOutcome, or of an
        invalid ``worker_crashed`` outcome (and a restarted slot) if the worker dies."""
        if corner not in self.affinity:
            raise ConfigError(f"corner {corner!r} is not served by this pool")
        out: Future = Future()
        inner, used = self._submit_on(corner, fn, job)
        i = self.affinity[corner]

        def done(f: Future) -> None:
            try:
                out.set_result(f.result())
            except BaseException as exc:  # noqa: BLE001
                if isinstance(exc, BrokenProcessPool):
                    # The executor this job ran on, not the slot's current one: another
                    # job's failure may already have replaced it with a healthy worker.
                    self._restart(i, used)
                out.set_result(invalid_outcome(
                    corner, stamp_ns, "worker_crashed",
                    f"the worker process failed ({type(exc).__name__}: {exc})",
                    fields[0], fields[1], solver))

        inner.add_done_callback(done)
        return out

    def warm_up(self, fields: dict[str, tuple[tuple[float, float], tuple[float, float]]],
                settings: EstimatorSettings, stamp_px: int = 0,
                frames: FrameFiles | None = None, slot: int | None = None) -> list[Future]:
        """Start building each corner's caches in its worker (or in worker ``slot``, where
        it is about to move); futures of :func:`warm_corner`.

        ``fields`` maps corner -> (field_intra_deg, field_extra_deg); ``frames`` also builds
        the field tiles of the corner's half-chips. The pool keeps each corner's latest
        warm-up and runs it again on a worker restarted after a crash, ahead of its first
        job (:attr:`rewarms` counts them).
        """
        with self._lock:
            for c, (fi, fe) in fields.items():
                if c in self.affinity:
                    self._warm_args[c] = (fi, fe, settings, stamp_px, frames)
        if frames is not None:
            self._prepare_blocks([c for c in fields if c in self.affinity], frames)
        return [self._submit_on(c, warm_corner, c, fi, fe, settings, stamp_px, frames,
                                slot=slot)[0]
                for c, (fi, fe) in fields.items() if c in self.affinity]

    def _prepare_blocks(self, corners: list[str], frames: FrameFiles) -> None:
        """Make the frames jobs' shared-memory blocks of ``corners`` now, each for two whole
        half-chips as decoded, so that the first visit does not make them; a window uses
        part of one. Sized for float32, what 8- and 16-bit and 32FC1 cameras decode to
        (:func:`.images.decoded_dtype`); a camera whose frames decode to float64 makes
        larger blocks on its first visit, kept from then on (:meth:`FrameBlocks.give_back`).
        Nothing where the sensor file cannot be read (the warm-up reports that) or /dev/shm
        has no room (the first jobs then try again)."""
        sizes = list(frames_nbytes(frames, corners).values())
        if sizes:
            self._blocks.prepare(max(sizes), len(sizes))

    def shutdown(self, wait: bool = False) -> None:
        """Stop the workers (queued jobs are cancelled)."""
        with self._lock:
            self._closed = True
            slots, self._slots = self._slots, [None] * self.n_workers
        for ex in slots:
            if ex is not None:
                ex.shutdown(wait=wait, cancel_futures=True)
        self._blocks.close()  # blocks of jobs still running are released when they end
