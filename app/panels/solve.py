"""Solve tab: 'Solve H', H +- sigma (CLI JSON names), gain, condition number, warnings,
Table-1 residual statistics, residual plots, and the outlier list with include/exclude toggles
that re-solve.

Rules: **Solve H** is a robust solve of every stored pose except those the operator excluded;
the poses it rejects are *flagged*. Each flagged or excluded pose gets a "use" toggle; changing
a toggle re-solves without robust screening, using exactly the poses switched on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from app.panels.state import AppState

TABLE_ROW_FMT = "| {name} | {value} | {sigma} | {truth} |"


@dataclass(frozen=True)
class SolveView:
    """A solve and what the panel shows: per-pose errors for every stored pose."""

    calibration: Any
    pose_index: np.ndarray          # (n,) all stored ok poses
    used: np.ndarray                # (n,) bool
    errors: np.ndarray              # (n, 3) Table-1 errors (x, y: eq 16 - camera; z: - plane)
    points: np.ndarray              # (n, 3) eq-16 spots with the solved H
    measured: np.ndarray            # (n, 3) camera spots on the fitted plane
    covariances: np.ndarray         # (n, 3, 3) of the eq-16 spots
    flagged: frozenset[int] = field(default_factory=frozenset)
    excluded: frozenset[int] = field(default_factory=frozenset)
    seconds: float = 0.0
    robust: bool = True
    number: int = 0
    dataset: Any = None             # the rows solved (excluded poses left out), for the report


def solve_frame(frame: pd.DataFrame, excluded: set[int] | frozenset[int], noise: Any,
                robust: bool = True, source: str = "session") -> SolveView:
    """Solve H from the session frame (solve CSV columns + pose_index) without ``excluded``."""
    from calib_core.calibrate import beam_residuals, solve
    from calib_core.errors import InputError
    from calib_core.io import dataset_from_frame

    t0 = time.perf_counter()
    if len(frame) == 0:
        raise InputError("no stored samples to solve: run an acquisition first")
    data = dataset_from_frame(frame, source)
    pose_index = frame["pose_index"].to_numpy(int)
    use = ~np.isin(pose_index, sorted(excluded))
    cal = solve(data.subset(np.flatnonzero(use)), noise=noise, robust=robust)
    row_to_pose = dict(zip(data.rows.tolist(), pose_index.tolist(), strict=True))
    flagged = frozenset(row_to_pose[int(r)] for r in cal.outliers)
    used = use & ~np.isin(pose_index, sorted(flagged))
    assert data.spot_xy is not None
    errors = beam_residuals(data.poses, data.d, data.spot_xy, cal.values, cal.model)
    points = cal.reconstruct(data.poses, data.d)
    alpha, beta = cal.point("alpha"), cal.point("beta")
    delta = cal.point("delta") if "delta" in cal.names else 0.0
    xy = data.spot_xy
    measured = np.column_stack([xy, alpha * xy[:, 0] + beta * xy[:, 1] + delta])
    return SolveView(cal, pose_index, used, errors, points, measured,
                     cal.point_covariance(data.poses, data.d), flagged,
                     frozenset(int(i) for i in excluded), time.perf_counter() - t0, robust,
                     dataset=data.subset(np.flatnonzero(use)))


def params_table(cal: Any, truth: dict[str, float] | None = None) -> str:
    """Markdown table: parameter (CLI JSON name), value, 1-sigma, and the simulated truth."""
    head = "| parameter | value | ±1σ | sim truth |" if truth else "| parameter | value | ±1σ | |"
    rows = [head, "|---|---:|---:|---:|"]
    for name, value, sigma in zip(cal.names, cal.values, cal.sigma, strict=True):
        t = "" if not truth or name not in truth else f"{truth[name]:.7g}"
        rows.append(TABLE_ROW_FMT.format(name=name, value=f"{value:.7g}", sigma=f"{sigma:.2g}",
                                         truth=t))
    t = "" if not truth else f"{truth.get('gain', float('nan')):.7g}"
    rows.append(TABLE_ROW_FMT.format(name="gain", value=f"{cal.gain:.7g}",
                                     sigma=f"{cal.gain_sigma:.2g}", truth=t))
    return "\n".join(rows)


def summary_markdown(view: SolveView) -> str:
    """Model, points used, condition number, Table-1 residual statistics (µm), warnings."""
    cal = view.calibration
    lines = [f"Solve #{view.number}: **{cal.model}** model: {cal.n_used} of "
             f"{len(view.pose_index)} poses used "
             f"({'robust' if view.robust else 'manual selection'}), condition number "
             f"**{cal.condition_number:.3g}**, solved in {view.seconds * 1000:.0f} ms", "",
             "| residual (µm) | mean abs | rms | max |", "|---|---:|---:|---:|"]
    for axis in ("x", "y", "z"):
        s = cal.residuals.get(axis, {})
        lines.append(f"| {axis} | {1000 * s.get('mean_abs', np.nan):.2f} | "
                     f"{1000 * s.get('rms', np.nan):.2f} | {1000 * s.get('max', np.nan):.2f} |")
    if cal.warnings:
        lines += ["", "**Warnings**", *(f"- {w}" for w in cal.warnings)]
    else:
        lines += ["", "No warnings."]
    return "\n".join(lines)


def residual_figures(view: SolveView) -> tuple[Any, Any]:
    """Plotly figures: histogram of x/y/z residuals (µm) and residual vs pose index."""
    import plotly.graph_objects as go

    e = 1000.0 * view.errors
    hist = go.Figure()
    scatter = go.Figure()
    for k, axis in enumerate("xyz"):
        hist.add_trace(go.Histogram(x=e[view.used, k], name=axis, opacity=0.6, nbinsx=20))
        scatter.add_trace(go.Scatter(x=view.pose_index, y=e[:, k], mode="markers", name=axis))
    bad = ~view.used
    if bad.any():
        scatter.add_trace(go.Scatter(x=view.pose_index[bad], y=np.linalg.norm(e[bad], axis=1),
                                     mode="markers", name="excluded |e|",
                                     marker={"symbol": "x", "size": 10, "color": "magenta"}))
    hist.update_layout(barmode="overlay", title="residual histogram (µm)",
                       margin={"l": 30, "r": 10, "t": 30, "b": 30}, height=260)
    scatter.update_layout(title="residual vs pose (µm)", xaxis_title="pose",
                          margin={"l": 30, "r": 10, "t": 30, "b": 30}, height=260)
    return hist, scatter


def load_data_csv(app: AppState, name: str, content: bytes) -> str:
    """Use an uploaded calibration data CSV (solve format) instead of the session (worker).

    Validated completely (:mod:`app.panels.upload`) before the state changes; rows get
    ``pose_index`` = row number unless the file has a valid one.
    """
    from app.panels.upload import display_name, upload_table
    from calib_core.errors import InputError
    from calib_core.io import dataset_from_frame, numeric_columns

    shown = display_name(name)
    frame = upload_table(name, content)
    data = dataset_from_frame(frame, shown, need_spot=True, min_rows=3)
    frame = frame.reset_index(drop=True)
    if "pose_index" in frame.columns:
        index = numeric_columns(frame, ("pose_index",), shown)[:, 0]
        if np.any(index != np.round(index)) or len(set(index.tolist())) != len(index):
            raise InputError(f"{shown}: column pose_index must hold distinct integers")
        frame["pose_index"] = index.astype(int)
    else:
        frame["pose_index"] = np.arange(len(frame))
    frame.attrs["sha256"] = hashlib.sha256(content).hexdigest()
    app.data_frame, app.data_source = frame, shown
    app.excluded, app.flagged = set(), set()
    app.calibration = app.solve_view = None
    app.changed("data")
    return f"{shown}: {len(data)} poses loaded; click 'Solve H'"


def run_solve(app: AppState, robust: bool = True) -> SolveView:
    """Solve the uploaded data CSV, else the open session (worker thread); publish the result."""
    from calib_core.errors import InputError

    if app.data_frame is not None:
        frame, source = app.data_frame, str(app.data_source)
    elif app.session is not None:
        frame, source = app.session.frame(), str(app.session_path)
    else:
        raise InputError("no session: run an acquisition, start with --session FILE.db or "
                         "load a data CSV")
    view = solve_frame(frame, app.excluded, app.workcell.noise, robust=robust, source=source)
    app.solve_count += 1
    view = dataclasses.replace(view, number=app.solve_count)
    app.calibration = view.calibration
    if robust:
        app.flagged = set(view.flagged)
    app.solve_view = view
    show_in_scene(app, view)
    app.changed("solve")
    return view


def show_in_scene(app: AppState, view: SolveView, ellipsoids: bool = False) -> None:
    """Spots coloured by |error|, fitted plane, error arrows, beam, optional ellipsoids."""
    sc = app.scene
    if sc is None:
        return
    cal = view.calibration
    norms = np.linalg.norm(view.errors, axis=1)
    sc.set_spots(view.points, norms, excluded=~view.used)
    delta = cal.point("delta") if "delta" in cal.names else 0.0
    sc.set_plane(cal.point("alpha"), cal.point("beta"), delta)
    sc.set_errors(view.measured, view.errors)
    sc.set_beam(cal.beam_point, cal.beam_vector)
    if ellipsoids:
        sc.set_ellipsoids(view.points, view.covariances)


def toggle_pose(app: AppState, pose: int, use: bool) -> SolveView:
    """Include or exclude one pose and re-solve with exactly the poses switched on."""
    if use:
        app.excluded.discard(pose)
    else:
        app.excluded.add(pose)
    return run_solve(app, robust=False)


def data_markdown(app: AppState) -> str:
    """Which data 'Solve H' uses."""
    if app.data_frame is not None:
        return f"data: uploaded file **{app.data_source}** ({len(app.data_frame)} poses)"
    if app.session_path is not None:
        return f"data: session {app.session_path.name}"
    return "data: none yet (acquire, or load a data CSV)"


def build(gui: Any, app: AppState) -> None:
    from app.panels.upload import add_upload

    data_md = gui.add_markdown(data_markdown(app))
    add_upload(gui, app, "Load data CSV", lambda name, content: load_data_csv(app, name, content),
               hint="Solve a measurement CSV (x_o,y_o,z_o,theta_deg|qw..qz,d,x_p,y_p) instead "
                    "of the session", mime_type=".csv,text/csv,text/plain")

    def show_data() -> None:
        data_md.content = data_markdown(app)
    app.on_change("data", show_data)
    app.on_change("session", show_data)
    solve_btn = gui.add_button("Solve H", color="blue", icon="calculator")
    if app.scene is not None:
        app.scene.legend = gui.add_html("<small>spots: grey until solved</small>")
    params = gui.add_markdown("")
    summary = gui.add_markdown("")
    arrows = gui.add_slider("Error arrow scale", min=10, max=5000, step=10,
                            initial_value=int(app.scene.arrow_scale) if app.scene else 1000)
    ellipsoids = gui.add_checkbox("1-sigma ellipsoids", initial_value=False)
    outlier_folder = gui.add_folder("Outliers (use pose?)")
    toggles: list[Any] = []
    exclude_n = gui.add_number("Pose to exclude", 0, min=0, step=1)
    exclude_btn = gui.add_button("Exclude pose and re-solve")
    import plotly.graph_objects as go

    with gui.add_folder("Residual plots"):
        hist_plot = gui.add_plotly(go.Figure(), aspect=1.4, visible=False)
        scatter_plot = gui.add_plotly(go.Figure(), aspect=1.4, visible=False)
    clicked_at = [0.0]

    def refresh() -> None:
        view: SolveView | None = app.solve_view
        if view is None:
            params.content = summary.content = ""
            return
        truth = app.world.truth() if app.sim and app.world is not None else None
        params.content = params_table(view.calibration, truth)
        summary.content = summary_markdown(view)
        if app.server is not None:
            app.server.flush()          # the numbers first, the plots in a later frame
        hist_plot.figure, scatter_plot.figure = residual_figures(view)
        hist_plot.visible = scatter_plot.visible = True
        for t in toggles:
            t.remove()
        toggles.clear()
        with outlier_folder:
            listed = sorted(app.flagged | app.excluded)
            if not listed:
                toggles.append(gui.add_markdown("No outliers flagged."))
            for pose in listed:
                k = int(np.flatnonzero(view.pose_index == pose)[0]) if pose in view.pose_index \
                    else None
                err = "" if k is None else f" |e| {1000 * np.linalg.norm(view.errors[k]):.1f} µm"
                box = gui.add_checkbox(f"pose {pose}{err}", initial_value=pose not in app.excluded)

                def on_toggle(_: Any, pose: int = pose, box: Any = box) -> None:
                    use = bool(box.value)
                    app.worker.submit("re-solve", lambda: toggle_pose(app, pose, use))
                box.on_update(on_toggle)
                toggles.append(box)
        if ellipsoids.value and app.scene is not None:
            app.scene.set_ellipsoids(view.points, view.covariances)
        if clicked_at[0]:
            app.last_solve_s = time.perf_counter() - clicked_at[0]
            clicked_at[0] = 0.0
    app.on_change("solve", refresh)
    app.on_change("data", refresh)

    @solve_btn.on_click
    def _(_: Any) -> None:
        clicked_at[0] = time.perf_counter()
        app.worker.submit("solve", lambda: run_solve(app, robust=True))

    @arrows.on_update
    def _(_: Any) -> None:
        if app.scene is not None:
            app.scene.set_arrow_scale(float(arrows.value))
            if ellipsoids.value and app.solve_view is not None:
                app.scene.set_ellipsoids(app.solve_view.points, app.solve_view.covariances)

    @ellipsoids.on_update
    def _(_: Any) -> None:
        if app.scene is None:
            return
        view = app.solve_view
        if ellipsoids.value and view is not None:
            app.scene.set_ellipsoids(view.points, view.covariances)
            app.scene.ellipsoids.visible = True
        else:
            app.scene.ellipsoids.visible = False

    @exclude_btn.on_click
    def _(_: Any) -> None:
        pose = int(exclude_n.value)
        app.worker.submit("re-solve", lambda: toggle_pose(app, pose, False))
