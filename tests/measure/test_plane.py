"""Plane identification from scans (seed eq 16-20) and by total least squares; sigma honesty."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.errors import InputError
from calib_core.measure import compare_with_camera, fit_plane, fit_scan_plane, reconstruct
from calib_core.noise import NoiseModel
from tests.measure import sim_scans as sim

# side (aluminium) plate like the seed's Table 3; true offset in the robot frame
ALPHA, BETA, OFFSET = 4.152e-3, -3.153e-3, -9.981
#: A Schoenflies calibration knows only z_t - delta: offsets come out relative to the datum.
OFFSET_DATUM = OFFSET - sim.DELTA
XY = sim.grid_xy(170.0, 40.0, 20.0, 7)
TRUE = np.array([ALPHA, BETA, OFFSET_DATUM])


def _fit(rng: np.random.Generator, method: str, calib_rng: np.random.Generator | None = None,
         noise: NoiseModel | None = None, targets: np.ndarray | None = None):
    targets = sim.plane_targets(ALPHA, BETA, OFFSET, XY) if targets is None else targets
    scan = sim.scan_targets(targets, rng, noise)
    pts = reconstruct(scan.poses, scan.d, sim.calibration(calib_rng), noise)
    return fit_scan_plane(pts, method), scan, pts


@pytest.mark.parametrize("method", ["ls", "orthogonal"])
def test_plane_within_3_sigma(method: str) -> None:
    rng = np.random.default_rng(10)
    for _ in range(5):
        fit, _, _ = _fit(rng, method, calib_rng=rng)
        est = np.array([fit.alpha, fit.beta, fit.offset])
        z = (est - TRUE) / np.sqrt(np.diag(fit.covariance))
        assert np.all(np.abs(z) < 3.5), z
        assert fit.n_points == 49 and not fit.warnings
        assert fit.rms < 0.02  # seed Table 4 level is 0.03-0.07 mm with a worse camera
        np.testing.assert_allclose(fit.normal, np.array([-ALPHA, -BETA, 1.0])
                                   / np.sqrt(1 + ALPHA**2 + BETA**2), atol=1e-3)
        # the calibration covariance (z_t - delta, common to all points) matters for the offset
        assert fit.cov_calibration[2, 2] > 0.3 * fit.cov_noise[2, 2]


@pytest.mark.parametrize("method", ["ls", "orthogonal"])
def test_sigma_honesty_monte_carlo(method: str) -> None:
    """100 scans, each with new scan noise and a new calibration drawn from its covariance:
    empirical scatter / reported sigma within 0.7-1.4 for alpha, beta, offset."""
    rng = np.random.default_rng(11)
    est, sig = [], []
    for _ in range(100):
        fit, _, _ = _fit(rng, method, calib_rng=rng)
        est.append([fit.alpha, fit.beta, fit.offset])
        sig.append(np.sqrt(np.diag(fit.covariance)))
    z = (np.array(est) - TRUE) / np.array(sig)  # each scan has its own design and sigma
    ratio = np.std(z, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    assert np.all(np.abs(np.mean(z, axis=0)) < 0.35), np.mean(z, axis=0)  # no bias


def test_calibration_part_is_common_to_all_points() -> None:
    """Noise-free scans, only the calibration varies: the scatter matches ``cov_calibration``
    (treating C_H as independent per-point noise would shrink it by ~sqrt(n))."""
    rng = np.random.default_rng(12)
    quiet = NoiseModel(camera=0, robot_xy=0, robot_z=0, robot_theta_deg=0, sensor=0)
    est, sig = [], []
    for _ in range(100):
        fit, _, _ = _fit(rng, "ls", calib_rng=rng, noise=quiet)
        est.append([fit.alpha, fit.beta, fit.offset])
        sig.append(np.sqrt(np.diag(fit.cov_calibration)))
    ratio = np.std((np.array(est) - TRUE) / np.array(sig), axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


def test_noise_free_fits_are_exact() -> None:
    pts = sim.plane_targets(ALPHA, BETA, OFFSET, XY)
    for method in ("ls", "orthogonal"):
        fit = fit_plane(pts, method)
        np.testing.assert_allclose([fit.alpha, fit.beta, fit.offset], [ALPHA, BETA, OFFSET],
                                   atol=1e-12)
        assert fit.rms < 1e-12


def test_steep_plane_orthogonal_fit() -> None:
    """A 50 deg slope: the orthogonal fit's normal is within 3 sigma and its sigma is honest."""
    slope = np.tan(np.radians(50.0))
    xy = sim.grid_xy(120.0, 30.0, 3.0, 6)
    targets = sim.plane_targets(slope, 0.2, 2.0, xy)
    n_true = np.array([-slope, -0.2, 1.0]) / np.linalg.norm([slope, 0.2, 1.0])
    rng = np.random.default_rng(13)
    errs, sig = [], []
    for _ in range(100):
        fit, _, _ = _fit(rng, "orthogonal", calib_rng=rng, targets=targets)
        err = fit.normal - n_true
        errs.append(err)
        sig.append(np.sqrt(np.diag(fit.normal_covariance)))
    z = (np.array(errs) / np.array(sig))[:, 0:2]
    ratio = np.std(z, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    assert np.all(np.abs(np.mean(z, axis=0)) < 0.35), np.mean(z, axis=0)
    vertical = fit_plane(np.column_stack([xy[:, 0], np.zeros(len(xy)), xy[:, 1]]), "orthogonal")
    assert any("steep" in w for w in vertical.warnings)
    steep_ls = fit_plane(sim.plane_targets(np.tan(np.radians(80.0)), 0.0, 0.0, xy), "ls")
    assert any("orthogonal fit" in w for w in steep_ls.warnings)
    np.testing.assert_allclose(np.abs(vertical.normal), [0, 1, 0], atol=1e-12)


def test_camera_comparison_like_tables_3_4() -> None:
    rng = np.random.default_rng(14)
    fit, scan, pts = _fit(rng, "ls")
    cam_sigma = 0.0123  # top camera, seed Table 2
    spot_xy = scan.truth[:, 0:2] + rng.normal(scale=cam_sigma, size=(len(scan.d), 2))
    cmp = compare_with_camera(pts.xyz, spot_xy, fit)
    err = cmp["point_errors"]
    for axis in ("x", "y"):
        assert 0.7 * cam_sigma < err[axis]["rms"] < 2.0 * cam_sigma, err  # + robot 12 um
        assert err[axis]["mean_abs"] <= err[axis]["rms"] <= err[axis]["max"]
    assert err["z"]["rms"] < 0.01
    diff = cmp["difference"]
    assert abs(diff["alpha"]) < 1e-3 and abs(diff["beta"]) < 1e-3 and abs(diff["offset"]) < 0.05
    assert cmp["camera_plane"]["alpha"] == pytest.approx(fit.alpha - diff["alpha"])
    # three points are enough for the camera plane too (no scatter needed)
    few = compare_with_camera(pts.xyz[:3], spot_xy[:3], fit)
    assert np.isfinite(few["camera_plane"]["offset"])


def test_bad_input() -> None:
    line = np.column_stack([np.arange(5.0), np.arange(5.0), np.zeros(5)])
    with pytest.raises(InputError, match="collinear"):
        fit_plane(line, "ls")
    with pytest.raises(InputError, match="collinear"):
        fit_plane(line, "orthogonal")
    with pytest.raises(InputError, match="too few"):
        fit_plane(line[:2], "ls")
    with pytest.raises(InputError, match="unknown plane fit"):
        fit_plane(sim.plane_targets(0, 0, 0, XY), "median")
    with pytest.raises(InputError, match="non-finite"):
        fit_plane(np.full((4, 3), np.nan))


def test_general_calibration_tilted_flange() -> None:
    """6-dof flange (tilts up to 15 deg) with a general calibration: z is absolute (no datum),
    rotation noise about every axis; parameters within 3 sigma, sigma honest."""
    rng = np.random.default_rng(15)
    targets = sim.plane_targets(ALPHA, BETA, OFFSET, XY)
    truth = np.array([ALPHA, BETA, OFFSET])
    z = []
    for _ in range(100):
        scan = sim.scan_targets(targets, rng, tilt_deg=15.0)
        assert scan.poses.theta_deg is None
        fit = fit_scan_plane(reconstruct(scan.poses, scan.d, sim.general_calibration(rng)))
        z.append((np.array([fit.alpha, fit.beta, fit.offset]) - truth)
                 / np.sqrt(np.diag(fit.covariance)))
    assert np.all(np.abs(z[0]) < 3.5)
    ratio = np.std(z, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
