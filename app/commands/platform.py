"""``lasercal platform``: simulate and calibrate the 2-dof platform that carries the pyramid."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

HELP = """\
Kinematic calibration of the 2-dof spherical parallel platform (spherical five-bar) carrying the
pyramid: identify base axis directions, link twists, actuator zero offsets and scales, the sphere
centre and the pyramid's mounting from pyramid poses measured at many joint configurations;
parameters the data cannot see are fixed at nominal and listed; errors before (nominal model)
and after calibration on a separate validation set, ISO 9283 style.

  simulate --out DIR [--seed N] [--poses]   write a simulated campaign
  calibrate DIR [--json]                    identify and evaluate a campaign

A campaign directory holds manifest.json, train.csv and validation.csv (scans of the three
faces per configuration, or measured poses), the beam calibration (calibration.json) for scans,
and truth.json for a simulated campaign (read by nothing but tests and reviewers).
"""

MANIFEST = "manifest.json"
FORMAT = "lasercal-platform-campaign/1"
COV_AXES = ("rx", "ry", "rz", "x", "y", "z")
COV_COLUMNS = tuple(f"cov_{COV_AXES[i]}_{COV_AXES[j]}" for i in range(6) for j in range(i, 6))
POSE_COLUMNS = ("config", "visit", "q1_deg", "q2_deg", "apex_x", "apex_y", "apex_z",
                "qw", "qx", "qy", "qz", *COV_COLUMNS)
SCAN_COLUMNS = ("config", "visit", "q1_deg", "q2_deg", "face", "x_o", "y_o", "z_o",
                "theta_deg", "d")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("platform", help="calibrate the 2-dof orientation platform (pyramid poses)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", parser_class=type(p))
    act.required = True
    s = act.add_parser("simulate", help="write a simulated calibration campaign",
                       description="Simulate a platform campaign with the true parameters of "
                                   "static_data/platform.toml [true] (or --spec): identification "
                                   "grid, validation set with repeated ISO 9283 poses.")
    s.add_argument("--out", required=True, metavar="DIR", help="campaign directory (created)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--poses", action="store_true",
                   help="write measured pyramid poses with covariance instead of face scans")
    s.add_argument("--per-face", type=int, default=8, metavar="N",
                   help="scan points per pyramid face (default 8)")
    s.add_argument("--spec", metavar="PLATFORM.toml",
                   help="nominal/true parameters, noise and design (default: packaged file)")
    s.set_defaults(func=run_simulate)
    c = act.add_parser("calibrate", help="identify the platform parameters of a campaign",
                       description="Identify the platform parameters from DIR/train.csv and "
                                   "report pose errors on DIR/validation.csv before (nominal) "
                                   "and after calibration.")
    c.add_argument("dir", metavar="DIR",
                   help="campaign directory: train.csv, validation.csv and optionally "
                        "manifest.json (written by simulate)")
    c.add_argument("--calib", metavar="H.json",
                   help="beam calibration for scan files (default: the manifest's, else "
                        "DIR/calibration.json)")
    c.add_argument("--nominal", metavar="PLATFORM.toml",
                   help="nominal parameters ([nominal]) and joint repeatability ([noise] "
                        "joint_deg) when DIR has no manifest (default: packaged file)")
    c.add_argument("--json", action="store_true", help="print exactly one JSON object")
    c.set_defaults(func=run_calibrate)


# ----------------------------------------------------------------------------- files

def _write_csv(path: Path, header: str, columns: dict[str, Any]) -> None:
    import pandas as pd

    frame = pd.DataFrame(columns)
    with path.open("w", encoding="utf-8", newline="") as fh:
        for line in header.splitlines():
            fh.write(f"# {line}\n")
        frame.to_csv(fh, index=False, float_format="%.10g")


def _visits(config: np.ndarray) -> np.ndarray:
    seen: dict[int, int] = {}
    out = np.empty(len(config), dtype=int)
    for k, c in enumerate(config):
        out[k] = seen.get(int(c), 0)
        seen[int(c)] = out[k] + 1
    return out


def write_poses(path: Path, poses: Any) -> None:
    """Pose CSV: config, visit, q, apex (mm), quaternion (w first), covariance upper triangle
    (rotation vector in deg, apex in mm: deg^2, deg mm, mm^2)."""
    from scipy.spatial.transform import Rotation

    quat = Rotation.from_matrix(poses.rotation).as_quat(scalar_first=True)
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    cols: dict[str, Any] = {"config": poses.config, "visit": _visits(poses.config),
                            "q1_deg": poses.q_deg[:, 0], "q2_deg": poses.q_deg[:, 1],
                            "apex_x": poses.apex[:, 0], "apex_y": poses.apex[:, 1],
                            "apex_z": poses.apex[:, 2], "qw": quat[:, 0], "qx": quat[:, 1],
                            "qy": quat[:, 2], "qz": quat[:, 3]}
    k = 0
    for i in range(6):
        for j in range(i, 6):
            cols[COV_COLUMNS[k]] = poses.cov[:, i, j]
            k += 1
    _write_csv(path, "measured pyramid poses of the platform campaign; mm, degrees;\n"
               "cov_*: covariance of (rotation vector e of R_meas = Exp(e) R_true, deg; apex, mm)",
               cols)


def write_scans(path: Path, scan_set: Any) -> None:
    """Scan CSV: config, visit, q, face, flange pose (x_o, y_o, z_o, theta_deg) and reading d."""
    sc = scan_set.scans
    visit = _visits(scan_set.config)[sc.row_pose]
    cols = {"config": scan_set.config[sc.row_pose], "visit": visit,
            "q1_deg": scan_set.q_deg[sc.row_pose, 0], "q2_deg": scan_set.q_deg[sc.row_pose, 1],
            "face": sc.face, "x_o": sc.position[:, 0], "y_o": sc.position[:, 1],
            "z_o": sc.position[:, 2], "theta_deg": sc.theta_deg, "d": sc.d}
    _write_csv(path, "pyramid face scans of the platform campaign; mm, degrees; one block of "
               "rows per (config, visit)", cols)


def _int_column(frame: Any, name: str, source: str) -> np.ndarray:
    from calib_core.errors import InputError
    from calib_core.io import numeric_columns

    v = numeric_columns(frame, (name,), source)[:, 0]
    if np.any(v != np.round(v)):
        raise InputError(f"{source}: column {name} must hold integers")
    return v.astype(int)


def read_poses(path: Path) -> Any:
    """A :class:`calib_core.platform.PoseSet` from a pose CSV (see :func:`write_poses`)."""
    from scipy.spatial.transform import Rotation

    from calib_core.errors import InputError
    from calib_core.io import numeric_columns, read_table
    from calib_core.platform import PoseSet

    frame = read_table(path)
    src = str(path)
    if len(frame) == 0:
        raise InputError(f"{src}: no rows")
    config = _int_column(frame, "config", src)
    q = numeric_columns(frame, ("q1_deg", "q2_deg"), src)
    apex = numeric_columns(frame, ("apex_x", "apex_y", "apex_z"), src)
    quat = numeric_columns(frame, ("qw", "qx", "qy", "qz"), src)
    norm = np.linalg.norm(quat, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        row = int(np.flatnonzero(np.abs(norm - 1.0) > 1e-3)[0])
        raise InputError(f"{src}: row {row}: quaternion is not a unit quaternion "
                         f"(norm {norm[row]:.6g})")
    tri = numeric_columns(frame, COV_COLUMNS, src)
    cov = np.zeros((len(frame), 6, 6))
    iu = np.triu_indices(6)
    cov[:, iu[0], iu[1]] = tri
    cov[:, iu[1], iu[0]] = tri
    if np.any(np.linalg.eigvalsh(cov)[:, 0] <= 0):
        row = int(np.flatnonzero(np.linalg.eigvalsh(cov)[:, 0] <= 0)[0])
        raise InputError(f"{src}: row {row}: covariance is not positive definite")
    rot = Rotation.from_quat(quat / norm[:, None], scalar_first=True).as_matrix()
    return PoseSet(config, q, rot, apex, cov)


def read_scans(path: Path, calib: Any) -> tuple[Any, tuple[str, ...]]:
    """Poses (and pyramid-fit warnings) from a scan CSV through the pyramid fit."""
    from calib_core.errors import InputError
    from calib_core.io import numeric_columns, poses_from_frame, read_table
    from calib_core.platform import poses_from_scans

    frame = read_table(path)
    src = str(path)
    if len(frame) == 0:
        raise InputError(f"{src}: no rows")
    if "face" not in frame.columns:
        raise InputError(f"{src}: missing column face (face name of each scan point)")
    config = _int_column(frame, "config", src)
    visit = _int_column(frame, "visit", src) if "visit" in frame.columns else np.zeros_like(config)
    q = numeric_columns(frame, ("q1_deg", "q2_deg"), src)
    flange = poses_from_frame(frame, src)
    d = numeric_columns(frame, ("d",), src)[:, 0]
    key = np.unique(np.column_stack([config, visit]), axis=0, return_inverse=True)[1].ravel()
    return poses_from_scans(config, q, key, flange, d, frame["face"].astype(str).str.strip()
                            .to_numpy(), calib, noise=None)


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


# ----------------------------------------------------------------------------- simulate

def run_simulate(args: argparse.Namespace) -> int:
    from calib_core.errors import InputError
    from calib_core.platform import PoseSet, forward, identify
    from drivers.sim.platform import load_spec, simulate_campaign, simulate_scan_campaign

    spec = load_spec(args.spec)
    if args.per_face < 3:
        raise InputError("--per-face must be at least 3 (points on each pyramid face)")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create the campaign directory ({exc.strerror})") from None
    if args.poses:
        camp = simulate_campaign(spec, args.seed)
        write_poses(out / "train.csv", camp.train)
        write_poses(out / "validation.csv", camp.validation)
        q_train, mode, calib_file = camp.train.q_deg, "poses", None
    else:
        scamp = simulate_scan_campaign(spec, args.seed, args.per_face)
        write_scans(out / "train.csv", scamp.train)
        write_scans(out / "validation.csv", scamp.validation)
        _write_json(out / "calibration.json", scamp.calibration.to_json_dict())
        q_train, mode, calib_file = scamp.train.q_deg, "scans", "calibration.json"
    # the true mechanism expressed in the identifiable parameters: fit of noise-free poses
    rot, apex = forward(spec.true, q_train)
    clean = PoseSet(np.arange(len(q_train)), q_train, rot, apex,
                    np.tile(np.diag([1e-6] * 3 + [1e-6] * 3), (len(q_train), 1, 1)))
    equivalent = identify(clean, spec.nominal)
    _write_json(out / "truth.json", {
        "params": spec.true,
        "identifiable_equivalent": equivalent.params,
        "fixed": [u["name"] for u in equivalent.unidentifiable],
        "note": "true parameters of the simulator; identifiable_equivalent holds the same "
                "mechanism with the unidentifiable parameters at nominal",
    })
    _write_json(out / MANIFEST, {
        "format": FORMAT, "mode": mode, "seed": args.seed, "simulated": True,
        "train": "train.csv", "validation": "validation.csv", "calibration": calib_file,
        "truth": "truth.json", "nominal": spec.nominal, "joint_sigma_deg": spec.noise.joint_deg,
        "per_face": args.per_face if mode == "scans" else None,
    })
    sys.stdout.write(f"wrote {mode} campaign to {out}: {len(q_train)} identification "
                     f"configurations, seed {args.seed}\n")
    return 0


# ----------------------------------------------------------------------------- calibrate

def _manifest(root: Path, nominal_toml: str | None) -> dict[str, Any]:
    """The manifest of ``root``, or one built from the default file names and ``nominal_toml``."""
    from calib_core.errors import InputError
    from calib_core.io import load_json_object
    from drivers.sim.platform import load_spec

    if (root / MANIFEST).exists():
        man = load_json_object(root / MANIFEST)
        if not isinstance(man, dict) or man.get("format") != FORMAT:
            raise InputError(f"{root / MANIFEST}: not a platform campaign manifest "
                             f"(expected format {FORMAT!r})")
        if nominal_toml is None:
            return man
    else:
        man = {"format": FORMAT, "train": "train.csv", "validation": "validation.csv"}
    spec = load_spec(nominal_toml)
    man = {**man, "nominal": spec.nominal, "joint_sigma_deg": spec.noise.joint_deg}
    if "mode" not in man:
        from calib_core.io import read_table

        path = root / str(man["train"])
        man["mode"] = "scans" if "face" in read_table(path).columns else "poses"
        man["calibration"] = "calibration.json"
    return man


def load_campaign(directory: str, calib_file: str | None = None,
                  nominal_toml: str | None = None) -> dict[str, Any]:
    """Nominal parameters, identification and validation pose sets of a campaign directory."""
    from calib_core.calibrate import BeamCalibration
    from calib_core.errors import InputError
    from calib_core.io import load_json_object
    from calib_core.platform import params_from_mapping

    root = Path(directory)
    if not root.is_dir():
        raise InputError(f"{root}: not a campaign directory")
    man = _manifest(root, nominal_toml)
    mode = man.get("mode")
    if mode not in ("poses", "scans"):
        raise InputError(f"{root / MANIFEST}: mode must be 'poses' or 'scans'")
    nominal = params_from_mapping(man.get("nominal") or {}, f"{root / MANIFEST} nominal")
    try:
        joint_sigma = float(man.get("joint_sigma_deg", 0.0))
    except (TypeError, ValueError):
        raise InputError(f"{root / MANIFEST}: joint_sigma_deg must be a number") from None
    if not math.isfinite(joint_sigma) or joint_sigma < 0:
        raise InputError(f"{root / MANIFEST}: joint_sigma_deg must be >= 0")
    warnings: list[str] = []
    sets = {}
    calib = None
    if mode == "scans":
        name = calib_file or man.get("calibration")
        if not name:
            raise InputError(f"{root}: scans need a beam calibration (--calib H.json)")
        calib_path = Path(calib_file) if calib_file else root / str(name)
        calib = BeamCalibration.from_json_dict(load_json_object(calib_path), str(calib_path))
    for key in ("train", "validation"):
        if not man.get(key):
            raise InputError(f"{root / MANIFEST}: missing {key!r} file name")
        path = root / str(man[key])
        if mode == "poses":
            sets[key] = read_poses(path)
        else:
            sets[key], w = read_scans(path, calib)
            warnings.extend(f"{key}: {x}" for x in w)
    return {"nominal": nominal, "joint_sigma_deg": joint_sigma, "mode": mode,
            "train": sets["train"], "validation": sets["validation"], "warnings": warnings}


def calibrate_campaign(directory: str, calib_file: str | None = None,
                       nominal_toml: str | None = None) -> dict[str, Any]:
    """The ``platform calibrate --json`` object for a campaign directory."""
    from calib_core.platform import evaluate, identify

    camp = load_campaign(directory, calib_file, nominal_toml)
    cal = identify(camp["train"], camp["nominal"], camp["joint_sigma_deg"])
    return {
        "mode": camp["mode"],
        "n_train": len(camp["train"]), "n_validation": len(camp["validation"]),
        "params": cal.params, "sigma": cal.sigma, "nominal": camp["nominal"],
        "free": list(cal.free),
        "unidentifiable": [dict(u) for u in cal.unidentifiable],
        "chi2_reduced": cal.chi2_reduced, "condition_number": cal.condition_number,
        "singular_values": [float(s) for s in cal.singular_values],
        "before": evaluate(camp["nominal"], camp["validation"]),
        "after": evaluate(cal.params, camp["validation"]),
        "warnings": [*camp["warnings"], *cal.warnings],
    }


def run_calibrate(args: argparse.Namespace) -> int:
    result = calibrate_campaign(args.dir, args.calib, args.nominal)
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(format_report(result, args.dir))
    return 0


def format_report(r: dict[str, Any], source: str) -> str:
    """Readable table of a :func:`calibrate_campaign` result."""
    lines = [f"platform calibration of {source} ({r['mode']}): {r['n_train']} identification "
             f"poses, {r['n_validation']} validation poses",
             f"reduced chi-square {r['chi2_reduced']:.3f}, condition number of the scaled "
             f"Jacobian {r['condition_number']:.3g}", "",
             f"{'parameter':<14} {'nominal':>12} {'identified':>12} {'sigma':>10}"]
    for name, value in r["params"].items():
        nom = r["nominal"][name]
        mark = "" if name in r["free"] else "  (fixed)"
        lines.append(f"{name:<14} {nom:>12.5f} {value:>12.5f} {r['sigma'][name]:>10.5f}{mark}")
    if r["unidentifiable"]:
        lines += ["", "not identifiable (kept at nominal):"]
        lines += [f"  {u['name']}: {u['reason']}" for u in r["unidentifiable"]]
    lines += ["", "validation (ISO 9283 style)        before      after"]
    rows = (("orientation mean (deg)", "orientation_mean_deg"),
            ("orientation RMS (deg)", "orientation_rms_deg"),
            ("orientation max (deg)", "orientation_max_deg"),
            ("apex mean (mm)", "apex_mean_mm"), ("apex RMS (mm)", "apex_rms_mm"),
            ("apex max (mm)", "apex_max_mm"),
            ("noise floor orientation (deg)", "noise_orientation_rms_deg"),
            ("noise floor apex (mm)", "noise_apex_rms_mm"), ("AP position (mm)", "ap_mm"),
            ("AP orientation (deg)", "ap_deg"), ("RP position (mm)", "rp_mm"),
            ("RP orientation (deg)", "rp_deg"))
    for label, key in rows:
        b, a = r["before"][key], r["after"][key]
        if b is None:
            lines.append(f"  {label:<30} {'n/a (no repeated visits)':>21}")
        else:
            lines.append(f"  {label:<30} {b:>10.5f} {a:>10.5f}")
    if r["warnings"]:
        lines += ["", "warnings:"] + [f"  {w}" for w in r["warnings"]]
    return "\n".join(lines) + "\n"
