"""End-to-end measuring figures in the simulated seed cell (run on demand).

1. Solve the packaged calibration example (``static_data/example_paper_grid.csv``, 42 poses).
2. Scan the side (aluminium) plate of the simulated cell with the simulated robot and sensor
   (three heights, rotations about z), reconstruct by eq 16 and fit the plane (seed Table 3
   scenario) by both fits; print the parameters +- sigma against the simulation's truth and a
   Monte Carlo of the scatter over repeated scans against the reported sigma.
3. Time the reconstruction + fit of a 1000-point scan and the pyramid pose from 30 points.

    .venv/bin/python bench/bench_measure.py [--repeats 50]
"""

from __future__ import annotations

import argparse
import time
from importlib import resources

import numpy as np

from calib_core.calibrate import solve
from calib_core.io import load_dataset
from calib_core.measure import fit_scan_plane, reconstruct
from calib_core.model import Poses, rotation_about_z
from calib_core.pyramid import load_geometry, pyramid_pose
from drivers.base import FlangePose
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld


def side_plate_scan(world: SimWorld, calib_t: np.ndarray) -> tuple[Poses, np.ndarray]:
    """Poses over the side plate (5 x 6 spots, three heights, theta -30..30) and readings."""
    side = world.workcell.side_plate
    cx, cy = side.centre
    pos, theta, d = [], [], []
    for k, dz in enumerate((-3.0, 0.0, 3.0)):
        for x in np.linspace(cx - 10, cx + 10, 5):
            for y in np.linspace(cy - 14, cy + 14, 6):
                th = (-30.0, 0.0, 30.0)[k]
                rz = rotation_about_z(np.array([th]))[0]
                z_plate = side.alpha * x + side.beta * y + side.delta
                o = np.array([x, y, z_plate]) - rz @ calib_t + [0.0, 0.0, dz]
                world.move(FlangePose(float(o[0]), float(o[1]), float(o[2]), th))
                reading = world.read_sensor()
                if reading.value is None:
                    continue
                rep = world.reported_pose()
                pos.append([rep.x, rep.y, rep.z])
                theta.append(rep.theta_deg)
                d.append(reading.value)
    th = np.array(theta)
    return Poses(np.array(pos), rotation_about_z(th), th), np.array(d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    with resources.as_file(resources.files("static_data") / "example_paper_grid.csv") as p:
        calib = solve(load_dataset(p))
    print(f"calibration: {calib.model}, c = {calib.point('c'):.5f} +- {calib.sigma[5]:.5f}")
    wc = load_workcell()
    side = wc.side_plate
    truth = np.array([side.alpha, side.beta, side.delta])  # glass datum delta = 0
    print(f"side plate truth: alpha {truth[0]:.4e}  beta {truth[1]:.4e}  offset {truth[2]:.4f}")
    for method in ("ls", "orthogonal"):
        est, sig = [], []
        for seed in range(args.repeats):
            world = SimWorld(wc, seed=seed + 1)
            poses, d = side_plate_scan(world, calib.beam_point)
            fit = fit_scan_plane(reconstruct(poses, d, calib), method)
            est.append([fit.alpha, fit.beta, fit.offset])
            sig.append(np.sqrt(np.diag(fit.covariance)))
            if seed == 0:
                s = fit.sigma
                print(f"[{method}] one scan, {fit.n_points} points: alpha {fit.alpha:.4e} +- "
                      f"{s['alpha']:.1e}, beta {fit.beta:.4e} +- {s['beta']:.1e}, offset "
                      f"{fit.offset:.4f} +- {s['offset']:.4f}, rms {fit.rms * 1e3:.1f} um")
        est_a, sig_a = np.array(est), np.array(sig)
        z = (est_a - truth) / sig_a
        print(f"[{method}] {args.repeats} scans (same calibration): mean error / sigma "
              f"{np.round(z.mean(axis=0), 2)}, scatter / mean sigma "
              f"{np.round(est_a.std(axis=0) / sig_a.mean(axis=0), 2)} "
              "(below 1: the calibration's share of sigma is common to all scans)")

    rng = np.random.default_rng(0)
    n = 1000
    th = rng.uniform(-30, 30, n)
    poses = Poses(rng.uniform(-20, 20, (n, 3)), rotation_about_z(th), th)
    d = rng.uniform(-5, 5, n)
    t0 = time.perf_counter()
    for _ in range(20):
        fit_scan_plane(reconstruct(poses, d, calib), "orthogonal")
    print(f"reconstruct + orthogonal fit, {n} points: "
          f"{(time.perf_counter() - t0) / 20 * 1e3:.2f} ms")
    geo = load_geometry()
    pts, labels = [], []
    for k, name in enumerate(geo.face_names):
        e1, e2 = geo.edges[(k - 1) % 3], geo.edges[k]
        for s, t in rng.uniform(0.5, 2.5, (10, 2)):
            pts.append(s * e1 + t * e2)
            labels.append(name)
    pts_a = np.array(pts) + rng.normal(scale=0.003, size=(30, 3))
    cov = np.broadcast_to(0.003**2 * np.eye(3), (30, 3, 3))
    t0 = time.perf_counter()
    for _ in range(20):
        pose = pyramid_pose(pts_a, labels, cov, geo)
    print(f"pyramid pose, 30 points: {(time.perf_counter() - t0) / 20 * 1e3:.2f} ms "
          f"(apex sigma {np.round(pose.apex_sigma * 1e3, 1)} um, rotation sigma "
          f"{np.round(pose.rotation_sigma_deg, 3)} deg at 3 um point noise)")


if __name__ == "__main__":
    main()
