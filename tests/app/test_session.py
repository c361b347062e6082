"""Session files: round trip, one row per pose, integrity check and recovery."""

from __future__ import annotations

import math
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from app.session import (
    FRAME_COLUMNS,
    Sample,
    Session,
    SessionDamaged,
    read_session_frame,
)
from calib_core.errors import InputError
from calib_core.grid import make_grid, paper_grid


def _sample(i: int, grid, status: str = "ok") -> Sample:
    cmd = grid.pose(i)
    rb = (cmd[0] + 1e-3, cmd[1] - 1e-3, cmd[2] + 2e-3, cmd[3] + 1e-3)
    if status != "ok":
        return Sample(i, cmd, rb, None, None, None, status=status, reason="sensor out-of-range",
                      timestamp=1e9 + i)
    return Sample(i, cmd, rb, 0.5 + i / 100, -6.0 + i / 7, 70.0 - i / 9, 0.9,
                  d_std=1e-3 * (i + 1), x_p_std=2e-3, y_p_std=3e-3, n_readings=3,
                  timestamp=1e9 + i)


def _filled(path: Path, n: int | None = None) -> Session:
    grid = paper_grid()
    s = Session.create(path, grid, workcell_toml="[cell]\nname = 'x'\n",
                       noise={"camera": 0.0031}, drivers={"robot": "sim"},
                       settings={"samples_per_pose": 3})
    for i in range(len(grid) if n is None else n):
        s.add_sample(_sample(i, grid, "skipped" if i == 5 else "ok"))
    return s


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    with _filled(path) as s:
        assert s.meta["schema"] == "lasercal-session/1"
        assert s.meta["workcell"] == "[cell]\nname = 'x'\n"
        assert s.meta_json("noise") == {"camera": 0.0031}
        assert s.meta_json("drivers") == {"robot": "sim"}
        assert "lasercal" in s.meta_json("software")
        np.testing.assert_array_equal(s.grid.poses, paper_grid().poses)
        assert s.pending_indices() == []
        assert s.pending_indices(retry_skipped=True) == [5]
    with Session.open(path, readonly=True) as s:
        back = s.samples()
        assert len(back) == 42
        assert back[7] == _sample(7, paper_grid())
        assert back[5].status == "skipped" and back[5].d is None
        assert back[5].reason == "sensor out-of-range"
    frame = read_session_frame(path)
    assert tuple(frame.columns) == FRAME_COLUMNS
    assert len(frame) == 41 and 5 not in set(frame["pose_index"])
    row = frame[frame["pose_index"] == 7].iloc[0]
    ref = _sample(7, paper_grid())
    assert row["x_o"] == ref.readback[0] and row["theta_deg"] == ref.readback[3]
    assert (row["d"], row["x_p"], row["y_p"]) == (ref.d, ref.x_p, ref.y_p)


def test_one_row_per_pose(tmp_path: Path) -> None:
    grid = make_grid([10], [0, 1], [0, 1])
    with Session.create(tmp_path / "s.db", grid) as s:
        s.add_sample(_sample(0, grid))
        with pytest.raises(InputError, match="pose 0 already has a stored sample"):
            s.add_sample(_sample(0, grid))
        s.add_sample(_sample(1, grid, "skipped"))
        s.add_sample(_sample(1, grid))  # a retry replaces the skipped sample
        assert [x.status for x in s.samples()] == ["ok", "ok"]
        with pytest.raises(InputError, match="not in the grid"):
            s.add_sample(Sample(9, (0, 0, 0, 0), None, 1, 1, 1))
        assert s.pending_indices() == [2, 3]
        s.log_event("pause", "hello")
        assert s.events()[-1][1:] == ("pause", "hello")


def test_refuses_existing_file_and_non_sessions(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    _filled(path, 3).close()
    with pytest.raises(InputError, match="already exists; continue it with --resume"):
        Session.create(path, paper_grid())
    with pytest.raises(InputError, match="no such session file"):
        read_session_frame(tmp_path / "none.db")
    (tmp_path / "empty.db").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty\.db: empty file"):
        read_session_frame(tmp_path / "empty.db")
    (tmp_path / "text.db").write_text("x_o,y_o\n1,2\n")
    with pytest.raises(InputError, match="not an SQLite database"):
        read_session_frame(tmp_path / "text.db")
    other = tmp_path / "other.db"
    sqlite3.connect(other).execute("CREATE TABLE t(x)").connection.commit()
    with pytest.raises(InputError, match="not a lasercal session file"):
        read_session_frame(other)


def test_committed_samples_visible_to_a_second_reader(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    writer = _filled(path, 10)  # still open: data live in the WAL
    assert Path(f"{path}-wal").exists()
    assert len(read_session_frame(path)) == 9
    writer.add_sample(_sample(10, paper_grid()))
    assert len(read_session_frame(path)) == 10
    writer.close()


def _page_of(path: Path, table: str) -> list[int]:
    con = sqlite3.connect(path)
    pages = [r[0] for r in con.execute(
        "SELECT pageno FROM dbstat WHERE name = ? AND pagetype = 'leaf' ORDER BY pageno",
        (table,))]
    con.close()
    return pages


def test_damaged_page_detected_and_rest_recovered(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    _filled(path).close()
    original = {s.pose_index: s for s in Session.open(path, readonly=True).samples()}
    leaves = _page_of(path, "samples")
    assert len(leaves) >= 2, "test needs samples over several pages"
    with path.open("r+b") as fh:  # overwrite the first samples leaf page with garbage
        fh.seek((leaves[0] - 1) * 4096)
        fh.write(bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)))
    with pytest.raises(SessionDamaged, match=r"s\.db: session file is damaged") as info:
        read_session_frame(path)
    out = info.value.recovered
    assert out == tmp_path / "s.recovered.db" and str(out) in str(info.value)
    with Session.open(out) as rec:
        got = rec.samples()
        assert 0 < len(got) < 42
        for s in got:  # everything recovered is exactly what was stored
            assert s == original[s.pose_index]
        np.testing.assert_array_equal(rec.grid.poses, paper_grid().poses)
        assert rec.meta["workcell"] == "[cell]\nname = 'x'\n"
        assert len(rec.pending_indices()) == 42 - len(got)


def test_truncated_file_detected_and_recovered(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    _filled(path).close()
    original = {s.pose_index: s for s in Session.open(path, readonly=True).samples()}
    size = path.stat().st_size
    shutil.copy(path, tmp_path / "t.db")
    with (tmp_path / "t.db").open("r+b") as fh:
        fh.truncate(size - 4096)  # the last page is lost
    with pytest.raises(SessionDamaged, match=r"t\.db: session file is damaged.*recovered \d+ "
                       r"sample\(s\) \(\d+ ok\) of 42 planned pose\(s\)"):
        Session.open(tmp_path / "t.db")
    with Session.open(tmp_path / "t.recovered.db") as rec:
        got = rec.samples()
        assert 0 < len(got) < 42
        assert all(s == original[s.pose_index] for s in got)
    with (tmp_path / "t.db").open("r+b") as fh:
        fh.truncate(3000)
    with pytest.raises(SessionDamaged, match="no pose or sample could be recovered"):
        read_session_frame(tmp_path / "t.db")


def test_nan_is_stored_as_null(tmp_path: Path) -> None:
    grid = make_grid([10], [0], [0])
    with Session.create(tmp_path / "s.db", grid) as s:
        s.add_sample(Sample(0, grid.pose(0), None, 1.0, 2.0, 3.0, float("nan")))
        back = s.samples()[0]
        assert back.quality is None and back.readback is None
        assert read_session_frame(tmp_path / "s.db")["x_o"].iloc[0] == 0.0  # commanded
        assert not math.isnan(back.d)


def test_failed_create_leaves_no_file(tmp_path: Path) -> None:
    class BadGrid(type(paper_grid())):
        def pose(self, index: int):
            if index == 2:
                raise InputError("grid pose 2: broken")
            return super().pose(index)

    path = tmp_path / "s.db"
    with pytest.raises(InputError, match="broken"):
        Session.create(path, BadGrid(paper_grid().poses, "bad"))
    assert list(tmp_path.iterdir()) == []
    Session.create(path, paper_grid(), extra_meta={"schema": "x", "operator": "ann"}).close()
    with Session.open(path) as s:
        assert s.meta["schema"] == "lasercal-session/1" and s.meta["operator"] == "ann"
