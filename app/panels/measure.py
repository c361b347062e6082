"""Measure tab: plane scan, Johansson gauges, pyramid pose and the 2-dof platform campaign.

Every computation is the CLI's (``lasercal measure`` / ``lasercal platform``): points by eq 16
(:func:`calib_core.measure.reconstruct`), the plane, gauge, pyramid and platform fits of
``calib_core``. The calibration is the last **Solve H** result, or an uploaded calibration JSON
(the ``solve --json`` object). Long work runs on the worker thread; results go to
``app.measurements`` (kind -> :class:`Measured`, whose ``result`` is the CLI ``--json`` object
and becomes a section of the downloaded report) and into the 3-D scene (handles created once).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from app.panels.export import offer_download
from app.panels.state import AppState
from calib_core.errors import InputError
from drivers.base import FlangePose, MotionRefused

#: Side-plate scan: k x k spots over this fraction of the plate, at these flange rotations.
SCAN_GRID = 5
SCAN_FILL = 0.7
SCAN_THETAS_DEG = (0.0, -8.0)
#: Platform drawing: axis length (mm) and the factor angular errors are exaggerated by.
AXIS_LENGTH_MM = 30.0
PLATFORM_ERROR_SCALE = 10.0
EDGE_LENGTH_MM = 8.0


@dataclass(frozen=True)
class Measured:
    """One measurement result: the CLI ``--json`` object, its markdown and drawing data."""

    kind: str
    source: str
    result: dict[str, Any]
    markdown: str
    points: np.ndarray | None = None
    draw: dict[str, Any] = field(default_factory=dict)


# ---- calibration ------------------------------------------------------------------------------
def calibration_for_measuring(app: AppState) -> Any:
    """The uploaded calibration JSON if any, else the last 'Solve H' result."""
    cal = app.measure_calibration if app.measure_calibration is not None else app.calibration
    if cal is None:
        raise InputError("no calibration: click 'Solve H' or upload a calibration JSON")
    return cal


def calibration_markdown(app: AppState) -> str:
    if app.measure_calibration is not None:
        return f"calibration: uploaded file ({app.measure_calibration.model} model)"
    if app.calibration is not None:
        return f"calibration: last 'Solve H' result ({app.calibration.model} model)"
    return "calibration: none yet (click 'Solve H' or upload a calibration JSON)"


def load_calibration_upload(app: AppState, name: str, content: bytes) -> str:
    """Use an uploaded calibration JSON for measuring (validated before the state changes)."""
    from app.panels.upload import display_name, upload_calibration

    cal = upload_calibration(name, content)
    app.measure_calibration = cal
    app.changed("measure")
    return f"{display_name(name)}: {cal.model} calibration loaded for measuring"


def _reference(cal: Any) -> str:
    from app.commands.measure import _z_reference

    return _z_reference(cal)


def _check_model(cal: Any, poses: Any, source: str) -> None:
    from app.commands.measure import _check_model as check

    check(cal, poses, source)


def _pm(value: float, sigma: float) -> str:
    return f"{value:.6g} ± {sigma:.2g}"


# ---- plane ------------------------------------------------------------------------------------
def side_plate_plan(workcell: Any, k: int = SCAN_GRID,
                    thetas: tuple[float, ...] = SCAN_THETAS_DEG) -> list[FlangePose]:
    """Flange poses putting the nominal beam's ``T`` (d = 0) on a ``k x k`` grid over the inner
    :data:`SCAN_FILL` of the side plate: ``O = P - Rz(theta) T``, theta cycling ``thetas``;
    poses outside the soft limits are left out."""
    from calib_core.model import rotation_about_z

    side, beam = workcell.side_plate, workcell.beam
    hx, hy = (SCAN_FILL * side.size[0] / 2, SCAN_FILL * side.size[1] / 2)
    xs = np.linspace(side.centre[0] - hx, side.centre[0] + hx, k)
    ys = np.linspace(side.centre[1] - hy, side.centre[1] + hy, k)
    plan = []
    for i, (x, y) in enumerate((x, y) for y in ys for x in xs):
        theta = float(thetas[i % len(thetas)])
        p = np.array([x, y, float(side.z_at(x, y))])
        o = p - rotation_about_z(np.array([theta]))[0] @ np.asarray(beam.t, float)
        pose = FlangePose(float(o[0]), float(o[1]), float(o[2]), theta)
        try:
            workcell.limits.check(pose, None)
        except MotionRefused:
            continue
        plan.append(pose)
    return plan


def scan_side_plate(app: AppState) -> pd.DataFrame:
    """Move through :func:`side_plate_plan` and read the sensor at each pose (worker thread).

    Needs 'Arm motion' (STOP disarms and ends the scan); out-of-range readings are skipped.
    Returns the scan as a measurement table (x_o, y_o, z_o, theta_deg, d).
    """
    app.require_motion()
    plan = side_plate_plan(app.workcell)
    if len(plan) < 3:
        raise InputError("side plate scan: fewer than 3 planned poses inside the soft limits")
    rows = []
    for k, target in enumerate(plan):
        if not app.armed:
            raise MotionRefused(f"side plate scan stopped after {k} of {len(plan)} poses "
                                "(motion disarmed)")
        current = app.robot.read_pose()
        app.robot.limits.check(target, current)
        pose = app.robot.move_to(target)
        reading = app.sensor.read()
        app.publish(pose, reading)
        if reading.ok:
            rows.append((pose.x, pose.y, pose.z, pose.theta_deg, reading.value))
    if len(rows) < 3:
        raise InputError(f"side plate scan: only {len(rows)} of {len(plan)} readings in range")
    return pd.DataFrame(rows, columns=["x_o", "y_o", "z_o", "theta_deg", "d"])


def plane_truth(app: AppState, cal: Any) -> dict[str, float] | None:
    """The side plate's true plane in the simulator, in the calibration's z reference."""
    if not (app.sim and app.world is not None):
        return None
    side, plate = app.workcell.side_plate, app.workcell.plate
    offset = side.delta - plate.delta if cal.model == "schoenflies" else side.delta
    return {"alpha": side.alpha, "beta": side.beta, "offset": offset}


def fit_plane(app: AppState, data: Any, method: str = "ls", truth: dict[str, float] | None = None
              ) -> Measured:
    """Plane of a scan data set with the measuring calibration (``measure plane``)."""
    from calib_core.measure import compare_with_camera, fit_scan_plane, reconstruct

    cal = calibration_for_measuring(app)
    _check_model(cal, data.poses, data.source)
    scan = reconstruct(data.poses, data.d, cal, app.workcell.noise)
    fit = fit_scan_plane(scan, method)
    out = fit.to_json_dict()
    out["z_reference"] = _reference(cal)
    if data.spot_xy is not None:
        out["comparison"] = compare_with_camera(scan.xyz, data.spot_xy, fit)
    sig = fit.sigma
    head = "| plane parameter | value | ±1σ | sim truth |" if truth else \
        "| plane parameter | value | ±1σ | |"
    lines = [f"**Plane** of {data.source}: {fit.n_points} points, {fit.method} fit, "
             f"RMS **{1000 * fit.rms:.2f} µm**", "", head, "|---|---:|---:|---:|"]
    for key, label in (("alpha", "alpha"), ("beta", "beta"), ("offset", "offset (mm)")):
        t = "" if not truth else f"{truth[key]:.7g}"
        value = {"alpha": fit.alpha, "beta": fit.beta, "offset": fit.offset}[key]
        lines.append(f"| {label} | {value:.7g} | {sig[key]:.2g} | {t} |")
    lines += ["", f"z: {out['z_reference']}"]
    lines += [f"- warning: {w}" for w in fit.warnings]
    return Measured("plane", data.source, out, "\n".join(lines), scan.xyz,
                    {"alpha": fit.alpha, "beta": fit.beta, "offset": fit.offset})


def run_plane_scan(app: AppState, method: str = "ls") -> Measured:
    """Scan the side plate, fit its plane, publish (worker thread)."""
    from calib_core.io import dataset_from_frame

    calibration_for_measuring(app)                  # refuse before moving
    frame = scan_side_plate(app)
    data = dataset_from_frame(frame, "side plate scan", need_spot=False, min_rows=3)
    cal = calibration_for_measuring(app)
    measured = fit_plane(app, data, method, plane_truth(app, cal))
    app.notify("plane scan", f"{len(frame)} points: alpha {measured.result['alpha']:.5g}, "
               f"beta {measured.result['beta']:.5g}", "success")
    return publish(app, dataclasses.replace(measured, draw={**measured.draw, "scan": frame}))


def scan_csv_bytes(app: AppState) -> bytes:
    """The last side-plate scan in the measurement CSV format ('lasercal measure plane' reads
    it back)."""
    plane = app.measurements.get("plane")
    if plane is None or "scan" not in plane.draw:
        raise InputError("no side plate scan yet: click 'Scan side plate'")
    head = "# lasercal side plate scan (flange pose, sensor reading; mm, deg)\n"
    return (head + plane.draw["scan"].to_csv(index=False, float_format="%.9g")).encode()


def plane_upload(app: AppState, name: str, content: bytes, method: str = "ls") -> str:
    from app.panels.upload import upload_dataset

    data = upload_dataset(name, content, need_spot=False, min_rows=3)
    m = publish(app, fit_plane(app, data, method))
    return f"{m.source}: plane fitted to {m.result['n_points']} points"


# ---- gauges -----------------------------------------------------------------------------------
def gauges_upload(app: AppState, name: str, content: bytes) -> str:
    """Johansson gauge check of an uploaded gauge CSV (``measure gauges``)."""
    from app.panels.upload import upload_dataset
    from calib_core.io import numeric_columns
    from calib_core.measure import gauge_check

    data = upload_dataset(name, content, need_spot=False, min_rows=3, required=("gauge_height",))
    heights = numeric_columns(data.extra, ("gauge_height",), data.source)[:, 0]
    cal = app.measure_calibration if app.measure_calibration is not None else app.calibration
    if cal is not None:
        _check_model(cal, data.poses, data.source)
    res = gauge_check(data.poses, data.d, heights, cal, app.workcell.noise)
    lines = [f"**Gauges** of {data.source}: {res.n_readings} readings", "",
             "| | value |", "|---|---:|", f"| c (gauges) | {_pm(res.c, res.c_sigma)} |"]
    if res.c_calibrated is not None:
        lines += [f"| c (calibration) | {_pm(res.c_calibrated, res.c_calibrated_sigma)} |",
                  f"| agreement | {res.agreement_sigmas:.2f} σ |"]
    lines.append(f"| residual RMS | {1000 * res.residual_rms:.2f} µm |")
    lines += [f"- warning: {w}" for w in res.warnings]
    publish(app, Measured("gauges", data.source, res.to_json_dict(), "\n".join(lines)))
    return f"{data.source}: c = {res.c:.5f} ± {res.c_sigma:.5f}"


# ---- pyramid ----------------------------------------------------------------------------------
def pyramid_upload(app: AppState, name: str, content: bytes) -> str:
    """Pyramid pose from an uploaded scan with a face column (``measure pyramid``)."""
    from app.panels.upload import upload_dataset
    from calib_core.measure import reconstruct
    from calib_core.pyramid import load_geometry, measure_pyramid

    data = upload_dataset(name, content, need_spot=False, min_rows=9, required=("face",))
    cal = calibration_for_measuring(app)
    _check_model(cal, data.poses, data.source)
    geometry = load_geometry(None)
    scan = reconstruct(data.poses, data.d, cal, app.workcell.noise)
    labels = data.extra["face"].astype(str).str.strip().to_numpy()
    try:
        pose = measure_pyramid(scan, labels, geometry)
    except InputError as exc:
        raise InputError(f"{data.source}: {exc}") from None
    out = pose.to_json_dict()
    out["z_reference"] = _reference(cal)
    names = geometry.face_names
    lines = [f"**Pyramid** of {data.source}: {pose.n_points} points, residual RMS "
             f"{1000 * pose.residual_rms:.2f} µm", "", "| | x | y | z |", "|---|---:|---:|---:|",
             "| apex (mm) | {:.4f} | {:.4f} | {:.4f} |".format(*pose.apex),
             "| ±1σ | {:.4f} | {:.4f} | {:.4f} |".format(*pose.apex_sigma),
             "| rotation vector (deg) | {:.4f} | {:.4f} | {:.4f} |".format(*pose.rotvec_deg),
             "| ±1σ | {:.4f} | {:.4f} | {:.4f} |".format(*pose.rotation_sigma_deg)]
    for k, e in enumerate(pose.edges):
        lines.append(f"| edge {names[k]}{names[(k + 1) % 3]} | {e[0]:.5f} | {e[1]:.5f} | "
                     f"{e[2]:.5f} |")
    lines += ["", "quaternion (w, x, y, z): ({:.6f}, {:.6f}, {:.6f}, {:.6f})".format(
        *pose.quaternion), f"z: {out['z_reference']}"]
    lines += [f"- warning: {w}" for w in pose.warnings]
    publish(app, Measured("pyramid", data.source, out, "\n".join(lines), scan.xyz,
                          {"apex": np.asarray(pose.apex, float),
                           "edges": np.asarray(pose.edges, float)}))
    return f"{data.source}: apex ({', '.join(f'{v:.3f}' for v in pose.apex)}) mm"


# ---- platform ---------------------------------------------------------------------------------
ISO_ROWS = (("orientation RMS (deg)", "orientation_rms_deg"),
            ("orientation max (deg)", "orientation_max_deg"),
            ("apex RMS (mm)", "apex_rms_mm"), ("apex max (mm)", "apex_max_mm"),
            ("AP position (mm)", "ap_mm"), ("AP orientation (deg)", "ap_deg"),
            ("RP position (mm)", "rp_mm"), ("RP orientation (deg)", "rp_deg"))


def platform_axes(params: dict[str, float], nominal: dict[str, float], validation: Any
                  ) -> dict[str, np.ndarray]:
    """Output axes on the validation set: measured (the measured pyramid rotation with the
    identified mounting removed, ``F = R_meas (Rz(out_rz) M)^T``, ``w = F e_z``), calibrated
    model and nominal model (``chain(...).w``); the sphere centre (identified)."""
    from scipy.spatial.transform import Rotation

    from calib_core.platform import chain

    p = params
    mount = Rotation.from_rotvec([p["mount_rx_deg"], p["mount_ry_deg"], p["mount_rz_deg"]],
                                 degrees=True).as_matrix()
    rz = Rotation.from_euler("z", p["out_rz_deg"], degrees=True).as_matrix()
    frame = validation.rotation @ (rz @ mount).T
    return {"centre": np.array([p["centre_x_mm"], p["centre_y_mm"], p["centre_z_mm"]]),
            "measured": frame[:, :, 2], "model": chain(params, validation.q_deg).w,
            "nominal": chain(nominal, validation.q_deg).w}


def run_platform_campaign(app: AppState, seed: int = 0) -> Measured:
    """Simulate a platform campaign into a temporary directory and calibrate it (worker)."""
    import json

    from app.commands.platform import calibrate_campaign, load_campaign, run_simulate

    with tempfile.TemporaryDirectory(prefix="lasercal-platform-") as tmp:
        run_simulate(argparse.Namespace(out=tmp, seed=int(seed), poses=False, per_face=8,
                                        spec=None))
        result = calibrate_campaign(tmp)
        validation = load_campaign(tmp)["validation"]
        truth = json.loads((Path(tmp) / "truth.json").read_text())["identifiable_equivalent"]
    axes = platform_axes(result["params"], result["nominal"], validation)
    before, after = result["before"], result["after"]
    lines = [f"**Platform campaign** (simulated, seed {seed}): {result['n_train']} "
             f"identification poses, {result['n_validation']} validation poses; reduced "
             f"chi-square {result['chi2_reduced']:.2f}", "",
             "| validation (ISO 9283 style) | before | after |", "|---|---:|---:|"]
    for label, key in ISO_ROWS:
        b, a = before.get(key), after.get(key)
        lines.append(f"| {label} | {'n/a' if b is None else f'{b:.4f}'} | "
                     f"{'n/a' if a is None else f'{a:.4f}'} |")
    lines += ["", "| parameter | identified | ±1σ | sim truth |", "|---|---:|---:|---:|"]
    for name in result["free"]:
        lines.append(f"| {name} | {result['params'][name]:.5f} | {result['sigma'][name]:.2g} | "
                     f"{truth[name]:.5f} |")
    if result["unidentifiable"]:
        lines += ["", "Kept at nominal (not identifiable): " + ", ".join(
            u["name"] for u in result["unidentifiable"])]
    lines += ["", f"Scene: output axes from the sphere centre, measured (green), calibrated "
              f"model (blue), nominal model (red); angular errors drawn x"
              f"{PLATFORM_ERROR_SCALE:g}."]
    app.notify("platform", f"calibrated: validation orientation RMS "
               f"{before['orientation_rms_deg']:.3f} -> {after['orientation_rms_deg']:.3f} deg",
               "success")
    return publish(app, Measured("platform", f"simulated campaign seed {seed}", result,
                                 "\n".join(lines), None, axes))


# ---- publishing and the scene -----------------------------------------------------------------
def publish(app: AppState, measured: Measured) -> Measured:
    """Store a result (replacing the previous one of its kind) and refresh tab and scene."""
    app.measurements[measured.kind] = measured
    app.changed("measure")
    return measured


class MeasureScene:
    """Scene handles of the Measure tab under ``/cell/measure`` (created once, then updated)."""

    def __init__(self, scene: Any) -> None:
        from app.scene import plane_mesh

        empty = np.zeros((0, 3), np.float32)
        no_lines = np.zeros((0, 2, 3), np.float32)
        rect, tri = plane_mesh(0.0, 0.0, 0.0, (0.0, 0.0), (1.0, 1.0))
        self.points = scene.add_point_cloud("/cell/measure/scan_points", empty,
                                            colors=(20, 90, 200), point_size=0.4,
                                            precision="float32", point_shape="circle")
        self.plane = scene.add_mesh_simple("/cell/measure/plane", rect, tri,
                                           color=(240, 120, 40), opacity=0.35, side="double",
                                           visible=False)
        self.apex = scene.add_icosphere("/cell/measure/apex", radius=0.5, color=(220, 30, 30),
                                        visible=False)
        self.edges = scene.add_line_segments("/cell/measure/edges", no_lines,
                                             colors=(220, 30, 30), thickness=3.0,
                                             thickness_units="screen", visible=False)
        self.axes = {key: scene.add_line_segments(f"/cell/measure/axes_{key}", no_lines,
                                                  colors=color, thickness=1.5,
                                                  thickness_units="screen", visible=False)
                     for key, color in (("measured", (30, 170, 60)), ("model", (40, 80, 230)),
                                        ("nominal", (230, 40, 40)))}

    def show(self, measurements: dict[str, Measured]) -> None:
        from app.scene import plane_mesh

        pts = [m.points for m in measurements.values() if m.points is not None]
        self.points.points = (np.vstack(pts) if pts else np.zeros((0, 3))).astype(np.float32)
        plane = measurements.get("plane")
        if plane is not None and plane.points is not None:
            xy = plane.points[:, :2]
            v, _ = plane_mesh(plane.draw["alpha"], plane.draw["beta"], plane.draw["offset"],
                              tuple(xy.mean(axis=0)), tuple(np.ptp(xy, axis=0) + 4.0))
            self.plane.vertices = v
            self.plane.visible = True
        pyr = measurements.get("pyramid")
        if pyr is not None:
            apex = pyr.draw["apex"]
            self.apex.position = apex
            self.apex.visible = True
            self.edges.points = np.stack([np.repeat(apex[None], 3, axis=0),
                                          apex + EDGE_LENGTH_MM * pyr.draw["edges"]],
                                         axis=1).astype(np.float32)
            self.edges.visible = True
        plat = measurements.get("platform")
        if plat is not None:
            d = plat.draw
            c, model = d["centre"], d["model"]
            for key in ("measured", "model", "nominal"):
                w = model + PLATFORM_ERROR_SCALE * (d[key] - model)
                w = w / np.linalg.norm(w, axis=1, keepdims=True)
                self.axes[key].points = np.stack([np.repeat(c[None], len(w), axis=0),
                                                  c + AXIS_LENGTH_MM * w],
                                                 axis=1).astype(np.float32)
                self.axes[key].visible = True


# ---- the tab ----------------------------------------------------------------------------------
def build(gui: Any, app: AppState) -> None:
    from app.panels.upload import add_upload

    scene = MeasureScene(app.server.scene) if app.server is not None else None
    cal_md = gui.add_markdown(calibration_markdown(app))
    add_upload(gui, app, "Upload calibration JSON",
               lambda name, content: load_calibration_upload(app, name, content),
               hint="the JSON of 'lasercal solve --json' (Export > Download solve JSON)",
               mime_type=".json,application/json,text/plain")
    use_solve = gui.add_button("Use the last Solve H result")
    with gui.add_folder("Plane"):
        method = gui.add_dropdown("Fit", ("ls", "orthogonal"), initial_value="ls",
                                  hint="ls: seed eq 20 (vertical least squares); orthogonal: "
                                       "total least squares for steep planes")
        scan_btn = gui.add_button("Scan side plate", icon="scan",
                                  hint="needs 'Arm motion' (Jog tab): scan the aluminium side "
                                       "plate and fit its plane")
        add_upload(gui, app, "Upload plane scan CSV",
                   lambda name, content: plane_upload(app, name, content, str(method.value)),
                   hint="x_o,y_o,z_o,theta_deg|qw..qz,d (optional x_p,y_p)",
                   mime_type=".csv,text/csv,text/plain")
        scan_csv = gui.add_button("Download last scan CSV", icon="download")
        plane_md = gui.add_markdown("")
    with gui.add_folder("Gauges", expand_by_default=False):
        add_upload(gui, app, "Upload gauge CSV",
                   lambda name, content: gauges_upload(app, name, content),
                   hint="gauge_height,d and the pose x_o,y_o,z_o,theta_deg",
                   mime_type=".csv,text/csv,text/plain")
        gauges_md = gui.add_markdown("")
    with gui.add_folder("Pyramid", expand_by_default=False):
        add_upload(gui, app, "Upload pyramid scan CSV",
                   lambda name, content: pyramid_upload(app, name, content),
                   hint="a scan with a face column (A, B, C), >= 3 points per face",
                   mime_type=".csv,text/csv,text/plain")
        pyramid_md = gui.add_markdown("")
    with gui.add_folder("Platform", expand_by_default=False):
        seed = gui.add_number("Campaign seed", 0, min=0, step=1)
        platform_btn = gui.add_button("Simulate + calibrate platform campaign")
        platform_md = gui.add_markdown("")
    shown = {"plane": plane_md, "gauges": gauges_md, "pyramid": pyramid_md,
             "platform": platform_md}

    def refresh() -> None:
        cal_md.content = calibration_markdown(app)
        for kind, handle in shown.items():
            m = app.measurements.get(kind)
            handle.content = m.markdown if m is not None else ""
        if scene is not None:
            scene.show(app.measurements)
    app.on_change("measure", refresh)
    app.on_change("solve", lambda: setattr(cal_md, "content", calibration_markdown(app)))

    @use_solve.on_click
    def _(_: Any) -> None:
        app.measure_calibration = None
        app.changed("measure")

    @scan_btn.on_click
    def _(event: Any) -> None:
        try:
            app.check_control(event.client_id)
            if not app.armed:
                raise MotionRefused("motion is disarmed: switch on 'Arm motion' (Jog tab) first")
        except Exception as exc:
            app.notify("plane scan", str(exc), "warning")
            return
        fit = str(method.value)
        app.notify("plane scan", "scanning the side plate ...", "info")
        app.worker.submit("plane scan", lambda: run_plane_scan(app, fit))

    @scan_csv.on_click
    def _(event: Any) -> None:
        offer_download(app, event.client, "scan CSV", "side-plate-scan.csv",
                       lambda: scan_csv_bytes(app))

    @platform_btn.on_click
    def _(_: Any) -> None:
        n = int(seed.value)
        app.notify("platform", "simulating and calibrating the platform campaign (a few "
                   "seconds) ...", "info")
        app.worker.submit("platform campaign", lambda: run_platform_campaign(app, n))
