"""``lasercal sensor|robot|emulate`` as subprocesses against pty emulators."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from drivers.base import FlangePose
from drivers.emulators import KeyenceEmulator
from drivers.grbl import GrblRobot
from drivers.keyence_il import KeyenceIL
from tests.drivers.conftest import LIMITS, TIMEOUT


def lasercal(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", *argv], capture_output=True, text=True,
                          timeout=60)


def run_main(argv: list[str]) -> int:
    """``lasercal ARGV`` in-process; exit status (usage errors raise SystemExit)."""
    from app.cli import main

    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


def test_sensor_read_value_out_of_range_invalid(keyence, physics):
    physics.value = 1.234
    out = lasercal("sensor", "read", "--port", keyence.path, "--timeout", "0.2")
    assert (out.returncode, out.stdout, out.stderr) == (0, "1.234\n", "")
    physics.value = None
    out = lasercal("sensor", "read", "--port", keyence.path)
    assert (out.returncode, out.stdout) == (0, "out-of-range\n")
    keyence.inject("amp_error", count=-1)
    out = lasercal("sensor", "read", "--port", keyence.path)
    assert (out.returncode, out.stdout) == (0, "invalid\n")
    assert "amplifier error" in out.stderr
    assert keyence.received == ["SR,00,037"] * 3


def test_sensor_errors_exit_2(keyence):
    keyence.inject("silent", count=-1)
    out = lasercal("sensor", "read", "--port", keyence.path, "--timeout", "0.2")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.startswith("error: Keyence DL-RS1A on ") and "did not answer" in out.stderr
    keyence.clear_faults()
    out = lasercal("sensor", "read", "--port", keyence.path, "--id", "3")
    assert out.returncode == 2 and "ER 65 no amplifier with this ID" in out.stderr
    assert len(out.stderr.splitlines()) == 1


def test_sensor_zero(keyence, physics):
    physics.value = 7.0
    out = lasercal("sensor", "zero", "--port", keyence.path)
    assert (out.returncode, out.stdout) == (0, "zeroed\n")
    assert keyence.offsets[0] == pytest.approx(7.0)


def test_robot_move_pose_and_refusal(grbl, tmp_path):
    out = lasercal("robot", "move", "--port", grbl.path, "--x", "10", "--y", "-5.5", "--z", "20",
                   "--theta", "30", "--timeout", "0.5")
    assert (out.returncode, out.stdout) == (0, "x=10.000 y=-5.500 z=20.000 theta=30.000\n")
    workcell = tmp_path / "cell.toml"
    workcell.write_text("[limits]\nx = [-10.0, 10.0]\ny = [-10.0, 10.0]\nz = [0.0, 30.0]\n"
                        "theta_deg = [-45.0, 45.0]\nmax_step = 5.0\n")
    before = grbl.received_bytes
    out = lasercal("robot", "move", "--port", grbl.path, "--workcell", str(workcell),
                   "--x", "11", "--y", "0", "--z", "20", "--theta", "0")
    assert out.returncode == 2
    assert out.stderr == ("error: target x=11 is outside the soft limits [-10, 10]; nothing "
                          "was sent to the robot\n")
    assert grbl.received_bytes == before  # the refused target never reached the controller
    out = lasercal("robot", "pose", "--port", grbl.path)
    assert (out.returncode, out.stdout) == (0, "x=10.000 y=-5.500 z=20.000 theta=30.000\n")


def test_robot_alarm_is_an_error_line(grbl):
    grbl.inject("alarm", code=1, match="G4")
    out = lasercal("robot", "move", "--port", grbl.path, "--x", "1", "--y", "1", "--z", "1",
                   "--theta", "0")
    assert out.returncode == 2
    assert "ALARM:1 hard limit triggered" in out.stderr and len(out.stderr.splitlines()) == 1
    assert lasercal("robot", "unlock", "--port", grbl.path).stdout == "unlocked\n"


@pytest.mark.parametrize("device", ["keyence", "grbl"])
def test_emulate_prints_path_and_serves_until_sigterm(device):
    argv = [sys.executable, "-m", "app", "emulate", device]
    argv += ["--value", "2.5"] if device == "keyence" else ["--move-time", "0.05"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/")
        if device == "keyence":
            with KeyenceIL(path, timeout=TIMEOUT) as sensor:
                assert sensor.read().value == pytest.approx(2.5)
        else:
            with GrblRobot(path, LIMITS, timeout=TIMEOUT) as robot:
                pose = robot.move_to(FlangePose(1.0, 2.0, 3.0, 4.0))
                assert pose.as_array() == pytest.approx([1.0, 2.0, 3.0, 4.0])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_emulator_in_process_is_not_left_behind():
    emu = KeyenceEmulator(lambda: 0.0).start()
    emu.close()
    assert emu.gone and not emu._thread.is_alive()


@pytest.mark.parametrize("argv", [
    ["sensor", "read", "--port", "/dev/nonexistent-tty"],
    ["sensor", "read", "--port", "/dev/null", "--timeout", "nan"],
    ["sensor", "read", "--port", "/dev/null", "--timeout", "-1"],
    ["sensor", "read", "--port", "/dev/null", "--baud", "fast"],
    ["sensor", "zero"],
    ["robot", "move", "--port", "/dev/null", "--x", "nan", "--y", "0", "--z", "0", "--theta", "0"],
    ["robot", "move", "--port", "/dev/null", "--x", "0", "--y", "0", "--z", "0", "--theta", "0",
     "--feed", "inf"],
    ["robot", "pose", "--port", "/dev/null", "--workcell", "/nonexistent.toml"],
    ["emulate", "grbl", "--move-time", "-1"],
    ["emulate", "keyence", "--value", "inf"],
])
def test_bad_arguments_give_one_error_line(argv, capsys):
    assert run_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("table", [
    "[limits]\nx = [1, 0]\ny = [0, 1]\nz = [0, 1]\ntheta_deg = [0, 1]\n",
    "[limits]\nx = 'wide'\ny = [0, 1]\nz = [0, 1]\ntheta_deg = [0, 1]\n",
    "[limits]\nx = [0, 1]\ny = [0, 1]\nz = [0, 1]\ntheta_deg = [0, 1]\nmax_step = true\n",
    "[beam]\n", "not toml ["])
def test_bad_workcell_limits_are_refused(tmp_path, table, capsys):
    path = tmp_path / "cell.toml"
    path.write_text(table)
    argv = ["robot", "pose", "--port", "/dev/null", "--workcell", str(path)]
    assert run_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: ") and len(err.splitlines()) == 1, err


def test_robot_without_workcell_file_uses_generous_limits(grbl, monkeypatch, capsys):
    import app.commands.robot as robot_cmd

    monkeypatch.setattr(robot_cmd, "DEFAULT_WORKCELL", "no_such_workcell.toml")
    argv = ["robot", "move", "--port", grbl.path, "--x", "500", "--y", "0", "--z", "0",
            "--theta", "0", "--timeout", "0.5"]
    assert run_main(argv) == 0
    out = capsys.readouterr()
    assert out.out == "x=500.000 y=0.000 z=0.000 theta=0.000\n"
    assert "note: no workcell file; generous default soft limits apply" in out.err
    argv[5] = "1500"
    assert run_main(argv) == 2
    assert "outside the soft limits [-1000, 1000]" in capsys.readouterr().err
