"""Simulated calibration campaign of the 2-dof orientation platform carrying the pyramid.

For each configuration the platform is commanded to ``q_cmd``; the actuators reach
``q_true = q_cmd + N(0, joint_deg^2)``; the true pyramid pose is the five-bar model
(:func:`calib_core.platform.forward`) with the *true* parameters at ``q_true``. The measured pose
carries Gaussian noise with a per-measurement covariance (principal axes at random, 1-sigma
between 0.6 and 1.4 times ``noise.rotation_deg`` / ``noise.apex_mm``): ``R_meas = Exp(e) R_true``
(``e`` a fixed-frame rotation vector), ``apex_meas = apex_true + n``. The covariance is reported
with the pose, as a pyramid fit would report it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calib_core.calibrate import BeamCalibration
from calib_core.errors import InputError
from calib_core.io import load_toml
from calib_core.model import SCHOENFLIES_PARAMS, rotation_about_z
from calib_core.noise import NoiseModel
from calib_core.platform import PoseSet, forward, params_from_mapping
from calib_core.pyramid import PyramidGeometry, load_geometry
from drivers.sim.workcell import load_workcell

#: First configuration id of the validation set (identification ids start at 0).
VALIDATION_ID0 = 1000


@dataclass(frozen=True)
class PlatformNoise:
    """1-sigma: apex (mm) and rotation (deg) of one measured pose, actuator repeatability (deg)."""

    apex_mm: float = 0.003
    rotation_deg: float = 0.005
    joint_deg: float = 0.002


@dataclass(frozen=True)
class PlatformSpec:
    """Nominal and true parameters, noise, and the campaign design of ``platform.toml``."""

    nominal: dict[str, float]
    true: dict[str, float]
    noise: PlatformNoise
    q1_range_deg: tuple[float, float] = (-30.0, 30.0)
    q2_range_deg: tuple[float, float] = (-30.0, 30.0)
    grid: int = 7
    validation_random: int = 20
    iso_repeats: int = 10


def _pair(value: Any, source: str, key: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{source}: [campaign] {key} must be [low, high] in degrees") from None
    if not lo < hi:
        raise InputError(f"{source}: [campaign] {key} must have low < high")
    return lo, hi


def spec_from_mapping(data: Mapping[str, Any], source: str = "platform.toml") -> PlatformSpec:
    """Build a :class:`PlatformSpec` from the parsed TOML; bad entries raise InputError."""
    nominal = params_from_mapping(data.get("nominal", {}), f"{source} [nominal]")
    true = params_from_mapping(data.get("true", {}), f"{source} [true]", base=nominal)
    nz = dict(data.get("noise", {}))
    unknown = sorted(set(nz) - {"apex_mm", "rotation_deg", "joint_deg"})
    if unknown:
        raise InputError(f"{source}: unknown [noise] key(s) {', '.join(unknown)}")
    noise = PlatformNoise(**{k: float(v) for k, v in nz.items()})
    if min(noise.apex_mm, noise.rotation_deg) <= 0 or noise.joint_deg < 0:
        raise InputError(f"{source}: [noise] sigmas must be positive")
    camp = dict(data.get("campaign", {}))
    spec = PlatformSpec(
        nominal, true, noise,
        _pair(camp.get("q1_range_deg", (-30, 30)), source, "q1_range_deg"),
        _pair(camp.get("q2_range_deg", (-30, 30)), source, "q2_range_deg"),
        int(camp.get("grid", 7)), int(camp.get("validation_random", 20)),
        int(camp.get("iso_repeats", 10)))
    if spec.grid < 3 or spec.validation_random < 0 or spec.iso_repeats < 2:
        raise InputError(f"{source}: [campaign] needs grid >= 3, validation_random >= 0, "
                         "iso_repeats >= 2")
    return spec


def load_spec(path: str | Path | None = None) -> PlatformSpec:
    """Read ``path`` or the packaged ``static_data/platform.toml``."""
    data, source = load_toml(path, "platform.toml", "platform file")
    return spec_from_mapping(data, source)


def design(spec: PlatformSpec, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Configuration ids and commanded ``q`` (deg) for identification and validation.

    Identification: the ``grid x grid`` lattice over the ranges. Validation: ``validation_random``
    uniform configurations within 90 % of the ranges, then the ISO 9283 style poses (centre and
    the four corners at 80 % of the ranges) each visited ``iso_repeats`` times.
    """
    (a1, b1), (a2, b2) = spec.q1_range_deg, spec.q2_range_deg
    g1, g2 = np.meshgrid(np.linspace(a1, b1, spec.grid), np.linspace(a2, b2, spec.grid))
    train_q = np.column_stack([g1.ravel(), g2.ravel()])
    c = np.array([(a1 + b1) / 2, (a2 + b2) / 2])
    h = np.array([(b1 - a1) / 2, (b2 - a2) / 2])
    rand_q = c + 0.9 * h * rng.uniform(-1, 1, (spec.validation_random, 2))
    iso_q = c + 0.8 * h * np.array([[0, 0], [1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)
    val_q = np.vstack([rand_q, np.repeat(iso_q, spec.iso_repeats, axis=0)])
    val_id = VALIDATION_ID0 + np.concatenate([
        np.arange(len(rand_q)), len(rand_q) + np.repeat(np.arange(5), spec.iso_repeats)])
    return np.arange(len(train_q)), train_q, val_id, val_q


def _random_cov(rng: np.random.Generator, sigma: float) -> np.ndarray:
    q = Rotation.random(random_state=rng).as_matrix()
    return q @ np.diag((sigma * rng.uniform(0.6, 1.4, 3)) ** 2) @ q.T


def true_poses(params: Mapping[str, float], q_cmd: np.ndarray, joint_deg: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """True pyramid rotation and apex at ``q_cmd + N(0, joint_deg^2)``."""
    q_true = q_cmd + rng.normal(0.0, joint_deg, q_cmd.shape) if joint_deg > 0 else q_cmd
    return forward(params, q_true)


def measured_poses(params: Mapping[str, float], config: np.ndarray, q_cmd: np.ndarray,
                   noise: PlatformNoise, rng: np.random.Generator) -> PoseSet:
    """Noisy measured pyramid poses (with their covariances) at the commanded ``q_cmd``."""
    r, apex = true_poses(params, q_cmd, noise.joint_deg, rng)
    n = len(q_cmd)
    cov = np.zeros((n, 6, 6))
    for k in range(n):
        cov[k, :3, :3] = _random_cov(rng, noise.rotation_deg)
        cov[k, 3:, 3:] = _random_cov(rng, noise.apex_mm)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((n, 6)))
    r_meas = Rotation.from_rotvec(e[:, :3], degrees=True).as_matrix() @ r
    return PoseSet(np.asarray(config), np.asarray(q_cmd, float), r_meas, apex + e[:, 3:], cov)


@dataclass(frozen=True)
class PlatformCampaign:
    """Simulated identification and validation pose sets, with the spec that made them."""

    spec: PlatformSpec
    seed: int
    train: PoseSet
    validation: PoseSet


def simulate_campaign(spec: PlatformSpec | None = None, seed: int = 0) -> PlatformCampaign:
    """Run the design of ``spec`` (default: packaged file) on the true mechanism."""
    spec = load_spec() if spec is None else spec
    rng = np.random.default_rng(seed)
    tid, tq, vid, vq = design(spec, rng)
    train = measured_poses(spec.true, tid, tq, spec.noise, rng)
    validation = measured_poses(spec.true, vid, vq, spec.noise, rng)
    return PlatformCampaign(spec, seed, train, validation)


# ----------------------------------------------------------------------------- full scans

@dataclass(frozen=True)
class PyramidScans:
    """Reported flange poses and readings scanning the pyramid, one block per measurement.

    ``row_pose`` (m,) index of the pose measurement each scan row belongs to; ``position``
    (m, 3), ``theta_deg`` (m,), ``d`` (m,), ``face`` (m,) face names.
    """

    row_pose: np.ndarray
    position: np.ndarray
    theta_deg: np.ndarray
    d: np.ndarray
    face: np.ndarray


def face_targets(geometry: PyramidGeometry, per_face: int, rng: np.random.Generator,
                 margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces in the pyramid frame (apex at origin) and their face index.

    ``s e_(k-1) + t e_k`` between the edges bounding face ``k``, above 5 % of the height from
    the base and ``margin`` mm from both edges.
    """
    edges = geometry.edges
    pts, face = [], []
    for k in range(3):
        e1, e2 = edges[(k - 1) % 3], edges[k]
        reach = geometry.height / -min(e1[2], e2[2])
        got = 0
        while got < per_face:
            s, t = rng.uniform(0, reach, 2)
            p = s * e1 + t * e2
            dist = min(np.linalg.norm(p - (p @ e) * e) for e in (e1, e2))
            if -p[2] > 0.95 * geometry.height or dist < margin:
                continue
            pts.append(p)
            face.append(k)
            got += 1
    return np.array(pts), np.array(face)


def scan_pyramid(rotations: np.ndarray, apexes: np.ndarray, beam_t: np.ndarray,
                 beam_u: np.ndarray, geometry: PyramidGeometry, noise: NoiseModel,
                 per_face: int, rng: np.random.Generator) -> PyramidScans:
    """Scan each true pyramid pose with a 4-dof robot carrying the true beam ``(T, u')``.

    Face ``k`` is scanned with ``theta`` chosen so the beam's horizontal part points against the
    face's outward normal (seen from the front; a convex body cannot hide a front face point).
    For a target ``P`` and true reading ``d``: ``O = P - Rz(theta) (T + d u')``; the robot
    reports ``O`` and ``theta`` and the sensor ``d`` with the ``noise`` sigmas (seed Table 2).
    """
    blocks = []
    phi_u = np.degrees(np.arctan2(beam_u[1], beam_u[0]))
    for i, (rot, apex) in enumerate(zip(rotations, apexes, strict=True)):
        local, face = face_targets(geometry, per_face, rng)
        target = local @ rot.T + apex
        normal = geometry.normals[face] @ rot.T
        theta = np.degrees(np.arctan2(normal[:, 1], normal[:, 0])) + 180.0 - phi_u
        theta = (theta + 180.0) % 360.0 - 180.0
        d = rng.uniform(-3.0, 3.0, len(target))
        r = rotation_about_z(theta)
        origin = target - np.einsum("nij,nj->ni", r, beam_t[None] + d[:, None] * beam_u[None])
        blocks.append((np.full(len(target), i), origin, theta, d, face))
    row, origin, theta, d, face = (np.concatenate(x) for x in zip(*blocks, strict=True))
    m = len(d)
    origin = origin + rng.normal(size=(m, 3)) * [noise.robot_xy, noise.robot_xy, noise.robot_z]
    theta = theta + rng.normal(size=m) * noise.robot_theta_deg
    d = d + rng.normal(size=m) * noise.sensor
    return PyramidScans(row, origin, theta, d, np.array(geometry.face_names)[face])


def simulated_beam_calibration() -> BeamCalibration:
    """The beam of the default workcell as a Schoenflies calibration (plate datum delta = 0).

    Values are the true ones; the covariance is a realistic diagonal one (4 um on x_t, y_t,
    12 um on z_t - delta, 2-3e-4 on a, b, c, 2e-5 on the plate tilt).
    """
    beam = load_workcell().beam
    h = np.array([beam.x_t, beam.y_t, beam.z_t, *beam.u_prime, 0.0, 0.0])
    sig = np.array([0.004, 0.004, 0.012, 3e-4, 3e-4, 2e-4, 2e-5, 2e-5])
    return BeamCalibration(model="schoenflies", names=SCHOENFLIES_PARAMS, values=h,
                           covariance=np.diag(sig**2))


@dataclass(frozen=True)
class ScanSet:
    """Commanded configurations (``config``, ``q_deg`` per measurement) and their scans."""

    config: np.ndarray
    q_deg: np.ndarray
    scans: PyramidScans


@dataclass(frozen=True)
class ScanCampaign:
    """A simulated campaign measured by scanning: beam calibration, identification, validation."""

    spec: PlatformSpec
    seed: int
    calibration: BeamCalibration
    train: ScanSet
    validation: ScanSet


def simulate_scan_campaign(spec: PlatformSpec | None = None, seed: int = 0, per_face: int = 8,
                           noise: NoiseModel | None = None) -> ScanCampaign:
    """The design of ``spec`` measured by scanning the pyramid's faces (``per_face`` points each)
    with the workcell's true beam; the returned calibration is the one the scans are read with."""
    spec = load_spec() if spec is None else spec
    noise = noise or NoiseModel()
    rng = np.random.default_rng(seed)
    calib = simulated_beam_calibration()
    geometry = load_geometry()
    tid, tq, vid, vq = design(spec, rng)
    sets = []
    for cid, q in ((tid, tq), (vid, vq)):
        rot, apex = true_poses(spec.true, q, spec.noise.joint_deg, rng)
        scans = scan_pyramid(rot, apex, calib.values[0:3], calib.values[3:6], geometry, noise,
                             per_face, rng)
        sets.append(ScanSet(cid, q, scans))
    return ScanCampaign(spec, seed, calib, sets[0], sets[1])
