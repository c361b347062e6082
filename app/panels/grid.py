"""Grid tab: heights, x-y spacing, rotation angles (default: the seed's 42 poses), preview."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from app.panels.state import AppState, pose_rotation
from calib_core.errors import InputError
from calib_core.grid import PoseGrid, axis_values, make_grid
from drivers.base import FlangePose


def parse_numbers(text: str, label: str) -> list[float]:
    """Numbers separated by commas or spaces ('15, 20, 25'); InputError names ``label``."""
    parts = [p for p in text.replace(",", " ").replace(";", " ").split() if p]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{label}: expected numbers separated by commas, got {text!r}") from None
    if not all(np.isfinite(values)):
        raise InputError(f"{label}: values must be finite")
    return values


@dataclass(frozen=True)
class GridSpec:
    """Grid inputs: heights and angles as text, x and y as [lo, hi] with a count each."""

    heights: str = "15, 20, 25"
    x_range: tuple[float, float] = (-2.0, 2.0)
    nx: int = 4
    y_range: tuple[float, float] = (-2.0, 2.0)
    ny: int = 3
    angles: str = "-6, -3.6, -1.2, 1.2, 3.6, 6"
    rotation_at: tuple[float, float, float] = (0.0, 0.0, 20.0)

    def to_grid(self) -> PoseGrid:
        """The pose grid (z outermost, then x, y; then the rotations at ``rotation_at``)."""
        heights = parse_numbers(self.heights, "heights")
        angles = parse_numbers(self.angles, "angles")
        xs = axis_values(*self.x_range, count=int(self.nx))
        ys = axis_values(*self.y_range, count=int(self.ny))
        name = "paper" if self == GridSpec() else "custom"
        return make_grid(heights, xs, ys, angles, rotation_at=self.rotation_at, name=name)


def check_reachable(grid: PoseGrid, limits: Any) -> None:
    """Raise (MotionRefused) naming the first pose outside the soft limits."""
    for i in range(len(grid)):
        x, y, z, t = grid.pose(i)
        try:
            limits.check(FlangePose(x, y, z, t))
        except Exception as exc:
            raise type(exc)(f"grid pose {i}: {exc}") from None


def preview_frames(grid: PoseGrid) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and rotations (n, 3, 3) of the planned flange poses."""
    poses = [FlangePose(*grid.pose(i)) for i in range(len(grid))]
    return (np.array([[p.x, p.y, p.z] for p in poses]).reshape(-1, 3),
            np.array([pose_rotation(p) for p in poses]).reshape(-1, 3, 3))


def apply_grid(app: AppState, spec: GridSpec) -> PoseGrid:
    """Make the grid, check it against the soft limits, make it the plan, draw it."""
    grid = spec.to_grid()
    check_reachable(grid, app.workcell.limits)
    app.grid = grid
    if app.scene is not None:
        app.scene.set_grid_preview(*preview_frames(grid))
    app.changed("grid")
    return grid


def build(gui: Any, app: AppState) -> None:
    d = GridSpec()
    heights = gui.add_text("Heights z (mm)", d.heights)
    x_range = gui.add_vector2("x from / to (mm)", d.x_range, step=0.1)
    nx = gui.add_number("x count", d.nx, min=1, max=100, step=1)
    y_range = gui.add_vector2("y from / to (mm)", d.y_range, step=0.1)
    ny = gui.add_number("y count", d.ny, min=1, max=100, step=1)
    angles = gui.add_text("Angles theta (deg)", d.angles)
    rot_at = gui.add_vector3("Rotate at x y z (mm)", d.rotation_at, step=0.1)
    preview = gui.add_checkbox("Show in 3-D", initial_value=False)
    apply = gui.add_button("Apply grid")
    count = gui.add_markdown("")

    def refresh() -> None:
        z = np.unique(np.round(app.grid.poses[:, 2], 6))
        count.content = f"**{len(app.grid)} poses** ({app.grid.name}), heights " \
                        f"{', '.join(f'{v:g}' for v in z)} mm"
        if app.scene is not None:
            app.scene.set_grid_preview(*preview_frames(app.grid))
            app.scene.grid_preview.visible = bool(preview.value)
    refresh()
    app.on_change("grid", refresh)

    @preview.on_update
    def _(_: Any) -> None:
        if app.scene is not None:
            app.scene.grid_preview.visible = bool(preview.value)

    @apply.on_click
    def _(_: Any) -> None:
        spec = GridSpec(heights.value, tuple(x_range.value), int(nx.value), tuple(y_range.value),
                        int(ny.value), angles.value, tuple(rot_at.value))
        try:
            grid = apply_grid(app, spec)
        except Exception as exc:
            app.notify("grid", str(exc), "warning")
            return
        app.notify("grid", f"{len(grid)} poses planned", "info")
