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


def test_session_pauses_on_an_unplugged_sensor_and_continues_after_replug(tmp_path):
    """The Keyence port vanishes at the 31st read: the run pauses with a clear message; the
    adapter comes back under the same name; resume completes the session with every pose
    stored exactly once, each with the displacement and spot of its pose (within 5 sigma)."""
    from app.acquisition import Runner, RunnerConfig
    from app.session import Session
    from calib_core.grid import paper_grid
    from drivers.sim.devices import SimCameraDirect

    world = SimWorld(load_workcell(), seed=5)
    grid = paper_grid()
    with CellEmulators(world) as cell:
        cell.keyence.inject("vanish", match="SR", skip=30)
        sensor_link = tmp_path / "ttyKEYENCE"
        sensor_link.symlink_to(cell.keyence.path)
        robot = GrblRobot(cell.grbl.path, world.workcell.limits, timeout=TIMEOUT)
        sensor = KeyenceIL(str(sensor_link), timeout=TIMEOUT)
        config = RunnerConfig(samples_per_pose=2, return_on_pause=True,
                              driver_retry_delay_s=0.05)
        with robot, sensor, Session.create(tmp_path / "s.db", grid) as session:
            runner = Runner(session, robot, sensor, SimCameraDirect(world), config)
            paused = runner.run()
            assert paused.state == "paused" and paused.done == 15  # 2 reads per pose
            assert "Keyence DL-RS1A port" in paused.message and "resume" in paused.message
            sensor_link.unlink()
            sensor_link.symlink_to(cell.keyence.replug())
            runner.resume()
            done = runner.run()
            samples = session.samples()
    assert done.state == "finished" and done.done == len(grid)
    assert sorted(s.pose_index for s in samples) == list(range(len(grid)))  # no loss, no dup
    camera_tol = 5 * world.workcell.noise.camera
    for sample in samples:
        hit = world.beam_hit(FlangePose(*grid.pose(sample.pose_index)))
        assert sample.ok and sample.d == pytest.approx(hit.s, abs=TOL)
        assert (sample.x_p, sample.y_p) == pytest.approx(tuple(hit.p[:2]), abs=camera_tol)
