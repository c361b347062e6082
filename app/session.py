"""The session file: one SQLite database (WAL) per calibration session, crash-safe.

Tables:

- ``meta(key, value)``: ``schema``, ``created`` (UTC ISO time), ``software`` (lasercal and
  Python versions, JSON), ``drivers`` (device name -> driver and version, JSON), ``workcell``
  (the workcell TOML text), ``noise`` (noise model, JSON), ``grid`` (grid name), ``settings``
  (runner settings, JSON) and any other key a caller adds.
- ``poses(pose_index, x_o, y_o, z_o, theta_deg)``: the planned grid.
- ``samples``: one row per measured pose (its readings averaged): commanded pose ``cmd_*``,
  pose read back ``x_o, y_o, z_o, theta_deg``, ``d``, ``x_p``, ``y_p``, ``quality``, their
  spreads, ``status`` ``ok``/``skipped`` with ``reason``, ``attempts``, ``timestamp``. At most
  one row per pose (a UNIQUE constraint), so nothing is ever stored twice.
- ``events(timestamp, kind, message)``: pauses, driver errors, resumes.

Each sample is committed (``synchronous=FULL``) the moment it is stored, so a ``kill -9``
loses at most the sample in flight. Opening checks the file (``PRAGMA integrity_check``); a
damaged file raises :class:`SessionDamaged` naming it, after copying whatever rows can still be
read into ``<name>.recovered.db`` next to it.
"""

from __future__ import annotations

import json
import math
import shutil
import sqlite3
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from calib_core.errors import InputError
from calib_core.grid import PoseGrid

SCHEMA = "lasercal-session/1"
SQLITE_MAGIC = b"SQLite format 3\x00"
#: Columns of the solve CSV format that :func:`read_session_frame` returns, in order.
FRAME_COLUMNS = ("x_o", "y_o", "z_o", "theta_deg", "d", "x_p", "y_p", "pose_index")

_DDL = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS poses (
    pose_index INTEGER PRIMARY KEY,
    x_o REAL NOT NULL, y_o REAL NOT NULL, z_o REAL NOT NULL, theta_deg REAL NOT NULL);
CREATE TABLE IF NOT EXISTS samples (
    sample_id INTEGER PRIMARY KEY,
    pose_index INTEGER NOT NULL UNIQUE,
    status TEXT NOT NULL CHECK (status IN ('ok', 'skipped')),
    reason TEXT NOT NULL DEFAULT '',
    cmd_x REAL NOT NULL, cmd_y REAL NOT NULL, cmd_z REAL NOT NULL, cmd_theta_deg REAL NOT NULL,
    x_o REAL, y_o REAL, z_o REAL, theta_deg REAL,
    d REAL, x_p REAL, y_p REAL, quality REAL,
    d_std REAL, x_p_std REAL, y_p_std REAL,
    n_readings INTEGER NOT NULL DEFAULT 0,
    attempts INTEGER NOT NULL DEFAULT 1,
    timestamp REAL NOT NULL);
CREATE TABLE IF NOT EXISTS events (
    event_id INTEGER PRIMARY KEY, timestamp REAL NOT NULL, kind TEXT NOT NULL,
    message TEXT NOT NULL);
"""
_SAMPLE_COLUMNS = (
    "pose_index", "status", "reason", "cmd_x", "cmd_y", "cmd_z", "cmd_theta_deg",
    "x_o", "y_o", "z_o", "theta_deg", "d", "x_p", "y_p", "quality", "d_std", "x_p_std",
    "y_p_std", "n_readings", "attempts", "timestamp",
)
_TABLE_COLUMNS: dict[str, tuple[str, ...]] = {
    "meta": ("key", "value"),
    "poses": ("pose_index", "x_o", "y_o", "z_o", "theta_deg"),
    "samples": _SAMPLE_COLUMNS,
    "events": ("timestamp", "kind", "message"),
}


class SessionDamaged(InputError):
    """The session file is corrupted or truncated; ``recovered`` is the salvage file, if any."""

    def __init__(self, message: str, recovered: Path | None = None) -> None:
        super().__init__(message)
        self.recovered = recovered


Pose4 = tuple[float, float, float, float]


@dataclass(frozen=True)
class Sample:
    """One stored pose measurement (readings averaged); mm and degrees, None where unknown."""

    pose_index: int
    commanded: Pose4
    readback: Pose4 | None
    d: float | None
    x_p: float | None
    y_p: float | None
    quality: float | None = None
    status: str = "ok"
    reason: str = ""
    d_std: float | None = None
    x_p_std: float | None = None
    y_p_std: float | None = None
    n_readings: int = 0
    attempts: int = 1
    timestamp: float = field(default_factory=time.time)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def row(self) -> tuple[Any, ...]:
        """Values in the order of the ``samples`` columns (NaN stored as NULL)."""
        rb = self.readback if self.readback is not None else (None,) * 4
        return (int(self.pose_index), self.status, self.reason, *map(float, self.commanded),
                *(_num(v) for v in rb), _num(self.d), _num(self.x_p), _num(self.y_p),
                _num(self.quality), _num(self.d_std), _num(self.x_p_std), _num(self.y_p_std),
                int(self.n_readings), int(self.attempts), float(self.timestamp))

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Sample:
        rb = tuple(row[k] for k in ("x_o", "y_o", "z_o", "theta_deg"))
        return cls(
            pose_index=int(row["pose_index"]),
            commanded=tuple(float(row[k]) for k in ("cmd_x", "cmd_y", "cmd_z",
                                                    "cmd_theta_deg")),  # type: ignore[arg-type]
            readback=None if any(v is None for v in rb) else tuple(map(float, rb)),  # type: ignore[arg-type]
            d=row["d"], x_p=row["x_p"], y_p=row["y_p"], quality=row["quality"],
            status=row["status"], reason=row["reason"], d_std=row["d_std"],
            x_p_std=row["x_p_std"], y_p_std=row["y_p_std"], n_readings=row["n_readings"],
            attempts=row["attempts"], timestamp=row["timestamp"])


def _num(value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def software_versions() -> dict[str, str]:
    """Versions of lasercal, Python, SQLite, numpy."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        own = version("lasercal")
    except PackageNotFoundError:
        own = "unknown"
    return {"lasercal": own, "python": sys.version.split()[0], "sqlite": sqlite3.sqlite_version,
            "numpy": np.__version__}


def _connect(path: Path) -> sqlite3.Connection:
    """Open an existing file (read-write if the OS allows, else read-only; never create)."""
    uri = f"{path.resolve().as_uri()}?mode=rw"
    conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False,
                           timeout=10.0)
    conn.row_factory = sqlite3.Row
    return conn


#: Page sizes SQLite allows, the default (4096, what sessions use) first.
PAGE_SIZES = (4096, 1024, 2048, 8192, 16384, 32768, 65536, 512)


def _body_page_sizes(size: int, page1: bytes) -> list[int]:
    """Page sizes for which a file without its SQLite header still looks like a database.

    Page 1's b-tree header follows the 100-byte file header: its type byte is 0x0D (a table
    leaf) or 0x05 (interior) and the file is a whole number of pages.
    """
    if len(page1) <= 100 or page1[100] not in (0x05, 0x0D):
        return []
    return [ps for ps in PAGE_SIZES if size >= 2 * ps and size % ps == 0]


def _check_header(path: Path, recover: bool = True) -> None:
    """Refuse a missing, empty or non-SQLite file (SQLite itself would open it as empty);
    a database whose 100-byte header was overwritten is reported damaged (and salvaged)."""
    try:
        if path.is_dir():
            raise InputError(f"{path}: is a directory, expected a session file (.db)")
        size = path.stat().st_size
        with path.open("rb") as fh:
            head = fh.read(112)
    except FileNotFoundError:
        raise InputError(f"{path}: no such session file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if size == 0:
        raise InputError(f"{path}: empty file, not a lasercal session")
    if not head.startswith(SQLITE_MAGIC):
        if _body_page_sizes(size, head):
            raise _damaged(path, "the SQLite file header is overwritten", recover)
        raise InputError(f"{path}: not a lasercal session file (not an SQLite database)")
    if size < 512 or len(head) < 100:
        raise SessionDamaged(f"{path}: session file is truncated ({size} bytes)")


class Session:
    """An open session file; every method is thread-safe (one connection behind a lock)."""

    def __init__(self, path: Path, conn: sqlite3.Connection, readonly: bool) -> None:
        self.path = path
        self.readonly = readonly
        self._conn = conn
        self._lock = threading.RLock()

    # ---- opening -------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, grid: PoseGrid, *, workcell_toml: str = "",
               noise: Mapping[str, float] | None = None,
               drivers: Mapping[str, str] | None = None,
               settings: Mapping[str, Any] | None = None,
               extra_meta: Mapping[str, str] | None = None) -> Session:
        """Create a new session file holding ``grid``; refuse an existing file."""
        path = Path(path)
        if path.exists() or Path(f"{path}-wal").exists():
            raise InputError(f"{path}: session file already exists; continue it with --resume "
                             "or choose another file")
        if not path.parent.is_dir():
            raise InputError(f"{path}: directory {path.parent} does not exist")
        meta = {
            **dict(extra_meta or {}),
            "schema": SCHEMA,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "software": json.dumps(software_versions()),
            "drivers": json.dumps(dict(drivers or {})),
            "workcell": workcell_toml,
            "noise": json.dumps(dict(noise or {})),
            "grid": grid.name,
            "settings": json.dumps(dict(settings or {})),
        }
        try:
            conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False,
                                   timeout=10.0)
        except sqlite3.Error as exc:
            raise InputError(f"{path}: cannot create the session file ({exc})") from None
        conn.row_factory = sqlite3.Row
        session = cls(path, conn, readonly=False)
        try:
            session._pragmas()
            with session._transaction() as c:  # all or nothing: tables, meta, grid
                for statement in _DDL.split(";"):
                    if statement.strip():
                        c.execute(statement)
                c.executemany("INSERT INTO meta(key, value) VALUES (?, ?)", meta.items())
                c.executemany("INSERT INTO poses VALUES (?, ?, ?, ?, ?)",
                              [(i, *grid.pose(i)) for i in range(len(grid))])
        except BaseException as exc:
            conn.close()
            for suffix in ("", "-wal", "-shm"):
                Path(f"{path}{suffix}").unlink(missing_ok=True)
            if isinstance(exc, sqlite3.Error):
                raise InputError(f"{path}: cannot create the session file ({exc})") from None
            raise
        return session

    @classmethod
    def open(cls, path: str | Path, *, readonly: bool = False, recover: bool = True) -> Session:
        """Open and check an existing session file.

        Raises :class:`SessionDamaged` for a corrupted or truncated file, after salvaging what
        can be read into ``<name>.recovered.db`` (when ``recover``).
        """
        path = Path(path)
        _check_header(path, recover)
        conn: sqlite3.Connection | None = None
        try:
            conn = _connect(path)
            conn.execute("PRAGMA busy_timeout = 10000")
            problems = [r[0] for r in conn.execute("PRAGMA integrity_check(20)")]
            if problems != ["ok"]:
                raise sqlite3.DatabaseError("integrity check: " + "; ".join(
                    p for p in problems[:4] if not p.startswith("***")))
            names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master "
                                                "WHERE type = 'table'")}
        except sqlite3.DatabaseError as exc:
            if conn is not None:
                conn.close()
            raise _damaged(path, str(exc), recover) from None
        missing = sorted(set(_TABLE_COLUMNS) - names)
        if missing:
            conn.close()
            raise InputError(f"{path}: not a lasercal session file (no table(s) "
                             f"{', '.join(missing)})")
        session = cls(path, conn, readonly)
        schema = session.meta.get("schema", "")
        if schema != SCHEMA:
            conn.close()
            raise InputError(f"{path}: unsupported session schema {schema!r} "
                             f"(this lasercal reads {SCHEMA})")
        if not readonly:
            try:
                session._configure()
            except sqlite3.OperationalError as exc:
                conn.close()
                raise InputError(f"{path}: cannot write the session file ({exc})") from None
        return session

    def _pragmas(self) -> None:
        """WAL journal, a full sync at every commit (a committed sample survives a power cut)."""
        with self._lock:
            self._conn.execute("PRAGMA journal_mode = WAL")
            self._conn.execute("PRAGMA synchronous = FULL")
            self._conn.execute("PRAGMA busy_timeout = 10000")

    def _configure(self) -> None:
        self._pragmas()
        with self._lock:
            self._conn.executescript(_DDL)

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        if self.readonly:
            raise InputError(f"{self.path}: session opened read-only")
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._conn.execute("COMMIT")

    def _query(self, sql: str, params: tuple[Any, ...] = ()) -> list[sqlite3.Row]:
        try:
            with self._lock:
                return self._conn.execute(sql, params).fetchall()
        except sqlite3.DatabaseError as exc:
            raise SessionDamaged(f"{self.path}: cannot read the session file ({exc})") from None

    # ---- contents ------------------------------------------------------------------------
    @property
    def meta(self) -> dict[str, str]:
        return {r["key"]: r["value"] for r in self._query("SELECT key, value FROM meta")}

    def meta_json(self, key: str) -> Any:
        """``meta[key]`` decoded from JSON ({} when absent or unreadable)."""
        try:
            return json.loads(self.meta.get(key, "{}"))
        except json.JSONDecodeError:
            return {}

    def set_meta(self, key: str, value: str) -> None:
        with self._transaction() as c:
            c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)", (key, value))

    @property
    def grid(self) -> PoseGrid:
        rows = self._query("SELECT x_o, y_o, z_o, theta_deg FROM poses ORDER BY pose_index")
        return PoseGrid(np.array([tuple(r) for r in rows], dtype=float).reshape(-1, 4),
                        self.meta.get("grid", "session"))

    def n_poses(self) -> int:
        return int(self._query("SELECT count(*) FROM poses")[0][0])

    def stored_indices(self, status: str | None = None) -> set[int]:
        """Pose indices with a stored sample (of ``status`` if given)."""
        if status is None:
            rows = self._query("SELECT pose_index FROM samples")
        else:
            rows = self._query("SELECT pose_index FROM samples WHERE status = ?", (status,))
        return {int(r[0]) for r in rows}

    def pending_indices(self, *, retry_skipped: bool = False) -> list[int]:
        """Planned poses without a stored sample (also the skipped ones if ``retry_skipped``)."""
        done = self.stored_indices("ok" if retry_skipped else None)
        return [i for i in range(self.n_poses()) if i not in done]

    def add_sample(self, sample: Sample) -> int:
        """Store and commit one sample; a skipped sample of the same pose is replaced.

        Raises :class:`InputError` if the pose is unknown or already has an ok sample.
        """
        if not 0 <= sample.pose_index < self.n_poses():
            raise InputError(f"{self.path}: pose index {sample.pose_index} is not in the grid")
        placeholders = ", ".join("?" * len(_SAMPLE_COLUMNS))
        try:
            with self._transaction() as c:
                c.execute("DELETE FROM samples WHERE pose_index = ? AND status = 'skipped'",
                          (sample.pose_index,))
                cur = c.execute(f"INSERT INTO samples ({', '.join(_SAMPLE_COLUMNS)}) "
                                f"VALUES ({placeholders})", sample.row())
                return int(cur.lastrowid or 0)
        except sqlite3.IntegrityError:
            raise InputError(f"{self.path}: pose {sample.pose_index} already has a stored "
                             "sample (is another acquisition writing this session?)") from None

    def samples(self) -> list[Sample]:
        """All stored samples, in pose order."""
        return [Sample.from_row(r) for r in self._query(
            f"SELECT {', '.join(_SAMPLE_COLUMNS)} FROM samples ORDER BY pose_index")]

    def samples_frame(self) -> pd.DataFrame:
        """All stored samples as a table (the ``samples`` columns), in pose order."""
        rows = self._query(f"SELECT {', '.join(_SAMPLE_COLUMNS)} FROM samples "
                           "ORDER BY pose_index")
        return pd.DataFrame([tuple(r) for r in rows], columns=list(_SAMPLE_COLUMNS))

    def log_event(self, kind: str, message: str) -> None:
        with self._transaction() as c:
            c.execute("INSERT INTO events(timestamp, kind, message) VALUES (?, ?, ?)",
                      (time.time(), kind, message))

    def events(self) -> list[tuple[float, str, str]]:
        return [(r[0], r[1], r[2]) for r in self._query(
            "SELECT timestamp, kind, message FROM events ORDER BY event_id")]

    def frame(self) -> pd.DataFrame:
        """The ok samples in the solve CSV format (see :func:`read_session_frame`)."""
        return _solve_frame(self.samples_frame())


def _solve_frame(samples: pd.DataFrame) -> pd.DataFrame:
    ok = samples[samples["status"] == "ok"].sort_values("pose_index")
    out = pd.DataFrame({
        "x_o": ok["x_o"].fillna(ok["cmd_x"]), "y_o": ok["y_o"].fillna(ok["cmd_y"]),
        "z_o": ok["z_o"].fillna(ok["cmd_z"]),
        "theta_deg": ok["theta_deg"].fillna(ok["cmd_theta_deg"]),
        "d": ok["d"], "x_p": ok["x_p"], "y_p": ok["y_p"], "pose_index": ok["pose_index"],
    })
    out = out.astype({c: float for c in FRAME_COLUMNS[:-1]} | {"pose_index": int})
    return out.reset_index(drop=True)


def read_session_frame(path: str | Path) -> pd.DataFrame:
    """The ok samples of a session file in the solve CSV format, in pose order.

    Columns ``x_o, y_o, z_o, theta_deg`` (the pose read back from the robot, the commanded
    one where none was read), ``d, x_p, y_p`` and ``pose_index``. Raises :class:`InputError`
    naming the file if it is missing, not a session or damaged.
    """
    with Session.open(path, readonly=True) as session:
        return session.frame()


# ---- recovery ------------------------------------------------------------------------------
def _recovered_path(path: Path) -> Path:
    base = path.with_name(f"{path.stem}.recovered.db")
    k = 2
    while base.exists():
        base = path.with_name(f"{path.stem}.recovered-{k}.db")
        k += 1
    return base


def _damaged(path: Path, detail: str, recover: bool) -> SessionDamaged:
    detail = detail.splitlines()[0] if detail else "unknown error"
    if not recover:
        return SessionDamaged(f"{path}: session file is damaged ({detail})")
    out = _recovered_path(path)
    try:
        counts = recover_session(path, out)
    except (OSError, sqlite3.Error, InputError) as exc:
        return SessionDamaged(f"{path}: session file is damaged ({detail}); recovery failed "
                              f"({exc})")
    if counts["samples"] == 0 and counts["poses"] == 0:
        out.unlink(missing_ok=True)
        Path(f"{out}-wal").unlink(missing_ok=True)
        Path(f"{out}-shm").unlink(missing_ok=True)
        return SessionDamaged(f"{path}: session file is damaged ({detail}); no pose or sample "
                              "could be recovered")
    return SessionDamaged(
        f"{path}: session file is damaged ({detail}); recovered {counts['samples']} sample(s) "
        f"({counts['ok']} ok) of {counts['poses']} planned pose(s) into {out}; "
        "check it, then use that file (e.g. --session ... --resume)", out)


def _salvage(conn: sqlite3.Connection, table: str, columns: tuple[str, ...],
             probe_limit: int) -> list[tuple[Any, ...]]:
    """Rows of ``table`` that can still be read: a full scan, else a probe rowid by rowid."""
    sql = f"SELECT {', '.join(columns)} FROM {table}"
    try:
        return [tuple(r) for r in conn.execute(sql + " ORDER BY rowid")]
    except sqlite3.DatabaseError:
        pass
    try:
        top = conn.execute(f"SELECT max(rowid) FROM {table}").fetchone()[0] or 0
    except sqlite3.DatabaseError:
        top = 0
    rows = []
    for rowid in range(1, max(int(top), probe_limit) + 1):
        try:
            row = conn.execute(sql + " WHERE rowid = ?", (rowid,)).fetchone()
        except sqlite3.DatabaseError:
            continue
        if row is not None:
            rows.append(tuple(row))
    return rows


def _salvage_all(copy: Path) -> dict[str, list[tuple[Any, ...]]]:
    """Readable rows of every session table of ``copy`` (empty lists when unreadable)."""
    src = sqlite3.connect(copy, isolation_level=None)
    try:
        src.execute("PRAGMA cell_size_check = ON")
        src.execute("PRAGMA writable_schema = ON")  # read a truncated file up to its end
        return {t: _salvage(src, t, cols, 2000 if t != "meta" else 100)
                for t, cols in _TABLE_COLUMNS.items()}
    except sqlite3.DatabaseError:
        return {t: [] for t in _TABLE_COLUMNS}
    finally:
        src.close()


def _rebuild_header(copy: Path, page_size: int, tmp: Path) -> None:
    """Write a plausible 100-byte SQLite header (``page_size``, UTF-8, WAL, no free list) over
    ``copy``'s, taken from a fresh database; the page count is the file's."""
    template = tmp / f"template-{page_size}.db"
    template.unlink(missing_ok=True)
    conn = sqlite3.connect(template, isolation_level=None)
    try:
        conn.execute(f"PRAGMA page_size = {page_size}")
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("CREATE TABLE t(x)")
    finally:
        conn.close()
    header = bytearray(template.read_bytes()[:100])
    pages = copy.stat().st_size // page_size
    header[28:32] = pages.to_bytes(4, "big")
    header[92:96] = header[24:28]  # the page count above is valid
    with copy.open("r+b") as fh:
        fh.write(bytes(header))


def recover_session(path: str | Path, out: str | Path) -> dict[str, int]:
    """Copy every readable row of a damaged session file into a new session file ``out``.

    Works on a copy (the damaged file and its ``-wal`` are never modified). Returns counts
    ``{"meta", "poses", "samples", "ok", "events"}``. Planned poses that could not be read
    are rebuilt from the commanded pose of their samples.
    """
    path, out = Path(path), Path(out)
    if out.exists():
        raise InputError(f"{out}: already exists")
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "damaged.db"
        shutil.copyfile(path, copy)
        for suffix in ("-wal",):
            if Path(f"{path}{suffix}").exists():
                shutil.copyfile(f"{path}{suffix}", f"{copy}{suffix}")
        got = _salvage_all(copy)
        with copy.open("rb") as fh:
            page1 = fh.read(112)
        if not (got["poses"] or got["samples"]):  # header overwritten: try each page size
            for page_size in _body_page_sizes(copy.stat().st_size, page1):
                _rebuild_header(copy, page_size, Path(tmp))
                got = _salvage_all(copy)
                if got["poses"] or got["samples"]:
                    break
    samples: dict[int, tuple[Any, ...]] = {}
    for row in got["samples"]:  # keep one row per pose, preferring an ok one
        if isinstance(row[0], int) and row[1] in ("ok", "skipped") and (
                row[0] not in samples or row[1] == "ok"):
            samples[row[0]] = row
    poses = {r[0]: r for r in got["poses"] if isinstance(r[0], int)}
    for idx, row in samples.items():
        poses.setdefault(idx, (idx, *row[3:7]))
    meta = {str(k): str(v) for k, v in got["meta"]}
    meta["schema"] = SCHEMA
    meta["recovered_from"] = str(path)
    conn = sqlite3.connect(out, isolation_level=None)
    try:
        conn.execute("PRAGMA journal_mode = WAL")
        conn.executescript(_DDL)
        conn.execute("BEGIN")
        conn.executemany("INSERT INTO meta VALUES (?, ?)", meta.items())
        conn.executemany("INSERT INTO poses VALUES (?, ?, ?, ?, ?)",
                         [poses[i] for i in sorted(poses)])
        conn.executemany(f"INSERT INTO samples ({', '.join(_SAMPLE_COLUMNS)}) VALUES "
                         f"({', '.join('?' * len(_SAMPLE_COLUMNS))})",
                         [samples[i] for i in sorted(samples)])
        conn.executemany("INSERT INTO events(timestamp, kind, message) VALUES (?, ?, ?)",
                         got["events"])
        conn.execute("INSERT INTO events(timestamp, kind, message) VALUES (?, ?, ?)",
                     (time.time(), "recovered", f"rows salvaged from damaged file {path}"))
        conn.execute("COMMIT")
    finally:
        conn.close()
    return {"meta": len(got["meta"]), "poses": len(poses), "samples": len(samples),
            "ok": sum(r[1] == "ok" for r in samples.values()), "events": len(got["events"])}
