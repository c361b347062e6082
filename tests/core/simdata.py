"""Test-side simulator of calibration sessions with known truth (independent of drivers/sim)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib_core.io import dataset_from_frame
from calib_core.noise import NoiseModel

SEED_BEAM = {"x_t": -6.386, "y_t": 70.055, "z_t": -20.073, "alpha": -0.713e-3,
             "beta": 5.671e-3, "delta": 0.0}
SEED_DIRECTION = np.array([0.250, -0.181, 0.952])


@dataclass(frozen=True)
class Truth:
    t: np.ndarray
    u: np.ndarray  # unit direction
    gain: float
    alpha: float
    beta: float
    delta: float

    def h(self, model: str) -> dict[str, float]:
        up = self.gain * self.u
        out = {"x_t": self.t[0], "y_t": self.t[1], "a": up[0], "b": up[1], "c": up[2],
               "alpha": self.alpha, "beta": self.beta}
        if model == "schoenflies":
            out["z_t_minus_delta"] = self.t[2] - self.delta
        else:
            out["z_t"], out["delta"] = self.t[2], self.delta
        return out


def seed_truth(gain: float = 1.0, delta: float = 0.0, t: np.ndarray | None = None,
               u: np.ndarray | None = None) -> Truth:
    t = np.array([SEED_BEAM["x_t"], SEED_BEAM["y_t"], SEED_BEAM["z_t"] + delta]) if t is None \
        else np.asarray(t, float)
    u = SEED_DIRECTION if u is None else np.asarray(u, float)
    return Truth(t, u / np.linalg.norm(u), gain, SEED_BEAM["alpha"], SEED_BEAM["beta"], delta)


def seed_grid(heights=(15.0, 20.0, 25.0), nx: int = 4, ny: int = 3, half: float = 2.0,
              angles=(-6.0, -3.6, -1.2, 1.2, 3.6, 6.0), rot_height: float = 20.0) -> np.ndarray:
    """(n, 4) x, y, z, theta_deg: the seed's 42-pose pattern."""
    rows = [(x, y, z, 0.0) for z in heights for x in np.linspace(-half, half, nx)
            for y in np.linspace(-half, half, ny)]
    rows += [(0.0, 0.0, rot_height, a) for a in angles]
    return np.array(rows)


def simulate(truth: Truth, grid: np.ndarray, noise: NoiseModel, rng: np.random.Generator,
             quaternions: np.ndarray | None = None, outliers: dict[int, tuple[float, float]]
             | None = None, noise_scale: tuple[float, float] = (1.0, 1.0)) -> pd.DataFrame:
    """Rows of a calibration file. ``grid`` (n, 4); ``quaternions`` (n, 4) wxyz for 6-dof.

    The spot is the beam ray ``O + R T + s R u`` cut by the plate; the sensor reports ``s/gain``
    so that ``u' = gain u``. Noise is added to what the devices report (seed Table 2 defaults);
    ``noise_scale`` multiplies (camera, robot x-y, robot rotation) and (robot z, sensor) sigmas.
    """
    n = len(grid)
    pos = grid[:, 0:3]
    if quaternions is None:
        rot = Rotation.from_euler("z", grid[:, 3:4], degrees=True)
    else:
        rot = Rotation.from_quat(quaternions, scalar_first=True)
    r = rot.as_matrix()
    p0 = pos + r @ truth.t
    ru = r @ truth.u
    s = (truth.alpha * p0[:, 0] + truth.beta * p0[:, 1] + truth.delta - p0[:, 2]) / (
        ru[:, 2] - truth.alpha * ru[:, 0] - truth.beta * ru[:, 1])
    spot = p0 + s[:, None] * ru
    kl, ka = noise_scale
    rep_pos = pos + rng.normal(size=(n, 3)) * [kl * noise.robot_xy, kl * noise.robot_xy,
                                               ka * noise.robot_z]
    d = s / truth.gain + rng.normal(size=n) * ka * noise.sensor
    xp = spot[:, 0:2] + rng.normal(size=(n, 2)) * kl * noise.camera
    for row, (dx, dy) in (outliers or {}).items():
        xp[row] += (dx, dy)
    frame = {"x_o": rep_pos[:, 0], "y_o": rep_pos[:, 1], "z_o": rep_pos[:, 2], "d": d,
             "x_p": xp[:, 0], "y_p": xp[:, 1]}
    sig_rot = kl * noise.robot_theta_deg
    if quaternions is None:
        frame["theta_deg"] = grid[:, 3] + rng.normal(size=n) * sig_rot
    else:
        tilt = Rotation.from_rotvec(np.radians(rng.normal(size=(n, 3)) * sig_rot))
        q = (tilt * rot).as_quat(scalar_first=True)
        frame.update(qw=q[:, 0], qx=q[:, 1], qy=q[:, 2], qz=q[:, 3])
    return pd.DataFrame(frame)


def as_dataset(frame: pd.DataFrame, name: str = "sim"):
    return dataset_from_frame(frame.astype(str), name)


def tilted_grid(rng: np.random.Generator, n: int = 60, max_tilt_deg: float = 10.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """A 6-dof pose set: x-y spread, 3 heights, rotations about z and tilts about x and y."""
    grid = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n),
                            rng.choice([15.0, 20.0, 25.0], n), np.zeros(n)])
    eul = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-max_tilt_deg, max_tilt_deg, n),
                           rng.uniform(-max_tilt_deg, max_tilt_deg, n)])
    q = Rotation.from_euler("zyx", eul, degrees=True).as_quat(scalar_first=True)
    return grid, q
