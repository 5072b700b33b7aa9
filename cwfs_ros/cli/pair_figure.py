"""The figure of ``cwfs-ros pair-demo``: the donuts, and the estimate against the truth and
the design, term by term, with the error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.cli.plotting import show_donut

__all__ = ["plot_estimate_truth_design"]


def plot_estimate_truth_design(result: Any, truth_nm: np.ndarray, path: str | Path, *,
                               intra: np.ndarray, extra: np.ndarray, title: str) -> Path:
    """Write a PNG: (a) the intra and extra donuts; (b) Z4..Z22 of the estimate, the
    ray-traced truth and the design (intrinsic) wavefront as grouped bars, nm; (c) the
    error (estimate - truth) per term, with its RMS."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    noll = np.asarray(result.noll)
    est = np.asarray(result.zernikes_nm)
    truth = np.asarray(truth_nm)
    design = np.asarray(result.intrinsic_nm)
    err = est - truth
    fig = Figure(figsize=(13.0, 8.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 3, height_ratios=[1.0, 1.2], width_ratios=[1.0, 1.0, 2.2])
    show_donut(fig.add_subplot(grid[0, 0]), intra, "(a) intra-focal donut")
    show_donut(fig.add_subplot(grid[0, 1]), extra, "extra-focal donut")
    ax = fig.add_subplot(grid[1, :])
    w = 0.27
    ax.bar(noll - w, est, width=w, color="tab:blue", label=f"estimate ({result.solver})")
    ax.bar(noll, truth, width=w, color="0.45", label="truth (batoid ray trace)")
    ax.bar(noll + w, design, width=w, color="tab:orange", label="design (intrinsic)")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xticks(noll)
    ax.set_xlabel("Noll index j")
    ax.set_ylabel("Z_j (nm of wavefront)")
    ax.set_title("(b) estimate, truth and design", fontsize=10)
    ax.legend(fontsize=9, loc="best")
    ax = fig.add_subplot(grid[0, 2])
    ax.bar(noll, err, color="tab:red")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xticks(noll)
    ax.set_xlabel("Noll index j")
    ax.set_ylabel("estimate - truth (nm)")
    ax.set_title(f"(c) error, RMS {np.sqrt(np.mean(err ** 2)):.1f} nm over Z4-Z22",
                 fontsize=10)
    fig.suptitle(title, fontsize=11)
    fig.savefig(path)
    return path
