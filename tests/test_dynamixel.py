"""The Dynamixel tendon-motor driver, exercised through the real SDK over a pty emulator.

The emulator (tests/dynamixel_emulator.py) speaks protocol 2.0 on a pseudo-terminal, so every
test here goes through dynamixel_sdk -> pyserial -> a real serial device -> packet parsing,
CRC and byte stuffing on both sides.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from dynamixel_emulator import (
    ADDR_GOAL_POSITION,
    ADDR_PRESENT_POSITION,
    ADDR_TORQUE_ENABLE,
    PING,
    SYNC_READ,
    SYNC_WRITE,
    WRITE,
    DynamixelEmulator,
    crc16,
    status_packet,
)

from vlr_drake.hardware.dynamixel import DynamixelError, TendonMotors

# Every bus call is bounded by the SDK's status timeout: a hang would trip this.
pytestmark = pytest.mark.timeout(30)

IDS = [1, 2, 3]
LIMITS = (np.full(3, -20000), np.full(3, 20000))


@pytest.fixture
def emulator():
    emu = DynamixelEmulator(IDS, initial_positions={1: 1200, 2: -300, 3: 5})
    emu.start()
    yield emu
    emu.stop()


def make_motors(emu: DynamixelEmulator, **kwargs) -> TendonMotors:
    # A generous latency keeps a loaded test machine from faking timeouts.
    kw = dict(tick_limits=LIMITS, latency_timer_ms=30.0, comm_retries=2)
    kw.update(kwargs)
    return TendonMotors(emu.port_name, 1000000, IDS, **kw)


def test_crc_matches_sdk_and_protocol_example(rng):
    from dynamixel_sdk import PacketHandler

    ph = PacketHandler(2.0)
    # Protocol 2.0 e-manual ping example: FF FF FD 00 01 03 00 01 -> CRC 19 4E.
    assert crc16(bytes([0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01])) == 0x4E19
    for n in (1, 7, 64, 300):
        data = rng.integers(0, 256, size=n).tolist()
        assert crc16(data) == ph.updateCRC(0, data, n)


def test_status_packet_stuffing_is_parsed_by_sdk():
    """A status packet whose parameters contain FF FF FD is stuffed, and the SDK's
    removeStuffing recovers the original parameters."""
    from dynamixel_sdk import PacketHandler

    pkt = status_packet(7, 0, bytes([0xFF, 0xFF, 0xFD, 0x00]))
    assert pkt.count(bytes([0xFF, 0xFF, 0xFD, 0xFD])) == 1  # stuffed
    out = PacketHandler(2.0).removeStuffing(list(pkt))
    assert out[9:13] == [0xFF, 0xFF, 0xFD, 0x00]


def test_read_and_write_with_stuffing_through_the_sdk(emulator):
    from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

    class SlackPort(PortHandler):
        # The emulator answers from a Python thread, which on a loaded machine can take longer
        # than the SDK's fixed status timeout (2 x 16 ms USB latency + 2 ms; a ping timed out
        # once in CI): 100 ms of slack, as the driver's configurable latency_timer_ms allows.
        def setPacketTimeout(self, packet_length):  # noqa: N802 (SDK name)
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * 100.0 + 2.0

    port, ph = SlackPort(emulator.port_name), PacketHandler(2.0)
    assert port.openPort() and port.setBaudRate(1000000)
    try:
        model, result, error = ph.ping(port, 2)
        assert (model, result, error) == (1020, COMM_SUCCESS, 0)
        value = 0x00FDFFFF  # little-endian FF FF FD 00: needs stuffing both ways
        result, error = ph.write4ByteTxRx(port, 2, ADDR_GOAL_POSITION, value)
        assert (result, error) == (COMM_SUCCESS, 0)
        assert emulator.goal_position(2) == value
        emulator.set_present_position(2, value)
        data, result, error = ph.read4ByteTxRx(port, 2, ADDR_PRESENT_POSITION)
        assert (data, result, error) == (value, COMM_SUCCESS, 0)
    finally:
        port.closePort()


def test_emulator_answers_a_bad_crc_with_a_crc_error(emulator):
    import serial

    ping = bytearray([0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01])
    crc = crc16(ping) ^ 0x0001  # one bit off
    with serial.Serial(emulator.port_name, 1000000, timeout=1.0) as port:
        port.write(bytes(ping) + bytes([crc & 0xFF, crc >> 8]))
        reply = port.read(11)
    assert reply == status_packet(1, 3)  # error 3: CRC error, no parameters
    assert emulator.bad_crc_count == 1 and not emulator.instructions(PING)


def test_safe_start_order(emulator):
    n_open = len(emulator.log)
    with make_motors(emulator) as motors:
        first = motors.read()[0]
        assert first.tolist() == [1200, -300, 5]
        assert all(emulator.torque_enabled(i) for i in IDS)
        assert all(emulator.operating_mode(i) == 5 for i in IDS)
        # every motor pinged
        assert sorted(i for _, i, _ in emulator.instructions(PING)) == IDS
        sync_reads = emulator.instructions(SYNC_READ)
        torque_on = [(t, i) for t, i, p in emulator.instructions(WRITE, ADDR_TORQUE_ENABLE) if p[2] == 1]
        assert sorted(i for _, i in torque_on) == IDS
        # positions read, then goal = present sent, then torque on
        assert sync_reads and min(t for t, _ in torque_on) > sync_reads[0][0] >= n_open
        goal_writes = emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)
        assert goal_writes and goal_writes[0][0] < min(t for t, _ in torque_on)
        assert [emulator.goal_position(i) for i in IDS] == [1200, -300, 5]  # nothing jumps
        # the operating mode (EEPROM) was written while torque was off
        mode_writes = [t for t, _, p in emulator.instructions(WRITE, 11)]
        assert len(mode_writes) == 3 and max(mode_writes) < min(t for t, _ in torque_on)
    assert not any(emulator.torque_enabled(i) for i in IDS)  # torque off on close


def test_goals_reach_motors_as_ticks(emulator):
    with make_motors(emulator) as motors:
        goal = np.array([4096, -2048, 17])
        motors.write_goal_ticks(goal)
        emulator.wait_idle()
        assert [emulator.goal_position(i) for i in IDS] == goal.tolist()
        pos, cur = motors.read()
        assert pos.tolist() == goal.tolist()  # the emulated motors follow at once (no lag)
        assert cur.tolist() == [0, 0, 0]  # at their goals the emulated motors draw no current


def test_limits_refused_before_sending(emulator):
    with make_motors(emulator) as motors:
        motors.write_goal_ticks(np.array([100, 200, 300]))
        emulator.wait_idle()
        n_writes = len(emulator.instructions(SYNC_WRITE))
        with pytest.raises(ValueError, match=r"motor ids \[2\]"):
            motors.write_goal_ticks(np.array([100, 20001, 300]))
        with pytest.raises(ValueError, match="integers"):
            motors.write_goal_ticks(np.array([100.0, 200.0, 300.0]))
        emulator.wait_idle()
        assert len(emulator.instructions(SYNC_WRITE)) == n_writes
        assert [emulator.goal_position(i) for i in IDS] == [100, 200, 300]
        assert motors.torque_on


def test_start_far_outside_the_limits_is_refused(emulator):
    """A wrong zero offset (motor far outside its limits) must not move anything."""
    # motor 1 sits at 1200: 300 ticks below its lower limit, beyond the 256-tick tolerance
    motors = make_motors(emulator, tick_limits=(np.array([1500, -400, 0]), np.array([3000, 400, 100])))
    with pytest.raises(DynamixelError, match=r"motor ids \[1\] start at \[1200\] ticks"):
        motors.open()
    assert not motors.is_open and not any(emulator.torque_enabled(i) for i in IDS)
    assert not emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)  # no goal was ever sent


def test_start_slightly_outside_is_clamped(emulator):
    lo, hi = np.array([1000, -250, 0]), np.array([3000, 400, 100])  # motor 2 at -300: 50 below
    with make_motors(emulator, tick_limits=(lo, hi)) as motors:
        assert motors.torque_on
        assert [emulator.goal_position(i) for i in IDS] == [1200, -250, 5]


def test_open_without_torque(emulator):
    motors = make_motors(emulator)
    ticks = motors.open(enable_torque=False)
    try:
        assert ticks.tolist() == [1200, -300, 5]
        assert not motors.torque_on and not any(emulator.torque_enabled(i) for i in IDS)
    finally:
        motors.close()


def test_missing_port_is_a_clear_error():
    motors = TendonMotors("/dev/does-not-exist-vlr", 1000000, IDS, LIMITS)
    with pytest.raises(DynamixelError, match="cannot open Dynamixel port '/dev/does-not-exist-vlr'"):
        motors.open()
    assert not motors.is_open


def test_missing_motor_named_at_start(emulator):
    emulator.missing_ids.add(2)
    motors = make_motors(emulator)
    with pytest.raises(DynamixelError, match="motor id 2 does not answer"):
        motors.open()
    assert not motors.is_open
    assert not any(emulator.torque_enabled(i) for i in IDS)


def test_transient_corrupt_reply_is_retried(emulator):
    with make_motors(emulator) as motors:
        motors.write_goal_ticks(np.array([10, 20, 30]))
        emulator.corrupt_next = 1
        pos, _ = motors.read()
        assert pos.tolist() == [10, 20, 30]
        assert motors.torque_on


def test_corrupt_packets_stop_with_torque_off(emulator):
    with make_motors(emulator) as motors:
        motors.write_goal_ticks(np.array([10, 20, 30]))
        emulator.corrupt_ids.add(3)
        with pytest.raises(DynamixelError, match=r"Incorrect status packet.*motor id 3"):
            motors.read()
        assert not motors.is_open
        assert not any(emulator.torque_enabled(i) for i in IDS)  # broadcast torque off landed
        with pytest.raises(DynamixelError, match="not open"):
            motors.write_goal_ticks(np.array([10, 20, 30]))


def test_motor_that_stops_answering(emulator):
    with make_motors(emulator) as motors:
        emulator.missing_ids.add(1)
        with pytest.raises(DynamixelError, match=r"no status packet.*motor id 1"):
            motors.read()
        assert not motors.is_open
        # motors 2 and 3 still listen and were switched off
        assert not emulator.torque_enabled(2) and not emulator.torque_enabled(3)


def test_hardware_error_is_named(emulator):
    with make_motors(emulator) as motors:
        emulator.set_hardware_error(2, 0x20)  # overload: the servo shuts its torque off
        with pytest.raises(DynamixelError, match=r"motor id 2 .* hardware error: overload \(status 0x20\)"):
            motors.read()
        assert not motors.is_open
        assert not any(emulator.torque_enabled(i) for i in IDS)


def test_a_hardware_error_from_before_is_named_and_rebooted_away(emulator):
    """A motor that stopped on an overload keeps the error (and its torque off) until it is
    rebooted: the start names it instead of failing its ping with the SDK's generic text,
    nothing gets torque, and a reboot clears it."""
    emulator.set_hardware_error(2, 0x20)
    motors = make_motors(emulator)
    with pytest.raises(DynamixelError, match=r"motor id 2 .* still reports a hardware error: overload "
                                             r"\(status 0x20\).*python -m vlr_drake.hardware reboot"):
        motors.open()
    assert not motors.is_open and not any(emulator.torque_enabled(i) for i in IDS)
    # stopped before the mode and the goals were written: only the clean-up's torque-off writes
    assert {p[2] for _, _, p in emulator.instructions(WRITE, ADDR_TORQUE_ENABLE)} == {0}
    assert emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION) == []
    assert motors.reboot() == [0, 0x20, 0] and emulator.reboots == IDS
    assert not motors.is_open
    try:  # starts again (the emulator resets the multi-turn count: 1200, 3796, 5)
        ticks = motors.open()
        assert ticks.tolist() == [1200, (-300) % 4096, 5] and all(emulator.torque_enabled(i) for i in IDS)
        with pytest.raises(DynamixelError, match="already open"):
            motors.reboot()
    finally:
        motors.close()


def test_bring_up_reboot_command(emulator):
    import io

    from vlr_drake.hardware.__main__ import main as bring_up

    emulator.set_hardware_error(3, 0x04)
    out = io.StringIO()
    over = f"port: {emulator.port_name}\nlatency_timer_ms: 30.0\nmotor_ids: [1, 2, 3]\n"
    assert bring_up(["reboot", "--set", over], out=out) == 0
    text = out.getvalue()
    assert "motor 3: had overheating; rebooted, torque off" in text and "motor 1: had no hardware error" in text
    assert emulator.reboots == IDS


def test_bring_up_applies_each_set(emulator):
    """--set twice had kept only the last text (the port given first dropped, the default
    /dev/ttyUSB0 opened)."""
    import io

    from vlr_drake.hardware.__main__ import main as bring_up

    out = io.StringIO()
    assert bring_up(["reboot", "--set", f"port: {emulator.port_name}", "--set",
                     "latency_timer_ms: 30.0\nmotor_ids: [1, 2, 3]\n"], out=out) == 0
    assert emulator.reboots == IDS


def test_silent_bus_does_not_hang(emulator):
    """... and a torque off that no motor confirms is said, not reported done: the motors
    may still hold their goals (a review: the stop message had said the torque was off)."""
    from vlr_drake.entry import Stopped, run
    from vlr_drake.hardware import dynamixel

    def main():
        with make_motors(emulator) as motors:
            emulator.silent = True
            with pytest.raises(DynamixelError, match=r"sync read of present position .*no status packet"), \
                    pytest.warns(RuntimeWarning, match=r"motors \[1, 2, 3\] did not confirm torque off"):
                motors.read()
            assert not motors.is_open and motors.unconfirmed == [1, 2, 3]
            assert emulator.torque_enabled(1)  # (the emulator: still on)
        raise Stopped("SIGTERM")

    import io
    from contextlib import redirect_stderr

    err = io.StringIO()
    with redirect_stderr(err):
        assert run("demo", main, hardware=True) == 128 + 15
    assert "torque off NOT confirmed on" in err.getvalue() and "cut the motors' power" in err.getvalue()
    assert dynamixel.unconfirmed_torque_off


def test_disconnected_port(emulator):
    with make_motors(emulator) as motors:
        emulator.disconnect()
        with pytest.raises(DynamixelError, match="failed"):
            motors.write_goal_ticks(np.array([1, 2, 3]))
            motors.read()
        assert not motors.is_open


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="tick_limits"):
        TendonMotors("/dev/null", 1000000, IDS, (np.zeros(2), np.zeros(2)))
    with pytest.raises(ValueError, match="lo <= hi"):
        TendonMotors("/dev/null", 1000000, IDS, (np.ones(3), np.zeros(3)))
    with pytest.raises(ValueError, match=r"goal_current_raw must be in 1..2047"):
        TendonMotors("/dev/null", 1000000, IDS, LIMITS, goal_current_raw=0)
    # what the config refuses, the driver refuses too: -1 retries had opened nothing but an
    # UnboundLocalError, and mode 3 (single-turn position) had been written to the motors
    for kw, match in [({"comm_retries": -1}, "comm_retries must be >= 0"),
                      ({"start_tolerance_ticks": -1}, "start_tolerance_ticks must be >= 0"),
                      ({"operating_mode": 3}, "operating_mode must be 4 .* or 5")]:
        with pytest.raises(ValueError, match=match):
            TendonMotors("/dev/null", 1000000, IDS, LIMITS, **kw)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_stop_signal_in_the_middle_of_bus_io_stops_the_command(emulator, sig):
    """A signal that lands inside a bus transaction is a stop, not a bus error: the command
    ends with 'stopped by' and 128 + the signal's number, torque off (the driver's handlers of
    failed I/O had turned it into a DynamixelError, exit status 2)."""
    import os
    import signal
    import threading
    import time

    from vlr_drake.entry import run

    timer = threading.Timer(0.3, os.kill, (os.getpid(), getattr(signal, sig)))

    def main():
        with make_motors(emulator, tick_limits=(np.full(3, -99999), np.full(3, 99999))) as motors:
            timer.start()
            start = time.monotonic()
            while time.monotonic() - start < 10.0:  # only bus I/O, no sleep: the signal lands in it
                motors.read()
        return 0

    try:
        status = run("demo", main, hardware=True)
    finally:
        timer.cancel()
    assert status == 128 + int(getattr(signal, sig))
    assert not any(emulator.torque_enabled(i) for i in IDS)


def test_a_model_without_current_control_is_named_in_current_mode():
    """An XL430 has no current-based position mode: named at the start, before any write; in
    extended position mode it starts."""
    from dynamixel_emulator import DynamixelEmulator

    with DynamixelEmulator(IDS, model_number=1060) as emu:
        motors = make_motors(emu)
        with pytest.raises(DynamixelError, match=r"id 1 is an XL430-W250, id 2 is an XL430-W250, id 3 is an "
                                                 r"XL430-W250; that model has no current-based position mode"):
            motors.open()
        # nothing written but the clean-up's torque off (address 64, value 0)
        assert all(p == bytes([ADDR_TORQUE_ENABLE, 0, 0]) for _, _, p in emu.instructions(WRITE))
        with make_motors(emu, operating_mode=4) as motors:
            assert motors.model_numbers == [1060] * 3 and all(emu.torque_enabled(i) for i in IDS)
    with DynamixelEmulator(IDS, model_number=1090) as emu:  # the 2XL430-W250 had been let through
        with pytest.raises(DynamixelError, match=r"id 1 is an 2XL430-W250.*no current-based position mode"):
            make_motors(emu).open()


def test_one_corrupted_reply_to_the_torque_off_is_retried(emulator):
    """close() asks each motor to confirm its torque off; one corrupted reply had left the
    motor unconfirmed and raised "cut the motors' power" (a review). It is retried as every
    other transaction is."""
    motors = make_motors(emulator)
    motors.open()
    emulator.corrupt_next = 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "did not confirm torque off" warning
        motors.close()
    assert motors.unconfirmed == [] and not any(emulator.torque_enabled(i) for i in IDS)


def test_a_status_error_in_a_sync_read_is_retried_and_named():
    """A motor that answers a sync read with an error (a CRC error after line noise, no data)
    is a failed attempt: retried, and named once the retries are spent. It had ended the run
    with 'list index out of range' at the first, and an error with data was read as data."""
    import dynamixel_emulator as de

    class NoisyLine(DynamixelEmulator):
        bad_reads = 0

        def _handle(self, pkt):
            body = de._unstuff(pkt[7:-2])
            if body and body[0] == SYNC_READ and self.bad_reads > 0:
                self.bad_reads -= 1
                self.log.append((0.0, pkt[4], SYNC_READ, bytes(body[1:])))
                block = slice(126, 136)  # present current .. present position
                return (self._status(1, 0, bytes(self.motors[1].table[block])) + self._status(2, de.ERR_CRC)
                        + self._status(3, 0, bytes(self.motors[3].table[block])))
            return super()._handle(pkt)

    emu = NoisyLine(IDS, initial_positions={1: 1200, 2: -300, 3: 5})
    emu.start()
    try:
        with make_motors(emu) as motors:
            sent = len(emu.instructions(SYNC_READ))
            emu.bad_reads = 1  # one transient fault: the retry reads
            pos, _ = motors.read()
            assert pos.tolist() == [1200, -300, 5] and len(emu.instructions(SYNC_READ)) - sent == 2
            emu.bad_reads = 3  # more than comm_retries = 2 allow
            with pytest.raises(DynamixelError, match=r"motor id 2 answered with status error .*CRC"):
                motors.read()
            assert not motors.is_open
    finally:
        emu.stop()


def test_a_lost_turn_is_refused_against_the_last_runs_record(emulator, tmp_path):
    """A power cycle or a reboot resets a motor's multi-turn count: the motor then reads a
    whole number of turns from where the last run left it, usually still inside its limits
    (45 mm of Model O tendon is 1.43 turns of its spool). The start refuses it, torque off,
    until the positions are zeroed again; the bring-up tool's open only reports it."""
    record = tmp_path / "motors.json"
    with make_motors(emulator, record_path=record) as motors:
        motors.write_goal_ticks(np.array([3000, -300, 5]))
    assert json.loads(record.read_text())["ticks"] == {"1": 3000, "2": -300, "3": 5}
    with make_motors(emulator, record_path=record):  # nothing moved: the start goes on
        pass
    emulator.set_present_position(1, 3000 - 4096 + 40)  # the count reset, the motor 40 ticks on
    n_goals = len(emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION))
    motors = make_motors(emulator, record_path=record)
    with pytest.raises(DynamixelError, match=r"motor id 1 reads -1056 ticks, -1 turn from the 3000 .*zero_offset_ticks "
                                             r"is wrong by those turns.*Torque stays off"):
        motors.open()
    assert not any(emulator.torque_enabled(i) for i in IDS)
    assert len(emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)) == n_goals  # no goal sent
    assert json.loads(record.read_text())["ticks"]["1"] == 3000  # the record is kept: refused again
    status = make_motors(emulator, record_path=record)
    status.open(enable_torque=False)
    status.close()
    assert len(status.record_findings) == 1 and "-1 turn" in status.record_findings[0]
    with pytest.raises(DynamixelError, match="motor id 1 reads -1056 ticks"):
        make_motors(emulator, record_path=record).open()
    # zeroed again: the record starts from the present positions, and a run starts
    zero = make_motors(emulator, record_path=record)
    zero.open(enable_torque=False)
    zero.accept_positions()
    zero.close()
    assert json.loads(record.read_text())["ticks"]["1"] == -1056
    with make_motors(emulator, record_path=record) as motors:
        assert motors.torque_on and motors.record_findings == []
    # two turns, and without a record nothing is checked
    emulator.set_present_position(3, 5 + 2 * 4096)
    with pytest.raises(DynamixelError, match=r"motor id 3 reads 8197 ticks, \+2 turns"):
        make_motors(emulator, record_path=record).open()
    with make_motors(emulator) as motors:
        assert motors.torque_on


def test_a_motor_turned_while_off_is_reported_and_a_bad_record_replaced(emulator, tmp_path, caplog):
    record = tmp_path / "motors.json"
    with make_motors(emulator, record_path=record):
        pass
    emulator.set_present_position(2, -300 + 1500)  # turned by hand: not a whole turn
    with caplog.at_level("WARNING"), make_motors(emulator, record_path=record) as motors:
        assert motors.torque_on
        assert "motor id 2 reads 1200 ticks, +0.37 turns" in motors.record_findings[0]
    assert "turned while its torque was off" in caplog.text
    assert json.loads(record.read_text())["ticks"]["2"] == 1200
    # a reset turn count and a finger that sprang back (-1.07 turns): refused as a lost turn is
    # (it had only been warned about, and the run had started 31 mm of tendon off)
    emulator.set_present_position(2, 1200 - 4096 - 300)
    with pytest.raises(DynamixelError, match=r"motor id 2 reads -3196 ticks, -1.07 turns .* half a turn or more"):
        make_motors(emulator, record_path=record).open()
    assert not any(emulator.torque_enabled(i) for i in IDS)
    assert json.loads(record.read_text())["ticks"]["2"] == 1200  # kept: refused again until zeroed
    emulator.set_present_position(2, 1200)
    record.write_text("{not json")
    with make_motors(emulator, record_path=record) as motors:
        assert motors.torque_on and "cannot be read" in motors.record_findings[0]
    assert json.loads(record.read_text())["ticks"] == {"1": 1200, "2": 1200, "3": 5}


def test_compare_with_record_matches_its_definition():
    from vlr_drake.hardware.dynamixel import compare_with_record

    rec = {"ticks": {"1": 1000, "2": 1000, "3": 1000}}
    lost, moved = compare_with_record(rec, [1, 2, 3, 4], [1000 + 4096 + 256, 1000 - 4096 - 257, 1000 + 256, 7],
                                      4096, 256)
    assert lost == [(1, 5352, 1000, 1)] and [m[:3] for m in moved] == [(2, -3353, 1000)]
    assert compare_with_record({}, [1], [5], 4096, 256) == ([], [])
    assert compare_with_record(rec, [1], [1000 - 2048], 4096, 256)[1][0][3] == -0.5  # half a turn: moved


def test_the_motor_record_path(tmp_path, monkeypatch):
    from vlr_drake.hardware.config import HardwareConfig, load_hardware_config

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    assert HardwareConfig(port="/dev/ttyUSB0").motor_record_path() == tmp_path / "state/vlr_drake/motors_dev_ttyUSB0.json"
    assert HardwareConfig(motor_record="").motor_record_path() is None
    # relative to the scenario file, as the calibration file
    (tmp_path / "cam.yaml").write_text("x")
    scen = tmp_path / "hw.yaml"
    scen.write_text("plant: hardware\nhardware:\n  motor_record: rec/motors.json\n  calibration_file: cam.yaml\n")
    cfg = load_hardware_config(filename=scen)
    assert cfg.motor_record_path() == tmp_path / "rec/motors.json" and cfg.calibration_file == str(tmp_path / "cam.yaml")
