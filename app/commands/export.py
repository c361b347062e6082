"""``lasercal export``: write a session's samples as a CSV file in the solve format."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

HELP = """\
Write the ok samples of a session file (from 'lasercal acquire') as CSV in the format
'lasercal solve' reads: columns x_o,y_o,z_o,theta_deg (pose read back from the robot),
d,x_p,y_p (mm, degrees), plus pose_index; '#' comment lines name the session. With --all,
skipped poses are listed too (columns status and reason; their measurements empty).
OUT.csv is written atomically ('-' writes to stdout). Exit status: 0 written, 2 bad input.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a session's samples as CSV (solve format)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("session", metavar="SESSION.db", help="session file")
    p.add_argument("--csv", required=True, metavar="OUT.csv", help="output CSV file, or -")
    p.add_argument("--all", action="store_true",
                   help="every stored pose with its status, reason, commanded pose and spreads")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.session import Session
    from calib_core.errors import InputError

    with Session.open(args.session, readonly=True) as session:
        meta = session.meta
        n_poses = session.n_poses()
        table = session.samples_frame() if args.all else session.frame()
        n_ok = len(session.stored_indices("ok"))
        n_stored = len(session.stored_indices())
    header = (f"# lasercal session {args.session}: {n_ok} ok and {n_stored - n_ok} skipped of "
              f"{n_poses} planned poses; created {meta.get('created', '?')}; mm and degrees\n")
    text = header + table.to_csv(index=False, float_format="%.9g", lineterminator="\n")
    if args.csv == "-":
        sys.stdout.write(text)
        return 0
    out = Path(args.csv)
    if out.is_dir():
        raise InputError(f"{out}: is a directory")
    if not out.parent.is_dir():
        raise InputError(f"{out}: directory {out.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, out)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise InputError(f"{out}: cannot write ({exc.strerror or exc})") from None
    sys.stderr.write(f"wrote {len(table)} row(s) to {out}\n")
    return 0
