"""GRBL and Keyence emulators backed by the simulated workcell physics (:mod:`drivers.sim`).

The flange is where the GRBL emulator is (work coordinates, theta = A, also mid-move); the
Keyence displacement is :meth:`drivers.sim.world.SimWorld.read_sensor` at that pose (beam to
the first plate surface, sensor noise, out-of-range -> ``+99.999``). The robot reports its own
position exactly (no repeatability noise on this path); the camera is not emulated.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.base import FlangePose
from drivers.emulators.grbl import GrblEmulator
from drivers.emulators.keyence import KeyenceEmulator

if TYPE_CHECKING:
    from drivers.sim.world import SimWorld


class CellEmulators:
    """``grbl`` (robot) and ``keyence`` (sensor) emulators sharing one :class:`SimWorld`."""

    def __init__(self, world: SimWorld, *, move_time: float = 0.0,
                 start: FlangePose | None = None) -> None:
        self.world = world
        p = world.true_pose if start is None else start
        self.grbl = GrblEmulator(move_time=move_time, start=(p.x, p.y, p.z, p.theta_deg))
        self.keyence = KeyenceEmulator(self.displacement)
        self._last: FlangePose | None = None

    def displacement(self) -> float | None:
        """The sensor reading (mm) at the GRBL emulator's current pose; None out of range."""
        pose = FlangePose(*self.grbl.position)
        with self.world.lock:
            if pose != self._last:
                self.world.move(pose)
                self._last = pose
            reading = self.world.read_sensor()
        return reading.value if reading.ok else None

    def start(self) -> CellEmulators:
        self.grbl.start()
        self.keyence.start()
        return self

    def close(self) -> None:
        self.keyence.close()
        self.grbl.close()

    def __enter__(self) -> CellEmulators:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
