"""``lasercal solve``: identify the beam H from a data file or a session."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from calib_core.calibrate import BeamCalibration
    from calib_core.io import Dataset
    from calib_core.noise import NoiseModel

HELP = """\
Identify the laser beam H (point T and direction u' in the flange frame, plus the plate tilt)
from poses pointing at a nearly level plate. Linear solution (seed eq 7-14, sign slip corrected),
then a maximum-likelihood refinement weighting every source by its 1-sigma, robust screening of
gross outliers, covariance matched to the scatter of the data, observability check.

FILE is a CSV (header; '#' comment lines; columns x_o,y_o,z_o,d,x_p,y_p and theta_deg or
qw,qx,qy,qz; mm and degrees) or a session file (.db) written by 'lasercal acquire'.
Exit status: 0 solved, 2 bad input or a pose design that cannot identify H.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("solve", help="identify the beam H from a data file or session",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", metavar="FILE", help="calibration data: CSV file or session .db")
    p.add_argument("--model", choices=("auto", "schoenflies", "general"), default="auto",
                   help="schoenflies: 4-dof robot, rotations about z (8 unknowns, z_t - delta); "
                        "general: 6-dof flange (9 unknowns); auto: by the orientation columns")
    p.add_argument("--no-robust", dest="robust", action="store_false",
                   help="plain fit: do not screen and exclude gross outliers")
    p.add_argument("--noise", metavar="NOISE.toml",
                   help="1-sigma per source (keys camera, robot_xy, robot_z, robot_theta_deg, "
                        "sensor; mm and deg; top level or [noise]); default: seed Table 2")
    p.add_argument("--holdout", type=float, metavar="FRACTION",
                   help="fit on 1-FRACTION of the poses, report statistics on the rest")
    p.add_argument("--seed", type=int, default=0, help="random seed of the hold-out split")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=run)


def load_calibration_data(path: str) -> Dataset:
    """A :class:`~calib_core.io.Dataset` from a CSV file or a session database."""
    from calib_core.io import dataset_from_frame, load_dataset

    if Path(path).suffix.lower() in (".db", ".sqlite", ".sqlite3"):
        from app.session import read_session_frame

        return dataset_from_frame(read_session_frame(path), path)
    return load_dataset(path)


def load_noise(path: str | None) -> NoiseModel:
    from calib_core.io import load_toml
    from calib_core.noise import NoiseModel

    return NoiseModel() if path is None else NoiseModel.from_mapping(load_toml(path)[0], path)


def run(args: argparse.Namespace) -> int:
    from calib_core.calibrate import solve

    noise = load_noise(args.noise)
    data = load_calibration_data(args.file)
    result = solve(data, model=args.model, noise=noise, robust=args.robust,
                   holdout=args.holdout, seed=args.seed)
    if args.json:
        json.dump(result.to_json_dict(), sys.stdout)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(format_report(result, args.file))
    return 0


def _fmt(value: float, sigma: float) -> str:
    return f"{value:+.6f} +- {sigma:.6f}" if abs(value) >= 1e-2 else f"{value:+.4e} +- {sigma:.2e}"


def format_report(result: BeamCalibration, source: str) -> str:
    """Readable table: H +- sigma, gain, conditioning, Table-1 residuals, outliers, warnings."""
    lines = [f"lasercal solve: {source}",
             f"model {result.model}, {result.n_used} of {result.n_points} poses used", "",
             "parameter          value +- 1-sigma"]
    for name, value, sigma in zip(result.names, result.values, result.sigma, strict=True):
        lines.append(f"  {name:16s} {_fmt(float(value), float(sigma))}")
    u = result.direction
    lines += ["", f"gain |u'|          {result.gain:.6f} +- {result.gain_sigma:.6f}",
              f"direction u        ({u[0]:+.6f}, {u[1]:+.6f}, {u[2]:+.6f})",
              f"condition number   {result.condition_number:.4g}",
              f"variance factors   lateral {result.variance_factors[0]:.3g}, axial "
              f"{result.variance_factors[1]:.3g} (1 = noise model confirmed)", "",
              "residuals [mm]     mean abs      RMS       max"]
    blocks = [("fit", result.residuals)]
    if result.holdout is not None:
        blocks.append((f"hold-out ({result.holdout['n']} poses)",
                       result.holdout["residuals"]))  # type: ignore[arg-type]
    for label, stats in blocks:
        if len(blocks) > 1:
            lines.append(f" {label}")
        for axis in ("x", "y", "z"):
            s = stats[axis]
            lines.append(f"  {axis}              {s['mean_abs']:9.4f} {s['rms']:9.4f} "
                         f"{s['max']:9.4f}")
    lines.append("")
    lines.append("outliers           " + (", ".join(f"row {r}" for r in result.outliers)
                                          or "none"))
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines) + "\n"
