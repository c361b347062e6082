"""GrblRobot driver against the GRBL 1.1 emulator on a pty: wire bytes, limits, errors, faults."""

from __future__ import annotations

import contextlib
import math
import threading
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import DeviceTimeout, DriverError, FlangePose, MotionRefused, Robot
from drivers.emulators import GrblEmulator
from drivers.grbl import (
    GRBL_ALARMS,
    GRBL_ERRORS,
    GrblAlarm,
    GrblError,
    GrblRobot,
    MotionStopped,
    parse_status,
)
from drivers.serial_port import PortLost
from tests.drivers.conftest import LIMITS, TIMEOUT

TARGET = FlangePose(10.0, -20.5, 30.25, 45.0)


def _close(pose: FlangePose, target: FlangePose, tol: float = 1e-6) -> bool:
    return bool(abs(pose.as_array() - target.as_array()).max() <= tol)


def _motion_lines(emu: GrblEmulator) -> list[str]:
    return [line for line in emu.received if line.startswith(("G", "$"))]


def test_move_sends_exact_bytes_and_reads_back(grbl, robot):
    assert isinstance(robot, Robot)
    pose = robot.move_to(TARGET)
    assert _close(pose, TARGET)
    assert grbl.received_bytes == (b"?G90 G1 X10.000 Y-20.500 Z30.250 A45.000 F1000\n"
                                   b"G4 P0\n?")
    assert _close(robot.read_pose(), TARGET)
    assert robot.describe() == (f"GRBL 1.1 on {grbl.path} 115200 8N1, feed 1000 mm/min, "
                                "tolerance 0.02")


@pytest.mark.parametrize("report", ["mpos", "wpos"])
def test_work_coordinates_with_offset(report):
    wco = (100.0, -50.0, 5.0, 0.0)
    with GrblEmulator(wco=wco, report=report) as emu, \
            GrblRobot(emu.path, LIMITS, timeout=TIMEOUT) as drv:
        assert _close(drv.read_pose(), FlangePose(0, 0, 0, 0))
        assert _close(drv.move_to(TARGET), TARGET)
        assert emu.machine_position == pytest.approx((110.0, -70.5, 35.25, 45.0))


def test_move_waits_for_the_end_of_motion(grbl, robot):
    grbl.move_time = 0.3
    t0 = time.monotonic()
    assert _close(robot.move_to(TARGET), TARGET)
    assert 0.28 < time.monotonic() - t0 < 1.0


@pytest.mark.parametrize("target", [
    FlangePose(150.0, 0.0, 10.0, 0.0), FlangePose(0.0, 0.0, -1.0, 0.0),
    FlangePose(0.0, 0.0, 10.0, 190.0), FlangePose(float("nan"), 0.0, 10.0, 0.0),
    FlangePose(0.0, 0.0, 10.0, 0.0, quaternion=(0.9, 0.3, 0.0, 0.3))])
def test_refused_target_never_reaches_the_controller(grbl, robot, target):
    with pytest.raises(MotionRefused, match="nothing was sent"):
        robot.move_to(target)
    time.sleep(0.05)
    assert grbl.received_bytes == b""


def test_z_only_quaternion_target_moves_axis_a(grbl, robot):
    half = math.radians(30.0) / 2
    pose = robot.move_to(FlangePose(1.0, 2.0, 3.0, 0.0,
                                    quaternion=(math.cos(half), 0.0, 0.0, math.sin(half))))
    assert _close(pose, FlangePose(1.0, 2.0, 3.0, 30.0), 1e-3)


def test_jog_beyond_max_step_is_refused(grbl, robot):
    with pytest.raises(MotionRefused, match="exceeds the maximum step 20"):
        robot.jog(dx=25.0)
    assert _motion_lines(grbl) == []
    assert _close(robot.jog(dx=5.0, dtheta=2.0), FlangePose(5.0, 0.0, 0.0, 2.0))


@pytest.mark.parametrize("code", [9, 20, 22])
def test_error_reply_is_a_clear_error(grbl, robot, code):
    grbl.inject("error", code=code, match="G90")
    with pytest.raises(GrblError) as info:
        robot.move_to(TARGET)
    assert f"error:{code} {GRBL_ERRORS[code]}" in str(info.value)
    assert "G4 P0" not in grbl.received


def test_alarm_during_move_locks_until_unlocked(grbl, robot):
    grbl.inject("alarm", code=1, match="G4")
    with pytest.raises(GrblAlarm, match=f"ALARM:1 {GRBL_ALARMS[1]}"):
        robot.move_to(TARGET)
    sent = len(_motion_lines(grbl))
    with pytest.raises(GrblAlarm, match="Alarm state"):
        robot.move_to(TARGET)
    assert len(_motion_lines(grbl)) == sent  # nothing sent while in alarm
    robot.unlock()
    assert _close(robot.move_to(TARGET), TARGET)


def test_emulator_locks_gcode_in_alarm(grbl, robot):
    grbl.inject("alarm", code=2, match="G90")
    with pytest.raises(GrblAlarm, match="ALARM:2 motion target exceeds machine travel"):
        robot.move_to(TARGET)
    with pytest.raises(GrblError, match="error:9 G-code locked out during alarm"):
        robot._command("G90 G1 X0 F100")


def test_status_timeout_retried_then_reported(grbl, robot):
    grbl.inject("silent", match="?")
    assert _close(robot.read_pose(), FlangePose(0, 0, 0, 0))
    grbl.inject("silent", count=-1, match="G90")
    with pytest.raises(DeviceTimeout, match=r"did not answer G90 G1 .* within 0.2 s \(3 attempts"):
        robot.move_to(TARGET)
    assert "G4 P0" not in grbl.received


@pytest.mark.parametrize("kind", ["noise", "truncate", "garbage"])
def test_garbled_replies(grbl, robot, kind):
    grbl.inject(kind, match="G90")
    grbl.inject(kind, match="?")
    assert _close(robot.move_to(TARGET), TARGET)
    grbl.inject(kind, count=-1, match="?")
    if kind == "noise":
        assert _close(robot.read_pose(), TARGET)
    else:
        with pytest.raises(DriverError, match="unusable replies to '\\?'"):
            robot.read_pose()


@pytest.mark.parametrize("kind", ["silent", "garbage", "truncate"])
def test_lost_end_of_motion_ok_is_recovered_by_status(grbl, robot, kind):
    grbl.move_time = 0.3
    grbl.inject(kind, match="G4")
    t0 = time.monotonic()
    assert _close(robot.move_to(TARGET), TARGET)
    assert time.monotonic() - t0 < 0.3 + 3 * TIMEOUT
    grbl.move_time = 5.0  # longer than the allowed move time
    with GrblRobot(grbl.path, LIMITS, timeout=TIMEOUT, move_timeout=0.5) as drv, \
            pytest.raises(DeviceTimeout, match=r"no end of motion \(G4 P0 ok\) within 0.5 s"):
        drv.move_to(FlangePose(0.0, 0.0, 0.0, 0.0))


def test_idle_before_pose_reached(grbl, robot):
    grbl.inject("early_idle", seconds=0.2)
    assert _close(robot.move_to(TARGET), TARGET)
    grbl.inject("early_idle", seconds=0.05, stall=True)
    with pytest.raises(DriverError, match=r"reports Idle at .* the pose was not reached"):
        robot.move_to(FlangePose(0.0, 0.0, 0.0, 0.0))


def test_stop_reaches_controller_within_100ms_during_a_move(grbl, robot):
    grbl.move_time = 2.0
    errors: list[BaseException] = []

    def move() -> None:
        try:
            robot.move_to(TARGET)
        except BaseException as exc:
            errors.append(exc)

    mover = threading.Thread(target=move)
    mover.start()
    deadline = time.monotonic() + 2.0
    while "G4 P0" not in grbl.received and time.monotonic() < deadline:
        time.sleep(0.005)
    time.sleep(0.1)
    t_stop = time.monotonic()
    robot.stop()
    mover.join(2.0)
    stamp = next(t for t, text in grbl.log if text == "!")
    assert stamp - t_stop < 0.1
    assert len(errors) == 1 and isinstance(errors[0], MotionStopped)
    held = grbl.position
    assert grbl.state == "Hold:0" and 0.0 < held[0] < TARGET.x
    time.sleep(0.1)
    assert grbl.position == held  # really stopped
    grbl.move_time = 0.0
    assert _close(robot.move_to(TARGET), TARGET)  # soft reset flushes the held queue
    assert "\x18" in grbl.received


def test_port_vanishes_mid_move_then_reconnect(grbl, robot):
    grbl.inject("vanish", match="G4")
    with pytest.raises(PortLost, match="was lost"):
        robot.move_to(TARGET)
    robot.reconnect(grbl.replug())
    assert _close(robot.move_to(TARGET), TARGET)


def test_unplugged_controller_reopened_under_the_same_name(grbl, tmp_path):
    link = tmp_path / "ttyGRBL"
    link.symlink_to(grbl.path)
    with GrblRobot(str(link), LIMITS, timeout=TIMEOUT) as drv:
        assert _close(drv.move_to(TARGET), TARGET)
        grbl.vanish()
        with pytest.raises(PortLost):
            drv.read_pose()
        link.unlink()
        link.symlink_to(grbl.replug())
        assert _close(drv.read_pose(), TARGET)  # the controller kept its position
        assert _close(drv.move_to(FlangePose(0, 0, 0, 0)), FlangePose(0, 0, 0, 0))


@pytest.mark.parametrize(("line", "state", "mpos", "wpos", "wco"), [
    ("<Idle|MPos:1.000,2.000,3.000,4.000|FS:0,0>", "Idle", (1, 2, 3, 4), None, None),
    ("<Hold:0|WPos:-1.5,0,0,90|FS:0,0|WCO:1,1,1,0>", "Hold:0", None, (-1.5, 0, 0, 90),
     (1, 1, 1, 0))])
def test_parse_status(line, state, mpos, wpos, wco):
    status = parse_status(line)
    assert (status.state, status.mpos, status.wpos, status.wco) == (state, mpos, wpos, wco)


@pytest.mark.parametrize("line", ["Idle|MPos:1,2,3,4", "<Idle|MPos:1,2,3>", "<Idle|FS:0,0>",
                                  "<Bogus|MPos:1,2,3,4>", "<Idle|MPos:1,x,3,4>",
                                  "<Idle|MPos:1,inf,3,4>"])
def test_parse_status_rejects_malformed(line):
    with pytest.raises(DriverError):
        parse_status(line)


@given(st.text(max_size=60))
def test_parse_status_only_raises_driver_errors(line):
    with contextlib.suppress(DriverError):
        parse_status(line)


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(junk=st.binary(min_size=1, max_size=40), kind=st.sampled_from(["garbage", "noise"]),
       match=st.sampled_from(["?", "G90", "G4"]))
def test_any_junk_gives_the_target_or_a_driver_error(grbl, junk, kind, match):
    grbl.clear_faults()
    grbl.inject(kind, data=junk, match=match)
    target = FlangePose(1.0, 2.0, 3.0, 4.0) if grbl.position[0] == 0.0 else FlangePose(0, 0, 0, 0)
    with GrblRobot(grbl.path, LIMITS, timeout=0.05, retries=1, settle_timeout=0.2,
                   move_timeout=0.3) as drv:
        try:
            pose = drv.move_to(target)
        except DriverError:
            drv.close()
            return
    if b"<" not in junk and b"ok" not in junk and b"ALARM" not in junk:
        assert _close(pose, target)


def test_on_motion_reports_the_poses_passed_through(grbl, robot):
    """With ``on_motion`` the driver polls ``?`` during the move: a 0.3 s move from x=0 to
    x=10 reports intermediate poses at increasing x, then ends at the target."""
    grbl.move_time = 0.3
    seen: list[FlangePose] = []
    pose = robot.move_to(FlangePose(10.0, 0.0, 20.0, 0.0), on_motion=seen.append)
    xs = [p.x for p in seen]
    assert len(xs) >= 3, xs  # ~9 at 1/30 s; fewer only on a stalled machine
    assert all(0.0 <= x <= 10.0 for x in xs) and xs == sorted(xs)
    assert any(0.5 < x < 9.5 for x in xs)  # truly between start and target
    assert pose.x == pytest.approx(10.0, abs=1e-3)
