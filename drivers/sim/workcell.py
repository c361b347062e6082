"""The simulated workcell file (TOML): true beam, plates, pyramid placement, noise, limits.

``load_workcell()`` reads ``static_data/workcell_default.toml`` (the seed's cell) through
``importlib.resources``; ``load_workcell(path)`` reads another file. Every table and key is
checked: a missing, unknown or ill-typed key raises :class:`InputError` naming the file and the
key. Units: mm and degrees.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from calib_core.errors import InputError
from calib_core.io import load_toml
from calib_core.noise import NoiseModel
from drivers.base import SoftLimits

DEFAULT_WORKCELL = "workcell_default.toml"


def apply_homography(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``(x', y') = (h0 . (x, y, 1), h1 . (x, y, 1)) / h2 . (x, y, 1)`` for points (n, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return np.column_stack([(h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w,
                            (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w])


@dataclass(frozen=True)
class Beam:
    """True beam in the flange frame: ``T = (x_t, y_t, z_t)`` and ``u' = gain * (a, b, c)``.

    ``(a, b, c)`` is a unit direction (normalised on load); ``z_t`` is relative to the glass
    plate datum. The sensor reports ``d = s / gain`` for a spot at distance ``s`` from ``T``
    along the beam, so ``P = O + R (T + d u')`` holds exactly.
    """

    x_t: float
    y_t: float
    z_t: float
    a: float
    b: float
    c: float
    gain: float

    @property
    def t(self) -> np.ndarray:
        return np.array([self.x_t, self.y_t, self.z_t])

    @property
    def direction(self) -> np.ndarray:
        """Unit beam direction ``u`` (flange frame)."""
        return np.array([self.a, self.b, self.c])

    @property
    def u_prime(self) -> np.ndarray:
        """``u' = gain * u``: the direction vector the linear model identifies."""
        return self.gain * self.direction


@dataclass(frozen=True)
class Plate:
    """A flat plate ``z = alpha x + beta y + delta``, a ``size`` rectangle around ``centre``."""

    alpha: float
    beta: float
    delta: float
    centre: tuple[float, float]
    size: tuple[float, float]
    thickness: float

    def z_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Height of the top surface: ``z = alpha x + beta y + delta``."""
        return self.alpha * x + self.beta * y + self.delta

    def contains(self, x: float, y: float) -> bool:
        """True when ``(x, y)`` lies inside the plate's rectangle (closed)."""
        return (abs(x - self.centre[0]) <= self.size[0] / 2
                and abs(y - self.centre[1]) <= self.size[1] / 2)

    @property
    def normal(self) -> np.ndarray:
        """Unit upward normal ``(-alpha, -beta, 1) / norm``."""
        n = np.array([-self.alpha, -self.beta, 1.0])
        return n / np.linalg.norm(n)

    def corners(self) -> np.ndarray:
        """The four top-surface corners (4, 3), counter-clockwise seen from above."""
        cx, cy = self.centre
        hx, hy = self.size[0] / 2, self.size[1] / 2
        xy = np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy],
                       [cx - hx, cy + hy]])
        return np.column_stack([xy, self.z_at(xy[:, 0], xy[:, 1])])


@dataclass(frozen=True)
class PyramidPlacement:
    """Centre of the 2-dof platform carrying the pyramid (fixed frame) and nominal sizes."""

    centre: tuple[float, float, float]
    size: float
    platform_radius: float


@dataclass(frozen=True)
class SensorSpec:
    """Displacement sensor: readings beyond ``+-range`` of the zero are out-of-range."""

    range: float
    reference_distance: float


@dataclass(frozen=True)
class CameraSpec:
    """Bottom camera: plate mm -> pixel model and the rendering parameters of the spot.

    Ideal pixel ``p = c + Rot(rotation_deg) (x - fov_centre) / pixel_size_mm`` with
    ``c = (resolution - 1) / 2``; the lens adds radial distortion ``k1`` on ``(p - c) / focal_px``
    (see :meth:`project`).
    """

    resolution: tuple[int, int]
    pixel_size_mm: float
    fov_centre: tuple[float, float]
    rotation_deg: float
    focal_px: float
    k1: float
    spot_sigma_px: float
    spot_aspect: float
    spot_peak: float
    speckle: float
    background: float
    texture: float
    sensor_noise: float
    bit_depth: int

    @property
    def fov_extent(self) -> tuple[float, float]:
        """Field of view along the image axes at the plate, mm: ``resolution * pixel_size_mm``."""
        return (self.resolution[0] * self.pixel_size_mm, self.resolution[1] * self.pixel_size_mm)

    def homography(self) -> np.ndarray:
        """3x3 ``H`` mapping plate ``(x, y, 1)`` (mm) to ideal (undistorted) pixels ``(u, v, 1)``.

        ``[u, v] = c + Rot(rotation_deg) ([x, y] - fov_centre) / pixel_size_mm``.
        """
        t = math.radians(self.rotation_deg)
        k = 1.0 / self.pixel_size_mm
        rot = k * np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        h = np.eye(3)
        h[0:2, 0:2] = rot
        h[0:2, 2] = self.principal_point - rot @ np.asarray(self.fov_centre)
        return h

    @property
    def principal_point(self) -> np.ndarray:
        """Image centre ``c = ((W - 1) / 2, (H - 1) / 2)`` (OpenCV: pixel 0's centre is 0)."""
        return np.array([(self.resolution[0] - 1) / 2, (self.resolution[1] - 1) / 2])

    def camera_matrix(self) -> np.ndarray:
        """OpenCV intrinsic matrix ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``."""
        cx, cy = self.principal_point
        return np.array([[self.focal_px, 0.0, cx], [0.0, self.focal_px, cy], [0.0, 0.0, 1.0]])

    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion vector ``(k1, k2, p1, p2, k3) = (k1, 0, 0, 0, 0)``."""
        return np.array([self.k1, 0.0, 0.0, 0.0, 0.0])

    def project(self, xy: np.ndarray) -> np.ndarray:
        """Plate ``(n, 2)`` mm to distorted pixels ``(n, 2)``.

        ``p_ideal = H (x, y, 1)``, ``q = (p_ideal - c) / f``, ``p = c + f q (1 + k1 |q|^2)``.
        """
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        q = (apply_homography(self.homography(), xy) - self.principal_point) / self.focal_px
        r2 = np.sum(q * q, axis=1, keepdims=True)
        return self.principal_point + self.focal_px * q * (1.0 + self.k1 * r2)

    def unproject(self, uv: np.ndarray, iterations: int = 5) -> np.ndarray:
        """Distorted pixels ``(n, 2)`` to plate mm ``(n, 2)``, the inverse of :meth:`project`.

        Undistort by the fixed point ``q <- q_d / (1 + k1 |q|^2)`` (``q_d = (p - c) / f``),
        then ``H^-1``.
        """
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        qd = (uv - self.principal_point) / self.focal_px
        q = qd.copy()
        for _ in range(iterations):  # converges by a factor ~2 |k1| |q|^2 per step
            r2 = np.einsum("ij,ij->i", q, q)[:, None]
            np.divide(qd, 1.0 + self.k1 * r2, out=q)
        ideal = self.principal_point + self.focal_px * q
        return apply_homography(np.linalg.inv(self.homography()), ideal)

    def in_view(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True for pixels ``(n, 2)`` at least ``margin`` px inside the image."""
        uv = np.atleast_2d(uv)
        w, h = self.resolution
        return ((uv[:, 0] >= margin) & (uv[:, 0] <= w - 1 - margin)
                & (uv[:, 1] >= margin) & (uv[:, 1] <= h - 1 - margin))

    def fov_corners(self, plate: Plate) -> np.ndarray:
        """Corners (4, 3) of the (undistorted) field of view on ``plate``, for drawing."""
        w, h = self.fov_extent
        t = math.radians(self.rotation_deg)
        rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
        xy = np.asarray(self.fov_centre) + local @ rot  # inverse rotation: image -> plate
        return np.column_stack([xy, plate.z_at(xy[:, 0], xy[:, 1])])


@dataclass(frozen=True)
class Timing:
    move_time_s: float


@dataclass(frozen=True)
class Workcell:
    """A whole simulated cell as read from its TOML file (``source`` names the file)."""

    source: str
    name: str
    beam: Beam
    plate: Plate
    side_plate: Plate
    pyramid: PyramidPlacement
    noise: NoiseModel
    sensor: SensorSpec
    camera: CameraSpec
    limits: SoftLimits
    timing: Timing

    def truth(self) -> dict[str, float]:
        """The parameters a calibration on the glass plate should recover (sensor not re-zeroed).

        ``z_t_minus_delta = z_t - delta``; ``a, b, c`` are ``u' = gain * u``.
        """
        u = self.beam.u_prime
        return {
            "x_t": self.beam.x_t, "y_t": self.beam.y_t, "z_t": self.beam.z_t,
            "z_t_minus_delta": self.beam.z_t - self.plate.delta,
            "a": float(u[0]), "b": float(u[1]), "c": float(u[2]),
            "alpha": self.plate.alpha, "beta": self.plate.beta, "delta": self.plate.delta,
            "gain": self.beam.gain,
        }


class _Reader:
    """Typed access to one TOML table with errors naming the file and ``[table] key``."""

    def __init__(self, data: Mapping[str, Any], source: str, table: str) -> None:
        self.source, self.table = source, table
        value = data.get(table)
        if value is None:
            raise InputError(f"{source}: missing table [{table}]")
        if not isinstance(value, Mapping):
            raise InputError(f"{source}: [{table}] must be a table")
        self.data = value
        self.used: set[str] = set()

    def _where(self, key: str) -> str:
        return f"{self.source}: [{self.table}] {key}"

    def _get(self, key: str) -> Any:
        if key not in self.data:
            raise InputError(f"{self._where(key)}: missing key")
        self.used.add(key)
        return self.data[key]

    def _num(self, key: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"{self._where(key)}: must be a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(f"{self._where(key)}: must be finite, got {value}")
        return float(value)

    def num(self, key: str, lo: float = -math.inf, hi: float = math.inf,
            lo_open: bool = False) -> float:
        value = self._num(key, self._get(key))
        if value < lo or value > hi or (lo_open and value == lo):
            bound = f"> {lo:g}" if lo_open else f"in [{lo:g}, {hi:g}]"
            raise InputError(f"{self._where(key)}: must be {bound}, got {value:g}")
        return value

    def vec(self, key: str, n: int, positive: bool = False) -> tuple[float, ...]:
        value = self._get(key)
        if not isinstance(value, list) or len(value) != n:
            raise InputError(f"{self._where(key)}: must be a list of {n} numbers, got {value!r}")
        out = tuple(self._num(key, v) for v in value)
        if positive and min(out) <= 0:
            raise InputError(f"{self._where(key)}: every entry must be > 0, got {value!r}")
        return out

    def text(self, key: str) -> str:
        value = self._get(key)
        if not isinstance(value, str):
            raise InputError(f"{self._where(key)}: must be a string, got {value!r}")
        return value

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise InputError(f"{self.source}: [{self.table}] unknown key(s) {', '.join(unknown)}")


def _plate(data: Mapping[str, Any], source: str, table: str) -> Plate:
    r = _Reader(data, source, table)
    plate = Plate(alpha=r.num("alpha", -1.0, 1.0), beta=r.num("beta", -1.0, 1.0),
                  delta=r.num("delta"), centre=r.vec("centre", 2),  # type: ignore[arg-type]
                  size=r.vec("size", 2, positive=True),  # type: ignore[arg-type]
                  thickness=r.num("thickness", 0.0))
    r.done()
    return plate


def workcell_from_mapping(data: Mapping[str, Any], source: str = "workcell") -> Workcell:
    """Validate a parsed workcell TOML document and build the :class:`Workcell`."""
    known = {"cell", "beam", "plate", "side_plate", "pyramid", "noise", "sensor", "camera",
             "limits", "timing"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise InputError(f"{source}: unknown table(s) {', '.join(unknown)}; "
                         f"expected {', '.join(sorted(known))}")

    r = _Reader(data, source, "cell")
    name = r.text("name")
    r.done()

    r = _Reader(data, source, "beam")
    t = (r.num("x_t"), r.num("y_t"), r.num("z_t"))
    abc = np.array([r.num("a"), r.num("b"), r.num("c")])
    norm = float(np.linalg.norm(abc))
    if norm < 1e-9:
        raise InputError(f"{source}: [beam] a, b, c: the direction must not be zero")
    abc = abc / norm
    beam = Beam(*t, *(float(v) for v in abc), gain=r.num("gain", 0.0, lo_open=True))
    r.done()

    plate = _plate(data, source, "plate")
    side_plate = _plate(data, source, "side_plate")

    r = _Reader(data, source, "pyramid")
    pyramid = PyramidPlacement(centre=r.vec("centre", 3),  # type: ignore[arg-type]
                               size=r.num("size", 0.0, lo_open=True),
                               platform_radius=r.num("platform_radius", 0.0, lo_open=True))
    r.done()

    if "noise" not in data or not isinstance(data["noise"], Mapping):
        raise InputError(f"{source}: missing table [noise]")
    missing = sorted({f.name for f in fields(NoiseModel)} - set(data["noise"]))
    if missing:
        raise InputError(f"{source}: [noise] missing key(s) {', '.join(missing)}")
    noise = NoiseModel.from_mapping(data["noise"], source=f"{source}: [noise]")

    r = _Reader(data, source, "sensor")
    sensor = SensorSpec(range=r.num("range", 0.0, lo_open=True),
                        reference_distance=r.num("reference_distance", 0.0, lo_open=True))
    r.done()

    r = _Reader(data, source, "camera")
    res = r.vec("resolution", 2, positive=True)
    if any(v != int(v) or v < 16 for v in res):
        raise InputError(f"{source}: [camera] resolution: two integers >= 16, got {res!r}")
    camera = CameraSpec(
        resolution=(int(res[0]), int(res[1])),
        pixel_size_mm=r.num("pixel_size_mm", 0.0, lo_open=True),
        fov_centre=r.vec("fov_centre", 2),  # type: ignore[arg-type]
        rotation_deg=r.num("rotation_deg", -180.0, 180.0),
        focal_px=r.num("focal_px", 0.0, lo_open=True), k1=r.num("k1", -1.0, 1.0),
        spot_sigma_px=r.num("spot_sigma_px", 0.3, 100.0),
        spot_aspect=r.num("spot_aspect", 1.0, 10.0), spot_peak=r.num("spot_peak", 0.0),
        speckle=r.num("speckle", 0.0, 1.0), background=r.num("background", 0.0),
        texture=r.num("texture", 0.0), sensor_noise=r.num("sensor_noise", 0.0),
        bit_depth=int(r.num("bit_depth", 8, 16)),
    )
    if camera.bit_depth not in (8, 12, 16):
        raise InputError(f"{source}: [camera] bit_depth must be 8, 12 or 16, "
                         f"got {camera.bit_depth}")
    r.done()

    r = _Reader(data, source, "limits")
    boxes = {}
    for key in ("x", "y", "z", "theta_deg"):
        lo, hi = r.vec(key, 2)
        if not lo < hi:
            raise InputError(f"{source}: [limits] {key}: need lo < hi, got [{lo:g}, {hi:g}]")
        boxes[key] = (lo, hi)
    limits = SoftLimits(**boxes, max_step=r.num("max_step", 0.0, lo_open=True))
    r.done()

    r = _Reader(data, source, "timing")
    timing = Timing(move_time_s=r.num("move_time_s", 0.0, 60.0))
    r.done()

    return Workcell(source=source, name=name, beam=beam, plate=plate, side_plate=side_plate,
                    pyramid=pyramid, noise=noise, sensor=sensor, camera=camera, limits=limits,
                    timing=timing)


def load_workcell(path: str | Path | None = None) -> Workcell:
    """Read a workcell TOML file; ``None`` loads the packaged default (the seed's cell)."""
    data, source = load_toml(path, DEFAULT_WORKCELL, "workcell file")
    return workcell_from_mapping(data, source)
