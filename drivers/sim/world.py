"""Physics of the simulated workcell: the true flange pose, the beam, the plates, the noise.

Conventions (mm, degrees):

- The flange is at the commanded pose exactly; the robot *reports* it with a repeatability
  error drawn once per move (``robot_xy`` on x, y, ``robot_z`` on z, ``robot_theta_deg`` on
  theta, or about each axis for a quaternion pose).
- The beam starts at ``P0 = O + R T`` and runs along ``R u'`` with ``u' = gain * u``
  (``|u| = 1``). The spot is the first plate surface met coming from the sensor head
  (largest ``s``), ``P = P0 + s R u'``; the sensor reports ``d = s - d0 + noise``, i.e. the
  distance along the beam divided by ``gain``, minus the zero offset ``d0`` (0 until
  :meth:`SimWorld.zero_sensor`); it is out of range when ``|s| > range`` (a physical window
  around ``T``, which sits at the reference distance from the head). Hence
  ``P = O + R (T + d0 u' + d u')`` holds exactly and the linear model recovers
  ``T_eff = T + d0 u'`` and ``u'`` (see :meth:`SimWorld.truth`).
- The camera sees the spot only on the glass plate, >= 10 px inside its image; its measured
  ``x_p, y_p`` carries ``noise.camera`` per axis (fresh draw per sample).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.base import FlangePose, ReadingStatus, SensorReading
from drivers.sim.workcell import Plate, Workcell


def pose_rotation(pose: FlangePose) -> np.ndarray:
    """``R`` of a flange pose: from its quaternion (w, x, y, z) if set, else ``Rz(theta)``."""
    if pose.quaternion is not None:
        return Rotation.from_quat(np.asarray(pose.quaternion, dtype=float),
                                  scalar_first=True).as_matrix()
    t = math.radians(pose.theta_deg)
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class BeamHit:
    """Where the beam meets a surface: its ``surface`` name, the point ``p`` (3,) and ``s``.

    ``s`` is the beam parameter of ``P = P0 + s R u'`` (the raw reading before zeroing/noise).
    """

    surface: str
    p: np.ndarray
    s: float


def intersect_plate(p0: np.ndarray, direction: np.ndarray, plate: Plate) -> float | None:
    """Parameter ``s`` where ``p0 + s direction`` meets ``z = alpha x + beta y + delta``.

    ``s = (delta - n.p0) / (n.direction)`` with ``n = (-alpha, -beta, 1)``; None when the beam
    is parallel to the plate or the point is outside the plate's rectangle.
    """
    n = np.array([-plate.alpha, -plate.beta, 1.0])
    den = float(n @ direction)
    if abs(den) < 1e-12:
        return None
    s = (plate.delta - float(n @ p0)) / den
    p = p0 + s * direction
    return s if plate.contains(float(p[0]), float(p[1])) else None


class SimWorld:
    """The true state of the simulated cell, shared by the simulated robot, sensor and camera.

    Thread-safe (one lock); all randomness comes from ``numpy.random.default_rng(seed)``.
    """

    def __init__(self, workcell: Workcell, seed: int | None = 0) -> None:
        self.workcell = workcell
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._pose = FlangePose(0.0, 0.0, float(np.clip(20.0, *workcell.limits.z)), 0.0)
        self._pose_error = np.zeros(6)  # dx dy dz (mm), rotation vector (deg), reported - true
        self._d0 = 0.0

    # -- robot ---------------------------------------------------------------------------
    @property
    def true_pose(self) -> FlangePose:
        with self._lock:
            return self._pose

    def move(self, target: FlangePose) -> None:
        """Put the flange at ``target`` and draw the reported pose's repeatability error."""
        nz = self.workcell.noise
        with self._lock:
            self._pose = target
            e = self._rng.normal(size=6)
            e[0:2] *= nz.robot_xy
            e[2] *= nz.robot_z
            if target.quaternion is None:
                e[3:5] = 0.0
            e[3:6] *= nz.robot_theta_deg
            self._pose_error = e

    def reported_pose(self) -> FlangePose:
        """The pose as the controller reports it: true pose plus this move's error."""
        with self._lock:
            p, e = self._pose, self._pose_error
            if p.quaternion is None:
                return FlangePose(p.x + e[0], p.y + e[1], p.z + e[2], p.theta_deg + e[5])
            r = Rotation.from_rotvec(np.radians(e[3:6])) * Rotation.from_quat(
                np.asarray(p.quaternion, dtype=float), scalar_first=True)
            q = r.as_quat(scalar_first=True)
            q = q if q[0] >= 0 else -q
            theta = math.degrees(math.atan2(r.as_matrix()[1, 0], r.as_matrix()[0, 0]))
            return FlangePose(p.x + e[0], p.y + e[1], p.z + e[2], theta,
                              tuple(float(v) for v in q))  # type: ignore[arg-type]

    # -- geometry ------------------------------------------------------------------------
    def beam_origin_direction(self, pose: FlangePose | None = None) -> tuple[np.ndarray,
                                                                             np.ndarray]:
        """``P0 = O + R T`` and ``R u'`` in the fixed frame for ``pose`` (default: true pose)."""
        pose = self.true_pose if pose is None else pose
        r = pose_rotation(pose)
        beam = self.workcell.beam
        return (np.array([pose.x, pose.y, pose.z]) + r @ beam.t, r @ beam.u_prime)

    def beam_hit(self, pose: FlangePose | None = None) -> BeamHit | None:
        """The first surface the beam meets coming down from the sensor head, or None."""
        p0, direction = self.beam_origin_direction(pose)
        head = self.workcell.sensor.reference_distance / self.workcell.beam.gain
        best: BeamHit | None = None
        for name, plate in (("plate", self.workcell.plate),
                            ("side_plate", self.workcell.side_plate)):
            s = intersect_plate(p0, direction, plate)
            if s is not None and s < head and (best is None or s > best.s):
                best = BeamHit(name, p0 + s * direction, s)
        return best

    # -- sensor --------------------------------------------------------------------------
    def read_sensor(self) -> SensorReading:
        """One reading ``d = s + N(0, sensor) - d0``.

        Out-of-range when no surface is hit or the raw ``s + noise`` is beyond ``+-range``: the
        measuring window is physical (``T`` of the workcell file sits at the reference
        distance), whatever the zero.
        """
        with self._lock:
            hit = self.beam_hit()
            if hit is None:
                return SensorReading(ReadingStatus.OUT_OF_RANGE, raw="no surface")
            raw = hit.s + self._rng.normal(0.0, self.workcell.noise.sensor)
            d = raw - self._d0
            if abs(raw) > self.workcell.sensor.range:
                return SensorReading(ReadingStatus.OUT_OF_RANGE, raw=f"{d:+.3f}")
            return SensorReading(ReadingStatus.OK, float(d), raw=f"{d:+.6f}")

    def zero_sensor(self) -> bool:
        """Zero the sensor at the current (noise-free) reading; False if no surface is in range."""
        with self._lock:
            hit = self.beam_hit()
            if hit is None or abs(hit.s) > self.workcell.sensor.range:
                return False
            self._d0 = hit.s
            return True

    @property
    def sensor_zero(self) -> float:
        """Current zero offset ``d0`` (raw beam parameter that now reads 0)."""
        with self._lock:
            return self._d0

    # -- camera --------------------------------------------------------------------------
    def true_spot(self) -> np.ndarray | None:
        """The true spot (3,) when it is on the glass plate, else None (camera sees nothing)."""
        hit = self.beam_hit()
        return None if hit is None or hit.surface != "plate" else hit.p

    def camera_spot(self) -> np.ndarray | None:
        """The spot x, y as the calibrated camera measures it: true + N(0, camera) per axis."""
        with self._lock:
            p = self.true_spot()
            if p is None or not self.workcell.camera.in_view(
                    self.workcell.camera.project(p[0:2]), margin=10.0)[0]:
                return None
            return p[0:2] + self._rng.normal(0.0, self.workcell.noise.camera, size=2)

    def normal(self, size: int | tuple[int, ...] | None = None) -> np.ndarray:
        """Standard normal draws from the world's generator (for rendering)."""
        with self._lock:
            return self._rng.normal(size=size)

    @property
    def rng(self) -> np.random.Generator:
        """The world's generator; hold :attr:`lock` while drawing from another thread."""
        return self._rng

    @property
    def lock(self) -> threading.RLock:
        return self._lock

    # -- truth ---------------------------------------------------------------------------
    def truth(self) -> dict[str, float]:
        """The H a solver should recover now (glass plate, current zero).

        ``T_eff = T + d0 u'``; keys ``x_t y_t z_t z_t_minus_delta a b c alpha beta delta gain``
        with ``(a, b, c) = u'`` and ``z_t_minus_delta = z_t - delta``.
        """
        wc = self.workcell
        u = wc.beam.u_prime
        t = wc.beam.t + self.sensor_zero * u
        return {
            "x_t": float(t[0]), "y_t": float(t[1]), "z_t": float(t[2]),
            "z_t_minus_delta": float(t[2] - wc.plate.delta),
            "a": float(u[0]), "b": float(u[1]), "c": float(u[2]),
            "alpha": wc.plate.alpha, "beta": wc.plate.beta, "delta": wc.plate.delta,
            "gain": wc.beam.gain,
        }
