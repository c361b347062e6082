"""``lasercal emulate``: serve a Keyence DL-RS1A or GRBL emulator on a pseudo-terminal."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.emulators import PtyEmulator

HELP = """\
Start a protocol emulator on a pseudo-terminal and print its device path (e.g. /dev/pts/5)
on its own line; then serve until Ctrl-C or SIGTERM. Point the hardware commands at it:

  lasercal emulate keyence --value 1.234 &     ->  lasercal sensor read --port /dev/pts/5
  lasercal emulate grbl --move-time 0.5 &      ->  lasercal robot move --port /dev/pts/6 ...

keyence: DL-RS1A with IL amplifier(s) reading a constant displacement (--value mm, or
--out-of-range); zero-set works. grbl: GRBL 1.1 with axes X Y Z A that moves to each target
in --move-time seconds and reports its own position. cell: both, on the simulated workcell
physics (the sensor reads the beam's distance to the plates at the GRBL's pose); prints the
GRBL path, then the Keyence path, each on its own line.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", help="serve a Keyence or GRBL protocol emulator on a pty",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    devices = p.add_subparsers(dest="device", metavar="DEVICE", parser_class=type(p))
    devices.required = True
    k = devices.add_parser("keyence", help="Keyence DL-RS1A + IL amplifier",
                           description="Keyence DL-RS1A emulator with a constant displacement.")
    group = k.add_mutually_exclusive_group()
    group.add_argument("--value", type=float, default=0.0, metavar="MM",
                       help="displacement reported (mm, default 0)")
    group.add_argument("--out-of-range", action="store_true",
                       help="report +99.999 (nothing in range)")
    k.add_argument("--amplifiers", type=int, default=1, metavar="N",
                   help="number of amplifiers (IDs 0..N-1, default 1)")
    k.set_defaults(func=run)
    g = devices.add_parser("grbl", help="GRBL 1.1 robot controller (X Y Z A)",
                           description="GRBL 1.1 emulator that reports its own position.")
    g.add_argument("--move-time", type=float, default=0.0, metavar="S",
                   help="seconds per move (default 0: instantaneous)")
    g.set_defaults(func=run)
    c = devices.add_parser("cell", help="GRBL + Keyence on the simulated workcell physics",
                           description="GRBL and Keyence emulators sharing the simulated "
                                       "workcell; prints the GRBL path, then the Keyence path.")
    c.add_argument("--workcell", metavar="FILE.toml",
                   help="workcell file (default: the packaged seed cell)")
    c.add_argument("--seed", type=int, default=0, help="random seed of the sensor noise")
    c.add_argument("--move-time", type=float, default=0.0, metavar="S",
                   help="seconds per move (default 0: instantaneous)")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import math

    from calib_core.errors import InputError
    from drivers.emulators import GrblEmulator, KeyenceEmulator

    if args.device != "keyence" and not (math.isfinite(args.move_time) and args.move_time >= 0):
        raise InputError("--move-time must be >= 0 seconds")
    if args.device == "cell":
        from drivers.emulators import CellEmulators
        from drivers.sim.workcell import load_workcell
        from drivers.sim.world import SimWorld

        cell = CellEmulators(SimWorld(load_workcell(args.workcell), seed=args.seed),
                             move_time=args.move_time)
        return _serve([cell.grbl, cell.keyence])
    if args.device == "keyence":
        if not 1 <= args.amplifiers <= 9 or not math.isfinite(args.value):
            raise InputError("--amplifiers must be 1..9 and --value finite")
        value = None if args.out_of_range else args.value
        emulator = KeyenceEmulator(lambda: value, amp_ids=tuple(range(args.amplifiers)))
    else:
        emulator = GrblEmulator(move_time=args.move_time)
    return _serve([emulator])


def _serve(emulators: list[PtyEmulator]) -> int:
    """Start, print each device path on its own line, serve until SIGINT/SIGTERM."""
    done = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: done.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for emulator in emulators:
            emulator.start()
        for emulator in emulators:
            print(emulator.path, flush=True)
            sys.stderr.write(f"{emulator.device} emulator serving on {emulator.path}\n")
        sys.stderr.write("Ctrl-C or SIGTERM to stop\n")
        while not done.wait(0.5):
            pass
    finally:
        for emulator in emulators:
            emulator.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
