"""Dashboard handlers without a browser: jog, grid, acquisition, solve, export, worker."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.panels import acquire, export, grid, jog, solve
from app.panels.state import AppState
from app.worker import Worker
from calib_core.calibrate import BeamCalibration
from calib_core.errors import InputError
from calib_core.grid import paper_grid
from calib_core.io import dataset_from_frame, read_table
from drivers.base import DriverError, FlangePose, MotionRefused
from drivers.sim.workcell import load_workcell


@pytest.fixture()
def app(tmp_path: Path) -> Iterator[AppState]:
    state = AppState(None, load_workcell(None), sim=True, session_path=tmp_path / "s.db",
                     seed=3, sim_move_time_s=0.0)
    state.worker.start()
    state.worker.call("connect", state.connect_sim)
    yield state
    state.worker.stop()
    state.close_session()


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppState]:
    """One simulated 42-pose acquisition and its robust solve, shared by the solve tests."""
    state = AppState(None, load_workcell(None), sim=True,
                     session_path=tmp_path_factory.mktemp("solve") / "s.db", seed=5,
                     sim_move_time_s=0.0)
    state.worker.start()
    state.worker.call("connect", state.connect_sim)
    progress = state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 120)
    assert progress.state == "finished" and progress.done == 42
    state.worker.call("solve", lambda: solve.run_solve(state))
    yield state
    state.worker.stop()
    state.close_session()


# ---- jog ------------------------------------------------------------------------------------
def test_jog_target_moves_one_axis_by_the_step() -> None:
    p = FlangePose(1.0, 2.0, 20.0, 5.0)
    assert jog.jog_target(p, "x", 1, 0.5) == FlangePose(1.5, 2.0, 20.0, 5.0)
    assert jog.jog_target(p, "y", -1, 0.25) == FlangePose(1.0, 1.75, 20.0, 5.0)
    assert jog.jog_target(p, "z", -1, 2.0) == FlangePose(1.0, 2.0, 18.0, 5.0)
    assert jog.jog_target(p, "theta", 1, 1.5) == FlangePose(1.0, 2.0, 20.0, 6.5)
    with pytest.raises(InputError):
        jog.jog_target(p, "w", 1, 1.0)
    with pytest.raises(MotionRefused):
        jog.jog_target(p, "x", 1, jog.MAX_JOG_STEP + 0.1)
    with pytest.raises(MotionRefused):
        jog.jog_target(p, "x", 1, 0.0)


def test_jog_refused_while_disarmed_and_nothing_moves(app: AppState) -> None:
    before = app.world.true_pose
    with pytest.raises(MotionRefused, match="Arm motion"):
        jog.jog(app, "x", 1, 1.0)
    with pytest.raises(MotionRefused):
        jog.go_to(app, 1.0, 1.0, 20.0, 0.0)
    time.sleep(0.1)
    assert app.world.true_pose == before


def test_armed_jog_moves_the_simulated_robot(app: AppState) -> None:
    app.armed = True
    start = app.world.true_pose
    jog.jog(app, "x", 1, 1.5).result(10)
    jog.jog(app, "theta", -1, 2.0).result(10)
    end = app.world.true_pose
    # the jog starts from the pose read back (repeatability noise ~ 2.5 um, 0.01 deg)
    assert end.x - start.x == pytest.approx(1.5, abs=0.02)
    assert end.theta_deg - start.theta_deg == pytest.approx(-2.0, abs=0.05)
    assert (end.y, end.z) == pytest.approx((start.y, start.z), abs=0.02)
    assert app.latest is not None and app.latest.pose.x == pytest.approx(end.x, abs=0.02)


def test_go_to_outside_soft_limits_is_refused_and_reported(app: AppState) -> None:
    app.armed = True
    before = app.world.true_pose
    z_hi = app.workcell.limits.z[1]
    future = jog.go_to(app, 0.0, 0.0, z_hi + 1.0, 0.0)
    with pytest.raises(MotionRefused, match="soft limits"):
        future.result(10)
    assert app.world.true_pose == before
    assert any(level == "error" and "soft limits" in body
               for _, level, _, body in app.messages)
    jog.go_to(app, 0.5, -0.5, 18.0, 1.0).result(10)       # the worker is still alive
    assert app.world.true_pose == FlangePose(0.5, -0.5, 18.0, 1.0)


def test_stop_disarms_and_pauses_a_running_acquisition(app: AppState) -> None:
    app.sim_move_time_s = 0.05
    app.worker.call("reconnect", app.connect_sim)
    app.armed = True
    future = app.worker.submit("acquire", lambda: acquire.run_acquisition(app, 1))
    deadline = time.monotonic() + 10
    while (app.runner is None or app.runner.state != "running") and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)
    app.stop_motion()
    progress = future.result(20)
    assert progress.state == "paused" and "STOP" in progress.message
    assert not app.armed
    assert 0 < progress.done < 42
    with pytest.raises(MotionRefused):
        jog.jog(app, "x", 1, 1.0)
    # resume continues the same session without storing any pose twice
    progress = app.worker.call("resume", lambda: acquire.run_acquisition(app, 1), 60)
    assert progress.state == "finished" and progress.done == 42
    frame = app.session.samples_frame()
    assert sorted(frame["pose_index"]) == list(range(42))


# ---- grid -----------------------------------------------------------------------------------
def test_default_grid_spec_is_the_seed_grid_of_42_poses() -> None:
    g = grid.GridSpec().to_grid()
    assert len(g) == 42
    np.testing.assert_allclose(g.poses, paper_grid().poses, atol=1e-12)


def test_custom_grid_counts_and_errors(app: AppState) -> None:
    spec = grid.GridSpec(heights="10 30", x_range=(-1.0, 1.0), nx=2, y_range=(0.0, 3.0), ny=4,
                         angles="-5, 5, 10", rotation_at=(0.0, 1.0, 20.0))
    g = grid.apply_grid(app, spec)
    assert len(g) == 2 * 2 * 4 + 3 and app.grid is g
    assert set(np.round(g.poses[:, 2], 9)) == {10.0, 30.0, 20.0}
    np.testing.assert_allclose(g.poses[-3:], [[0, 1, 20, -5], [0, 1, 20, 5], [0, 1, 20, 10]])
    positions, rotations = grid.preview_frames(g)
    assert positions.shape == (19, 3) and rotations.shape == (19, 3, 3)
    np.testing.assert_allclose(rotations[-1] @ [1, 0, 0], [np.cos(np.radians(10)),
                                                           np.sin(np.radians(10)), 0], atol=1e-12)
    with pytest.raises(InputError, match="heights"):
        grid.GridSpec(heights="15, twenty").to_grid()
    with pytest.raises(MotionRefused, match="grid pose"):
        grid.apply_grid(app, grid.GridSpec(heights=f"{app.workcell.limits.z[1] + 5}"))
    assert app.grid is g  # a refused grid leaves the plan unchanged


# ---- acquisition + solve --------------------------------------------------------------------
def test_acquisition_stores_every_pose_in_the_session_file(solved: AppState) -> None:
    frame = pd.DataFrame(solved.session.frame())
    assert len(frame) == 42 and solved.session_path.exists()
    np.testing.assert_allclose(frame[["x_o", "y_o", "z_o", "theta_deg"]].to_numpy(),
                               paper_grid().poses, atol=0.05)   # read back = commanded + noise
    assert "finished" in acquire.status_markdown(solved.progress)


def test_solve_recovers_the_simulated_truth_within_4_sigma(solved: AppState) -> None:
    view = solved.solve_view
    cal = view.calibration
    truth = solved.world.truth()
    assert cal.model == "schoenflies" and cal.n_used >= 40
    for name, value, sigma in zip(cal.names, cal.values, cal.sigma, strict=True):
        assert abs(value - truth[name]) <= 4 * sigma, (name, value, truth[name], sigma)
    assert view.errors.shape == (42, 3) and view.points.shape == (42, 3)
    assert np.max(np.abs(view.errors)) < 0.1                     # mm: no gross outlier
    # the eq-16 spots lie on the fitted plane within the residuals
    z_plane = cal.point("alpha") * view.points[:, 0] + cal.point("beta") * view.points[:, 1]
    assert np.max(np.abs(view.points[:, 2] - z_plane)) < 0.1
    assert view.seconds < 2.0


def test_results_table_uses_cli_json_names(solved: AppState) -> None:
    cal = solved.calibration
    table = solve.params_table(cal, solved.world.truth())
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:5]]
            for line in table.splitlines()[2:]}
    assert list(rows) == [*cal.to_json_dict()["params"], "gain"]
    value, sigma, truth = rows["x_t"]
    assert float(value) == pytest.approx(cal.point("x_t"), rel=1e-6)
    assert float(sigma) == pytest.approx(cal.to_json_dict()["sigma"]["x_t"], rel=0.05)
    assert float(truth) == pytest.approx(solved.world.truth()["x_t"], rel=1e-6)
    summary = solve.summary_markdown(solved.solve_view)
    assert "condition number" in summary and "| z |" in summary
    hist, scatter = solve.residual_figures(solved.solve_view)
    assert len(hist.data) == 3 and len(scatter.data) >= 3


def test_outlier_toggles_resolve_with_the_chosen_poses(solved: AppState) -> None:
    try:
        view = solved.worker.call("exclude", lambda: solve.toggle_pose(solved, 7, False))
        assert 7 in view.excluded and not view.robust
        assert view.calibration.n_used == 42 - 1 - len(view.flagged - {7})
        assert not view.used[list(view.pose_index).index(7)]
        view = solved.worker.call("include", lambda: solve.toggle_pose(solved, 7, True))
        assert 7 not in view.excluded and view.used[list(view.pose_index).index(7)]
    finally:
        solved.excluded.clear()
        solved.worker.call("solve", lambda: solve.run_solve(solved))


def test_export_csv_and_json_read_back(solved: AppState, tmp_path: Path) -> None:
    csv = tmp_path / "session.csv"
    csv.write_bytes(export.session_csv(solved))
    data = dataset_from_frame(read_table(csv), str(csv))
    assert len(data) == 42
    np.testing.assert_allclose(data.d, solved.session.frame()["d"].to_numpy(), atol=1e-8)
    back = BeamCalibration.from_json_dict(json.loads(export.solve_json(solved)))
    np.testing.assert_allclose(back.values, solved.calibration.values, rtol=1e-12)


def test_solve_and_export_without_data_give_operator_errors(app: AppState) -> None:
    with pytest.raises(InputError, match="no session"):
        solve.run_solve(app)
    with pytest.raises(InputError, match="no session"):
        export.session_csv(app)
    with pytest.raises(InputError, match="Solve H"):
        export.solve_json(app)


# ---- worker ---------------------------------------------------------------------------------
def test_worker_survives_failing_commands_and_reports_them() -> None:
    notes: list[tuple[str, str, str]] = []
    worker = Worker(lambda t, b, lvl: notes.append((t, b, lvl))).start()
    try:
        def bad() -> None:
            raise DriverError("sensor unplugged")
        with pytest.raises(DriverError):
            worker.call("read", bad)
        with pytest.raises(ZeroDivisionError):
            worker.call("oops", lambda: 1 / 0)
        assert worker.call("ok", lambda: 42) == 42
    finally:
        worker.stop()
    assert notes[0] == ("read", "sensor unplugged", "error")
    assert notes[1][2] == "error" and "ZeroDivisionError" in notes[1][1]


def test_worker_runs_commands_in_order_on_one_thread() -> None:
    seen: list[tuple[int, str]] = []
    worker = Worker(lambda *a: None).start()
    try:
        futures = [worker.submit(f"c{i}", lambda i=i: seen.append(
            (i, threading.current_thread().name))) for i in range(20)]
        for f in futures:
            f.result(5)
    finally:
        worker.stop()
    assert [i for i, _ in seen] == list(range(20))
    assert {name for _, name in seen} == {"lasercal-worker"}


def test_idle_faults_notify_once_per_distinct_message() -> None:
    notes: list[str] = []
    calls = [0]

    def idle() -> None:
        calls[0] += 1
        raise DriverError("sensor stuck at +99.999")
    worker = Worker(lambda t, b, lvl: notes.append(b), idle=idle, idle_period_s=0.005).start()
    time.sleep(0.2)
    worker.stop()
    assert calls[0] > 5 and notes == ["sensor stuck at +99.999"]


def test_live_idle_hook_publishes_pose_and_reading(app: AppState) -> None:
    app.latest = None
    deadline = time.monotonic() + 5
    while app.latest is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert app.latest is not None and app.latest.reading is not None
    assert app.latest.reading.ok


def test_status_and_eta_formatting() -> None:
    assert acquire.format_eta(None) == "-"
    assert acquire.format_eta(42.4) == "42 s"
    assert acquire.format_eta(600) == "10.0 min"


def test_existing_session_opens_for_review(solved: AppState) -> None:
    review = AppState(None, load_workcell(None), sim=False, session_path=solved.session_path)
    review.worker.start()
    try:
        review.worker.call("open", lambda: review.open_session(solved.session_path))
        assert len(review.grid) == 42 and not review.connected
        points, index = acquire.spots_of_session(review)
        assert points.shape == (42, 3) and list(index) == list(range(42))
        view = review.worker.call("solve", lambda: solve.run_solve(review))   # no hardware
        np.testing.assert_allclose(view.calibration.values, solved.calibration.values,
                                   rtol=1e-9, atol=1e-12)
        assert "Solve #1:" in solve.summary_markdown(view)
    finally:
        review.worker.stop()
        review.close_session()


def test_only_the_tab_in_control_moves_until_handed_over(app: AppState) -> None:
    app.armed = True
    jog.jog(app, "x", 1, 0.5, client_id=1).result(10)     # first tab takes control
    assert app.controller == 1
    before = app.world.true_pose
    with pytest.raises(MotionRefused, match="tab #1 holds control"):
        jog.jog(app, "x", 1, 0.5, client_id=2)
    with pytest.raises(MotionRefused, match="holds control"):
        jog.go_to(app, 0.0, 0.0, 20.0, 0.0, client_id=2)
    assert app.world.true_pose == before
    app.take_control(2)                                     # explicit hand-over
    jog.jog(app, "y", -1, 0.5, client_id=2).result(10)
    with pytest.raises(MotionRefused):
        jog.jog(app, "x", 1, 0.5, client_id=1)
    assert any("handed over" in body for _, _, _, body in app.messages)
    app.release_control(2)                                  # tab closed
    assert app.controller is None
    app.stop_motion()                                       # STOP needs no control
    assert not app.armed


def test_chessboard_calibration_of_the_rendered_sim_camera(app: AppState) -> None:
    from app.panels import setup

    assert "needs no calibration" in app.worker.call("cal", lambda: setup.calibrate_camera(app))
    app.sim_camera = "rendered"
    app.worker.call("connect", app.connect_sim)
    message = app.worker.call("cal", lambda: setup.calibrate_camera(app), 60)
    rms_um = float(message.split("(")[1].split(" µm")[0])
    assert "192 corners" in message and rms_um < 5.0
    spot = app.worker.call("spot", app.camera.measure_spot, 30)
    truth = app.world.true_spot()
    assert spot.ok and np.hypot(spot.x - truth[0], spot.y - truth[1]) < 0.05


def test_stop_ends_a_move_in_flight_within_100_ms(app: AppState) -> None:
    app.sim_move_time_s = 2.0
    app.worker.call("reconnect", app.connect_sim)
    app.armed = True
    future = jog.jog(app, "x", 1, 5.0)
    time.sleep(0.3)                                  # the move is under way
    t0 = time.perf_counter()
    app.stop_motion()
    with pytest.raises(DriverError, match="stopped"):
        future.result(5)
    latency = time.perf_counter() - t0
    assert latency < 0.1, latency
    x = app.world.true_pose.x
    assert 0.2 < x < 2.0                              # stopped part-way (about 0.75 mm)


def test_a_reconnecting_tab_gets_the_current_state(tmp_path: Path) -> None:
    """A websocket client opened after a solve receives the spots and the results table."""
    import msgspec.msgpack
    import viser
    import zstandard
    from websockets.sync.client import connect

    from app.panels import build_dashboard
    from app.server import GuardedServer

    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    state = build_dashboard(server.viser, load_workcell(None), session_path=tmp_path / "s.db")
    try:
        state.sim_move_time_s = 0.0
        state.worker.call("connect", state.connect_sim)
        state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 60)
        state.worker.call("solve", lambda: solve.run_solve(state), 60)
        x_t = f"{state.calibration.point('x_t'):.7g}"
        texts: list[str] = []
        names: set[str] = set()
        dctx = zstandard.ZstdDecompressor()
        with connect(f"ws://127.0.0.1:{guard.port}/?token={guard.token}",
                     subprotocols=[f"viser-v{viser.__version__}"],
                     additional_headers={"Origin": f"http://127.0.0.1:{guard.port}"},
                     max_size=None) as ws:
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and not any(x_t in t for t in texts):
                frame = ws.recv(timeout=5)
                size, csize = (int.from_bytes(frame[k:k + 8], "little") for k in (0, 8))
                payload = msgspec.msgpack.decode(dctx.decompress(frame[16:16 + csize],
                                                                 max_output_size=size))
                for m in payload["messages"]:
                    names.add(str(m.get("name", "")))
                    texts.append(str(m))
        assert any(x_t in t and "z_t_minus_delta" in t for t in texts)
        assert {"/cell/spots", "/cell/fitted_plane", "/cell/errors", "/cell/glass_plate",
                "/cell/flange", "/cell/live_spot"} <= names
    finally:
        state.worker.stop()
        state.close_session()
        server.stop()


def test_dashboard_drives_the_serial_drivers_over_emulated_devices(tmp_path: Path) -> None:
    """Hardware path: GRBL and Keyence drivers over pty emulators of the simulated cell."""
    from drivers.emulators.cell import CellEmulators
    from drivers.grbl import GrblRobot
    from drivers.keyence_il import KeyenceIL
    from drivers.sim.devices import SimCameraDirect
    from drivers.sim.world import SimWorld

    workcell = load_workcell(None)
    world = SimWorld(workcell, seed=11)
    state = AppState(None, workcell, sim=False, session_path=tmp_path / "hw.db")
    with CellEmulators(world) as emu:
        state.worker.start()
        try:
            state.worker.call("attach", lambda: state.attach(
                GrblRobot(emu.grbl.path, workcell.limits), KeyenceIL(emu.keyence.path),
                SimCameraDirect(world)), 30)
            assert not state.sim and state.connected
            state.armed = True
            jog.jog(state, "y", 1, 0.75, client_id=1).result(30)
            assert world.true_pose.y == pytest.approx(0.75, abs=1e-3)
            state.armed = False
            progress = state.worker.call("acquire",
                                         lambda: acquire.run_acquisition(state, 1), 120)
            assert progress.state == "finished" and progress.done == 42
            view = state.worker.call("solve", lambda: solve.run_solve(state), 60)
            truth = world.truth()
            for name, value, sigma in zip(view.calibration.names, view.calibration.values,
                                          view.calibration.sigma, strict=True):
                assert abs(value - truth[name]) <= 4 * sigma, (name, value, truth[name], sigma)
        finally:
            state.worker.stop()
            state.close_session()
            state.disconnect()
