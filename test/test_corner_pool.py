"""The per-corner process pool: jobs never raise, orientation settings, worker crash recovery."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from cwfs_ros.errors import ConfigError
from cwfs_ros.runtime.corner_pool import CornerJob, CornerPool, run_corner_job, synthetic_donut
from cwfs_ros.runtime.visits import load_corner_fields
from cwfs_ros.wfs.orientation import Orientation
from cwfs_ros.wfs.settings import EstimatorSettings, validate_settings

FIELDS = load_corner_fields()


def job(img_in, img_ex, corner="R44", **kw):
    f = FIELDS[corner]
    return CornerJob(corner, 123, img_in, img_ex, f["intra"], f["extra"],
                     kw.pop("settings", EstimatorSettings()), **kw)


def test_jobs_report_problems_instead_of_raising():
    tiny = run_corner_job(job(np.ones((1, 1)), np.ones((1, 1))))
    assert not tiny.valid and tiny.reason == "stamp_too_small"
    assert tiny.status.startswith("stamp_too_small:") and np.all(np.isnan(tiny.zernikes_nm))
    assert tiny.zernikes_nm.shape == (19,) and tiny.noll == tuple(range(4, 23))
    assert tiny.n_pairs == 0  # no pair behind an invalid corner
    d = synthetic_donut(160, 60.0, 0.61)
    bad = d.copy()
    bad[5, 5] = np.inf
    assert run_corner_job(job(bad, d)).reason == "non_finite"
    assert run_corner_job(job(d, np.zeros((160, 170)))).reason == "shape_mismatch"
    cfg = run_corner_job(job(d, d, settings=EstimatorSettings(band="q")))
    assert not cfg.valid and cfg.reason == "config" and "band" in cfg.status
    padded = run_corner_job(job(np.ones((3, 3)), np.ones((3, 3)),
                                settings=EstimatorSettings(pad_px=2)))
    assert "received stamps intra 3x3, extra 3x3 px, padded by 2 px" in padded.status


def test_validate_settings():
    validate_settings(EstimatorSettings())
    for bad in (EstimatorSettings(solver="nope"), EstimatorSettings(band="q"),
                EstimatorSettings(instrument="no_such"), EstimatorSettings(pad_px=-1)):
        with pytest.raises(ConfigError):
            validate_settings(bad)


def test_library_default_solver_is_the_nodes():
    """A library user who takes the defaults (EstimatorSettings(), estimate_corner_frames,
    estimate_wavefront) gets the solver wavefront_node runs with, the one the README's
    figures are for."""
    import inspect

    from cwfs_ros.config import config_dir, load_yaml
    from cwfs_ros.frames.selection import estimate_corner_frames
    from cwfs_ros.wfs.estimator import estimate_wavefront

    params = load_yaml(config_dir() / "params.yaml")
    node = params["wavefront_node"]["ros__parameters"]["solver"]
    assert node == "lsq"
    assert EstimatorSettings().solver == node
    assert inspect.signature(estimate_wavefront).parameters["solver"].default == node
    frames_default = inspect.signature(estimate_corner_frames).parameters["settings"].default
    assert frames_default.solver == node


def test_orientation_settings_undo_a_rotated_or_flipped_camera():
    """A stamp delivered rotated / flipped, declared as such, gives the same wavefront."""
    sim = pytest.importorskip("cwfs_ros.sim")
    geo = sim.load_corner_geometry()["R04"]
    tel = sim.perturbed_telescope(np.r_[20.0, np.zeros(49)])
    rng = np.random.default_rng(5)
    kw = dict(wavelength_nm=622.0, npix=160, n_photons=2e5, rng=rng)
    intra = sim.render_donut(tel, geo.intra_field_deg, -1.5, **kw)
    extra = sim.render_donut(tel, geo.extra_field_deg, 1.5, **kw)
    ref = run_corner_job(job(intra, extra, "R04"))
    assert ref.valid, ref.status
    # camera delivers intra rotated by +90 deg and extra mirrored in x
    got = run_corner_job(job(np.rot90(intra, 1), extra[:, ::-1], "R04",
                             orient_intra=Orientation(3), orient_extra=Orientation(0, "lr")))
    np.testing.assert_array_equal(got.zernikes_nm, ref.zernikes_nm)
    # undeclared, the same stamps give a different (wrong) answer
    wrong = run_corner_job(job(np.rot90(intra, 1), extra[:, ::-1], "R04"))
    assert not wrong.valid or np.max(np.abs(wrong.zernikes_nm - ref.zernikes_nm)) > 20.0


def test_a_late_crash_report_does_not_restart_the_new_worker():
    """Two jobs queued behind a worker's death both report it. Between the two reports a new
    job starts the slot's new worker (here from the first report's callback, as a node's
    next visit may); the second report must restart the dead executor it ran on, not that
    new one, which used to be shut down with the new job in it (worker_crashed)."""
    pool = CornerPool(["R00"], n_workers=1)
    try:
        tiny = np.ones((1, 1))
        killer = pool._submit_on("R00", os._exit, 3)[0]
        first = pool.submit(job(tiny, tiny, "R00"))
        second = pool.submit(job(tiny, tiny, "R00"))
        started: list = []
        first.add_done_callback(lambda _f: started.append(pool.submit(job(tiny, tiny, "R00"))))
        assert first.result(timeout=60).reason == "worker_crashed"
        assert second.result(timeout=60).reason == "worker_crashed"
        assert killer.exception(timeout=60) is not None
        (new,) = started
        out = new.result(timeout=60)
        assert out.reason == "stamp_too_small", out.status  # ran on the new worker
        assert pool.restarts == 1
    finally:
        pool.shutdown()


def test_a_restarted_worker_is_warmed_again_before_its_first_job():
    """A worker that died is replaced by a bare process: without the corner's warm-up its
    first visits build the caches (frames: trace field tiles) and miss the visit timeout.
    The pool runs the corner's last warm-up on the new worker first, so the first job there
    finds the pair geometry built (a cache hit) instead of building it."""
    pool = CornerPool(["R00"], n_workers=1)
    try:
        f = FIELDS["R00"]
        (warm,) = pool.warm_up({"R00": (f["intra"], f["extra"])}, EstimatorSettings())
        assert warm.result(timeout=300)["ok"]
        d = synthetic_donut(160, 60.0, 0.61)
        killer = pool._submit_on("R00", os._exit, 3)[0]
        assert pool.submit(job(d, d, "R00")).result(timeout=60).reason == "worker_crashed"
        assert killer.exception(timeout=60) is not None
        out = pool.submit(job(d, d, "R00")).result(timeout=300)
        assert pool.restarts == 1 and pool.rewarms == 1
        hits, builds, _held, _size = out.caches["pair_geometry"]
        assert builds == 1 and hits >= 1, out.caches  # built by the warm-up, hit by the job
    finally:
        pool.shutdown()


def test_pool_affinity_and_recovery_from_a_dead_worker():
    pool = CornerPool(["R00", "R04", "R40"], n_workers=2)
    try:
        assert pool.affinity == {"R00": 0, "R04": 1, "R40": 0}
        tiny = np.ones((1, 1))
        # kill R00's worker while a job is queued behind the kill
        killer = pool._submit_on("R00", os._exit, 3)[0]
        queued = pool.submit(job(tiny, tiny, "R00"))
        out = queued.result(timeout=60)
        assert killer.exception(timeout=60) is not None
        assert not out.valid and out.reason == "worker_crashed" and out.corner == "R00"
        # the slot is restarted: the next job runs normally
        again = pool.submit(job(tiny, tiny, "R00")).result(timeout=60)
        assert again.reason == "stamp_too_small" and pool.restarts == 1
        # the other slot was not affected
        other = pool.submit(job(tiny, tiny, "R04")).result(timeout=60)
        assert other.reason == "stamp_too_small" and other.worker_pid != again.worker_pid
        with pytest.raises(ConfigError):
            pool.submit(job(tiny, tiny, "R44"))
    finally:
        pool.shutdown()
    with pytest.raises(RuntimeError):
        pool.submit(job(np.ones((1, 1)), np.ones((1, 1)), "R00"))


def test_corners_move_to_the_worker_they_are_assigned_and_queues_are_counted():
    """assign() serves a corner from another worker from the next job on; the queue counts
    cover what each worker still has to run."""
    pool = CornerPool(["R00", "R04"], n_workers=2)
    try:
        assert pool.affinity == {"R00": 0, "R04": 1}
        pid = {c: pool._submit_on(c, os.getpid)[0].result(timeout=60) for c in ("R00", "R04")}
        assert pid["R00"] != pid["R04"]
        pool.assign({"R00": 1, "R04": 0})
        moved = {c: pool._submit_on(c, os.getpid)[0].result(timeout=60) for c in ("R00", "R04")}
        assert moved == {"R00": pid["R04"], "R04": pid["R00"]}
        # Two sleeps queued on worker 0 (R04 now): counted until they finish.
        futs = [pool._submit_on("R04", time.sleep, 0.5)[0] for _ in range(2)]
        assert pool.queued()[0] == 2 and pool.queued()[1] == 0
        for f in futs:
            f.result(timeout=30)
        end = time.monotonic() + 10  # the count drops in the future's done callback
        while pool.queued() != {0: 0, 1: 0} and time.monotonic() < end:
            time.sleep(0.01)
        assert pool.queued() == {0: 0, 1: 0}
        with pytest.raises(ConfigError, match="assignment"):
            pool.assign({"R00": 2, "R04": 0})
        with pytest.raises(ConfigError, match="assignment"):
            pool.assign({"R00": 0})
    finally:
        pool.shutdown()
