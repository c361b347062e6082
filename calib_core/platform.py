"""Kinematic calibration of the 2-dof spherical parallel platform (spherical five-bar, "agile eye").

Geometry (fixed frame ``O``, mm and degrees at the interfaces, radians inside)
-------------------------------------------------------------------------------
Every revolute axis passes through the sphere centre ``C``. Five links: base, proximal 1 and 2,
distal 1 and 2; five joints with unit axes

- ``u1, u2`` base -> proximal ``i`` (actuated), fixed in ``O``;
- ``v1, v2`` proximal ``i`` -> distal ``i``;
- ``w`` distal 1 -> distal 2 (the output axis).

Base axes: ``u1 = Ry(u1_ry) Rz(u1_rz) x``, ``u2 = Rx(u2_rx) Rz(u2_rz) y`` (nominally x and y,
orthogonal). Proximal link ``i`` has twist ``alpha_i = angle(u_i, v_i)``; its home direction is

    v_i0 = cos(alpha_i) u_i + sin(alpha_i) p_i,   p_i = unit(r_i - (r_i . u_i) u_i)

with reference ``r_1 = y``, ``r_2 = x``, and the actuator turns it about ``u_i`` by the joint
angle ``theta_i = scale_i q_i + zero_i + link_i_az`` (Rodrigues; ``zero_i`` is the encoder's
zero offset, ``link_i_az`` the machining error of the link's azimuth about ``u_i``; the data see
only their sum, so one of them is always reported unidentifiable):

    v_i = v_i0 cos(theta_i) + (u_i x v_i0) sin(theta_i) + u_i (u_i . v_i0) (1 - cos(theta_i)).

Closure: distal link ``i`` holds ``v_i`` and ``w`` at the distal twist ``beta_i``, so
``w . v_i = cos(beta_i)`` (i = 1, 2) and ``|w| = 1``. With ``g = v1 . v2`` and
``n = v2 x v1`` (``|n|^2 = 1 - g^2``) the solution is ``w = a v1 + b v2 + c n`` with

    a = (cos b1 - g cos b2) / (1 - g^2),   b = (cos b2 - g cos b1) / (1 - g^2),
    c = +sqrt(1 - a^2 - b^2 - 2 a b g) / |n|,

the ``+`` root being the assembly mode of the nominal design (``w = z`` at ``q = 0``). No real
root (``1 - a^2 - b^2 - 2abg < 0``) means the loop cannot close.

Nominally (all twists 90 deg, axes x and y, no offsets) ``v1 = Rx(q1) y``, ``v2 = Ry(q2) x`` and
``w ~ v2 x v1 = (cos q1 sin q2, -sin q1 cos q2, cos q1 cos q2)``.

Output frame: the platform is distal link 1, whose pose is fixed by ``v1`` and ``w``:

    F = [e_x, e_y, e_z],  e_z = w,  e_y = unit(v1 - (v1 . w) w),  e_x = e_y x e_z

(``F = I`` at the nominal home), turned about ``w`` by the output link's machining error
``out_rz`` (indistinguishable from the mounting's rotation, hence reported unidentifiable). The
pyramid is mounted on it by the rotation ``M = Exp(mount_r)`` (rotation vector in degrees) and
the apex offset ``m`` (mm, in the output frame):

    R_pyramid = F Rz(out_rz) M,    apex = C + F Rz(out_rz) m.

Identification
--------------
Measured pyramid poses ``(R_k, apex_k)`` with covariance ``S_k`` (6x6, order rotation then
apex; rotation error as the fixed-frame rotation vector ``e`` of ``R_meas = Exp(e) R_true`` in
degrees, apex in mm) at commanded joints ``q_k``. Residual ``r_k = (log(R_k R_model^T), apex_k -
apex_model)``; its covariance adds the joint repeatability ``J_q diag(sigma_q^2) J_q^T``.
``scipy.optimize.least_squares`` minimises ``sum_k r_k^T S_k^-1 r_k`` over the identifiable
parameters. Observability: SVD of the whitened Jacobian with unit-norm columns; each singular
value below ``RANK_TOL * s_max`` marks a parameter combination the data cannot see; the free
parameter with the largest weight in that singular vector is fixed at nominal and reported.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib_core.errors import InputError
from calib_core.measure import Calibration
from calib_core.model import Poses
from calib_core.noise import NoiseModel
from calib_core.pyramid import PyramidGeometry

#: Parameter names in vector order (units in the suffix; ``scale_i`` is dimensionless).
PARAM_NAMES: tuple[str, ...] = (
    "centre_x_mm", "centre_y_mm", "centre_z_mm",
    "u1_ry_deg", "u1_rz_deg", "u2_rx_deg", "u2_rz_deg",
    "alpha1_deg", "alpha2_deg", "beta1_deg", "beta2_deg",
    "zero1_deg", "zero2_deg", "scale1", "scale2",
    "link1_az_deg", "link2_az_deg", "out_rz_deg",
    "mount_rx_deg", "mount_ry_deg", "mount_rz_deg",
    "mount_x_mm", "mount_y_mm", "mount_z_mm",
)
#: Defaults of a nominal design (centre and apex offset normally come from the workcell file).
DEFAULT_NOMINAL: dict[str, float] = {
    **dict.fromkeys(PARAM_NAMES, 0.0),
    "alpha1_deg": 90.0, "alpha2_deg": 90.0, "beta1_deg": 90.0, "beta2_deg": 90.0,
    "scale1": 1.0, "scale2": 1.0,
}
#: Absolute central-difference step per parameter (deg, mm, or 1 for the scales).
_STEP = {name: (1e-7 if name.startswith("scale") else 1e-5) for name in PARAM_NAMES}
#: Relative singular value below which a parameter combination counts as unobservable.
RANK_TOL = 1e-6
#: Order in which parameters are preferred for fixing when a null vector weighs several alike.
_FIX_PREFERENCE = ("out_rz_deg", "link1_az_deg", "link2_az_deg", "mount_rx_deg", "mount_ry_deg",
                   "mount_rz_deg", "mount_x_mm", "mount_y_mm", "mount_z_mm", "zero1_deg",
                   "zero2_deg")


def params_from_mapping(data: Mapping[str, object], source: str = "platform parameters",
                        base: Mapping[str, float] | None = None) -> dict[str, float]:
    """Full parameter set: ``base`` (default :data:`DEFAULT_NOMINAL`) updated by ``data``.

    Unknown names and non-finite values raise :class:`InputError`.
    """
    out = dict(DEFAULT_NOMINAL if base is None else base)
    for key, value in data.items():
        if key not in DEFAULT_NOMINAL:
            raise InputError(f"{source}: unknown platform parameter {key!r}; "
                             f"expected one of {', '.join(PARAM_NAMES)}")
        try:
            v = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise InputError(f"{source}: {key} = {value!r} is not a number") from None
        if not np.isfinite(v):
            raise InputError(f"{source}: {key} = {value!r} is not finite")
        out[key] = v
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def rodrigues(axis: np.ndarray, v: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rotate ``v`` (n, 3) about the unit ``axis`` (3,) by ``theta`` (n,) rad.

    ``v cos t + (axis x v) sin t + axis (axis . v)(1 - cos t)``.
    """
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    return v * c + np.cross(axis, v) * s + axis[None, :] * (v @ axis)[:, None] * (1.0 - c)


def closure(v1: np.ndarray, v2: np.ndarray, beta1_deg: float, beta2_deg: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Output axis ``w`` (n, 3) with ``w . v_i = cos(beta_i)``, ``|w| = 1``, and a validity mask.

    ``w = a v1 + b v2 + c (v2 x v1)`` with ``a, b`` from the 2x2 Gram system
    ``[1 g; g 1] [a b]^T = [cos b1, cos b2]^T`` (``g = v1 . v2``) and
    ``c = +sqrt(1 - a^2 - b^2 - 2abg) / |v2 x v1|``. Where the radicand is negative the loop
    cannot close: the mask is False and the radicand is clipped to 0.
    """
    g = np.sum(v1 * v2, axis=1)
    c1, c2 = np.cos(np.radians(beta1_deg)), np.cos(np.radians(beta2_deg))
    den = 1.0 - g**2
    a = (c1 - g * c2) / den
    b = (c2 - g * c1) / den
    n = np.cross(v2, v1)
    radicand = 1.0 - a**2 - b**2 - 2.0 * a * b * g
    ok = (radicand >= 0.0) & (den > 1e-12)
    c = np.sqrt(np.clip(radicand, 0.0, None) / np.maximum(den, 1e-300))
    return a[:, None] * v1 + b[:, None] * v2 + c[:, None] * n, ok


@dataclass(frozen=True)
class Chain:
    """Intermediate axes of the mechanism for each configuration (fixed frame)."""

    u1: np.ndarray
    u2: np.ndarray
    v1: np.ndarray
    v2: np.ndarray
    w: np.ndarray
    frame: np.ndarray
    valid: np.ndarray


def chain(params: Mapping[str, float], q_deg: np.ndarray) -> Chain:
    """Base axes ``u_i``, intermediate axes ``v_i``, output axis ``w`` and frame ``F`` (n, 3, 3).

    See the module docstring for the equations; ``q_deg`` is (n, 2) commanded joint angles.
    """
    p = params
    q = np.atleast_2d(np.asarray(q_deg, dtype=float))
    x, y = np.eye(3)[0], np.eye(3)[1]
    u1 = _rot("yz", [p["u1_ry_deg"], p["u1_rz_deg"]]) @ x
    u2 = _rot("xz", [p["u2_rx_deg"], p["u2_rz_deg"]]) @ y
    vs = []
    for u, ref, i in ((u1, y, 1), (u2, x, 2)):
        perp = _unit(ref - (ref @ u) * u)
        al = np.radians(p[f"alpha{i}_deg"])
        v0 = np.cos(al) * u + np.sin(al) * perp
        theta = np.radians(p[f"scale{i}"] * q[:, i - 1] + p[f"zero{i}_deg"]
                           + p[f"link{i}_az_deg"])
        vs.append(rodrigues(u, np.broadcast_to(v0, (len(q), 3)), theta))
    v1, v2 = vs
    w, ok = closure(v1, v2, p["beta1_deg"], p["beta2_deg"])
    ey = _unit(v1 - np.sum(v1 * w, axis=1)[:, None] * w)
    ex = np.cross(ey, w)
    frame = np.stack([ex, ey, w], axis=2)
    return Chain(u1, u2, v1, v2, w, frame, ok)


def forward(params: Mapping[str, float], q_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pyramid pose for joint angles ``q_deg`` (n, 2): rotation (n, 3, 3) and apex (n, 3) mm.

    ``R = F Rz(out_rz) Exp(mount_r)``, ``apex = C + F Rz(out_rz) m`` (module docstring).
    Raises :class:`InputError` when the loop cannot close at some configuration.
    """
    ch = chain(params, q_deg)
    if not np.all(ch.valid):
        bad = int(np.flatnonzero(~ch.valid)[0])
        raise InputError(f"platform loop cannot close at configuration {bad} "
                         f"(q = {np.atleast_2d(q_deg)[bad].tolist()} deg)")
    return _pose(params, ch.frame)


def _pose(params: Mapping[str, float], frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = params
    mount = Rotation.from_rotvec([p["mount_rx_deg"], p["mount_ry_deg"], p["mount_rz_deg"]],
                                 degrees=True).as_matrix()
    offset = np.array([p["mount_x_mm"], p["mount_y_mm"], p["mount_z_mm"]])
    centre = np.array([p["centre_x_mm"], p["centre_y_mm"], p["centre_z_mm"]])
    out = frame @ _rot("z", p["out_rz_deg"])
    return out @ mount, centre + out @ offset


def pose_error(r_meas: np.ndarray, apex_meas: np.ndarray, r_model: np.ndarray,
               apex_model: np.ndarray) -> np.ndarray:
    """Residual (n, 6): ``log(R_meas R_model^T)`` as a rotation vector in degrees, then apex mm."""
    rv = Rotation.from_matrix(np.einsum("nij,nkj->nik", r_meas, r_model)).as_rotvec(degrees=True)
    return np.concatenate([rv, apex_meas - apex_model], axis=1)


@dataclass(frozen=True)
class PoseSet:
    """Measured pyramid poses at commanded joint angles.

    ``config`` (n,) configuration ids (repeated visits share an id), ``q_deg`` (n, 2),
    ``rotation`` (n, 3, 3), ``apex`` (n, 3) mm, ``cov`` (n, 6, 6): rotation-vector error in deg^2
    (fixed frame, ``R_meas = Exp(e) R_true``) then apex in mm^2.
    """

    config: np.ndarray
    q_deg: np.ndarray
    rotation: np.ndarray
    apex: np.ndarray
    cov: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.config)
        shapes = {"q_deg": (n, 2), "rotation": (n, 3, 3), "apex": (n, 3), "cov": (n, 6, 6)}
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise InputError(f"pose set: {name} has shape {np.shape(getattr(self, name))}, "
                                 f"expected {shape}")
        for name in ("q_deg", "rotation", "apex", "cov"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(f"pose set: {name} holds non-finite values")

    def __len__(self) -> int:
        return len(self.config)


def joint_jacobian(params: Mapping[str, float], q_deg: np.ndarray, step: float = 1e-4
                   ) -> np.ndarray:
    """``d(pose)/d(q)`` (n, 6, 2) by central differences; pose as in :func:`pose_error`."""
    q = np.asarray(q_deg, dtype=float)
    out = np.empty((len(q), 6, 2))
    for j in range(2):
        dq = np.zeros(2)
        dq[j] = step
        rp, ap = forward(params, q + dq)
        rm, am = forward(params, q - dq)
        out[:, :, j] = pose_error(rp, ap, rm, am) / (2 * step)
    return out


def whitening(poses: PoseSet, params: Mapping[str, float], joint_sigma_deg: float) -> np.ndarray:
    """``L_k^-1`` (n, 6, 6) with ``L_k L_k^T = S_k + sigma_q^2 J_q J_q^T``."""
    cov = poses.cov.copy()
    if joint_sigma_deg > 0:
        jq = joint_jacobian(params, poses.q_deg)
        cov = cov + joint_sigma_deg**2 * np.einsum("nij,nkj->nik", jq, jq)
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise InputError("pose covariance is not positive definite") from None
    return np.linalg.inv(chol)


def _residual_fn(poses: PoseSet, nominal: Mapping[str, float], free: Sequence[str],
                 wmat: np.ndarray):
    base = dict(nominal)

    def fun(x: np.ndarray) -> np.ndarray:
        p = {**base, **dict(zip(free, x, strict=True))}
        ch = chain(p, poses.q_deg)
        r, a = _pose(p, ch.frame)
        res = pose_error(poses.rotation, poses.apex, r, a)
        return np.einsum("nij,nj->ni", wmat, res).ravel()

    return fun


def _numeric_jacobian(fun, x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    cols = []
    for k, h in enumerate(steps):
        e = np.zeros_like(x)
        e[k] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.stack(cols, axis=1)


@dataclass(frozen=True)
class Observability:
    """Free / fixed parameters with reasons, singular values and condition of the scaled J."""

    free: tuple[str, ...]
    unidentifiable: tuple[dict[str, str], ...]
    singular_values: np.ndarray
    condition_number: float


def observability(jac: np.ndarray, names: Sequence[str], tol: float = RANK_TOL) -> Observability:
    """Drop parameters until the column-normalised Jacobian has full rank.

    ``J_s = J diag(1/|J_k|)``; while ``s_min < tol s_max`` the free parameter with the largest
    ``|V_k|`` in the weakest right singular vector (candidates within half of the largest
    weight ordered by ``_FIX_PREFERENCE``) is fixed; the reason gives the least-squares
    combination of the remaining parameters that reproduces its effect.
    """
    names = list(names)
    norms = np.linalg.norm(jac, axis=0)
    dropped: list[dict[str, str]] = []
    for k in np.flatnonzero(norms < 1e-12 * max(norms.max(), 1e-300)):
        dropped.append({"name": names[k], "reason": "has no effect on the pyramid pose"})
    keep = [k for k in range(len(names)) if norms[k] >= 1e-12 * max(norms.max(), 1e-300)]
    while keep:
        js = jac[:, keep] / norms[keep]
        _, s, vt = np.linalg.svd(js, full_matrices=False)
        if s[-1] >= tol * s[0]:
            break
        v = vt[-1]
        mag = np.abs(v)
        cand = [i for i in range(len(keep)) if mag[i] >= 0.5 * mag.max()]
        pref = [i for i in cand if names[keep[i]] in _FIX_PREFERENCE]
        pick = (min(pref, key=lambda i: _FIX_PREFERENCE.index(names[keep[i]])) if pref
                else cand[0])
        others = [k for i, k in enumerate(keep) if i != pick]
        col = jac[:, keep[pick]] / norms[keep[pick]]
        coef = np.linalg.lstsq(jac[:, others] / norms[others], col, rcond=tol)[0]
        coef = coef * norms[keep[pick]] / norms[others]  # back to parameter units
        big = np.abs(coef) > 1e-3 * np.abs(coef).max()
        partners = [f"{coef[i]:+.3g} x {names[others[i]]}" for i in np.argsort(-np.abs(coef))
                    if big[i]]
        reason = ("acts like " + " ".join(partners) if partners else "unobservable") + \
            f" (relative singular value {s[-1] / s[0]:.1e}); fixed at nominal"
        dropped.append({"name": names[keep[pick]], "reason": reason})
        keep.pop(pick)
    if not keep:
        return Observability((), tuple(dropped), np.zeros(0), float("inf"))
    s = np.linalg.svd(jac[:, keep] / norms[keep], compute_uv=False)
    return Observability(tuple(names[k] for k in keep), tuple(dropped), s, float(s[0] / s[-1]))


@dataclass(frozen=True)
class PlatformCalibration:
    """Identified parameters (all names; fixed ones at nominal), 1-sigma, and fit statistics."""

    params: dict[str, float]
    sigma: dict[str, float]
    free: tuple[str, ...]
    unidentifiable: tuple[dict[str, str], ...]
    covariance: np.ndarray = field(repr=False)
    chi2_reduced: float = 1.0
    n_poses: int = 0
    condition_number: float = float("nan")
    singular_values: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    warnings: tuple[str, ...] = ()


def identify(poses: PoseSet, nominal: Mapping[str, float], joint_sigma_deg: float = 0.0,
             fixed: Sequence[str] = ()) -> PlatformCalibration:
    """Weighted nonlinear least squares for the platform parameters from measured pyramid poses.

    Minimises ``sum_k |L_k^-1 r_k|^2`` (module docstring) from ``nominal``; parameters found
    unobservable at nominal (SVD, :func:`observability`) or listed in ``fixed`` stay at nominal.
    The covariance is ``(J^T J)^-1 max(1, chi2/dof)`` of the whitened Jacobian at the solution.
    """
    nominal = params_from_mapping({}, base=nominal)
    n = len(poses)
    if n < 4:
        raise InputError(f"platform calibration needs at least 4 pose measurements, got {n}")
    unknown = sorted(set(fixed) - set(PARAM_NAMES))
    if unknown:
        raise InputError(f"unknown parameter(s) to fix: {', '.join(unknown)}")
    forward(nominal, poses.q_deg)  # raises if the nominal loop cannot close
    wmat = whitening(poses, nominal, joint_sigma_deg)
    candidates = [p for p in PARAM_NAMES if p not in fixed]
    fun = _residual_fn(poses, nominal, candidates, wmat)
    x0 = np.array([nominal[p] for p in candidates])
    steps = np.array([_STEP[p] for p in candidates])
    obs = observability(_numeric_jacobian(fun, x0, steps), candidates)
    free = list(obs.free)
    unid = [*({"name": p, "reason": "fixed by request"} for p in fixed), *obs.unidentifiable]
    fun = _residual_fn(poses, nominal, free, wmat)
    x0 = np.array([nominal[p] for p in free])
    steps = np.array([_STEP[p] for p in free])
    sol = least_squares(fun, x0, jac=lambda x: _numeric_jacobian(fun, x, steps), method="lm",
                        xtol=1e-12, ftol=1e-12)
    jac = _numeric_jacobian(fun, sol.x, steps)
    dof = max(sol.fun.size - len(free), 1)
    chi2 = float(sol.fun @ sol.fun) / dof
    cov = np.linalg.pinv(jac.T @ jac) * max(1.0, chi2)
    sig = np.sqrt(np.diag(cov))
    params = {**nominal, **dict(zip(free, sol.x.tolist(), strict=True))}
    sigma = dict.fromkeys(PARAM_NAMES, 0.0)
    sigma.update(zip(free, sig.tolist(), strict=True))
    warnings = []
    if chi2 > 4.0:
        warnings.append(f"reduced chi-square {chi2:.2f}: residuals exceed the stated noise "
                        "(model error or optimistic covariances); sigmas scaled up")
    corr = cov / np.outer(sig, sig)
    for i, j in zip(*np.triu_indices(len(free), 1), strict=True):
        if abs(corr[i, j]) > 0.995:
            warnings.append(f"{free[i]} and {free[j]} are strongly correlated "
                            f"(rho = {corr[i, j]:+.3f})")
    return PlatformCalibration(params, sigma, tuple(free), tuple(unid), cov, chi2, n,
                               obs.condition_number, obs.singular_values, tuple(warnings))


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    return float(np.mean(x)), float(np.sqrt(np.mean(x**2))), float(np.max(x))


def evaluate(params: Mapping[str, float], poses: PoseSet) -> dict[str, object]:
    """Pose errors of ``params`` against measured poses, ISO 9283 style.

    Per measurement: orientation error = angle of ``R_meas R_model^T`` (deg), apex error =
    ``|apex_meas - apex_model|`` (mm); their mean, RMS and max. For each configuration visited
    ``m >= 2`` times (commanded pose ``c`` = the model's prediction, attained poses ``j``):

    - ``AP_P = |mean_j(apex_j) - apex_c|`` (mm); ``AP_o = |mean_j(e_j)|`` (deg) with
      ``e_j = log(R_j R_c^T)`` (the per-axis ISO ``AP_a, AP_b, AP_c`` as one vector);
    - ``RP_l = mean(l_j) + 3 S_l`` with ``l_j = |apex_j - mean(apex)|`` and ``S_l`` its
      standard deviation (n - 1); ``RP_o = max over axes of 3 S`` of the ``e_j`` components.

    ``noise_*_rms`` is the RMS error the measurement noise alone gives (``sqrt(mean tr S)``
    of the rotation / apex blocks): the floor a perfect model reaches. ``ap_*``/``rp_*`` are
    the worst over those configurations (None without repeated visits);
    ``iso_poses`` lists each.
    """
    r, a = forward(params, poses.q_deg)
    err = pose_error(poses.rotation, poses.apex, r, a)
    ang = np.linalg.norm(err[:, :3], axis=1)
    dist = np.linalg.norm(err[:, 3:], axis=1)
    out: dict[str, object] = {
        "n_poses": len(poses),
        "noise_orientation_rms_deg": float(np.sqrt(np.mean(np.trace(poses.cov[:, :3, :3],
                                                                    axis1=1, axis2=2)))),
        "noise_apex_rms_mm": float(np.sqrt(np.mean(np.trace(poses.cov[:, 3:, 3:], axis1=1,
                                                            axis2=2)))),
    }
    for key, x in (("orientation", ang), ("apex", dist)):
        unit = "deg" if key == "orientation" else "mm"
        mean, rms, mx = _stats(x)
        out.update({f"{key}_mean_{unit}": mean, f"{key}_rms_{unit}": rms,
                    f"{key}_max_{unit}": mx})
    iso = []
    for cfg in np.unique(poses.config):
        idx = np.flatnonzero(poses.config == cfg)
        if len(idx) < 2:
            continue
        e = err[idx]
        l_j = np.linalg.norm(e[:, 3:] - e[:, 3:].mean(axis=0), axis=1)
        iso.append({
            "config": int(cfg), "visits": len(idx),
            "q_deg": poses.q_deg[idx[0]].tolist(),
            "ap_mm": float(np.linalg.norm(e[:, 3:].mean(axis=0))),
            "ap_deg": float(np.linalg.norm(e[:, :3].mean(axis=0))),
            "rp_mm": float(l_j.mean() + 3 * l_j.std(ddof=1)),
            "rp_deg": float(3 * e[:, :3].std(axis=0, ddof=1).max()),
        })
    out["iso_poses"] = iso
    for key in ("ap_mm", "ap_deg", "rp_mm", "rp_deg"):
        out[key] = max((p[key] for p in iso), default=None)
    return out


def poses_from_scans(config: np.ndarray, q_deg: np.ndarray, measurement: np.ndarray,
                     flange: Poses, d: np.ndarray, face: np.ndarray, calib: Calibration,
                     geometry: PyramidGeometry | None = None,
                     noise: NoiseModel | None = None) -> tuple[PoseSet, tuple[str, ...]]:
    """One pyramid pose per measurement from scan rows (eq 16 points, three-face fit).

    Rows sharing ``measurement`` (n,) form one scan; each must have a single ``config`` and
    ``q_deg``. Points ``P = O + R (T + d u')`` with scan-noise and calibration covariance
    (:func:`calib_core.measure.reconstruct`), pose and covariance by
    :func:`calib_core.pyramid.measure_pyramid`; the rotation covariance is converted from rad^2
    to deg^2. The calibration's covariance enters every pose independently (conservative per
    pose; its correlation across configurations is not modelled). Returns the poses and the
    pyramid fits' warnings, prefixed by the configuration.
    """
    from calib_core.measure import reconstruct
    from calib_core.pyramid import measure_pyramid

    meas = np.asarray(measurement)
    keys, first = np.unique(meas, return_index=True)
    order = np.argsort(first)
    keys, first = keys[order], first[order]
    n = len(keys)
    rot, apex, cov = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 6, 6))
    warnings: list[str] = []
    scale = np.concatenate([np.full(3, np.degrees(1.0)), np.ones(3)])
    for k, key in enumerate(keys):
        idx = np.flatnonzero(meas == key)
        cfg = config[idx]
        if np.any(cfg != cfg[0]) or np.ptp(q_deg[idx], axis=0).max() > 0:
            raise InputError(f"measurement {key}: rows disagree on config or q1_deg, q2_deg")
        try:
            fit = measure_pyramid(reconstruct(flange.subset(idx), d[idx], calib, noise),
                                  face[idx], geometry)
        except InputError as exc:
            raise InputError(f"configuration {cfg[0]}: {exc}") from None
        rot[k], apex[k] = fit.rotation, fit.apex
        cov[k] = fit.pose_cov * np.outer(scale, scale)
        warnings.extend(f"configuration {cfg[0]}: {w}" for w in fit.warnings)
    return PoseSet(np.asarray(config)[first], np.asarray(q_deg, float)[first], rot, apex,
                   cov), tuple(warnings)
