"""Pose-grid planning: the seed's default calibration grid and user-defined grids.

A grid is an ordered list of flange poses ``(x_o, y_o, z_o, theta_deg)`` in mm and degrees.
The seed's grid (``paper_grid``) is a 4 x 3 x-y grid over [-2, 2] x [-2, 2] mm (steps 4/3 and
2 mm) at the heights z = 15, 20, 25 mm with theta = 0 (36 poses), then 6 rotations
theta = -6 .. 6 deg (step 2.4 deg) at (0, 0, 20) (6 poses): 42 poses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.errors import InputError

GRID_COLUMNS = ("x_o", "y_o", "z_o", "theta_deg")
#: Largest grid accepted (poses): a bound against a wrong file or a typo in a spacing.
MAX_POSES = 100_000


@dataclass(frozen=True)
class PoseGrid:
    """Planned flange poses, ``poses`` (n, 4): columns x_o, y_o, z_o (mm), theta_deg (deg)."""

    poses: np.ndarray
    name: str = "custom"

    def __post_init__(self) -> None:
        arr = np.asarray(self.poses, dtype=float).reshape(-1, 4)
        if not np.all(np.isfinite(arr)):
            raise InputError(f"grid {self.name}: non-finite pose coordinate")
        arr.setflags(write=False)
        object.__setattr__(self, "poses", arr)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def pose(self, index: int) -> tuple[float, float, float, float]:
        """Pose ``index`` as ``(x_o, y_o, z_o, theta_deg)``."""
        x, y, z, t = (float(v) for v in self.poses[index])
        return x, y, z, t

    def to_frame(self) -> pd.DataFrame:
        """The grid as a table with columns x_o, y_o, z_o, theta_deg and pose_index."""
        frame = pd.DataFrame(self.poses, columns=list(GRID_COLUMNS))
        frame.insert(0, "pose_index", np.arange(len(self)))
        return frame

    def preview(self) -> str:
        """Text preview: a summary line, then one numbered line per pose."""
        z = np.unique(np.round(self.poses[:, 2], 6))
        t = np.unique(np.round(self.poses[:, 3], 6))
        lines = [
            f"grid {self.name}: {len(self)} poses; heights z = "
            f"{', '.join(f'{v:g}' for v in z)} mm; theta = {', '.join(f'{v:g}' for v in t)} deg",
            f"{'#':>4} {'x_o':>10} {'y_o':>10} {'z_o':>10} {'theta_deg':>10}",
        ]
        lines += [f"{i:>4} {x:>10.4f} {y:>10.4f} {zz:>10.4f} {th:>10.4f}"
                  for i, (x, y, zz, th) in enumerate(self.poses)]
        return "\n".join(lines)


def axis_values(lo: float, hi: float, *, step: float | None = None,
                count: int | None = None) -> np.ndarray:
    """Evenly spaced coordinates from ``lo`` to ``hi``: either ``count`` values (ends included)
    or ``lo + k step`` for k = 0, 1, ... while <= ``hi`` (within 1e-9 relative)."""
    if (step is None) == (count is None):
        raise InputError("give exactly one of step or count for a grid axis")
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
        raise InputError(f"grid axis range [{lo:g}, {hi:g}] is empty or not finite")
    if count is not None:
        if count < 1 or count > MAX_POSES:
            raise InputError(f"grid axis count must be in 1..{MAX_POSES}, got {count}")
        return np.array([0.5 * (lo + hi)]) if count == 1 else np.linspace(lo, hi, count)
    assert step is not None
    if not np.isfinite(step) or step <= 0:
        raise InputError(f"grid axis step must be > 0, got {step:g}")
    n = int(np.floor((hi - lo) / step * (1 + 1e-9) + 1e-9)) + 1
    if n > MAX_POSES:
        raise InputError(f"grid axis step {step:g} over [{lo:g}, {hi:g}] gives {n} values, "
                         f"more than {MAX_POSES}")
    return lo + step * np.arange(n)


def make_grid(heights: Sequence[float], xs: Sequence[float], ys: Sequence[float],
              angles_deg: Sequence[float] = (),
              rotation_at: tuple[float, float, float] | None = None,
              name: str = "custom") -> PoseGrid:
    """A translation grid (for z in heights, x in xs, y in ys; theta = 0), then the rotations.

    Order: z outermost, then x, then y. The rotations ``theta in angles_deg`` are made at
    ``rotation_at`` = (x, y, z), by default the x-y centre of the grid at the middle height.
    """
    heights, xs, ys = (np.asarray(v, dtype=float).ravel() for v in (heights, xs, ys))
    angles = np.asarray(angles_deg, dtype=float).ravel()
    for label, values in (("heights", heights), ("x", xs), ("y", ys), ("angles", angles)):
        if not np.all(np.isfinite(values)):
            raise InputError(f"grid {name}: non-finite value in {label}")
    n = heights.size * xs.size * ys.size + angles.size
    if n == 0:
        raise InputError(f"grid {name}: no poses (give heights, x and y values, or angles)")
    if n > MAX_POSES:
        raise InputError(f"grid {name}: {n} poses, more than {MAX_POSES}")
    zz, xx, yy = np.meshgrid(heights, xs, ys, indexing="ij")
    translation = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel(), np.zeros(zz.size)])
    if angles.size:
        if rotation_at is None:
            if xs.size == 0 or ys.size == 0 or heights.size == 0:
                raise InputError(f"grid {name}: give rotation_at for rotations without a grid")
            rotation_at = (0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max()),
                           float(np.sort(heights)[(heights.size - 1) // 2]))
        cx, cy, cz = (float(v) for v in rotation_at)
        rot = np.column_stack([np.full(angles.size, cx), np.full(angles.size, cy),
                               np.full(angles.size, cz), angles])
        translation = np.vstack([translation, rot])
    return PoseGrid(translation, name)


def paper_grid() -> PoseGrid:
    """The seed's default grid (42 poses; see the module docstring)."""
    return make_grid(heights=(15.0, 20.0, 25.0), xs=np.linspace(-2.0, 2.0, 4),
                     ys=np.linspace(-2.0, 2.0, 3), angles_deg=np.linspace(-6.0, 6.0, 6),
                     rotation_at=(0.0, 0.0, 20.0), name="paper")


def grid_from_frame(frame: pd.DataFrame, source: str) -> PoseGrid:
    """A grid from a table with columns x_o, y_o, z_o, theta_deg (other columns ignored)."""
    from calib_core.io import numeric_columns

    if len(frame) == 0:
        raise InputError(f"{source}: no poses in the grid file")
    if len(frame) > MAX_POSES:
        raise InputError(f"{source}: {len(frame)} poses, more than {MAX_POSES}")
    return PoseGrid(numeric_columns(frame, GRID_COLUMNS, source), Path(source).stem)


def load_grid(spec: str | Path) -> PoseGrid:
    """``'paper'`` for the seed's grid, else a CSV file with columns x_o, y_o, z_o, theta_deg."""
    if str(spec) == "paper":
        return paper_grid()
    from calib_core.io import read_table

    return grid_from_frame(read_table(spec), str(spec))
