#!/usr/bin/env python3
"""What wavefront_node spends on one frame before its worker starts: the image's identity
(SHA-256 of the message), decoding, the pixel checks, and the hand-off of a corner's two
frames to the worker's shared-memory block (new, then reused), on one core.

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
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from cwfs_ros.frames.selection import CornerFrameJob
from cwfs_ros.runtime.images import decode_image, inspect_pixels
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
    a = ap.parse_args()
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

    steps = {
        "identity (SHA-256)": lambda: message_digest(msg),
        "decode to float64": lambda: decode_image(msg.data, height=msg.height,
                                                  width=msg.width, encoding=msg.encoding,
                                                  step=msg.step),
        "pixel checks": lambda: inspect_pixels(image, "32FC1", full_scale_ok=True),
        "whole record (the three)": lambda: image_record_from_msg(msg, "R00", "intra", 0.0,
                                                                   full_scale_ok=True),
        "hand-off of a corner's 2 frames": hand_off,
    }
    print(f"{img.shape[0]}x{img.shape[1]} 32FC1 frame ({what}), median of {a.reps} "
          "(first call):")
    for name, fn in steps.items():
        first, med = _times_ms(fn, a.reps)
        print(f"  {name:34s} {med:6.1f} ms  ({first:.1f})")
    blocks.close()


if __name__ == "__main__":
    from cwfs_ros.runtime.threads import limit_blas_threads

    limit_blas_threads()
    main()
