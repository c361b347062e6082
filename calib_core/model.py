"""Frames, rotations and the linear beam model (seed eq 3-13, corrected).

A pose ``i`` has the flange position ``O_i`` and orientation ``R_i``; the beam is the point
``T`` and the direction ``u' = (a, b, c)`` in the flange frame; the sensor reads ``d_i``.
The spot is

    P_i = O_i + R_i (T + d_i u')                                   (eq 4-5)

and lies on the plate ``z = alpha x + beta y + delta`` (eq 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

#: Unknowns of the 4-dof (Schoenflies, ``R = Rz(theta)``) model, seed eq 7.
SCHOENFLIES_PARAMS: tuple[str, ...] = (
    "x_t", "y_t", "z_t_minus_delta", "a", "b", "c", "alpha", "beta",
)
#: Unknowns of the general (6-dof flange) model: ``z_t`` and ``delta`` separate.
GENERAL_PARAMS: tuple[str, ...] = (
    "x_t", "y_t", "z_t", "a", "b", "c", "alpha", "beta", "delta",
)
MODELS: dict[str, tuple[str, ...]] = {"schoenflies": SCHOENFLIES_PARAMS, "general": GENERAL_PARAMS}


def params_of(model: str) -> tuple[str, ...]:
    """Parameter names of ``model`` ('schoenflies' or 'general'), in vector order."""
    return MODELS[model]


@dataclass(frozen=True)
class Poses:
    """Flange poses: ``position`` (n, 3) mm, ``rotation`` (n, 3, 3), optional ``theta_deg`` (n,)."""

    position: np.ndarray
    rotation: np.ndarray
    theta_deg: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def subset(self, idx: np.ndarray) -> Poses:
        """The poses at ``idx`` (index array or boolean mask)."""
        theta = None if self.theta_deg is None else self.theta_deg[idx]
        return Poses(self.position[idx], self.rotation[idx], theta)

    @property
    def is_rotation_about_z(self) -> bool:
        """True when every orientation is a rotation about z (third row of R equals (0, 0, 1))."""
        return bool(np.allclose(self.rotation[:, 2, :], [0.0, 0.0, 1.0], atol=1e-9))


def rotation_about_z(theta_deg: np.ndarray) -> np.ndarray:
    """``Rz(theta)`` for each angle (seed eq 9); returns (n, 3, 3)."""
    t = np.radians(np.asarray(theta_deg, dtype=float))
    c, s = np.cos(t), np.sin(t)
    r = np.zeros((*t.shape, 3, 3))
    r[..., 0, 0], r[..., 0, 1] = c, -s
    r[..., 1, 0], r[..., 1, 1] = s, c
    r[..., 2, 2] = 1.0
    return r


def rotation_from_quaternion(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) from unit quaternions ``(qw, qx, qy, qz)`` (scalar first)."""
    return Rotation.from_quat(np.asarray(q_wxyz, dtype=float), scalar_first=True).as_matrix()


def beam_regressor(poses: Poses, d: np.ndarray, spot_xy: np.ndarray, model: str) -> np.ndarray:
    """Stacked regressor ``R-bar`` of eq 12-13 (sign slip corrected), shape (n, 3, p).

    General form (9 columns ``x_t y_t z_t a b c alpha beta delta``), per pose::

        [ R[0,:]   d R[0,:]    0     0     0 ]
        [ R[1,:]   d R[1,:]    0     0     0 ]
        [ R[2,:]   d R[2,:]  -x_p  -y_p   -1 ]

    For ``R = Rz(theta)`` the z_t and delta columns coincide up to sign, so the Schoenflies model
    keeps the first 8 columns and the third reads ``z_t - delta`` (eq 12: first row
    ``[cos, -sin, 0, d cos, -d sin, 0, 0, 0]``).
    """
    r = poses.rotation
    n = len(poses)
    a = np.zeros((n, 3, 9))
    a[:, :, 0:3] = r
    a[:, :, 3:6] = d[:, None, None] * r
    a[:, 2, 6] = -spot_xy[:, 0]
    a[:, 2, 7] = -spot_xy[:, 1]
    a[:, 2, 8] = -1.0
    return a[:, :, : len(params_of(model))]


def beam_observation(poses: Poses, spot_xy: np.ndarray) -> np.ndarray:
    """Left-hand side ``S_i = (x_p - x_o, y_p - y_o, -z_o)`` of eq 7, shape (n, 3)."""
    s = np.empty((len(poses), 3))
    s[:, 0:2] = spot_xy - poses.position[:, 0:2]
    s[:, 2] = -poses.position[:, 2]
    return s


def beam_point_and_direction(h: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """``T`` (with ``z_t - delta`` in place of ``z_t`` for Schoenflies) and ``u'`` from ``H``."""
    h = np.asarray(h, dtype=float)
    return h[0:3], h[3:6]


def spot_positions(poses: Poses, d: np.ndarray, t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Eq 16 for N points at once: ``P = O + R (T + d u')``, shape (N, 3).

    With a Schoenflies calibration ``T`` holds ``z_t - delta`` as its z, so the returned z is
    ``z_P - delta``: the height above the calibration plate's datum.
    """
    v = t[None, :] + np.asarray(d, dtype=float)[:, None] * u[None, :]
    return poses.position + np.einsum("nij,nj->ni", poses.rotation, v)


def spot_jacobian(poses: Poses, d: np.ndarray) -> np.ndarray:
    """``dP/d(x_t, y_t, z_t, a, b, c)`` for eq 16, shape (N, 3, 6): ``[R, d R]``."""
    r = poses.rotation
    return np.concatenate([r, np.asarray(d, dtype=float)[:, None, None] * r], axis=2)
