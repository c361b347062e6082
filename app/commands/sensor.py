"""``lasercal sensor``: read or zero a Keyence IL sensor through a DL-RS1A (RS-232C)."""

from __future__ import annotations

import argparse
import math
import sys

HELP = """\
Talk to a Keyence IL-series displacement sensor through a DL-RS1A RS-232C unit (8N1).

  read  print one reading in mm (e.g. 1.234), or 'out-of-range' (beyond the measuring range)
        or 'invalid' (amplifier error or non-numeric value; the reason goes to stderr)
  zero  zero-set the amplifier (SW,<id>,001,0 / SW,<id>,001,1, then poll SR,<id>,054)

Timeouts are retried --retries times. Exit status: 0 done (also out-of-range/invalid),
2 device error (ER reply, timeout, port missing) with one 'error:' line on stderr.
"""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", required=True, help="serial port, e.g. /dev/ttyUSB0 or /dev/pts/5")
    p.add_argument("--baud", type=int, default=9600, help="baud rate (default 9600)")
    p.add_argument("--id", type=int, default=0, dest="amp_id",
                   help="amplifier ID, 0 = first amplifier (default 0)")
    p.add_argument("--timeout", type=float, default=0.5, metavar="S",
                   help="seconds to wait for each reply (default 0.5)")
    p.add_argument("--retries", type=int, default=2,
                   help="re-sends after a timeout or garbled reply (default 2)")
    p.add_argument("--command", choices=("SR", "M0"), default="SR",
                   help="read command: SR (one amplifier, default) or M0 (all amplifiers)")
    p.set_defaults(func=run)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sensor", help="read or zero a Keyence IL sensor (DL-RS1A)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION", parser_class=type(p))
    actions.required = True
    _common(actions.add_parser("read", help="print one reading in mm",
                               description="Print one reading in mm, 'out-of-range' or "
                                           "'invalid'."))
    _common(actions.add_parser("zero", help="zero-set the amplifier",
                               description="Zero-set the amplifier at the current reading."))


def run(args: argparse.Namespace) -> int:
    from calib_core.errors import InputError
    from drivers.keyence_il import KeyenceIL, describe_invalid

    if not (math.isfinite(args.timeout) and args.timeout > 0) or not 0 <= args.retries <= 100:
        raise InputError("--timeout must be a finite number of seconds > 0 and --retries "
                         "0..100")
    with KeyenceIL(args.port, baudrate=args.baud, amp_id=args.amp_id, timeout=args.timeout,
                   retries=args.retries, command=args.command) as sensor:
        if args.action == "zero":
            sensor.zero()
            print("zeroed")
            return 0
        reading = sensor.read()
    if reading.ok:
        print(f"{reading.value:.3f}")
    else:
        print(reading.status.value)
        if reading.status.value == "invalid":
            sys.stderr.write(f"note: {describe_invalid(reading)}\n")
    return 0
