"""The one thread that owns the drivers; GUI callbacks only enqueue commands for it.

A command is a callable with a label. Its result or exception goes into a
:class:`concurrent.futures.Future`; an exception also becomes an operator notification
(``notify(title, body, level)``), so a failed device call never kills the page or the thread.
Between commands the worker calls an optional ``idle`` hook every ``idle_period_s`` (live view).
"""

from __future__ import annotations

import queue
import threading
import traceback
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from calib_core.errors import LasercalError

#: ``notify(title, body, level)`` with level "info", "warning" or "error".
Notify = Callable[[str, str, str], None]


def operator_message(exc: BaseException) -> str:
    """One line for the operator: the message of a LasercalError, else type and text."""
    if isinstance(exc, LasercalError):
        return str(exc)
    return f"internal error ({type(exc).__name__}: {exc})"


@dataclass
class _Command:
    label: str
    fn: Callable[[], Any]
    future: Future = field(default_factory=Future)


class Worker:
    """A FIFO of commands run one at a time on a daemon thread named ``lasercal-worker``."""

    def __init__(self, notify: Notify, idle: Callable[[], None] | None = None,
                 idle_period_s: float = 0.04) -> None:
        self._notify = notify
        self._idle = idle
        self._idle_period = idle_period_s
        self._queue: queue.Queue[_Command | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="lasercal-worker", daemon=True)
        self._busy = threading.Event()
        self._last_idle_error = ""
        self.current: str | None = None

    def start(self) -> Worker:
        self._thread.start()
        return self

    @property
    def busy(self) -> bool:
        """True while a command runs."""
        return self._busy.is_set()

    def pending(self) -> int:
        """Commands waiting in the queue."""
        return self._queue.qsize()

    def submit(self, label: str, fn: Callable[[], Any]) -> Future:
        """Queue ``fn`` (called without arguments on the worker thread); returns its future."""
        cmd = _Command(label, fn)
        self._queue.put(cmd)
        return cmd.future

    def call(self, label: str, fn: Callable[[], Any], timeout: float | None = 60.0) -> Any:
        """Submit and wait for the result (re-raises the command's exception)."""
        return self.submit(label, fn).result(timeout)

    def on_worker_thread(self) -> bool:
        return threading.current_thread() is self._thread

    def stop(self, timeout: float = 10.0) -> None:
        """Finish the queued commands, then end the thread."""
        self._queue.put(None)
        if self._thread.is_alive() and not self.on_worker_thread():
            self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            try:
                cmd = self._queue.get(timeout=self._idle_period if self._idle else None)
            except queue.Empty:
                self._run_idle()
                continue
            if cmd is None:
                return
            self._execute(cmd)

    def _execute(self, cmd: _Command) -> None:
        if not cmd.future.set_running_or_notify_cancel():
            return
        self._busy.set()
        self.current = cmd.label
        try:
            result = cmd.fn()
        except BaseException as exc:  # the worker must survive every command
            cmd.future.set_exception(exc)
            if not isinstance(exc, LasercalError):
                traceback.print_exception(exc)
            self._safe_notify(cmd.label, operator_message(exc), "error")
        else:
            cmd.future.set_result(result)
        finally:
            self.current = None
            self._busy.clear()

    def _run_idle(self) -> None:
        assert self._idle is not None
        try:
            self._idle()
        except BaseException as exc:
            message = operator_message(exc)
            if message != self._last_idle_error:  # one notification per distinct fault
                self._last_idle_error = message
                self._safe_notify("live view", message, "warning")
        else:
            self._last_idle_error = ""

    def _safe_notify(self, title: str, body: str, level: str) -> None:
        try:
            self._notify(title, body, level)
        except Exception:
            traceback.print_exc()
