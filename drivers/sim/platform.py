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

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calib_core.errors import InputError
from calib_core.platform import PoseSet, forward, params_from_mapping

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
    try:
        if path is None:
            text = resources.files("static_data").joinpath("platform.toml").read_text("utf-8")
            source = "static_data/platform.toml"
        else:
            text, source = Path(path).read_text("utf-8"), str(path)
        data = tomllib.loads(text)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({exc})") from None
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
