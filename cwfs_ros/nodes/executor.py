"""The executor the composed nodes spin on: rclpy's MultiThreadedExecutor, less a busy loop.

Why not rclpy's own: in rclpy 7.1.6 (the newest Jazzy wheel on PyPI) the executor's scan of
its in-progress tasks yields a callback that has been handed to the thread pool but has not
started yet (it is neither executing nor done). ``MultiThreadedExecutor`` then submits it
again and, since it found work, does not wait on the wait set: the spin thread loops, holding
the GIL, until a worker gets the GIL to start the callback (rclpy issue #1452, fixed upstream
after 7.1.6). Measured on the 2-core VM (2026-12-02), ofc_node and one client in one process,
40 messages at 10 Hz: the process used 21 s of CPU in 19 s, the client's 0.1 s sleeps
overran by up to 3 s, and one ``publish`` of a correction took 1.5 s. With this class: the
sleeps keep time and the process is idle between messages (``bench/bench_executor.py``).

This class hands each ready callback to the pool once. When the scan yields one that is still
queued, the spin thread waits (GIL released) for up to :data:`QUEUED_WAIT_S` for a worker to
take it instead of queueing it again. Everything else (callback groups, coroutine callbacks
resumed after an ``await``, exceptions raised in the spin thread) is rclpy's own behaviour.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable

from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    ShutdownException,
    TimeoutException,
)
from rclpy.executors import MultiThreadedExecutor as _RclpyMultiThreadedExecutor
from rclpy.task import Task
from rclpy.timer import Timer

__all__ = ["QUEUED_WAIT_S", "MultiThreadedExecutor"]

# How long the spin thread sleeps on a queued callback before it looks again. Short against
# any callback's latency budget; long enough that the loop costs nothing.
QUEUED_WAIT_S = 0.002


class MultiThreadedExecutor(_RclpyMultiThreadedExecutor):
    """``rclpy.executors.MultiThreadedExecutor`` that submits each ready callback once.

    Same constructor and use (``add_node``, ``spin``, ``spin_once``, ``shutdown``).
    ``submissions`` counts the callbacks handed to the pool (for tests and benchmarks).
    """

    def __init__(self, num_threads: int | None = None, *, context=None) -> None:
        super().__init__(num_threads=num_threads, context=context)
        # Task -> the pool's future of its latest submission, until the task is done.
        self._queued: dict[Task, concurrent.futures.Future] = {}
        self.submissions = 0

    def _spin_once_impl(self, timeout_sec: float | Timer | None = None,
                        wait_condition: Callable[[], bool] = lambda: False) -> None:
        try:
            handler, _entity, _node = self.wait_for_ready_callbacks(
                timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException,
                ConditionReachedException):
            return
        pending = self._queued.get(handler)
        if pending is not None and not pending.done():
            # Submitted and not yet started (a running task is not yielded): let a worker
            # take it. A coroutine task that ran up to an ``await`` has a done submission
            # and is submitted again below, as rclpy does.
            concurrent.futures.wait([pending], timeout=QUEUED_WAIT_S)
        else:
            self._queued[handler] = self._executor.submit(handler)
            self.submissions += 1
        for task in [t for t in self._queued if t.done()]:
            del self._queued[task]
            task.result()  # raise a callback's exception in the spin thread, as rclpy does
