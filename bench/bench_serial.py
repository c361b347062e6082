"""Serial drivers over pty emulators: round-trip times, stop latency, fault recovery.

Prints, for the real drivers talking to the in-process emulators over a pseudo-terminal:
Keyence ``SR`` read round trip, GRBL ``move_to`` cycle (zero move time: ``?``, ``G1``,
``G4 P0``, ``?``), the delay from ``GrblRobot.stop()`` to the emulator receiving ``!`` while a
move is in flight, and the time to recover from one lost reply at the default 0.5 s timeout.

    /work/venv/bin/python bench/bench_serial.py [--n 300]
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time
from collections.abc import Callable

from drivers.base import FlangePose, SoftLimits
from drivers.emulators import GrblEmulator, KeyenceEmulator
from drivers.grbl import GrblRobot, MotionStopped
from drivers.keyence_il import KeyenceIL

LIMITS = SoftLimits((-100.0, 100.0), (-100.0, 100.0), (-100.0, 100.0), (-180.0, 180.0))


def summary(name: str, seconds: list[float]) -> None:
    ms = sorted(s * 1e3 for s in seconds)
    p99 = ms[min(len(ms) - 1, round(0.99 * (len(ms) - 1)))]
    print(f"{name:<38} median {statistics.median(ms):7.2f} ms   p99 {p99:7.2f} ms   "
          f"max {ms[-1]:7.2f} ms   (n={len(ms)})")


def timed(fn: Callable[[], object], n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300, help="repetitions per figure")
    n = ap.parse_args().n

    with KeyenceEmulator(lambda: 1.234) as emu, KeyenceIL(emu.path) as sensor:
        summary("Keyence SR read round trip", timed(sensor.read, n))
        emu.inject("silent")
        summary("Keyence read with one lost reply", timed(sensor.read, 1))

    with GrblEmulator() as emu, GrblRobot(emu.path, LIMITS) as robot:
        poses = [FlangePose(i % 7, i % 5, i % 3, i % 11) for i in range(n)]
        it = iter(poses)
        summary("GRBL move_to cycle (zero move time)", timed(lambda: robot.move_to(next(it)), n))
        summary("GRBL read_pose ('?')", timed(robot.read_pose, n))

        emu.move_time = 5.0
        delays = []
        for k in range(min(n, 20)):
            failed: list[BaseException] = []

            def move(k: int = k, failed: list[BaseException] = failed) -> None:
                try:
                    robot.move_to(FlangePose(50.0 + k, 0.0, 0.0, 0.0))
                except MotionStopped as exc:
                    failed.append(exc)

            mover = threading.Thread(target=move)
            mover.start()
            while "G4 P0" not in emu.received[-3:]:
                time.sleep(0.002)
            time.sleep(0.05)
            t0 = time.monotonic()
            robot.stop()
            mover.join()
            bang = [t for t, text in emu.log if text == "!"][-1]
            delays.append(bang - t0)
            assert failed, "the move was not stopped"
        summary("GRBL stop() -> '!' received, mid-move", delays)


if __name__ == "__main__":
    main()
