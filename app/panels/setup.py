"""Setup tab: simulated or hardware cell, connect, sensor zero, camera chessboard calibration."""

from __future__ import annotations

from typing import Any

from app.panels.state import AppState
from drivers.base import DriverError


def zero_sensor(app: AppState) -> float | None:
    """Zero the sensor at the current reading (worker thread); returns the reading after."""
    app.require_devices()
    app.sensor.zero()
    reading = app.sensor.read()
    app.publish(app.robot.read_pose(), reading)
    return reading.value if reading.ok else None


def calibrate_camera(app: AppState) -> str:
    """Chessboard calibration through the camera driver, when it offers one (worker thread)."""
    app.require_devices()
    method = getattr(app.camera, "calibrate_chessboard", None)
    if method is None:
        if app.sim:
            return "the simulated camera is calibrated by construction; nothing to do"
        raise DriverError("this camera driver has no chessboard calibration")
    result = method()
    return f"camera calibrated: {result}"


def build(gui: Any, app: AppState) -> None:
    mode = gui.add_dropdown("Cell", ("simulated", "hardware"),
                            initial_value="simulated" if app.sim else "hardware")
    robot_port = gui.add_text("Robot port", "/dev/ttyUSB0")
    sensor_port = gui.add_text("Sensor port", "/dev/ttyUSB1")
    camera = gui.add_text("Camera", "0")
    connect = gui.add_button("Connect", icon="plug-connected")
    status = gui.add_markdown("")
    zero = gui.add_button("Sensor zero")
    chess = gui.add_button("Camera chessboard calibration")

    def refresh() -> None:
        if app.connected:
            kind = "simulated cell" if app.sim else "hardware"
            status.content = f"**Connected** ({kind}): {type(app.robot).__name__}, " \
                             f"{type(app.sensor).__name__}, {type(app.camera).__name__}"
        else:
            status.content = "**Not connected**"
    refresh()
    app.on_change("devices", refresh)

    @connect.on_click
    def _(_: Any) -> None:
        if mode.value == "simulated":
            app.worker.submit("connect", app.connect_sim)
        else:
            app.worker.submit("connect", lambda: app.connect_hardware(
                robot_port.value, sensor_port.value, camera.value))

    @zero.on_click
    def _(_: Any) -> None:
        def cmd() -> None:
            value = zero_sensor(app)
            app.notify("sensor zero", f"sensor zeroed; reading now {value}", "success")
        app.worker.submit("sensor zero", cmd)

    @chess.on_click
    def _(_: Any) -> None:
        app.worker.submit("camera calibration",
                          lambda: app.notify("camera", calibrate_camera(app), "info"))
