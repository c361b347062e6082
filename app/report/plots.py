"""Report figures (matplotlib, Agg canvas, no pyplot state): residuals and the pose grid.

Residuals are drawn in micrometres (the tables give mm); outlier poses are marked in red and
kept off the scale of the plots so that the inliers stay readable.
"""

from __future__ import annotations

import io
import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from app.report.data import Report

COLORS = {"fit": "#1f5fa8", "holdout": "#e07b00", "evaluated": "#2b8a3e", "outlier": "#c92a2a"}
LABELS = {"fit": "fit set", "holdout": "hold-out", "evaluated": "evaluated", "outlier": "outlier"}
AXES = ("x", "y", "z")
UM = 1000.0  # mm -> micrometre


def _new(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def nice_length(value: float) -> float:
    """The largest 1, 2 or 5 x 10^k not above ``value`` (a scale-bar length)."""
    if not value > 0 or not math.isfinite(value):
        return 1.0
    exp = math.floor(math.log10(value))
    for m in (5.0, 2.0, 1.0):
        if m * 10**exp <= value:
            return m * 10**exp
    return 10.0**exp


def _inlier_sets(report: Report) -> list[str]:
    return [s for s in ("fit", "holdout", "evaluated") if (report.poses["set"] == s).any()]


def histograms(report: Report) -> Figure:
    """Residual histograms per axis (µm), fit and hold-out/evaluated sets, ±expected RMS."""
    fig = _new(8.0, 3.0)
    axs = fig.subplots(1, 3)
    p = report.poses
    sets = _inlier_sets(report)
    exp_label = next(iter(report.expected), None)
    for k, axis in enumerate(AXES):
        ax = axs[k]
        values = [p.loc[p["set"] == s, f"e_{axis}"].to_numpy() * UM for s in sets]
        allv = np.concatenate(values) if values else np.zeros(1)
        lim = max(float(np.max(np.abs(allv))), 1e-6)
        bins = np.linspace(-lim, lim, 16)
        ax.hist(values, bins=bins, stacked=True, color=[COLORS[s] for s in sets],
                label=[LABELS[s] for s in sets], edgecolor="white", linewidth=0.5)
        if exp_label is not None:
            e = report.expected[exp_label][axis] * UM
            for x in (-e, e):
                ax.axvline(x, color="#555", linestyle="--", linewidth=1)
        ax.set_xlabel(f"{axis} residual [µm]")
        ax.set_ylabel("poses" if k == 0 else "")
        ax.set_title(f"{axis}: RMS {np.sqrt(np.mean(allv**2)):.2f} µm", fontsize=9)
    axs[0].legend(fontsize=7, loc="upper left")
    n_out = int((p["set"] == "outlier").sum())
    fig.suptitle("Residual histograms (dashed: ±RMS expected from the noise model)"
                 + (f"; {n_out} outlier(s) not shown" if n_out else ""), fontsize=10)
    return fig


def error_vectors(report: Report) -> Figure:
    """x-y residual vectors drawn at the camera spot positions, scaled, with a scale bar."""
    fig = _new(8.0, 5.0)
    ax = fig.subplots()
    p = report.poses
    inl = p[p["set"] != "outlier"]
    span = max(float(np.ptp(p["x_p"])), float(np.ptp(p["y_p"])), 1e-3)
    mag = np.hypot(inl["e_x"], inl["e_y"]).to_numpy()
    ref = float(np.percentile(mag, 95)) if len(mag) else 1e-3
    ref = max(ref, 1e-9)
    scale = ref / (0.12 * span)  # mm of error per mm of plot
    ax.scatter(p["x_p"], p["y_p"], s=6, color="#999", zorder=1)
    for s in _inlier_sets(report):
        q = p[p["set"] == s]
        ax.quiver(q["x_p"], q["y_p"], q["e_x"], q["e_y"], angles="xy", scale_units="xy",
                  scale=scale, color=COLORS[s], width=0.003, label=LABELS[s], zorder=2)
    for _, q in p[p["set"] == "outlier"].iterrows():
        ax.scatter([q["x_p"]], [q["y_p"]], marker="x", s=60, color=COLORS["outlier"], zorder=3)
        ax.annotate(f"row {int(q['row'])}: {np.hypot(q['e_x'], q['e_y']) * UM:.0f} µm",
                    (q["x_p"], q["y_p"]), textcoords="offset points", xytext=(6, 6),
                    color=COLORS["outlier"], fontsize=8)
    bar = nice_length(ref)
    x0, x1 = float(p["x_p"].min()), float(p["x_p"].max())
    y0, y1 = float(p["y_p"].min()), float(p["y_p"].max())
    pad = 0.15 * span
    bx, by = x0, y0 - 0.6 * pad
    ax.plot([bx, bx + bar / scale], [by, by], color="black", linewidth=3)
    ax.text(bx + bar / scale / 2, by - 0.04 * span, f"{bar * UM:g} µm error", ha="center",
            va="top", fontsize=9)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("spot x_p [mm]")
    ax.set_ylabel("spot y_p [mm]")
    ax.set_title(f"x-y residuals at the spot positions (arrows scaled: {bar * UM:g} µm = "
                 f"{bar / scale:.2f} mm of plot)", fontsize=10)
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    return fig


def _clipped(ax, x: np.ndarray, y: np.ndarray, sets: np.ndarray, lim: float) -> None:
    """Scatter by set; outliers beyond ±lim drawn as red triangles at the edge."""
    for s in ("fit", "holdout", "evaluated"):
        m = sets == s
        if m.any():
            ax.scatter(x[m], y[m], s=12, color=COLORS[s], label=LABELS[s])
    m = sets == "outlier"
    inside = m & (np.abs(y) <= lim)
    off = m & (np.abs(y) > lim)
    if inside.any():
        ax.scatter(x[inside], y[inside], s=40, marker="x", color=COLORS["outlier"],
                   label="outlier")
    if off.any():
        ax.scatter(x[off], np.clip(y[off], -lim, lim), s=40, marker="^",
                   color=COLORS["outlier"], label="outlier (off scale)")
    ax.set_ylim(-lim * 1.08, lim * 1.08)
    ax.axhline(0, color="#777", linewidth=0.8)
    ax.grid(alpha=0.3)


def _limit(report: Report, axis: str) -> float:
    p = report.poses
    inl = p.loc[p["set"] != "outlier", f"e_{axis}"].to_numpy() * UM
    return max(float(np.max(np.abs(inl))) if len(inl) else 1.0, 1e-3) * 1.15


def residual_vs_index(report: Report) -> Figure:
    """Residual (µm) per axis against the pose row number."""
    fig = _new(8.0, 4.4)
    axs = fig.subplots(3, 1, sharex=True)
    p = report.poses
    sets = p["set"].to_numpy()
    for k, axis in enumerate(AXES):
        _clipped(axs[k], p["row"].to_numpy(), p[f"e_{axis}"].to_numpy() * UM, sets,
                 _limit(report, axis))
        axs[k].set_ylabel(f"{axis} [µm]")
    axs[0].legend(fontsize=7, ncol=4, loc="upper right")
    axs[2].set_xlabel("pose (row number)")
    fig.suptitle("Residuals against pose order (drift or a bad stretch shows here)", fontsize=10)
    return fig


def residual_vs_pose(report: Report) -> Figure:
    """Residual (µm) per axis against the flange height z_o and the rotation angle."""
    fig = _new(8.0, 5.4)
    axs = fig.subplots(3, 2, sharex="col")
    p = report.poses
    sets = p["set"].to_numpy()
    for k, axis in enumerate(AXES):
        lim = _limit(report, axis)
        _clipped(axs[k, 0], p["z_o"].to_numpy(), p[f"e_{axis}"].to_numpy() * UM, sets, lim)
        _clipped(axs[k, 1], p["rotation_deg"].to_numpy(), p[f"e_{axis}"].to_numpy() * UM,
                 sets, lim)
        axs[k, 0].set_ylabel(f"{axis} [µm]")
    axs[2, 0].set_xlabel("flange height z_o [mm]")
    axs[2, 1].set_xlabel("rotation [deg]")
    axs[0, 1].legend(fontsize=7, loc="upper right")
    fig.suptitle("Residuals against height and rotation (a trend means an unmodelled effect)",
                 fontsize=10)
    return fig


def pose_grid(report: Report) -> Figure:
    """The flange positions in 3-D, coloured by rotation; outliers and hold-out marked."""
    fig = _new(8.0, 5.0)
    ax = fig.add_subplot(projection="3d")
    p = report.poses
    main = p[p["set"].isin(("fit", "evaluated"))]
    sc = ax.scatter(main["x_o"], main["y_o"], main["z_o"], c=main["rotation_deg"],
                    cmap="viridis", s=28, depthshade=False, label="fit / evaluated")
    hold = p[p["set"] == "holdout"]
    if len(hold):
        ax.scatter(hold["x_o"], hold["y_o"], hold["z_o"], facecolors="none",
                   edgecolors=COLORS["holdout"], s=50, linewidths=1.5, label="hold-out")
    out = p[p["set"] == "outlier"]
    if len(out):
        ax.scatter(out["x_o"], out["y_o"], out["z_o"], marker="x", color=COLORS["outlier"],
                   s=70, label="outlier")
    fig.colorbar(sc, ax=ax, shrink=0.6, label="rotation [deg]")
    ax.set_xlabel("x_o [mm]")
    ax.set_ylabel("y_o [mm]")
    ax.set_zlabel("z_o [mm]")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(f"Pose grid: {len(p)} flange poses", fontsize=10)
    return fig


#: (key, caption, builder) of every report figure, in order.
FIGURES = (
    ("histograms", "Residual histograms per axis", histograms),
    ("vectors", "x-y error vectors at the spot positions", error_vectors),
    ("vs_index", "Residuals against pose order", residual_vs_index),
    ("vs_pose", "Residuals against height and rotation", residual_vs_pose),
    ("grid", "The pose grid in 3-D", pose_grid),
)


def figures(report: Report) -> list[tuple[str, str, Figure]]:
    """(key, caption, figure) of every report figure."""
    return [(key, caption, build(report)) for key, caption, build in FIGURES]


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    """The figure as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
