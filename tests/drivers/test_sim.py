"""Simulated workcell: file loading, beam geometry, noise, devices, and a full solved session."""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from calib_core.calibrate import solve
from calib_core.errors import InputError
from calib_core.io import dataset_from_frame, load_dataset
from calib_core.model import Poses, rotation_about_z, spot_positions
from calib_core.noise import NoiseModel
from drivers.base import (
    DisplacementSensor,
    DriverError,
    FlangePose,
    MotionRefused,
    ReadingStatus,
    Robot,
    SoftLimits,
    SpotCamera,
)
from drivers.sim.devices import SimCamera, SimCameraDirect, SimRobot, SimSensor
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld

ZERO_NOISE = NoiseModel(0.0, 0.0, 0.0, 0.0, 0.0)
EQ15 = np.array([0.250, -0.181, 0.952])


def paper_grid() -> list[FlangePose]:
    """The seed's 42 poses: 4x3 x-y grids at z = 15, 20, 25 plus 6 rotations at z = 20."""
    poses = [FlangePose(x, y, z, 0.0) for z in (15.0, 20.0, 25.0)
             for x in np.linspace(-2.0, 2.0, 4) for y in (-2.0, 0.0, 2.0)]
    poses += [FlangePose(0.0, 0.0, 20.0, t) for t in np.linspace(-6.0, 6.0, 6)]
    return poses


def run_session(world: SimWorld, grid: list[FlangePose]) -> pd.DataFrame:
    """Move, read the sensor and the camera at each pose; the solve CSV columns as strings."""
    robot, sensor, camera = SimRobot(world), SimSensor(world), SimCameraDirect(world)
    rows = []
    for target in grid:
        pose = robot.move_to(target)
        reading, spot = sensor.read(), camera.measure_spot()
        assert reading.ok and spot.ok, (target, reading, spot)
        rows.append({"x_o": pose.x, "y_o": pose.y, "z_o": pose.z, "theta_deg": pose.theta_deg,
                     "d": reading.value, "x_p": spot.x, "y_p": spot.y})
    return pd.DataFrame(rows).map(repr)


def with_noise(noise: NoiseModel, gain: float = 1.0):
    wc = load_workcell()
    return dataclasses.replace(wc, noise=noise,
                               beam=dataclasses.replace(wc.beam, gain=gain))


# -- the workcell file ------------------------------------------------------------------------

def test_default_workcell_reproduces_the_seed_cell():
    wc = load_workcell()
    truth = wc.truth()
    assert truth["x_t"] == -6.386 and truth["y_t"] == 70.055
    assert truth["z_t_minus_delta"] == -20.073
    u = np.array([truth["a"], truth["b"], truth["c"]])
    assert np.linalg.norm(u) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(u, EQ15 / np.linalg.norm(EQ15), atol=1e-12)
    assert (truth["alpha"], truth["beta"], truth["gain"]) == (-0.713e-3, 5.671e-3, 1.0)
    assert (wc.side_plate.alpha, wc.side_plate.beta) == (4.152e-3, -3.153e-3)
    # Table 3: z_t - delta on the side plate is -14.981 mm
    assert wc.beam.z_t - wc.side_plate.delta == pytest.approx(-14.981, abs=1e-9)
    assert wc.noise == NoiseModel()  # Table 2 defaults
    assert isinstance(wc.limits, SoftLimits) and wc.sensor.range == 10.0
    assert wc.camera.resolution == (1280, 1024)


def test_example_session_matches_the_packaged_truth():
    base = resources.files("static_data")
    truth = json.loads(base.joinpath("example_paper_grid.truth.json").read_text())
    data = load_dataset(Path(str(base.joinpath("example_paper_grid.csv"))))
    assert len(data) == 42
    assert truth["x_t"] == load_workcell().truth()["x_t"]


def test_example_csv_is_the_paper_grid():
    base = resources.files("static_data")
    data = load_dataset(Path(str(base.joinpath("example_paper_grid.csv"))))
    grid = paper_grid()
    np.testing.assert_allclose(data.poses.position, [[p.x, p.y, p.z] for p in grid], atol=1e-6)
    assert data.poses.theta_deg is not None
    np.testing.assert_allclose(data.poses.theta_deg, [p.theta_deg for p in grid], atol=1e-6)


@pytest.mark.parametrize(("edit", "expected"), [
    (lambda s: s.replace("gain = 1.0", ""), r"\[beam\] gain: missing key"),
    (lambda s: s.replace("gain = 1.0", "gain = 1.0\ncolour = 3"), r"\[beam\] unknown key.*colour"),
    (lambda s: s.replace("alpha = -0.713e-3", 'alpha = "x"'), r"\[plate\] alpha: must be a number"),
    (lambda s: s.replace("range = 10.0", "range = -1.0"), r"\[sensor\] range: must be > 0"),
    (lambda s: s.replace("x = [-40.0, 70.0]", "x = [70.0, -40.0]"), r"\[limits\] x: need lo < hi"),
    (lambda s: s.replace("sensor = 0.002", "sensor = -0.002"), r"\[noise\].*sensor"),
    (lambda s: s.replace("[timing]", "[timming]"), r"unknown table.*timming"),
    (lambda s: s.replace("[beam]", "[beam"), r"not valid TOML"),
])
def test_bad_workcell_files_name_file_and_key(tmp_path, edit, expected):
    text = resources.files("static_data").joinpath("workcell_default.toml").read_text()
    path = tmp_path / "cell.toml"
    path.write_text(edit(text))
    with pytest.raises(InputError, match=expected) as info:
        load_workcell(path)
    assert str(path) in str(info.value)


def test_missing_workcell_file(tmp_path):
    with pytest.raises(InputError, match="no such workcell file"):
        load_workcell(tmp_path / "nope.toml")


# -- geometry ---------------------------------------------------------------------------------

@pytest.mark.parametrize("gain", [1.0, 1.02])
def test_true_h_reconstructs_the_spot_on_the_plate(gain):
    """Noise-free: eq 16 with the truth H puts every spot on the true point, within 1e-9 mm."""
    world = SimWorld(with_noise(ZERO_NOISE, gain), seed=1)
    frame = run_session(world, paper_grid()).astype(float)
    truth = world.truth()
    poses = Poses(frame[["x_o", "y_o", "z_o"]].to_numpy(),
                  rotation_about_z(frame["theta_deg"].to_numpy()), frame["theta_deg"].to_numpy())
    t = np.array([truth["x_t"], truth["y_t"], truth["z_t_minus_delta"]])
    u = np.array([truth["a"], truth["b"], truth["c"]])
    assert np.linalg.norm(u) == pytest.approx(gain)
    p = spot_positions(poses, frame["d"].to_numpy(), t, u)
    np.testing.assert_allclose(p[:, 0:2], frame[["x_p", "y_p"]].to_numpy(), atol=1e-9)
    plate = world.workcell.plate
    z_plate = plate.z_at(p[:, 0], p[:, 1]) - plate.delta
    np.testing.assert_allclose(p[:, 2], z_plate, atol=1e-9)
    # the seed's readings: d about +5.7 at z = 15, +0.5 at z = 20, -4.75 at z = 25
    assert frame["d"].iloc[0] * gain == pytest.approx(5.74, abs=0.05)


def test_zeroing_moves_t_along_the_beam():
    world = SimWorld(with_noise(ZERO_NOISE), seed=0)
    world.move(FlangePose(1.0, -1.0, 17.0, 3.0))
    before = world.truth()
    SimSensor(world).zero()
    assert world.read_sensor().value == pytest.approx(0.0, abs=1e-12)
    after = world.truth()
    d0 = world.sensor_zero
    for i, k in enumerate(("x_t", "y_t", "z_t")):
        expected = before[k] + d0 * before["abc"[i]]
        assert after[k] == pytest.approx(expected, abs=1e-12)
    world.move(FlangePose(-2.0, 2.0, 22.0, -5.0))
    frame = run_session(world, [FlangePose(-2.0, 2.0, 22.0, -5.0)]).astype(float)
    poses = Poses(frame[["x_o", "y_o", "z_o"]].to_numpy(), rotation_about_z([-5.0]))
    t = np.array([after["x_t"], after["y_t"], after["z_t_minus_delta"]])
    u = np.array([after["a"], after["b"], after["c"]])
    p = spot_positions(poses, frame["d"].to_numpy(), t, u)
    np.testing.assert_allclose(p[0, 0:2], frame[["x_p", "y_p"]].to_numpy()[0], atol=1e-9)


def test_side_plate_is_hit_and_seen_by_no_bottom_camera():
    world = SimWorld(with_noise(ZERO_NOISE), seed=0)
    world.move(FlangePose(50.0, 0.0, 15.0, 0.0))
    hit = world.beam_hit()
    assert hit is not None and hit.surface == "side_plate"
    sp = world.workcell.side_plate
    assert hit.p[2] == pytest.approx(sp.z_at(hit.p[0], hit.p[1]), abs=1e-12)
    assert world.read_sensor().ok
    assert not SimCameraDirect(world).measure_spot().ok


# -- noise ------------------------------------------------------------------------------------

def test_noise_levels_follow_table_2():
    world = SimWorld(load_workcell(), seed=3)
    target = FlangePose(0.0, 0.0, 20.0, 0.0)
    robot = SimRobot(world)
    reps = np.array([robot.move_to(target).as_array() for _ in range(3000)]) - target.as_array()
    sd = reps.std(axis=0)
    np.testing.assert_allclose(sd, [0.0025, 0.0025, 0.005, 0.01], rtol=0.06)
    reads = np.array([world.read_sensor().value for _ in range(3000)])
    assert reads.std() == pytest.approx(0.002, rel=0.06)
    spots = np.array([world.camera_spot() for _ in range(3000)])
    np.testing.assert_allclose(spots.std(axis=0), [0.0031, 0.0031], rtol=0.06)
    truth_xy = world.true_spot()[0:2]
    np.testing.assert_allclose(spots.mean(axis=0), truth_xy, atol=4 * 0.0031 / np.sqrt(3000))


def test_same_seed_same_session():
    a = run_session(SimWorld(load_workcell(), seed=7), paper_grid())
    b = run_session(SimWorld(load_workcell(), seed=7), paper_grid())
    c = run_session(SimWorld(load_workcell(), seed=8), paper_grid())
    assert a.equals(b) and not a.equals(c)


# -- devices ----------------------------------------------------------------------------------

def test_devices_implement_the_protocols():
    world = SimWorld(load_workcell())
    assert isinstance(SimRobot(world), Robot)
    assert isinstance(SimSensor(world), DisplacementSensor)
    assert isinstance(SimCameraDirect(world), SpotCamera)


def test_sensor_out_of_range_and_zero_refused():
    world = SimWorld(load_workcell(), seed=0)
    robot, sensor = SimRobot(world), SimSensor(world)
    robot.move_to(FlangePose(0.0, 0.0, 31.0, 0.0))  # d about -10.3: beyond the +-10 mm range
    reading = sensor.read()
    assert reading.status is ReadingStatus.OUT_OF_RANGE and reading.value is None
    with pytest.raises(DriverError, match="zero-set impossible"):
        sensor.zero()
    robot.move_to(FlangePose(0.0, 0.0, 29.0, 0.0))
    assert sensor.read().ok
    robot.move_to(FlangePose(-40.0, -40.0, 20.0, 0.0))  # beam misses every plate
    assert sensor.read().status is ReadingStatus.OUT_OF_RANGE


def test_robot_refuses_targets_outside_the_limits():
    world = SimWorld(load_workcell(), seed=0)
    robot = SimRobot(world)
    before = world.true_pose
    for bad in (FlangePose(0, 0, 41.0, 0), FlangePose(71.0, 0, 20, 0),
                FlangePose(0, 0, 20, 95.0), FlangePose(float("nan"), 0, 20, 0)):
        with pytest.raises(MotionRefused):
            robot.move_to(bad)
        assert world.true_pose == before
    tight = SimRobot(world, limits=dataclasses.replace(world.workcell.limits, max_step=1.0))
    with pytest.raises(MotionRefused, match="maximum step"):
        tight.move_to(FlangePose(0.0, 5.0, 20.0, 0.0))


def test_move_time_and_stop():
    world = SimWorld(with_noise(ZERO_NOISE), seed=0)
    robot = SimRobot(world, move_time_s=0.2)
    t0 = time.monotonic()
    robot.move_to(FlangePose(1.0, 0.0, 20.0, 0.0))
    assert time.monotonic() - t0 >= 0.19
    timer = threading.Timer(0.05, robot.stop)
    timer.start()
    with pytest.raises(DriverError, match="stopped"):
        robot.move_to(FlangePose(1.0, 10.0, 20.0, 0.0))
    timer.join()
    y = world.true_pose.y
    assert 0.5 < y < 9.5  # stopped part-way
    robot.close()
    with pytest.raises(DriverError, match="closed"):
        robot.read_pose()


# -- the full session through the solver ------------------------------------------------------

@pytest.mark.parametrize(("seed", "gain"), [(11, 1.0), (12, 1.01)])
def test_simulated_session_solves_to_the_truth(seed, gain):
    """42 noisy poses (Table 2) -> solve -> every parameter within 4 sigma of the truth."""
    world = SimWorld(with_noise(NoiseModel(), gain), seed=seed)
    frame = run_session(world, paper_grid())
    cal = solve(dataset_from_frame(frame, "sim"), model="auto", noise=NoiseModel())
    assert cal.model == "schoenflies" and cal.n_used >= 40
    truth = world.truth()
    err = np.array([cal.point(n) - truth[n] for n in cal.names])
    z = err / cal.sigma
    assert np.all(np.abs(z) < 4.0), dict(zip(cal.names, z, strict=True))
    # the recovered point accuracy is at the level of the seed's Table 1 (tens of microns)
    assert abs(cal.point("x_t") - truth["x_t"]) < 0.1
    assert np.linalg.norm([cal.point(k) for k in "abc"]) == pytest.approx(gain, abs=0.01)


def test_rendered_camera_session_solves_to_the_truth():
    """The same session measured through rendered frames and the OpenCV detector."""
    world = SimWorld(load_workcell(), seed=21)
    robot, sensor, camera = SimRobot(world), SimSensor(world), SimCamera(world, seed=21)
    camera.calibrate()
    rows = []
    for target in paper_grid():
        pose = robot.move_to(target)
        reading, spot = sensor.read(), camera.measure_spot()
        assert reading.ok and spot.ok and spot.quality > 0.5, spot.reason
        rows.append({"x_o": pose.x, "y_o": pose.y, "z_o": pose.z, "theta_deg": pose.theta_deg,
                     "d": reading.value, "x_p": spot.x, "y_p": spot.y})
    cal = solve(dataset_from_frame(pd.DataFrame(rows).map(repr), "rendered"), model="auto")
    truth = world.truth()
    z = np.array([(cal.point(n) - truth[n]) / s for n, s in zip(cal.names, cal.sigma,
                                                                  strict=True)])
    assert np.all(np.abs(z) < 4.0), dict(zip(cal.names, z, strict=True))


def six_dof_grid() -> list[FlangePose]:
    """Poses tilted up to 2 degrees about x and y, at three heights: z_t and delta separate."""
    rng = np.random.default_rng(5)
    poses = []
    for z in (16.0, 20.0, 24.0):
        for _ in range(14):
            rot = Rotation.from_euler("xyz", [*rng.uniform(-2, 2, 2), rng.uniform(-6, 6)],
                                      degrees=True)
            q = rot.as_quat(scalar_first=True)
            poses.append(FlangePose(*rng.uniform(-2, 2, 2), z, 0.0,
                                    tuple(float(v) for v in q)))
    return poses


def test_six_dof_poses_separate_z_t_and_delta():
    wc = load_workcell()
    wc = dataclasses.replace(wc, plate=dataclasses.replace(wc.plate, delta=0.7))
    world = SimWorld(wc, seed=2)
    robot, sensor, camera = SimRobot(world), SimSensor(world), SimCameraDirect(world)
    rows = []
    for target in six_dof_grid():
        pose = robot.move_to(target)
        reading, spot = sensor.read(), camera.measure_spot()
        assert reading.ok and spot.ok and pose.quaternion is not None
        qw, qx, qy, qz = pose.quaternion
        rows.append({"x_o": pose.x, "y_o": pose.y, "z_o": pose.z, "qw": qw, "qx": qx,
                     "qy": qy, "qz": qz, "d": reading.value, "x_p": spot.x, "y_p": spot.y})
    cal = solve(dataset_from_frame(pd.DataFrame(rows).map(repr), "6dof"), model="auto")
    assert cal.model == "general"
    truth = world.truth()
    assert truth["delta"] == 0.7
    z = np.array([(cal.point(n) - truth[n]) / s for n, s in zip(cal.names, cal.sigma,
                                                                  strict=True)])
    assert np.all(np.abs(z) < 4.0), dict(zip(cal.names, z, strict=True))


def test_measuring_window_is_physical_after_zeroing():
    """Zeroed at z = 25 (raw -4.75), the reading at z = 15 is about +10.5: beyond +-10 from the
    zero but inside the sensor's physical window, so still a valid reading."""
    world = SimWorld(with_noise(ZERO_NOISE), seed=0)
    robot, sensor = SimRobot(world), SimSensor(world)
    robot.move_to(FlangePose(0.0, 0.0, 25.0, 0.0))
    sensor.zero()
    robot.move_to(FlangePose(0.0, 0.0, 15.0, 0.0))
    reading = sensor.read()
    assert reading.ok and reading.value == pytest.approx(10.5, abs=0.2)
    robot.move_to(FlangePose(0.0, 0.0, 31.0, 0.0))
    assert sensor.read().status is ReadingStatus.OUT_OF_RANGE


def test_sim_robot_reports_the_poses_of_a_move() -> None:
    """``on_motion``: a 0.2 s move passes through straight-line poses (x rising from the start
    towards the target, about every 1/30 s), then the move ends at the target."""
    world = SimWorld(load_workcell(None), seed=0)
    robot = SimRobot(world, move_time_s=0.2)
    robot.move_to(FlangePose(-2.0, 0.0, 20.0, 0.0))
    seen: list[FlangePose] = []
    end = robot.move_to(FlangePose(2.0, 0.0, 20.0, 0.0), on_motion=seen.append)
    xs = [p.x for p in seen]
    assert 2 <= len(xs) <= 8, xs  # ~5 at 1/30 s; fewer only on a stalled machine
    assert xs == sorted(xs) and xs[0] > -2.05 and xs[-1] < 2.0
    assert world.true_pose.x == 2.0 and end.x == pytest.approx(2.0, abs=0.02)
