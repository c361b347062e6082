"""``lasercal camera``: calibrate on a rendered chessboard, then measure a rendered spot."""

from __future__ import annotations

import json
import re

import numpy as np

from app.cli import main
from drivers.camera_cv import PixelToPlate
from drivers.sim.workcell import load_workcell

CAMERA = load_workcell().camera


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_calibrate_render_and_measure(tmp_path, capsys):
    calib, board = tmp_path / "cam.json", tmp_path / "board.png"
    code, out, _ = run(capsys, "camera", "calibrate", "--sim", "--out", str(calib))
    assert code == 0 and "corners 192" in out
    mapping = PixelToPlate.from_json_dict(json.loads(calib.read_text()))
    uv = np.array([[100.0, 100.0], [640.0, 512.0], [1200.0, 950.0]])
    np.testing.assert_allclose(mapping.to_plate(uv), CAMERA.unproject(uv), atol=0.002)

    # the same board from an image file, geometry given on the command line
    assert run(capsys, "camera", "render", "--chessboard", "--out", str(board))[0] == 0
    code, out, _ = run(capsys, "camera", "calibrate", "--image", str(board), "--pattern",
                       "16x12", "--square", "1", "--origin", "-13.5", "64.5", "--intrinsics",
                       str(calib), "--out", str(tmp_path / "cam2.json"))
    assert code == 0 and "scale 16.00 um/px" in out

    spot, off = tmp_path / "spot.png", tmp_path / "off.png"
    code, out, _ = run(capsys, "camera", "render", "--x", "1", "--y", "-1", "--theta", "3",
                       "--out", str(spot))
    truth = [float(v) for v in re.search(r"x=(\S+) y=(\S+) mm", out).groups()]
    run(capsys, "camera", "render", "--laser-off", "--seed", "1", "--out", str(off))
    code, out, _ = run(capsys, "camera", "spot", "--image", str(spot), "--background",
                       str(off), "--calib", str(calib))
    assert code == 0
    xy = [float(v) for v in re.search(r"x=(\S+) y=(\S+) mm", out).groups()]
    # camera noise 3.1 um (1-sigma per axis) is in the rendered spot: 5 sigma bound
    assert np.abs(np.subtract(xy, truth)).max() < 5 * 0.0031

    code, out, _ = run(capsys, "camera", "spot", "--image", str(off), "--calib", str(calib))
    assert code == 0 and out.startswith("rejected: no spot")


def test_errors_are_one_line(tmp_path, capsys):
    off = tmp_path / "off.png"
    run(capsys, "camera", "render", "--laser-off", "--out", str(off))
    code, _, err = run(capsys, "camera", "calibrate", "--image", str(off), "--pattern", "16x12",
                       "--out", str(tmp_path / "x.json"))
    assert code == 2 and "needs --square, --origin" in err
    code, _, err = run(capsys, "camera", "calibrate", "--image", str(off), "--pattern", "16x12",
                       "--square", "1", "--origin", "0", "0", "--out", str(tmp_path / "x.json"))
    assert code == 2 and "chessboard with 16x12 inner corners not found" in err
    code, _, err = run(capsys, "camera", "spot", "--image", str(tmp_path / "none.png"),
                       "--calib", str(tmp_path / "none.json"))
    assert code == 2 and err.count("\n") == 1 and "no such file" in err
