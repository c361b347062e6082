"""``lasercal report``: a calibration report (HTML, PDF, JSON, CSV) from a session or data file."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = """\
Write a calibration report an engineer can review and sign: header (what, when, operator note,
workcell, hardware or simulated, driver and software versions, SHA-256 of the data file, noise
model), the beam H +- sigma, gain and direction, correlation matrix (|rho| > 0.8 flagged),
conditioning, residuals like the seed's Table 1 (fit and hold-out sets) against the noise floor
expected from the noise model, excluded outliers and why, warnings in plain words, plots, and a
signature block.

SOURCE is a session file (.db) or a CSV data file. H is solved from it (same options as
'lasercal solve') unless --calib gives a calibration file; then every pose is evaluated with it.

--out FILE.html  one self-contained HTML file (no network needed to view it)
--out FILE.pdf   the same content as PDF
--out DIR        DIR/report.html, report.pdf, calibration.json (solve --json + report block;
                 usable as --calib), residuals.csv (per pose, mm)

Exit status: 0 written, 2 bad input.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write a calibration report (HTML, PDF, JSON, CSV)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", metavar="SESSION.db|DATA.csv", help="session file or CSV data")
    p.add_argument("--out", required=True, metavar="FILE.html|FILE.pdf|DIR",
                   help="output file (by extension) or directory (all four files)")
    p.add_argument("--calib", metavar="H.json",
                   help="use this calibration instead of solving; residuals evaluated with it")
    p.add_argument("--model", choices=("auto", "schoenflies", "general"), default="auto",
                   help="beam model, as for 'lasercal solve'")
    p.add_argument("--no-robust", dest="robust", action="store_false",
                   help="plain fit: do not screen and exclude gross outliers")
    p.add_argument("--noise", metavar="NOISE.toml",
                   help="1-sigma per source (as for 'lasercal solve'); default: seed Table 2")
    p.add_argument("--holdout", type=float, metavar="FRACTION",
                   help="fit on 1-FRACTION of the poses, report the rest as a hold-out set")
    p.add_argument("--seed", type=int, default=0, help="random seed of the hold-out split")
    p.add_argument("--note", default="", metavar="TEXT", help="operator note for the header")
    p.add_argument("--measure", action="append", default=[], metavar="RESULT.json",
                   help="add a section from a 'lasercal measure ... --json' or 'platform "
                        "calibrate --json' output (repeatable)")
    p.add_argument("--platform", metavar="DIR",
                   help="add the platform calibration of campaign DIR (as 'platform calibrate')")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.commands.solve import load_calibration_data, load_noise
    from app.report import render_bundle, write_report
    from app.report.data import build_report, evaluate_calibration, section_from_json, source_meta
    from calib_core.calibrate import BeamCalibration, solve
    from calib_core.errors import InputError
    from calib_core.io import load_json_object

    if args.calib and (args.holdout is not None or args.noise):
        raise InputError("--calib evaluates a given calibration: --holdout and --noise do not "
                         "apply (the calibration file carries its noise model)")
    out = Path(args.out)
    if out.suffix.lower() in (".html", ".htm", ".pdf") and not out.parent.is_dir():
        raise InputError(f"{out}: directory {out.parent} does not exist")
    sections = []
    for path in args.measure:
        data = load_json_object(path)
        sections.append(section_from_json(data, path))
    if args.platform:
        from app.commands.platform import calibrate_campaign

        sections.append(section_from_json(calibrate_campaign(args.platform), args.platform))

    data = load_calibration_data(args.source)
    meta = source_meta(args.source, args.note)
    if args.calib:
        raw = load_json_object(args.calib)
        result = evaluate_calibration(BeamCalibration.from_json_dict(raw, args.calib), data, raw)
        meta.update(calibration_mode="evaluated",
                    calibration_source=f"given: {args.calib} (not fitted to this data; "
                                       "every pose evaluated with it)")
    else:
        result = solve(data, model=args.model, noise=load_noise(args.noise), robust=args.robust,
                       holdout=args.holdout, seed=args.seed)
        meta.update(calibration_mode="solved", calibration_source="solved from this data",
                    options={"model": result.model, "robust": args.robust,
                             "holdout": args.holdout, "seed": args.seed,
                             "noise file": args.noise or "default (seed Table 2)"})
    suffix = out.suffix.lower()
    formats = ("html",) if suffix in (".html", ".htm") else ("pdf",) if suffix == ".pdf" else (
        "html", "pdf", "json", "csv")
    files = render_bundle(build_report(result, data, meta, sections), formats)
    for path in write_report(files, out):
        print(path)
    return 0
