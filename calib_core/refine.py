"""Maximum-likelihood refinement of ``H`` (errors in variables, effective variance).

Every source of noise (camera, robot, sensor) enters the eq-7 residual of pose ``i`` through its
first-order Jacobian; the residual covariance ``C_i`` (see :mod:`calib_core.noise`) whitens the
system, and ``H`` minimises ``sum_i r_i^T C_i^-1 r_i`` with ``r_i = R-bar_i H - S_i``. Because
``C_i`` depends on ``H`` (lever arms, plate tilt), the weights are updated until ``H`` settles.
Two variance factors scale the lateral and axial noise groups (Foerstner's variance-component
estimate) so that the covariance of ``H`` matches the scatter the data really show.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calib_core.model import Poses
from calib_core.noise import NoiseModel, residual_covariance_components

#: Floor added to each residual covariance (mm^2) so a noise-free source cannot make it singular.
COVARIANCE_FLOOR = 1e-14
#: Relative change of the variance factors at which the iteration stops (0.5 % in sigma).
FACTOR_RTOL = 1e-2
#: Variance factors are kept within this range of the noise model.
VARIANCE_FACTOR_LIMITS = (1e-4, 1e4)


@dataclass(frozen=True)
class WeightedFit:
    """``H``, its unscaled normal-matrix inverse, whitened residuals (n, 3) and variance factors."""

    h: np.ndarray
    normal_inverse: np.ndarray
    whitened: np.ndarray
    variance_factors: tuple[float, float]
    iterations: int

    @property
    def pose_chi2(self) -> np.ndarray:
        """Squared Mahalanobis norm of each pose's residual (3 degrees of freedom)."""
        return np.sum(self.whitened**2, axis=1)


def residual_covariance(poses: Poses, d: np.ndarray, spot_xy: np.ndarray, h: np.ndarray,
                        model: str, noise: NoiseModel,
                        factors: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """``C_i = k_lat C_lat,i + k_ax C_ax,i`` (n, 3, 3) from the two noise groups."""
    lateral, axial = residual_covariance_components(poses, d, spot_xy, h, model, noise)
    return factors[0] * lateral + factors[1] * axial + COVARIANCE_FLOOR * np.eye(3)


def whiten(cov: np.ndarray, regressor: np.ndarray, observation: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """``L_i^-1 R-bar_i`` and ``L_i^-1 S_i`` with ``C_i = L_i L_i^T`` (Cholesky), per pose."""
    chol = np.linalg.cholesky(cov)
    a_w = np.linalg.solve(chol, regressor)
    s_w = np.linalg.solve(chol, observation[:, :, None])[:, :, 0]
    return a_w, s_w


def weighted_least_squares(a_w: np.ndarray, s_w: np.ndarray, h0: np.ndarray,
                           loss: str = "linear", f_scale: float = 1.0) -> np.ndarray:
    """Minimise ``sum rho(|A_w H - S_w|^2)``.

    The residual is linear in ``H``: for the quadratic loss the minimiser is the least-squares
    solution (``numpy.linalg.lstsq``); a robust loss (e.g. 'soft_l1') is minimised by
    ``scipy.optimize.least_squares`` (iteratively reweighted trust region).
    """
    p = a_w.shape[2]
    a2 = a_w.reshape(-1, p)
    s2 = s_w.reshape(-1)
    if loss == "linear":
        return np.linalg.lstsq(a2, s2, rcond=None)[0]
    result = least_squares(lambda h: a2 @ h - s2, h0, jac=lambda h: a2, loss=loss,
                           f_scale=f_scale, method="trf", x_scale="jac", xtol=1e-12,
                           ftol=1e-12, gtol=1e-12)
    return result.x


def variance_factor_update(regressor: np.ndarray, observation: np.ndarray, h: np.ndarray,
                           components: tuple[np.ndarray, np.ndarray],
                           factors: tuple[float, float]) -> tuple[float, float]:
    """Foerstner's variance-component step ``k_g = r^T W V_g W r / tr(Q V_g)``.

    ``W = C^-1`` (block diagonal), ``N = A^T W A``, ``Q = W - W A N^-1 A^T W`` and ``V_g`` the
    group's unscaled covariance; ``tr(Q V_g)`` is the group's share of the redundancy.
    """
    cov = factors[0] * components[0] + factors[1] * components[1] + COVARIANCE_FLOOR * np.eye(3)
    w = np.linalg.inv(cov)
    r = np.einsum("nij,j->ni", regressor, h) - observation
    wr = np.einsum("nij,nj->ni", w, r)
    wa = w @ regressor  # (n, 3, p)
    n_inv = np.linalg.inv(np.einsum("nip,niq->pq", regressor, wa))
    new = []
    for k, v in zip(factors, components, strict=True):
        quad = np.einsum("ni,nij,nj->", wr, v, wr)
        redundancy = np.einsum("nij,nji->", w, v) - np.trace(
            n_inv @ np.einsum("nip,nij,njq->pq", wa, v, wa))
        value = k * quad / redundancy if redundancy > 1e-9 else k
        new.append(float(np.clip(value, *VARIANCE_FACTOR_LIMITS)))
    return new[0], new[1]


def maximum_likelihood_fit(poses: Poses, d: np.ndarray, spot_xy: np.ndarray,
                           regressor: np.ndarray, observation: np.ndarray, h0: np.ndarray,
                           model: str, noise: NoiseModel, *, loss: str = "linear",
                           f_scale: float = 1.0, estimate_variance: bool = True,
                           factors: tuple[float, float] = (1.0, 1.0),
                           max_iterations: int = 8) -> WeightedFit:
    """Iterate weights (and variance factors) and the weighted fit until ``H`` settles."""
    h = np.asarray(h0, dtype=float)
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007
        comps = residual_covariance_components(poses, d, spot_xy, h, model, noise)
        cov = factors[0] * comps[0] + factors[1] * comps[1] + COVARIANCE_FLOOR * np.eye(3)
        a_w, s_w = whiten(cov, regressor, observation)
        h_new = weighted_least_squares(a_w, s_w, h, loss=loss, f_scale=f_scale)
        new_factors = factors
        if estimate_variance:
            new_factors = variance_factor_update(regressor, observation, h_new, comps, factors)
        a2 = a_w.reshape(-1, a_w.shape[2])
        settled = (np.linalg.norm(a2 @ (h_new - h)) < 1e-3
                   and np.allclose(new_factors, factors, rtol=FACTOR_RTOL))
        h, factors = h_new, new_factors
        if settled:
            break
    comps = residual_covariance_components(poses, d, spot_xy, h, model, noise)
    cov = factors[0] * comps[0] + factors[1] * comps[1] + COVARIANCE_FLOOR * np.eye(3)
    a_w, s_w = whiten(cov, regressor, observation)
    a2 = a_w.reshape(-1, a_w.shape[2])
    whitened = np.einsum("nij,j->ni", a_w, h) - s_w
    return WeightedFit(h, np.linalg.pinv(a2.T @ a2), whitened, factors, iterations)
