"""Measurement noise model (seed Table 2) and its propagation to the eq-7 residuals."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

import numpy as np

from calib_core.errors import InputError
from calib_core.model import Poses


@dataclass(frozen=True)
class NoiseModel:
    """1-sigma of each measurement source, mm and degrees (defaults: seed Table 2).

    ``camera``: spot x_p, y_p; ``robot_xy``: flange x_o, y_o; ``robot_z``: flange z_o;
    ``robot_theta_deg``: flange orientation (about z, or about each axis for a 6-dof flange);
    ``sensor``: reading d.
    """

    camera: float = 0.0031
    robot_xy: float = 0.0025
    robot_z: float = 0.005
    robot_theta_deg: float = 0.01
    sensor: float = 0.002

    @classmethod
    def from_mapping(cls, data: Mapping[str, object], source: str = "noise model") -> NoiseModel:
        """Build from a mapping (a TOML document, or its ``[noise]`` table); unknown keys fail."""
        table = data.get("noise", data)
        if not isinstance(table, Mapping):
            raise InputError(f"{source}: [noise] must be a table")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            raise InputError(f"{source}: unknown noise key(s) {', '.join(unknown)}; "
                             f"expected {', '.join(sorted(known))}")
        values: dict[str, float] = {}
        for key, value in table.items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InputError(f"{source}: noise '{key}' must be a number, got {value!r}")
            if not np.isfinite(value) or value < 0:
                raise InputError(f"{source}: noise '{key}' must be finite and >= 0, got {value}")
            values[key] = float(value)
        return cls(**values)

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def residual_covariance_components(
    poses: Poses, d: np.ndarray, spot_xy: np.ndarray, h: np.ndarray, model: str,
    noise: NoiseModel,
) -> tuple[np.ndarray, np.ndarray]:
    """First-order covariance of the eq-7 residuals ``r_i = P_i - (x_p, y_p, plane)``, (n, 3, 3).

    ``r = O + R (T + d u') - (x_p, y_p, alpha x_p + beta y_p + delta)``, so with ``v = T + d u'``

        dr/dO = I,  dr/d(omega) = -[R v]_x,  dr/dd = R u',
        dr/dx_p = (-1, 0, -alpha),  dr/dy_p = (0, -1, -beta)

    and ``C_i = J Sigma J^T``. Returned as two groups that a variance-component estimate can scale
    apart: the lateral sources (camera, robot x-y, robot rotation) and the axial ones (robot z,
    sensor).
    """
    n = len(poses)
    t, u = h[0:3].copy(), h[3:6]
    if model == "schoenflies":
        t[2] = 0.0  # z_t is not known; a rotation about z does not see it
    alpha, beta = h[6], h[7]
    rv = np.einsum("nij,nj->ni", poses.rotation, t[None, :] + d[:, None] * u[None, :])
    ru = np.einsum("nij,j->ni", poses.rotation, u)

    lateral = np.zeros((n, 3, 3))
    lateral[:, 0, 0] = lateral[:, 1, 1] = noise.robot_xy**2
    j_cam = np.zeros((n, 3, 2))
    j_cam[:, 0, 0] = j_cam[:, 1, 1] = -1.0
    j_cam[:, 2, 0], j_cam[:, 2, 1] = -alpha, -beta
    lateral += noise.camera**2 * j_cam @ j_cam.transpose(0, 2, 1)
    s_rot = np.radians(noise.robot_theta_deg)
    skew = np.zeros((n, 3, 3))  # -[Rv]_x : the change of R v for a small rotation omega
    skew[:, 0, 1], skew[:, 0, 2] = rv[:, 2], -rv[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = -rv[:, 2], rv[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = rv[:, 1], -rv[:, 0]
    g = skew[:, :, 2:3] if poses.theta_deg is not None else skew  # 4-dof: about z only
    lateral += s_rot**2 * g @ g.transpose(0, 2, 1)

    axial = noise.sensor**2 * ru[:, :, None] * ru[:, None, :]
    axial[:, 2, 2] += noise.robot_z**2
    return lateral, axial
