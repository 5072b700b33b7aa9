"""The executor the composed nodes spin on: rclpy's MultiThreadedExecutor, less a busy loop.

Why not rclpy's own: in rclpy 7.1.6 (the newest Jazzy wheel on PyPI, pinned in
``requirements/ros.txt``) the executor's scan of its in-progress tasks yields a callback
that has been handed to the thread pool but has not started yet (it is neither executing
nor done), and its wait set returns at once while that callback's message is still untaken
(measured: ~8,000 such empty waits for 20 messages; the subscription's QoS
event handlers keep reporting ready). So ``MultiThreadedExecutor`` submits the callback
again and again, and the spin thread loops holding the GIL until a worker gets the GIL to
start it (rclpy issue #1452, fixed upstream after 7.1.6). Measured on the 2-core VM
(2026-12-02, ``bench/bench_executor.py``: ofc_node and one client in one process, 40
messages at 10 Hz): 140-389 pool submissions per callback run, 4.7-16.6 s of CPU for a 4-s
burst, the client's 0.1 s sleeps overrunning by up to 2.3 s and corrections arriving up to
2.7 s late; in one run one ``publish`` by ofc_node took 1.5 s. With this class: one
submission per callback, 0.2 s of CPU, the sleeps keep time and the latency stays below
16 ms.

This class hands each ready callback to the pool once. When the scan yields one that is still
queued, the spin thread waits (GIL released) for up to :data:`QUEUED_WAIT_S` for a worker to
take it instead of queueing it again, and asks for one more scan when that submission ends
(a coroutine callback woken meanwhile is then resumed). A coroutine callback parked on an
``await`` is submitted again each time it can go on, as in rclpy. Callback groups, and
exceptions raised in the spin thread, are rclpy's own behaviour.

It also waits in :meth:`MultiThreadedExecutor.shutdown`: rclpy 7.1.6's ``shutdown(timeout_sec)``
sets its shut-down flag and then skips its own wait because of that flag, so it returns
while callbacks still run, and the nodes destroyed next fail under them (``cannot use
Destroyable because destruction was requested``, then printed as "never retrieved" when
the task is collected).

The class overrides an rclpy internal (``_spin_once_impl``) and reads two more
(``_executor``, the pool; the task scan): ``test_executor.test_written_for_this_rclpy``
stops the suite when the pinned rclpy changes, so that this is checked again (a newer rclpy
may carry the upstream fix, and then this class can go).
"""

from __future__ import annotations

import concurrent.futures
import threading
from collections.abc import Callable

from rclpy._rclpy_pybind11 import InvalidHandle, RCLError
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    ShutdownException,
    TimeoutException,
)
from rclpy.executors import MultiThreadedExecutor as _RclpyMultiThreadedExecutor
from rclpy.logging import get_logger
from rclpy.task import Task
from rclpy.timer import Timer

__all__ = ["QUEUED_WAIT_S", "RCLPY_VERSION", "MultiThreadedExecutor", "count_pool_submissions"]

# The rclpy release whose internals this class was written against (see the module doc).
RCLPY_VERSION = "7.1.6"

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

    def _wake_after(self, _future: concurrent.futures.Future) -> None:
        """``wake()`` from a pool thread; a no-op once the executor is shut down (its guard
        condition is then destroyed, possibly while this runs)."""
        try:
            self.wake()
        except (AttributeError, InvalidHandle, RCLError):
            pass

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        """Stop dispatching, wait up to ``timeout_sec`` (None or negative: no limit; 0: no
        wait) for the callbacks already handed to the pool to end, then let rclpy release
        the executor's resources, as rclpy documents and 7.1.6 does not do (module doc).
        The caller may then destroy the nodes.

        The wait comes before rclpy's clean-up because a callback still queued in the pool
        when it starts runs normally only while the executor's guard condition exists.  An
        exception raised by one of those callbacks is logged here (logger
        ``cwfs_ros.executor``): no spin may be left to raise it.  Returns False if a
        callback was still running at the timeout.  Called from a callback (a pool thread),
        it does not wait, since that callback's own run would be among those waited for.
        """
        with self._shutdown_lock:  # rclpy's first step: no further dispatch
            if not self._is_shutdown:
                self._is_shutdown = True
                if self._guard is not None:
                    self._guard.trigger()
        pending = [f for f in list(self._queued.values()) if not f.done()]
        in_pool = threading.current_thread() in getattr(self._executor, "_threads", ())
        finished = True
        if pending and not in_pool and timeout_sec != 0:
            timeout = None if timeout_sec is None or timeout_sec < 0 else timeout_sec
            finished = not concurrent.futures.wait(pending, timeout=timeout).not_done
        elif pending:
            finished = False
        for task in self._take_done():
            exc = None if task.cancelled() else task.exception()
            if exc is not None:
                get_logger("cwfs_ros.executor").error(
                    f"a callback failed during shutdown: {type(exc).__name__}: {exc}")
        super().shutdown(timeout_sec=timeout_sec)
        return finished

    def _take_done(self) -> list[Task]:
        """Remove the finished tasks from the queue map and return them.  The spin thread
        and a shutdown from another thread both do this: a snapshot of the keys, and a
        task the other thread already took is skipped."""
        done = []
        for task in list(self._queued):
            if (task.done() or task.cancelled()) and \
                    self._queued.pop(task, None) is not None:
                done.append(task)
        return done

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
            # Submitted and not yet started (a running task is not yielded), or a run just
            # ending: let a worker take it. If a coroutine task is woken while its last run
            # is still ending, that wake-up is spent here, so scan once more when the run
            # ends (rclpy's second submission resumed it instead). A coroutine task parked on
            # an ``await`` has a done submission and is submitted again below, as in rclpy.
            if not getattr(pending, "_cwfs_wake", False):  # once per submission, not per pass
                pending._cwfs_wake = True
                pending.add_done_callback(self._wake_after)
            concurrent.futures.wait([pending], timeout=QUEUED_WAIT_S)
        else:
            self._queued[handler] = self._executor.submit(handler)
            self.submissions += 1
        for task in self._take_done():
            if not task.cancelled():
                task.result()  # a callback's exception is raised here, as rclpy does


def count_pool_submissions(executor: _RclpyMultiThreadedExecutor) -> dict[str, int]:
    """Count what a MultiThreadedExecutor, rclpy's or this one, hands to its thread pool
    (wraps the pool's ``submit``; ``["n"]`` of the returned dict): the measure of the busy
    loop, for ``bench/bench_executor.py`` and the tests."""
    count = {"n": 0}
    submit = executor._executor.submit

    def counted(fn, *a, **k):
        count["n"] += 1
        return submit(fn, *a, **k)

    executor._executor.submit = counted
    return count
