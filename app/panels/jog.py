"""Jog tab: step size, +-x/y/z/theta, go-to pose; motion only with 'Arm motion' switched on.

The STOP button lives above the tabs (see :mod:`app.panels`), so it is always visible.
"""

from __future__ import annotations

from concurrent.futures import Future
from typing import Any

from app.panels.state import AppState
from calib_core.errors import InputError
from drivers.base import FlangePose, MotionRefused

AXES = ("x", "y", "z", "theta")
#: Largest single jog step (mm or degrees); larger steps are refused before anything moves.
MAX_JOG_STEP = 10.0


def jog_target(current: FlangePose, axis: str, sign: int, step: float) -> FlangePose:
    """``current`` moved by ``sign * step`` along ``axis`` (mm for x/y/z, degrees for theta)."""
    if axis not in AXES:
        raise InputError(f"unknown jog axis {axis!r}; use one of {', '.join(AXES)}")
    if sign not in (-1, 1):
        raise InputError("jog direction must be +1 or -1")
    if not 0 < step <= MAX_JOG_STEP:
        raise MotionRefused(f"jog step {step:g} must be in (0, {MAX_JOG_STEP:g}]")
    x, y, z, t = current.x, current.y, current.z, current.theta_deg
    delta = sign * step
    if axis == "x":
        x += delta
    elif axis == "y":
        y += delta
    elif axis == "z":
        z += delta
    else:
        t += delta
    return FlangePose(x, y, z, t)


def jog(app: AppState, axis: str, sign: int, step: float,
        client_id: int | None = None) -> Future:
    """Queue a jog; refused at once (MotionRefused) when disarmed, another tab holds control,
    or the step is invalid."""
    app.require_motion(client_id)
    jog_target(FlangePose(0, 0, 0), axis, sign, step)  # validate before queueing

    def cmd() -> FlangePose:
        return app.move_to(jog_target(app.robot.read_pose(), axis, sign, step))
    return app.worker.submit(f"jog {axis}{'+' if sign > 0 else '-'}", cmd)


def go_to(app: AppState, x: float, y: float, z: float, theta: float,
          client_id: int | None = None) -> Future:
    """Queue an absolute move (soft limits and the maximum step are checked before it moves)."""
    app.require_motion(client_id)
    return app.worker.submit("go to", lambda: app.move_to(FlangePose(x, y, z, theta)))


def build(gui: Any, app: AppState) -> None:
    arm = gui.add_checkbox("Arm motion", initial_value=app.armed,
                           hint="Motion commands are refused while this is off")
    step = gui.add_slider("Step (mm / deg)", min=0.01, max=MAX_JOG_STEP, step=0.01,
                          initial_value=1.0)
    pose_md = gui.add_markdown("")
    for axis in AXES:
        group = gui.add_button_group(f"Jog {axis}", (f"-{axis}", f"+{axis}"))

        def on_click(event: Any, axis: str = axis) -> None:
            sign = 1 if event.target.value.startswith("+") else -1
            try:
                jog(app, axis, sign, float(step.value), event.client_id)
            except Exception as exc:  # shown to the operator, never raised into viser
                app.notify("jog", str(exc), "warning")
        group.on_click(on_click)
    target = gui.add_vector3("Go-to x y z (mm)", (0.0, 0.0, 20.0), step=0.01)
    theta = gui.add_number("Go-to theta (deg)", 0.0, step=0.01)
    goto = gui.add_button("Go to")

    @arm.on_update
    def _(event: Any) -> None:
        if (arm.value and event.client_id is not None
                and not app.has_control(event.client_id, "arm motion")):
            arm.value = False
            return
        app.armed = bool(arm.value)

    def refresh_arm() -> None:
        if arm.value != app.armed:
            arm.value = app.armed
    app.on_change("arm", refresh_arm)

    def refresh_pose() -> None:
        s = app.latest
        if s is not None:
            text = (f"x {s.pose.x:.3f}  y {s.pose.y:.3f}  z {s.pose.z:.3f} mm, "
                    f"theta {s.pose.theta_deg:.3f} deg")
            if pose_md.content != text:
                pose_md.content = text
    app.on_change("live", refresh_pose)

    @goto.on_click
    def _(event: Any) -> None:
        x, y, z = target.value
        try:
            go_to(app, float(x), float(y), float(z), float(theta.value), event.client_id)
        except Exception as exc:
            app.notify("go to", str(exc), "warning")
