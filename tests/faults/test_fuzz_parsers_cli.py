"""Property-based fuzzing of the serial reply parsers and of every sub-command's arguments.

Parsers: any bytes a device may send reach the real drivers through an in-memory serial port
(pyserial's ``Serial`` replaced, nothing else); the result is a reading/pose or a
:class:`DriverError`, never another exception, never a made-up number.

CLI: for every leaf sub-command of ``lasercal`` (found by walking the argparse tree), argument
lists that each carry at least one bad value (non-numbers, NaN/inf, unknown choices, missing,
empty, binary or directory paths, outputs under a missing directory) run in-process through
``app.cli.main`` in an empty working directory: exit 2, exactly one ``error:`` line, nothing on
stdout, no file created, changed or removed (``camera render --out`` also gets an image format
OpenCV cannot write).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import re
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.cli import build_parser, main
from drivers.base import DriverError, FlangePose, ReadingStatus, SoftLimits
from drivers.grbl import STATES, GrblRobot, parse_status
from drivers.keyence_il import KeyenceIL, parse_error, parse_value

SETTINGS = settings(max_examples=120, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])
LIMITS = SoftLimits(x=(-100, 100), y=(-100, 100), z=(0, 200), theta_deg=(-180, 180),
                    max_step=20.0)


# ---- an in-memory serial port ------------------------------------------------------------
class FakeSerial:
    """Stands in for ``serial.Serial``: every write is answered with :attr:`reply`."""

    reply: bytes = b""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self._buf = bytearray()

    @property
    def in_waiting(self) -> int:
        return len(self._buf)

    def read(self, n: int = 1) -> bytes:
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def write(self, data: bytes) -> int:
        self._buf += type(self).reply
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


@pytest.fixture
def fake_port(monkeypatch: pytest.MonkeyPatch) -> type[FakeSerial]:
    import serial

    monkeypatch.setattr(serial, "Serial", FakeSerial)
    return FakeSerial


NUMBER = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(lambda v: f"{v:+07.3f}"),
                   st.sampled_from(["+99.999", "-99.999", "+EE.EEE", "+01.234", "1e5", "--1",
                                    "+0001.5", "", " ", "+1.2.3", "٣", "0x1F", "+FFFFFFF"]))
KEYENCE_LINES = st.one_of(
    st.binary(max_size=60),
    st.builds(lambda n: f"SR,00,037,{n}\r\n".encode(), NUMBER),
    st.builds(lambda ns: ("M0," + ",".join(ns) + "\r\n").encode(), st.lists(NUMBER, max_size=3)),
    st.builds(lambda c, k: f"ER,{c},{k}\r\n".encode(), st.sampled_from(["SR", "M0", "", "X"]),
              st.one_of(st.integers(-5, 200).map(str), st.text(max_size=3))),
)


@SETTINGS
@given(reply=KEYENCE_LINES, command=st.sampled_from(["SR", "M0"]))
def test_keyence_any_reply_is_a_reading_or_a_driver_error(
        fake_port: type[FakeSerial], reply: bytes, command: str) -> None:
    fake_port.reply = reply
    sensor = KeyenceIL("fake", timeout=0.005, retries=0, command=command)
    try:
        reading = sensor.read()
    except DriverError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    finally:
        sensor.close()
    if reading.status is ReadingStatus.OK:
        assert reading.value is not None and math.isfinite(reading.value)
        assert reading.raw in reply.decode("ascii", "replace")       # the value it was sent
        assert float(reading.raw) == reading.value
    else:
        assert reading.value is None


@SETTINGS
@given(line=st.text(max_size=40))
def test_keyence_field_parsers_never_raise(line: str) -> None:
    reading = parse_value(line)
    assert reading.ok == (reading.value is not None)
    err = parse_error(line)
    assert err is None or (isinstance(err[1], int) and line.strip().startswith("ER,"))


AXIS = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32).map(repr),
                 st.sampled_from(["", "1e999", "-0", "1.2.3", "x", "nan", "٣"]))
STATUS_LINES = st.one_of(
    st.binary(max_size=80),
    st.builds(lambda state, key, axes, tail: (f"<{state}|{key}:{','.join(axes)}{tail}>\r\n"
                                              ).encode("utf-8", "replace"),
              st.one_of(st.sampled_from((*STATES, "Hold:0", "Door:1", "idle", "")),
                        st.text(max_size=5)),
              st.sampled_from(["MPos", "WPos", "WCO", "Pos", ""]),
              st.lists(AXIS, max_size=6),
              st.sampled_from(["", "|FS:0,0", "|WCO:0,0,0,0", "|WCO:1,2", "|", "|Ov:100"])),
    st.sampled_from([b"ok\r\n", b"error:9\r\n", b"ALARM:1\r\n", b"error:\r\n", b"ALARM:x\r\n",
                     b"<Idle|MPos:0,0,0,0>", b"<Idle|MPos:0,0,0,0\r\n"]),
)


@SETTINGS
@given(reply=STATUS_LINES)
def test_grbl_any_reply_is_a_pose_or_a_driver_error(
        fake_port: type[FakeSerial], reply: bytes) -> None:
    fake_port.reply = reply
    robot = GrblRobot("fake", LIMITS, timeout=0.005, retries=0, settle_timeout=0.01,
                      move_timeout=0.05)
    try:
        pose = robot.read_pose()
    except DriverError as exc:
        assert str(exc) and "\n" not in str(exc)
    else:
        assert all(math.isfinite(v) for v in pose.as_array())
    try:
        robot.move_to(FlangePose(1.0, 2.0, 3.0, 4.0))
    except DriverError as exc:
        assert str(exc) and "\n" not in str(exc)
    finally:
        robot.close()


@SETTINGS
@given(line=st.one_of(st.text(max_size=60), STATUS_LINES.map(lambda b: b.decode("ascii",
                                                                                "replace"))))
def test_grbl_status_parser_only_raises_driver_errors(line: str) -> None:
    try:
        status = parse_status(line)
    except DriverError:
        return
    pos = status.wpos if status.wpos is not None else status.mpos
    assert pos is not None and len(pos) == 4 and all(math.isfinite(v) for v in pos)


# ---- every sub-command's arguments --------------------------------------------------------
def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
            ) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for action in subs:
        for name, sub in action.choices.items():
            yield from _leaves(sub, (*path, name))


LEAVES = dict(_leaves(build_parser()))
OUTPUTS = {"--out", "--csv"}
FREE_TEXT = {"--note"}                    # any text is a valid value
INPUT_POISONS = ("{d}", "{d}/junk.bin", "{d}/empty.csv", "{d}/nodir/x.db", "{d}/junk.bin/x.db")
OUTPUT_POISONS = ("{d}/nodir/x.png", "{d}/junk.bin/x.png")
#: Output directories are created with their parents: only a file in the way is an error.
DIR_OUTPUTS = {("platform", "simulate")}


def _poisons(action: argparse.Action, leaf: tuple[str, ...]) -> tuple[str, ...]:
    if action.choices:
        return ("bogus", "")
    if action.type is int:
        return ("abc", "1.5", "", "0x10", "1e3")
    if action.type is float:
        return ("nan", "inf", "-inf", "abc", "", "1e999")
    if set(action.option_strings) & OUTPUTS:
        if leaf in DIR_OUTPUTS:
            return ("{d}/junk.bin", "{d}/junk.bin/x")
        return (*OUTPUT_POISONS, "{d}/x.txt") if leaf == ("camera", "render") else OUTPUT_POISONS
    return INPUT_POISONS


@st.composite
def bad_arguments(draw: st.DrawFn, leaf: tuple[str, ...]) -> list[str]:
    """Arguments for ``leaf`` with at least one poisoned value (``{d}``: the sandbox)."""
    parser = LEAVES[leaf]
    valued = [a for a in parser._actions if not isinstance(a, argparse._HelpAction)
              and a.nargs != 0 and not set(a.option_strings) & FREE_TEXT]
    flags = [a for a in parser._actions if a.nargs == 0 and a.option_strings
             and not isinstance(a, argparse._HelpAction)]
    chosen = draw(st.lists(st.sampled_from(valued), min_size=1, max_size=4, unique_by=id))
    args: list[str] = []
    for action in chosen:
        n = action.nargs if isinstance(action.nargs, int) else 1
        values = [draw(st.sampled_from(_poisons(action, leaf))) for _ in range(n)]
        args += [*action.option_strings[:1], *values]
    for action in draw(st.lists(st.sampled_from(flags), max_size=2, unique_by=id)) if flags \
            else []:
        args.insert(draw(st.integers(0, len(args))), action.option_strings[0])
    return args


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*")}


class _Watchdog(Exception):
    pass


def _alarm(*_: object) -> None:
    raise _Watchdog("a sub-command ran for 20 s on bad arguments")


def _run_in(sandbox: Path, argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, 20.0)
    try:
        os.chdir(sandbox)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:
                code = int(exc.code or 0)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        os.chdir(cwd)
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("leaf", sorted(LEAVES), ids=" ".join)
def test_bad_arguments_give_one_error_line_and_write_nothing(leaf: tuple[str, ...]) -> None:
    @settings(max_examples=40, deadline=None, derandomize=True)
    @given(args=bad_arguments(leaf))
    def check(args: list[str]) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            sandbox = Path(tmp)
            (sandbox / "junk.bin").write_bytes(b"\xff\x00junk\r\n\x89PNG" * 20)
            (sandbox / "empty.csv").write_bytes(b"")
            argv = [*leaf, *(a.replace("{d}", tmp) for a in args)]
            before = _snapshot(sandbox)
            code, out, err = _run_in(sandbox, argv)
            after = _snapshot(sandbox)
        shown = " ".join(argv).replace(tmp, "T")
        lines = err.strip().splitlines()
        assert code == 2, (shown, code, err)
        assert len(lines) == 1 and lines[0].startswith("error:"), (shown, err)
        assert "Traceback" not in err and out == "", (shown, out)
        assert after == before, (shown, set(after) ^ set(before))
    check()


def test_every_sub_command_is_fuzzed() -> None:
    names = {leaf[0] for leaf in LEAVES}
    from app.cli import COMMANDS

    assert names == set(COMMANDS)
    assert re.fullmatch(r"\d+", str(len(LEAVES))) and len(LEAVES) >= len(COMMANDS)
