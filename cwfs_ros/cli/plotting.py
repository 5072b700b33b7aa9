"""Diagnostic figure of one wavefront estimate (matplotlib, Agg; optional dependency).

matplotlib is imported inside :func:`plot_result`, never at module level, and the figure is
drawn on an explicit Agg canvas without pyplot, so importing this module costs nothing, the
core never needs matplotlib, and the caller's pyplot backend and state are left untouched.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plot_closed_loop", "plot_result", "show_donut"]

# Convergence panel: how many of the largest terms get a legend entry.
_N_LABELLED = 6


def _finite_limits(images: list[np.ndarray], lo: float = 1.0, hi: float = 99.0
                   ) -> tuple[float, float]:
    """Robust common colour limits (percentiles of the finite pixels of all images)."""
    vals = np.concatenate([im[np.isfinite(im)].ravel() for im in images]) if images else []
    if len(vals) == 0:
        return 0.0, 1.0
    vmin, vmax = (float(v) for v in np.percentile(vals, [lo, hi]))
    if not vmax > vmin:
        vmin, vmax = vmin - 0.5, vmax + 0.5
    return vmin, vmax


def _crop_finite(image: np.ndarray, pad: int = 2) -> tuple[np.ndarray, tuple[int, int]]:
    """The bounding box of the finite pixels (plus ``pad``) and its (row, col) origin."""
    ok = np.isfinite(image)
    if not ok.any():
        return image, (0, 0)
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, image.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, image.shape[1])
    return image[r0:r1, c0:c1], (r0, c0)


def show_donut(ax: Any, image: np.ndarray | None, title: str) -> None:
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if image is None:
        ax.text(0.5, 0.5, "not available", ha="center", va="center", transform=ax.transAxes)
        return
    img = np.asarray(image, dtype=float)
    vmin, vmax = _finite_limits([img], 0.5, 99.8)
    ax.imshow(img, origin="lower", cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")


def plot_result(result: Any, path: str | Path, *, intra: np.ndarray | None = None,
                extra: np.ndarray | None = None, title: str | None = None) -> Path:
    """Write a PNG summarising a :class:`~cwfs_ros.wfs.estimator.WavefrontResult`.

    Panels: (a) the input intra and extra donuts and the final compensated intra and extra
    pupil images (the latter on common colour limits, with the common pupil outlined);
    (b) Z4..Z22 in nm as bars, with the design (intrinsic) part as a second series;
    (c) convergence: each term's estimate against the outer iteration (paper Fig. 5), the
    largest terms labelled.

    Args:
        result: the estimate.
        path: output PNG file (parent directories must exist).
        intra, extra: the raw input images; default: the background-subtracted stamps the
            estimator used (``result.inputs``).
        title: first line of the figure title (e.g. the input file names); the instrument,
            band, solver, field and status lines always follow.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    inputs = getattr(result, "inputs", None) or {}
    if intra is None and "intra" in inputs:
        intra = inputs["intra"].image
    if extra is None and "extra" in inputs:
        extra = inputs["extra"].image

    fig = Figure(figsize=(13.0, 8.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    outer = fig.add_gridspec(2, 1, height_ratios=[1.0, 1.35])
    top = outer[0].subgridspec(1, 4)
    bottom = outer[1].subgridspec(1, 2, width_ratios=[1.0, 1.15])
    _result_donuts(fig, [fig.add_subplot(top[0, i]) for i in range(4)], result, intra, extra)
    _result_zernikes(fig.add_subplot(bottom[0, 0]), result)
    _result_convergence(fig.add_subplot(bottom[0, 1]), result)

    status = (f"caustic: {'yes' if result.caustic else 'no'}, "
              f"settled: {'yes' if result.converged else 'no'}, "
              f"iterations: {result.iterations}, wall time: {result.wall_time_s:.3f} s")
    meta = (f"{result.instrument}, band {result.band} ({result.wavelength_nm:g} nm), "
            f"solver {result.solver}, field ({result.field_deg[0]:.3f}, "
            f"{result.field_deg[1]:.3f}) deg")
    lines = ([title] if title else []) + [meta, status]
    fig.suptitle("\n".join(lines), fontsize=11)
    fig.savefig(path, format="png")
    return path


def _result_donuts(fig: Any, axes: list[Any], result: Any, intra: np.ndarray | None,
                   extra: np.ndarray | None) -> None:
    """Panel (a): the inputs on their own scales, the compensated images on common limits
    (so that intra and extra compare), the common pupil outlined."""
    show_donut(axes[0], intra, "(a) intra, input")
    show_donut(axes[1], extra, "extra, input")
    comp = getattr(result, "compensated", None) or {}
    common = (getattr(result, "masks", None) or {}).get("common")
    shown = [np.asarray(comp[k], float) for k in ("intra", "extra") if k in comp]
    # Limits from the common pupil, where the signal is used: the residual non-uniformity
    # stays visible instead of being squashed by the dark boundary ring.
    inside = [im[common] for im in shown if common is not None and common.shape == im.shape]
    vmin, vmax = _finite_limits(inside if inside and all(v.size for v in inside) else shown)
    im = None
    for ax, key in zip(axes[2:], ("intra", "extra"), strict=True):
        ax.set_title(f"{key}, compensated", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        if key not in comp:
            ax.text(0.5, 0.5, "not available\n(caustic)", ha="center", va="center",
                    transform=ax.transAxes)
            continue
        img, (r0, c0) = _crop_finite(np.asarray(comp[key], float))
        im = ax.imshow(img, origin="lower", cmap="viridis", vmin=vmin, vmax=vmax,
                       interpolation="nearest")
        if common is not None and common.any():
            sub = common[r0:r0 + img.shape[0], c0:c0 + img.shape[1]]
            ax.contour(sub.astype(float), levels=[0.5], colors="w", linewidths=0.6)
    if im is not None:
        fig.colorbar(im, ax=axes[2:], shrink=0.85, label="normalised intensity")


def _result_zernikes(ax_b: Any, result: Any) -> None:
    """Panel (b): the estimate's Z4..Z22 beside the design (intrinsic) part, nm."""
    noll = np.asarray(result.noll)
    z = np.asarray(result.zernikes_nm, float)
    design = np.asarray(result.intrinsic_nm, float)
    w = 0.4
    ax_b.bar(noll - w / 2, z, width=w, color="C0", label="estimate (total)")
    ax_b.bar(noll + w / 2, design, width=w, color="C1", label="design (intrinsic)")
    ax_b.axhline(0.0, color="k", lw=0.6)
    ax_b.set_xticks(noll)
    ax_b.set_xlim(noll[0] - 0.7, noll[-1] + 0.7)
    ax_b.set_xlabel("Noll index")
    ax_b.set_ylabel("Zernike coefficient (nm)")
    ax_b.set_title("(b) Z4..Z22", fontsize=10)
    ax_b.grid(axis="y", alpha=0.3)
    ax_b.legend(fontsize=8)


def _result_convergence(ax_c: Any, result: Any) -> None:
    """Panel (c): each term's estimate against the outer iteration, design part included (so
    the last point of each line is the bar in (b)); the largest terms coloured and labelled."""
    noll = np.asarray(result.noll)
    design = np.asarray(result.intrinsic_nm, float)
    hist = np.asarray(result.history_nm, float)
    n_it = hist.shape[0] if hist.ndim == 2 else 0
    ax_c.set_title("(c) convergence", fontsize=10)
    ax_c.set_xlabel("outer iteration")
    ax_c.set_ylabel("estimated term (nm)")
    if n_it == 0:
        ax_c.text(0.5, 0.5, "no iteration completed", ha="center", va="center",
                  transform=ax_c.transAxes)
        return
    it = np.arange(1, n_it + 1)
    js = [int(j) for j in noll if j <= hist.shape[1]]
    traces = {j: hist[:, j - 1] + design[j - int(noll[0])] for j in js}
    final = {j: abs(float(traces[j][-1])) for j in js}
    biggest = max(final.values()) if final else 0.0
    ranked = sorted(js, key=final.__getitem__, reverse=True)
    labelled = [j for j in ranked[:_N_LABELLED] if final[j] > 0.02 * biggest > 0]
    colours = [f"C{i}" for i in range(10)]
    for j in js:
        if j in labelled:
            c = colours[labelled.index(j) % 10]
            ax_c.plot(it, traces[j], "-o", color=c, ms=3, lw=1.6, label=f"Z{j}")
        else:
            ax_c.plot(it, traces[j], "-", color="0.6", lw=0.8, alpha=0.7)
    _convergence_legend(ax_c, labelled, len(js))
    ax_c.axhline(0.0, color="k", lw=0.6)
    ax_c.set_xlim(0.5, n_it + 0.5)
    ax_c.set_xticks(it if n_it <= 20 else np.linspace(1, n_it, 10).round().astype(int))
    ax_c.grid(alpha=0.3)


def _convergence_legend(ax_c: Any, labelled: list[int], n_terms: int) -> None:
    """The labelled terms, largest first, and one grey entry for the others (if any)."""
    from matplotlib.lines import Line2D

    handles, labels = ax_c.get_legend_handles_labels()
    order = sorted(range(len(labels)), key=lambda i: labelled.index(int(labels[i][1:])))
    handles, labels = [handles[i] for i in order], [labels[i] for i in order]
    if len(labelled) < n_terms:
        handles.append(Line2D([], [], color="0.6", lw=0.8))
        labels.append("other terms")
    ax_c.legend(handles, labels, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                borderaxespad=0.0, title="largest", title_fontsize=8)


def plot_closed_loop(run: Any, path: str | Path) -> Path:
    """Write the closed-loop demo's figure (a :class:`cwfs_ros.cli.demo.LoopRun`) as a PNG.

    Rows: (a) the 8 donuts of the first and of the last visit kept; (b) per corner, the
    estimated against the true Zernikes (design removed) of the first visit, with the last
    visit's estimate and truth as lighter markers; (c) the wavefront error per visit (true
    and estimated, log scale) and the telescope's DoF state per visit, each DoF group on
    its own normalised scale.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    recs = list(run.records)
    fig = Figure(figsize=(16.0, 13.0), dpi=90, layout="constrained")
    FigureCanvasAgg(fig)
    outer = fig.add_gridspec(3, 1, height_ratios=[1.25, 1.0, 1.0])
    _loop_donuts(fig, outer[0], recs)
    _loop_zernikes(fig, outer[1], recs)
    bot = outer[2].subgridspec(1, 2, width_ratios=[1.0, 1.3])
    _loop_convergence(fig.add_subplot(bot[0, 0]), recs)
    _loop_dof_state(fig.add_subplot(bot[0, 1]), recs)
    fig.suptitle(
        f"cwfs_ros closed loop: camera_sim_node -> wavefront_node -> ofc_node, "
        f"{len(recs)} visits, {run.config.n_photons:g} photons per donut"
        + (f", camera rotator {getattr(run.config, 'rotator_angle_deg', 0.0):g} deg"
           if getattr(run.config, "rotator_angle_deg", 0.0) else ""), fontsize=12)
    fig.savefig(path, format="png")
    return path


def _loop_donuts(fig: Any, spec: Any, recs: list[Any]) -> None:
    """Row (a): the donuts of the first and the last visit kept, one row each."""
    from cwfs_ros.layout import CORNERS, SIDES

    kept = [r for r in recs if r.images]
    rows = kept[:1] + kept[-1:] if len(kept) > 1 else kept
    top = spec.subgridspec(max(len(rows), 1), len(CORNERS) * len(SIDES))
    for i, r in enumerate(rows):
        for j, (c, s) in enumerate((c, s) for c in CORNERS for s in SIDES):
            ax = fig.add_subplot(top[i, j])
            label = f"visit {r.visit}: {c} {s}" if j == 0 else f"{c} {s}"
            show_donut(ax, r.images.get((c, s)), label)
    if not rows:
        ax = fig.add_subplot(top[0, 0])
        ax.text(0.5, 0.5, "no donuts kept", transform=ax.transAxes)


def _loop_zernikes(fig: Any, spec: Any, recs: list[Any]) -> None:
    """Row (b): per corner, estimate against truth with the design removed (what the loop
    corrects): the first visit as bars, the last as markers."""
    from cwfs_ros.layout import CORNERS, NOLL

    mid = spec.subgridspec(1, len(CORNERS))
    first, last = recs[0], recs[-1]
    noll = np.asarray(NOLL)
    n = len(noll)
    w = 0.38
    for k, c in enumerate(CORNERS):
        ax = fig.add_subplot(mid[0, k])
        sl = slice(k * n, (k + 1) * n)
        for rec, alpha, tag in ((first, 1.0, f"visit {first.visit}"),
                                (last, 0.45, f"visit {last.visit}")):
            truth = rec.truth_nm[sl] - rec.intrinsic_nm[sl]
            est = rec.estimate_nm[sl] - rec.intrinsic_nm[sl]
            if rec is first:
                ax.bar(noll - w / 2, truth, width=w, color="0.55", label=f"truth, {tag}")
                ax.bar(noll + w / 2, est, width=w, color="C0", label=f"estimate, {tag}")
            else:
                ax.plot(noll, truth, "_", color="k", ms=9, alpha=alpha, label=f"truth, {tag}")
                ax.plot(noll, est, ".", color="C3", ms=6, alpha=0.9, label=f"estimate, {tag}")
        err = np.sqrt(np.nanmean((first.estimate_nm[sl] - first.truth_nm[sl]) ** 2))
        ax.set_title(f"(b) {c}, design removed; visit {first.visit} error {err:.1f} nm rms",
                     fontsize=9)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xticks(noll[::2])
        ax.set_xlabel("Noll index")
        if k == 0:
            ax.set_ylabel("nm of wavefront")
            ax.legend(fontsize=7)
        ax.grid(axis="y", alpha=0.3)


def _loop_convergence(ax: Any, recs: list[Any]) -> None:
    """Row (c), left: the true (corners, science field) and measured wavefront error per
    visit, the estimate's own error on the same norm, and the refused corrections."""
    from cwfs_ros.layout import NOLL

    n = len(NOLL)
    v = np.array([r.visit for r in recs])
    true_e = np.array([r.true_error_nm for r in recs])
    est_e = np.array([r.estimated_error_nm for r in recs])
    est_err = np.array([r.median_estimate_error_nm for r in recs])
    ax.semilogy(v, true_e, "-o", color="k", label="true wavefront error, corners")
    field_e = np.array([getattr(r, "field_error_nm", np.nan) for r in recs])
    if np.any(np.isfinite(field_e)):
        ax.semilogy(v, field_e, "-D", color="C2", ms=4,
                    label="true wavefront error, science field (GQ)")
        fwhm = np.array([getattr(r, "fwhm_arcsec", np.nan) for r in recs])
        ax2 = ax.twinx()
        ax2.plot(v, fwhm, ":", color="C2", marker="v", ms=4, alpha=0.7)
        ax2.set_ylabel("optical FWHM over the field (arcsec, dotted)", color="C2")
        ax2.set_ylim(bottom=0.0)
    ax.semilogy(v, est_e, "--s", color="C0", ms=4, label="measured by wavefront_node")
    ax.semilogy(v, est_err * np.sqrt(n), ":^", color="C3", ms=4,
                label="estimate error (same norm)")
    bad = [r.visit for r in recs if not r.correction_valid]
    if bad:
        ax.plot(bad, true_e[np.isin(v, bad)], "x", color="r", ms=10,
                label="correction refused")
    ax.set_xlabel("visit")
    ax.set_ylabel("sqrt(sum Z4..Z22^2): corner mean, field GQ (nm)")
    title = f"(c) convergence: corners {true_e[0]:.0f} -> {true_e[-1]:.0f} nm"
    if np.all(np.isfinite(field_e)):
        title += f", field {field_e[0]:.0f} -> {field_e[-1]:.0f} nm"
    ax.set_title(title, fontsize=10)
    ax.set_xticks(v)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)


def _loop_dof_state(ax: Any, recs: list[Any]) -> None:
    """Row (c), right: the DoF state in units of each DoF's range (config/ofc/dof.yaml), rms
    per group: how far each actuator group is from nominal, on one physical scale."""
    from cwfs_ros.ofc.control import load_dof_spec

    v = np.array([r.visit for r in recs])
    state = np.array([r.dof_state for r in recs]) / load_dof_spec().range
    groups = (("M2 hexapod", slice(0, 5)), ("camera hexapod", slice(5, 10)),
              ("M1M3 bending modes", slice(10, 30)), ("M2 bending modes", slice(30, 50)))
    for i, (name, sl) in enumerate(groups):
        g = np.sqrt(np.mean(state[:, sl] ** 2, axis=1))
        ax.semilogy(v, np.maximum(g, 1e-7), "-o", ms=4, color=f"C{i}", label=name)
    ax.set_xlabel("visit")
    ax.set_ylabel("rms of DoF state / DoF range")
    ax.set_xticks(v)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title("telescope state per actuator group (0 = nominal)", fontsize=10)
