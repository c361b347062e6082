"""Spot detector benchmark: RMS error (px) against the rendered truth and frames/s at 1280x1024.

Run: /work/venv/bin/python bench/bench_spot.py [--frames 300] [--seed 0]

Frames are rendered first (not timed) from the default workcell's camera (spot sigma 3 px,
read noise 1.5 grey levels, plate texture, laser-off background frame); then ``detect_spot``
runs on each (timed, single thread, best of three passes). Rows: the default speckle and
variants, the plain centroid for comparison, and the simulated camera's full grab (render) +
detect + map cycle.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import cv2
import numpy as np

from drivers.camera_cv import DetectorConfig, detect_spot
from drivers.sim.devices import SimCamera
from drivers.sim.render import FrameRenderer
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld


def run(renderer: FrameRenderer, n: int, seed: int, speckle: float | None,
        config: DetectorConfig) -> tuple[float, float, float, int]:
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(40, 1240, n), rng.uniform(40, 984, n)])
    angles = rng.uniform(0, 180, n)
    frames = [renderer.render([renderer.spot_for(u, v, angle_deg=a)], speckle=speckle)
              for (u, v), a in zip(truth, angles, strict=True)]
    background = renderer.render()
    detect_spot(frames[0], background, config)  # warm-up
    elapsed = float("inf")
    for _ in range(3):  # best of three passes: the machine may be shared
        t0 = time.perf_counter()
        dets = [detect_spot(f, background, config) for f in frames]
        elapsed = min(elapsed, time.perf_counter() - t0)
    ok = np.array([d.ok for d in dets])
    uv = np.array([(d.u, d.v) for d in dets])
    err = np.linalg.norm(uv[ok] - truth[ok], axis=1)
    return float(np.sqrt(np.mean(err**2))), float(err.max()), n / elapsed, int(ok.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    wc = load_workcell()
    cam = wc.camera
    renderer = FrameRenderer(cam, seed=args.seed)
    w, h = cam.resolution
    print(f"spot detection at {w}x{h}, spot sigma {cam.spot_sigma_px} px, read noise "
          f"{cam.sensor_noise} grey levels, {args.frames} frames per row")
    print(f"{'case':42s} {'rms px':>8s} {'max px':>8s} {'frames/s':>9s} {'ok':>5s}")
    rows = [
        (f"default (speckle {cam.speckle:g}), Gaussian fit", None, DetectorConfig()),
        ("no speckle, Gaussian fit", 0.0, DetectorConfig()),
        ("no speckle, centroid only", 0.0, DetectorConfig(fit=False)),
        ("speckle 0.05, Gaussian fit", 0.05, DetectorConfig()),
        ("speckle 0.10, Gaussian fit", 0.10, DetectorConfig()),
        (f"default (speckle {cam.speckle:g}), centroid only", None, DetectorConfig(fit=False)),
    ]
    for name, speckle, config in rows:
        rms, mx, fps, ok = run(renderer, args.frames, args.seed, speckle, config)
        print(f"{name:42s} {rms:8.4f} {mx:8.4f} {fps:9.0f} {ok:5d}")

    world = SimWorld(dataclasses.replace(wc), seed=args.seed)
    sim = SimCamera(world, seed=args.seed)
    t0 = time.perf_counter()
    mapping = sim.calibrate()
    t_cal = time.perf_counter() - t0
    uv = np.random.default_rng(1).uniform([20, 20], [w - 21, h - 21], size=(2000, 2))
    err = np.linalg.norm(mapping.to_plate(uv) - cam.unproject(uv), axis=1) * 1000
    print(f"chessboard calibration: {t_cal:.2f} s, corner reprojection {mapping.rms_px:.3f} px, "
          f"mapping error over the field rms {np.sqrt(np.mean(err**2)):.3f} um, "
          f"max {err.max():.3f} um")
    n = min(args.frames, 100)
    t0 = time.perf_counter()
    for _ in range(n):
        sim.measure_spot()
    dt = (time.perf_counter() - t0) / n
    print(f"SimCamera.measure_spot (render + detect + map): {1000 * dt:.1f} ms per sample")


if __name__ == "__main__":
    main()
