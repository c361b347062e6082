"""Serial faults injected through the GRBL and Keyence pty emulators, on the whole stack.

The real drivers (:class:`GrblRobot`, :class:`KeyenceIL`) talk to emulators that follow one
simulated workcell; the acquisition :class:`Runner` stores into a real session file. Each test
injects one fault and asserts what the software did: the operator message, the bounded retries
(counted in the emulator's received lines), the run paused (not crashed), the samples in the
session file (none lost, none duplicated, none wrong), and reconnect-and-continue.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from app.acquisition import Runner, RunnerConfig
from app.session import Session
from drivers.base import DeviceTimeout, DriverError, FlangePose, ReadingStatus
from drivers.emulators import CellEmulators
from drivers.grbl import GrblAlarm, GrblError, GrblRobot
from drivers.keyence_il import KeyenceError, KeyenceIL
from drivers.serial_port import PortLost
from drivers.sim.devices import SimCameraDirect
from drivers.sim.world import SimWorld
from tests.faults.conftest import SENSOR_TOL, TIMEOUT, small_grid

CONFIG = RunnerConfig(samples_per_pose=1, return_on_pause=True, driver_retries=1,
                      driver_retry_delay_s=0.02, max_retries=1)


def _devices(cell: CellEmulators, robot_path: str | None = None) -> tuple[GrblRobot, KeyenceIL]:
    robot = GrblRobot(robot_path or cell.grbl.path, cell.world.workcell.limits,
                      timeout=TIMEOUT, retries=2, settle_timeout=0.4)
    return robot, KeyenceIL(cell.keyence.path, timeout=TIMEOUT, retries=2)


def _assert_complete_and_true(session: Session, world: SimWorld, n: int,
                              skipped: set[int] = frozenset()) -> None:
    """Every pose stored exactly once; good samples hold their own pose's displacement."""
    samples = session.samples()
    assert sorted(s.pose_index for s in samples) == list(range(n))
    grid = session.grid
    for s in samples:
        assert s.ok == (s.pose_index not in skipped), (s.pose_index, s.reason)
        if s.ok:
            hit = world.beam_hit(FlangePose(*grid.pose(s.pose_index)))
            assert s.d == pytest.approx(hit.s, abs=SENSOR_TOL), s.pose_index


def _on_disk(path: Path) -> list[int]:
    """Pose indices stored in the file, read by a second connection (what survives a crash)."""
    with Session.open(path, readonly=True) as other:
        return sorted(s.pose_index for s in other.samples())


# ---- the port vanishes ---------------------------------------------------------------------
def test_robot_unplugged_mid_run_pauses_then_continues_on_a_new_port(
        cell: CellEmulators, tmp_path: Path) -> None:
    """The GRBL port vanishes while the 8th move is sent (adapter unplugged): the run pauses
    with a message naming the port; every stored sample is in the file; the adapter comes
    back under another name; Runner.set_devices + run completes with no loss or duplicate."""
    grid, db = small_grid(12), tmp_path / "s.db"
    cell.grbl.inject("vanish", match="G90 G1", skip=7)
    robot, sensor = _devices(cell)
    with sensor, Session.create(db, grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 7)
        assert "pose 7: GRBL controller port" in paused.message
        assert "unplugged" in paused.message or "plug the device back" in paused.message
        assert paused.message.endswith("fix the device, then resume")
        assert _on_disk(db) == list(range(7))                 # committed, visible to others
        assert any(kind == "driver-error" for _, kind, _ in session.events())
        robot.close()
        new_path = cell.grbl.replug()                          # a new device name
        with GrblRobot(new_path, cell.world.workcell.limits, timeout=TIMEOUT,
                       settle_timeout=0.4) as robot2:
            runner.set_devices(robot=robot2)
            runner.resume()
            done = runner.run()
        assert (done.state, done.done, done.skipped) == ("finished", 12, 0)
        _assert_complete_and_true(session, cell.world, 12)


def test_sensor_port_lost_is_a_port_lost_error_then_reconnects(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        robot.move_to(FlangePose(0, 0, 20, 0))
        cell.keyence.vanish()
        with pytest.raises(PortLost, match=r"Keyence DL-RS1A port .* lost"):
            sensor.read()
        with pytest.raises(PortLost, match="still missing"):   # no hang, no crash
            sensor.read()
        sensor.reconnect(cell.keyence.replug())
        assert sensor.read().value == pytest.approx(
            cell.world.beam_hit(FlangePose(0, 0, 20, 0)).s, abs=SENSOR_TOL)


# ---- timeouts ----------------------------------------------------------------------------
def test_sensor_timeout_bounded_retries_then_device_timeout(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        cell.keyence.inject("silent", count=-1)
        n0 = len(cell.keyence.received)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"did not answer SR,00,037 within 0.15 s "
                                                r"\(3 attempts\)"):
            sensor.read()
        elapsed = time.monotonic() - t0
        assert cell.keyence.received[n0:] == ["SR,00,037"] * 3   # exactly retries + 1 sends
        assert 3 * TIMEOUT <= elapsed < 3 * TIMEOUT + 1.0          # bounded: no hang
        cell.keyence.clear_faults()
        cell.keyence.inject("silent", count=2)                   # two lost replies: recovered
        assert sensor.read().ok


def test_robot_status_timeout_bounded_then_device_timeout(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        cell.grbl.inject("silent", count=-1, match="?")
        n0 = len(cell.grbl.received)
        with pytest.raises(DeviceTimeout, match=r"did not answer '\?'.*3 attempts"):
            robot.read_pose()
        assert cell.grbl.received[n0:] == ["?"] * 3


def test_run_pauses_on_a_silent_sensor_and_resumes(cell: CellEmulators, tmp_path: Path) -> None:
    grid = small_grid(6)
    cell.keyence.inject("silent", count=-1, match="SR", skip=3)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 3)
        assert "pose 3: Keyence DL-RS1A" in paused.message and "did not answer" in paused.message
        cell.keyence.clear_faults()
        runner.resume()
        assert runner.run().state == "finished"
        _assert_complete_and_true(session, cell.world, 6)


# ---- garbage, truncated lines, ER replies ------------------------------------------------
@pytest.mark.parametrize("kind", ["garbage", "truncate", "noise"])
def test_garbled_sensor_replies_are_retried_and_never_stored(
        cell: CellEmulators, tmp_path: Path, kind: str) -> None:
    """Every second reply garbled / cut in half / preceded by junk: the driver re-sends, the
    session holds the true displacements only."""
    grid = small_grid(6)
    robot, sensor = _devices(cell)
    for k in range(6):
        cell.keyence.inject(kind, match="SR", skip=1 if k else 0)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        done = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG).run()
        assert done.state == "finished"
        _assert_complete_and_true(session, cell.world, 6)


def test_persistent_garbage_is_a_clear_error_not_a_timeout(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        cell.keyence.inject("garbage", count=-1)
        with pytest.raises(DriverError, match="sent unusable replies to SR,00,037 "
                                              r"\(3 attempts") as info:
            sensor.read()
        assert not isinstance(info.value, DeviceTimeout)
        cell.grbl.inject("truncate", count=-1, match="?")
        with pytest.raises(DriverError, match=r"GRBL controller .* unusable replies"):
            robot.read_pose()


@pytest.mark.parametrize(("code", "meaning"), [
    (0, "ER 00 invalid command"), (22, "ER 22 parameter out of range"),
    (65, "ER 65 no amplifier with this ID")])
def test_er_reply_pauses_the_run_with_its_meaning(
        cell: CellEmulators, tmp_path: Path, code: int, meaning: str) -> None:
    grid = small_grid(5)
    cell.keyence.inject("er", count=-1, code=code, match="SR", skip=2)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 2)
        assert f"Keyence DL-RS1A on {sensor.port} refused SR: {meaning}" in paused.message
        # ER is an answer, not a transport fault: one send per driver attempt (no re-sends)
        assert cell.keyence.received.count("SR,00,037") == 2 + CONFIG.driver_retries + 1
        cell.keyence.clear_faults()
        runner.resume()
        assert runner.run().state == "finished"
        _assert_complete_and_true(session, cell.world, 5)


def test_er29_communication_error_is_retried_within_the_budget(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        cell.keyence.inject("er", count=2, code=29)
        assert sensor.read().ok
        cell.keyence.inject("er", count=-1, code=29)
        with pytest.raises(KeyenceError, match=r"ER 29 communication error .*persisting"):
            sensor.read()


# ---- GRBL error:N / ALARM:N --------------------------------------------------------------
def test_grbl_error_pauses_the_run_with_its_meaning(cell: CellEmulators, tmp_path: Path) -> None:
    grid = small_grid(5)
    cell.grbl.inject("error", count=2, code=33, match="G90 G1", skip=3)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 3)
        assert "rejected 'G90 G1" in paused.message
        assert "error:33 motion target invalid" in paused.message
        runner.resume()
        assert runner.run().state == "finished"
        _assert_complete_and_true(session, cell.world, 5)


def test_grbl_alarm_pauses_locks_motion_until_unlocked(
        cell: CellEmulators, tmp_path: Path) -> None:
    grid = small_grid(5)
    cell.grbl.inject("alarm", code=1, match="G90 G1", skip=2)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 2)
        assert "ALARM:1 hard limit triggered" in paused.message
        runner.resume()                                  # resume without unlocking: refused
        again = runner.run()
        assert again.state == "paused" and "Alarm state" in again.message
        assert again.done == 2
        with pytest.raises(GrblAlarm):
            robot.move_to(FlangePose(0, 0, 20, 0))
        robot.unlock()                                   # the operator checked the machine
        runner.resume()
        assert runner.run().state == "finished"
        _assert_complete_and_true(session, cell.world, 5)
    assert "$X" in cell.grbl.received


def test_grbl_error_reply_to_a_command_is_a_grbl_error(cell: CellEmulators) -> None:
    robot, sensor = _devices(cell)
    with robot, sensor:
        cell.grbl.inject("error", code=9, match="G90")
        with pytest.raises(GrblError, match="error:9 G-code locked out during alarm"):
            robot.move_to(FlangePose(1, 1, 20, 0))


# ---- Idle before the pose is reached --------------------------------------------------------
def test_idle_before_the_pose_is_reached_is_detected_not_stored(
        cell: CellEmulators, tmp_path: Path) -> None:
    """The controller says Idle (and ok to G4 P0) while the axes stall half-way: the driver
    sees Idle away from the target and raises; nothing is stored for that pose."""
    grid = small_grid(5)
    cell.grbl.inject("early_idle", count=2, match="G90 G1", skip=2, stall=True)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done) == ("paused", 2)
        assert "reports Idle at" in paused.message and "the pose was not reached" in paused.message
        assert session.stored_indices() == {0, 1}
        runner.resume()
        assert runner.run().state == "finished"
        _assert_complete_and_true(session, cell.world, 5)


def test_early_idle_then_arrival_is_measured_at_the_target(
        cell: CellEmulators, tmp_path: Path) -> None:
    """Idle reported 0.25 s early, the axes arrive later: the driver waits for the real
    arrival, so the stored displacement is the target pose's, not a pose on the way."""
    grid = small_grid(4)
    cell.grbl.inject("early_idle", count=-1, match="G90 G1", seconds=0.25)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        done = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG).run()
        assert done.state == "finished"
        _assert_complete_and_true(session, cell.world, 4)


# ---- a sensor stuck at +99.999 ------------------------------------------------------------
def test_stuck_sensor_is_out_of_range_skipped_then_the_run_pauses(
        cell: CellEmulators, tmp_path: Path) -> None:
    grid = small_grid(8)
    robot, sensor = _devices(cell)
    with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
        robot.move_to(FlangePose(*grid.pose(0)))
        cell.keyence.inject("stuck", count=-1)
        reading = sensor.read()
        assert reading.status is ReadingStatus.OUT_OF_RANGE and reading.value is None
        runner = Runner(session, robot, sensor, SimCameraDirect(cell.world), CONFIG)
        paused = runner.run()
        assert (paused.state, paused.done, paused.skipped) == ("paused", 2, 2)
        assert ("3 poses in a row could not be measured (last: sensor out-of-range (+99.999) "
                "(2 attempt(s)))") in paused.message
        assert all(s.reason.startswith("sensor out-of-range (+99.999)") and s.d is None
                   for s in session.samples())
        cell.keyence.clear_faults()
        runner.resume()
        done = runner.run()
        assert (done.state, done.done, done.skipped) == ("finished", 8, 2)
        _assert_complete_and_true(session, cell.world, 8, skipped={0, 1})
