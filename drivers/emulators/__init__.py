"""Protocol emulators serving on a pseudo-terminal, for byte-for-byte driver tests.

``KeyenceEmulator`` (DL-RS1A) and ``GrblEmulator`` (GRBL 1.1) run a background thread on the
master side of ``pty.openpty()``; drivers open :attr:`PtyEmulator.path` with pyserial. Faults are
injected with :meth:`PtyEmulator.inject`; every line received is kept in ``received``.
``CellEmulators`` pairs both on the simulated workcell physics.
"""

from drivers.emulators.base import Fault, PtyEmulator
from drivers.emulators.cell import CellEmulators
from drivers.emulators.grbl import GrblEmulator
from drivers.emulators.keyence import KeyenceEmulator

__all__ = ["CellEmulators", "Fault", "GrblEmulator", "KeyenceEmulator", "PtyEmulator"]
