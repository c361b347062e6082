"""``lasercal serve``: the browser dashboard (viser) behind the token + Origin guard."""

from __future__ import annotations

import argparse
import signal
import socket
import threading
from pathlib import Path

HELP = """\
Serve the calibration dashboard: a live 3-D view of the workcell and a guided flow
(Setup, Jog, Grid, Acquire, Solve, Export) in the browser.

Without hardware the simulated cell runs (the default, or --sim). --session FILE.db opens an
existing session for review (no hardware needed) or continues it; new samples go to that
file, or to lasercal-session-<time>.db in the current directory.

Security: the dashboard can move the robot. It listens on 127.0.0.1 unless --host says
otherwise (then a warning is printed); the URL printed at start-up carries a random token
(exchanged for a cookie); every request without it, or from another web site, gets 403.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve the calibration dashboard in the browser",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sim", action="store_true",
                   help="simulated workcell (the default while no hardware is configured)")
    p.add_argument("--hardware", action="store_true",
                   help="start without the simulator; connect the devices in the Setup tab")
    p.add_argument("--workcell", metavar="FILE.toml",
                   help="workcell description (default: the packaged seed cell)")
    p.add_argument("--session", metavar="FILE.db", type=Path,
                   help="session file to review or continue (created on the first acquisition "
                        "if it does not exist)")
    p.add_argument("--host", default="127.0.0.1",
                   help="interface to listen on (default 127.0.0.1; any other prints a warning)")
    p.add_argument("--port", type=int, default=8080,
                   help="port to listen on (default 8080; 0 picks a free port)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated cell")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.panels import build_dashboard
    from app.server import GuardedServer
    from calib_core.errors import InputError
    from drivers.sim.workcell import load_workcell

    if args.sim and args.hardware:
        raise InputError("give either --sim or --hardware, not both")
    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in 0..65535, got {args.port}")
    try:  # an unknown host name is the operator's typo, not a server failure
        if args.host.strip("[]"):  # '' binds every interface
            socket.getaddrinfo(args.host.strip("[]"), args.port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise InputError(f"--host {args.host!r}: not an address or known host name "
                         f"({exc})") from None
    if args.session is not None:
        if args.session.is_dir():
            raise InputError(f"{args.session}: is a directory, expected a session file")
        if not args.session.exists() and not args.session.parent.is_dir():
            raise InputError(f"{args.session}: directory {args.session.parent} does not exist")
        if args.session.exists():
            from app.session import Session
            Session.open(args.session, readonly=True).close()  # damaged/foreign: error now
    workcell = load_workcell(args.workcell)
    server = GuardedServer(args.host, args.port, label="lasercal")
    try:
        server.start()
        app = build_dashboard(server.viser, workcell, sim=not args.hardware,
                              session_path=args.session, seed=args.seed)
        server.announce()
        done = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        done.wait()
        app.worker.stop(timeout=5)
        app.close_session()
        app.disconnect()
    finally:
        server.stop()
    return 0
