"""Test-side scan simulator: a true beam on a 4-dof (Schoenflies) robot scanning surfaces.

For a target spot ``P`` on the surface, a true orientation ``Rz(theta)`` and a true reading
``d0``, the flange is at ``O = P - R (T + d0 u)``; the robot then reports ``O`` and ``theta`` with
noise and the sensor reports ``d0`` with noise (seed Table 2, ``NoiseModel`` defaults).
The beam stays within 20 deg of vertical, so every face the tests use is seen from the front
(no self-occlusion on a convex pyramid).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calib_core.calibrate import BeamCalibration
from calib_core.model import GENERAL_PARAMS, SCHOENFLIES_PARAMS, Poses, rotation_about_z
from calib_core.noise import NoiseModel
from calib_core.pyramid import PyramidGeometry

#: Beam close to the seed's eq 15: T in the flange frame (true z_t), u' = (a, b, c).
TRUE_T = np.array([-6.386, 70.055, -15.073])
TRUE_U = np.array([0.250, -0.181, 0.952])
#: Calibration plate datum (its z at x = y = 0) and tilt.
DELTA = 5.0
PLATE_ALPHA, PLATE_BETA = -0.713e-3, 5.671e-3
#: 1-sigma of the calibration parameters (x_t, y_t, z_t - delta, a, b, c, alpha, beta).
CALIB_SIGMA = np.array([0.004, 0.004, 0.012, 3e-4, 3e-4, 2e-4, 2e-5, 2e-5])


def true_h() -> np.ndarray:
    """True Schoenflies ``H = (x_t, y_t, z_t - delta, a, b, c, alpha, beta)``."""
    return np.array([*TRUE_T[:2], TRUE_T[2] - DELTA, *TRUE_U, PLATE_ALPHA, PLATE_BETA])


def calib_covariance(seed: int = 7) -> np.ndarray:
    """A realistic calibration covariance: ``CALIB_SIGMA`` with random correlations (|rho|<~0.6)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(8, 8))
    corr = a @ a.T + 8 * np.eye(8)
    dg = np.sqrt(np.diag(corr))
    corr = corr / np.outer(dg, dg)
    return corr * np.outer(CALIB_SIGMA, CALIB_SIGMA)


def calibration(rng: np.random.Generator | None = None,
                cov: np.ndarray | None = None) -> BeamCalibration:
    """The calibration a solve would give: true ``H`` (or a draw ``N(H, C)`` with ``rng``)."""
    cov = calib_covariance() if cov is None else cov
    h = true_h()
    if rng is not None:
        h = rng.multivariate_normal(h, cov)
    return BeamCalibration(model="schoenflies", names=SCHOENFLIES_PARAMS, values=h,
                           covariance=cov)


@dataclass(frozen=True)
class Scan:
    poses: Poses
    d: np.ndarray
    truth: np.ndarray  # true spot positions (n, 3), robot frame


def scan_targets(targets: np.ndarray, rng: np.random.Generator,
                 noise: NoiseModel | None = None, theta_deg: np.ndarray | None = None,
                 d0: np.ndarray | None = None, tilt_deg: float = 0.0) -> Scan:
    """Reported poses and readings that put the true spot on each target (n, 3).

    ``tilt_deg > 0``: a 6-dof flange, ``Rz(theta)`` times a random tilt up to ``tilt_deg``,
    reported as a rotation matrix with noise about each axis (``theta_deg`` is then None).
    """
    noise = noise or NoiseModel()
    n = len(targets)
    theta = rng.uniform(-30, 30, n) if theta_deg is None else np.asarray(theta_deg, float)
    d_true = rng.uniform(-4, 4, n) if d0 is None else np.asarray(d0, float)
    rot = rotation_about_z(theta)
    if tilt_deg > 0:
        rot = np.array([random_rotation(rng, tilt_deg) @ r for r in rot])
    origin = targets - np.einsum("nij,nj->ni", rot, TRUE_T[None] + d_true[:, None] * TRUE_U)
    pos = origin + rng.normal(size=(n, 3)) * [noise.robot_xy, noise.robot_xy, noise.robot_z]
    d_rep = d_true + rng.normal(size=n) * noise.sensor
    if tilt_deg > 0:
        err = Rotation.from_rotvec(np.radians(noise.robot_theta_deg) * rng.normal(size=(n, 3)))
        return Scan(Poses(pos, err.as_matrix() @ rot, None), d_rep, targets)
    theta_rep = theta + rng.normal(size=n) * noise.robot_theta_deg
    return Scan(Poses(pos, rotation_about_z(theta_rep), theta_rep), d_rep, targets)


def general_calibration(rng: np.random.Generator | None = None) -> BeamCalibration:
    """A 6-dof (general model) calibration: ``(x_t, y_t, z_t, a, b, c, alpha, beta, delta)``
    with the true values (or a draw from the covariance with ``rng``); z is absolute."""
    sig = np.array([*CALIB_SIGMA[0:2], 0.012, *CALIB_SIGMA[3:8], 0.012])
    cov = np.diag(sig**2)
    cov[2, 8] = cov[8, 2] = 0.5 * sig[2] * sig[8]
    h = np.array([*TRUE_T, *TRUE_U, PLATE_ALPHA, PLATE_BETA, DELTA])
    if rng is not None:
        h = rng.multivariate_normal(h, cov)
    return BeamCalibration(model="general", names=GENERAL_PARAMS, values=h, covariance=cov)


def plane_targets(alpha: float, beta: float, offset: float, xy: np.ndarray) -> np.ndarray:
    """Points of ``z = alpha x + beta y + offset`` above ``xy`` (n, 2)."""
    return np.column_stack([xy, alpha * xy[:, 0] + beta * xy[:, 1] + offset])


def grid_xy(x0: float, y0: float, half: float, k: int) -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(x0 - half, x0 + half, k), np.linspace(y0 - half, y0 + half, k))
    return np.column_stack([gx.ravel(), gy.ravel()])


def pyramid_targets(geometry: PyramidGeometry, rotation: np.ndarray, apex: np.ndarray,
                    per_face: int, rng: np.random.Generator, margin: float = 0.3
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Random points on each face (world frame) and their face names.

    A point on face k is ``apex + s e_(k-1) + t e_k`` on the two edges bounding it, inside the
    face (height above the base > 0) and ``margin`` mm away from the edges.
    """
    edges = geometry.edges  # AB, BC, CA: face k lies between edges k-1 (CA/AB/BC) and k
    pts, labels = [], []
    for k, name in enumerate(geometry.face_names):
        e1, e2 = edges[(k - 1) % 3], edges[k]
        drop = -min(e1[2], e2[2])  # height lost per mm along an edge
        reach = geometry.height / drop
        got = 0
        while got < per_face:
            s, t = rng.uniform(0, reach, 2)
            p = s * e1 + t * e2
            if -p[2] > geometry.height * 0.95:
                continue
            if min(_dist_to_line(p, e1), _dist_to_line(p, e2)) < margin:
                continue
            pts.append(rotation @ p + apex)
            labels.append(name)
            got += 1
    return np.array(pts), np.array(labels)


def _dist_to_line(p: np.ndarray, e: np.ndarray) -> float:
    return float(np.linalg.norm(p - (p @ e) * e))


def random_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation by up to ``max_deg`` about a random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(np.radians(rng.uniform(0, max_deg)) * axis).as_matrix()


def write_scan_csv(path: Path, scan: Scan, **columns: np.ndarray) -> Path:
    """CSV in the measurement format (x_o, y_o, z_o, theta_deg, d, extra columns)."""
    assert scan.poses.theta_deg is not None
    cols = {"x_o": scan.poses.position[:, 0], "y_o": scan.poses.position[:, 1],
            "z_o": scan.poses.position[:, 2], "theta_deg": scan.poses.theta_deg, "d": scan.d,
            **columns}
    lines = ["# simulated scan", ",".join(cols)]
    for i in range(len(scan.d)):
        lines.append(",".join(str(v[i]) if isinstance(v[i], str | np.str_) else repr(float(v[i]))
                              for v in cols.values()))
    path.write_text("\n".join(lines) + "\n")
    return path


def gauge_readings(heights: np.ndarray, spots_xy: np.ndarray, rng: np.random.Generator,
                   noise: NoiseModel | None = None, theta_deg: float = 10.0, d0: float = -4.0
                   ) -> Scan:
    """Gauge blocks of ``heights`` on the calibration plate under a flange held at each of
    ``spots_xy`` (the spot there on the bare plate reads ``d0``); every height at every spot.

    The robot is commanded (and reports) the same pose; the true pose scatters by its
    repeatability; the true reading follows from the beam meeting the gauge top
    ``z = alpha x + beta y + delta + h``: ``d = (delta + h - m . (O + R T)) / (m . R u)``,
    ``m = (-alpha, -beta, 1)``.
    """
    noise = noise or NoiseModel()
    rot = rotation_about_z(np.array([theta_deg]))[0]
    m = np.array([-PLATE_ALPHA, -PLATE_BETA, 1.0])
    pos, d, truth = [], [], []
    for xy in spots_xy:
        p0 = np.array([xy[0], xy[1], PLATE_ALPHA * xy[0] + PLATE_BETA * xy[1] + DELTA])
        origin = p0 - rot @ (TRUE_T + d0 * TRUE_U)
        for h in heights:
            o_true = origin + rng.normal(size=3) * [noise.robot_xy, noise.robot_xy,
                                                     noise.robot_z]
            start = o_true + rot @ TRUE_T
            d_true = (DELTA + h - m @ start) / (m @ (rot @ TRUE_U))
            pos.append(origin)
            d.append(d_true + rng.normal() * noise.sensor)
            truth.append(start + d_true * rot @ TRUE_U)
    n = len(d)
    theta = np.full(n, theta_deg)
    return Scan(Poses(np.array(pos), rotation_about_z(theta), theta), np.array(d),
                np.array(truth))
