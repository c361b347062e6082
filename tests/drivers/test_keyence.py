"""KeyenceIL driver against the DL-RS1A emulator on a pty: wire bytes, values, errors, faults."""

from __future__ import annotations

import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import DeviceTimeout, DriverError, ReadingStatus
from drivers.emulators import KeyenceEmulator
from drivers.keyence_il import ER_CODES, KeyenceError, KeyenceIL, describe_invalid, parse_value
from drivers.serial_port import PortLost
from tests.drivers.conftest import TIMEOUT


def test_read_sends_exact_bytes_and_returns_mm(keyence, sensor, physics):
    physics.value = 1.234
    reading = sensor.read()
    assert reading.status is ReadingStatus.OK
    assert reading.value == pytest.approx(1.234, abs=1e-9)
    assert reading.raw == "+01.234"
    assert keyence.received_bytes == b"SR,00,037\r\n"
    assert sensor.describe() == f"Keyence DL-RS1A on {keyence.path} 9600 8N1, amplifier 00, read SR"
    physics.value = -12.5
    assert sensor.read().value == pytest.approx(-12.5, abs=1e-9)


@pytest.mark.parametrize(("truth", "status"), [
    (None, ReadingStatus.OUT_OF_RANGE), (150.0, ReadingStatus.OUT_OF_RANGE),
    (-150.0, ReadingStatus.OUT_OF_RANGE), (99.998, ReadingStatus.OK)])
def test_out_of_range_is_never_a_number(sensor, physics, truth, status):
    physics.value = truth
    reading = sensor.read()
    assert reading.status is status
    assert (reading.value is None) == (status is not ReadingStatus.OK)


def test_m0_reads_the_requested_amplifier():
    with KeyenceEmulator({0: lambda: 1.0, 1: lambda: -2.5}, amp_ids=(0, 1)) as emu:
        with KeyenceIL(emu.path, amp_id=1, command="M0", timeout=TIMEOUT) as drv:
            assert drv.read().value == pytest.approx(-2.5, abs=1e-9)
        with KeyenceIL(emu.path, amp_id=2, command="M0", timeout=TIMEOUT) as drv, \
                pytest.raises(KeyenceError, match="none for amplifier ID 02"):
            drv.read()
        assert emu.received.count("M0") == 2


def test_stuck_sensor_and_amplifier_error(keyence, sensor):
    keyence.inject("stuck", count=-1)
    assert [sensor.read().status for _ in range(3)] == [ReadingStatus.OUT_OF_RANGE] * 3
    keyence.clear_faults()
    assert sensor.read().ok
    keyence.inject("amp_error")
    bad = sensor.read()
    assert bad.status is ReadingStatus.INVALID and bad.value is None
    assert "amplifier error" in describe_invalid(bad)


@pytest.mark.parametrize("code", sorted(ER_CODES.keys() - {29}))
def test_er_replies_become_clear_errors(keyence, sensor, code):
    keyence.inject("er", code=code)
    with pytest.raises(KeyenceError) as info:
        sensor.read()
    assert f"ER {code:02d} {ER_CODES[code]}" in str(info.value)
    assert keyence.received == ["SR,00,037"]  # not retried: the unit refused the command
    assert sensor.read().ok


def test_emulator_answers_real_er_codes(keyence, physics):
    with KeyenceIL(keyence.path, amp_id=7, timeout=TIMEOUT) as drv, \
            pytest.raises(KeyenceError, match="ER 65 no amplifier with this ID"):
        drv.read()


def test_er29_communication_error_is_retried(keyence, sensor):
    keyence.inject("er", code=29, count=2)
    assert sensor.read().ok
    assert keyence.received == ["SR,00,037"] * 3
    keyence.inject("er", code=29, count=-1)
    with pytest.raises(KeyenceError, match="ER 29 communication error"):
        sensor.read()


def test_timeout_is_retried_then_reported(keyence, sensor):
    keyence.inject("silent", count=2)
    assert sensor.read().ok
    assert keyence.received == ["SR,00,037"] * 3
    keyence.inject("silent", count=-1)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"did not answer SR,00,037 within 0.2 s \(3 attempts"):
        sensor.read()
    elapsed = time.monotonic() - t0
    assert 3 * TIMEOUT - 0.05 < elapsed < 3 * TIMEOUT + 0.5


@pytest.mark.parametrize("kind", ["garbage", "truncate"])
def test_garbled_or_truncated_reply_is_retried(keyence, sensor, kind):
    keyence.inject(kind)
    reading = sensor.read()
    assert reading.ok and reading.value == pytest.approx(1.234)
    assert keyence.received == ["SR,00,037"] * 2
    keyence.inject(kind, count=-1)
    with pytest.raises(DriverError, match="unusable replies") as info:
        sensor.read()
    assert not isinstance(info.value, DeviceTimeout)


def test_noise_before_reply_and_late_reply(keyence, sensor, physics):
    keyence.inject("noise")
    assert sensor.read().value == pytest.approx(1.234)
    keyence.inject("delay", seconds=1.5 * TIMEOUT)
    assert sensor.read().value == pytest.approx(1.234)
    time.sleep(2 * TIMEOUT)  # the second answer arrives late: it must not be taken next time
    physics.value = 5.0
    assert sensor.read().value == pytest.approx(5.0)


def test_zero_set_sequence(keyence, sensor, physics):
    keyence.zero_polls = 3
    physics.value = 3.5
    sensor.zero()
    assert keyence.received == ["SW,00,001,0", "SW,00,001,1"] + ["SR,00,054"] * 4
    physics.value = 4.0
    assert sensor.read().value == pytest.approx(0.5, abs=1e-9)


def test_zero_set_impossible(keyence, sensor, physics):
    keyence.inject("zero_impossible")
    with pytest.raises(KeyenceError, match="zero-set impossible"):
        sensor.zero()
    physics.value = None
    with pytest.raises(KeyenceError, match="zero-set impossible"):
        sensor.zero()


def test_port_vanishes_then_reconnect(keyence, sensor):
    assert sensor.read().ok
    keyence.vanish()
    with pytest.raises(PortLost, match="was lost"):
        sensor.read()
    with pytest.raises(PortLost, match="cannot open"):
        sensor.reconnect()
    sensor.reconnect(keyence.replug())
    assert sensor.read().value == pytest.approx(1.234)


def test_replugged_device_under_the_same_name_is_reopened(keyence, tmp_path):
    link = tmp_path / "ttyKEYENCE"  # like /dev/serial/by-id/...
    link.symlink_to(keyence.path)
    with KeyenceIL(str(link), timeout=TIMEOUT) as drv:
        assert drv.read().ok
        keyence.vanish()
        with pytest.raises(PortLost, match="was lost"):
            drv.read()
        with pytest.raises(PortLost, match="still missing; plug the device back in"):
            drv.read()
        link.unlink()
        link.symlink_to(keyence.replug())
        assert drv.read().value == pytest.approx(1.234)
    with pytest.raises(PortLost, match="is closed"):
        drv.read()


def test_port_vanishes_mid_command(keyence, sensor):
    keyence.inject("vanish")
    with pytest.raises(PortLost):
        sensor.read()
    assert keyence.gone


def test_cannot_open_missing_port():
    with pytest.raises(PortLost, match="cannot open Keyence DL-RS1A port '/dev/nonexistent-tty'"):
        KeyenceIL("/dev/nonexistent-tty")


@pytest.mark.parametrize(("field", "status", "value"), [
    ("+01.234", ReadingStatus.OK, 1.234), ("-00.050", ReadingStatus.OK, -0.05),
    ("+99.999", ReadingStatus.OUT_OF_RANGE, None), ("-99.999", ReadingStatus.OUT_OF_RANGE, None),
    ("+EE.EEE", ReadingStatus.INVALID, None), ("", ReadingStatus.INVALID, None),
    ("+1e5", ReadingStatus.INVALID, None), ("nan", ReadingStatus.INVALID, None),
    ("--1.0", ReadingStatus.INVALID, None)])
def test_parse_value(field, status, value):
    reading = parse_value(field)
    assert reading.status is status
    assert reading.value == (pytest.approx(value) if value is not None else None)


@given(st.text(max_size=30))
def test_parse_value_never_raises_nor_invents(field):
    reading = parse_value(field)
    assert (reading.value is not None) == reading.ok
    if reading.ok:
        assert abs(reading.value) < 1e4


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(junk=st.binary(min_size=1, max_size=40), kind=st.sampled_from(["garbage", "noise"]))
def test_any_junk_gives_the_true_reading_or_a_driver_error(keyence, physics, junk, kind):
    keyence.clear_faults()
    keyence.inject(kind, data=junk)
    with KeyenceIL(keyence.path, timeout=0.05, retries=1) as drv:
        try:
            reading = drv.read()
        except DriverError:
            return
    if b"SR,00,037," not in junk:
        assert reading.ok and reading.value == pytest.approx(physics.value)
