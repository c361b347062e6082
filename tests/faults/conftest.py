"""Shared pieces of the fault-injection suite: a small grid, the emulated cell, helpers."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from calib_core.grid import PoseGrid, paper_grid
from drivers.emulators import CellEmulators
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld

#: Per-attempt reply timeout of the serial drivers in these tests (the real units: 0.5-1 s).
TIMEOUT = 0.15
#: 5 sigma of the default cell's sensor noise (0.002 mm) plus the 0.001 mm wire quantum.
SENSOR_TOL = 5 * 0.002 + 0.001


def small_grid(n: int = 12) -> PoseGrid:
    """The first ``n`` poses of the seed's paper grid (two heights, three angles)."""
    return PoseGrid(np.asarray(paper_grid().poses[:n]), name=f"paper[:{n}]")


@pytest.fixture
def world() -> SimWorld:
    return SimWorld(load_workcell(), seed=11)


@pytest.fixture
def cell(world: SimWorld) -> Iterator[CellEmulators]:
    """GRBL + Keyence pty emulators following one simulated workcell."""
    with CellEmulators(world) as emus:
        yield emus
    assert emus.grbl.errors == [] and emus.keyence.errors == []
