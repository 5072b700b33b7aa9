"""Faults from outside the process: ``cwfs-ros bringup --sim`` SIGKILLed (only its main
process, as the OOM killer or a crash does) leaves no descendant alive; Ctrl-C to its process
group exits cleanly, without tracebacks, and leaves none either.

Descendants are read from /proc (pid, parent, start time) while the bringup runs; after the
fault each must be gone or a zombie, under the same start time (a reused pid is another
process).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros,
              pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")]

ROOT = Path(__file__).resolve().parents[1]


def _stat(pid: int) -> tuple[int, str, int] | None:
    """(parent pid, state, start time) of ``pid``, or None if it does not exist."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    rest = text[text.rindex(")") + 2:].split()
    return int(rest[1]), rest[0], int(rest[19])


def descendants(root: int) -> dict[int, int]:
    """{pid: start time} of every live descendant of ``root``."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            st = _stat(int(d.name))
            if st is not None:
                parent[int(d.name)] = st
    out, todo = {}, [root]
    while todo:
        p = todo.pop()
        for pid, (ppid, _, start) in parent.items():
            if ppid == p and pid not in out:
                out[pid] = start
                todo.append(pid)
    return out


def alive(procs: dict[int, int]) -> dict[int, str]:
    """Those of ``procs`` still running (not gone, not a zombie): {pid: state}."""
    out = {}
    for pid, start in procs.items():
        st = _stat(pid)
        if st is not None and st[2] == start and st[1] != "Z":
            out[pid] = st[1]
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:120]
    except OSError:
        return "?"


def _start_bringup(domain: int) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    return subprocess.Popen([sys.executable, "-m", "cwfs_ros.cli", "bringup", "--sim"],
                            env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _running_with_workers(proc: subprocess.Popen) -> dict[int, int]:
    """Wait until the bringup has its estimator and render workers (the fork server, the
    resource tracker and >= 2 workers), then return its descendants."""
    deadline = time.monotonic() + 120
    best: dict[int, int] = {}
    stable_since = None
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"bringup exited: {proc.stderr.read()[-2000:]}"
        d = descendants(proc.pid)
        if set(d) - set(best):
            best.update(d)
            stable_since = time.monotonic()
        # The render pool starts with the first visit; then nothing new for 3 s.
        if len(best) >= 5 and stable_since is not None and time.monotonic() - stable_since > 3:
            return {p: s for p, s in best.items() if p in d}
        time.sleep(0.2)
    raise AssertionError(f"bringup did not start its workers: {best}")


def _wait_gone(procs: dict[int, int], timeout: float) -> dict[int, str]:
    deadline = time.monotonic() + timeout
    left = alive(procs)
    while left and time.monotonic() < deadline:
        time.sleep(0.1)
        left = alive(procs)
    return left


def _cleanup(proc: subprocess.Popen, procs: dict[int, int]) -> None:
    for pid in alive(procs):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)


def test_sigkill_of_the_bringup_leaves_no_descendant(ros_domain):
    proc = _start_bringup(ros_domain)
    procs: dict[int, int] = {}
    try:
        procs = _running_with_workers(proc)
        os.kill(proc.pid, signal.SIGKILL)  # the main process only
        proc.wait(10)
        left = _wait_gone(procs, 15.0)
        assert not left, {p: (s, _cmdline(p)) for p, s in left.items()}
    finally:
        _cleanup(proc, procs)


def test_ctrl_c_exits_cleanly_without_tracebacks(ros_domain):
    proc = _start_bringup(ros_domain)
    procs: dict[int, int] = {}
    try:
        procs = _running_with_workers(proc)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole process group
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-3000:]
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
        left = _wait_gone(procs, 15.0)
        assert not left, {p: (s, _cmdline(p)) for p, s in left.items()}
    finally:
        _cleanup(proc, procs)
