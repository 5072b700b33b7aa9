#!/usr/bin/env python3
"""What wavefront_node spends on one frame before its worker starts: rclpy's take of the
message (its deserialisation, in a thread as the executor's), the image's identity (SHA-256
of the message), decoding, the pixel checks, and the hand-off of a corner's two frames to the
worker's shared-memory block (new, then reused), on one core.

The process keeps its freed heap as the cwfs-ros entry points make the node's do
(cwfs_ros.runtime.memory); ``--glibc-defaults`` leaves glibc's allocator as it is, to compare.

The frame is R00's intra frame of bench_frames_graph.py's first visit (``--frames``, as it
sends them: 32FC1) when rendered, else ``--rows`` x ``--cols`` of sky noise (the pixel checks
then take ~3 ms less: they read a sample of rows, whose spread of values sets their cost).
Prints the median of ``--reps`` and the first call of each step (a fresh process: what the
first visit after start pays).

    .venv/bin/python bench/bench_image_ingest.py
"""

from __future__ import annotations

import argparse
import array
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from cwfs_ros.frames.selection import CornerFrameJob
from cwfs_ros.runtime.images import decode_image, inspect_pixels
from cwfs_ros.runtime.memory import keep_freed_memory
from cwfs_ros.runtime.shared_frames import FrameBlocks
from cwfs_ros.runtime.visits import image_record_from_msg, message_digest

REPO = Path(__file__).resolve().parents[1]


def _message(img: np.ndarray) -> SimpleNamespace:
    """An Image-shaped message (the fields image_record_from_msg reads), data as rclpy
    gives it (array of bytes)."""
    stamp = SimpleNamespace(sec=1, nanosec=0)
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp, frame_id="focal_plane"),
                           height=img.shape[0], width=img.shape[1], encoding="32FC1",
                           step=4 * img.shape[1], is_bigendian=0,
                           data=array.array("B", img.astype("<f4").tobytes()))


def _times_ms(fn, reps: int) -> tuple[float, float]:
    """(first call, median of the next ``reps``) in ms."""
    out = []
    for _ in range(reps + 1):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return out[0], float(np.median(out[1:]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2000)
    ap.add_argument("--cols", type=int, default=1000)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--frames", type=Path, default=REPO / "out" / "bench_frames_graph" /
                    "visit00.npz")
    ap.add_argument("--glibc-defaults", action="store_true",
                    help="do not keep freed heap memory (runtime.memory)")
    a = ap.parse_args()
    kept = False if a.glibc_defaults else keep_freed_memory()
    if a.frames.exists():
        with np.load(a.frames) as z:
            img, what = z["R00_intra"].astype(np.float32), f"R00 intra of {a.frames.name}"
    else:
        img = np.random.default_rng(0).normal(1000.0, 7.0, (a.rows, a.cols)).astype(np.float32)
        what = "sky noise"
    msg = _message(img)
    image = decode_image(msg.data, height=msg.height, width=msg.width, encoding=msg.encoding,
                         step=msg.step)
    blocks = FrameBlocks(keep=1)

    def hand_off() -> None:
        light, shm = blocks.share(CornerFrameJob("R00", 1, image, image))
        blocks.give_back(shm)

    serialized, pool = _serialized(img), ThreadPoolExecutor(1)

    def take() -> None:
        pool.submit(_deserialize, serialized).result()

    steps = {
        "rclpy take (deserialisation)": take,
        "identity (SHA-256)": lambda: message_digest(msg),
        "decode (32FC1: a view)": lambda: decode_image(msg.data, height=msg.height,
                                                       width=msg.width, encoding=msg.encoding,
                                                       step=msg.step),
        "pixel checks": lambda: inspect_pixels(image, "32FC1", full_scale_ok=True),
        "whole record (the three)": lambda: image_record_from_msg(msg, "R00", "intra", 0.0,
                                                                   full_scale_ok=True),
        "hand-off of a corner's 2 frames": hand_off,
    }
    print(f"{img.shape[0]}x{img.shape[1]} 32FC1 frame ({what}), median of {a.reps} "
          f"(first call); freed heap {'kept' if kept else 'returned (glibc defaults)'}:")
    for name, fn in steps.items():
        first, med = _times_ms(fn, a.reps)
        print(f"  {name:34s} {med:6.1f} ms  ({first:.1f})")
    blocks.close()
    pool.shutdown()


def _serialized(img: np.ndarray) -> bytes:
    """The frame as a serialised sensor_msgs/Image, as DDS hands it to rclpy."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    m = Image()
    m.height, m.width, m.encoding, m.step = img.shape[0], img.shape[1], "32FC1", 4 * img.shape[1]
    m.data = img.astype("<f4").tobytes()
    return serialize_message(m)


def _deserialize(data: bytes) -> None:
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    deserialize_message(data, Image)


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    main()
