"""Property-based fuzzing of the file loaders and the solve CLI: never a traceback.

Any input either loads or raises :class:`InputError`; through the CLI it gives exit status 2
and exactly one ``error:`` line, and writes nothing to stdout.
"""

from __future__ import annotations

import contextlib
import io
import string
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.cli import main
from calib_core.calibrate import solve
from calib_core.errors import InputError
from calib_core.io import load_dataset, load_toml
from calib_core.noise import NoiseModel

COLUMNS = ["x_o", "y_o", "z_o", "theta_deg", "d", "x_p", "y_p", "qw", "qx", "qy", "qz", "junk"]
CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.text(alphabet=string.printable, max_size=6),
    st.sampled_from(["", "nan", "inf", "-inf", "1e400", "0x10", " 1.5 ", "1,5", "\"", "#"]),
)
SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def csv_texts(draw: st.DrawFn) -> str:
    cols = draw(st.lists(st.sampled_from(COLUMNS), min_size=0, max_size=9))
    n = draw(st.integers(0, 12))
    rows = [",".join(draw(CELLS) for _ in cols) for _ in range(n)]
    lines = [",".join(cols), *rows]
    if draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), "# comment")
    return "\n".join(lines)


def run_cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:  # argparse usage errors
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def assert_one_error_line(code: int, out: str, err: str) -> None:
    assert code == 2, (code, err)
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), err


@SETTINGS
@given(text=csv_texts())
def test_csv_loader_and_solve_never_crash(tmp_path: Path, text: str) -> None:
    path = tmp_path / "fuzz.csv"
    path.write_text(text)
    try:
        data = load_dataset(path)
        solve(data)
    except InputError as exc:
        assert str(exc) and "\n" not in str(exc)


@SETTINGS
@given(blob=st.binary(max_size=400))
def test_cli_on_arbitrary_bytes(tmp_path: Path, blob: bytes) -> None:
    path = tmp_path / "blob.csv"
    path.write_bytes(blob)
    code, out, err = run_cli("solve", str(path), "--json")
    if code != 0:
        assert_one_error_line(code, out, err)


@SETTINGS
@given(text=st.text(max_size=200))
def test_noise_toml_never_crashes(tmp_path: Path, text: str) -> None:
    path = tmp_path / "noise.toml"
    path.write_text(text)
    try:
        NoiseModel.from_mapping(load_toml(path)[0], str(path))
    except InputError as exc:
        assert "noise.toml" in str(exc)


@SETTINGS
@given(values=st.dictionaries(st.sampled_from(["camera", "sensor", "robot_z", "bogus"]),
                              st.one_of(st.floats(), st.text(max_size=3), st.booleans()),
                              max_size=4))
def test_noise_values_validated(values: dict[str, object]) -> None:
    try:
        model = NoiseModel.from_mapping(values)
    except InputError:
        return
    assert all(np.isfinite(v) and v >= 0 for v in model.as_dict().values())


@SETTINGS
@given(args=st.lists(st.one_of(st.sampled_from(["--model", "--holdout", "--noise", "--json",
                                                "--no-robust", "--seed", "-x", "--"]),
                               st.text(alphabet=string.printable, max_size=5)), max_size=5))
def test_solve_arguments_fuzz(args: list[str]) -> None:
    example = str(Path(__file__).resolve().parents[2] / "static_data" / "example_paper_grid.csv")
    code, out, err = run_cli("solve", example, *args)
    if code != 0:
        assert_one_error_line(code, out, err)
