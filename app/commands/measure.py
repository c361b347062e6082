"""``lasercal measure``: planes, Johansson gauges and the pyramid pose with a calibrated sensor."""

from __future__ import annotations

import argparse
import json
import sys

HELP = """\
Measure with a calibrated sensor (seed eq 16-20). Each scan row is a flange pose plus a reading:
P = O + R (T + d u'), with T, u' from the calibration file (the JSON of 'lasercal solve --json').
A Schoenflies (4-dof) calibration only knows z_t - delta, so every z (and plane offset, apex z)
is the height above the calibration plate's datum; a general (6-dof) one gives robot-frame z.
Uncertainties propagate the scan noise (seed Table 2, or --noise) and the calibration covariance.

Scan files: CSV like the solve format: x_o,y_o,z_o,d and theta_deg or qw,qx,qy,qz (mm, deg);
optional x_p,y_p (camera spot: compared like the seed's Tables 3-4), face (pyramid face name).
Exit status: 0 done, 2 bad input.
"""

GAUGE_HELP = """\
Johansson gauge check: blocks of known height on the calibration plate under the spot. The
least-squares slope of (gauge_height - z_o + alpha x_P + beta y_P) against d estimates c (the
beam's vertical component); with --calib it is compared with the calibrated c in sigmas.
FILE columns: gauge_height (mm, the block under the spot; 0 for the bare plate), d, and the pose
x_o,y_o,z_o with theta_deg (or qw,qx,qy,qz, all with the same tilt). At least 3 rows.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("measure", help="measure planes, gauges and the pyramid pose",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    msub = p.add_subparsers(dest="what", metavar="WHAT", parser_class=type(p))
    msub.required = True

    plane = msub.add_parser("plane", help="fit a plane to a scan (seed eq 17-20)",
                            description=HELP,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    plane.add_argument("scan", metavar="SCAN", help="scan CSV file")
    _common(plane, calib_required=True)
    plane.add_argument("--fit", choices=("ls", "orthogonal"), default="ls",
                       help="ls: seed eq 20, z = alpha x + beta y + offset by vertical least "
                            "squares (default); orthogonal: total least squares, for steep planes")
    plane.set_defaults(func=run_plane)

    gauges = msub.add_parser("gauges", help="estimate c from Johansson gauge readings",
                             description=GAUGE_HELP,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
    gauges.add_argument("file", metavar="FILE", help="gauge CSV file")
    _common(gauges, calib_required=False)
    gauges.set_defaults(func=run_gauges)

    pyr = msub.add_parser("pyramid", help="pose of the pyramid from scans of its three faces",
                          description=HELP + "\nEach row needs a 'face' column naming the face "
                          "(A, B, C in the default geometry); at least 3 points per face.",
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    pyr.add_argument("scan", metavar="SCAN", help="scan CSV file with a face column")
    _common(pyr, calib_required=True)
    pyr.add_argument("--geometry", metavar="PYRAMID.toml",
                     help="nominal pyramid (default: the packaged static_data/pyramid.toml)")
    pyr.set_defaults(func=run_pyramid)


def _common(p: argparse.ArgumentParser, calib_required: bool) -> None:
    p.add_argument("--calib", metavar="H.json", required=calib_required,
                   help="calibration file (the JSON printed by 'lasercal solve --json')")
    p.add_argument("--noise", metavar="NOISE.toml",
                   help="1-sigma per source (robot_xy, robot_z, robot_theta_deg, sensor; mm, "
                        "deg); default: seed Table 2")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")


def load_calibration(path: str):
    """The :class:`~calib_core.calibrate.BeamCalibration` in a ``solve --json`` file."""
    from calib_core.calibrate import BeamCalibration
    from calib_core.io import load_json_object

    return BeamCalibration.from_json_dict(load_json_object(path), path)


def _check_model(calib, poses, source: str) -> None:
    from calib_core.errors import InputError

    if calib.model == "schoenflies" and not poses.is_rotation_about_z:
        raise InputError(f"{source}: the calibration is Schoenflies (z_t unknown) but the scan "
                         "tilts the flange; only rotations about z can be reconstructed")


def _z_reference(calib) -> str:
    return ("height above the calibration plate datum (z_P - delta)"
            if calib.model == "schoenflies" else "robot frame")


def _emit(args: argparse.Namespace, obj: dict[str, object], text: str) -> int:
    if args.json:
        json.dump(obj, sys.stdout)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(text)
    return 0


def run_plane(args: argparse.Namespace) -> int:
    from app.commands.solve import load_noise
    from calib_core.io import load_dataset
    from calib_core.measure import compare_with_camera, fit_scan_plane, reconstruct

    noise = load_noise(args.noise)
    calib = load_calibration(args.calib)
    data = load_dataset(args.scan, need_spot=False, min_rows=3)
    _check_model(calib, data.poses, args.scan)
    scan = reconstruct(data.poses, data.d, calib, noise)
    fit = fit_scan_plane(scan, args.fit)
    out = fit.to_json_dict()
    out["z_reference"] = _z_reference(calib)
    if data.spot_xy is not None:
        out["comparison"] = compare_with_camera(scan.xyz, data.spot_xy, fit)
    sig = fit.sigma
    lines = [f"lasercal measure plane: {args.scan} ({fit.n_points} points, {fit.method} fit)",
             f"z reference: {out['z_reference']}", "",
             "plane z = alpha x + beta y + offset    value +- 1-sigma",
             f"  alpha        {fit.alpha:+.6e} +- {sig['alpha']:.2e}",
             f"  beta         {fit.beta:+.6e} +- {sig['beta']:.2e}",
             f"  offset [mm]  {fit.offset:+.6f} +- {sig['offset']:.6f}",
             "  normal       ({:+.6f}, {:+.6f}, {:+.6f})".format(*fit.normal),
             f"  rms [mm]     {fit.rms:.4f}   chi2/dof {fit.chi2_reduced:.3g}"]
    if "comparison" in out:
        cmp = out["comparison"]
        cam, diff = cmp["camera_plane"], cmp["difference"]  # type: ignore[index]
        lines += ["", "vs camera (seed Table 3)   scanner        camera         difference"]
        for key, val in (("alpha", fit.alpha), ("beta", fit.beta), ("offset", fit.offset)):
            lines.append(f"  {key:8s}                {val:+.6e}  {cam[key]:+.6e}  "
                         f"{diff[key]:+.3e}")
        lines += ["", "point errors [mm] (Table 4)  mean abs      RMS       max"]
        for axis, s in cmp["point_errors"].items():  # type: ignore[index]
            lines.append(f"  {axis}                       {s['mean_abs']:8.4f} {s['rms']:9.4f} "
                         f"{s['max']:9.4f}")
    lines += [f"warning: {w}" for w in fit.warnings]
    return _emit(args, out, "\n".join(lines) + "\n")


def run_gauges(args: argparse.Namespace) -> int:
    from app.commands.solve import load_noise
    from calib_core.io import load_dataset, numeric_columns
    from calib_core.measure import gauge_check

    noise = load_noise(args.noise)
    calib = load_calibration(args.calib) if args.calib else None
    data = load_dataset(args.file, need_spot=False, min_rows=3)
    heights = numeric_columns(data.extra, ("gauge_height",), args.file)[:, 0]
    if calib is not None:
        _check_model(calib, data.poses, args.file)
    res = gauge_check(data.poses, data.d, heights, calib, noise)
    lines = [f"lasercal measure gauges: {args.file} ({res.n_readings} readings)", "",
             f"  c (gauges)       {res.c:.6f} +- {res.c_sigma:.6f}",
             f"  intercept [mm]   {res.intercept:+.4f}",
             f"  residual rms     {res.residual_rms:.4f} mm   chi2/dof {res.chi2_reduced:.3g}"]
    if res.c_calibrated is not None:
        lines += [f"  c (calibration)  {res.c_calibrated:.6f} +- {res.c_calibrated_sigma:.6f}",
                  f"  agreement        {res.agreement_sigmas:.2f} sigma"]
    lines += [f"warning: {w}" for w in res.warnings]
    return _emit(args, res.to_json_dict(), "\n".join(lines) + "\n")


def run_pyramid(args: argparse.Namespace) -> int:
    from app.commands.solve import load_noise
    from calib_core.errors import InputError
    from calib_core.io import load_dataset
    from calib_core.measure import reconstruct
    from calib_core.pyramid import load_geometry, measure_pyramid

    noise = load_noise(args.noise)
    calib = load_calibration(args.calib)
    geometry = load_geometry(args.geometry)
    data = load_dataset(args.scan, need_spot=False, min_rows=9)
    if "face" not in data.extra.columns:
        raise InputError(f"{args.scan}: missing column face (the pyramid face of each point: "
                         f"{', '.join(geometry.face_names)})")
    _check_model(calib, data.poses, args.scan)
    scan = reconstruct(data.poses, data.d, calib, noise)
    labels = data.extra["face"].astype(str).to_numpy()
    try:
        pose = measure_pyramid(scan, labels, geometry)
    except InputError as exc:
        raise InputError(f"{args.scan}: {exc}") from None
    out = pose.to_json_dict()
    out["z_reference"] = _z_reference(calib)
    lines = [f"lasercal measure pyramid: {args.scan} ({pose.n_points} points)",
             f"z reference: {out['z_reference']}", "",
             "                  x            y            z       (rotation vector in deg)",
             "  apex [mm]   {:+11.4f}  {:+11.4f}  {:+11.4f}".format(*pose.apex),
             "  +- 1-sigma  {:11.4f}  {:11.4f}  {:11.4f}".format(*pose.apex_sigma),
             "  rot. vector {:+11.4f}  {:+11.4f}  {:+11.4f}".format(*pose.rotvec_deg),
             "  +- 1-sigma  {:11.4f}  {:11.4f}  {:11.4f}".format(*pose.rotation_sigma_deg),
             "  quaternion (w, x, y, z) ({:+.6f}, {:+.6f}, {:+.6f}, {:+.6f})".format(
                 *pose.quaternion), ""]
    names = geometry.face_names
    for k, e in enumerate(pose.edges):
        lines.append(f"  edge {names[k]}{names[(k + 1) % 3]}     "
                     "({:+.5f}, {:+.5f}, {:+.5f})".format(*e))
    lines.append("  face rms [mm] " + ", ".join(
        f"{n} {r:.4f}" for n, r in zip(names, pose.face_rms, strict=True)))
    lines.append(f"  residual rms {pose.residual_rms:.4f} mm   chi2/dof {pose.chi2_reduced:.3g}")
    lines += [f"warning: {w}" for w in pose.warnings]
    return _emit(args, out, "\n".join(lines) + "\n")
