"""Real serial drivers against the GRBL + Keyence emulators on the simulated workcell physics."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from drivers.base import FlangePose, MotionRefused, ReadingStatus
from drivers.emulators import CellEmulators
from drivers.grbl import GrblRobot
from drivers.keyence_il import KeyenceIL
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld
from tests.drivers.conftest import TIMEOUT

#: 5 sigma of the default cell's sensor noise (0.002 mm) plus the 0.001 mm wire quantum.
TOL = 5 * 0.002 + 0.001


@pytest.fixture
def cell():
    world = SimWorld(load_workcell(), seed=3)
    with CellEmulators(world) as emus:
        yield emus
    assert emus.grbl.errors == [] and emus.keyence.errors == []


def test_sensor_reads_the_beam_at_the_robot_pose(cell):
    limits = cell.world.workcell.limits
    with GrblRobot(cell.grbl.path, limits, timeout=TIMEOUT) as robot, \
            KeyenceIL(cell.keyence.path, timeout=TIMEOUT) as sensor:
        for pose in (FlangePose(-2, -2, 15, 0), FlangePose(2, 0, 20, 6), FlangePose(0, 2, 25, -6)):
            assert robot.move_to(pose).as_array() == pytest.approx(pose.as_array(), abs=1e-3)
            truth = cell.world.beam_hit(pose).s
            assert sensor.read().value == pytest.approx(truth, abs=TOL)
        sensor.zero()
        assert sensor.read().value == pytest.approx(0.0, abs=2 * TOL)
        before = cell.world.beam_hit(FlangePose(0, 2, 25, -6)).s
        robot.move_to(FlangePose(0, 2, 24, -6))
        after = cell.world.beam_hit(FlangePose(0, 2, 24, -6)).s
        assert sensor.read().value == pytest.approx(after - before, abs=2 * TOL)
        robot.move_to(FlangePose(60, 70, 15, 0))  # beam off the plates
        assert sensor.read().status is ReadingStatus.OUT_OF_RANGE
        with pytest.raises(MotionRefused):
            robot.move_to(FlangePose(0, 0, 45, 0))  # above the workcell's z limit
    assert not any(line.startswith("G90 G1 X0.000 Y0.000 Z45") for line in cell.grbl.received)


def test_emulate_cell_prints_both_paths():
    proc = subprocess.Popen([sys.executable, "-m", "app", "emulate", "cell", "--seed", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        grbl_path = proc.stdout.readline().strip()
        keyence_path = proc.stdout.readline().strip()
        assert grbl_path.startswith("/dev/") and keyence_path.startswith("/dev/")
        world = SimWorld(load_workcell(), seed=1)
        pose = FlangePose(-2.0, -2.0, 15.0, 0.0)
        with GrblRobot(grbl_path, world.workcell.limits, timeout=TIMEOUT) as robot, \
                KeyenceIL(keyence_path, timeout=TIMEOUT) as sensor:
            robot.move_to(pose)
            assert sensor.read().value == pytest.approx(world.beam_hit(pose).s, abs=TOL)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
