"""Frames handed to a worker through shared memory: exact, reused, released, and a fallback."""

from __future__ import annotations

import os
import pickle
import time
from multiprocessing import shared_memory

import numpy as np
import pytest

from cwfs_ros.frames.selection import CornerFrameJob
from cwfs_ros.runtime import shared_frames
from cwfs_ros.runtime.corner_pool import CornerPool, run_frame_job
from cwfs_ros.runtime.shared_frames import FrameBlocks, SharedFrameJob, release


def _frames(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two half-chip windows of sky noise, the intra one with a third of its pixels NaN: a
    job the worker refuses with the exact count of those pixels in its message."""
    rng = np.random.default_rng(seed)
    intra = rng.normal(1000.0, 7.0, (300, 200))
    extra = rng.normal(1000.0, 7.0, (300, 200)).astype(np.float32)
    intra[rng.random(intra.shape) < 0.33] = np.nan
    return intra, extra


def _job(intra: np.ndarray, extra: np.ndarray) -> CornerFrameJob:
    return CornerFrameJob("R00", 123, intra, extra)


def _exists(name: str) -> bool:
    try:
        shared_memory.SharedMemory(name=name).close()
    except FileNotFoundError:
        return False
    return True


def test_frames_come_back_bit_for_bit_and_the_block_is_released():
    intra, extra = _frames()
    big_endian = extra.astype(">f4")
    light, shm = FrameBlocks(keep=0).share(_job(intra, big_endian))
    try:
        assert isinstance(light, SharedFrameJob) and light.job.intra.size == 0
        assert len(pickle.dumps(light)) < 2000  # no pixels in the message
        job = light.load()
        np.testing.assert_array_equal(job.intra, intra)  # NaN in the same places
        assert job.extra.dtype == big_endian.dtype
        assert job.extra.tobytes() == big_endian.tobytes()
        assert job.corner == "R00" and job.stamp_ns == 123
    finally:
        release(shm)
    assert not _exists(light.frames.name)
    release(shm)  # twice: nothing
    with pytest.raises(FileNotFoundError):
        light.load()


def test_frames_jobs_through_the_pool_read_their_frames_and_reuse_one_block(monkeypatch):
    made: list[str] = []
    back: list[str] = []
    share, give_back = FrameBlocks.share, FrameBlocks.give_back

    def spy_share(self, job):
        out = share(self, job)
        if out is not None:
            made.append(out[1].name)
        return out

    def spy_give_back(self, shm):
        back.append(shm.name)
        give_back(self, shm)

    monkeypatch.setattr(FrameBlocks, "share", spy_share)
    monkeypatch.setattr(FrameBlocks, "give_back", spy_give_back)
    pool = CornerPool(["R00"], n_workers=1)
    try:
        for seed in (1, 2):
            intra, extra = _frames(seed)
            expected = run_frame_job(_job(intra, extra))  # in this process, no shared memory
            n_nan = int(np.isnan(intra).sum())
            assert expected.reason == "non_finite" and f"{n_nan} non-finite" in expected.status
            out = pool.submit_frames(_job(intra, extra)).result(timeout=120)
            assert out.worker_pid != os.getpid()
            assert (out.valid, out.reason, out.status) == (False, "non_finite", expected.status)
            # Given back by the future's done callback, which may run just after result().
            deadline = time.monotonic() + 10.0
            while len(back) < len(made) and time.monotonic() < deadline:
                time.sleep(0.01)
            assert back == made
        assert len(made) == 2 and made[0] == made[1], "one block, reused"
        assert _exists(made[0])
        assert (pool.frames_shared, pool.frames_piped) == (2, 0)  # /diagnostics frame_transport
    finally:
        pool.shutdown(wait=True)
    assert not _exists(made[0])  # released with the pool


def test_idle_blocks_are_reused_by_size_and_the_smallest_released_beyond_keep():
    blocks = FrameBlocks(keep=1)
    small, big = _frames(4), (np.zeros((400, 300)), np.zeros((400, 300)))
    a = blocks.share(_job(*small))
    blocks.give_back(a[1])
    b = blocks.share(_job(*small))
    assert b[1].name == a[1].name  # the idle block again
    c = blocks.share(_job(*big))  # too large for any idle block: a new one
    assert c[1].name != b[1].name and c[1].size >= 2 * 400 * 300 * 8
    blocks.give_back(b[1])
    blocks.give_back(c[1])  # beyond keep=1: the smaller block is released, the larger kept
    assert not _exists(b[1].name) and _exists(c[1].name)
    e = blocks.share(_job(*big))  # frames as large again: no new block for them
    assert e[1].name == c[1].name
    blocks.give_back(e[1])
    d = blocks.share(_job(*small))  # and smaller ones fit in it
    assert d[1].name == c[1].name
    np.testing.assert_array_equal(d[0].load().intra, small[0])
    blocks.close()
    assert _exists(d[1].name)  # still lent out
    blocks.give_back(d[1])  # after close: released
    assert not _exists(d[1].name)


def test_blocks_made_ahead_serve_the_first_jobs_and_stay_within_keep(monkeypatch):
    small = _frames(5)
    blocks = FrameBlocks(keep=2)
    assert blocks.prepare(2 * small[0].nbytes + 4096, 5) == 2  # no more than keep
    assert blocks.prepare(2 * small[0].nbytes, 1) == 0  # already holding keep idle blocks
    first = blocks.share(_job(*small))
    second = blocks.share(_job(*small))
    assert first[1].size >= 2 * small[0].nbytes + 4096 and second[1].name != first[1].name
    np.testing.assert_array_equal(second[0].load().extra, small[1])
    # Both blocks lent to running jobs still count: a warm-up repeated now makes none.
    assert blocks.prepare(2 * small[0].nbytes, 2) == 0
    no_room = FrameBlocks(keep=1)
    monkeypatch.setattr(shared_frames, "SHM_RESERVE_BYTES", 2 ** 62)
    assert no_room.prepare(1000, 1) == 0  # no room in /dev/shm: nothing made
    for out in (first, second):
        blocks.give_back(out[1])
    names = [first[1].name, second[1].name]
    blocks.close()
    assert not any(_exists(n) for n in names)


def test_without_room_in_dev_shm_the_frames_go_through_the_pipe(monkeypatch):
    monkeypatch.setattr(shared_frames, "SHM_RESERVE_BYTES", 2 ** 62)
    intra, extra = _frames(2)
    assert FrameBlocks(keep=0).share(_job(intra, extra)) is None
    pool = CornerPool(["R00"], n_workers=1)
    try:
        out = pool.submit_frames(_job(intra, extra)).result(timeout=120)
        assert out.reason == "non_finite"
        assert out.status == run_frame_job(_job(intra, extra)).status
        assert (pool.frames_shared, pool.frames_piped) == (0, 1)
    finally:
        pool.shutdown(wait=True)


def test_a_block_gone_before_the_worker_reads_it_is_an_invalid_outcome():
    intra, extra = _frames(3)
    light, shm = FrameBlocks(keep=0).share(_job(intra, extra))
    release(shm)
    out = run_frame_job(light)
    assert not out.valid and out.reason == "internal_error"
    assert "shared memory" in out.status and np.all(np.isnan(out.zernikes_nm))
