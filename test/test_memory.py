"""The node process's heap keeps what it frees (cwfs_ros.runtime.memory), in fresh processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from cwfs_ros.runtime.memory import HEAP_VARIABLES

# In a fresh interpreter: a 64 MB array made and freed, and where glibc put it (mallinfo2:
# hblkhd = bytes in mmap'ed blocks, fordblks = free bytes kept in the heap).
PROBE = r"""
import ctypes, json, sys
import numpy as np
from cwfs_ros.runtime import memory

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
applied = memory.keep_freed_memory() if sys.argv[1] == "keep" else False
prefaulted = memory.prefault_heap(16 << 20)
a = np.ones(8_000_000)
mapped = libc.mallinfo2().hblkhd
del a
print(json.dumps({"applied": applied, "prefaulted": prefaulted, "mapped": mapped,
                  "kept": libc.mallinfo2().fordblks}))
"""


def _probe(mode: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in HEAP_VARIABLES}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env={**clean, **env},
                         capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_freed_frames_stay_in_the_heap_only_where_asked():
    default = _probe("default")
    # glibc's defaults: a 64 MB block is its own mapping, returned to the system on free.
    assert not default["applied"] and not default["prefaulted"]
    assert default["mapped"] >= 64e6 and default["kept"] < 64e6
    kept = _probe("keep")
    # Kept: the block comes from the heap and stays there, free, for the next frame.
    assert kept["applied"] and kept["prefaulted"]
    assert kept["mapped"] < 32e6 and kept["kept"] >= 64e6  # (a few MB mapped at import)
    # A user's own allocator settings win.
    user = _probe("keep", MALLOC_ARENA_MAX="4")
    assert not user["applied"] and not user["prefaulted"] and user["mapped"] >= 64e6


def test_a_launched_frames_node_keeps_and_prefaults_its_heap(ros_context, tmp_path):
    """The entry point keeps the heap; the frames warm-up maps one visit's frames of it
    (/diagnostics ``heap_prefault_mb``): R00's two whole half-chips as float32, 64 MB, below
    max_pending_mb. This test process keeps glibc's defaults."""
    import rclpy
    from conftest import REPO_ROOT, wait_for
    from diagnostic_msgs.msg import DiagnosticArray

    seen: list[dict[str, str]] = []
    node = rclpy.create_node("heap_probe", context=ros_context)
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda a: seen.extend(
        {kv.key: kv.value for kv in st.values} for st in a.status
        if st.name.startswith("wavefront_node")), 10)
    env = {k: v for k, v in os.environ.items() if k not in HEAP_VARIABLES}
    env.update(ROS_DOMAIN_ID=str(ros_context.get_domain_id()), ROS_HOME=str(tmp_path))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cwfs_ros.ros.launch", "node", "wavefront_node", "--ros-args",
         "-p", "input_mode:=frames", "-p", "corners:=[R00]", "-p", "workers:=1",
         "-p", "max_pending_mb:=1000.0", "-p", "diagnostics_period_s:=0.2"],
        env=env, cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True)
    executor = rclpy.executors.SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        wait_for(lambda: executor.spin_once(timeout_sec=0.1) or
                 any("heap_prefault_mb" in s for s in seen), 90, "the node's diagnostics")
        assert [s["heap_prefault_mb"] for s in seen if "heap_prefault_mb" in s][-1] == "64"
    finally:
        os.killpg(proc.pid, 9)
        proc.wait(30)
        executor.shutdown()
        node.destroy_node()
