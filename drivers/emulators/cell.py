"""GRBL and Keyence emulators backed by the simulated workcell physics (:mod:`drivers.sim`).

The world's flange follows the GRBL emulator (work coordinates, theta = A; set at the end of
each move, and at each sensor reading also mid-move), so a simulated camera on the same world
sees the spot at the emulated robot's pose. The Keyence displacement is
:meth:`drivers.sim.world.SimWorld.read_sensor` at that pose (beam to the first plate surface,
sensor noise, out-of-range -> ``+99.999``). The robot reports its own position exactly (no
repeatability noise on this path); the camera is not emulated (use a simulated camera).
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
        self._last: FlangePose | None = None
        self.grbl = GrblEmulator(move_time=move_time, start=(p.x, p.y, p.z, p.theta_deg),
                                 on_arrive=self._follow)
        self.keyence = KeyenceEmulator(self.displacement)

    def _follow(self, work: tuple[float, ...]) -> None:
        """Put the world's flange where the robot is (once per distinct pose)."""
        pose = FlangePose(*work)
        with self.world.lock:
            if pose != self._last:
                self.world.move(pose)
                self._last = pose

    def displacement(self) -> float | None:
        """The sensor reading (mm) at the GRBL emulator's current pose; None out of range."""
        with self.world.lock:
            self._follow(self.grbl.position)
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
