"""Fixtures: protocol emulators on a pty and the real serial drivers connected to them."""

from __future__ import annotations

import pytest

from drivers.base import SoftLimits
from drivers.emulators import GrblEmulator, KeyenceEmulator
from drivers.grbl import GrblRobot
from drivers.keyence_il import KeyenceIL

#: Short per-attempt timeout so fault tests stay fast (the real unit answers within 0.5 s).
TIMEOUT = 0.2
LIMITS = SoftLimits(x=(-100.0, 100.0), y=(-100.0, 100.0), z=(0.0, 200.0),
                    theta_deg=(-180.0, 180.0), max_step=20.0)


class Physics:
    """A settable true displacement (mm, None = nothing in range)."""

    def __init__(self, value: float | None = 1.234) -> None:
        self.value = value

    def __call__(self) -> float | None:
        return self.value


@pytest.fixture
def physics() -> Physics:
    return Physics()


@pytest.fixture
def keyence(physics):
    emu = KeyenceEmulator(physics).start()
    yield emu
    emu.close()
    assert emu.errors == []


@pytest.fixture
def sensor(keyence):
    drv = KeyenceIL(keyence.path, timeout=TIMEOUT, retries=2)
    yield drv
    drv.close()


@pytest.fixture
def grbl():
    emu = GrblEmulator().start()
    yield emu
    emu.close()
    assert emu.errors == []


@pytest.fixture
def robot(grbl):
    drv = GrblRobot(grbl.path, LIMITS, timeout=TIMEOUT, retries=2, settle_timeout=0.5)
    yield drv
    drv.close()
