"""``lasercal acquire``: run a calibration session into a crash-safe session file."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import time
from pathlib import Path
from typing import Any, TextIO

HELP = """\
Move the robot through a pose grid, read the displacement sensor and the spot camera at every
pose (several readings averaged), and store each pose's sample in the session file (SQLite)
the moment it is taken. A kill or power cut loses at most the pose in flight; --resume goes on
where the session stopped without measuring stored poses again. Solve with
'lasercal solve SESSION.db'; export with 'lasercal export SESSION.db --csv OUT.csv'.

Devices: the simulated workcell (--sim, the default when no hardware option is given; the
workcell file sets the true beam, plate, noise and soft limits), or hardware: a GRBL robot
(--robot-port), a Keyence IL sensor on a DL-RS1A (--sensor-port) and a camera (--camera with
its --camera-calib); soft limits from the [limits] table of --workcell (else the packaged cell).
Invalid readings (sensor out of range, no spot) are retried, then the pose is stored as
skipped with the reason. A device error stops the run with a message; the session keeps every
stored pose; continue with --resume. Ctrl-C stops cleanly the same way.

Progress goes to stderr; a summary line to stdout. Exit status: 0 done, 2 bad input or device
error, 130 interrupted.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("acquire", help="run a calibration session (simulated or hardware)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", required=True, metavar="FILE.db",
                   help="session file to create (refused if it exists, unless --resume)")
    p.add_argument("--resume", action="store_true",
                   help="continue an existing session: grid, workcell and settings from the file")
    p.add_argument("--retry-skipped", action="store_true",
                   help="with --resume: measure the skipped poses again")
    p.add_argument("--grid", metavar="paper|FILE.csv",
                   help="pose grid: 'paper' (the seed's 42 poses: 4x3 x-y grid at z=15,20,25 "
                        "mm plus 6 rotations -6..6 deg; the default) or a CSV with x_o,y_o,z_o,"
                        "theta_deg")
    p.add_argument("--preview", action="store_true",
                   help="print the grid's poses and exit (nothing moves, nothing is written)")
    p.add_argument("--samples", type=int, metavar="K",
                   help="sensor and camera readings averaged per pose (default 3)")
    p.add_argument("--settle", type=float, metavar="S",
                   help="wait after each move before reading, seconds (default 0 simulated, "
                        "0.3 hardware)")
    p.add_argument("--retries", type=int, metavar="N",
                   help="re-reads of an invalid measurement before the pose is skipped "
                        "(default 2)")
    p.add_argument("--max-skips-in-a-row", type=int, metavar="N",
                   help="stop when N poses in a row cannot be measured (a faulty device; the "
                        "last one is measured again on --resume); 0: never (default 3)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    sim = p.add_argument_group("simulated workcell")
    sim.add_argument("--sim", action="store_true",
                     help="use the simulated workcell (default when no hardware is given)")
    sim.add_argument("--workcell", metavar="FILE.toml",
                     help="workcell file (default: the packaged seed cell); with hardware it "
                          "is stored in the session (noise, limits)")
    sim.add_argument("--seed", type=int, help="random seed of the simulation (default 0)")
    sim.add_argument("--move-time", type=float, metavar="S",
                     help="simulated duration of one move (default: from the workcell file)")
    sim.add_argument("--sim-camera", choices=("rendered", "direct"), default="rendered",
                     help="rendered: images through the OpenCV spot detector (default); "
                          "direct: the simulated measurement without images (fast)")
    hw = p.add_argument_group("hardware")
    hw.add_argument("--robot-port", metavar="PORT", help="GRBL robot serial port")
    hw.add_argument("--robot-baud", type=int, default=115200, help="robot baud rate")
    hw.add_argument("--sensor-port", metavar="PORT", help="Keyence DL-RS1A serial port")
    hw.add_argument("--sensor-baud", type=int, default=9600, help="sensor baud rate")
    hw.add_argument("--sensor-id", type=int, default=0, help="Keyence amplifier ID")
    hw.add_argument("--camera", metavar="INDEX|URL", help="camera (cv2.VideoCapture source)")
    hw.add_argument("--camera-calib", metavar="FILE.json",
                    help="camera calibration JSON (camera_matrix, dist_coeffs, homography: "
                         "pixels -> plate mm); required with --camera")
    p.set_defaults(func=run)


class ProgressBar:
    """A one-line progress bar on a terminal, else one line per stored pose."""

    def __init__(self, stream: TextIO, quiet: bool = False) -> None:
        self.stream = stream
        self.quiet = quiet
        self.tty = stream.isatty()
        self._printed = 0

    def __call__(self, p: Any) -> None:
        if self.quiet:
            return
        if p.state == "running" and (p.current is None or p.done == self._printed):
            return
        if p.state == "finished" and not self.tty:
            return
        self._printed = p.done
        width = 30
        filled = round(width * p.fraction)
        eta = "" if p.eta_s is None else f" eta {p.eta_s:5.1f} s"
        last = ""
        if p.last is not None:
            s = p.last
            last = (f" | pose {s.pose_index}: d={s.d:+.4f} x_p={s.x_p:.4f} y_p={s.y_p:.4f}"
                    if s.ok else f" | pose {s.pose_index} skipped: {s.reason}")
        skipped = f" ({p.skipped} skipped)" if p.skipped else ""
        line = (f"[{'#' * filled}{'.' * (width - filled)}] {p.done}/{p.total}{skipped}"
                f"{eta}{last}")
        if self.tty:
            self.stream.write("\r\x1b[2K" + line[:160])
            if p.state != "running":
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _parse_workcell(text: str, source: str) -> Any:
    """The :class:`~drivers.sim.workcell.Workcell` of a TOML text; errors name ``source``."""
    import tomllib

    from calib_core.errors import InputError
    from drivers.sim.workcell import workcell_from_mapping

    try:
        return workcell_from_mapping(tomllib.loads(text), source)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({exc})") from None


def _sim_devices(args: argparse.Namespace, workcell_text: str, source: str,
                 seed: int) -> tuple[Any, Any, Any, Any]:
    from drivers.sim import devices
    from drivers.sim.world import SimWorld

    workcell = _parse_workcell(workcell_text, source)
    world = SimWorld(workcell, seed=seed)
    robot = devices.SimRobot(world, move_time_s=args.move_time)
    sensor = devices.SimSensor(world)
    rendered = getattr(devices, "SimCamera", None)
    if args.sim_camera == "rendered" and rendered is not None:
        camera = rendered(world, seed=seed)
    else:
        camera = devices.SimCameraDirect(world)
    return workcell, robot, sensor, camera


def _hardware_devices(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """Open the GRBL robot, the Keyence sensor and the OpenCV camera (closed again on error)."""
    import json

    from calib_core.errors import InputError

    missing = [flag for flag, value in (("--robot-port", args.robot_port),
                                        ("--sensor-port", args.sensor_port),
                                        ("--camera", args.camera),
                                        ("--camera-calib", args.camera_calib)) if value is None]
    if missing:
        raise InputError(f"hardware acquisition needs {', '.join(missing)} too "
                         "(or use --sim)")
    try:
        from app.commands.robot import load_limits
        from drivers.camera_cv import OpenCVCamera, PixelToPlate
        from drivers.grbl import GrblRobot
        from drivers.keyence_il import KeyenceIL
    except ImportError as exc:
        raise InputError(f"hardware driver not available in this installation ({exc})") from None
    try:
        mapping = PixelToPlate.from_json_dict(json.loads(
            Path(args.camera_calib).read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{args.camera_calib}: cannot read the camera calibration "
                         f"({exc})") from None
    limits, _ = load_limits(args.workcell)
    opened: list[Any] = []
    try:
        opened.append(GrblRobot(args.robot_port, limits, baudrate=args.robot_baud))
        opened.append(KeyenceIL(args.sensor_port, baudrate=args.sensor_baud,
                                amp_id=args.sensor_id))
        source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
        opened.append(OpenCVCamera(source, mapping=mapping))
    except BaseException:
        for device in opened:
            with contextlib.suppress(Exception):
                device.close()
        raise
    return opened[0], opened[1], opened[2]


def _noise_of(text: str, source: str) -> dict[str, float]:
    """The ``[noise]`` table of a (possibly partial) workcell text, else the seed's Table 2."""
    import tomllib

    from calib_core.errors import InputError
    from calib_core.noise import NoiseModel

    try:
        data = tomllib.loads(text) if text else {}
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({exc})") from None
    if "noise" not in data:
        return NoiseModel().as_dict()
    return NoiseModel.from_mapping(data, source).as_dict()


def _workcell_text(path: str | None) -> tuple[str, str]:
    """(TOML text, source name) of ``path`` or of the packaged default workcell."""
    from importlib import resources

    from calib_core.errors import InputError

    if path is None:
        from drivers.sim.workcell import DEFAULT_WORKCELL

        ref = resources.files("static_data").joinpath(DEFAULT_WORKCELL)
        return ref.read_text(encoding="utf-8"), f"static_data/{DEFAULT_WORKCELL}"
    try:
        return Path(path).read_text(encoding="utf-8"), path
    except FileNotFoundError:
        raise InputError(f"{path}: no such workcell file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the workcell file ({exc})") from None


def run(args: argparse.Namespace) -> int:
    import json

    from app.acquisition import Runner, RunnerConfig, check_grid_limits, describe_device
    from app.session import Session
    from calib_core.errors import InputError
    from calib_core.grid import load_grid
    from drivers.base import DriverError

    hardware = any(v is not None for v in (args.robot_port, args.sensor_port, args.camera))
    if hardware and args.sim:
        raise InputError("--sim cannot be combined with --robot-port/--sensor-port/--camera")
    if args.retry_skipped and not args.resume:
        raise InputError("--retry-skipped needs --resume")
    if args.resume:
        fixed = [flag for flag, value in (("--grid", args.grid), ("--workcell", args.workcell),
                                          ("--seed", args.seed)) if value is not None]
        if fixed:
            raise InputError(f"{', '.join(fixed)} cannot change on --resume: the session file "
                             "keeps its own")
    if args.move_time is not None and not args.move_time >= 0:
        raise InputError(f"--move-time must be >= 0 seconds, got {args.move_time}")

    if args.preview:
        grid = Session.open(args.session, readonly=True).grid if args.resume else \
            load_grid(args.grid or "paper")
        print(grid.preview())
        return 0

    session_path = Path(args.session)
    if args.resume:
        if not session_path.exists():
            raise InputError(f"{session_path}: no such session file; start a new session "
                             "without --resume")
        session = Session.open(session_path)
        settings = session.meta_json("settings")
        if settings.get("mode", "sim") != ("hardware" if hardware else "sim"):
            session.close()
            raise InputError(f"{session_path}: the session was recorded in "
                             f"{settings.get('mode')} mode; resume it the same way")
        workcell_text = session.meta.get("workcell", "")
        source = f"{session_path} (workcell)"
    else:
        if session_path.exists():
            raise InputError(f"{session_path}: session file already exists; continue it with "
                             "--resume or choose another file")
        grid = load_grid(args.grid or "paper")
        settings = {}
        workcell_text, source = _workcell_text(args.workcell) if (
            not hardware or args.workcell) else ("", "")
        session = None

    samples = args.samples if args.samples is not None else settings.get("samples_per_pose", 3)
    settle = args.settle if args.settle is not None else settings.get(
        "settle_s", 0.3 if hardware else 0.0)
    retries = args.retries if args.retries is not None else settings.get("max_retries", 2)
    seed = int(settings.get("seed", args.seed or 0))
    streak = args.max_skips_in_a_row if args.max_skips_in_a_row is not None else \
        settings.get("max_skips_in_a_row", 3)
    config = RunnerConfig(samples_per_pose=int(samples), settle_s=float(settle),
                          max_retries=int(retries), retry_skipped=args.retry_skipped,
                          return_on_pause=True, max_skips_in_a_row=int(streak))
    noise: dict[str, float] = {}
    try:
        if hardware:
            robot, sensor, camera = _hardware_devices(args)
            noise = _noise_of(workcell_text, source)
        else:
            # a resumed simulation continues with fresh noise draws (same truth)
            n_stored = 0 if session is None else len(session.stored_indices())
            sim_seed = seed if n_stored == 0 else seed * 1_000_003 + n_stored
            workcell, robot, sensor, camera = _sim_devices(args, workcell_text, source, sim_seed)
            noise = workcell.noise.as_dict()
    except BaseException:
        if session is not None:
            session.close()
        raise

    try:
        if session is None:
            check_grid_limits(grid, robot.limits)
            session = Session.create(
                session_path, grid, workcell_toml=workcell_text, noise=noise,
                drivers={"robot": describe_device(robot), "sensor": describe_device(sensor),
                         "camera": describe_device(camera)},
                settings={"mode": "hardware" if hardware else "sim", "seed": seed,
                          "samples_per_pose": config.samples_per_pose,
                          "settle_s": config.settle_s, "max_retries": config.max_retries,
                          "max_skips_in_a_row": config.max_skips_in_a_row,
                          "grid": args.grid or "paper", "workcell_source": source})
        else:
            session.log_event("resume", f"resumed with {json.dumps(vars(args), default=str)}")
        bar = ProgressBar(sys.stderr, args.quiet)
        runner = Runner(session, robot, sensor, camera, config, on_progress=bar)
        previous = {s: signal.signal(s, lambda *_: runner.abort(stop_motion=True))
                    for s in (signal.SIGINT, signal.SIGTERM)}
        started = time.monotonic()
        try:
            result = runner.run()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        elapsed = time.monotonic() - started
        where = f"{result.done}/{result.total} poses stored in {session_path}"
        if result.state == "aborted":
            sys.stderr.write(f"error: interrupted; {where}; continue with --resume\n")
            return 130
        if result.state == "paused":
            raise DriverError(f"{result.message.removesuffix('; fix the device, then resume')}"
                              f"; {where}; fix the device, then continue with --resume")
        skipped = f" ({result.skipped} skipped; see 'lasercal export')" if result.skipped else ""
        print(f"session {session_path}: {where.split(' in ')[0]}{skipped} in {elapsed:.1f} s; "
              f"solve with: lasercal solve {session_path}")
        return 0
    finally:
        for device in (robot, sensor, camera):
            with contextlib.suppress(Exception):  # closing must not hide the result
                device.close()
        if session is not None:
            session.close()
