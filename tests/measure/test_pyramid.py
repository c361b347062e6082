"""Pyramid pose from three scanned faces: truth within 3 sigma, honest sigmas, warnings, errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_core.errors import InputError
from calib_core.measure import reconstruct
from calib_core.pyramid import PyramidGeometry, load_geometry, measure_pyramid, pyramid_pose
from tests.measure import sim_scans as sim

APEX = np.array([150.0, 40.0, 30.0])
#: A Schoenflies calibration knows z_t - delta: reconstructed z is height above the plate datum.
APEX_DATUM = APEX - [0.0, 0.0, sim.DELTA]


def _measure(rng: np.random.Generator, rot: np.ndarray, per_face: int = 8,
             calib_rng: np.random.Generator | None = None):
    geo = load_geometry()
    pts, labels = sim.pyramid_targets(geo, rot, APEX, per_face, rng)
    scan = sim.scan_targets(pts, rng)
    cal = sim.calibration(calib_rng)
    return measure_pyramid(reconstruct(scan.poses, scan.d, cal), labels, geo)


def _rot_error(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Small rotation (rad) about world axes taking ``true`` to ``est``."""
    return Rotation.from_matrix(est @ true.T).as_rotvec()


def test_geometry_file_is_consistent() -> None:
    geo = load_geometry()
    assert geo.face_names == ("A", "B", "C")
    np.testing.assert_allclose(np.linalg.norm(geo.normals, axis=1), 1.0, atol=1e-12)
    # faces at 45 deg to the axis, 120 deg apart; edges point down, away from the apex
    np.testing.assert_allclose(geo.normals[:, 2], np.sqrt(0.5), atol=1e-12)
    assert np.all(geo.edges[:, 2] < 0)
    for k in range(3):  # edge k lies on faces k and k+1
        assert abs(geo.edges[k] @ geo.normals[k]) < 1e-12
        assert abs(geo.edges[k] @ geo.normals[(k + 1) % 3]) < 1e-12


def test_pose_matches_truth_within_3_sigma() -> None:
    rng = np.random.default_rng(1)
    for _ in range(5):
        rot = sim.random_rotation(rng, 25.0)
        pose = _measure(rng, rot)
        assert not pose.warnings
        z = (pose.apex - APEX_DATUM) / pose.apex_sigma
        assert np.all(np.abs(z) < 3.5), z
        w = _rot_error(pose.rotation, rot)
        chi2 = w @ np.linalg.solve(pose.rotation_cov, w)
        assert chi2 < 14.2, chi2  # chi2(3) at 99.7 %
        # sigmas realistic for 8 points per 3 mm face with seed Table 2 noise
        assert 0.003 < pose.apex_sigma.max() < 0.05
        assert 0.01 < pose.rotation_sigma_deg.max() < 0.3
        np.testing.assert_allclose(np.linalg.norm(pose.edges, axis=1), 1.0, atol=1e-12)
        true_edges = load_geometry().edges @ rot.T
        assert np.degrees(np.arccos(np.clip(np.sum(pose.edges * true_edges, 1), -1, 1))).max() < 1
        q = pose.quaternion
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(Rotation.from_quat(q, scalar_first=True).as_matrix(),
                                   pose.rotation, atol=1e-12)


def test_sigma_honesty_monte_carlo() -> None:
    """Scatter of apex and rotation over 100 scans (new noise and a new calibration draw each
    time) against the reported sigma: ratio 0.7-1.4."""
    rng = np.random.default_rng(2)
    rot = sim.random_rotation(np.random.default_rng(3), 15.0)
    apex_err, rot_err, apex_sig, rot_sig = [], [], [], []
    for _ in range(100):
        pose = _measure(rng, rot, per_face=6, calib_rng=rng)
        apex_err.append(pose.apex - APEX_DATUM)
        rot_err.append(_rot_error(pose.rotation, rot))
        apex_sig.append(pose.apex_sigma)
        rot_sig.append(np.sqrt(np.diag(pose.rotation_cov)))
    ratio_apex = np.std(apex_err, axis=0) / np.mean(apex_sig, axis=0)
    ratio_rot = np.std(rot_err, axis=0) / np.mean(rot_sig, axis=0)
    assert np.all((ratio_apex > 0.7) & (ratio_apex < 1.4)), ratio_apex
    assert np.all((ratio_rot > 0.7) & (ratio_rot < 1.4)), ratio_rot
    # no bias: the mean of 100 errors within 3.5 sigma / sqrt(100)
    assert np.all(np.abs(np.mean(apex_err, axis=0)) < 0.35 * np.mean(apex_sig, axis=0))


def test_intersection_apex_and_noise_free_exactness() -> None:
    geo = load_geometry()
    rng = np.random.default_rng(4)
    rot = sim.random_rotation(rng, 30.0)
    pts, labels = sim.pyramid_targets(geo, rot, APEX, 5, rng)
    pose = pyramid_pose(pts, labels, None, geo)
    np.testing.assert_allclose(pose.apex, APEX, atol=1e-9)
    np.testing.assert_allclose(pose.apex_intersection, APEX, atol=1e-9)
    np.testing.assert_allclose(pose.rotation, rot, atol=1e-10)
    np.testing.assert_allclose(pose.face_normals, geo.normals @ rot.T, atol=1e-10)
    # labels are case-insensitive and may come as any order of rows
    order = rng.permutation(len(pts))
    pose2 = pyramid_pose(pts[order], np.char.lower(labels[order]), None, geo)
    np.testing.assert_allclose(pose2.apex, APEX, atol=1e-9)


def test_near_parallel_faces_warn() -> None:
    tilt = np.radians(8.0)  # faces only 8 deg from horizontal: normals ~14 deg apart
    normals = [[np.sin(tilt) * np.cos(a), np.sin(tilt) * np.sin(a), np.cos(tilt)]
               for a in np.radians([0.0, 120.0, 240.0])]
    faces = [{"name": n, "normal": v} for n, v in zip("ABC", normals, strict=True)]
    geo = PyramidGeometry.from_mapping({"height": 0.5, "faces": faces})
    rng = np.random.default_rng(5)
    pts, labels = sim.pyramid_targets(geo, np.eye(3), APEX, 6, rng, margin=0.1)
    pts = pts + rng.normal(scale=0.002, size=pts.shape)
    pose = pyramid_pose(pts, labels, np.broadcast_to(0.002**2 * np.eye(3), (len(pts), 3, 3)), geo)
    assert any("nearly parallel" in w for w in pose.warnings)


def test_wrong_labels_warn_about_shape() -> None:
    geo = load_geometry()
    rng = np.random.default_rng(6)
    pts, labels = sim.pyramid_targets(geo, np.eye(3), APEX, 6, rng)
    swapped = np.where(labels == "A", "B", np.where(labels == "B", "A", labels))
    pose = pyramid_pose(pts, swapped, None, geo)
    assert any("nominal geometry" in w for w in pose.warnings)


@pytest.mark.parametrize(("per_face_drop", "labels_bad", "message"), [
    (True, False, "at least 3"),
    (False, True, "not one of"),
])
def test_bad_input(per_face_drop: bool, labels_bad: bool, message: str) -> None:
    geo = load_geometry()
    pts, labels = sim.pyramid_targets(geo, np.eye(3), APEX, 4, np.random.default_rng(8))
    if per_face_drop:
        keep = np.flatnonzero(labels != "C")[:]
        keep = np.concatenate([keep, np.flatnonzero(labels == "C")[:2]])
        pts, labels = pts[keep], labels[keep]
    if labels_bad:
        labels = labels.copy().astype(object)
        labels[3] = "D"
    with pytest.raises(InputError, match=message):
        pyramid_pose(pts, labels, None, geo)


def test_bad_geometry() -> None:
    with pytest.raises(InputError, match="three"):
        PyramidGeometry.from_mapping({"faces": [{"name": "A", "normal": [0, 0, 1]}]})
    with pytest.raises(InputError, match="coplanar"):
        PyramidGeometry.from_mapping({"faces": [
            {"name": "A", "normal": [1, 0, 1]}, {"name": "B", "normal": [0, 1, 1]},
            {"name": "C", "normal": [1, 1, 2]}]})
