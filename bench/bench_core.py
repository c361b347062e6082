"""Benchmark of the calibration core (run on demand: ``python bench/bench_core.py``).

Goals (issue 2): solve 42 poses in < 5 ms in-process; eq-16 reconstruction of 1e6 points in
< 0.1 s. Prints the median of repeated runs.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from calib_core.calibrate import solve
from calib_core.io import load_dataset
from calib_core.model import Poses, rotation_about_z

EXAMPLE = Path(__file__).resolve().parents[1] / "static_data" / "example_paper_grid.csv"


def median_time(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    data = load_dataset(EXAMPLE)
    t_solve = median_time(lambda: solve(data), 200)
    print(f"solve, 42 poses (robust ML + variance components): {t_solve * 1e3:.2f} ms "
          f"median of 200 (goal < 5 ms)")
    cal = solve(data)
    rng = np.random.default_rng(0)
    n = 1_000_000
    theta = rng.uniform(-10, 10, n)
    poses = Poses(rng.uniform(-5, 5, (n, 3)), rotation_about_z(theta), theta)
    d = rng.uniform(-5, 5, n)
    t_rec = median_time(lambda: cal.reconstruct(poses, d), 10)
    print(f"eq 16 reconstruction, 1e6 points: {t_rec * 1e3:.1f} ms median of 10 (goal < 100 ms)")
    t_cov = median_time(lambda: cal.point_covariance(poses, d), 3)
    print(f"eq 16 point covariance, 1e6 points: {t_cov * 1e3:.1f} ms median of 3")


if __name__ == "__main__":
    main()
