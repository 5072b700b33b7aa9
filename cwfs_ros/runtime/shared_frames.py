"""Hand a frames job's two frames to its worker process through shared memory (no ROS).

A frames job carries two decoded half-chip frames (64 MB for two whole 4000 x 2000
half-chips as float32). Pickled through the worker's pipe, 32 MB of them cost the node ~100
ms of pickling and pipe writes, holding the GIL against the decoding of the next images, and
several hundred ms on the first visit after start (docs/performance.md, Frames). Here the
node copies them once into a POSIX shared-memory block and sends only its name; the worker
copies them out and lets go of the block. The node takes the block back when the job's
future is done, whatever the outcome (a dead worker included), and reuses it for a later job
(:class:`FrameBlocks`). Blocks are registered with multiprocessing's resource tracker, which
unlinks them if the node itself dies.

A block is made only while ``/dev/shm`` keeps :data:`SHM_RESERVE_BYTES` free beyond it (the
DDS shared-memory transport lives there too), and its pages are reserved when it is made: a
tmpfs without room for a page written into a block would kill the writer with SIGBUS rather
than raise. Otherwise, and where shared
memory cannot be made at all, the frames go through the pipe as before: slower, same
numbers.
"""

from __future__ import annotations

import mmap
import os
import threading
from dataclasses import dataclass, replace
from multiprocessing import shared_memory
from typing import Any

import numpy as np

__all__ = ["SHM_RESERVE_BYTES", "FrameBlocks", "SharedFrameJob", "SharedFrames", "release"]

# Room left free in /dev/shm beyond a block (bytes): the DDS transport's segments (16 MiB
# each, config/fastdds_profile.xml) and other users' blocks.
SHM_RESERVE_BYTES = 256 * 2 ** 20
_SHM_DIR = "/dev/shm"


@dataclass(frozen=True)
class SharedFrames:
    """Where a job's two frames lie: the block ``name`` and each frame's shape and dtype
    (intra first, then extra, back to back from offset 0)."""

    name: str
    shapes: tuple[tuple[int, ...], tuple[int, ...]]
    dtypes: tuple[str, str]

    def load(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the two frames (the block is closed before returning).

        Raises:
            OSError: the block is gone (``FileNotFoundError``) or cannot be mapped.
        """
        shm = shared_memory.SharedMemory(name=self.name)
        try:
            out, offset = [], 0
            for shape, dtype in zip(self.shapes, self.dtypes, strict=True):
                view = np.ndarray(shape, np.dtype(dtype), buffer=shm.buf, offset=offset)
                out.append(view.copy())
                offset += view.nbytes
                del view  # no export of shm.buf may outlive close()
            return out[0], out[1]
        finally:
            shm.close()


@dataclass(frozen=True)
class SharedFrameJob:
    """A frames job whose frames travel in shared memory: ``job`` with empty frames, and
    where the real ones are (what crosses the process boundary is a few hundred bytes)."""

    job: Any
    frames: SharedFrames

    @property
    def corner(self) -> str:
        return self.job.corner

    @property
    def stamp_ns(self) -> int:
        return self.job.stamp_ns

    def load(self) -> Any:
        """The job with its frames (copied out of the block)."""
        intra, extra = self.frames.load()
        return replace(self.job, intra=intra, extra=extra)


def _room_for(nbytes: int) -> bool:
    """Whether /dev/shm keeps SHM_RESERVE_BYTES free after a block of ``nbytes``; True where
    there is no /dev/shm to ask (shared memory elsewhere is not a size-limited tmpfs)."""
    try:
        st = os.statvfs(_SHM_DIR)
    except OSError:
        return True
    return st.f_bavail * st.f_frsize >= nbytes + SHM_RESERVE_BYTES


class FrameBlocks:
    """The shared-memory blocks of a pool's frames jobs, kept from job to job.

    A block made afresh for every job costs the node its page faults (~8k for a corner's
    32 MB, tens of ms on the first touch of tmpfs pages); a block given back when its job is
    done serves a later one of the same size or smaller. At most ``keep`` idle blocks are
    kept (a pool keeps one per served corner: its jobs run one after the other); the others
    are released. :meth:`close` releases them all.
    """

    def __init__(self, keep: int) -> None:
        self._keep = max(0, int(keep))
        self._idle: list[shared_memory.SharedMemory] = []
        self._lent = 0  # blocks handed out by share() and not yet given back
        self._lock = threading.Lock()
        self._closed = False

    def share(self, job: Any) -> tuple[SharedFrameJob, shared_memory.SharedMemory] | None:
        """Copy ``job``'s two frames (``intra``, ``extra``) into a block.

        Returns the light job to submit and the block, to be handed to :meth:`give_back`
        once the job is done; or None when there is no room for a new block or shared memory
        cannot be made (the caller then sends ``job`` itself).
        """
        frames = [np.ascontiguousarray(job.intra), np.ascontiguousarray(job.extra)]
        shm = self._block(sum(f.nbytes for f in frames))
        if shm is None:
            return None
        with self._lock:
            self._lent += 1
        offset = 0
        for f in frames:
            np.ndarray(f.shape, f.dtype, buffer=shm.buf, offset=offset)[...] = f
            offset += f.nbytes
        where = SharedFrames(shm.name, (frames[0].shape, frames[1].shape),
                             (frames[0].dtype.str, frames[1].dtype.str))
        empty = np.zeros((0, 0))
        return SharedFrameJob(replace(job, intra=empty, extra=empty), where), shm

    def _block(self, nbytes: int) -> shared_memory.SharedMemory | None:
        """The smallest idle block that holds ``nbytes``, else a new one (None: no room)."""
        with self._lock:
            fits = [b for b in self._idle if b.size >= nbytes]
            if fits:
                best = min(fits, key=lambda b: b.size)
                self._idle.remove(best)
                return best
        return self._new_block(nbytes)

    @staticmethod
    def _new_block(nbytes: int) -> shared_memory.SharedMemory | None:
        """A new block of ``nbytes`` with its pages reserved (None: no room)."""
        if not _room_for(nbytes):
            return None
        try:
            shm = shared_memory.SharedMemory(create=True, size=max(nbytes, 1))
        except OSError:
            return None
        if not _reserve(shm):
            release(shm)
            return None
        return shm

    def prepare(self, nbytes: int, count: int) -> int:
        """Make up to ``count`` idle blocks of ``nbytes`` now, so that the first jobs do
        not pay for making them (~90 ms for a corner of two whole 4000 x 2000 half-chips, on
        the first visit after start). The blocks already made, idle or lent to a running
        job, count against ``keep``: a warm-up repeated while the node runs makes none.
        Nothing beyond the room in /dev/shm. Returns how many were made."""
        made = 0
        for _ in range(max(0, int(count))):
            with self._lock:
                if self._closed or len(self._idle) + self._lent >= self._keep:
                    break
            shm = self._new_block(int(nbytes))
            if shm is None:
                break
            # Map its pages into this process now as well (a write per page): the first copy
            # into it would otherwise fault them in.
            view = np.ndarray((shm.size,), np.uint8, buffer=shm.buf)
            view[::mmap.PAGESIZE] = 0
            del view  # no export of shm.buf may outlive close()
            with self._lock:
                kept = not self._closed and len(self._idle) + self._lent < self._keep
                if kept:
                    self._idle.append(shm)
            if not kept:
                release(shm)
                break
            made += 1
        return made

    def give_back(self, shm: shared_memory.SharedMemory) -> None:
        """A block whose job is done: kept for the next job, or released.

        Beyond ``keep`` idle blocks the smallest goes: a block made because none was large
        enough (frames larger than the warm-up's, or a wider decoded type) then serves the
        next visits instead of being made again for each of them.
        """
        with self._lock:
            self._lent = max(0, self._lent - 1)
            if self._closed:
                drop = [shm]
            else:
                self._idle.append(shm)
                self._idle.sort(key=lambda b: b.size, reverse=True)
                drop, self._idle = self._idle[self._keep:], self._idle[:self._keep]
        for b in drop:
            release(b)

    def close(self) -> None:
        """Release the idle blocks; blocks given back later are released then."""
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for b in idle:
            release(b)


def _reserve(shm: shared_memory.SharedMemory) -> bool:
    """Give the block its pages now (``posix_fallocate`` on its /dev/shm file): a tmpfs
    that fills up between the free-space check and the copy then says ENOSPC here (False)
    instead of killing the node with SIGBUS on the first page written beyond it. True where
    there is no such file to reserve on."""
    try:
        fd = os.open(os.path.join(_SHM_DIR, shm.name.lstrip("/")), os.O_RDWR)
    except OSError:
        return True
    try:
        os.posix_fallocate(fd, 0, shm.size)
    except OSError:
        return False
    finally:
        os.close(fd)
    return True


def release(shm: shared_memory.SharedMemory) -> None:
    """Close and unlink a block made by :class:`FrameBlocks` (already gone: nothing)."""
    shm.close()
    try:
        shm.unlink()
    except FileNotFoundError:
        pass
