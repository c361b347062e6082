"""Uploads through the browser, refused cleanly when hostile: size, binary, wrong columns, NaN.

Every uploaded file is checked before anything in the state changes: at most
:data:`MAX_UPLOAD_BYTES`, UTF-8 text without NUL bytes, and (tables) parsed by
:mod:`calib_core.io` with the required columns and finite numbers. A refusal is one
:class:`~calib_core.errors.InputError` line that reaches the operator as a notification.
The parse runs on the worker thread; the viser callback only enqueues it.
"""

from __future__ import annotations

import contextlib
import json
import re
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from app.panels.state import AppState
from calib_core.errors import InputError

#: Largest accepted upload (bytes); a calibration session of thousands of poses is < 1 MB.
MAX_UPLOAD_BYTES = 5 * 1024 * 1024
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


def display_name(name: str) -> str:
    """The uploaded file's base name, printable and at most 80 characters."""
    base = Path(str(name).replace("\\", "/")).name
    clean = "".join(ch if ch.isprintable() else "?" for ch in base)[:80]
    return clean or "upload"


def upload_text(name: str, content: bytes, limit: int = MAX_UPLOAD_BYTES) -> str:
    """The file as text: refused when larger than ``limit``, not UTF-8, or holding NUL bytes."""
    shown = display_name(name)
    if len(content) > limit:
        raise InputError(f"{shown}: file is {len(content)} bytes, larger than the "
                         f"{limit // (1024 * 1024)} MB upload limit")
    if not content.strip():
        raise InputError(f"{shown}: empty file")
    if b"\x00" in content:
        raise InputError(f"{shown}: binary data, expected a CSV/JSON text file")
    try:
        return content.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{shown}: not a UTF-8 text file") from None


def upload_table(name: str, content: bytes, required: Sequence[str] = (),
                 limit: int = MAX_UPLOAD_BYTES) -> pd.DataFrame:
    """An uploaded CSV through :func:`calib_core.io.read_table` (errors name the upload)."""
    from calib_core.io import read_table

    upload_text(name, content, limit)
    shown = display_name(name)
    with tempfile.TemporaryDirectory(prefix="lasercal-upload-") as tmp:
        path = Path(tmp) / (_SAFE_NAME.sub("_", shown) or "upload.csv")
        path.write_bytes(content)
        try:
            frame = read_table(path)
        except InputError as exc:
            raise InputError(str(exc).replace(str(path), shown)) from None
    missing = [c for c in required if c not in frame.columns]
    if missing:
        raise InputError(f"{shown}: missing column(s) {', '.join(missing)} "
                         f"(found: {', '.join(frame.columns) or 'none'})")
    return frame


def upload_dataset(name: str, content: bytes, *, need_spot: bool = True, min_rows: int = 1,
                   required: Sequence[str] = ()) -> Any:
    """An uploaded measurement CSV as a validated :class:`calib_core.io.Dataset`."""
    from calib_core.io import dataset_from_frame

    frame = upload_table(name, content, required)
    return dataset_from_frame(frame, display_name(name), need_spot=need_spot, min_rows=min_rows)


def upload_json(name: str, content: bytes) -> dict[str, Any]:
    """An uploaded JSON file holding one object."""
    text = upload_text(name, content)
    shown = display_name(name)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{shown}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    except RecursionError:
        raise InputError(f"{shown}: JSON nested too deeply") from None
    if not isinstance(data, dict):
        raise InputError(f"{shown}: expected a JSON object")
    return data


def read_json_file(path: str) -> dict[str, Any]:
    """A JSON object from a file on the server (same checks as an upload)."""
    try:
        content = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return upload_json(path, content)


def upload_calibration(name: str, content: bytes) -> Any:
    """An uploaded calibration file (the ``lasercal solve --json`` object)."""
    import numpy as np

    from calib_core.calibrate import BeamCalibration

    shown = display_name(name)
    cal = BeamCalibration.from_json_dict(upload_json(name, content), shown)
    if not (np.all(np.isfinite(cal.values)) and np.all(np.isfinite(cal.covariance))):
        raise InputError(f"{shown}: the calibration holds non-finite numbers")
    return cal


def refuse_oversized(server: Any, app: AppState, limit: int = MAX_UPLOAD_BYTES) -> None:
    """Drop an upload as soon as it announces more than ``limit`` bytes (before buffering).

    Registered after viser's own handler of the transfer start; dropping the transfer state makes
    viser ignore its parts (the post-upload size check stays as the second line of defence).
    """
    from viser import _messages

    def on_start(client_id: int, message: Any) -> None:
        if message.size_bytes <= limit:
            return
        with contextlib.suppress(Exception):
            server.gui._current_file_upload_states.pop(message.transfer_uuid, None)
        app.notify("upload", f"{display_name(message.filename)}: file is {message.size_bytes} "
                   f"bytes, larger than the {limit // (1024 * 1024)} MB upload limit; refused",
                   "error")

    with contextlib.suppress(Exception):
        server._websock_server.register_handler(_messages.FileTransferStartUpload, on_start)


def add_upload(gui: Any, app: AppState, label: str, handle: Callable[[str, bytes], str],
               *, hint: str | None = None, mime_type: str = "*/*") -> Any:
    """An upload button whose file goes to ``handle(name, content)`` on the worker thread.

    ``handle`` validates completely before changing any state and returns a success message;
    its :class:`InputError` becomes an error notification (by the worker).
    """
    button = gui.add_upload_button(label, icon="upload", hint=hint, mime_type=mime_type)

    @button.on_upload
    def _(_: Any) -> None:
        file = button.value
        name, content = str(file.name), bytes(file.content)

        def cmd() -> str:
            message = handle(name, content)
            app.notify(label, message, "success")
            return message
        app.worker.submit(label, cmd)
    return button
