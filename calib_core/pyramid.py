"""Pose of a three-face pyramid from scan points on its faces (seed, "Calibration of a robot").

Steps: (1) fit each face by total least squares; (2) intersect the three planes for the apex;
(3) edges as cross products of face normals, signed away from the apex; (4) orientation by an
orthogonal Procrustes fit of the nominal face normals onto the measured ones; (5) refine the
6-dof pose ``p_world = R p_pyr + apex`` by weighted least squares of the point-to-face distances
``r_i = (R n_k) . (P_i - apex)`` of the known pyramid (faces through its apex), covariance from
the Jacobian plus the calibration covariance common to all points.

Rotation uncertainty is a small rotation ``omega`` (rad) about the *world* axes:
``R = exp([omega]_x) R_hat``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib_core.errors import InputError
from calib_core.measure import ScanPoints, orthogonal_plane

#: Smallest angle (deg) between two face normals before the apex is called ill-conditioned.
PARALLEL_WARNING_DEG = 20.0
#: Procrustes misfit (deg, RMS over the normals) above which the faces disagree with the geometry.
SHAPE_WARNING_DEG = 1.0
MIN_POINTS_PER_FACE = 3


@dataclass(frozen=True)
class PyramidGeometry:
    """Nominal pyramid: face names, outward unit normals (3, 3) in its own frame (apex at the
    origin, every face through it) and height (mm)."""

    name: str
    face_names: tuple[str, str, str]
    normals: np.ndarray
    height: float

    @property
    def edges(self) -> np.ndarray:
        """Nominal unit edge directions (3, 3) AB, BC, CA, pointing from the apex to the base."""
        return _edges(self.normals, -np.sum(self.normals, axis=0))

    @classmethod
    def from_mapping(cls, data: Mapping[str, object], source: str = "pyramid geometry"
                     ) -> PyramidGeometry:
        """Build from the TOML layout of ``static_data/pyramid.toml``."""
        faces = data.get("faces")
        if not isinstance(faces, Sequence) or len(faces) != 3:
            raise InputError(f"{source}: expected exactly three [[faces]] tables")
        names, normals = [], []
        for k, face in enumerate(faces):
            if not isinstance(face, Mapping) or "name" not in face or "normal" not in face:
                raise InputError(f"{source}: face {k} needs 'name' and 'normal'")
            vec = np.asarray(face["normal"], dtype=float)
            if vec.shape != (3,) or not np.all(np.isfinite(vec)) or np.linalg.norm(vec) == 0:
                raise InputError(f"{source}: face {face['name']!r}: normal must be 3 finite "
                                 "numbers, not all zero")
            names.append(str(face["name"]).strip())
            normals.append(vec / np.linalg.norm(vec))
        if len({n.upper() for n in names}) != 3:
            raise InputError(f"{source}: face names must be distinct, got {names}")
        nmat = np.array(normals)
        if np.linalg.svd(nmat, compute_uv=False)[-1] < 1e-3:
            raise InputError(f"{source}: face normals are (nearly) coplanar; no apex")
        try:
            height = float(data.get("height", 0.0))  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise InputError(f"{source}: height must be a number") from None
        return cls(str(data.get("name", "pyramid")), (names[0], names[1], names[2]), nmat, height)


def load_geometry(path: str | Path | None = None) -> PyramidGeometry:
    """Read a pyramid TOML file (default: the packaged ``static_data/pyramid.toml``)."""
    from calib_core.io import load_toml

    return PyramidGeometry.from_mapping(*load_toml(path, "pyramid.toml", "pyramid file"))


@dataclass(frozen=True)
class PyramidPose:
    """Measured pose ``p_world = rotation @ p_pyr + apex``.

    ``apex_cov`` (3, 3) mm^2, ``rotation_cov`` (3, 3) rad^2 (small rotation about world axes),
    ``pose_cov`` (6, 6) over ``(omega, apex)``; ``edges`` (3, 3) unit vectors AB, BC, CA from the
    face-plane fits, away from the apex; ``apex_intersection`` the apex from the three fitted
    planes (no nominal geometry used); ``face_normals`` (3, 3) the fitted outward normals.
    """

    apex: np.ndarray
    rotation: np.ndarray
    quaternion: np.ndarray
    apex_cov: np.ndarray
    rotation_cov: np.ndarray
    pose_cov: np.ndarray
    edges: np.ndarray
    apex_intersection: np.ndarray
    face_normals: np.ndarray
    face_rms: tuple[float, float, float]
    residual_rms: float
    chi2_reduced: float
    n_points: int
    residuals: np.ndarray = field(repr=False)
    warnings: tuple[str, ...] = ()

    @property
    def apex_sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.apex_cov), 0.0, None))

    @property
    def rotation_sigma_deg(self) -> np.ndarray:
        """1-sigma of the small rotation about world x, y, z (deg)."""
        return np.degrees(np.sqrt(np.clip(np.diag(self.rotation_cov), 0.0, None)))

    @property
    def rotvec_deg(self) -> np.ndarray:
        """Rotation vector (axis times angle, deg) of ``rotation``."""
        return np.degrees(Rotation.from_matrix(self.rotation).as_rotvec())

    def to_json_dict(self) -> dict[str, object]:
        def vec(v: np.ndarray) -> list[float]:
            return [float(x) for x in v]

        return {
            "apex": vec(self.apex), "apex_sigma": vec(self.apex_sigma),
            "quaternion": vec(self.quaternion),
            "rotation_vector_deg": vec(self.rotvec_deg),
            "rotation_sigma_deg": vec(self.rotation_sigma_deg),
            "edges": [vec(e) for e in self.edges],
            "apex_intersection": vec(self.apex_intersection),
            "face_normals": [vec(n) for n in self.face_normals],
            "face_rms": list(self.face_rms), "residual_rms": self.residual_rms,
            "chi2_reduced": self.chi2_reduced, "n_points": self.n_points,
            "rotation_matrix": [vec(r) for r in self.rotation],
            "warnings": list(self.warnings),
        }


def _edges(normals: np.ndarray, inward: np.ndarray) -> np.ndarray:
    """Unit ``n_k x n_(k+1)`` for k = 0, 1, 2, each signed to have ``e . inward_k > 0``."""
    inward = np.broadcast_to(inward, (3, 3))
    out = np.empty((3, 3))
    for k in range(3):
        e = np.cross(normals[k], normals[(k + 1) % 3])
        e /= np.linalg.norm(e)
        out[k] = e if e @ inward[k] >= 0 else -e
    return out


def face_indices(labels: Sequence[object] | np.ndarray, geometry: PyramidGeometry
                 ) -> np.ndarray:
    """Map face labels (names, case-insensitive) to 0, 1, 2; unknown labels fail."""
    names = [n.upper() for n in geometry.face_names]
    out = np.empty(len(labels), dtype=int)
    for i, lab in enumerate(labels):
        key = str(lab).strip().upper()
        if key not in names:
            raise InputError(f"row {i}: face label {lab!r} is not one of "
                             f"{', '.join(geometry.face_names)}")
        out[i] = names.index(key)
    return out


def pyramid_pose(points: np.ndarray, face_labels: Sequence[object] | np.ndarray,
                 point_cov: np.ndarray | None = None, geometry: PyramidGeometry | None = None,
                 *, common_jac: np.ndarray | None = None,
                 common_cov: np.ndarray | None = None) -> PyramidPose:
    """Pyramid pose from points (n, 3) on its faces, labelled by face name.

    ``point_cov`` (n, 3, 3): independent per-point noise (None: weights from the residual
    scatter); ``common_jac`` (n, 3, p) and ``common_cov`` (p, p): a common error source such as
    the calibration, ``dP_i/dH`` and ``C_H``. Pose covariance
    ``C = k (J^T J)^-1 + (sum_i G_i J_H,i) C_H (...)^T`` with whitened residual Jacobian ``J``,
    ``G_i = -(J^T J)^-1 J_i^T m_i^T / sigma_i`` (``m_i = R n_k``) and ``k = max(1, chi2/dof)``.
    """
    geometry = geometry or load_geometry()
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise InputError("pyramid points must be a finite (n, 3) array")
    if len(face_labels) != len(pts):
        raise InputError(f"{len(face_labels)} face labels for {len(pts)} points")
    face = face_indices(face_labels, geometry)
    warnings: list[str] = []
    for k, name in enumerate(geometry.face_names):
        cnt = int(np.sum(face == k))
        if cnt < MIN_POINTS_PER_FACE:
            raise InputError(f"face {name}: {cnt} point(s), at least {MIN_POINTS_PER_FACE} "
                             "needed on each of the three faces")

    # (1) faces by total least squares, normals signed outward (other faces' points inside)
    normals, dists, face_rms = np.empty((3, 3)), np.empty(3), []
    for k in range(3):
        sel = pts[face == k]
        nrm, h, _, _ = orthogonal_plane(sel)
        others = pts[face != k].mean(axis=0)
        if nrm @ others - h > 0:
            nrm, h = -nrm, -h
        normals[k], dists[k] = nrm, h
        face_rms.append(float(np.sqrt(np.mean((sel @ nrm - h) ** 2))))
    # (2) apex from the three planes; conditioning of the face normals
    angles = [np.degrees(np.arccos(np.clip(abs(normals[j] @ normals[k]), 0, 1)))
              for j, k in ((0, 1), (1, 2), (2, 0))]
    if min(angles) < PARALLEL_WARNING_DEG:
        warnings.append(f"face normals nearly parallel (smallest angle {min(angles):.1f} deg): "
                        "apex and rotation are ill-conditioned")
    if np.linalg.svd(normals, compute_uv=False)[-1] < 1e-6:
        raise InputError("the three fitted faces do not meet in a point (normals coplanar)")
    apex0 = np.linalg.solve(normals, dists)
    # (3) edges away from the apex
    inward = np.array([pts[(face == k) | (face == (k + 1) % 3)].mean(axis=0) - apex0
                       for k in range(3)])
    edges = _edges(normals, inward)
    # (4) orientation: Procrustes of nominal normals onto the measured ones
    rot0, rssd = Rotation.align_vectors(normals, geometry.normals)
    misfit = np.degrees(rssd / np.sqrt(3.0))
    if misfit > SHAPE_WARNING_DEG:
        warnings.append(f"measured face angles differ from the nominal geometry by "
                        f"{misfit:.2f} deg RMS: wrong face labels or a different pyramid?")

    # (5) direct least squares of the known pyramid against the raw points
    nom = geometry.normals[face]  # (n, 3)

    def world_normals(x: np.ndarray) -> np.ndarray:
        rot = (Rotation.from_rotvec(x[0:3]) * rot0).as_matrix()
        return nom @ rot.T

    m0 = world_normals(np.zeros(6))
    if point_cov is not None:
        sig = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", m0, point_cov, m0), 1e-18))
    else:
        sig = np.ones(len(pts))

    def resid(x: np.ndarray) -> np.ndarray:
        return np.einsum("ni,ni->n", world_normals(x), pts - x[3:6]) / sig

    sol = least_squares(resid, np.concatenate([np.zeros(3), apex0]), x_scale=[1e-3] * 3 + [1.0] * 3,
                        xtol=1e-14, ftol=1e-14, gtol=1e-14)
    rot = (Rotation.from_rotvec(sol.x[0:3]) * rot0)
    apex = sol.x[3:6]
    m = nom @ rot.as_matrix().T
    q = pts - apex
    r = np.einsum("ni,ni->n", m, q)
    # analytic Jacobian at the solution, omega about world axes: dr/domega = m x q, dr/da = -m
    jac = np.concatenate([np.cross(m, q), -m], axis=1) / sig[:, None]
    dof = len(pts) - 6
    if dof <= 0:
        raise InputError(f"{len(pts)} points cannot give a pose with uncertainty; at least 7 "
                         "needed (3 per face recommended)")
    chi2 = float(np.sum((r / sig) ** 2) / dof)
    if point_cov is None:
        scale = chi2
    else:
        scale = max(1.0, chi2)
        if chi2 > 1.0 + 4.0 * np.sqrt(2.0 / dof):
            warnings.append(f"residuals exceed the point-noise model (chi2/dof = {chi2:.2f}); "
                            "noise sigma scaled up")
    ninv = np.linalg.inv(jac.T @ jac)
    cov = scale * ninv
    if common_jac is not None and common_cov is not None:
        grad = -np.einsum("ij,nj,nk->nik", ninv, jac, m / sig[:, None])  # (n, 6, 3) d x/d P_i
        sens = np.einsum("nij,njk->ik", grad, common_jac)
        cov = cov + sens @ common_cov @ sens.T
    quat = rot.as_quat(scalar_first=True)
    if quat[0] < 0:
        quat = -quat
    return PyramidPose(
        apex=apex, rotation=rot.as_matrix(), quaternion=quat, apex_cov=cov[3:6, 3:6],
        rotation_cov=cov[0:3, 0:3], pose_cov=cov, edges=edges, apex_intersection=apex0,
        face_normals=normals, face_rms=(face_rms[0], face_rms[1], face_rms[2]),
        residual_rms=float(np.sqrt(np.mean(r**2))), chi2_reduced=chi2, n_points=len(pts),
        residuals=r, warnings=tuple(warnings))


def measure_pyramid(scan: ScanPoints, face_labels: Sequence[object] | np.ndarray,
                    geometry: PyramidGeometry | None = None) -> PyramidPose:
    """:func:`pyramid_pose` on reconstructed scan points with scan noise and calibration
    covariance propagated."""
    return pyramid_pose(scan.xyz, face_labels, scan.noise_cov, geometry,
                        common_jac=scan.jac, common_cov=scan.param_cov)
