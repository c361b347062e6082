"""Platform calibration figures over several simulated campaigns (run on demand).

    .venv/bin/python bench/bench_platform.py [N_SEEDS]

Per seed, for measured poses (0.005 deg, 3 um) and for face scans (8 points per face through
the pyramid fit): the largest |identified - truth| / sigma over the identifiable parameters, and
the validation orientation / apex RMS before (nominal) and after calibration, with run times.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from calib_core import platform as pf
from calib_core.model import Poses, rotation_about_z
from drivers.sim.platform import load_spec, simulate_campaign, simulate_scan_campaign


def _scan_poses(camp, scan_set) -> pf.PoseSet:
    sc = scan_set.scans
    flange = Poses(sc.position, rotation_about_z(sc.theta_deg), sc.theta_deg)
    return pf.poses_from_scans(scan_set.config[sc.row_pose], scan_set.q_deg[sc.row_pose],
                               sc.row_pose, flange, sc.d, sc.face, camp.calibration)[0]


def main(n_seeds: int = 5) -> None:
    spec = load_spec()
    for seed in range(n_seeds):
        for mode in ("poses", "scans"):
            t0 = time.perf_counter()
            if mode == "poses":
                camp = simulate_campaign(spec, seed)
                train, val = camp.train, camp.validation
            else:
                scamp = simulate_scan_campaign(spec, seed)
                train, val = _scan_poses(scamp, scamp.train), _scan_poses(scamp, scamp.validation)
            t1 = time.perf_counter()
            cal = pf.identify(train, spec.nominal, spec.noise.joint_deg)
            t2 = time.perf_counter()
            rot, apex = pf.forward(spec.true, train.q_deg)
            clean = pf.PoseSet(train.config, train.q_deg, rot, apex,
                               np.tile(np.eye(6) * 1e-6, (len(train), 1, 1)))
            eq = pf.identify(clean, spec.nominal).params
            z = max(abs(cal.params[n] - eq[n]) / cal.sigma[n] for n in cal.free)
            b, a = pf.evaluate(spec.nominal, val), pf.evaluate(cal.params, val)
            print(f"seed {seed} {mode:5s}: max|z| {z:4.2f}  orientation RMS "
                  f"{b['orientation_rms_deg']:.4f} -> {a['orientation_rms_deg']:.4f} deg "
                  f"(floor {a['noise_orientation_rms_deg']:.4f})  apex RMS "
                  f"{b['apex_rms_mm'] * 1e3:.1f} -> {a['apex_rms_mm'] * 1e3:.1f} um  "
                  f"[simulate {t1 - t0:.2f} s, identify {t2 - t1:.2f} s]")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
