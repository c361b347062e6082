"""The 3-D scene of the dashboard: every handle is created once, then updated in place.

All geometry is in the fixed frame in mm (1 scene unit = 1 mm) under the node ``/cell``;
points are sent as float32. Static parts come from the workcell TOML (glass plate,
aluminium side plate, pyramid on its platform, camera field of view); the flange frame, robot
body, sensor bracket, beam and live spot follow the robot; spots, fitted plane, error vectors,
1-sigma ellipsoids and the pose-grid preview follow the session and the solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

ARROW_SCALE_RANGE = (10.0, 5000.0)
#: Viridis stops for the residual colour map (low -> high).
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98],
                     [253, 231, 37]], dtype=float)


def colormap(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """RGB uint8 (n, 3) for ``values`` in ``[0, vmax]`` on a viridis ramp (linear interpolation)."""
    v = np.asarray(values, dtype=float)
    top = float(vmax if vmax is not None else (np.max(v) if v.size else 1.0)) or 1.0
    t = np.clip(v / top, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    lo = np.floor(t).astype(int).clip(0, len(_VIRIDIS) - 2)
    f = (t - lo)[:, None]
    return np.round(_VIRIDIS[lo] * (1 - f) + _VIRIDIS[lo + 1] * f).astype(np.uint8)


def legend_html(vmax_um: float) -> str:
    """HTML colour bar for residual magnitudes 0 .. ``vmax_um`` micrometres."""
    stops = ", ".join(f"rgb({r:.0f},{g:.0f},{b:.0f})" for r, g, b in _VIRIDIS)
    return (f'<div style="font-size:0.8em">|residual| (µm)<div style="height:10px;'
            f'background:linear-gradient(to right, {stops})"></div>'
            f'<div style="display:flex;justify-content:space-between"><span>0</span>'
            f'<span>{vmax_um / 2:.3g}</span><span>{vmax_um:.3g}</span></div></div>')


def box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box from corner ``lo`` to ``hi``: vertices (8, 3), faces (12, 3)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float32)
    return v, _BOX_FACES


_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]],
                      dtype=np.uint32)


def slab_mesh(top: np.ndarray, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """A plate: its four top corners (4, 3) counter-clockwise and the same ``thickness`` below."""
    top = np.asarray(top, dtype=np.float32)
    bottom = top - np.array([0, 0, thickness], dtype=np.float32)
    v = np.vstack([bottom, top]).astype(np.float32)
    return v, _BOX_FACES


def disc_mesh(centre: np.ndarray, radius: float, height: float,
              n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Closed cylinder of ``radius`` with its top face at ``centre`` (z up)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n)])
    c = np.asarray(centre, dtype=float)
    v = np.vstack([ring + c, ring + c - [0, 0, height], [c, c - [0, 0, height]]])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, n + i, j], [j, n + i, n + j], [2 * n, i, j], [2 * n + 1, n + j, n + i]]
    return v.astype(np.float32), np.array(faces, dtype=np.uint32)


def pyramid_mesh(centre: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Square pyramid of base side ``size`` standing on ``centre``, apex height ``size / 2``."""
    h = size / 2
    offsets = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0], [0, 0, size / 2]])
    v = (np.asarray(centre, dtype=float) + offsets).astype(np.float32)
    faces = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]],
                     dtype=np.uint32)
    return v, faces


def plane_mesh(alpha: float, beta: float, delta: float, centre: tuple[float, float],
               size: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Rectangle on ``z = alpha x + beta y + delta`` (two triangles, both sides drawn)."""
    cx, cy = centre
    hx, hy = size[0] / 2, size[1] / 2
    xy = np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])
    z = alpha * xy[:, 0] + beta * xy[:, 1] + delta
    return (np.column_stack([xy, z]).astype(np.float32),
            np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32))


def ellipsoid_axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma semi-axes (n, 3) and orientations wxyz (n, 4) of covariances (n, 3, 3).

    ``cov = V diag(s^2) V^T`` (eigen-decomposition); a unit sphere scaled by ``s`` and rotated
    by ``V`` is the 1-sigma ellipsoid.
    """
    w, v = np.linalg.eigh(np.asarray(cov, dtype=float))
    v = v * np.sign(np.linalg.det(v))[:, None, None]  # proper rotations
    return np.sqrt(np.clip(w, 0.0, None)), Rotation.from_matrix(v).as_quat(scalar_first=True)


def _unit_sphere(n_lat: int = 10, n_lon: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1: vertices (2 + (n_lat - 1) n_lon, 3), triangle faces."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    tt, pp = np.meshgrid(lat, lon, indexing="ij")
    ring = np.column_stack([np.sin(tt).ravel() * np.cos(pp).ravel(),
                            np.sin(tt).ravel() * np.sin(pp).ravel(), np.cos(tt).ravel()])
    v = np.vstack([[0, 0, 1], ring, [0, 0, -1]]).astype(np.float32)
    south = len(v) - 1

    def idx(i: int, j: int) -> int:
        return 1 + i * n_lon + j % n_lon
    faces = [[0, idx(0, j), idx(0, j + 1)] for j in range(n_lon)]
    for i in range(n_lat - 2):
        for j in range(n_lon):
            faces += [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)],
                      [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]
    faces += [[south, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)] for j in range(n_lon)]
    return v, np.array(faces, dtype=np.uint32)


def _wxyz(rotation: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rotation).as_quat(scalar_first=True)


@dataclass(frozen=True)
class Beam:
    """Beam point ``T`` and direction ``u'`` in the flange frame (mm)."""

    t: np.ndarray
    u: np.ndarray


class WorkcellScene:
    """Scene handles for the workcell (created once in ``__init__``, then only updated)."""

    def __init__(self, server, workcell, gui_legend=None) -> None:
        sc = server.scene
        self._server = server
        self.workcell = workcell
        sc.set_up_direction("+z")
        # no HDRI (it would be fetched from the internet) and no shadows (slow in software GL)
        sc.configure_environment_map(hdri=None)
        sc.configure_default_lights(enabled=True, cast_shadow=False)
        cam = server.initial_camera
        cam.look_at = (10.0, 80.0, 10.0)
        cam.position = (150.0, -60.0, 140.0)
        cam.far = 5000.0
        self.root = sc.add_frame("/cell", show_axes=False)
        plate, side = workcell.plate, workcell.side_plate
        v, f = slab_mesh(plate.corners(), plate.thickness)
        self.glass = sc.add_mesh_simple("/cell/glass_plate", v, f, color=(170, 215, 235),
                                        opacity=0.35, side="double")
        v, f = slab_mesh(side.corners(), side.thickness)
        self.side_plate = sc.add_mesh_simple("/cell/side_plate", v, f, color=(176, 180, 186),
                                             flat_shading=True)
        pyr = workcell.pyramid
        c = np.asarray(pyr.centre, dtype=float)
        v, f = disc_mesh(c, pyr.platform_radius, 4.0)
        self.platform = sc.add_mesh_simple("/cell/platform", v, f, color=(90, 90, 100))
        v, f = pyramid_mesh(c, pyr.size)
        self.pyramid = sc.add_mesh_simple("/cell/platform/pyramid", v, f, color=(200, 160, 90),
                                          flat_shading=True)
        corners = workcell.camera.fov_corners(plate)
        eye = np.append(np.mean(corners[:, :2], axis=0), plate.delta - 60.0)
        rect = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
        rays = np.stack([np.repeat(eye[None], 4, axis=0), corners], axis=1)
        self.camera_fov = sc.add_line_segments(
            "/cell/camera_fov", np.concatenate([rect, rays]).astype(np.float32),
            colors=(40, 120, 220), thickness=1.5, thickness_units="screen")
        # robot: flange frame with body, bracket, beam under it (flange frame coordinates)
        self.flange = sc.add_frame("/cell/flange", axes_length=12.0, axes_radius=0.6)
        nominal = Beam(workcell.beam.t, workcell.beam.u_prime)
        head = nominal.t + workcell.sensor.reference_distance * workcell.beam.direction
        v, f = box_mesh(np.array([-12.0, -12.0, 0.0]), np.array([12.0, 12.0, 120.0]))
        self.robot_body = sc.add_mesh_simple("/cell/flange/robot_body", v, f,
                                             color=(230, 120, 40), flat_shading=True)
        lo = np.minimum([0.0, 0.0, 0.0], head) - 4.0
        hi = np.maximum([0.0, 0.0, 0.0], head) + 4.0
        lo[2], hi[2] = head[2] - 2.0, head[2] + 6.0
        v, f = box_mesh(lo, hi)
        self.bracket = sc.add_mesh_simple("/cell/flange/sensor_bracket", v, f,
                                          color=(110, 110, 120), flat_shading=True)
        self.beam_line = sc.add_line_segments(
            "/cell/flange/beam", np.array([[head, nominal.t]], dtype=np.float32),
            colors=(255, 30, 30), thickness=2.0, thickness_units="screen")
        self.live_spot = sc.add_icosphere("/cell/live_spot", radius=0.8, color=(255, 40, 40),
                                          visible=False)
        # session and solve results (empty until there is data)
        empty = np.zeros((0, 3), dtype=np.float32)
        self.spots = sc.add_point_cloud("/cell/spots", empty, colors=(90, 90, 90),
                                        point_size=0.35, precision="float32",
                                        point_shape="circle")
        v, f = plane_mesh(plate.alpha, plate.beta, plate.delta, plate.centre, plate.size)
        self.fitted_plane = sc.add_mesh_simple("/cell/fitted_plane", v, f, color=(60, 200, 120),
                                               opacity=0.3, side="double", visible=False)
        self.error_arrows = sc.add_arrows("/cell/errors", np.zeros((0, 2, 3), np.float32),
                                          colors=(230, 60, 60), shaft_radius=0.12,
                                          head_radius=0.35, head_length=0.8, visible=False)
        sv, sf = _unit_sphere()
        self.ellipsoids = sc.add_batched_meshes_simple(
            "/cell/ellipsoids", sv, sf, np.zeros((0, 4), np.float32), empty,
            batched_scales=np.zeros((0, 3), np.float32), batched_colors=(250, 150, 40),
            opacity=0.45, visible=False)
        self.grid_preview = sc.add_batched_axes(
            "/cell/grid_preview", np.zeros((0, 4), np.float32), empty, axes_length=3.0,
            axes_radius=0.25, visible=False)
        self.legend = gui_legend
        self._beam = nominal
        self._error_starts = np.zeros((0, 3))
        self._error_vectors = np.zeros((0, 3))
        self.arrow_scale = 1000.0
        self.pose_updates = 0

    # -- robot and live view ------------------------------------------------------------------
    def set_beam(self, t: np.ndarray, u: np.ndarray) -> None:
        """Use beam ``T``, ``u'`` (flange frame) for the drawn beam and live spot."""
        self._beam = Beam(np.asarray(t, float), np.asarray(u, float))

    def set_pose(self, position: np.ndarray, rotation: np.ndarray, d: float | None,
                 reading_known: bool = True) -> None:
        """Move flange, robot and beam to the pose; the live spot at ``O + R (T + d u')``.

        ``d`` None hides the spot (out of range); ``reading_known`` False (a pose with no reading
        yet) moves the flange and leaves beam and spot until the next reading.
        """
        position = np.asarray(position, dtype=float)
        rotation = np.asarray(rotation, dtype=float)
        beam = self._beam
        head = beam.t + self.workcell.sensor.reference_distance * (
            beam.u / max(np.linalg.norm(beam.u), 1e-12))
        end = beam.t + (d if d is not None else -self.workcell.sensor.range) * beam.u
        with self._scene_atomic():
            self.flange.position = position
            self.flange.wxyz = _wxyz(rotation)
            if not reading_known:
                pass
            elif d is None:
                self.beam_line.points = np.array([[head, end]], dtype=np.float32)
                self.live_spot.visible = False
            else:
                self.beam_line.points = np.array([[head, end]], dtype=np.float32)
                self.live_spot.position = position + rotation @ end
                self.live_spot.visible = True
        self.pose_updates += 1

    # -- session and results -----------------------------------------------------------------
    def set_spots(self, points: np.ndarray, residual_norm: np.ndarray | None = None,
                  excluded: np.ndarray | None = None) -> None:
        """Collected spots (n, 3) mm, coloured by ``|residual|`` (mm) when given."""
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if residual_norm is None or len(residual_norm) != len(pts):
            colors = np.tile(np.array([[120, 120, 120]], np.uint8), (len(pts), 1))
            vmax = 0.0
        else:
            r = np.asarray(residual_norm, dtype=float)
            vmax = float(np.max(r)) if r.size else 0.0
            colors = colormap(r, vmax)
        if excluded is not None and len(excluded) == len(pts):
            colors[np.asarray(excluded, bool)] = (255, 0, 255)
        self.spots.points = pts
        self.spots.colors = colors
        if self.legend is not None:
            self.legend.content = legend_html(vmax * 1000.0) if vmax > 0 else (
                "<small>spots: grey until solved</small>")

    def set_plane(self, alpha: float, beta: float, delta: float) -> None:
        plate = self.workcell.plate
        v, _ = plane_mesh(alpha, beta, delta, plate.centre, plate.size)
        self.fitted_plane.vertices = v
        self.fitted_plane.visible = True

    def set_errors(self, starts: np.ndarray, vectors: np.ndarray) -> None:
        """Error vectors (n, 3) mm at ``starts``, drawn ``arrow_scale`` times longer."""
        self._error_starts = np.asarray(starts, float).reshape(-1, 3)
        self._error_vectors = np.asarray(vectors, float).reshape(-1, 3)
        self._draw_errors()
        self.error_arrows.visible = len(self._error_starts) > 0

    def set_arrow_scale(self, k: float) -> None:
        """Exaggeration of the error vectors, clipped to x10 .. x5000."""
        self.arrow_scale = float(np.clip(k, *ARROW_SCALE_RANGE))
        self._draw_errors()

    def _draw_errors(self) -> None:
        s = self._error_starts
        self.error_arrows.points = np.stack(
            [s, s + self.arrow_scale * self._error_vectors], axis=1).astype(np.float32)

    def set_ellipsoids(self, centres: np.ndarray, covariances: np.ndarray) -> None:
        """1-sigma ellipsoids of points (covariances (n, 3, 3) mm^2), x the arrow scale."""
        centres = np.asarray(centres, float).reshape(-1, 3)
        if len(centres) == 0:
            self.ellipsoids.visible = False
            return
        axes, wxyz = ellipsoid_axes(covariances)
        self.ellipsoids.batched_positions = centres.astype(np.float32)
        self.ellipsoids.batched_wxyzs = wxyz.astype(np.float32)
        self.ellipsoids.batched_scales = (axes * self.arrow_scale).astype(np.float32)

    def set_grid_preview(self, positions: np.ndarray, rotations: np.ndarray) -> None:
        """Planned flange poses as a batch of small frames."""
        positions = np.asarray(positions, float).reshape(-1, 3)
        wxyz = (Rotation.from_matrix(rotations).as_quat(scalar_first=True)
                if len(positions) else np.zeros((0, 4)))
        self.grid_preview.batched_positions = positions.astype(np.float32)
        self.grid_preview.batched_wxyzs = wxyz.astype(np.float32)
        self.grid_preview.visible = len(positions) > 0

    def _scene_atomic(self):
        return self._server.atomic()
