"""Figures of the validation report (matplotlib on an explicit Agg canvas, no pyplot state).

matplotlib is imported inside each function so that importing this module is free.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.validation.common import NOLL

__all__ = ["plot_fig4", "plot_convergence", "plot_fig7", "plot_fig9", "plot_fig10",
           "plot_noise", "plot_solver"]


def _figure(w: float, h: float) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=90, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: Path) -> Path:
    fig.savefig(path)
    return path


def plot_fig4(data: dict, path: Path) -> Path:
    """|<Z_i, Z_j>| of standard and annular Zernikes on the annulus (paper Fig. 4)."""
    fig = _figure(10.0, 4.6)
    axes = fig.subplots(1, 2)
    for ax, key, title in zip(axes, ("standard", "annular"),
                              ("standard Zernikes", "annular Zernikes"), strict=True):
        g = np.abs(data[key])
        im = ax.imshow(g, origin="lower", cmap="viridis", vmin=0, vmax=1,
                       extent=(0.5, g.shape[0] + 0.5, 0.5, g.shape[0] + 0.5))
        ax.set_title(f"|<Zi,Zj>|, {title}, eps = {data['eps']:g}", fontsize=10)
        ax.set_xlabel("Noll j")
        ax.set_ylabel("Noll i")
    fig.colorbar(im, ax=axes, shrink=0.8)
    return _save(fig, path)


def plot_convergence(cases: list[dict], path: Path, title: str) -> Path:
    """Per case: the input donuts, each term against outer iteration, the final composition
    of the last five iterations with the truth (paper Figs. 5 and 6)."""
    n = len(cases)
    fig = _figure(4.6 * n, 10.5)
    fig.suptitle(title, fontsize=11)
    gs = fig.add_gridspec(3, n, height_ratios=[0.8, 1.0, 1.0])
    for c, case in enumerate(cases):
        sub = gs[0, c].subgridspec(1, 2)
        for k, key in enumerate(("intra", "extra")):
            ax = fig.add_subplot(sub[0, k])
            ax.imshow(case[key], origin="lower", cmap="gray", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{key}" + (f"\n{case['label']}" if k == 0 else ""), fontsize=8,
                         loc="left")
        hist = np.asarray(case["history"])
        it = np.arange(1, hist.shape[0] + 1)
        ax = fig.add_subplot(gs[1, c])
        k0 = case["noll"] - 4
        for j in range(19):
            if j != k0:
                ax.plot(it, hist[:, j], color="0.7", lw=0.8)
        ax.plot(it, hist[:, k0], "o-", color="C3", label=f"Z{case['noll']} estimate")
        ax.axhline(case["truth"][k0], color="C0", ls="--", label="truth")
        ax.set_xlabel("outer iteration")
        ax.set_ylabel("nm")
        ax.legend(fontsize=8)
        ax.set_title("convergence (grey: the other terms)", fontsize=9)
        ax = fig.add_subplot(gs[2, c])
        for h in hist[-5:]:
            ax.plot(NOLL, h, "-", color="C3", alpha=0.6, lw=1.0)
        ax.plot(NOLL, case["truth"], "x", color="C0", ms=7, label="truth")
        ax.plot(NOLL, case["estimate"], "o", mfc="none", color="C3", label="final estimate")
        ax.set_xticks(NOLL)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("Noll j (annular Zernike)")
        ax.set_ylabel("nm")
        ax.legend(fontsize=8)
        ax.set_title("last five iterations" + (" (caustic!)" if case["caustic"] else ""),
                     fontsize=9)
    return _save(fig, path)


def plot_fig7(data: dict, path: Path) -> Path:
    """Recovered (red circles) against the model's truth (blue crosses), paper Fig. 7."""
    panels = data["panels"]
    fig = _figure(6.0 * len(panels), 4.4)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, p in zip(axes, panels, strict=True):
        ax.plot(NOLL, p["truth"], "x", color="C0", ms=8, label="model truth (batoid)")
        ax.plot(NOLL, p["estimate"], "o", mfc="none", color="C3", ms=8, label="recovered")
        ax.axhline(0, color="0.8", lw=0.8)
        ax.set_xticks(NOLL)
        ax.set_xlabel("Noll j")
        ax.set_ylabel("nm")
        s = p["setup"]
        ax.set_title(f"M2 dx 0.5 mm, {s.name} ({s.defocus_mm:g} mm), intra "
                     f"{tuple(round(v, 3) for v in p['fields'][0])}", fontsize=9)
        ax.legend(fontsize=8)
    return _save(fig, path)


def plot_fig9(data: dict, path: Path) -> Path:
    """True (blue crosses) and recovered (red circles) Z5 against M2 rx (paper Fig. 9)."""
    panels = data["panels"]
    fig = _figure(6.0 * len(panels), 4.6)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, p in zip(axes, panels, strict=True):
        rows = p["rows"]
        rx = np.array([r["rx"] for r in rows])
        ax.plot(rx, [r["true"] for r in rows], "x", color="C0", ms=8, label="true Z5")
        ax.plot(rx, [r["est"] for r in rows], "o", mfc="none", color="C3", ms=8,
                label="recovered Z5")
        cz = [r["rx"] for r in rows if r["caustic"]]
        if cz:
            ax.plot(cz, [r["est"] for r in rows if r["caustic"]], "s", mfc="none",
                    color="k", ms=12, label="caustic flagged")
        refused = [r["rx"] for r in rows if r["status"] != "ok"]
        for x in refused:
            ax.axvline(x, color="C1", alpha=0.3, lw=6)
        if p["limit"] < len(rows):
            ax.axvline(rows[p["limit"]]["rx"], color="k", ls="--", lw=1,
                       label="geometric limit (ray fold)")
        s = p["setup"]
        ax.set_xlabel("M2 rx (deg)")
        ax.set_ylabel("Z5 (nm)")
        ax.set_title(f"{s.name} ({s.defocus_mm:g} mm); slope {p['slope']:.3f} before the "
                     f"limit" + ("; orange: image refused" if refused else ""), fontsize=9)
        ax.legend(fontsize=8)
    return _save(fig, path)


def plot_fig10(data: dict, path: Path) -> Path:
    """Diagonal of the covariance and its singular values, ideal against sensor (Fig. 10)."""
    panels = data["panels"]
    fig = _figure(11.0, 4.0 * len(panels))
    axes = np.atleast_2d(fig.subplots(len(panels), 2))
    for row, p in zip(axes, panels, strict=True):
        s = p["setup"]
        idx = np.arange(1, 77)
        row[0].semilogy(idx, np.diag(p["cov_i"]), "x-", color="C0", lw=0.8,
                        label="ideal sensor (atmosphere)")
        row[0].semilogy(idx, np.diag(p["cov_e"]), "o-", mfc="none", color="C3", lw=0.8,
                        label="simulated + estimated")
        row[0].set_xlabel("sensor index (19 x corner + j - 4)")
        row[0].set_ylabel("variance (nm^2)")
        row[0].set_title(f"{s.name} ({s.defocus_mm:g} mm), {p['n']} realisations",
                         fontsize=9)
        row[0].legend(fontsize=8)
        k = np.arange(1, len(p["s_i"]) + 1)
        row[1].semilogy(k, p["s_i"], "x-", color="C0", label="ideal sensor")
        row[1].semilogy(k, p["s_e"], "o-", mfc="none", color="C3", label="sensor")
        row[1].semilogy(k, p["s_d"], ".-", color="0.5", label="sensor - ideal (algorithm)")
        row[1].set_xlim(0.5, max(p["n"], 2) + 0.5)
        row[1].set_ylim(bottom=max(float(np.min(p["s_d"][: max(p["n"] - 1, 1)])) / 3, 1e-3))
        row[1].set_xlabel("singular value index")
        row[1].set_ylabel("nm^2")
        row[1].legend(fontsize=8)
    return _save(fig, path)


def plot_noise(data: dict, path: Path) -> Path:
    """Wavefront error and per-term error against photons per donut."""
    fig = _figure(11.0, 4.4)
    a, b = fig.subplots(1, 2)
    n = data["photons"]
    a.loglog(n, data["median"], "o-", color="C3", label="median WFE (vs truth)")
    a.loglog(n, data["noise"], "s--", color="C0", label="noise part (spread over seeds)")
    a.loglog(n, data["noise"][-1] * np.sqrt(n[-1] / n), ":", color="0.5", label="N^-1/2")
    for level in (10.0, 50.0):
        a.axhline(level, color="k", lw=0.8, ls=":")
    a.set_xlabel(f"photons per donut (sky {data['sky']:g} e/px, subtracted)")
    a.set_ylabel("sqrt(sum Z4..Z22 err^2) (nm)")
    a.legend(fontsize=8)
    a.set_title("split R44 pair, 1.5 mm, nominal telescope", fontsize=9)
    pt = data["per_term"]
    for j in range(19):
        b.loglog(n, pt[:, j], "-", lw=0.9, label=f"Z{j + 4}" if j % 3 == 0 else None)
    b.set_xlabel("photons per donut")
    b.set_ylabel("rms error per term (nm)")
    b.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def plot_solver(data: dict, path: Path) -> Path:
    """Normalised singular spectrum of the corner sensitivity, and the DoF recovered."""
    from cwfs_ros.sim.telescope import DOF_NAMES

    fig = _figure(12.0, 4.4)
    a, b = fig.subplots(1, 2, width_ratios=[1, 2])
    rel = data["singular"]
    a.semilogy(np.arange(1, rel.size + 1), np.maximum(rel, 1e-17), "o-", ms=3)
    a.axvline(data["n_modes"] + 0.5, color="C3", ls="--", label=f"{data['n_modes']} kept modes")
    a.axhline(1e-3, color="0.5", ls=":", label="1e-3")
    a.set_xlabel("mode")
    a.set_ylabel("s / s_max (normalised DoF units)")
    a.legend(fontsize=8)
    w = data["weights"]
    x = np.arange(50)
    b.bar(x - 0.2, data["dof"] / w, 0.4, color="C0", label="true state")
    for k, (label, r) in enumerate(data["results"].items()):
        b.bar(x + 0.2 * (k + 0) + 0.0 * k, r["dof_est"] / w, 0.4 / len(data["results"]),
              color=f"C{3 + k}", label=f"recovered ({label})", alpha=0.8)
    b.set_xticks(x[::2])
    b.set_xticklabels([DOF_NAMES[i] for i in x[::2]], rotation=90, fontsize=6)
    b.set_ylabel("DoF / normalisation weight")
    b.legend(fontsize=8)
    return _save(fig, path)
