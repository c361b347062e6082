"""The calibration pipeline: linear solution, observability, robust ML fit, covariance, statistics.

``solve`` turns a :class:`~calib_core.io.Dataset` into a :class:`BeamCalibration` whose
``to_json_dict`` is the ``lasercal solve --json`` object and the calibration file read back by
``from_json_dict``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.special import fdtri

from calib_core.errors import DesignError, InputError
from calib_core.io import Dataset
from calib_core.linear import linear_solution
from calib_core.model import (
    Poses,
    beam_observation,
    beam_regressor,
    params_of,
    spot_jacobian,
    spot_positions,
)
from calib_core.noise import NoiseModel
from calib_core.observability import CONDITION_WARNING, analyse_observability
from calib_core.refine import (
    VARIANCE_FACTOR_LIMITS,
    maximum_likelihood_fit,
    residual_covariance,
    whiten,
)
from calib_core.stats import axis_statistics, holdout_split

#: |rho| above which a parameter correlation is flagged.
CORRELATION_FLAG = 0.8
#: Family-wise false-alarm probability of the outlier test over all poses of a data set.
OUTLIER_FALSE_ALARM = 0.01
#: Huber-like soft-L1 threshold of the robust pre-fit, in robust standard deviations.
ROBUST_F_SCALE = 2.0
#: Tilt (rad) below which a 6-dof orientation counts as a rotation about z (~0.06 deg).
TILT_TOLERANCE = 1e-3
#: A warning is given when more than this fraction of the poses are excluded as outliers.
OUTLIER_FRACTION_WARNING = 0.2


@dataclass(frozen=True)
class BeamCalibration:
    """Identified beam ``H`` with covariance, quality figures and residual statistics."""

    model: str
    names: tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray
    n_points: int = 0
    n_used: int = 0
    outliers: tuple[int, ...] = ()
    residuals: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    condition_number: float = float("nan")
    singular_values: tuple[float, ...] = ()
    warnings: tuple[str, ...] = ()
    variance_factors: tuple[float, float] = (1.0, 1.0)
    chi2_reduced: float = float("nan")
    noise: NoiseModel = field(default_factory=NoiseModel)
    holdout: Mapping[str, object] | None = None
    rows_used: tuple[int, ...] = ()

    def point(self, name: str) -> float:
        """The value of parameter ``name``."""
        return float(self.values[self.names.index(name)])

    @property
    def sigma(self) -> np.ndarray:
        """1-sigma of each parameter."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def beam_point(self) -> np.ndarray:
        """``T`` (z is ``z_t - delta`` for a Schoenflies calibration)."""
        return self.values[0:3].copy()

    @property
    def beam_vector(self) -> np.ndarray:
        """``u' = (a, b, c)``: the beam direction times the sensor gain."""
        return self.values[3:6].copy()

    @property
    def gain(self) -> float:
        """``|u'|``: the sensor's scale factor (1 for a perfectly scaled sensor)."""
        return float(np.linalg.norm(self.beam_vector))

    @property
    def gain_sigma(self) -> float:
        """``sigma_|u'|^2 = g^T C_u g`` with ``g = u'/|u'|``."""
        g = self.direction
        return float(np.sqrt(max(g @ self.covariance[3:6, 3:6] @ g, 0.0)))

    @property
    def direction(self) -> np.ndarray:
        """Unit beam direction ``u = u'/|u'|``."""
        return self.beam_vector / self.gain

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix ``rho_jk = C_jk / (sigma_j sigma_k)``."""
        s = np.where(self.sigma > 0, self.sigma, 1.0)
        return self.covariance / np.outer(s, s)

    def strong_correlations(self, threshold: float = CORRELATION_FLAG
                            ) -> list[tuple[str, str, float]]:
        """Parameter pairs with ``|rho| > threshold``."""
        rho = self.correlation
        p = len(self.names)
        return [(self.names[j], self.names[k], float(rho[j, k]))
                for j in range(p) for k in range(j + 1, p) if abs(rho[j, k]) > threshold]

    def reconstruct(self, poses: Poses, d: np.ndarray) -> np.ndarray:
        """Eq 16 for N points: ``P = O + R (T + d u')`` (N, 3)."""
        return spot_positions(poses, d, self.beam_point, self.beam_vector)

    def point_covariance(self, poses: Poses, d: np.ndarray) -> np.ndarray:
        """Covariance (N, 3, 3) of eq-16 points from the covariance of ``H``: ``J C_H J^T``."""
        jac = spot_jacobian(poses, d)
        return (jac @ self.covariance[0:6, 0:6]) @ jac.transpose(0, 2, 1)

    def to_json_dict(self) -> dict[str, object]:
        """The ``lasercal solve --json`` object (also the calibration file)."""
        sig = self.sigma
        out: dict[str, object] = {
            "model": self.model,
            "n_points": self.n_points,
            "n_used": self.n_used,
            "params": {n: float(v) for n, v in zip(self.names, self.values, strict=True)},
            "sigma": {n: float(s) for n, s in zip(self.names, sig, strict=True)},
            "gain": self.gain,
            "gain_sigma": self.gain_sigma,
            "direction": [float(v) for v in self.direction],
            "residuals": {k: dict(v) for k, v in self.residuals.items()},
            "condition_number": self.condition_number,
            "outliers": [int(r) for r in self.outliers],
            "warnings": list(self.warnings),
            "singular_values": [float(v) for v in self.singular_values],
            "correlations_flagged": [
                {"params": [a, b], "rho": r} for a, b, r in self.strong_correlations()],
            "variance_factors": {"lateral": self.variance_factors[0],
                                 "axial": self.variance_factors[1]},
            "chi2_reduced": self.chi2_reduced,
            "noise": self.noise.as_dict(),
            "covariance": {"names": list(self.names),
                           "matrix": [[float(v) for v in row] for row in self.covariance]},
        }
        if self.holdout is not None:
            out["holdout"] = dict(self.holdout)
        return out

    @classmethod
    def from_json_dict(cls, data: Mapping[str, object], source: str = "calibration"
                       ) -> BeamCalibration:
        """Read a calibration written by :meth:`to_json_dict`; errors name the missing key."""
        try:
            model = str(data["model"])
            names = params_of(model)
            params = data["params"]
            values = np.array([float(params[n]) for n in names])  # type: ignore[index]
            cov_block = data.get("covariance")
            if isinstance(cov_block, Mapping) and list(cov_block.get("names", [])) == list(names):
                covariance = np.array(cov_block["matrix"], dtype=float)
            else:
                sig = data["sigma"]
                covariance = np.diag([float(sig[n]) ** 2 for n in names])  # type: ignore[index]
        except KeyError as exc:
            raise InputError(f"{source}: missing key {exc} in the calibration") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"{source}: malformed calibration ({exc})") from None
        if covariance.shape != (len(names), len(names)) or not np.all(np.isfinite(covariance)):
            raise InputError(f"{source}: covariance must be a finite {len(names)}x{len(names)} "
                             "matrix")
        if not np.all(np.isfinite(values)) or np.linalg.norm(values[3:6]) == 0:
            raise InputError(f"{source}: parameters must be finite with a non-zero (a, b, c)")
        return cls(model=model, names=names, values=values, covariance=covariance,
                   n_points=int(data.get("n_points", 0)), n_used=int(data.get("n_used", 0)))


def choose_model(dataset: Dataset, model: str) -> str:
    """'auto' -> 'general' for quaternion files, 'schoenflies' for theta files; check the rest."""
    if model == "auto":
        return "general" if dataset.orientation == "quaternion" else "schoenflies"
    if model not in ("schoenflies", "general"):
        raise InputError(f"unknown model {model!r}: use auto, schoenflies or general")
    if model == "schoenflies" and not dataset.poses.is_rotation_about_z:
        tilted = np.flatnonzero(~np.all(np.isclose(dataset.poses.rotation[:, 2, :],
                                                   [0.0, 0.0, 1.0], atol=TILT_TOLERANCE),
                                        axis=1))
        if tilted.size:
            raise InputError(f"{dataset.source}: row {int(dataset.rows[tilted[0]])}: orientation "
                             "is not a rotation about z; use --model general")
    return model


def beam_residuals(poses: Poses, d: np.ndarray, spot_xy: np.ndarray, h: np.ndarray,
                   model: str) -> np.ndarray:
    """Table-1 errors (n, 3): x, y = eq-16 spot minus camera; z = eq-16 spot minus the plane."""
    return np.einsum("nij,j->ni", beam_regressor(poses, d, spot_xy, model), h) - \
        beam_observation(poses, spot_xy)


def outlier_threshold(n: int) -> float:
    """Limit on a pose's chi-square (3 dof) scaled by the robust variance factors.

    The scale is a MAD estimate, so the test is ``F(3, nu)`` with ``nu ~ 0.37 x 3n`` (the MAD's
    efficiency), at a family-wise false-alarm rate of 1 % over ``n`` poses:
    ``3 F^-1(1 - 0.01/n; 3, 1.11 n)``.
    """
    return float(3.0 * fdtri(3, 0.37 * 3 * n, 1.0 - OUTLIER_FALSE_ALARM / n))


def robust_variance_factors(data: Dataset, h: np.ndarray, model: str, noise: NoiseModel,
                            inliers: np.ndarray) -> tuple[float, float]:
    """Robust lateral/axial variance factors: ``k = (1.4826 median|r_j / sigma_j|)^2``.

    ``r`` are the eq-7 residuals of the ``inliers`` and ``sigma_j`` their model standard
    deviations; x and y rows give the lateral factor, z rows the axial one.
    """
    assert data.spot_xy is not None
    r = beam_residuals(data.poses, data.d, data.spot_xy, h, model)[inliers]
    cov = residual_covariance(data.poses.subset(inliers), data.d[inliers],
                              data.spot_xy[inliers], h, model, noise)
    e = np.abs(r) / np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    lateral = (1.4826 * np.median(e[:, 0:2])) ** 2
    axial = (1.4826 * np.median(e[:, 2])) ** 2
    return (float(np.clip(lateral, *VARIANCE_FACTOR_LIMITS)),
            float(np.clip(axial, *VARIANCE_FACTOR_LIMITS)))


def _fit(data: Dataset, model: str, noise: NoiseModel, robust: bool
         ) -> tuple[np.ndarray, object, list[int], list[str], object]:
    """Observability check, robust outlier screening and the final ML fit on one data set."""
    names = params_of(model)
    poses, d, spot = data.poses, data.d, data.spot_xy
    assert spot is not None
    reg = beam_regressor(poses, d, spot, model)
    obs = beam_observation(poses, spot)
    h_lin = linear_solution(reg, obs)
    a_w, _ = whiten(residual_covariance(poses, d, spot, h_lin, model, noise), reg, obs)
    design = analyse_observability(a_w.reshape(-1, len(names)), names)
    if design.unidentifiable:
        raise DesignError(f"{data.source}: {design.message()}")

    warnings: list[str] = []
    inliers = np.ones(len(data), dtype=bool)
    h0, factors = h_lin, (1.0, 1.0)
    if robust:
        n = len(data)
        threshold = outlier_threshold(n)
        for _ in range(5):
            idx = np.flatnonzero(inliers)
            sub = poses.subset(idx)
            factors = robust_variance_factors(data, h0, model, noise, inliers)
            pre = maximum_likelihood_fit(sub, d[idx], spot[idx], reg[idx], obs[idx], h0,
                                         model, noise, loss="soft_l1", f_scale=ROBUST_F_SCALE,
                                         estimate_variance=False, factors=factors,
                                         max_iterations=1)
            h0 = pre.h
            factors = robust_variance_factors(data, h0, model, noise, inliers)
            a_all, s_all = whiten(residual_covariance(poses, d, spot, h0, model, noise, factors),
                                  reg, obs)
            chi2 = np.sum((np.einsum("nij,j->ni", a_all, h0) - s_all) ** 2, axis=1)
            new_inliers = chi2 <= threshold
            if np.array_equal(new_inliers, inliers):
                break
            inliers = new_inliers
        if (~inliers).sum() > OUTLIER_FRACTION_WARNING * n:
            warnings.append(f"{int((~inliers).sum())} of {n} poses rejected as outliers: check "
                            "the noise model and the camera/sensor")
        idx = np.flatnonzero(inliers)
        if len(idx) < len(data):
            sub_design = analyse_observability(
                whiten(residual_covariance(poses.subset(idx), d[idx], spot[idx], h0, model,
                                           noise), reg[idx], obs[idx])[0]
                .reshape(-1, len(names)), names)
            if sub_design.unidentifiable:
                raise DesignError(f"{data.source}: after excluding outlier rows "
                                  f"{', '.join(str(int(r)) for r in data.rows[~inliers])}: "
                                  f"{sub_design.message()}")
    idx = np.flatnonzero(inliers)
    fit = maximum_likelihood_fit(poses.subset(idx), d[idx], spot[idx], reg[idx], obs[idx], h0,
                                 model, noise, factors=factors)
    outlier_rows = [int(r) for r in data.rows[~inliers]]
    return idx, fit, outlier_rows, warnings, design


def solve(dataset: Dataset, model: str = "auto", noise: NoiseModel | None = None,
          robust: bool = True, holdout: float | None = None, seed: int = 0
          ) -> BeamCalibration:
    """Identify ``H`` from a calibration data set (seed eq 7-14, then ML refinement).

    Steps: linear solution (eq 14) -> observability (refuse a rank-deficient design) -> robust
    screening of gross outliers (soft-L1 fit, per-pose chi-square test with a family-wise false
    alarm of 1 %) -> ML fit with variance-component estimation on the inliers -> covariance
    ``(A_w^T A_w)^-1`` with the estimated variance factors, so the sigmas follow the scatter the
    data show -> Table-1 residual statistics (and on the hold-out rows if requested).
    """
    noise = noise or NoiseModel()
    if dataset.spot_xy is None:
        raise InputError(f"{dataset.source}: calibration needs the camera columns x_p, y_p")
    model = choose_model(dataset, model)
    names = params_of(model)
    min_rows = int(np.ceil((len(names) + 6) / 3))
    fit_set, hold_set = dataset, None
    if holdout is not None:
        if not 0.0 < holdout < 1.0:
            raise InputError(f"--holdout must be between 0 and 1 (exclusive), got {holdout}")
        fit_idx, hold_idx = holdout_split(len(dataset), holdout, seed)
        if len(hold_idx) == 0:
            raise InputError(f"{dataset.source}: --holdout {holdout} leaves no row to hold out "
                             f"of {len(dataset)}")
        fit_set, hold_set = dataset.subset(fit_idx), dataset.subset(hold_idx)
    if len(fit_set) < min_rows:
        raise InputError(f"{dataset.source}: too few rows: {len(fit_set)} pose(s) to fit, at "
                         f"least {min_rows} needed for the {model} model")

    idx, fit, outlier_rows, warnings, design = _fit(fit_set, model, noise, robust)
    used = fit_set.subset(idx)
    assert used.spot_xy is not None
    dof = 3 * len(idx) - len(names)
    chi2_red = float(np.sum(fit.whitened**2) / dof) if dof > 0 else float("nan")
    covariance = fit.normal_inverse
    errors = beam_residuals(used.poses, used.d, used.spot_xy, fit.h, model)

    if design.condition_number > CONDITION_WARNING:
        warnings.append(f"poorly conditioned design (condition number "
                        f"{design.condition_number:.3g}): add heights, x-y spread or rotations")
    result = BeamCalibration(
        model=model, names=names, values=fit.h, covariance=covariance,
        n_points=len(dataset), n_used=len(idx), outliers=tuple(outlier_rows),
        residuals=axis_statistics(errors), condition_number=design.condition_number,
        singular_values=tuple(float(s) for s in design.singular_values),
        warnings=tuple(warnings), variance_factors=fit.variance_factors,
        chi2_reduced=chi2_red, noise=noise, rows_used=tuple(int(r) for r in used.rows),
    )
    for a, b, rho in result.strong_correlations():
        warnings.append(f"strong correlation between {a} and {b} (rho = {rho:+.3f})")
    gain_dev = abs(result.gain - 1.0)
    if gain_dev > 3 * result.gain_sigma and gain_dev > 1e-3:
        warnings.append(f"|u'| = {result.gain:.5f} +- {result.gain_sigma:.5f} differs from 1: "
                        "the sensor (or robot z) scale is off by that factor")
    if outlier_rows:
        warnings.append(f"excluded outlier row(s): {', '.join(map(str, outlier_rows))}")
    holdout_block = None
    if hold_set is not None:
        assert hold_set.spot_xy is not None
        hold_err = beam_residuals(hold_set.poses, hold_set.d, hold_set.spot_xy, fit.h, model)
        holdout_block = {"fraction": holdout, "n": len(hold_set),
                         "rows": [int(r) for r in hold_set.rows],
                         "residuals": axis_statistics(hold_err)}
    return BeamCalibration(**{**result.__dict__, "warnings": tuple(warnings),
                              "holdout": holdout_block})
