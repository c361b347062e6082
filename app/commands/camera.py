"""``lasercal camera``: chessboard calibration of the spot camera, spot check, rendered frames."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

HELP = """\
The spot camera under the glass plate: pixels -> plate mm through lens undistortion and a
homography fitted on a chessboard lying on the plate.

  calibrate  find the chessboard's inner corners (cv2.findChessboardCornersSB + cornerSubPix) in
             an image (--image), a live camera (--camera) or the simulated cell (--sim), fit the
             homography and write the calibration JSON used by 'acquire --camera-calib'
  spot       detect the laser spot in an image or a live frame and print its plate x, y (mm),
             pixel u, v and quality, or 'rejected: <reason>' (no spot, two spots, saturated)
  render     write a frame of the simulated camera (spot at a flange pose, or the chessboard)

Board geometry: --pattern COLSxROWS inner corners, --square side (mm), --origin X Y the
fixed-frame position of the inner corner that appears nearest the image's top-left, --angle the
direction of the board's first row in the fixed frame (degrees), --mirrored when the board's
second axis runs clockwise from the first seen from above (+z). Exit status 0, or 2 with one
'error:' line.
"""


def _source(p: argparse.ArgumentParser, sim: bool) -> None:
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--image", metavar="FILE", help="a still image (PNG, TIFF, ...)")
    g.add_argument("--camera", metavar="INDEX|URL", help="a cv2.VideoCapture source")
    if sim:
        g.add_argument("--sim", action="store_true",
                       help="the simulated camera of --workcell (rendered chessboard)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("camera", help="calibrate the spot camera on a chessboard; check a spot",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION", parser_class=type(p))
    actions.required = True

    c = actions.add_parser("calibrate", help="fit pixels -> plate mm from a chessboard image",
                           description="Fit the camera's pixel -> plate mapping from one image "
                                       "of a chessboard lying on the plate.")
    _source(c, sim=True)
    c.add_argument("--pattern", metavar="COLSxROWS",
                   help="inner corners, e.g. 16x12 (default with --sim: the sim board)")
    c.add_argument("--square", type=float, metavar="MM", help="square side in mm")
    c.add_argument("--origin", type=float, nargs=2, metavar=("X", "Y"),
                   help="fixed-frame x, y (mm) of the corner nearest the image's top-left")
    c.add_argument("--angle", type=float, default=0.0, metavar="DEG",
                   help="direction of the board's rows in the fixed frame (default 0)")
    c.add_argument("--mirrored", action="store_true",
                   help="the board's columns run clockwise from its rows seen from +z")
    c.add_argument("--intrinsics", metavar="FILE.json",
                   help="camera_matrix and dist_coeffs of a prior lens calibration (JSON)")
    c.add_argument("--estimate-distortion", action="store_true",
                   help="estimate focal length and k1, k2 from this one view instead")
    c.add_argument("--workcell", metavar="FILE.toml", help="workcell for --sim (default: "
                                                            "the packaged seed cell)")
    c.add_argument("--out", required=True, metavar="FILE.json",
                   help="where to write the calibration (for acquire --camera-calib)")
    c.set_defaults(func=run)

    s = actions.add_parser("spot", help="detect the laser spot and print plate x, y",
                           description="Detect the laser spot and print plate x, y (mm).")
    _source(s, sim=False)
    s.add_argument("--calib", required=True, metavar="FILE.json",
                   help="camera calibration written by 'camera calibrate'")
    s.add_argument("--background", metavar="FILE",
                   help="laser-off image subtracted before detection (with --image)")
    s.add_argument("--background-frames", type=int, default=0, metavar="N",
                   help="with --camera: first grab N laser-off frames as the background")
    s.add_argument("--samples", type=int, default=1, metavar="N",
                   help="frames averaged (with --camera; default 1)")
    s.set_defaults(func=run)

    r = actions.add_parser("render", help="write a frame of the simulated camera",
                           description="Write a frame of the simulated camera: the spot with "
                                       "the flange at --x --y --z --theta, or the chessboard.")
    r.add_argument("--workcell", metavar="FILE.toml", help="workcell (default: the seed cell)")
    r.add_argument("--x", type=float, default=0.0)
    r.add_argument("--y", type=float, default=0.0)
    r.add_argument("--z", type=float, default=20.0)
    r.add_argument("--theta", type=float, default=0.0, help="degrees")
    r.add_argument("--chessboard", action="store_true", help="render the calibration board")
    r.add_argument("--laser-off", action="store_true", help="a background frame (no spot)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", required=True, metavar="FILE.png")
    r.set_defaults(func=run)


def _read_image(path: str) -> Any:
    import cv2

    from calib_core.errors import InputError

    if not Path(path).is_file():
        raise InputError(f"{path}: no such image file")
    image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not an image OpenCV can read")
    return image


def _pattern(text: str) -> tuple[int, int]:
    from calib_core.errors import InputError

    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--pattern must be COLSxROWS, e.g. 16x12; got {text!r}") from None
    if cols < 2 or rows < 2:
        raise InputError(f"--pattern needs at least 2x2 inner corners; got {text!r}")
    return cols, rows


def _calibrate(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from calib_core.errors import InputError
    from calib_core.io import load_json_object
    from drivers.camera_cv import OpenCVCamera, PixelToPlate, calibrate_chessboard
    from drivers.sim.render import Chessboard

    k = dist = None
    if args.intrinsics:
        prior = PixelToPlate.from_json_dict({"homography": np.eye(3).tolist(),
                                             **load_json_object(args.intrinsics)})
        k, dist = prior.camera_matrix, prior.dist_coeffs
    if args.sim:
        from drivers.sim.devices import SimCamera
        from drivers.sim.workcell import load_workcell
        from drivers.sim.world import SimWorld

        cam = SimCamera(SimWorld(load_workcell(args.workcell), seed=0))
        board = cam.default_board()
        if k is None and not args.estimate_distortion:
            k, dist = cam.spec.camera_matrix(), cam.spec.dist_coeffs()
    else:
        board = None
    if args.pattern or args.square is not None or args.origin is not None or board is None:
        missing = [n for n, v in (("--pattern", args.pattern), ("--square", args.square),
                                  ("--origin", args.origin)) if v is None]
        if missing:
            raise InputError(f"camera calibrate needs {', '.join(missing)} (board geometry)")
        if not args.square > 0:
            raise InputError(f"--square must be > 0 mm, got {args.square}")
        board = Chessboard(_pattern(args.pattern), args.square, tuple(args.origin),
                           args.angle, args.mirrored)
    if args.sim:
        image = cam.renderer.render_chessboard(board)
    elif args.image:
        image = _read_image(args.image)
    else:
        source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
        live = OpenCVCamera(source)
        try:
            image = live.grab()
        finally:
            live.close()
    mapping = calibrate_chessboard(image, board.pattern, board.corners_mm(), k, dist,
                                   args.estimate_distortion)
    Path(args.out).write_text(json.dumps(mapping.to_json_dict(), indent=2) + "\n",
                              encoding="utf-8")
    scale = mapping.mm_per_px(np.array([image.shape[1] / 2, image.shape[0] / 2]))
    print(f"corners {mapping.n_corners}, residual {mapping.rms_px:.3f} px "
          f"({1000 * mapping.rms_mm:.2f} um), scale {1000 * scale:.2f} um/px; wrote {args.out}")
    return 0


def _spot(args: argparse.Namespace) -> int:
    from calib_core.errors import InputError
    from calib_core.io import load_json_object
    from drivers.camera_cv import (
        OpenCVCamera,
        PixelToPlate,
        detect_spot,
        measurement_from,
    )

    mapping = PixelToPlate.from_json_dict(load_json_object(args.calib))
    if args.samples < 1 or args.background_frames < 0:
        raise InputError("--samples must be >= 1 and --background-frames >= 0")
    if args.image:
        background = _read_image(args.background) if args.background else None
        m = measurement_from(detect_spot(_read_image(args.image), background), mapping)
    else:
        source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
        cam = OpenCVCamera(source, mapping, average=args.samples)
        try:
            if args.background_frames:
                cam.capture_background(args.background_frames)
            m = cam.measure_spot()
        finally:
            cam.close()
    if not m.ok:
        print(f"rejected: {m.reason}")
        return 0
    print(f"x={m.x:.4f} y={m.y:.4f} mm  u={m.u:.3f} v={m.v:.3f} px  quality={m.quality:.2f}")
    return 0


def _render(args: argparse.Namespace) -> int:
    import cv2

    from calib_core.errors import InputError
    from drivers.base import FlangePose
    from drivers.sim.devices import SimCamera, SimRobot
    from drivers.sim.workcell import load_workcell
    from drivers.sim.world import SimWorld

    if not cv2.haveImageWriter(args.out):
        raise InputError(f"{args.out}: OpenCV cannot write this image format (use .png)")
    world = SimWorld(load_workcell(args.workcell), seed=args.seed)
    cam = SimCamera(world, seed=args.seed)
    if args.chessboard:
        image = cam.renderer.render_chessboard(cam.default_board())
    elif args.laser_off:
        image = cam.renderer.render()
    else:
        SimRobot(world).move_to(FlangePose(args.x, args.y, args.z, args.theta))
        image = cam.grab()
    if not cv2.imwrite(args.out, image):
        raise InputError(f"{args.out}: cannot write the image (extension? directory?)")
    truth = world.true_spot() if not (args.chessboard or args.laser_off) else None
    extra = "" if truth is None else f"; true spot x={truth[0]:.4f} y={truth[1]:.4f} mm"
    print(f"wrote {args.out}{extra}")
    return 0


def run(args: argparse.Namespace) -> int:
    return {"calibrate": _calibrate, "spot": _spot, "render": _render}[args.action](args)
