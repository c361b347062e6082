"""Measure tab, uploads, data CSV solve, report download and hardware connect, without a browser.

Numbers are checked against simulated truth: the side plate of the workcell TOML, the scan
simulator of tests/measure (true beam, plate, pyramid) and the platform simulator.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.panels import acquire, export, measure, solve
from app.panels.state import AppState
from app.panels.upload import MAX_UPLOAD_BYTES, upload_dataset
from calib_core.errors import InputError
from calib_core.pyramid import load_geometry
from drivers.base import DriverError, MotionRefused
from drivers.sim.workcell import load_workcell
from tests.measure import sim_scans as sim


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppState]:
    state = AppState(None, load_workcell(None), sim=True,
                     session_path=tmp_path_factory.mktemp("measure") / "s.db", seed=8,
                     sim_move_time_s=0.0)
    state.worker.start()
    state.worker.call("connect", state.connect_sim)
    state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 120)
    state.worker.call("solve", lambda: solve.run_solve(state))
    yield state
    state.worker.stop()
    state.close_session()


def csv_bytes(scan: sim.Scan, **columns: np.ndarray) -> bytes:
    lines = ["# simulated scan", ",".join(["x_o", "y_o", "z_o", "theta_deg", "d", *columns])]
    assert scan.poses.theta_deg is not None
    for i in range(len(scan.d)):
        p = scan.poses.position[i]
        extra = [str(v[i]) for v in columns.values()]
        lines.append(",".join([repr(float(p[0])), repr(float(p[1])), repr(float(p[2])),
                               repr(float(scan.poses.theta_deg[i])), repr(float(scan.d[i])),
                               *extra]))
    return ("\n".join(lines) + "\n").encode()


def with_nan(content: bytes) -> bytes:
    """The CSV with its first data row's first value replaced by NaN."""
    lines = content.split(b"\n")
    k = next(i for i, ln in enumerate(lines) if not ln.startswith(b"#")) + 1
    lines[k] = b"nan," + lines[k].split(b",", 1)[1]
    return b"\n".join(lines)


def calib_bytes(cal) -> bytes:
    return json.dumps(cal.to_json_dict()).encode()


# ---- plane ------------------------------------------------------------------------------------
def test_side_plate_scan_matches_the_workcell_truth_within_3_sigma(solved: AppState) -> None:
    solved.armed = False
    before = solved.world.true_pose
    with pytest.raises(MotionRefused, match="Arm motion"):
        solved.worker.call("scan", lambda: measure.run_plane_scan(solved))
    assert solved.world.true_pose == before and "plane" not in solved.measurements
    solved.armed = True
    try:
        m = solved.worker.call("scan", lambda: measure.run_plane_scan(solved), 60)
    finally:
        solved.armed = False
    side = solved.workcell.side_plate
    fit = m.result
    assert fit["n_points"] == len(measure.side_plate_plan(solved.workcell)) == 25
    for key, truth in (("alpha", side.alpha), ("beta", side.beta),
                       ("offset", side.delta - solved.workcell.plate.delta)):
        assert abs(fit[key] - truth) <= 3 * fit["sigma"][key], (key, fit[key], truth)
    assert fit["rms"] < 0.02
    assert "| alpha |" in m.markdown and "sim truth" in m.markdown
    assert solved.measurements["plane"] is m and len(m.draw["scan"]) == 25


def test_scan_csv_reads_back_and_stop_ends_a_scan(solved: AppState) -> None:
    m = solved.measurements["plane"]
    again = measure.fit_plane(solved, upload_dataset("scan.csv", measure.scan_csv_bytes(solved),
                                                     need_spot=False))
    assert again.result["alpha"] == pytest.approx(m.result["alpha"], abs=1e-3 * m.result[
        "sigma"]["alpha"])
    with pytest.raises(InputError, match="no side plate scan"):
        measure.scan_csv_bytes(AppState(None, load_workcell(None)))
    solved.sim_move_time_s = 0.05
    solved.worker.call("reconnect", solved.connect_sim)
    solved.armed = True
    try:
        future = solved.worker.submit("scan", lambda: measure.run_plane_scan(solved))
        time.sleep(0.4)
        solved.stop_motion()                                    # STOP: disarm + feed hold
        with pytest.raises((MotionRefused, DriverError), match="stopped"):
            future.result(10)
        assert solved.measurements["plane"] is m                # nothing published
    finally:
        solved.armed = False
        solved.sim_move_time_s = 0.0
        solved.worker.call("reconnect", solved.connect_sim)


def test_uploaded_calibration_and_plane_scan(solved: AppState) -> None:
    rng = np.random.default_rng(4)
    alpha, beta, offset = 0.02, -0.01, 3.0 + sim.DELTA
    scan = sim.scan_targets(sim.plane_targets(alpha, beta, offset, sim.grid_xy(30, 60, 8, 5)),
                            rng)
    previous = solved.measurements.get("plane")
    with pytest.raises(InputError, match="missing key"):
        measure.load_calibration_upload(solved, "H.json", b'{"model": "schoenflies"}')
    assert solved.measure_calibration is None
    measure.load_calibration_upload(solved, "H.json", calib_bytes(sim.calibration()))
    try:
        assert "uploaded" in measure.calibration_markdown(solved)
        measure.plane_upload(solved, "plane.csv", csv_bytes(scan))
        fit = solved.measurements["plane"].result
        for key, truth in (("alpha", alpha), ("beta", beta), ("offset", offset - sim.DELTA)):
            assert abs(fit[key] - truth) <= 3 * fit["sigma"][key], (key, fit[key], truth)
        with pytest.raises(InputError, match="missing column"):
            measure.plane_upload(solved, "bad.csv", b"x_o,y_o,z_o,theta_deg\n" + b"1,2,3,4\n" * 3)
        assert solved.measurements["plane"].result is fit       # a refusal changes nothing
    finally:
        solved.measure_calibration = None
        if previous is not None:
            solved.measurements["plane"] = previous


def test_gauges_and_pyramid_uploads(solved: AppState) -> None:
    rng = np.random.default_rng(5)
    heights = np.array([0.0, 1.0, 1.5, 2.0, 3.0, 5.0, 7.0])
    spots = np.array([[20.0, 60.0], [40.0, 80.0]])
    scan = sim.gauge_readings(heights, spots, rng)
    solved.measure_calibration = sim.calibration()
    try:
        measure.gauges_upload(solved, "gauges.csv",
                              csv_bytes(scan, gauge_height=np.tile(heights, len(spots))))
        res = solved.measurements["gauges"].result
        assert abs(res["c"] - sim.TRUE_U[2]) < 3.5 * res["c_sigma"]
        assert res["agreement_sigmas"] < 3.5
        with pytest.raises(InputError, match="gauge_height"):
            measure.gauges_upload(solved, "g.csv", csv_bytes(scan))

        geo = load_geometry()
        rot = sim.random_rotation(rng, 15.0)
        apex = np.array([150.0, 40.0, 30.0])
        pts, labels = sim.pyramid_targets(geo, rot, apex, 8, rng)
        pscan = sim.scan_targets(pts, rng)
        measure.pyramid_upload(solved, "pyr.csv", csv_bytes(pscan, face=labels))
        m = solved.measurements["pyramid"]
        z = (np.array(m.result["apex"]) - (apex - [0, 0, sim.DELTA])) / np.array(
            m.result["apex_sigma"])
        assert np.all(np.abs(z) < 3.5), z
        true_edges = geo.edges @ rot.T
        cosines = np.sum(np.array(m.result["edges"]) * true_edges, axis=1)
        assert np.degrees(np.arccos(np.clip(cosines, -1, 1))).max() < 1.0
        assert m.draw["edges"].shape == (3, 3) and "apex (mm)" in m.markdown
        with pytest.raises(InputError, match="face"):
            measure.pyramid_upload(solved, "p.csv", csv_bytes(pscan))
    finally:
        solved.measure_calibration = None


def test_platform_campaign_calibrates_and_draws_axes(solved: AppState) -> None:
    m = solved.worker.call("platform", lambda: measure.run_platform_campaign(solved, 1), 120)
    before, after = m.result["before"], m.result["after"]
    assert after["orientation_rms_deg"] < before["orientation_rms_deg"] / 4
    assert after["apex_rms_mm"] < before["apex_rms_mm"] / 20
    assert "| orientation RMS (deg) |" in m.markdown and "sim truth" in m.markdown
    d = m.draw
    n = m.result["n_validation"]
    assert d["measured"].shape == d["model"].shape == d["nominal"].shape == (n, 3)

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))
    # measured output axes sit closer to the calibrated model than to the nominal one
    assert np.sqrt(np.mean(angle(d["measured"], d["model"]) ** 2)) < \
        0.5 * np.sqrt(np.mean(angle(d["measured"], d["nominal"]) ** 2))
    np.testing.assert_allclose(d["centre"], [m.result["params"][f"centre_{a}_mm"]
                                             for a in "xyz"])


# ---- uploads and the data CSV solve -----------------------------------------------------------
def test_data_csv_upload_solves_like_the_session(solved: AppState) -> None:
    content = export.session_csv(solved)
    reference = solved.calibration
    state = AppState(None, load_workcell(None), sim=False)
    state.worker.start()
    try:
        message = state.worker.call("load", lambda: solve.load_data_csv(
            state, "C:\\data\\session.csv", content))
        assert "42 poses" in message and state.data_source == "session.csv"
        view = state.worker.call("solve", lambda: solve.run_solve(state))
        # the CSV holds 9 significant digits: the same solve within 1 % of a sigma
        assert np.all(np.abs(view.calibration.values - reference.values)
                      < 0.01 * reference.sigma)
        assert "uploaded file **session.csv**" in solve.data_markdown(state)
        files = state.worker.call("report", lambda: export.report_files(state), 120)
        assert hashlib.sha256(content).hexdigest() in files["report.html"].decode()
        frame = state.data_frame
        for bad, match in ((b"\x00\x01\x02" * 100, "binary"),
                           (b"\xff\xfe garbage", "UTF-8"),
                           (content.replace(b",x_p,", b",x_q,"), "missing column"),
                           (with_nan(content), "not a finite number"),
                           (b"x" * (MAX_UPLOAD_BYTES + 1), "upload limit")):
            with pytest.raises(InputError, match=match):
                state.worker.call("load", lambda bad=bad: solve.load_data_csv(state, "x.csv", bad))
            assert state.data_frame is frame and state.calibration is view.calibration
    finally:
        state.worker.stop()


def test_upload_dataset_names_the_upload_not_the_temp_file() -> None:
    with pytest.raises(InputError) as info:
        upload_dataset("../../etc/scan.csv", b"x_o,y_o,z_o,theta_deg,d\n1,2,3,4,abc\n",
                       need_spot=False)
    assert str(info.value).startswith("scan.csv: row 0, column d")
    assert "lasercal-upload" not in str(info.value)


# ---- report -----------------------------------------------------------------------------------
def test_download_report_bundle_with_measure_sections(solved: AppState) -> None:
    with pytest.raises(InputError, match="Solve H"):
        export.report_files(AppState(None, load_workcell(None), sim=True))
    files = solved.worker.call("report", lambda: export.report_files(solved, "test note"), 120)
    assert set(files) == {"report.html", "report.pdf", "calibration.json", "residuals.csv"}
    assert files["report.pdf"].startswith(b"%PDF")
    html = files["report.html"].decode()
    assert "test note" in html and solved.session_path.name in html
    calib = json.loads(files["calibration.json"])
    assert calib["params"]["x_t"] == pytest.approx(solved.calibration.point("x_t"), rel=1e-12)
    for kind in solved.measurements:
        title = {"plane": "Plane identification", "platform": "Platform calibration",
                 "gauges": "Johansson gauge check", "pyramid": "Pyramid pose"}[kind]
        assert title in html
    name, data = export.report_download(files, "zip (HTML, PDF, JSON, CSV)", "s")
    assert name == "s.report.zip"
    assert sorted(zipfile.ZipFile(io.BytesIO(data)).namelist()) == sorted(files)
    assert export.report_download(files, "PDF", "s") == ("s.report.pdf", files["report.pdf"])


# ---- hardware connect -------------------------------------------------------------------------
def test_hardware_connect_with_a_camera_calibration_json(tmp_path: Path) -> None:
    """GRBL and Keyence over pty emulators, OpenCVCamera on PNG frames, mapping from JSON."""
    import cv2

    from drivers.camera_cv import OpenCVCamera, PixelToPlate
    from drivers.emulators.cell import CellEmulators
    from drivers.sim.render import FrameRenderer
    from drivers.sim.world import SimWorld

    workcell = load_workcell(None)
    cam = workcell.camera
    renderer = FrameRenderer(cam, seed=2)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), renderer.render([renderer.spot_for(
            500.0 + 50 * i, 400.0)]))
    mapping = PixelToPlate(cam.camera_matrix(), cam.dist_coeffs(),
                           np.linalg.inv(cam.homography()))
    calib_file = tmp_path / "camera.json"
    calib_file.write_text(json.dumps(mapping.to_json_dict()))
    world = SimWorld(workcell, seed=4)
    state = AppState(None, workcell, sim=False)
    with CellEmulators(world) as emu:
        state.worker.start()
        try:
            with pytest.raises(DriverError, match="camera 0 cannot be opened"):  # int index
                state.worker.call("connect", lambda: state.connect_hardware(
                    emu.grbl.path, emu.keyence.path, " 0 ", str(calib_file)), 30)
            assert not state.connected
            with pytest.raises(InputError, match="no such file"):
                state.worker.call("connect", lambda: state.connect_hardware(
                    emu.grbl.path, emu.keyence.path, "0", str(tmp_path / "none.json")), 30)
            state.worker.call("connect", lambda: state.connect_hardware(
                emu.grbl.path, emu.keyence.path, str(tmp_path / "f%03d.png"),
                str(calib_file)), 30)
            assert state.connected and not state.sim
            assert isinstance(state.camera, OpenCVCamera)
            np.testing.assert_allclose(state.camera.mapping.homography, mapping.homography)
            spot = state.worker.call("spot", state.camera.measure_spot, 30)
            assert spot.ok
            np.testing.assert_allclose([spot.x, spot.y],
                                       cam.unproject(np.array([[500.0, 400.0]]))[0], atol=0.005)
        finally:
            state.worker.stop()
            state.disconnect()
