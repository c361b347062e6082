"""The dashboard's GUI: one module per tab, plus the STOP button above the tabs.

``build_dashboard(server, workcell, ...)`` creates the shared :class:`AppState`, the scene and
every tab once; all browser tabs share them (viser replays the state to a reconnecting tab).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from app.panels import acquire, export, grid, jog, measure, setup, solve
from app.panels.state import AppState
from app.panels.upload import refuse_oversized

TABS = (("Setup", setup), ("Jog", jog), ("Grid", grid), ("Acquire", acquire),
        ("Solve", solve), ("Measure", measure), ("Export", export))


def build_dashboard(server: Any, workcell: Any, *, sim: bool = True,
                    session_path: Path | None = None, seed: int | None = 0) -> AppState:
    """Build the scene and GUI on ``server`` (a viser.ViserServer); start the worker."""
    gui = server.gui
    gui.configure_theme(control_width="large", dark_mode=False)
    app = AppState(server, workcell, sim=sim, session_path=session_path, seed=seed)
    stop = gui.add_button("STOP", color="red", icon="hand-stop",
                          hint="Feed hold now, pause the acquisition, disarm motion")
    stop.on_click(lambda _: _stop(app))
    control = gui.add_markdown("")
    take = gui.add_button("Take control", hint="Hand control of the cell to this browser tab")
    take.on_click(lambda event: app.take_control(event.client_id))

    def show_control() -> None:
        control.content = ("control: nobody (the first tab to command the cell takes it)"
                           if app.controller is None else f"control: tab #{app.controller}")
    show_control()
    app.on_change("control", show_control)
    server.on_client_disconnect(lambda client: app.release_control(client.client_id))
    refuse_oversized(server, app)
    tabs = gui.add_tab_group()
    for title, module in TABS:
        with tabs.add_tab(title):
            module.build(gui, app)
    app.worker.start()
    if session_path is not None and session_path.exists():
        app.worker.submit("open session", lambda: app.open_session(session_path))
    if sim:
        app.worker.submit("connect", app.connect_sim)
    app.worker.submit("preload", _preload)
    return app


def _stop(app: AppState) -> None:
    try:
        app.stop_motion()
    except Exception as exc:  # STOP must always answer
        app.notify("STOP", f"stop failed: {exc}", "error")
        return
    app.notify("STOP", "motion stopped, acquisition paused, motion disarmed", "warning")


def _preload() -> None:
    """Import the solver and plotly now, so the first 'Solve H' is fast."""
    import plotly.graph_objects  # noqa: F401

    import calib_core.calibrate  # noqa: F401
