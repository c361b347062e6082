"""Export tab: download the session as CSV and the solve result as JSON (viser download API)."""

from __future__ import annotations

import json
from typing import Any

from app.panels.state import AppState
from calib_core.errors import InputError


def session_csv(app: AppState) -> bytes:
    """The stored ok samples in the measurement CSV format (``lasercal solve`` reads it back),
    with ``#`` comment lines naming the session."""
    if app.session is None:
        raise InputError("no session to export: run an acquisition first")
    frame = app.session.frame()
    meta = app.session.meta
    header = [f"# lasercal session {app.session_path}",
              f"# created {meta.get('created', '?')}; grid {meta.get('grid', '?')}; "
              f"{len(frame)} ok samples of {app.session.n_poses()} poses"]
    return ("\n".join(header) + "\n" + frame.to_csv(index=False, float_format="%.9g")).encode()


def solve_json(app: AppState) -> bytes:
    """The solve result: the ``lasercal solve --json`` object (the calibration file)."""
    if app.calibration is None:
        raise InputError("nothing to export: click 'Solve H' first")
    return (json.dumps(app.calibration.to_json_dict(), indent=2) + "\n").encode()


def build(gui: Any, app: AppState) -> None:
    csv_btn = gui.add_button("Download session CSV", icon="download")
    json_btn = gui.add_button("Download solve JSON", icon="download")

    def stem() -> str:
        return app.session_path.stem if app.session_path is not None else "lasercal"

    @csv_btn.on_click
    def _(event: Any) -> None:
        try:
            data = session_csv(app)
        except InputError as exc:
            app.notify("export", str(exc), "warning")
            return
        event.client.send_file_download(f"{stem()}.csv", data, save_immediately=True)

    @json_btn.on_click
    def _(event: Any) -> None:
        try:
            data = solve_json(app)
        except InputError as exc:
            app.notify("export", str(exc), "warning")
            return
        event.client.send_file_download(f"{stem()}.calib.json", data, save_immediately=True)
