"""The content of a calibration report: header, result, residuals per pose, noise floor, verdict.

Everything here is plain data computed from a :class:`~calib_core.calibrate.BeamCalibration`,
the :class:`~calib_core.io.Dataset` it came from and a metadata mapping; the renderers
(``html``, ``pdf``, ``export``) only format it. Units: mm and degrees.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from calib_core.calibrate import BeamCalibration, beam_residuals, outlier_threshold
from calib_core.io import Dataset
from calib_core.model import beam_regressor
from calib_core.noise import residual_covariance_components
from calib_core.refine import residual_covariance
from calib_core.stats import AXES, axis_statistics

#: Observed/expected residual RMS ratio outside which the verdict asks for a review.
RATIO_HIGH = 1.5
RATIO_LOW = 0.67
#: Packages whose installed versions the header lists.
VERSION_PACKAGES = ("lasercal", "numpy", "scipy", "pandas", "matplotlib", "viser", "pyserial",
                    "opencv-python-headless")
#: Per-pose table columns written to residuals.csv (mm and degrees).
POSE_COLUMNS = ("row", "pose_index", "set", "x_o", "y_o", "z_o", "rotation_deg", "d", "x_p",
                "y_p", "spot_x", "spot_y", "spot_z", "e_x", "e_y", "e_z", "chi2")


@dataclass(frozen=True)
class Report:
    """All numbers and texts of one report.

    ``poses``: one row per data row (:data:`POSE_COLUMNS`); ``set`` is ``fit``, ``holdout``,
    ``outlier`` or ``evaluated`` (rows checked against a given calibration).
    ``stats[label][axis]``: Table-1 mean_abs / rms / max (mm) per set label.
    ``expected[label][axis]``: residual RMS (mm) expected from the noise model.
    """

    calibration: BeamCalibration
    meta: dict[str, Any]
    poses: pd.DataFrame
    stats: dict[str, dict[str, dict[str, float]]]
    expected: dict[str, dict[str, float]]
    outliers: list[dict[str, Any]]
    verdict: dict[str, Any]
    warnings: list[tuple[str, str]]
    sections: list[dict[str, Any]] = field(default_factory=list)

    @property
    def mode(self) -> str:
        """'solved' (H fitted to this data) or 'evaluated' (H from a calibration file)."""
        return str(self.meta.get("calibration_mode", "solved"))

    def json_dict(self) -> dict[str, Any]:
        """``solve --json`` object plus a ``report`` block (metadata, noise floor, verdict)."""
        out = self.calibration.to_json_dict()
        if self.mode == "evaluated":
            out["residuals"] = self.stats["evaluated"]
        out["report"] = {
            "meta": {k: v for k, v in self.meta.items()},
            "residuals": self.stats,
            "expected_rms": self.expected,
            "outliers": self.outliers,
            "verdict": self.verdict,
            "warnings_explained": [{"warning": w, "explanation": e} for w, e in self.warnings],
            "sections": self.sections,
        }
        return _json_safe(out)


def _json_safe(value: Any) -> Any:
    """NaN/inf -> None, numpy scalars -> Python, recursively (strict JSON)."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        v = float(value)
        return v if math.isfinite(v) else None
    return value


# ---- metadata ------------------------------------------------------------------------------

def sha256_of(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def installed_versions() -> dict[str, str]:
    """Python and the installed versions of :data:`VERSION_PACKAGES` (importlib.metadata)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": sys.version.split()[0]}
    for name in VERSION_PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def source_meta(path: str | Path, note: str = "") -> dict[str, Any]:
    """Header metadata of a data source: its SHA-256, and what a session or CSV records.

    A session file gives its created time, mode (simulated/hardware), drivers, software versions
    at acquisition, workcell TOML and grid name; a CSV gives its ``#`` comment lines (a comment
    mentioning 'simulated' marks the data as simulated).
    """
    path = Path(path)
    meta: dict[str, Any] = {"source": str(path), "sha256": sha256_of(path), "note": note}
    if path.suffix.lower() in (".db", ".sqlite", ".sqlite3"):
        from app.session import Session

        with Session.open(path, readonly=True) as session:
            raw = session.meta
            settings = session.meta_json("settings")
            meta.update(
                kind="session", created=raw.get("created", ""),
                mode={"sim": "simulated", "hardware": "hardware"}.get(
                    str(settings.get("mode", "")), "not recorded"),
                drivers=session.meta_json("drivers"),
                software_recorded=session.meta_json("software"),
                workcell=raw.get("workcell", ""),
                workcell_source=str(settings.get("workcell_source", "")),
                grid=raw.get("grid", ""),
                session_noise=session.meta_json("noise"))
    else:
        try:
            lines = path.read_text(encoding="utf-8-sig").splitlines()
        except (OSError, UnicodeDecodeError):
            lines = []
        comments = [ln.lstrip()[1:].strip() for ln in lines if ln.lstrip().startswith("#")]
        simulated = any("simulat" in c.lower() for c in comments)
        meta.update(kind="csv", comments=comments,
                    mode="simulated (per file comment)" if simulated else "not recorded (CSV)")
    return meta


def complete_meta(meta: Mapping[str, Any] | None) -> dict[str, Any]:
    """Fill the keys the renderers expect; given values win."""
    base: dict[str, Any] = {
        "title": "Laser beam calibration report", "source": "(in-memory data)", "sha256": "",
        "note": "", "kind": "data", "created": "", "mode": "not recorded", "drivers": {},
        "software_recorded": {}, "workcell": "", "workcell_source": "", "grid": "",
        "calibration_mode": "solved", "calibration_source": "solved from this data",
        "options": {},
    }
    out = {**base, **dict(meta or {})}
    out.setdefault("generated", datetime.now(UTC).isoformat(timespec="seconds"))
    out["versions"] = out.get("versions") or installed_versions()
    return out


# ---- residuals and the noise floor -----------------------------------------------------------

def rotation_angle_deg(dataset: Dataset) -> np.ndarray:
    """theta_deg for a 4-dof file, else the rotation angle of each flange orientation (deg)."""
    if dataset.poses.theta_deg is not None:
        return np.asarray(dataset.poses.theta_deg, dtype=float)
    tr = np.trace(dataset.poses.rotation, axis1=1, axis2=2)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def expected_rms(result: BeamCalibration, dataset: Dataset, fit_idx: np.ndarray,
                 eval_idx: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """Residual RMS per axis expected from the noise model (mm).

    With ``C_i`` the noise-model covariance of pose ``i``'s residual (factors 1),
    ``A_i`` its regressor rows and ``N = sum_fit A_i^T C_i^-1 A_i``:

        fit set:        E[r_i r_i^T] = C_i - A_i N^-1 A_i^T      (the fit absorbs p dof)
        other poses:    E[r_i r_i^T] = C_i + A_i N^-1 A_i^T      (prediction error)

    and the expected RMS of axis k is ``sqrt(mean_i E[r_i r_i^T]_kk)``. When ``fit_idx`` is
    empty (a given calibration), ``N^-1`` is the calibration's covariance.
    """
    assert dataset.spot_xy is not None
    h, model = result.values, result.model
    reg = beam_regressor(dataset.poses, dataset.d, dataset.spot_xy, model)
    lat, ax = residual_covariance_components(dataset.poses, dataset.d, dataset.spot_xy, h, model,
                                             result.noise)
    cov = lat + ax
    if len(fit_idx):
        c_fit = residual_covariance(dataset.poses.subset(fit_idx), dataset.d[fit_idx],
                                    dataset.spot_xy[fit_idx], h, model, result.noise)
        a = reg[fit_idx]
        normal = np.einsum("nji,njk,nkl->il", a, np.linalg.inv(c_fit), a)
        n_inv = np.linalg.pinv(normal)
    else:
        n_inv = result.covariance
    out: dict[str, dict[str, float]] = {}
    sets = [("fit", fit_idx, -1.0)] if len(fit_idx) else []
    if eval_idx is not None and len(eval_idx):
        sets.append(("holdout" if len(fit_idx) else "evaluated", eval_idx, +1.0))
    for label, idx, sign in sets:
        a = reg[idx]
        var = np.diagonal(cov[idx], axis1=1, axis2=2) + sign * np.einsum(
            "nkj,jl,nkl->nk", a, n_inv, a)
        out[label] = {axis: float(np.sqrt(max(var[:, k].mean(), 0.0)))
                      for k, axis in enumerate(AXES)}
    return out


def evaluate_calibration(calib: BeamCalibration, dataset: Dataset,
                         raw: Mapping[str, Any] | None = None) -> BeamCalibration:
    """A given calibration with this data's Table-1 residuals (every row evaluated, none fitted).

    ``raw`` (the calibration file's JSON) supplies condition number, singular values, warnings,
    noise model and variance factors when it holds them.
    """
    from calib_core.calibrate import choose_model
    from calib_core.noise import NoiseModel

    if dataset.spot_xy is None:
        raise_input(f"{dataset.source}: the report needs the camera columns x_p, y_p")
    choose_model(dataset, calib.model)  # refuses a 4-dof calibration for tilted poses
    assert dataset.spot_xy is not None
    err = beam_residuals(dataset.poses, dataset.d, dataset.spot_xy, calib.values, calib.model)
    raw = raw or {}
    vf = raw.get("variance_factors") or {}
    noise = NoiseModel.from_mapping(raw["noise"], "calibration noise") if isinstance(
        raw.get("noise"), Mapping) else calib.noise
    return replace(
        calib, n_points=len(dataset), n_used=len(dataset), outliers=(),
        residuals=axis_statistics(err), rows_used=tuple(int(r) for r in dataset.rows),
        condition_number=float(raw.get("condition_number", float("nan")) or float("nan")),
        singular_values=tuple(float(v) for v in raw.get("singular_values", []) or []),
        warnings=tuple(str(w) for w in raw.get("warnings", []) or []),
        variance_factors=(float(vf.get("lateral", 1.0)), float(vf.get("axial", 1.0))),
        chi2_reduced=float(raw.get("chi2_reduced", float("nan")) or float("nan")),
        noise=noise, holdout=None)


def raise_input(message: str) -> None:
    from calib_core.errors import InputError

    raise InputError(message)


def pose_table(result: BeamCalibration, dataset: Dataset, evaluated: bool
               ) -> pd.DataFrame:
    """Per-pose residuals (mm) and chi-square at the final ``H`` (see :data:`POSE_COLUMNS`)."""
    assert dataset.spot_xy is not None
    rows = np.asarray(dataset.rows, dtype=int)
    err = beam_residuals(dataset.poses, dataset.d, dataset.spot_xy, result.values, result.model)
    spot = result.reconstruct(dataset.poses, dataset.d)  # 4-dof: z is z_P - delta
    cov = residual_covariance(dataset.poses, dataset.d, dataset.spot_xy, result.values,
                              result.model, result.noise, tuple(result.variance_factors))
    chi2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)
    hold = set(int(r) for r in (result.holdout or {}).get("rows", []))  # type: ignore[union-attr]
    out_rows = set(int(r) for r in result.outliers)
    labels = ["evaluated" if evaluated else "outlier" if r in out_rows else
              "holdout" if r in hold else "fit" for r in rows]
    pose_index = dataset.extra["pose_index"].astype(int).to_numpy() if (
        "pose_index" in dataset.extra.columns) else rows
    return pd.DataFrame({
        "row": rows, "pose_index": pose_index, "set": labels,
        "x_o": dataset.poses.position[:, 0], "y_o": dataset.poses.position[:, 1],
        "z_o": dataset.poses.position[:, 2], "rotation_deg": rotation_angle_deg(dataset),
        "d": dataset.d, "x_p": dataset.spot_xy[:, 0], "y_p": dataset.spot_xy[:, 1],
        "spot_x": spot[:, 0], "spot_y": spot[:, 1], "spot_z": spot[:, 2],
        "e_x": err[:, 0], "e_y": err[:, 1], "e_z": err[:, 2], "chi2": chi2,
    }, columns=list(POSE_COLUMNS))


# ---- warnings in plain words and the verdict -------------------------------------------------

_CORRELATION_HINTS = {
    frozenset({"z_t_minus_delta", "beta"}): (
        "the plate tilt beta times the beam's y offset shifts the spot height the same way as "
        "z_t - delta; more spread of the spot in y (rotations, y range) separates them"),
    frozenset({"z_t", "delta"}): (
        "z_t and the plate height delta are only separated by tilting the flange; add poses "
        "with larger tilts"),
    frozenset({"z_t_minus_delta", "alpha"}): (
        "the plate tilt alpha times the beam's x offset shifts the spot height like "
        "z_t - delta; more spread of the spot in x separates them"),
}


def explain_warning(text: str) -> str:
    """A plain-words explanation of a solver warning (what it means, what to do)."""
    low = text.lower()
    if low.startswith("strong correlation between"):
        names = low.removeprefix("strong correlation between ").split(" (")[0].split(" and ")
        hint = _CORRELATION_HINTS.get(frozenset(n.strip() for n in names))
        return ("These two parameters are nearly interchangeable in this pose design: each "
                "alone is uncertain (see their sigmas) but their combination, and the points "
                "reconstructed with the calibration, are well determined"
                + (f"; {hint}." if hint else
                   "; a wider range of heights, x-y positions or rotations separates them."))
    if "poorly conditioned" in low:
        return ("The poses barely distinguish some parameter combinations, so small measurement "
                "errors move the result a lot: add heights, x-y spread or rotations and repeat.")
    if "differs from 1" in low:
        return ("The sensor reading scale (or the robot's z scale) does not match: distances "
                "measured with this sensor are off by that factor unless this calibration is "
                "used. Check the sensor's scaling settings.")
    if "rejected as outliers" in low:
        return ("An unusually large share of poses was excluded: the noise model is probably too "
                "optimistic, or the camera/sensor misbehaved. Inspect the excluded rows.")
    if low.startswith("excluded outlier row"):
        return ("These poses disagree with the others far beyond the noise model (see the "
                "outlier table); they were left out of the fit. Re-measure them if in doubt.")
    if "rotation" in low and "range" in low:
        return ("The rotations span too small an angle to pin down the named parameter; "
                "widen the rotation range.")
    return "See the solver documentation for this condition."


def build_verdict(stats: Mapping[str, Mapping[str, Mapping[str, float]]],
                  expected: Mapping[str, Mapping[str, float]], result: BeamCalibration,
                  warnings: Sequence[tuple[str, str]]) -> dict[str, Any]:
    """Residual RMS vs the noise floor per set and axis, and the overall status.

    ``status`` is 'consistent' when every ratio observed/expected lies in
    [:data:`RATIO_LOW`, :data:`RATIO_HIGH`] and no warning other than correlations and the
    list of excluded outliers was raised; otherwise 'review'.
    """
    ratios: dict[str, dict[str, float]] = {}
    lines: list[str] = []
    review = False
    names = {"fit": "fit set", "holdout": "hold-out set", "evaluated": "evaluated poses"}
    for label, exp in expected.items():
        ratios[label] = {}
        for axis in AXES:
            obs = float(stats[label][axis]["rms"])
            ratio = obs / exp[axis] if exp[axis] > 0 else float("inf")
            ratios[label][axis] = ratio
        worst = max(ratios[label].values())
        best = min(ratios[label].values())
        set_name = names.get(label, label)
        if worst > RATIO_HIGH:
            review = True
            axes = ", ".join(a for a in AXES if ratios[label][a] > RATIO_HIGH)
            lines.append(f"{set_name}: residuals on {axes} exceed the noise floor by more than "
                         f"{RATIO_HIGH}x: unmodelled errors (robot accuracy, plate flatness, "
                         "camera scale) or a too optimistic noise model.")
        elif best < RATIO_LOW:
            axes = ", ".join(a for a in AXES if ratios[label][a] < RATIO_LOW)
            lines.append(f"{set_name}: residuals on {axes} are well below the noise floor: the "
                         "noise model is pessimistic (the reported sigmas are scaled to the "
                         "observed scatter by the variance factors).")
        else:
            lines.append(f"{set_name}: residual RMS within {RATIO_LOW}-{RATIO_HIGH}x of the "
                         "noise floor expected from the noise model on every axis.")
    benign = ("strong correlation", "excluded outlier row")
    serious = [w for w, _ in warnings if not w.lower().startswith(benign)]
    if serious:
        review = True
    if result.outliers:
        lines.append(f"{len(result.outliers)} pose(s) excluded as outliers "
                     f"(rows {', '.join(map(str, result.outliers))}).")
    n_corr = sum(1 for w, _ in warnings if w.lower().startswith("strong correlation"))
    if n_corr:
        lines.append(f"{n_corr} strongly correlated parameter pair(s): expected for this kind "
                     "of design; the reconstructed points are not affected.")
    for w in serious:
        lines.append(f"Warning: {w}.")
    status = "review" if review else "consistent"
    headline = ("Residuals consistent with the noise model" if status == "consistent" else
                "Review needed before use")
    return {"status": status, "headline": headline, "ratios": ratios, "lines": lines}


# ---- optional application sections -----------------------------------------------------------

def section_from_json(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """A report section from a ``measure ... --json`` or ``platform calibrate --json`` object.

    The kind is recognised by its keys. ``params``/``sigma`` (and ``nominal``) become a
    parameter table, ``before``/``after`` the ISO 9283 style validation table, every other
    scalar or short vector a (name, text) row.
    """
    keys = set(data)
    if {"before", "after"} <= keys:
        kind = "Platform calibration (2-dof spherical five-bar)"
    elif "apex" in keys and "quaternion" in keys:
        kind = "Pyramid pose"
    elif "agreement_sigmas" in keys:
        kind = "Johansson gauge check"
    elif {"alpha", "beta", "offset"} <= keys:
        kind = "Plane identification"
    else:
        kind = "Measurement"

    def text(v: Any) -> str:
        if isinstance(v, bool) or v is None:
            return "n/a" if v is None else str(v)
        if isinstance(v, str):
            return v
        if isinstance(v, int | float):
            return f"{v:.6g}"
        if isinstance(v, list | tuple) and all(
                isinstance(x, int | float) and not isinstance(x, bool) for x in v):
            digits = 6 if len(v) <= 9 else 4
            return "(" + ", ".join(f"{x:.{digits}g}" for x in v) + ")"
        if isinstance(v, list | tuple) and all(isinstance(x, str) for x in v):
            return "; ".join(v) or "none"
        if isinstance(v, list | tuple) and all(
                isinstance(x, Mapping) and "name" in x for x in v):
            return "; ".join(f"{x['name']}: {x.get('reason', '')}" for x in v) or "none"
        return json.dumps(_json_safe(v))[:400]

    tables: list[dict[str, Any]] = []
    used: set[str] = set()
    params, sigma = data.get("params"), data.get("sigma")
    if isinstance(params, Mapping) and isinstance(sigma, Mapping):
        nominal = data.get("nominal") if isinstance(data.get("nominal"), Mapping) else {}
        tables.append({"caption": "Identified parameters",
                       "columns": ["parameter", "nominal", "identified", "1-sigma"],
                       "rows": [[k, text(nominal.get(k)), text(v), text(sigma.get(k))]
                                for k, v in params.items()]})
        used |= {"params", "sigma", "nominal"}
    before, after = data.get("before"), data.get("after")
    if isinstance(before, Mapping) and isinstance(after, Mapping):
        tables.append({"caption": "Validation set, ISO 9283 style",
                       "columns": ["figure", "before (nominal)", "after (calibrated)"],
                       "rows": [[k, text(before[k]), text(after.get(k))] for k in before
                                if not isinstance(before[k], Mapping | list)]})
        used |= {"before", "after"}
    rows: list[tuple[str, str]] = []
    for key, value in data.items():
        if key in used:
            continue
        if isinstance(value, Mapping) and all(not isinstance(v, Mapping) for v in value.values()):
            rows += [(f"{key}.{k2}", text(v2)) for k2, v2 in value.items()]
        else:
            rows.append((key, text(value)))
    return {"title": kind, "source": source, "rows": rows, "tables": tables}


# ---- assembling ------------------------------------------------------------------------------

def build_report(result: BeamCalibration, dataset: Dataset, meta: Mapping[str, Any] | None = None,
                 sections: Sequence[Mapping[str, Any]] = ()) -> Report:
    """The report of ``result`` on ``dataset`` (the full data set that was solved, or evaluated
    with a given calibration when ``meta['calibration_mode'] == 'evaluated'``)."""
    if dataset.spot_xy is None:
        raise_input(f"{dataset.source}: the report needs the camera columns x_p, y_p")
    meta_full = complete_meta(meta)
    meta_full["noise"] = result.noise.as_dict()
    evaluated = meta_full["calibration_mode"] == "evaluated"
    poses = pose_table(result, dataset, evaluated)
    sets = poses["set"].to_numpy()
    err = poses[["e_x", "e_y", "e_z"]].to_numpy()
    fit_idx = np.flatnonzero(sets == "fit")
    other = np.flatnonzero(np.isin(sets, ("holdout", "evaluated")))
    stats: dict[str, dict[str, dict[str, float]]] = {}
    if evaluated:
        stats["evaluated"] = axis_statistics(err[other])
    else:
        stats["fit"] = {a: dict(v) for a, v in result.residuals.items()}
        if len(other):
            stats["holdout"] = {a: dict(v) for a, v in
                                result.holdout["residuals"].items()}  # type: ignore[index]
    expected = expected_rms(result, dataset, fit_idx, other)
    n_fit = int(np.sum(sets != "holdout"))
    threshold = outlier_threshold(n_fit) if n_fit else float("nan")
    outliers = []
    for k in np.flatnonzero(sets == "outlier"):
        p = poses.iloc[int(k)]
        outliers.append({
            "row": int(p["row"]), "e_x": float(p["e_x"]), "e_y": float(p["e_y"]),
            "e_z": float(p["e_z"]), "chi2": float(p["chi2"]), "threshold": threshold,
            "reason": (f"chi-square {p['chi2']:.1f} (3 dof) at the final fit is above the "
                       f"robust test's limit {threshold:.1f} (1 % false-alarm probability over "
                       f"all {n_fit} poses): a gross error such as a camera mis-detection or a "
                       "sensor glitch, so the pose was left out of the fit")})
    warnings = [(w, explain_warning(w)) for w in result.warnings]
    verdict = build_verdict(stats, expected, result, warnings)
    return Report(calibration=result, meta=meta_full, poses=poses, stats=stats,
                  expected=expected, outliers=outliers, verdict=verdict, warnings=warnings,
                  sections=[dict(s) for s in sections])
