"""Acquire tab: Start acquisition, Pause / Resume / Abort, progress with ETA, last sample.

The run happens on the worker thread (:class:`app.acquisition.Runner`, which commits every
sample to the session file the moment it is measured). Pausing returns the worker to the
queue (``return_on_pause``), so the operator can jog or reconnect before resuming.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from app.panels.state import AppState, TapRobot, TapSensor


def spots_of_session(app: AppState) -> tuple[np.ndarray, np.ndarray]:
    """Camera spots of the stored ok samples as points on the nominal plate (n, 3), and their
    pose indices (n,)."""
    if app.session is None:
        return np.zeros((0, 3)), np.zeros(0, int)
    frame = app.session.frame()
    x, y = frame["x_p"].to_numpy(float), frame["y_p"].to_numpy(float)
    z = np.asarray(app.workcell.plate.z_at(x, y), dtype=float)
    return np.column_stack([x, y, z]), frame["pose_index"].to_numpy(int)


def run_acquisition(app: AppState, samples_per_pose: int = 3) -> Any:
    """Run (or continue) the acquisition of the planned grid (worker thread)."""
    from app.acquisition import Runner, RunnerConfig

    app.require_devices()
    if app.runner is not None and app.runner.state == "paused":
        runner = app.runner
        # the devices attached now, which after a fault and a reconnect are not the old ones
        runner.set_devices(TapRobot(app.robot, app), TapSensor(app.sensor, app), app.camera)
        runner.resume()
    else:
        session = app.ensure_session()
        config = RunnerConfig(samples_per_pose=samples_per_pose, return_on_pause=True)

        def on_progress(progress: Any) -> None:
            app.progress = progress
            app.changed("progress")
        runner = Runner(session, TapRobot(app.robot, app), TapSensor(app.sensor, app),
                        app.camera, config, on_progress=on_progress)
        app.runner = runner
    progress = runner.run()
    app.progress = progress
    app.changed("progress")
    if progress.state == "finished":
        app.notify("acquisition", f"finished: {progress.done} of {progress.total} poses stored "
                   f"({progress.skipped} skipped) in {app.session_path}", "success")
    elif progress.state == "paused":
        app.notify("acquisition", f"paused: {progress.message}", "warning")
    return progress


def format_eta(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = max(0.0, float(seconds))
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def status_markdown(progress: Any) -> str:
    if progress is None:
        return "Not started."
    lines = [f"**{progress.state}**: {progress.done} / {progress.total} poses "
             f"({progress.skipped} skipped), ETA {format_eta(progress.eta_s)}"]
    if progress.message:
        lines.append(f"  \n{progress.message}")
    last = progress.last
    if last is not None:
        d = "-" if last.d is None else f"{last.d:.4f}"
        xy = "-" if last.x_p is None else f"({last.x_p:.4f}, {last.y_p:.4f})"
        lines.append(f"  \nlast: pose {last.pose_index} [{last.status}] d = {d} mm, "
                     f"spot {xy} mm {last.reason}")
    return "".join(lines)


def build(gui: Any, app: AppState) -> None:
    session_text = gui.add_text("Session file", str(app.session_path or ""),
                                hint="Empty: a new lasercal-session-<time>.db in the current "
                                     "directory")
    per_pose = gui.add_number("Readings per pose", 3, min=1, max=50, step=1)
    start = gui.add_button("Start acquisition", color="green", icon="player-play")
    controls = gui.add_button_group("Run", ("Pause", "Resume", "Abort"))
    bar = gui.add_progress_bar(0.0, animated=False)
    status = gui.add_markdown("Not started.")
    live = gui.add_checkbox("Live view", initial_value=app.live)
    live_md = gui.add_markdown("")
    last_live = [0.0]

    def refresh_progress() -> None:
        p = app.progress
        bar.value = 100.0 * p.fraction if p is not None else 0.0
        status.content = status_markdown(p)
        if app.scene is not None and app.session is not None:
            points, _ = spots_of_session(app)
            if app.calibration is None:
                app.scene.set_spots(points)
    app.on_change("progress", refresh_progress)

    def refresh_session() -> None:
        session_text.value = str(app.session_path or "")
        if app.session is not None and app.runner is None:
            n, total = len(app.session.stored_indices()), app.session.n_poses()
            status.content = f"session {app.session_path.name}: {n} / {total} poses stored"
            bar.value = 100.0 * n / total if total else 0.0
            if app.scene is not None:
                app.scene.set_spots(spots_of_session(app)[0])
    app.on_change("session", refresh_session)
    refresh_session()

    def refresh_live() -> None:
        now = time.monotonic()
        if now - last_live[0] < 0.2:
            return
        last_live[0] = now
        s = app.latest
        if s is None:
            return
        r = s.reading
        text = "live reading: " + ("-" if r is None else (f"{r.value:+.4f} mm" if r.ok
                                                           else str(r.status)))
        live_md.content = text
    app.on_change("live", refresh_live)

    @live.on_update
    def _(_: Any) -> None:
        app.live = bool(live.value)

    @start.on_click
    def _(event: Any) -> None:
        if not app.has_control(event.client_id, "acquisition"):
            return
        if app.runner is not None and app.runner.state == "running":
            app.notify("acquisition", "already running", "info")
            return
        text = session_text.value.strip()
        if text and (app.session_path is None or Path(text) != app.session_path):
            app.close_session()
            app.session_path = Path(text)
            app.runner = None
        if app.runner is not None and app.runner.state != "paused":
            app.runner = None
        n = int(per_pose.value)
        app.worker.submit("acquisition", lambda: run_acquisition(app, n))

    @controls.on_click
    def _(event: Any) -> None:
        runner = app.runner
        action = event.target.value
        if runner is None:
            app.notify("acquisition", "no acquisition to " + action.lower(), "info")
        elif action == "Pause":
            runner.pause()
        elif action == "Abort":
            runner.abort()
            app.notify("acquisition", "aborted; stored samples are kept", "warning")
        elif action == "Resume":
            if not app.has_control(event.client_id, "acquisition"):
                return
            if runner.state != "paused":
                app.notify("acquisition", f"nothing to resume (state {runner.state})", "info")
                return
            app.worker.submit("acquisition", lambda: run_acquisition(app, int(per_pose.value)))

