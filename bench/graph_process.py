"""The graph in its own process, for benchmarks that play the camera from this one.

``start_bringup`` runs ``python -m cwfs_ros.ros.launch bringup --ros-args ...`` as the
leader of its own process group on ``domain`` (its output discarded); ``stop_bringup``
sends SIGINT to that process group, then SIGKILL if it has not exited; ``stop_client``
tears down this process's node.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def start_bringup(ros_args: Sequence[str], domain: int) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    return subprocess.Popen([sys.executable, "-m", "cwfs_ros.ros.launch", "bringup",
                             "--ros-args", *ros_args],
                            env=env, cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)


def stop_bringup(proc: subprocess.Popen, wait_s: float = 20.0) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def stop_client(executor: Any, spinner: threading.Thread, node: Any) -> None:
    import rclpy

    executor.shutdown(timeout_sec=1.0)
    spinner.join(5.0)
    node.destroy_node()
    rclpy.try_shutdown()
