"""A real ``lasercal serve`` process on a free port and Debian's headless Chromium."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
URL_LINE = re.compile(r"^(http://127\.0\.0\.1:(\d+)/\?token=([A-Za-z0-9_-]+))$")


@dataclass
class Served:
    url: str
    port: int
    token: str
    session: Path
    output: list[str]


def start_serve(workdir: Path, *extra: str) -> tuple[subprocess.Popen[str], Served]:
    session = workdir / "session.db"
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "serve", "--port", "0", "--session", str(session), *extra],
        cwd=workdir, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    output: list[str] = []
    assert proc.stdout is not None
    for line in proc.stdout:
        output.append(line.rstrip("\n"))
        m = URL_LINE.match(line.rstrip("\n"))
        if m:
            break
    else:
        raise AssertionError("lasercal serve printed no URL:\n" + "\n".join(output))
    stream = proc.stdout
    threading.Thread(target=lambda: [output.append(x.rstrip("\n")) for x in stream],
                     daemon=True).start()
    return proc, Served(m.group(1), int(m.group(2)), m.group(3), session, output)


def stop_serve(proc: subprocess.Popen[str]) -> int:
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait(timeout=5)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    proc, info = start_serve(tmp_path_factory.mktemp("serve"))
    yield info
    assert stop_serve(proc) == 0, "\n".join(info.output)


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()
