"""Acquisition overhead per pose in the simulator with zero move time (goal < 20 ms).

Runs the paper grid (42 poses) through :class:`app.acquisition.Runner` with the simulated
robot (move_time_s = 0), sensor and the direct (non-rendering) camera, committing every sample
to a session file (WAL, synchronous=FULL) in a temporary directory; prints the median time
per pose over several sessions, the time of one commit, and for scale a full simulated pose
with the rendered camera.

    .venv/bin/python bench/bench_acquire.py [--repeats 5] [--dir DIR]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from app.acquisition import Runner, RunnerConfig
from app.session import Sample, Session
from calib_core.grid import paper_grid
from drivers.sim import devices
from drivers.sim.devices import SimCameraDirect, SimRobot, SimSensor
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld


def per_pose(directory: Path, k: int, seed: int, rendered: bool = False) -> float:
    world = SimWorld(load_workcell(), seed=seed)
    grid = paper_grid()
    camera = devices.SimCamera(world, seed=seed) if rendered else SimCameraDirect(world)
    with Session.create(directory / f"b{k}_{seed}_{rendered}.db", grid) as session:
        runner = Runner(session, SimRobot(world, move_time_s=0.0), SimSensor(world),
                        camera, RunnerConfig(samples_per_pose=k))
        t0 = time.perf_counter()
        result = runner.run()
        elapsed = time.perf_counter() - t0
    assert result.done == len(grid)
    return elapsed / len(grid)


def commit_time(directory: Path, run: int) -> float:
    grid = paper_grid()
    with Session.create(directory / f"commit{run}.db", grid) as session:
        t0 = time.perf_counter()
        for i in range(len(grid)):
            session.add_sample(Sample(i, grid.pose(i), grid.pose(i), 0.5, 1.0, 2.0, 1.0))
        return (time.perf_counter() - t0) / len(grid)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dir", type=Path, help="where the session files go (default: a "
                        "temporary directory)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        directory = Path(tmp)
        commit = statistics.median(commit_time(directory, r) for r in range(args.repeats))
        print(f"session commit per sample (WAL, synchronous=FULL): {commit * 1e3:.2f} ms")
        for k in (1, 3, 10):
            times = [per_pose(directory, k, seed) for seed in range(args.repeats)]
            print(f"runner overhead per pose, {k:2d} reading(s) averaged, zero move time: "
                  f"median {statistics.median(times) * 1e3:.2f} ms, max {max(times) * 1e3:.2f} "
                  f"ms over {args.repeats} sessions of 42 poses (goal < 20 ms)")
        if hasattr(devices, "SimCamera"):  # for scale: rendering + OpenCV detection per frame
            times = [per_pose(directory, 3, seed, rendered=True) for seed in range(2)]
            print(f"full simulated pose with the rendered camera (1280x1024 frames through the "
                  f"spot detector), 3 readings: median {statistics.median(times) * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
