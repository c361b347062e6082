"""Pose grids: the seed's 42-pose grid, user grids, grid files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib_core.errors import InputError
from calib_core.grid import axis_values, load_grid, make_grid, paper_grid

EXAMPLE = Path(__file__).resolve().parents[2] / "static_data" / "example_paper_grid.csv"


def test_paper_grid_matches_the_seed_pattern() -> None:
    grid = paper_grid()
    assert len(grid) == 42
    p = grid.poses
    # 36 translation poses: 3 heights x 4 x 3, theta 0
    assert np.unique(p[:36, 2]).tolist() == [15.0, 20.0, 25.0]
    np.testing.assert_allclose(np.unique(p[:36, 0]), [-2, -2 / 3, 2 / 3, 2], atol=1e-12)
    assert np.unique(p[:36, 1]).tolist() == [-2.0, 0.0, 2.0]
    assert np.all(p[:36, 3] == 0)
    # 6 rotations -6..6 deg (step 2.4) at (0, 0, 20)
    np.testing.assert_allclose(p[36:, 3], [-6, -3.6, -1.2, 1.2, 3.6, 6], atol=1e-12)
    np.testing.assert_array_equal(p[36:, :3], np.tile([0.0, 0.0, 20.0], (6, 1)))


def test_paper_grid_equals_the_example_file_row_by_row() -> None:
    frame = pd.read_csv(EXAMPLE, comment="#")
    np.testing.assert_allclose(paper_grid().poses,
                               frame[["x_o", "y_o", "z_o", "theta_deg"]].to_numpy(), atol=1e-6)


def test_load_grid_file_and_paper_keyword(tmp_path: Path) -> None:
    np.testing.assert_allclose(load_grid(EXAMPLE).poses, paper_grid().poses, atol=1e-6)
    assert load_grid("paper").name == "paper"
    bad = tmp_path / "bad.csv"
    bad.write_text("x_o,y_o,z_o\n1,2,3\n")
    with pytest.raises(InputError, match=r"bad\.csv: missing column\(s\) theta_deg"):
        load_grid(bad)
    with pytest.raises(InputError, match="no such file"):
        load_grid(tmp_path / "none.csv")


def test_user_grid_from_spacing_and_angles() -> None:
    xs = axis_values(-3, 3, step=1.5)
    np.testing.assert_allclose(xs, [-3, -1.5, 0, 1.5, 3])
    np.testing.assert_allclose(axis_values(-2, 2, step=4 / 3), [-2, -2 / 3, 2 / 3, 2])
    np.testing.assert_allclose(axis_values(-1, 1, count=3), [-1, 0, 1])
    grid = make_grid(heights=[10, 30], xs=xs, ys=axis_values(0, 2, step=1),
                     angles_deg=[-10, 10])
    assert len(grid) == 2 * 5 * 3 + 2
    # default rotation point: x-y centre, middle height (lower of the two middles)
    np.testing.assert_allclose(grid.poses[-2:], [[0, 1, 10, -10], [0, 1, 10, 10]])
    assert grid.pose(1) == (-3.0, 1.0, 10.0, 0.0)  # y varies fastest


def test_bad_grid_input_is_an_input_error() -> None:
    with pytest.raises(InputError):
        axis_values(1, 0, step=1)
    with pytest.raises(InputError):
        axis_values(0, 1, step=0)
    with pytest.raises(InputError):
        axis_values(0, 1e9, step=1e-3)
    with pytest.raises(InputError):
        make_grid([], [], [])


def test_preview_lists_every_pose() -> None:
    text = paper_grid().preview()
    lines = text.splitlines()
    assert lines[0].startswith("grid paper: 42 poses; heights z = 15, 20, 25 mm")
    assert len(lines) == 2 + 42
    assert lines[-1].split() == ["41", "0.0000", "0.0000", "20.0000", "6.0000"]
