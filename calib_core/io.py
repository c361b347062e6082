"""Loading measurement files into validated arrays, with errors that name file, row and column.

File format: CSV with a header; lines starting ``#`` are comments; column order free; extra
columns kept. Required ``x_o, y_o, z_o, d`` (and ``x_p, y_p`` for calibration data) plus either
``theta_deg`` or ``qw, qx, qy, qz``. Rows are numbered from 0 in file order, comments and header
excluded.
"""

from __future__ import annotations

import io as _io
import json
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.errors import InputError
from calib_core.model import Poses, rotation_about_z, rotation_from_quaternion

POSITION_COLUMNS = ("x_o", "y_o", "z_o")
QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")
SPOT_COLUMNS = ("x_p", "y_p")
#: Largest file read (bytes): far above any real session, small enough to refuse a wrong file.
MAX_FILE_BYTES = 200 * 1024 * 1024


@dataclass(frozen=True)
class Dataset:
    """One measurement file as arrays: poses, readings ``d`` (n,), optional camera spots (n, 2)."""

    source: str
    poses: Poses
    d: np.ndarray
    spot_xy: np.ndarray | None
    rows: np.ndarray
    extra: pd.DataFrame = field(repr=False)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def orientation(self) -> str:
        """'theta' for a 4-dof (rotation about z) file, 'quaternion' for a 6-dof one."""
        return "theta" if self.poses.theta_deg is not None else "quaternion"

    def subset(self, idx: np.ndarray) -> Dataset:
        """The rows at ``idx`` (index array or boolean mask), row numbers kept."""
        spot = None if self.spot_xy is None else self.spot_xy[idx]
        extra = self.extra.iloc[np.arange(len(self))[idx]].reset_index(drop=True)
        return Dataset(self.source, self.poses.subset(idx), self.d[idx], spot, self.rows[idx],
                       extra)


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a CSV measurement file (``#`` lines skipped) as strings; errors name the file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise InputError(f"{path}: file is {size} bytes, larger than the "
                             f"{MAX_FILE_BYTES} byte limit")
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a CSV file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a UTF-8 text file") from None
    if "\x00" in text:
        raise InputError(f"{path}: binary data, expected a CSV text file")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{path}: empty file (no header)")
    try:
        frame = pd.read_csv(_io.StringIO("\n".join(lines)), dtype=str, skipinitialspace=True,
                            keep_default_na=False)
    except (pd.errors.ParserError, ValueError) as exc:
        raise InputError(f"{path}: not a valid CSV file ({str(exc).splitlines()[0]})") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    duplicated = sorted({c for c in frame.columns if list(frame.columns).count(c) > 1})
    if duplicated:
        raise InputError(f"{path}: duplicated column(s) {', '.join(duplicated)}")
    return frame


def numeric_columns(frame: pd.DataFrame, columns: Sequence[str], source: str) -> np.ndarray:
    """The named columns as a finite float array (n, k); errors name the row and column."""
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise InputError(f"{source}: missing column(s) {', '.join(missing)} "
                         f"(found: {', '.join(frame.columns) or 'none'})")
    out = np.empty((len(frame), len(columns)))
    for k, col in enumerate(columns):
        values = pd.to_numeric(frame[col].astype(str).str.strip(), errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            row = int(bad[0])
            raise InputError(f"{source}: row {row}, column {col}: "
                             f"{frame[col].iloc[row]!r} is not a finite number")
        out[:, k] = values
    return out


def poses_from_frame(frame: pd.DataFrame, source: str) -> Poses:
    """Flange poses from ``x_o, y_o, z_o`` plus ``theta_deg`` or ``qw, qx, qy, qz``."""
    position = numeric_columns(frame, POSITION_COLUMNS, source)
    has_q = all(c in frame.columns for c in QUATERNION_COLUMNS)
    if "theta_deg" in frame.columns and not has_q:
        theta = numeric_columns(frame, ("theta_deg",), source)[:, 0]
        return Poses(position, rotation_about_z(theta), theta)
    if not has_q:
        raise InputError(f"{source}: missing orientation: give column theta_deg (rotation about "
                         "z) or columns qw, qx, qy, qz (unit quaternion)")
    q = numeric_columns(frame, QUATERNION_COLUMNS, source)
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        raise InputError(f"{source}: row {int(bad[0])}: quaternion norm {norm[bad[0]]:.6f} "
                         "is not 1 (within 1e-3)")
    return Poses(position, rotation_from_quaternion(q / norm[:, None]), None)


def dataset_from_frame(frame: pd.DataFrame, source: str, *, need_spot: bool = True,
                       min_rows: int = 1) -> Dataset:
    """Validate a table of measurements and turn it into a :class:`Dataset`."""
    if len(frame) < min_rows:
        raise InputError(f"{source}: too few rows: {len(frame)} data row(s), "
                         f"at least {min_rows} needed")
    poses = poses_from_frame(frame, source)
    d = numeric_columns(frame, ("d",), source)[:, 0]
    spot = None
    if need_spot or all(c in frame.columns for c in SPOT_COLUMNS):
        spot = numeric_columns(frame, SPOT_COLUMNS, source)
    return Dataset(source, poses, d, spot, np.arange(len(frame)), frame.reset_index(drop=True))


def load_dataset(path: str | Path, *, need_spot: bool = True, min_rows: int = 1) -> Dataset:
    """Read and validate a measurement CSV file."""
    return dataset_from_frame(read_table(path), str(path), need_spot=need_spot,
                              min_rows=min_rows)


def load_toml(path: str | Path | None, default: str | None = None, what: str = "file"
              ) -> tuple[dict[str, object], str]:
    """Read a TOML file, or ``static_data/<default>`` when ``path`` is None.

    Returns the document and its name for messages; errors name the file (``what`` says what
    kind of file was expected, e.g. "workcell file").
    """
    if path is None:
        if default is None:
            raise InputError(f"no {what} given")
        source, read = f"static_data/{default}", resources.files("static_data").joinpath(default)
    else:
        source, read = str(path), Path(path)
    try:
        text = read.read_bytes().decode("utf-8")
        return tomllib.loads(text), source
    except FileNotFoundError:
        raise InputError(f"{source}: no such {what}") from None
    except IsADirectoryError:
        raise InputError(f"{source}: is a directory, expected a {what}") from None
    except OSError as exc:
        raise InputError(f"{source}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(f"{source}: not a UTF-8 text file") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({exc})") from None


def load_json_object(path: str | Path) -> dict[str, object]:
    """Read a JSON file holding one object; errors name the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object")
    return data
