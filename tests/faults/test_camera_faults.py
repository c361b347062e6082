"""Camera faults: no spot, two spots (a reflection), a saturated frame, a frozen stream.

Each fault is injected into the rendered simulated camera (real frames through the OpenCV
detector); the detector refuses the frame with a reason, and the acquisition runner stores the
pose as *skipped* with that reason, never as a good sample, then pauses after
``max_skips_in_a_row`` such poses; once the camera is fixed the run completes.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from app.acquisition import Runner, RunnerConfig
from app.session import Session
from drivers.camera_cv import FROZEN_FRAME, OpenCVCamera, PixelToPlate
from drivers.sim.devices import SimCamera, SimRobot, SimSensor
from drivers.sim.render import FrameRenderer
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld
from tests.faults.conftest import small_grid

FAULTS = [("no_spot", "no spot"), ("second_reflection", "two spots"),
          ("saturate", "saturated"), ("freeze", "frozen frame")]


@pytest.mark.parametrize(("fault", "reason"), FAULTS)
def test_faulty_frame_is_refused_with_its_reason(fault: str, reason: str) -> None:
    world = SimWorld(load_workcell(), seed=2)
    camera = SimCamera(world, seed=2)
    assert camera.measure_spot().ok                      # a good frame first
    camera.set_faults([fault])
    for _ in range(3):
        m = camera.measure_spot()
        assert not m.ok and reason in m.reason, m.reason
        assert np.isnan(m.x) and np.isnan(m.y)           # never a made-up position
    camera.set_faults([])
    assert camera.measure_spot().ok                      # fault gone: fresh frames again


@pytest.mark.parametrize(("fault", "reason"), FAULTS)
def test_runner_skips_the_pose_with_the_reason_then_pauses(
        tmp_path: Path, fault: str, reason: str) -> None:
    world = SimWorld(load_workcell(), seed=4)
    camera = SimCamera(world, seed=4)
    grid = small_grid(8)
    with Session.create(tmp_path / "s.db", grid) as session:
        runner = Runner(session, SimRobot(world, move_time_s=0.0), SimSensor(world), camera,
                        RunnerConfig(samples_per_pose=1, max_retries=1, return_on_pause=True,
                                     max_skips_in_a_row=3))
        assert camera.measure_spot().ok  # the camera worked (a frozen one re-sends this frame)
        camera.set_faults([fault])
        paused = runner.run()
        assert paused.state == "paused"
        assert (paused.done, paused.skipped) == (2, 2)   # the third is measured again later
        assert "3 poses in a row could not be measured (last: camera: " in paused.message
        assert reason in paused.message
        skipped = [s for s in session.samples() if not s.ok]
        assert len(skipped) == 2 and all(reason in s.reason for s in skipped)
        assert all(s.x_p is None and s.d is None for s in skipped)
        camera.set_faults([])
        runner.resume()
        done = runner.run()
    assert (done.state, done.done, done.skipped) == ("finished", 8, 2)


def test_opencv_camera_refuses_a_frozen_stream(tmp_path: Path) -> None:
    """The hardware camera class (cv2.VideoCapture on an image sequence): a stream that
    re-delivers the same image is refused as a frozen frame; a new image is measured."""
    spec = load_workcell().camera
    r = FrameRenderer(spec, seed=5)
    spot = r.render([r.spot_for(600.0, 500.0)])
    moved = r.render([r.spot_for(610.0, 505.0)])
    for i, frame in enumerate([spot, spot, moved]):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), frame)
    mapping = PixelToPlate(spec.camera_matrix(), spec.dist_coeffs(),
                           np.linalg.inv(spec.homography()))
    camera = OpenCVCamera(str(tmp_path / "f%03d.png"), mapping)
    try:
        first = camera.measure_spot()
        assert first.ok and abs(first.u - 600.0) < 0.3
        frozen = camera.measure_spot()
        assert not frozen.ok and frozen.reason == FROZEN_FRAME
        fresh = camera.measure_spot()
        assert fresh.ok and abs(fresh.u - 610.0) < 0.3
    finally:
        camera.close()
