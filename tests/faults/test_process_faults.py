"""Process faults: ``kill -9`` of the dashboard server mid-acquisition, and damaged session files.

The server is the real ``lasercal serve --session X.db`` process, driven the way an operator
does (headless Chromium clicks **Start acquisition**); it is killed with SIGKILL while samples
are being stored, restarted with the same ``--session`` and the acquisition continued: every
sample stored before the kill is still there unchanged, none is measured twice.

Damaged files (truncated, header overwritten, bytes flipped in a page) are detected by
``lasercal solve X.db`` and ``lasercal export X.db``: exit 2, one ``error:`` line that says what
was recovered and where; the salvage file holds exactly the readable samples.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import signal
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.acquisition import Runner, RunnerConfig
from app.cli import main
from app.session import Sample, Session
from calib_core.grid import paper_grid
from drivers.sim.devices import SimCameraDirect, SimRobot, SimSensor
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld
from tests.e2e.conftest import CHROMIUM, CHROMIUM_ARGS, start_serve, stop_serve


def _rows(db: Path) -> list[tuple]:
    """(pose_index, status, d, x_p, y_p, timestamp) of every row, read by another process's
    way in (a plain read-only SQLite connection, as after a crash)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
    try:
        return [tuple(r) for r in con.execute(
            "SELECT pose_index, status, d, x_p, y_p, timestamp FROM samples ORDER BY pose_index")]
    except sqlite3.OperationalError:  # not created yet
        return []
    finally:
        con.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _start_acquisition(browser, url: str):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.set_default_timeout(60_000)
    page.goto(url)
    page.get_by_text("Connected", exact=False).first.wait_for()
    page.get_by_role("tab", name="Acquire").click()
    page.get_by_role("button", name="Start acquisition").click()
    return page


def test_serve_killed_mid_acquisition_restarts_and_continues(
        tmp_path: Path, browser) -> None:
    proc, served = start_serve(tmp_path)
    db = served.session
    try:
        page = _start_acquisition(browser, served.url)
        deadline = time.monotonic() + 60
        while len(_rows(db)) < 8 and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        page.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    before = _rows(db)
    assert 8 <= len(before) < 42, len(before)                 # killed mid-acquisition
    assert [r[0] for r in before] == list(range(len(before)))

    proc, served = start_serve(tmp_path)                       # same --session file
    try:
        assert served.session == db
        page = _start_acquisition(browser, served.url)
        page.get_by_text(re.compile(r"finished: 42 / 42 poses")).wait_for(timeout=120_000)
        page.close()
    finally:
        assert stop_serve(proc) == 0, "\n".join(served.output)
    after = _rows(db)
    assert [r[0] for r in after] == list(range(42))            # none lost, none twice
    assert after[:len(before)] == before                       # stored ones untouched
    assert min(r[5] for r in after[len(before):]) > max(r[5] for r in before)
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()
    print(f"\nserve killed with {len(before)} of 42 samples stored; after the restart 42, "
          "the first ones unchanged")


# ---- damaged session files --------------------------------------------------------------
def _cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def complete_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[int, Sample]]:
    """A full 42-pose simulated session file (closed, checkpointed) and its samples."""
    path = tmp_path_factory.mktemp("complete") / "full.db"
    world = SimWorld(load_workcell(), seed=8)
    with Session.create(path, paper_grid(), workcell_toml="[cell]\n") as session:
        Runner(session, SimRobot(world, move_time_s=0.0), SimSensor(world),
               SimCameraDirect(world), RunnerConfig(samples_per_pose=1)).run()
        samples = {s.pose_index: s for s in session.samples()}
    assert len(samples) == 42
    return path, samples


def _samples_page(path: Path) -> int:
    """Page number (1-based) of the last leaf page of the samples table."""
    con = sqlite3.connect(path)
    pages = [r[0] for r in con.execute(
        "SELECT pageno FROM dbstat WHERE name = 'samples' AND pagetype = 'leaf'")]
    con.close()
    assert pages
    return max(pages)


def _truncate(path: Path) -> None:
    with path.open("r+b") as fh:
        fh.truncate(path.stat().st_size - 4096)


def _flip(path: Path) -> None:
    page = _samples_page(path)
    with path.open("r+b") as fh:
        fh.seek((page - 1) * 4096 + 8)
        data = bytearray(fh.read(64))
        fh.seek((page - 1) * 4096 + 8)
        fh.write(bytes(b ^ 0xA5 for b in data))               # the cell pointer array


def _header(path: Path) -> None:
    with path.open("r+b") as fh:
        fh.write(bytes(np.random.default_rng(1).integers(0, 256, 100, dtype=np.uint8)))


@pytest.mark.parametrize("command", ["solve", "export"])
@pytest.mark.parametrize("damage", [_truncate, _flip, _header], ids=["truncate", "flip", "header"])
def test_damaged_session_is_detected_and_salvaged(
        tmp_path: Path, complete_session, damage, command: str) -> None:
    source, original = complete_session
    path = tmp_path / "s.db"
    path.write_bytes(source.read_bytes())
    damage(path)
    out_csv = tmp_path / "out.csv"
    args = [command, str(path)] + (["--csv", str(out_csv)] if command == "export" else [])
    code, out, err = _cli(*args)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: session file is damaged")
    assert not out_csv.exists()                                # nothing half-written
    recovered = tmp_path / "s.recovered.db"
    m = re.search(r"recovered (\d+) sample\(s\) \((\d+) ok\) of 42 planned pose\(s\) into (\S+);",
                  lines[0])
    assert m is not None, lines[0]
    assert Path(m.group(3)) == recovered
    with Session.open(recovered, readonly=True) as rec:
        got = rec.samples()
        assert len(got) == int(m.group(1)) > 0
        assert all(s == original[s.pose_index] for s in got)  # salvaged rows are exact
        assert rec.n_poses() == 42
    code, out, err = _cli("solve", str(recovered), "--json")   # the salvage is usable
    assert code == 0, err


def test_damaged_page_size_field_is_salvaged(tmp_path: Path, complete_session) -> None:
    """Only the page-size bytes of the header are wrong: SQLite refuses the file; the salvage
    rebuilds the header and recovers every sample."""
    source, original = complete_session
    path = tmp_path / "p.db"
    path.write_bytes(source.read_bytes())
    with path.open("r+b") as fh:
        fh.seek(16)
        fh.write(b"\x00\x03")                                  # page size 3: invalid
    code, out, err = _cli("export", str(path), "--csv", "-")
    assert code == 2 and out == "" and "recovered 42 sample(s) (42 ok)" in err, err
    with Session.open(tmp_path / "p.recovered.db", readonly=True) as rec:
        assert {s.pose_index: s for s in rec.samples()} == original


@pytest.mark.parametrize("tear", ["truncate", "flip"])
def test_torn_wal_after_a_crash_loses_only_the_last_commits(tmp_path: Path, tear: str) -> None:
    """The files as a power cut leaves them: the main file and a write-ahead log whose tail
    is torn (cut mid-frame) or corrupted (a flipped byte half-way: the frame checksums fail).
    Opening gives a consistent prefix of the stored samples, each exactly as stored; resuming
    measures the rest, with no pose twice."""
    world = SimWorld(load_workcell(), seed=9)
    grid = paper_grid()
    live = tmp_path / "live.db"
    session = Session.create(live, grid)
    Runner(session, SimRobot(world, move_time_s=0.0), SimSensor(world), SimCameraDirect(world),
           RunnerConfig(samples_per_pose=1)).run()
    original = {s.pose_index: s for s in session.samples()}
    crash = tmp_path / "crash.db"                       # copy while the writer still runs
    crash.write_bytes(live.read_bytes())
    wal = Path(f"{live}-wal").read_bytes()
    assert len(wal) > 42 * 1000, "the samples must still be in the log"
    if tear == "truncate":
        wal = wal[:-100]
    else:
        middle = len(wal) // 2
        wal = wal[:middle] + bytes([wal[middle] ^ 0xFF]) + wal[middle + 1:]
    Path(f"{crash}-wal").write_bytes(wal)
    session.close()
    with Session.open(crash) as s:
        kept = s.samples()
        assert [x.pose_index for x in kept] == list(range(len(kept)))     # a prefix
        assert all(x == original[x.pose_index] for x in kept)
        assert (len(kept) in (40, 41)) if tear == "truncate" else (0 < len(kept) < 42)
        Runner(s, SimRobot(world, move_time_s=0.0), SimSensor(world), SimCameraDirect(world),
               RunnerConfig(samples_per_pose=1)).run()
        assert sorted(x.pose_index for x in s.samples()) == list(range(42))
    print(f"\ntorn WAL ({tear}): {len(kept)} of 42 samples kept")
