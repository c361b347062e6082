"""Device faults through the dashboard's state and worker (no browser): an unplugged sensor
pauses the acquisition with a notification; the operator reconnects and resumes."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.panels import acquire
from app.panels.state import AppState
from drivers.emulators import CellEmulators
from drivers.grbl import GrblRobot
from drivers.keyence_il import KeyenceIL
from drivers.sim.devices import SimCameraDirect
from drivers.sim.workcell import load_workcell
from drivers.sim.world import SimWorld
from tests.faults.conftest import TIMEOUT


@pytest.fixture
def hardware(tmp_path: Path) -> Iterator[tuple[AppState, CellEmulators]]:
    workcell = load_workcell(None)
    world = SimWorld(workcell, seed=13)
    state = AppState(None, workcell, sim=False, session_path=tmp_path / "hw.db")
    with CellEmulators(world) as emu:
        state.worker.start()
        try:
            yield state, emu
        finally:
            state.worker.stop()
            state.close_session()
            state.disconnect()


def _attach(state: AppState, emu: CellEmulators, keyence_path: str) -> None:
    state.worker.call("attach", lambda: state.attach(
        GrblRobot(emu.grbl.path, state.workcell.limits, timeout=TIMEOUT),
        KeyenceIL(keyence_path, timeout=TIMEOUT), SimCameraDirect(emu.world)), 30)


def test_unplugged_sensor_pauses_with_a_notification(hardware) -> None:
    state, emu = hardware
    _attach(state, emu, emu.keyence.path)
    emu.keyence.inject("vanish", match="SR", skip=20)
    progress = state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 60)
    assert progress.state == "paused" and progress.done == 20
    assert "Keyence DL-RS1A port" in progress.message
    assert any(level == "warning" and "paused" in body and "Keyence" in body
               for _, level, _, body in state.messages)
    assert state.session.stored_indices() == set(range(20))


def test_reconnect_then_resume_completes_the_session(hardware) -> None:
    state, emu = hardware
    _attach(state, emu, emu.keyence.path)
    emu.keyence.inject("vanish", match="SR", skip=20)
    paused = state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 60)
    assert paused.state == "paused"
    new_path = emu.keyence.replug()                        # the adapter back, another name
    _attach(state, emu, new_path)                          # Setup > Connect
    t0 = time.monotonic()
    done = state.worker.call("acquire", lambda: acquire.run_acquisition(state, 1), 60)
    assert done.state == "finished", done.message
    assert sorted(state.session.stored_indices()) == list(range(42))
    assert time.monotonic() - t0 < 30
