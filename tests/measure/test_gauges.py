"""Johansson gauge check: the slope of gauge height against reading estimates c."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.calibrate import BeamCalibration
from calib_core.errors import InputError
from calib_core.measure import gauge_check
from calib_core.model import Poses, rotation_from_quaternion
from tests.measure import sim_scans as sim

HEIGHTS = np.array([0.0, 1.0, 1.5, 2.0, 3.0, 5.0, 7.0])  # mm, a Johansson set
SPOTS = np.array([[20.0, 60.0], [40.0, 80.0]])
C_TRUE = sim.TRUE_U[2]


def _heights() -> np.ndarray:
    return np.tile(HEIGHTS, len(SPOTS))


def test_c_agrees_with_truth_and_calibration() -> None:
    rng = np.random.default_rng(20)
    for _ in range(5):
        scan = sim.gauge_readings(HEIGHTS, SPOTS, rng)
        res = gauge_check(scan.poses, scan.d, _heights(), sim.calibration(rng))
        assert abs(res.c - C_TRUE) < 3.5 * res.c_sigma, (res.c, res.c_sigma)
        assert 2e-4 < res.c_sigma < 2e-3  # 14 readings, 5 um robot z noise over ~7 mm
        assert res.agreement_sigmas is not None and res.agreement_sigmas < 3.5
        assert res.c_calibrated is not None and abs(res.c_calibrated - C_TRUE) < 1e-3
        assert res.n_readings == 14 and not res.warnings
        # intercept is z_t - delta: the spot on the bare plate at d = 0
        assert abs(res.intercept - (sim.TRUE_T[2] - sim.DELTA)) < 0.05


def test_sigma_honesty_monte_carlo() -> None:
    rng = np.random.default_rng(21)
    z, za = [], []
    for _ in range(100):
        scan = sim.gauge_readings(HEIGHTS, SPOTS, rng)
        cal = sim.calibration(rng)
        res = gauge_check(scan.poses, scan.d, _heights(), cal)
        z.append((res.c - C_TRUE) / res.c_sigma)
        za.append(res.agreement_sigmas)
    assert 0.7 < np.std(z) < 1.4, np.std(z)
    assert abs(np.mean(z)) < 0.35
    # |N(0,1)| has mean 0.80: the agreement is a proper number of sigmas
    assert 0.55 < np.mean(za) < 1.1, np.mean(za)


def test_without_calibration() -> None:
    rng = np.random.default_rng(22)
    scan = sim.gauge_readings(HEIGHTS, SPOTS, rng)
    res = gauge_check(scan.poses, scan.d, _heights())
    assert res.agreement_sigmas is None and res.c_calibrated is None
    assert any("no calibration" in w for w in res.warnings)
    assert abs(res.c - C_TRUE) < 0.003  # the plate tilt (5.7e-3) barely matters over 2 mm


def test_wrong_calibration_disagrees() -> None:
    rng = np.random.default_rng(23)
    scan = sim.gauge_readings(HEIGHTS, SPOTS, rng)
    good = sim.calibration()
    values = good.values.copy()
    values[5] += 0.01  # c off by 1 %
    bad = BeamCalibration(good.model, good.names, values, good.covariance)
    res = gauge_check(scan.poses, scan.d, _heights(), bad)
    assert res.agreement_sigmas is not None and res.agreement_sigmas > 5


def test_bad_input() -> None:
    rng = np.random.default_rng(24)
    scan = sim.gauge_readings(HEIGHTS, SPOTS[:1], rng)
    with pytest.raises(InputError, match="too few"):
        gauge_check(scan.poses.subset(np.arange(2)), scan.d[:2], HEIGHTS[:2])
    with pytest.raises(InputError, match="must differ"):
        gauge_check(scan.poses, np.full(len(HEIGHTS), 1.0), np.full(len(HEIGHTS), 2.0))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(HEIGHTS), 1))
    q[1] = [np.cos(0.05), np.sin(0.05), 0.0, 0.0]
    tilted = Poses(scan.poses.position, rotation_from_quaternion(q), None)
    with pytest.raises(InputError, match="tilt"):
        gauge_check(tilted, scan.d, HEIGHTS)
