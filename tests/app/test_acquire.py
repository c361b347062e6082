"""Acquisition runner and the acquire/export commands against the simulated workcell."""

from __future__ import annotations

import io
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.acquisition import Progress, Runner, RunnerConfig
from app.session import Session, read_session_frame
from calib_core.calibrate import solve
from calib_core.grid import make_grid, paper_grid
from calib_core.io import dataset_from_frame, load_dataset
from drivers.base import (
    DriverError,
    FlangePose,
    ReadingStatus,
    SensorReading,
    SpotMeasurement,
)
from drivers.sim.devices import SimCameraDirect, SimRobot, SimSensor
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld

ROOT = Path(__file__).resolve().parents[2]


def _devices(seed: int = 0):
    world = SimWorld(load_workcell(), seed=seed)
    return world, SimRobot(world), SimSensor(world), SimCameraDirect(world)


def test_simulated_session_recovers_the_workcell_truth(tmp_path: Path) -> None:
    world, robot, sensor, camera = _devices(seed=0)
    seen: list[Progress] = []
    with Session.create(tmp_path / "s.db", paper_grid()) as session:
        result = Runner(session, robot, sensor, camera, RunnerConfig(samples_per_pose=3),
                        on_progress=seen.append).run()
    assert (result.state, result.done, result.total, result.skipped) == ("finished", 42, 42, 0)
    done = [p.done for p in seen if p.state == "running" and p.current is not None]
    assert done == list(range(1, 43))
    assert all(p.eta_s is not None and p.last is not None for p in seen[2:])
    frame = read_session_frame(tmp_path / "s.db")
    assert frame["pose_index"].tolist() == list(range(42))
    # the stored pose is the robot's read-back: commanded + repeatability (robot_xy 2.5 um)
    dx = frame[["x_o", "y_o"]].to_numpy() - paper_grid().poses[:, :2]
    assert 0.5e-3 < dx.std() < 5e-3
    cal = solve(dataset_from_frame(frame, "s.db")).to_json_dict()
    truth = world.truth()
    assert cal["model"] == "schoenflies" and cal["n_used"] == 42
    for name, value in cal["params"].items():
        assert abs(value - truth[name]) < 3 * cal["sigma"][name], name


class FlakySensor:
    """Out-of-range at the poses in ``bad``; once invalid (then fine) at the poses in ``once``."""

    def __init__(self, inner: SimSensor, robot: SimRobot, bad: set[int], once: set[int],
                 grid) -> None:
        self.inner, self.robot, self.bad, self.once, self.grid = inner, robot, bad, once, grid
        self.reads = 0

    def _pose_index(self) -> int:
        p = self.robot.world.true_pose.as_array()
        return int(np.argmin(np.abs(self.grid.poses - p).sum(axis=1)))

    def read(self) -> SensorReading:
        self.reads += 1
        i = self._pose_index()
        if i in self.bad:
            return SensorReading(ReadingStatus.OUT_OF_RANGE, raw="+99.999")
        if i in self.once:
            self.once.discard(i)
            return SensorReading(ReadingStatus.INVALID, raw="+EE.EEE")
        return self.inner.read()

    def zero(self) -> None: ...

    def close(self) -> None: ...


def test_invalid_readings_are_retried_then_skipped_with_reason(tmp_path: Path) -> None:
    grid = paper_grid()
    _, robot, sensor, camera = _devices()
    flaky = FlakySensor(sensor, robot, bad={3}, once={7}, grid=grid)
    with Session.create(tmp_path / "s.db", grid) as session:
        result = Runner(session, robot, flaky, camera,
                        RunnerConfig(samples_per_pose=2, max_retries=2)).run()
        samples = {s.pose_index: s for s in session.samples()}
        assert (result.done, result.skipped) == (42, 1)
        assert samples[3].status == "skipped" and samples[3].d is None
        assert samples[3].reason == "sensor out-of-range (+99.999) (3 attempt(s))"
        assert samples[7].ok and samples[7].attempts == 2 and samples[7].n_readings == 2
        assert len(read_session_frame(tmp_path / "s.db")) == 41
        flaky.bad = set()  # fixed: measure the skipped pose again, nothing else
        reads = flaky.reads
        result = Runner(session, robot, flaky, camera,
                        RunnerConfig(samples_per_pose=2, retry_skipped=True)).run()
        assert (result.done, result.skipped) == (42, 0) and flaky.reads == reads + 2
        assert session.samples()[7] == samples[7]


class NoSpotCamera(SimCameraDirect):
    def measure_spot(self) -> SpotMeasurement:
        return SpotMeasurement(False, reason="no spot in the camera's view")


def test_no_spot_skips(tmp_path: Path) -> None:
    world, robot, sensor, _ = _devices()
    grid = make_grid([20], [0], [0, 1])
    with Session.create(tmp_path / "s.db", grid) as session:
        Runner(session, robot, sensor, NoSpotCamera(world), RunnerConfig(max_retries=1)).run()
        assert [s.reason for s in session.samples()] == [
            "camera: no spot in the camera's view (2 attempt(s))"] * 2


class FailingRobot(SimRobot):
    """Raises DriverError on every move while ``broken`` is set."""

    def __init__(self, world: SimWorld) -> None:
        super().__init__(world)
        self.broken = threading.Event()
        self.moves = 0

    def move_to(self, target: FlangePose) -> FlangePose:
        self.moves += 1
        if self.broken.is_set():
            raise DriverError("robot: serial port /dev/ttyUSB0 vanished")
        return super().move_to(target)


def test_driver_error_pauses_then_resume_continues(tmp_path: Path) -> None:
    world, _, sensor, camera = _devices()
    robot = FailingRobot(world)

    def on_progress(p: Progress) -> None:
        if p.done == 10 and p.state == "running":
            robot.broken.set()

    with Session.create(tmp_path / "s.db", paper_grid()) as session:
        runner = Runner(session, robot, sensor, camera,
                        RunnerConfig(samples_per_pose=1, driver_retries=2,
                                     driver_retry_delay_s=0.0, return_on_pause=True),
                        on_progress=on_progress)
        result = runner.run()
        assert result.state == "paused" and result.done == 10
        assert result.message == ("pose 10: robot: serial port /dev/ttyUSB0 vanished; "
                                  "fix the device, then resume")
        assert robot.moves == 10 + 3  # the failing pose was tried 1 + 2 times
        assert ("driver-error", "pose 10: robot: serial port /dev/ttyUSB0 vanished") in [
            e[1:] for e in session.events()]
        # reconnect (a new robot object) and continue
        runner.set_devices(robot=SimRobot(world))
        runner.resume()
        result = runner.run()
        assert (result.state, result.done) == ("finished", 42)
        assert sorted(s.pose_index for s in session.samples()) == list(range(42))


def test_pause_blocks_until_resume_and_abort_drops_nothing_stored(tmp_path: Path) -> None:
    _, robot, sensor, camera = _devices()
    states: list[str] = []
    with Session.create(tmp_path / "s.db", paper_grid()) as session:
        runner: Runner

        def on_progress(p: Progress) -> None:
            states.append(p.state)
            if p.done == 5 and p.state == "running":
                runner.pause()
                threading.Timer(0.2, runner.resume).start()
            if p.done == 20 and p.state == "running":
                runner.abort()

        runner = Runner(session, robot, sensor, camera, RunnerConfig(samples_per_pose=1),
                        on_progress=on_progress)
        t0 = time.monotonic()
        result = runner.run()
        assert time.monotonic() - t0 >= 0.2
        assert "paused" in states and (result.state, result.done) == ("aborted", 20)
        assert session.pending_indices() == list(range(20, 42))
        result = Runner(session, robot, sensor, camera).run()  # a later run resumes
        assert (result.state, result.done) == ("finished", 42)


def test_robot_not_at_target_is_a_driver_error(tmp_path: Path) -> None:
    world, _, sensor, camera = _devices()

    class Lazy(SimRobot):  # reports Idle before the pose is reached
        def move_to(self, target: FlangePose) -> FlangePose:
            super().move_to(target)
            return replace(target, x=target.x + 0.5)

    with Session.create(tmp_path / "s.db", make_grid([20], [0], [0])) as session:
        result = Runner(session, Lazy(world), sensor, camera,
                        RunnerConfig(driver_retries=0, return_on_pause=True)).run()
    assert result.state == "paused" and "not at the target" in result.message
    assert result.done == 0


# ---- the commands, as subprocesses -------------------------------------------------------
def _lasercal(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def test_acquire_export_and_refusals(tmp_path: Path) -> None:
    db, out = tmp_path / "s.db", tmp_path / "s.csv"
    r = _lasercal("acquire", "--session", str(db), "--sim-camera", "direct", "--samples", "2")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"session {db}: 42/42 poses stored")
    assert "[##############################] 42/42" in r.stderr
    r = _lasercal("acquire", "--session", str(db))
    assert r.returncode == 2
    assert r.stderr == (f"error: {db}: session file already exists; continue it with "
                        "--resume or choose another file\n")
    r = _lasercal("acquire", "--session", str(db), "--resume")  # nothing left to do
    assert r.returncode == 0 and "42/42 poses stored" in r.stdout
    r = _lasercal("export", str(db), "--csv", str(out))
    assert r.returncode == 0, r.stderr
    exported = load_dataset(out)  # the solve format
    r = _lasercal("export", str(db), "--csv", "-", "--all")
    full = pd.read_csv(io.StringIO(r.stdout), comment="#")
    assert r.returncode == 0 and len(full) == 42 and set(full["status"]) == {"ok"}
    assert {"cmd_x", "reason", "d_std", "n_readings", "timestamp"} <= set(full.columns)
    assert (full["n_readings"] == 2).all()
    frame = read_session_frame(db)
    np.testing.assert_allclose(exported.d, frame["d"], rtol=1e-8)
    assert exported.extra["pose_index"].astype(int).tolist() == list(range(42))
    with Session.open(db, readonly=True) as s:
        assert s.meta_json("settings")["samples_per_pose"] == 2
        assert s.meta_json("noise")["camera"] == 0.0031
        assert "SimRobot" in s.meta_json("drivers")["robot"]
        assert "[beam]" in s.meta["workcell"]
    r = _lasercal("acquire", "--session", str(tmp_path / "x.db"), "--robot-port", "/dev/null")
    assert r.returncode == 2 and "needs --sensor-port, --camera, --camera-calib too" in r.stderr
    assert not (tmp_path / "x.db").exists()
    r = _lasercal("acquire", "--session", str(tmp_path / "x.db"), "--preview")
    assert r.returncode == 0 and len(r.stdout.splitlines()) == 44
    r = _lasercal("export", str(tmp_path / "none.db"), "--csv", str(out))
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "no such" in r.stderr


def test_sigkill_mid_session_then_resume_loses_and_duplicates_nothing(tmp_path: Path) -> None:
    db = tmp_path / "k.db"
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "acquire", "--sim", "--session", str(db), "--settle",
         "0.05", "--sim-camera", "direct", "--seed", "3"],
        cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    assert proc.stderr is not None
    try:
        for line in proc.stderr:  # one line per stored pose (stderr is not a terminal)
            if line.startswith("[") and " 15/42 " in line:
                break
        else:
            pytest.fail("acquire ended before 15 poses")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert Path(f"{db}-wal").exists()  # killed: nothing was checkpointed on close
    with Session.open(db, readonly=True) as s:
        before = {x.pose_index: x for x in s.samples()}
    assert 15 <= len(before) < 42
    assert sorted(before) == list(range(len(before)))

    r = _lasercal("acquire", "--sim", "--session", str(db), "--resume", "--sim-camera",
                  "direct")
    assert r.returncode == 0, r.stderr
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    indices = [row[0] for row in con.execute("SELECT pose_index FROM samples")]
    con.close()
    assert len(indices) == 42 and sorted(indices) == list(range(42))
    with Session.open(db, readonly=True) as s:
        after = {x.pose_index: x for x in s.samples()}
        assert [e[1] for e in s.events()].count("resume") == 1
    for i, sample in before.items():
        assert after[i] == sample  # unchanged, same timestamp
    assert min(after[i].timestamp for i in after if i not in before) > max(
        x.timestamp for x in before.values())
    frame = pd.read_csv(io.StringIO(_lasercal("export", str(db), "--csv", "-").stdout),
                        comment="#")
    assert len(frame) == 42


def test_hardware_drivers_over_pty_emulators(tmp_path: Path) -> None:
    """GrblRobot and KeyenceIL through their pty emulators, whose physics follow one SimWorld;
    a GRBL error is retried, a stuck sensor skips its pose, the rest solves to the truth."""
    from drivers.emulators import GrblEmulator, KeyenceEmulator
    from drivers.grbl import GrblRobot
    from drivers.keyence_il import KeyenceIL

    world = SimWorld(load_workcell(), seed=11)
    noise = world.workcell.noise
    grbl = GrblEmulator(start=(0.0, 0.0, 20.0, 0.0)).start()

    def pose() -> FlangePose:
        return FlangePose(*grbl.position)

    def displacement() -> float | None:
        hit = world.beam_hit(pose())
        return None if hit is None else hit.s + float(world.normal()) * noise.sensor

    class PtyWorldCamera(SimCameraDirect):  # the spot where the emulated robot really is
        def measure_spot(self) -> SpotMeasurement:
            hit = world.beam_hit(pose())
            xy = hit.p[:2] + world.normal(2) * noise.camera
            return SpotMeasurement(True, float(xy[0]), float(xy[1]), quality=1.0)

    keyence = KeyenceEmulator(displacement).start()
    robot = GrblRobot(grbl.path, world.workcell.limits)
    sensor = KeyenceIL(keyence.path)
    try:
        grbl.inject("error", code=33, match="G90")  # the first move is rejected once
        keyence.inject("stuck", count=2, match="SR")  # +99.999 for both attempts at pose 0
        grid = paper_grid()
        with Session.create(tmp_path / "hw.db", grid) as session:
            runner = Runner(session, robot, sensor, PtyWorldCamera(world),
                            RunnerConfig(samples_per_pose=2, max_retries=1,
                                         driver_retry_delay_s=0.0))
            result = runner.run()
            samples = session.samples()
            events = session.events()
    finally:
        robot.close()
        sensor.close()
        grbl.close()
        keyence.close()
    assert (result.state, result.done, result.skipped) == ("finished", 42, 1)
    assert samples[0].status == "skipped"
    assert samples[0].reason == "sensor out-of-range (+99.999) (2 attempt(s))"
    assert not any(kind == "driver-error" for _, kind, _ in events)  # retried in place
    g90 = [line for line in grbl.received if line.startswith("G90")]
    assert len(g90) == 43  # 42 moves + the rejected one
    frame = read_session_frame(tmp_path / "hw.db")
    assert len(frame) == 41
    np.testing.assert_allclose(frame[["x_o", "y_o", "z_o", "theta_deg"]].to_numpy(),
                               grid.poses[1:], atol=1e-3)  # read back from GRBL, 3 decimals
    cal = solve(dataset_from_frame(frame, "hw.db")).to_json_dict()
    truth = world.truth()
    for name, value in cal["params"].items():
        assert abs(value - truth[name]) < 3 * cal["sigma"][name], name


def test_grid_outside_soft_limits_is_refused_before_anything(tmp_path: Path) -> None:
    grid_file = tmp_path / "g.csv"
    grid_file.write_text("x_o,y_o,z_o,theta_deg\n0,0,20,0\n0,0,60,0\n")
    db = tmp_path / "s.db"
    r = _lasercal("acquire", "--session", str(db), "--grid", str(grid_file), "--quiet")
    assert r.returncode == 2
    assert r.stderr == ("error: grid pose 1: target z=60 is outside the soft limits [0, 40]; "
                        "nothing was sent to the robot; fix the grid or the limits "
                        "(no pose was measured)\n")
    assert not db.exists()
    r = _lasercal("acquire", "--session", str(db), "--resume")
    assert r.returncode == 2 and "start a new session without --resume" in r.stderr
    r = _lasercal("acquire", "--session", str(db), "--resume", "--grid", "paper")
    assert r.returncode == 2
    assert r.stderr == ("error: --grid cannot change on --resume: the session file keeps "
                        "its own\n")


def test_skips_in_a_row_pause_and_the_last_pose_is_measured_again(tmp_path: Path) -> None:
    grid = paper_grid()
    _, robot, sensor, camera = _devices()
    stuck = FlakySensor(sensor, robot, bad=set(range(6, 42)), once=set(), grid=grid)
    with Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, stuck, camera,
                        RunnerConfig(samples_per_pose=1, max_retries=1, return_on_pause=True))
        result = runner.run()
        assert (result.state, result.done, result.skipped) == ("paused", 8, 2)
        assert result.message == (
            "pose 8: 3 poses in a row could not be measured (last: sensor out-of-range "
            "(+99.999) (2 attempt(s))); the pose is not stored and will be measured again; "
            "fix the device, then resume")
        stuck.bad = set()  # the operator fixed the sensor
        runner.resume()
        result = runner.run()
        assert (result.state, result.done, result.skipped) == ("finished", 42, 2)
        assert session.stored_indices("skipped") == {6, 7}
        assert [e[1] for e in session.events()].count("skip-streak") == 1


def test_cli_session_with_rendered_camera_solves_to_the_workcell_truth(tmp_path: Path) -> None:
    """The default simulated session (frames rendered and measured by the OpenCV detector),
    then ``lasercal solve SESSION.db --json``: H within 3 reported sigma of the truth."""
    import json

    db = tmp_path / "s.db"
    r = _lasercal("acquire", "--session", str(db), "--quiet", "--seed", "1")
    assert r.returncode == 0, r.stderr
    with Session.open(db, readonly=True) as s:
        assert "SimCamera" in s.meta_json("drivers")["camera"]
        assert "SimCameraDirect" not in s.meta_json("drivers")["camera"]
    r = _lasercal("solve", str(db), "--json")
    assert r.returncode == 0, r.stderr
    cal = json.loads(r.stdout)
    truth = load_workcell().truth()
    assert cal["n_used"] == 42
    for name, value in cal["params"].items():
        assert abs(value - truth[name]) < 3 * cal["sigma"][name], name


def test_stop_during_a_move_pauses_without_moving_again(tmp_path: Path) -> None:
    world, _, sensor, camera = _devices()

    class Counting(SimRobot):
        moves = 0

        def move_to(self, target: FlangePose) -> FlangePose:
            Counting.moves += 1
            return super().move_to(target)

    robot = Counting(world, move_time_s=0.3)
    with Session.create(tmp_path / "s.db", paper_grid()) as session:
        runner = Runner(session, robot, sensor, camera,
                        RunnerConfig(samples_per_pose=1, driver_retries=3,
                                     return_on_pause=True))

        def stop() -> None:  # what the dashboard's STOP button does
            runner.pause("STOP pressed by the operator")
            robot.stop()

        threading.Timer(0.45, stop).start()  # mid-way through the second move
        t0 = time.monotonic()
        result = runner.run()
        assert time.monotonic() - t0 < 0.8
        assert (result.state, result.done, Counting.moves) == ("paused", 1, 2)
        assert result.message == "STOP pressed by the operator"
        assert ("driver-error", "pose 1: motion stopped before reaching the target") in [
            e[1:] for e in session.events()]
        runner.resume()
        robot.move_time_s = 0.0
        assert runner.run().done == 42
