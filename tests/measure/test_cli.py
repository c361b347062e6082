"""``lasercal measure plane|gauges|pyramid``: JSON contracts, readable output, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from calib_core.pyramid import load_geometry
from tests.measure import sim_scans as sim

ALPHA, BETA, OFFSET = 4.152e-3, -3.153e-3, -9.981
APEX = np.array([150.0, 40.0, 30.0])


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("measure")
    rng = np.random.default_rng(30)
    calib = tmp / "H.json"
    calib.write_text(json.dumps(sim.calibration().to_json_dict()))
    plane = sim.scan_targets(sim.plane_targets(ALPHA, BETA, OFFSET,
                                               sim.grid_xy(170.0, 40.0, 20.0, 6)), rng)
    cam = plane.truth[:, 0:2] + rng.normal(scale=0.0123, size=(len(plane.d), 2))
    heights = np.tile([0.0, 1.0, 2.0, 3.0, 5.0], 2)
    gauges = sim.gauge_readings(heights[:5], np.array([[20.0, 60.0], [40.0, 80.0]]), rng)
    geo = load_geometry()
    rot = sim.random_rotation(rng, 20.0)
    pts, labels = sim.pyramid_targets(geo, rot, APEX, 6, rng)
    pyr = sim.scan_targets(pts, rng)
    return {
        "calib": calib,
        "plane": sim.write_scan_csv(tmp / "plane.csv", plane),
        "plane_cam": sim.write_scan_csv(tmp / "plane_cam.csv", plane, x_p=cam[:, 0],
                                        y_p=cam[:, 1]),
        "gauges": sim.write_scan_csv(tmp / "gauges.csv", gauges, gauge_height=heights),
        "pyramid": sim.write_scan_csv(tmp / "pyramid.csv", pyr, face=labels),
        "pyramid_noface": sim.write_scan_csv(tmp / "pyramid_noface.csv", pyr),
        "bad_json": _write(tmp / "bad.json", "{not json"),
    }


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _run_json(capsys: pytest.CaptureFixture[str], *argv: object) -> dict:
    assert main([str(a) for a in argv]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    return json.loads(out)


def test_plane_json_contract(files: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    res = _run_json(capsys, "measure", "plane", files["plane"], "--calib", files["calib"],
                    "--json")
    for key in ("alpha", "beta", "offset", "normal", "rms", "n_points", "sigma"):
        assert key in res
    assert set(res["sigma"]) == {"alpha", "beta", "offset"}
    assert res["n_points"] == 36 and "comparison" not in res
    truth = {"alpha": ALPHA, "beta": BETA, "offset": OFFSET - sim.DELTA}
    for key, val in truth.items():
        assert abs(res[key] - val) < 3.5 * res["sigma"][key], key
    assert abs(np.linalg.norm(res["normal"]) - 1) < 1e-12
    assert "datum" in res["z_reference"]


def test_plane_with_camera_and_orthogonal(files: dict[str, Path],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    res = _run_json(capsys, "measure", "plane", files["plane_cam"], "--calib", files["calib"],
                    "--fit", "orthogonal", "--json")
    assert res["method"] == "orthogonal"
    cmp = res["comparison"]
    assert set(cmp) == {"camera_plane", "difference", "point_errors"}
    assert set(cmp["point_errors"]) == {"x", "y", "z"}
    assert 0.005 < cmp["point_errors"]["x"]["rms"] < 0.03  # camera + robot rotation at 72 mm
    assert main(["measure", "plane", str(files["plane_cam"]), "--calib",
                 str(files["calib"])]) == 0
    text = capsys.readouterr().out
    assert "alpha" in text and "Table 4" in text and "offset [mm]" in text


def test_gauges_json_contract(files: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    res = _run_json(capsys, "measure", "gauges", files["gauges"], "--calib", files["calib"],
                    "--json")
    assert abs(res["c"] - sim.TRUE_U[2]) < 3.5 * res["c_sigma"]
    assert res["agreement_sigmas"] is not None and 0 <= res["agreement_sigmas"] < 3.5
    res = _run_json(capsys, "measure", "gauges", files["gauges"], "--json")
    assert res["agreement_sigmas"] is None and res["c_sigma"] > 0
    assert main(["measure", "gauges", str(files["gauges"]), "--calib", str(files["calib"])]) == 0
    assert "agreement" in capsys.readouterr().out


def test_pyramid_json_contract(files: dict[str, Path],
                               capsys: pytest.CaptureFixture[str]) -> None:
    res = _run_json(capsys, "measure", "pyramid", files["pyramid"], "--calib", files["calib"],
                    "--json")
    apex, sig = np.array(res["apex"]), np.array(res["apex_sigma"])
    assert np.all(np.abs(apex - (APEX - [0, 0, sim.DELTA])) < 3.5 * sig)
    assert len(res["quaternion"]) == 4 and abs(np.linalg.norm(res["quaternion"]) - 1) < 1e-9
    assert len(res["rotation_sigma_deg"]) == 3 and all(s > 0 for s in res["rotation_sigma_deg"])
    edges = np.array(res["edges"])
    assert edges.shape == (3, 3)
    np.testing.assert_allclose(np.linalg.norm(edges, axis=1), 1.0, atol=1e-12)
    assert main(["measure", "pyramid", str(files["pyramid"]), "--calib",
                 str(files["calib"])]) == 0
    text = capsys.readouterr().out
    assert "apex [mm]" in text and "edge AB" in text


@pytest.mark.parametrize(("argv", "message"), [
    (["plane", "{missing}", "--calib", "{calib}"], "no such file"),
    (["plane", "{plane}", "--calib", "{bad_json}"], "not valid JSON"),
    (["plane", "{plane}", "--calib", "{plane}"], "not valid JSON"),
    (["plane", "{plane}", "--calib", "{calib}", "--fit", "median"], "invalid choice"),
    (["plane", "{plane}"], "--calib"),
    (["gauges", "{plane}", "--calib", "{calib}"], "gauge_height"),
    (["pyramid", "{pyramid_noface}", "--calib", "{calib}"], "missing column face"),
    (["pyramid", "{plane}", "--calib", "{calib}"], "missing column face"),
    (["pyramid", "{pyramid}", "--calib", "{calib}", "--geometry", "{calib}"], "TOML"),
])
def test_bad_input_is_one_error_line(files: dict[str, Path], capsys: pytest.CaptureFixture[str],
                                     argv: list[str], message: str) -> None:
    names = {k: str(v) for k, v in files.items()} | {"missing": "/nonexistent/scan.csv"}
    args = ["measure", *(a.format(**names) for a in argv)]
    try:
        status = main(args)
    except SystemExit as exc:  # argparse usage errors
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("error:") and err.count("\n") == 1 and message in err, err
    assert "Traceback" not in err


def test_tilted_scan_with_schoenflies_calibration(files: dict[str, Path], tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    text = files["plane"].read_text().splitlines()
    header = text[1].replace("theta_deg", "qw,qx,qy,qz")
    rows = []
    for line in text[2:]:
        cols = line.split(",")
        rows.append(",".join([*cols[:3], "0.9998,0.02,0.0,0.0", cols[4]]))
    bad = _write(tmp_path / "tilted.csv", "\n".join([header, *rows]) + "\n")
    assert main(["measure", "plane", str(bad), "--calib", str(files["calib"])]) == 2
    assert "Schoenflies" in capsys.readouterr().err
