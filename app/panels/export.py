"""Export tab: download the session as CSV, the solve result as JSON and the calibration report
(HTML, PDF, JSON, CSV; :func:`app.report.build_report_bytes`) through viser's download API."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Callable
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


#: Report formats offered: label -> file names of the bundle (several are zipped).
REPORT_FORMATS = {"zip (HTML, PDF, JSON, CSV)": ("report.html", "report.pdf", "calibration.json",
                                                  "residuals.csv"),
                  "HTML": ("report.html",), "PDF": ("report.pdf",)}


def report_files(app: AppState, note: str = "") -> dict[str, bytes]:
    """The report of the last 'Solve H' on the rows it solved, with the Measure tab's results as
    sections (worker thread; a few seconds)."""
    from app.report import build_report_bytes
    from app.report.data import section_from_json, source_meta

    view = app.solve_view
    if view is None or view.dataset is None:
        raise InputError("nothing to report: click 'Solve H' first")
    if app.data_frame is None and app.session_path is not None and app.session_path.exists():
        meta = source_meta(app.session_path, note)
    else:
        frame = app.data_frame
        meta = {"source": str(view.dataset.source), "note": note,
                "sha256": frame.attrs.get("sha256", "") if frame is not None else "",
                "mode": "not recorded (uploaded CSV)"}
    meta.update(calibration_mode="solved",
                calibration_source="solved in the dashboard ('Solve H')",
                options={"model": view.calibration.model, "robust": view.robust,
                         "excluded poses": ", ".join(map(str, sorted(view.excluded))) or "none",
                         "noise": "workcell file"})
    sections = [section_from_json(m.result, m.source) for m in app.measurements.values()]
    return build_report_bytes(view.calibration, view.dataset, meta, sections)


def report_download(files: dict[str, bytes], fmt: str, stem: str) -> tuple[str, bytes]:
    """(file name, bytes) to send: one file, or a zip of several."""
    names = REPORT_FORMATS[fmt]
    if len(names) == 1:
        name = names[0]
        return f"{stem}.{name}", files[name]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in names:
            zf.writestr(name, files[name])
    return f"{stem}.report.zip", buf.getvalue()


def offer_download(app: AppState, client: Any, title: str, filename: str,
                   build: Callable[[], bytes]) -> None:
    """Send ``build()`` to ``client`` as ``filename``; a refusal becomes a warning notification."""
    try:
        data = build()
    except InputError as exc:
        app.notify(title, str(exc), "warning")
        return
    client.send_file_download(filename, data, save_immediately=True)


def build(gui: Any, app: AppState) -> None:
    csv_btn = gui.add_button("Download session CSV", icon="download")
    json_btn = gui.add_button("Download solve JSON", icon="download")
    with gui.add_folder("Report"):
        fmt = gui.add_dropdown("Report format", tuple(REPORT_FORMATS),
                               initial_value=next(iter(REPORT_FORMATS)))
        note = gui.add_text("Operator note", "")
        report_btn = gui.add_button("Download report", icon="file-certificate",
                                    hint="HTML and PDF report, calibration JSON and residual CSV "
                                         "of the last Solve H (takes a few seconds)")

    def stem() -> str:
        return app.session_path.stem if app.session_path is not None else "lasercal"

    @csv_btn.on_click
    def _(event: Any) -> None:
        offer_download(app, event.client, "export", f"{stem()}.csv", lambda: session_csv(app))

    @json_btn.on_click
    def _(event: Any) -> None:
        offer_download(app, event.client, "export", f"{stem()}.calib.json",
                       lambda: solve_json(app))

    @report_btn.on_click
    def _(event: Any) -> None:
        client, choice, text = event.client, str(fmt.value), str(note.value)
        if app.solve_view is None:
            app.notify("report", "nothing to report: click 'Solve H' first", "warning")
            return
        app.notify("report", "rendering the report (a few seconds) ...", "info")

        def cmd() -> str:
            name, data = report_download(report_files(app, text), choice, stem())
            client.send_file_download(name, data, save_immediately=True)
            app.notify("report", f"{name} sent ({len(data) // 1024} kB)", "success")
            return name
        app.worker.submit("report", cmd)
