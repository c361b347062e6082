"""Hostile uploads through the dashboard's websocket (the viser upload protocol, behind the
token/Origin guard): huge, binary, wrong columns, NaN, bad JSON are refused with one clear
notification and the state does not change; a good file afterwards is accepted."""

from __future__ import annotations

import contextlib
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec.msgpack
import pytest

from app.panels import acquire, export, solve
from app.panels.state import AppState
from app.panels.upload import MAX_UPLOAD_BYTES
from drivers.sim.workcell import load_workcell

PART = 256 * 1024


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Any, AppState]]:
    from app.panels import build_dashboard
    from app.server import GuardedServer

    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    state = build_dashboard(server.viser, load_workcell(None),
                            session_path=tmp_path_factory.mktemp("upload") / "s.db")
    try:
        state.sim_move_time_s = 0.0
        state.worker.call("connect", state.connect_sim)
        state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 60)
        state.worker.call("solve", lambda: solve.run_solve(state), 60)
        yield server, guard, state
    finally:
        state.worker.stop()
        state.close_session()
        server.stop()


def button_uuid(server: Any, label: str) -> str:
    handles = server.viser.gui._gui_input_handle_from_uuid
    return next(u for u, h in handles.items() if getattr(h, "label", None) == label)


def send_upload(ws: Any, button: str, name: str, content: bytes,
                declared: int | None = None, parts: int | None = None) -> None:
    """The browser's upload: a start message, then the parts (as viser's client sends them)."""
    chunks = [content[i:i + PART] for i in range(0, len(content), PART)] or []
    transfer = str(uuid.uuid4())
    ws.send(msgspec.msgpack.encode({
        "type": "FileTransferStartUpload", "source_component_uuid": button,
        "transfer_uuid": transfer, "filename": name, "mime_type": "text/csv",
        "part_count": len(chunks) if parts is None else parts,
        "size_bytes": len(content) if declared is None else declared}))
    for i, chunk in enumerate(chunks):
        ws.send(msgspec.msgpack.encode({
            "type": "FileTransferPart", "source_component_uuid": button,
            "transfer_uuid": transfer, "part_index": i, "content": chunk}))


def drain(ws: Any) -> None:
    """Read (and drop) what the server sends, as a browser does."""
    with contextlib.suppress(Exception):
        while True:
            ws.recv()


def wait_message(state: AppState, since: int, text: str, timeout: float = 15.0
                 ) -> tuple[str, str]:
    """(level, body) of the first notification after ``since`` whose body holds ``text``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for _, level, _, body in list(state.messages)[since:]:
            if text in body:
                return level, body
        time.sleep(0.02)
    raise AssertionError(f"no notification with {text!r}: {list(state.messages)[since:]}")


def test_hostile_uploads_are_refused_and_change_nothing(dashboard, tmp_path: Path) -> None:
    import viser
    from websockets.sync.client import connect

    server, guard, state = dashboard
    data_button = button_uuid(server, "Load data CSV")
    calib_button = button_uuid(server, "Upload calibration JSON")
    good = export.session_csv(state)
    calibration, view = state.calibration, state.solve_view
    header, first, *rest = [ln for ln in good.split(b"\n") if not ln.startswith(b"#")]
    cases = [
        ("huge.csv", good * (MAX_UPLOAD_BYTES // len(good) + 2), "upload limit"),
        ("image.png", bytes(range(256)) * 64, "binary data"),
        ("latin1.csv", "x_o;y_o;zé\n".encode("latin-1") * 10, "not a UTF-8 text file"),
        ("columns.csv", good.replace(b"x_p", b"x_pixel"), "missing column(s) x_p"),
        ("nan.csv", b"\n".join([header, b"nan," + first.split(b",", 1)[1], *rest]),
         "not a finite number"),
        ("empty.csv", b"", "empty file"),
    ]
    with connect(f"ws://127.0.0.1:{guard.port}/?token={guard.token}",
                 subprotocols=[f"viser-v{viser.__version__}"],
                 additional_headers={"Origin": f"http://127.0.0.1:{guard.port}"},
                 max_size=None) as ws:
        threading.Thread(target=drain, args=(ws,), daemon=True).start()
        ws.send(msgspec.msgpack.encode({   # viser counts a client as connected from its camera
            "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0],
            "position": [150.0, -60.0, 140.0], "fov": 1.0, "near": 0.01, "far": 5000.0,
            "image_height": 600, "image_width": 800, "look_at": [10.0, 80.0, 10.0],
            "up_direction": [0.0, 0.0, 1.0]}))
        for name, content, expected in cases:
            since = len(state.messages)
            send_upload(ws, data_button, name, content)
            level, body = wait_message(state, since, expected)
            assert level == "error" and body.startswith(name), body
            assert "\n" not in body and "Traceback" not in body
            assert state.data_frame is None and state.calibration is calibration
            assert state.solve_view is view
        # a client that announces 1 GB: dropped at the start, nothing buffered
        since = len(state.messages)
        send_upload(ws, data_button, "liar.csv", good[:PART * 2], declared=1 << 30, parts=4096)
        level, body = wait_message(state, since, "larger than the 5 MB upload limit")
        assert level == "error" and body.startswith("liar.csv")
        time.sleep(0.2)
        assert server.viser.gui._current_file_upload_states == {}
        # a broken calibration JSON for the Measure tab
        since = len(state.messages)
        send_upload(ws, calib_button, "H.json", b'{"model": "schoenflies", "params": [1, 2')
        level, body = wait_message(state, since, "not valid JSON")
        assert level == "error" and state.measure_calibration is None
        # the same path accepts a good file
        since = len(state.messages)
        send_upload(ws, data_button, "good.csv", good)
        level, body = wait_message(state, since, "42 poses loaded")
        assert level == "success" and state.data_source == "good.csv"
        assert len(state.data_frame) == 42
    state.worker.call("back to the session", lambda: state.open_session(state.session_path))
    assert state.data_frame is None
