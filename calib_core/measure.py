"""Measuring with a calibrated sensor: scan points (seed eq 16), planes (eq 17-20), gauges.

A scan point is ``P = O + R (T + d u')`` (eq 16). With a Schoenflies calibration ``T`` holds
``z_t - delta``, so every reconstructed ``z`` is the height above the calibration plate's datum
(``z_P - delta``) and plane offsets are relative to that datum too; a general (6-dof)
calibration gives absolute ``z`` in the robot frame.

Uncertainty has two parts that are propagated separately:

- scan noise (robot pose, sensor reading; seed Table 2), independent from point to point;
- the calibration covariance ``C_H``, common to every point: a fitted quantity ``q(P_1..P_n)``
  gets ``C_q,cal = (sum_i dq/dP_i dP_i/dH) C_H (...)^T``, not ``sum_i`` of per-point terms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from calib_core.errors import InputError
from calib_core.model import Poses, spot_jacobian, spot_positions
from calib_core.noise import NoiseModel
from calib_core.stats import axis_statistics

#: |n_z| of a fitted plane below which ``z = alpha x + beta y + offset`` is flagged as steep.
STEEP_NZ = 0.3
#: Assumed 1-sigma of a gauge block's height (mm): Johansson grade 0 at <= 10 mm is ~0.1 um.
GAUGE_SIGMA = 0.0001


class Calibration(Protocol):
    """What measuring needs of a calibration (``calib_core.calibrate.BeamCalibration``)."""

    model: str
    names: tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray


# ----------------------------------------------------------------------------- scan points

@dataclass(frozen=True)
class ScanPoints:
    """Reconstructed points with the two parts of their uncertainty.

    ``xyz`` (n, 3) mm; ``noise_cov`` (n, 3, 3) scan noise (independent per point);
    ``jac`` (n, 3, p) ``dP_i/dH`` over all calibration parameters; ``param_cov`` (p, p) ``C_H``.
    """

    xyz: np.ndarray
    noise_cov: np.ndarray
    jac: np.ndarray
    param_cov: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def cov(self) -> np.ndarray:
        """Total per-point covariance ``C_i = C_noise,i + J_i C_H J_i^T`` (n, 3, 3)."""
        return self.noise_cov + np.einsum("nij,jk,nlk->nil", self.jac, self.param_cov, self.jac)

    def subset(self, idx: np.ndarray) -> ScanPoints:
        return ScanPoints(self.xyz[idx], self.noise_cov[idx], self.jac[idx], self.param_cov)


def scan_noise_covariance(poses: Poses, d: np.ndarray, t: np.ndarray, u: np.ndarray,
                          noise: NoiseModel) -> np.ndarray:
    """Covariance (n, 3, 3) of eq-16 points from robot and sensor noise (seed Table 2).

    ``dP = dO + omega x R v + R u' dd`` with ``v = T + d u'``: robot x-y and z noise on ``O``,
    rotation noise ``omega`` about z (4-dof poses) or about each axis (6-dof), sensor noise on
    ``d``. For Schoenflies ``T_z`` is ``z_t - delta``; a rotation about z does not see it.
    """
    n = len(poses)
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = noise.robot_xy**2
    cov[:, 2, 2] = noise.robot_z**2
    rv = np.einsum("nij,nj->ni", poses.rotation, t[None, :] + d[:, None] * u[None, :])
    skew = np.zeros((n, 3, 3))  # omega x (R v) = -[R v]_x omega
    skew[:, 0, 1], skew[:, 0, 2] = rv[:, 2], -rv[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = -rv[:, 2], rv[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = rv[:, 1], -rv[:, 0]
    g = skew[:, :, 2:3] if poses.theta_deg is not None else skew
    cov += np.radians(noise.robot_theta_deg) ** 2 * g @ g.transpose(0, 2, 1)
    ru = np.einsum("nij,j->ni", poses.rotation, u)
    cov += noise.sensor**2 * ru[:, :, None] * ru[:, None, :]
    return cov


def reconstruct(poses: Poses, d: np.ndarray, calib: Calibration,
                noise: NoiseModel | None = None) -> ScanPoints:
    """Eq 16 for every row: ``P = O + R (T + d u')`` with its uncertainty parts.

    ``dP/dH = [R, d R, 0...]`` (:func:`calib_core.model.spot_jacobian`) over the first six
    calibration parameters ``(x_t, y_t, z_t | z_t - delta, a, b, c)``; zero for the plate ones.
    """
    noise = noise or NoiseModel()
    values = np.asarray(calib.values, dtype=float)
    cov_h = np.asarray(calib.covariance, dtype=float)
    d = np.asarray(d, dtype=float)
    if len(poses) == 0:
        raise InputError("no scan points")
    t, u = values[0:3], values[3:6]
    xyz = spot_positions(poses, d, t, u)
    jac = np.zeros((len(poses), 3, len(values)))
    jac[:, :, 0:6] = spot_jacobian(poses, d)
    return ScanPoints(xyz, scan_noise_covariance(poses, d, t, u, noise), jac, cov_h)


# ----------------------------------------------------------------------------- planes

@dataclass(frozen=True)
class PlaneFit:
    """A fitted plane ``z = alpha x + beta y + offset``, equivalently ``normal . P = distance``.

    ``normal`` is the unit normal with ``n_z >= 0``; ``covariance`` (3, 3) is that of
    ``(alpha, beta, offset)`` = ``cov_noise + cov_calibration``; ``rms`` is the RMS of the
    orthogonal point-to-plane distances (mm); ``chi2_reduced`` compares the residuals with the
    scan-noise model (the noise part is scaled by it when it exceeds 1).
    """

    method: str
    alpha: float
    beta: float
    offset: float
    normal: np.ndarray
    distance: float
    covariance: np.ndarray
    cov_noise: np.ndarray
    cov_calibration: np.ndarray
    normal_covariance: np.ndarray
    rms: float
    n_points: int
    chi2_reduced: float
    residuals: np.ndarray = field(repr=False)
    warnings: tuple[str, ...] = ()

    @property
    def sigma(self) -> dict[str, float]:
        s = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {"alpha": float(s[0]), "beta": float(s[1]), "offset": float(s[2])}

    def z_at(self, xy: np.ndarray) -> np.ndarray:
        """Height of the plane at ``xy`` (n, 2)."""
        return self.alpha * xy[:, 0] + self.beta * xy[:, 1] + self.offset

    def to_json_dict(self) -> dict[str, object]:
        return {
            "method": self.method, "alpha": self.alpha, "beta": self.beta,
            "offset": self.offset, "normal": [float(v) for v in self.normal],
            "distance": self.distance, "rms": self.rms, "n_points": self.n_points,
            "sigma": self.sigma,
            "normal_sigma_deg": float(np.degrees(np.sqrt(max(
                np.trace(self.normal_covariance), 0.0)))),
            "chi2_reduced": self.chi2_reduced, "warnings": list(self.warnings),
        }


def _check_points(xyz: np.ndarray, minimum: int = 3) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (n, 3) array, got shape {xyz.shape}")
    if len(xyz) < minimum:
        raise InputError(f"too few points for a plane: {len(xyz)}, at least {minimum} needed")
    if not np.all(np.isfinite(xyz)):
        raise InputError("points contain non-finite values")
    return xyz


def ls_plane(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Seed eq 19-20: ``p = (L^T L)^-1 L^T z`` with ``L_i = (x_i, y_i, 1)``, ``p = (alpha,
    beta, offset)``; returns ``p`` and ``dp/dP_i`` (n, 3, 3).

    From the normal equations ``F = sum_i L_i^T (z_i - L_i p) = 0``:
    ``dp/dP_i = (L^T L)^-1 [e_1 r_i - alpha L_i^T, e_2 r_i - beta L_i^T, L_i^T]``.
    """
    xyz = _check_points(xyz)
    lmat = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
    ltl = lmat.T @ lmat
    if np.linalg.cond(ltl) > 1e12:
        raise InputError("points are collinear in x-y: the plane z = alpha x + beta y + offset "
                         "is not determined")
    p = np.linalg.solve(ltl, lmat.T @ xyz[:, 2])
    r = xyz[:, 2] - lmat @ p
    blocks = np.zeros((len(xyz), 3, 3))
    blocks[:, :, 0] = -p[0] * lmat
    blocks[:, 0, 0] += r
    blocks[:, :, 1] = -p[1] * lmat
    blocks[:, 1, 1] += r
    blocks[:, :, 2] = lmat
    return p, np.linalg.solve(ltl, blocks.transpose(1, 0, 2).reshape(3, -1)).reshape(
        3, len(xyz), 3).transpose(1, 0, 2)


def orthogonal_plane(xyz: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Total least squares: ``n`` = singular vector of the centred points with the smallest
    singular value, ``h = n . centroid``; returns ``n`` (n_z >= 0, else largest component > 0),
    ``h``, ``dn/dP_i`` (n, 3, 3) and ``dh/dP_i`` (n, 3).

    With ``S = sum_i q_i q_i^T`` (``q_i = P_i - c``), ``S n = lambda_3 n`` and residuals
    ``r_i = n . q_i``: ``dn/dP_i = -(S - lambda_3 I)^+ (r_i I + q_i n^T)``,
    ``dh/dP_i = c^T dn/dP_i + n^T / N``.
    """
    xyz = _check_points(xyz)
    c = xyz.mean(axis=0)
    q = xyz - c
    _, sv, vt = np.linalg.svd(q, full_matrices=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise InputError("points are collinear: the plane is not determined")
    nrm = vt[2]
    k = 2 if abs(nrm[2]) > 1e-12 else int(np.argmax(np.abs(nrm)))
    if nrm[k] < 0:
        nrm = -nrm
    h = float(nrm @ c)
    # (S - l3 I)^+ in the basis of the right singular vectors
    pinv = vt[0:2].T @ np.diag(1.0 / (sv[0:2] ** 2 - sv[2] ** 2)) @ vt[0:2]
    r = q @ nrm
    inner = r[:, None, None] * np.eye(3)[None] + q[:, :, None] * nrm[None, None, :]
    dn = -np.einsum("ij,njk->nik", pinv, inner)
    dh = np.einsum("i,nik->nk", c, dn) + nrm[None, :] / len(xyz)
    return nrm, h, dn, dh


def _propagate(grad: np.ndarray, noise_cov: np.ndarray | None, jac: np.ndarray | None,
               param_cov: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``sum_i G_i C_i G_i^T`` and ``(sum_i G_i J_i) C_H (sum_i G_i J_i)^T`` for ``G`` (n, m, 3)."""
    m = grad.shape[1]
    c_noise = np.zeros((m, m)) if noise_cov is None else np.einsum(
        "nij,njk,nlk->il", grad, noise_cov, grad)
    if jac is None or param_cov is None:
        return c_noise, np.zeros((m, m))
    sens = np.einsum("nij,njk->ik", grad, jac)
    return c_noise, sens @ param_cov @ sens.T


def fit_plane(xyz: np.ndarray, method: str = "ls", noise_cov: np.ndarray | None = None,
              jac: np.ndarray | None = None, param_cov: np.ndarray | None = None) -> PlaneFit:
    """Fit a plane by the seed's least squares (``method='ls'``, eq 20: vertical residuals) or
    by total least squares (``'orthogonal'``: orthogonal residuals, right for steep planes).

    Covariance of ``(alpha, beta, offset)``: ``k sum_i G_i C_i G_i^T + (sum_i G_i J_i) C_H
    (sum_i G_i J_i)^T`` with ``G_i = dp/dP_i``, ``C_i`` = ``noise_cov`` (scan noise),
    ``J_i = dP_i/dH`` = ``jac``, ``C_H`` = ``param_cov``, and
    ``k = max(1, chi2_reduced)``. Without ``noise_cov`` the noise part is the residual scatter.
    For the orthogonal fit ``alpha = -n_x/n_z, beta = -n_y/n_z, offset = h/n_z``.
    """
    xyz = _check_points(xyz)
    n = len(xyz)
    warnings: list[str] = []
    if method == "ls":
        p, grad = ls_plane(xyz)
        nrm = np.array([-p[0], -p[1], 1.0]) / np.sqrt(1.0 + p[0] ** 2 + p[1] ** 2)
        h = float(p[2] * nrm[2])
        # n = (-a, -b, 1)/s : dn/dp for the normal covariance
        s = np.sqrt(1.0 + p[0] ** 2 + p[1] ** 2)
        dn_dp = np.zeros((3, 3))
        dn_dp[:, 0] = (np.array([-1.0, 0.0, 0.0]) - nrm * (p[0] / s)) / s
        dn_dp[:, 1] = (np.array([0.0, -1.0, 0.0]) - nrm * (p[1] / s)) / s
        grad_n = np.einsum("ij,njk->nik", dn_dp, grad)
        res_dir = np.array([-p[0], -p[1], 1.0])  # vertical residual z - L p
        resid_v = xyz @ res_dir - p[2]
        var_dir = res_dir
        resid = resid_v * nrm[2]  # orthogonal distance
        dof_resid = resid_v
        if abs(nrm[2]) < STEEP_NZ:
            warnings.append(f"steep plane (|n_z| = {abs(nrm[2]):.2f}): vertical least squares "
                            "is poorly suited; use the orthogonal fit")
    elif method == "orthogonal":
        nrm, h, dn, dh = orthogonal_plane(xyz)
        if abs(nrm[2]) < STEEP_NZ:
            warnings.append(f"steep plane (|n_z| = {abs(nrm[2]):.2f}): alpha, beta and offset "
                            "are ill-defined; use the normal and distance")
        nz = nrm[2] if abs(nrm[2]) > 1e-12 else 1e-12
        p = np.array([-nrm[0] / nz, -nrm[1] / nz, h / nz])
        dp_dn = np.array([[-1 / nz, 0, nrm[0] / nz**2],
                          [0, -1 / nz, nrm[1] / nz**2],
                          [0, 0, -h / nz**2]])
        grad = np.einsum("ij,njk->nik", dp_dn, dn)
        grad[:, 2, :] += dh / nz
        grad_n = dn
        resid = xyz @ nrm - h
        var_dir = nrm
        dof_resid = resid
    else:
        raise InputError(f"unknown plane fit {method!r}: expected 'ls' or 'orthogonal'")
    dof = n - 3
    if noise_cov is not None:
        var = np.einsum("i,nij,j->n", var_dir, noise_cov, var_dir)
        chi2 = float(np.sum(dof_resid**2 / np.maximum(var, 1e-30)) / dof) if dof > 0 else 1.0
        scale = max(1.0, chi2)
        if dof > 0 and chi2 > 1.0 + 4.0 * np.sqrt(2.0 / dof):
            warnings.append(f"residuals exceed the scan-noise model (chi2/dof = {chi2:.2f}); "
                            "noise sigma scaled up (surface roughness or a wrong calibration?)")
        c_eff = scale * noise_cov
    else:
        if dof <= 0:
            raise InputError("a plane from 3 points without a noise model has no uncertainty; "
                             "give more points")
        chi2 = float("nan")
        s2 = float(np.sum(dof_resid**2) / dof)
        axis = np.array([0.0, 0.0, 1.0]) if method == "ls" else nrm  # direction of the residual
        c_eff = np.broadcast_to(s2 * np.outer(axis, axis), (n, 3, 3)).copy()
    c_noise, c_cal = _propagate(grad, c_eff, jac, param_cov)
    cn_noise, cn_cal = _propagate(grad_n, c_eff, jac, param_cov)
    return PlaneFit(
        method=method, alpha=float(p[0]), beta=float(p[1]), offset=float(p[2]), normal=nrm,
        distance=float(h), covariance=c_noise + c_cal, cov_noise=c_noise, cov_calibration=c_cal,
        normal_covariance=cn_noise + cn_cal, rms=float(np.sqrt(np.mean(resid**2))),
        n_points=n, chi2_reduced=chi2, residuals=resid, warnings=tuple(warnings))


def fit_scan_plane(scan: ScanPoints, method: str = "ls") -> PlaneFit:
    """:func:`fit_plane` on reconstructed points with both uncertainty parts."""
    return fit_plane(scan.xyz, method, scan.noise_cov, scan.jac, scan.param_cov)


def compare_with_camera(scan_xyz: np.ndarray, spot_xy: np.ndarray, fit: PlaneFit
                        ) -> dict[str, object]:
    """Seed Tables 3-4: the plane from camera-derived points ``(x_p, y_p, z_scan)`` against the
    scanner's, and per-axis point errors ``x - x_p``, ``y - y_p``, ``z - z_cam(x_p, y_p)``
    (``z_cam`` the camera plane), each as mean-abs / RMS / max (mm)."""
    spot_xy = np.asarray(spot_xy, dtype=float)
    cam_pts = np.column_stack([spot_xy, scan_xyz[:, 2]])
    if fit.method == "ls":
        cam = ls_plane(cam_pts)[0]
    else:
        nrm, h, _, _ = orthogonal_plane(cam_pts)
        cam = np.array([-nrm[0], -nrm[1], h]) / (nrm[2] if abs(nrm[2]) > 1e-12 else 1e-12)
    z_cam = cam[0] * spot_xy[:, 0] + cam[1] * spot_xy[:, 1] + cam[2]
    errors = np.column_stack([scan_xyz[:, 0:2] - spot_xy, scan_xyz[:, 2] - z_cam])
    keys = ("alpha", "beta", "offset")
    mine = (fit.alpha, fit.beta, fit.offset)
    return {
        "camera_plane": {k: float(v) for k, v in zip(keys, cam, strict=True)},
        "difference": {k: float(m - v) for k, m, v in zip(keys, mine, cam, strict=True)},
        "point_errors": axis_statistics(errors),
    }


# ----------------------------------------------------------------------------- gauges

@dataclass(frozen=True)
class GaugeCheck:
    """Johansson gauge check: slope ``c`` of the gauge heights against the readings.

    ``c_sigma`` includes scan noise and the calibration covariance (through the plate-tilt
    correction); ``agreement_sigmas = |c - c_calibrated| / sigma(c - c_calibrated)`` with the
    correlation through the calibration taken into account.
    """

    c: float
    c_sigma: float
    intercept: float
    n_readings: int
    residual_rms: float
    chi2_reduced: float
    c_calibrated: float | None
    c_calibrated_sigma: float | None
    agreement_sigmas: float | None
    residuals: np.ndarray = field(repr=False)
    warnings: tuple[str, ...] = ()

    def to_json_dict(self) -> dict[str, object]:
        return {
            "c": self.c, "c_sigma": self.c_sigma, "intercept": self.intercept,
            "n_readings": self.n_readings, "residual_rms": self.residual_rms,
            "chi2_reduced": self.chi2_reduced, "c_calibrated": self.c_calibrated,
            "c_calibrated_sigma": self.c_calibrated_sigma,
            "agreement_sigmas": self.agreement_sigmas, "warnings": list(self.warnings),
        }


def _gauge_line(poses: Poses, d: np.ndarray, heights: np.ndarray, values: np.ndarray | None
                ) -> tuple[float, float, np.ndarray]:
    """LS line ``w = c d + b``, ``w = h - z_o + alpha x_P + beta y_P`` (no tilt term without
    a calibration); returns ``c``, ``b`` and residuals."""
    w = heights - poses.position[:, 2]
    if values is not None:
        xy = spot_positions(poses, d, values[0:3], values[3:6])[:, 0:2]
        w = w + values[6] * xy[:, 0] + values[7] * xy[:, 1]
    a = np.column_stack([d, np.ones_like(d)])
    (c, b), *_ = np.linalg.lstsq(a, w, rcond=None)
    return float(c), float(b), w - a @ np.array([c, b])


def gauge_check(poses: Poses, d: np.ndarray, heights: np.ndarray,
                calib: Calibration | None = None, noise: NoiseModel | None = None) -> GaugeCheck:
    """Estimate ``c`` from gauge blocks of known height ``h`` on the calibration plate.

    The spot on a gauge top satisfies ``h = z_o + R[2,:] T + (R[2,:] u') d - delta
    - alpha x_P - beta y_P``, so with a common flange tilt the least-squares slope of
    ``w = h - z_o + alpha x_P + beta y_P`` against ``d`` is the beam's vertical component
    ``R[2,:] u'`` (= ``c`` for a Schoenflies robot). Noise per reading
    ``sigma_w^2 = sigma_z^2 + (c sigma_d)^2 + sigma_gauge^2``;
    ``sigma_c^2 = k sigma_w^2 / sum (d - mean d)^2 + g^T C_H g`` with ``g = dc/dH`` (numeric)
    and ``k = max(1, chi2_reduced)``.
    """
    noise = noise or NoiseModel()
    d = np.asarray(d, dtype=float)
    heights = np.asarray(heights, dtype=float)
    n = len(d)
    if n < 3:
        raise InputError(f"too few gauge readings: {n}, at least 3 needed")
    if not np.all(np.isfinite(heights)):
        raise InputError("gauge heights must be finite")
    spread = float(np.sum((d - d.mean()) ** 2))
    if np.sqrt(spread / n) < 10 * noise.sensor or np.ptp(heights) == 0:
        raise InputError("gauge heights (and readings d) must differ: the slope is not defined")
    rz = poses.rotation[:, 2, :]
    if np.max(np.abs(rz - rz[0])) > 1e-6:
        raise InputError("gauge readings must share the flange tilt (rotations about z only)")
    warnings: list[str] = []
    values = None if calib is None else np.asarray(calib.values, dtype=float)
    c, b, resid = _gauge_line(poses, d, heights, values)
    var_w = noise.robot_z**2 + (c * noise.sensor) ** 2 + GAUGE_SIGMA**2
    dof = n - 2
    chi2 = float(np.sum(resid**2) / var_w / dof) if dof > 0 else 1.0
    if dof > 0 and chi2 > 1.0 + 4.0 * np.sqrt(2.0 / dof):
        warnings.append(f"gauge residuals exceed the noise model (chi2/dof = {chi2:.2f}); "
                        "sigma scaled up (gauge not under the spot, or dirt?)")
    var_c = max(1.0, chi2) * var_w / spread
    c_cal = c_cal_sigma = agreement = None
    if calib is None:
        warnings.append("no calibration given: plate tilt not corrected, no comparison")
    else:
        assert values is not None
        cov_h = np.asarray(calib.covariance, dtype=float)
        g = np.zeros(len(values))
        for k in range(len(values)):
            step = max(np.sqrt(max(cov_h[k, k], 0.0)), 1e-9)
            hi, lo = values.copy(), values.copy()
            hi[k] += step
            lo[k] -= step
            g[k] = (_gauge_line(poses, d, heights, hi)[0]
                    - _gauge_line(poses, d, heights, lo)[0]) / (2 * step)
        g_cal = np.zeros(len(values))
        g_cal[3:6] = rz[0]
        c_cal = float(rz[0] @ values[3:6])
        c_cal_sigma = float(np.sqrt(g_cal @ cov_h @ g_cal))
        var_diff = var_c + (g - g_cal) @ cov_h @ (g - g_cal)
        agreement = float(abs(c - c_cal) / np.sqrt(var_diff))
        var_c += g @ cov_h @ g
    return GaugeCheck(c=c, c_sigma=float(np.sqrt(var_c)), intercept=b, n_readings=n,
                      residual_rms=float(np.sqrt(np.mean(resid**2))), chi2_reduced=chi2,
                      c_calibrated=c_cal, c_calibrated_sigma=c_cal_sigma,
                      agreement_sigmas=agreement, residuals=resid, warnings=tuple(warnings))
