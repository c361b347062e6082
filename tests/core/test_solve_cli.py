"""The ``lasercal solve`` command: JSON contract, table, and one-line errors for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.core.simdata import seed_grid, seed_truth, simulate
from tests.core.test_solve import EXAMPLE, NOISE, SHARED

ROOT = Path(__file__).resolve().parents[2]


def lasercal(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_json_contract_and_values() -> None:
    out = lasercal("solve", str(EXAMPLE), "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)  # exactly one JSON object
    required = {"model", "n_points", "n_used", "params", "sigma", "gain", "gain_sigma",
                "direction", "residuals", "condition_number", "outliers", "warnings"}
    assert required <= set(data)
    names = ["x_t", "y_t", "z_t_minus_delta", "a", "b", "c", "alpha", "beta"]
    assert list(data["params"]) == names and list(data["sigma"]) == names
    assert data["model"] == "schoenflies" and data["n_points"] == data["n_used"] == 42
    truth = json.loads((SHARED / "example_paper_grid.truth.json").read_text())
    for n in names:
        assert abs(data["params"][n] - truth[n]) < 3 * data["sigma"][n], n
    assert set(data["residuals"]) == {"x", "y", "z"}
    assert set(data["residuals"]["x"]) == {"mean_abs", "rms", "max"}
    assert abs(np.linalg.norm(data["direction"]) - 1) < 1e-12


def test_readable_table() -> None:
    out = lasercal("solve", str(EXAMPLE))
    assert out.returncode == 0
    for text in ("x_t", "z_t_minus_delta", "gain |u'|", "condition number", "outliers"):
        assert text in out.stdout


def test_outliers_listed_by_row_and_no_robust(tmp_path: Path) -> None:
    frame = simulate(seed_truth(), seed_grid(), NOISE, np.random.default_rng(7),
                     outliers={3: (0.5, 0.0)})
    path = tmp_path / "with_outlier.csv"
    path.write_text("# a comment line\n" + frame.to_csv(index=False))
    data = json.loads(lasercal("solve", str(path), "--json").stdout)
    assert data["outliers"] == [3] and data["n_used"] == 41
    plain = json.loads(lasercal("solve", str(path), "--json", "--no-robust").stdout)
    assert plain["outliers"] == [] and plain["n_used"] == 42


def test_noise_file_and_holdout(tmp_path: Path) -> None:
    noise = tmp_path / "noise.toml"
    noise.write_text("[noise]\ncamera = 0.0123\nrobot_xy = 0.0025\nrobot_z = 0.005\n"
                     "robot_theta_deg = 0.01\nsensor = 0.002\n")
    data = json.loads(lasercal("solve", str(EXAMPLE), "--json", "--noise", str(noise),
                               "--holdout", "0.3").stdout)
    assert data["noise"]["camera"] == 0.0123
    assert data["holdout"]["n"] == 13 and data["n_used"] == 29


def _write(tmp_path: Path, text: str) -> str:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    return str(path)


GOOD = EXAMPLE.read_text()
HEADER_AND_ROWS = [ln for ln in GOOD.splitlines() if not ln.startswith("#")]


@pytest.mark.parametrize(("text", "expect"), [
    ("\n".join(HEADER_AND_ROWS).replace("x_p", "xp"), "missing column(s) x_p"),
    ("\n".join([HEADER_AND_ROWS[0], *HEADER_AND_ROWS[1:5], "1,2,3,0,nan,4,5",
                *HEADER_AND_ROWS[5:]]), "row 4, column d"),
    ("\n".join([HEADER_AND_ROWS[0], *HEADER_AND_ROWS[1:8], "1,2,3,0,0.5,abc,5",
                *HEADER_AND_ROWS[8:]]), "row 7, column x_p"),
    ("\n".join([HEADER_AND_ROWS[0], "1,2,3,0,inf,4,5", *HEADER_AND_ROWS[2:]]), "row 0"),
    ("\n".join(HEADER_AND_ROWS[:4]), "too few rows"),
    ("", "empty file"),
    ("\n".join(HEADER_AND_ROWS).replace("theta_deg", "angle"), "missing orientation"),
])
def test_bad_input_gives_one_error_line(tmp_path: Path, text: str, expect: str) -> None:
    out = lasercal("solve", _write(tmp_path, text), "--json")
    assert out.returncode == 2
    assert out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), out.stderr
    assert expect in lines[0] and "bad.csv" in lines[0]


def test_unreadable_binary_degenerate_and_usage(tmp_path: Path) -> None:
    cases = [("solve", str(tmp_path / "missing.csv")), ("solve", str(tmp_path))]
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    cases.append(("solve", str(binary)))
    one_height = simulate(seed_truth(), seed_grid(heights=(20.0,)), NOISE,
                          np.random.default_rng(0))
    flat = tmp_path / "flat.csv"
    flat.write_text(one_height.to_csv(index=False))
    cases.append(("solve", str(flat)))
    cases.append(("solve", str(EXAMPLE), "--holdout", "1.5"))
    cases.append(("solve", str(EXAMPLE), "--model", "banana"))
    for args in cases:
        out = lasercal(*args)
        assert out.returncode == 2, args
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:"), (args, out.stderr)
        assert "Traceback" not in out.stderr
    out = lasercal("solve", str(flat))
    assert "c (" in out.stderr and "second flange height" in out.stderr
