"""``lasercal robot``: move a GRBL robot, read its pose, clear an alarm."""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

#: Used when no workcell file is found or given (and said so in --help).
DEFAULT_LIMITS: dict[str, Any] = {"x": (-1000.0, 1000.0), "y": (-1000.0, 1000.0),
                                  "z": (-1000.0, 1000.0), "theta_deg": (-360.0, 360.0),
                                  "max_step": math.inf}
DEFAULT_WORKCELL = "workcell_default.toml"

LIMITS_HELP = f"""\
Soft limits: a move outside them is refused before anything is sent. They come from the
[limits] table (x, y, z, theta_deg as [lo, hi]; max_step) of --workcell FILE.toml, else of the
packaged static_data/{DEFAULT_WORKCELL}; if neither exists, generous defaults apply:
x, y, z in [-1000, 1000] mm, theta in [-360, 360] deg (a note says so on stderr)."""

HELP = f"""\
Drive a robot behind a GRBL 1.1 controller (115200 8N1; axes X Y Z in mm, A = theta in deg).

  move    G90 G1 X.. Y.. Z.. A.. F.., wait for the end of motion (G4 P0), print the pose
          read back ('?' status report, work coordinates)
  pose    print the current pose
  unlock  clear an alarm lock ($X) after checking the machine

{LIMITS_HELP}

Output: 'x=10.000 y=-20.500 z=30.250 theta=45.000'. Exit status: 0 done, 2 refused target,
controller error/alarm or timeout, with one 'error:' line on stderr.
"""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", required=True, help="serial port, e.g. /dev/ttyACM0 or /dev/pts/6")
    p.add_argument("--baud", type=int, default=115200, help="baud rate (default 115200)")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S",
                   help="seconds to wait for each reply (default 1)")
    p.add_argument("--retries", type=int, default=2,
                   help="re-sends after a timeout or garbled reply (default 2)")
    p.add_argument("--workcell", metavar="FILE.toml", help="workcell file with the [limits]")
    p.set_defaults(func=run)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("robot", help="move a GRBL robot or read its pose",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION", parser_class=type(p))
    actions.required = True
    move = actions.add_parser("move", help="move to a pose and print the pose read back",
                              description="Move to (x, y, z, theta), wait for the end of motion, "
                                          "print the pose read back.\n\n" + LIMITS_HELP,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    for axis, unit in (("x", "mm"), ("y", "mm"), ("z", "mm"), ("theta", "deg")):
        move.add_argument(f"--{axis}", type=float, required=True, help=f"target {axis} ({unit})")
    move.add_argument("--feed", type=float, default=1000.0, help="feed rate mm/min (default 1000)")
    move.add_argument("--move-timeout", type=float, metavar="S",
                      help="seconds allowed for the move (default 10 + 3x its nominal time)")
    _common(move)
    _common(actions.add_parser("pose", help="print the current pose",
                               description="Print the current pose (work coordinates)."))
    _common(actions.add_parser("unlock", help="clear an alarm lock ($X)",
                               description="Send $X to clear an alarm lock."))


def _pair(value: Any, key: str, source: str) -> tuple[float, float]:
    from calib_core.errors import InputError

    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{source}: [limits] {key} must be [lo, hi] numbers") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise InputError(f"{source}: [limits] {key}: need finite lo < hi")
    return lo, hi


def load_limits(path: str | None):  # -> (SoftLimits, str)
    """Soft limits from the ``[limits]`` table of ``path`` or of the packaged default workcell.

    Returns (limits, source); source is "" when the generous defaults were used.
    """
    import tomllib
    from importlib import resources

    from calib_core.errors import InputError
    from drivers.base import SoftLimits

    if path is not None:
        source = path
        try:
            with open(path, "rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise InputError(f"{path}: no such workcell file") from None
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: cannot read the workcell file ({exc})") from None
    else:
        source = f"static_data/{DEFAULT_WORKCELL}"
        ref = resources.files("static_data").joinpath(DEFAULT_WORKCELL)
        if not ref.is_file():
            return SoftLimits(**DEFAULT_LIMITS), ""
        try:
            data = tomllib.loads(ref.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{source}: cannot read the workcell file ({exc})") from None
    table = data.get("limits")
    if not isinstance(table, dict):
        raise InputError(f"{source}: no [limits] table")
    boxes = {key: _pair(table.get(key), key, source) for key in ("x", "y", "z", "theta_deg")}
    max_step = table.get("max_step", math.inf)
    if isinstance(max_step, bool) or not isinstance(max_step, int | float) or max_step <= 0:
        raise InputError(f"{source}: [limits] max_step must be a number > 0")
    return SoftLimits(**boxes, max_step=float(max_step)), source


def format_pose(pose) -> str:
    return f"x={pose.x:.3f} y={pose.y:.3f} z={pose.z:.3f} theta={pose.theta_deg:.3f}"


def run(args: argparse.Namespace) -> int:
    from calib_core.errors import InputError
    from drivers.base import FlangePose
    from drivers.grbl import GrblRobot

    if not (math.isfinite(args.timeout) and args.timeout > 0) or not 0 <= args.retries <= 100:
        raise InputError("--timeout must be a finite number of seconds > 0 and --retries "
                         "0..100")
    limits, source = load_limits(args.workcell)
    if not source:
        sys.stderr.write("note: no workcell file; generous default soft limits apply "
                         "(x, y, z in [-1000, 1000] mm, theta in [-360, 360] deg)\n")
    feed = getattr(args, "feed", 1000.0)
    if not (math.isfinite(feed) and feed > 0):
        raise InputError("--feed must be > 0 mm/min")
    move_timeout = getattr(args, "move_timeout", None)
    if move_timeout is not None and not (math.isfinite(move_timeout) and move_timeout > 0):
        raise InputError("--move-timeout must be a finite number of seconds > 0")
    target = None
    if args.action == "move":
        target = FlangePose(args.x, args.y, args.z, args.theta)
        limits.check(target)  # refuse before even opening the port
    with GrblRobot(args.port, limits, baudrate=args.baud, timeout=args.timeout,
                   retries=args.retries, feed=feed,
                   move_timeout=move_timeout) as robot:
        if args.action == "unlock":
            robot.unlock()
            print("unlocked")
            return 0
        pose = robot.read_pose() if target is None else robot.move_to(target)
    print(format_pose(pose))
    return 0
