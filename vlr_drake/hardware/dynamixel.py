"""Tendon motors: a safe driver for Dynamixel X-series servos (protocol 2.0) on one bus.

The Yale Model O pulls each finger's tendon with one Dynamixel servo (DESIGN.md section 8).
:class:`TendonMotors` wraps the ``dynamixel_sdk`` package (PortHandler, protocol 2.0
PacketHandler, GroupSyncWrite, GroupSyncRead) and works in motor ticks; the tendon <-> tick
conversion and the tendon limits live in :class:`vlr_drake.hardware.config.TendonMotorMap`.

Safe start (:meth:`TendonMotors.open`):
  1. open the port at the configured baud rate (a missing device is a clear error);
  2. ping every motor (an id that does not answer is named in the error; a model without
     current sensing in current-based position mode is refused by name) and read its
     hardware error status (address 70): a motor still holding an error from an earlier
     run (overload, overheating; kept until it is rebooted) stops the start, named, with
     the way to reboot it (:meth:`TendonMotors.reboot`,
     ``python -m vlr_drake.hardware reboot``);
  3. torque off, then set the operating mode (address 11; 4 = extended position,
     5 = current-based position) and, in mode 5, the goal current (address 102);
  4. read all present positions with one sync read (address 132); a motor far outside its
     limits (a wrong zero offset) stops the start with torque off, and so does one whose
     position is a whole number of turns from where the last run left it (its multi-turn
     count was reset by a power cycle or a reboot: :func:`compare_with_record`);
  5. set each goal position to the position just read, so nothing jumps;
  6. only then enable torque (address 64), confirmed motor by motor.

Running: :meth:`write_goal_ticks` refuses goals outside the tick limits before anything is
sent; one sync write (address 116, 4 bytes) moves all motors; :meth:`read` returns present
positions and currents from one sync read of addresses 126..135. A status packet with the
alert bit set makes the driver read the motor's hardware error status (address 70) and stop
with an error naming it (overload, overheating, ...). A failed transaction is
retried ``comm_retries`` times; then torque is switched off (best effort) and
:class:`DynamixelError` names what failed. :meth:`close` (also on leaving a ``with`` block)
switches torque off, records where the motors are (``record_path``) and closes the port.
Every SDK call is bounded by the SDK's status timeout (2 x latency timer + 2 ms + transfer
time), so nothing hangs.
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np

__all__ = [
    "DynamixelError",
    "TendonMotors",
    "compare_with_record",
    "ADDR_OPERATING_MODE",
    "ADDR_TORQUE_ENABLE",
    "ADDR_GOAL_CURRENT",
    "ADDR_GOAL_POSITION",
    "ADDR_PRESENT_CURRENT",
    "ADDR_PRESENT_POSITION",
]

log = logging.getLogger(__name__)

#: Ports whose motors did not all confirm torque off when their bus was closed (appended by
#: TendonMotors.close; a command's stop message reads it rather than claim the torque is off).
unconfirmed_torque_off: list[str] = []

# X-series control table (protocol 2.0).
ADDR_OPERATING_MODE = 11  # 1 byte, EEPROM
ADDR_TORQUE_ENABLE = 64  # 1 byte
ADDR_HARDWARE_ERROR_STATUS = 70  # 1 byte, bits below
ADDR_GOAL_CURRENT = 102  # 2 bytes
GOAL_CURRENT_MAX = 2047  # the register's range, raw units (about 2.69 mA each on an XM430)
#: Model numbers (address 0, what a ping returns) of X-series servos without current
#: sensing: their operating modes are velocity, position, extended position and PWM
#: (ROBOTIS e-manual, each model's specifications), so no current-based position mode.
NO_CURRENT_MODELS = {1060: "XL430-W250", 1070: "XC430-W150", 1080: "XC430-W240", 1090: "2XL430-W250",
                     1160: "2XC430-W250"}
#: How long a motor takes to answer again after a REBOOT instruction [s].
REBOOT_WAIT_S = 0.5
ADDR_GOAL_POSITION = 116  # 4 bytes
ADDR_PRESENT_CURRENT = 126  # 2 bytes, signed
ADDR_PRESENT_POSITION = 132  # 4 bytes, signed
#: One sync read covers present current (126), velocity (128) and position (132).
READ_BLOCK_START, READ_BLOCK_LENGTH = ADDR_PRESENT_CURRENT, 10
#: Alert bit of a status packet's error byte: the motor has a hardware error.
ERRBIT_ALERT = 0x80
#: Hardware error status bits (address 70) of X-series servos.
HARDWARE_ERROR_BITS = {
    0: "input voltage",
    2: "overheating",
    3: "motor encoder",
    4: "electrical shock",
    5: "overload",
}
#: Goal position range of extended position mode [ticks].
EXTENDED_POSITION_LIMIT = 1_048_575


class DynamixelError(RuntimeError):
    """A bus or motor failure (torque has been switched off where the bus still answers)."""


def hardware_error_text(status: int) -> str:
    """Names of the bits set in a hardware error status byte (address 70)."""
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if status & (1 << bit)]
    return ", ".join(names) or f"unknown (0x{status:02x})"


def _sync_read_class(sdk):
    class _SyncRead(sdk.GroupSyncRead):
        """GroupSyncRead that keeps each status packet's error byte (whose alert bit says the
        motor has a hardware error); the SDK's own rxPacket drops it."""

        def rxPacket(self):  # noqa: N802 (SDK name)
            self.errors = {}
            self.last_result = False
            result = sdk.COMM_RX_FAIL
            for dxl_id in self.data_dict:
                self.data_dict[dxl_id], result, self.errors[dxl_id] = self.ph.readRx(
                    self.port, dxl_id, self.data_length
                )
                if result != sdk.COMM_SUCCESS:
                    return result
            self.last_result = result == sdk.COMM_SUCCESS
            return result

    return _SyncRead


def _signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


def compare_with_record(record: dict, motor_ids, ticks, ticks_per_rev: int, tolerance: int) -> tuple[list, list]:
    """Motors whose position is not where the last run left them (``record``, as
    :meth:`TendonMotors.close` writes it: ``{"ticks": {id: ticks}, "written": ...}``).

    Returns ``(lost, moved)``: ``lost`` the (id, ticks now, ticks then, turns) of motors a
    whole number of turns away, within ``tolerance`` ticks (a power cycle or a reboot reset
    the multi-turn count: the zero offset is wrong by those turns); ``moved`` those of
    motors that moved otherwise by more than ``tolerance`` while their torque was off
    (turned by hand: their turn count cannot be checked). Motors the record does not name
    are neither."""
    then = record.get("ticks", {})
    lost, moved = [], []
    for i, now in zip(motor_ids, np.asarray(ticks).tolist(), strict=True):
        last = then.get(str(i))
        if last is None:
            continue
        d = int(now) - int(last)
        turns = int(round(d / ticks_per_rev))
        if turns and abs(d - turns * ticks_per_rev) <= tolerance:
            lost.append((i, int(now), int(last), turns))
        elif abs(d) > tolerance:
            moved.append((i, int(now), int(last), d / ticks_per_rev))
    return lost, moved


class TendonMotors:
    """The tendon servos of one hand on one Dynamixel bus (protocol 2.0, X-series).

    Args:
        port: serial device name (e.g. ``/dev/ttyUSB0``).
        baud_rate: bus baud rate [bit/s].
        motor_ids: motor ids, one per tendon, in the hand's finger order.
        tick_limits: (lowest, highest) allowed goal ticks per motor, each (N,); goals outside
            them are refused before anything is sent.
        operating_mode: 4 (extended position) or 5 (current-based position).
        goal_current_raw: goal current written in mode 5 (1..2047 raw units; it limits the
            tendon's pull: the motor's own value is its current limit, near the stall current).
        latency_timer_ms: status-packet timeout slack of the adapter [ms].
        comm_retries: retries of a failed transaction before :class:`DynamixelError`.
        start_tolerance_ticks: how far outside its limits a motor may start (it is then
            clamped into them when torque comes on); farther is an error. Also how far a
            motor may be from a whole number of turns off its recorded position and still
            count as having lost those turns.
        ticks_per_rev: encoder ticks per revolution (X-series: 4096).
        record_path: a JSON file where :meth:`close` records the motors' positions and
            :meth:`open` compares them (:func:`compare_with_record`); None: no record.
    """

    def __init__(
        self,
        port: str,
        baud_rate: int,
        motor_ids: list[int],
        tick_limits: tuple[np.ndarray, np.ndarray],
        operating_mode: int = 5,
        goal_current_raw: int = 300,
        latency_timer_ms: float = 16.0,
        comm_retries: int = 2,
        start_tolerance_ticks: int = 256,
        ticks_per_rev: int = 4096,
        record_path: str | Path | None = None,
    ):
        self.port_name = str(port)
        self.baud_rate = int(baud_rate)
        self.motor_ids = [int(i) for i in motor_ids]
        lo, hi = (np.asarray(x, np.int64) for x in tick_limits)
        n = len(self.motor_ids)
        if lo.shape != (n,) or hi.shape != (n,):
            raise ValueError(f"tick_limits must be two arrays of shape ({n},), got {lo.shape} and {hi.shape}")
        if (
            np.any(lo > hi)
            or np.any(np.abs(lo) > EXTENDED_POSITION_LIMIT)
            or np.any(np.abs(hi) > EXTENDED_POSITION_LIMIT)
        ):
            raise ValueError(
                f"tick_limits must satisfy lo <= hi within +-{EXTENDED_POSITION_LIMIT}, got {lo} and {hi}"
            )
        self.tick_lower, self.tick_upper = lo, hi
        self.operating_mode = int(operating_mode)
        if self.operating_mode not in (4, 5):  # (3, single-turn position, had been written to the motors)
            raise ValueError(f"operating_mode must be 4 (extended position) or 5 (current-based position), "
                             f"got {operating_mode}")
        self.goal_current_raw = int(goal_current_raw)
        if self.operating_mode == 5 and not 1 <= self.goal_current_raw <= GOAL_CURRENT_MAX:
            raise ValueError(f"goal_current_raw must be in 1..{GOAL_CURRENT_MAX} in current-based position mode (5), "
                             f"got {self.goal_current_raw}")
        self.latency_timer_ms = float(latency_timer_ms)
        self.comm_retries = int(comm_retries)
        self.unconfirmed: list[int] = []  # motors that did not confirm the last torque off
        self.start_tolerance_ticks = int(start_tolerance_ticks)
        # (-1 retries had made no attempt at all: the first transaction an UnboundLocalError)
        for name, v in (("comm_retries", self.comm_retries), ("start_tolerance_ticks", self.start_tolerance_ticks)):
            if v < 0:
                raise ValueError(f"{name} must be >= 0, got {v}")
        self.ticks_per_rev = int(ticks_per_rev)
        if self.ticks_per_rev <= 0:
            raise ValueError(f"ticks_per_rev must be positive, got {ticks_per_rev}")
        self.record_path = None if record_path is None else Path(record_path)
        #: What :meth:`open` found against the record: messages (the bring-up tool prints them).
        self.record_findings: list[str] = []
        self._record_trusted = False  # close() records the positions only when True
        self.is_open = False
        self.torque_on = False
        #: The motors' model numbers, read by :meth:`open`'s pings.
        self.model_numbers: list[int] = []
        self._port = None
        self._ph = None
        self._sync_write = None
        self._sync_read = None

    @classmethod
    def from_config(cls, config, tick_limits: tuple[np.ndarray, np.ndarray]) -> TendonMotors:
        """Driver for a :class:`vlr_drake.hardware.config.HardwareConfig`."""
        return cls(
            port=config.port,
            baud_rate=config.baud_rate,
            motor_ids=list(config.motor_ids),
            tick_limits=tick_limits,
            operating_mode=config.operating_mode,
            goal_current_raw=config.goal_current_raw,
            latency_timer_ms=config.latency_timer_ms,
            comm_retries=config.comm_retries,
            start_tolerance_ticks=config.start_tolerance_ticks,
            ticks_per_rev=config.ticks_per_rev,
            record_path=config.motor_record_path(),
        )

    # --- life cycle -------------------------------------------------------------------------
    def open(self, enable_torque: bool = True) -> np.ndarray:
        """Safe start (module docstring, steps 1-6). Returns the first positions (N,) [ticks].

        A motor found more than ``start_tolerance_ticks`` outside its tick limits is an error
        (a wrong zero offset, e.g. after a power cycle reset the multi-turn count): nothing
        moves. So is one a whole number of turns from where the last run left it (the
        ``record_path`` record): the multi-turn count was reset and the zero offset is wrong by
        those turns, though the motor may still read inside its limits. Within the tolerance
        the first goal is the present position clamped into the limits.
        ``enable_torque=False`` stops after the first read (for bring-up tools): what the
        record shows is then only reported, in :attr:`record_findings`.
        """
        import dynamixel_sdk as sdk

        if self.is_open:
            raise DynamixelError(f"port {self.port_name} is already open")
        self._record_trusted = False  # until the positions are read and checked
        self._open_port()
        try:
            self.model_numbers = [  # a motor with a hardware error answers with the alert bit
                int(self._call(f"ping motor id {dxl_id}", lambda i=dxl_id: self._ph.ping(self._port, i), dxl_id,
                               allow_alert=True))
                for dxl_id in self.motor_ids]
            self._refuse_models_without_current()
            for dxl_id in self.motor_ids:
                self._refuse_hardware_error(dxl_id)
            for dxl_id in self.motor_ids:
                self._write1(dxl_id, ADDR_TORQUE_ENABLE, 0, "torque off")
                mode = self._call(
                    f"read operating mode of motor id {dxl_id}",
                    lambda i=dxl_id: self._ph.read1ByteTxRx(self._port, i, ADDR_OPERATING_MODE),
                    dxl_id,
                )
                if mode != self.operating_mode:
                    self._write1(dxl_id, ADDR_OPERATING_MODE, self.operating_mode, "set operating mode")
                if self.operating_mode == 5:
                    self._call(
                        f"set goal current of motor id {dxl_id}",
                        lambda i=dxl_id: self._ph.write2ByteTxRx(
                            self._port, i, ADDR_GOAL_CURRENT, self.goal_current_raw
                        ),
                        dxl_id,
                    )
            self._sync_write = sdk.GroupSyncWrite(self._port, self._ph, ADDR_GOAL_POSITION, 4)
            self._sync_read = _sync_read_class(sdk)(self._port, self._ph, READ_BLOCK_START, READ_BLOCK_LENGTH)
            for dxl_id in self.motor_ids:
                self._sync_read.addParam(dxl_id)
            ticks, _ = self._read_once()
            outside = np.maximum(self.tick_lower - ticks, ticks - self.tick_upper)
            far = outside > self.start_tolerance_ticks
            if np.any(far):
                ids = [i for i, f in zip(self.motor_ids, far, strict=True) if f]
                raise DynamixelError(
                    f"motor ids {ids} start at {ticks[far].tolist()} ticks, more than "
                    f"{self.start_tolerance_ticks} ticks outside their limits [{self.tick_lower[far].tolist()}, "
                    f"{self.tick_upper[far].tolist()}]; check zero_offset_ticks (a power cycle resets the "
                    "multi-turn count). Torque stays off."
                )
            self._check_record(ticks, refuse=enable_torque)
            if enable_torque:
                # Hold where the motors are: goal = present (clamped into the limits), then torque on.
                self._send_goal(np.clip(ticks, self.tick_lower, self.tick_upper))
                for dxl_id in self.motor_ids:
                    self._write1(dxl_id, ADDR_TORQUE_ENABLE, 1, "torque on")
                    self.torque_on = True
        except BaseException:
            self.close()
            raise
        log.info(
            "Dynamixel bus %s open, motors %s at %s ticks, torque %s",
            self.port_name,
            self.motor_ids,
            ticks,
            "on" if self.torque_on else "off",
        )
        return ticks

    def _check_record(self, ticks: np.ndarray, refuse: bool) -> None:
        """Compare the positions just read with the record of the last run (see :meth:`open`)."""
        self.record_findings = []
        self._record_trusted = True
        if self.record_path is None or not self.record_path.exists():
            return
        try:
            record = json.loads(self.record_path.read_text())
            lost, moved = compare_with_record(record, self.motor_ids, ticks, self.ticks_per_rev,
                                              self.start_tolerance_ticks)
        except (OSError, ValueError, TypeError, AttributeError) as e:
            self.record_findings.append(f"the motors' record {self.record_path} cannot be read ({e}); "
                                        "it is written again at the end")
            log.warning(self.record_findings[-1])
            return
        when = record.get("written", "the last run")
        for i, now, last, turns in lost:
            self.record_findings.append(
                f"motor id {i} reads {now} ticks, {turns:+d} turn{'s' if abs(turns) > 1 else ''} from the {last} "
                f"where the last run left it ({when}): a power cycle or a reboot reset its multi-turn count, so "
                "zero_offset_ticks is wrong by those turns; measure it again (python -m vlr_drake.hardware zero)")
        # Half a turn or more from the record is refused as a lost turn is: a power cycle and a
        # finger that sprang back after torque off read as -1.07 turns, which had only been
        # warned about, and the run had started a turn (31 mm of tendon) off (a review).
        far = [m for m in moved if abs(m[3]) >= 0.5]
        near = [m for m in moved if abs(m[3]) < 0.5]
        for i, now, last, turns in far:
            self.record_findings.append(
                f"motor id {i} reads {now} ticks, {turns:+.2f} turns from the {last} where the last run left it "
                f"({when}): half a turn or more, so a power cycle or a reboot may have reset its multi-turn count "
                "and it moved as well; measure zero_offset_ticks again (python -m vlr_drake.hardware zero)")
        for i, now, last, turns in near:
            self.record_findings.append(
                f"motor id {i} reads {now} ticks, {turns:+.2f} turns from the {last} where the last run left it "
                f"({when}): turned while its torque was off (less than half a turn: its turn count holds)")
            log.warning(self.record_findings[-1])
        if lost or far:
            self._record_trusted = False
            if refuse:
                raise DynamixelError("; ".join(self.record_findings[:len(lost) + len(far)])
                                     + f" (record: {self.record_path}). Torque stays off.")

    def accept_positions(self) -> None:
        """Take the present positions as right (they were just zeroed): :meth:`close` records
        them even where :meth:`open` found a lost turn."""
        self._record_trusted = True

    def _write_record(self) -> None:
        """Record where the motors are (after torque off), best effort: a failure is logged."""
        if self.record_path is None or not self._record_trusted or self._sync_read is None:
            return
        try:
            ticks, _ = self._read_once()
            data = {"port": self.port_name, "ticks": {str(i): int(t) for i, t in zip(self.motor_ids, ticks, strict=True)},
                    "written": time.strftime("%Y-%m-%d %H:%M:%S")}
            self.record_path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.record_path.with_suffix(".tmp")
            tmp.write_text(json.dumps(data, indent=1))
            tmp.replace(self.record_path)
        except Exception as e:  # the run's end must not fail on it
            log.warning("the motors' positions were not recorded in %s: %s", self.record_path, e)

    def _open_port(self) -> None:
        import dynamixel_sdk as sdk

        latency = self.latency_timer_ms

        class _Port(sdk.PortHandler):
            # The SDK's status timeout uses a fixed 16 ms USB latency; make it configurable.
            def setPacketTimeout(self, packet_length):  # noqa: N802 (SDK name)
                self.packet_start_time = self.getCurrentTime()
                self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * latency + 2.0

        self._port = _Port(self.port_name)
        self._ph = sdk.PacketHandler(2.0)
        try:
            ok = self._port.setBaudRate(self.baud_rate)
        except Exception as e:  # serial.SerialException, OSError
            self._port = None
            raise DynamixelError(f"cannot open Dynamixel port '{self.port_name}': {e}") from e
        if not ok:
            self._port = None
            raise DynamixelError(f"cannot open Dynamixel port '{self.port_name}' at {self.baud_rate} baud")
        self.is_open = True

    def _refuse_models_without_current(self) -> None:
        """Current-based position mode (5) on a model that has none (:data:`NO_CURRENT_MODELS`)
        is refused by name, before anything is written (the motor would refuse the mode
        with the SDK's generic "data value exceeds the limit")."""
        if self.operating_mode != 5:
            return
        bad = [(i, NO_CURRENT_MODELS[m]) for i, m in zip(self.motor_ids, self.model_numbers, strict=True)
               if m in NO_CURRENT_MODELS]
        if bad:
            names = ", ".join(f"id {i} is an {name}" for i, name in bad)
            models = "these models have" if len({name for _, name in bad}) > 1 else "that model has"
            raise DynamixelError(
                f"motors on '{self.port_name}': {names}; {models} no current-based position mode "
                "(operating_mode 5: the goal current that limits the tendon's pull); use a model with current "
                "control (XM430, XM540, XH430, XL330, XC330), or operating_mode 4 knowing that nothing then limits "
                "the pull and that motor_current reads the motor's load, not its current")

    def _refuse_hardware_error(self, dxl_id: int) -> None:
        """Raise naming the error when the motor still holds a hardware error (address 70; an
        overload or overheating of an earlier run is kept until the motor is rebooted)."""
        status = self._hardware_error_status(dxl_id)
        if status:
            raise DynamixelError(
                f"motor id {dxl_id} on '{self.port_name}' still reports a hardware error: "
                f"{hardware_error_text(status)} (status 0x{status:02x}); it keeps its torque off until it is "
                "rebooted (python -m vlr_drake.hardware reboot --config ...; find the cause first)"
            )

    def _hardware_error_status(self, dxl_id: int) -> int:
        """The motor's hardware error status byte (address 70; 0: none)."""
        return int(self._call(
            f"read hardware error status of motor id {dxl_id}",
            lambda: self._ph.read1ByteTxRx(self._port, dxl_id, ADDR_HARDWARE_ERROR_STATUS),
            dxl_id,
            allow_alert=True,
        ))

    def reboot(self) -> list[int]:
        """Reboot every motor (the Dynamixel REBOOT instruction), which clears a hardware
        error; torque is off after it. The port must not be open; it is opened and closed
        here. Returns the hardware error status each motor had (address 70). A reboot may
        reset a motor's multi-turn count, as a power cycle does: ``open`` then finds the
        motors far outside their limits until ``zero_offset_ticks`` are measured again."""
        import time

        if self.is_open:
            raise DynamixelError(f"port {self.port_name} is already open")
        self._open_port()
        had = []
        try:
            for dxl_id in self.motor_ids:
                had.append(self._hardware_error_status(dxl_id))
                self._call(f"reboot motor id {dxl_id}", lambda i=dxl_id: self._ph.reboot(self._port, i), dxl_id,
                           allow_alert=True)
            time.sleep(REBOOT_WAIT_S)  # the motors start again
            for dxl_id in self.motor_ids:
                self._call(f"ping motor id {dxl_id} after its reboot", lambda i=dxl_id: self._ph.ping(self._port, i),
                           dxl_id)
        finally:
            self._close_port()
        return had

    def _close_port(self) -> None:
        try:
            self._port.closePort()
        except Exception:
            pass
        self.is_open = False

    def close(self) -> None:
        """Torque off (best effort: one broadcast sync write, then confirmed writes) and close
        the port. Safe to call more than once and after errors."""
        if not self.is_open:
            return
        confirmed = False
        try:
            confirmed = self.torque_off()
            self._write_record()
        finally:
            self._close_port()
            log.info("Dynamixel bus %s closed", self.port_name)
            if not confirmed:  # said, not reported as off (a review: a silent bus was "off")
                unconfirmed_torque_off.append(self.port_name)
                warnings.warn(f"Dynamixel bus '{self.port_name}': motors {self.unconfirmed} did not confirm "
                              "torque off; their torque may still be on: cut the motors' power",
                              RuntimeWarning, stacklevel=2)

    def torque_off(self) -> bool:
        """Switch torque off on every motor. Returns True when every motor confirmed it."""
        import dynamixel_sdk as sdk

        if not self.is_open:
            return False
        self._port.is_using = False
        try:
            group = sdk.GroupSyncWrite(self._port, self._ph, ADDR_TORQUE_ENABLE, 1)
            for dxl_id in self.motor_ids:
                group.addParam(dxl_id, [0])
            group.txPacket()
        except Exception as e:
            log.warning("broadcast torque off on %s failed: %s", self.port_name, e)
        self.unconfirmed = []
        for dxl_id in self.motor_ids:
            # retried as every other transaction (one corrupted reply had raised "cut the
            # motors' power" for a motor whose torque the broadcast had switched off: a review)
            for _ in range(1 + self.comm_retries):
                try:
                    self._port.is_using = False
                    result, error = self._ph.write1ByteTxRx(self._port, dxl_id, ADDR_TORQUE_ENABLE, 0)
                    if result == sdk.COMM_SUCCESS and (error & ~ERRBIT_ALERT) == 0:
                        break
                except Exception:  # noqa: BLE001 - retried, then reported as unconfirmed
                    pass
            else:
                self.unconfirmed.append(dxl_id)
        self.torque_on = False
        return not self.unconfirmed

    def __enter__(self) -> TendonMotors:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- running ----------------------------------------------------------------------------
    def write_goal_ticks(self, ticks: np.ndarray) -> None:
        """Send goal positions (N,) [ticks] to all motors with one sync write.

        Goals outside the tick limits raise ``ValueError`` and nothing is sent (the motors
        hold their last goal). A bus failure raises :class:`DynamixelError` after torque off.
        """
        ticks = np.asarray(ticks)
        if ticks.shape != (len(self.motor_ids),):
            raise ValueError(f"goal ticks must have shape ({len(self.motor_ids)},), got {ticks.shape}")
        if not np.issubdtype(ticks.dtype, np.integer):
            raise ValueError(f"goal ticks must be integers, got dtype {ticks.dtype}")
        bad = (ticks < self.tick_lower) | (ticks > self.tick_upper)
        if np.any(bad):
            ids = [i for i, b in zip(self.motor_ids, bad, strict=True) if b]
            raise ValueError(
                f"goal ticks {ticks.tolist()} outside the limits [{self.tick_lower.tolist()}, "
                f"{self.tick_upper.tolist()}] for motor ids {ids}; nothing sent"
            )
        self._require_open()
        self._guarded(lambda: self._send_goal(ticks))

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Present positions (N,) [ticks] and currents (N,) [raw units] from one sync read."""
        self._require_open()
        return self._guarded(self._read_once)

    # --- internals --------------------------------------------------------------------------
    def _require_open(self) -> None:
        if not self.is_open:
            raise DynamixelError(f"Dynamixel port '{self.port_name}' is not open")

    def _guarded(self, fn):
        """Run ``fn``; on any failure switch torque off, close the port and raise: a bus
        error as :class:`DynamixelError`, an interruption (Ctrl-C, a stop signal: not an
        Exception) as itself."""
        try:
            return fn()
        except BaseException as e:
            log.error("Dynamixel failure on %s: %r; switching torque off", self.port_name, e)
            try:
                self.close()
            except Exception:
                pass
            if isinstance(e, DynamixelError) or not isinstance(e, Exception):
                raise
            raise DynamixelError(f"Dynamixel bus '{self.port_name}' failed: {e}") from e

    def _call(self, what: str, fn, dxl_id: int | None = None, allow_alert: bool = False):
        """Run one SDK transaction with retries. ``fn`` returns (value..., result, error).
        ``allow_alert``: a status error byte that is only the alert bit counts as success."""
        import dynamixel_sdk as sdk

        last = ""
        for _ in range(self.comm_retries + 1):
            try:
                out = fn()
            except Exception as e:
                raise DynamixelError(f"{what}: port '{self.port_name}' failed: {e}") from e
            out = out if isinstance(out, tuple) else (out,)
            if len(out) == 3:
                value, result, error = out
            else:
                value, (result, error) = None, out
            if allow_alert:
                error &= ~ERRBIT_ALERT
            if result == sdk.COMM_SUCCESS and error == 0:
                return value
            if result != sdk.COMM_SUCCESS:
                last = self._ph.getTxRxResult(result)
            else:
                last = self._ph.getRxPacketError(error)
        who = (
            f" (motor id {dxl_id} on '{self.port_name}' at {self.baud_rate} baud)"
            if dxl_id is not None
            else ""
        )
        if result == sdk.COMM_RX_TIMEOUT and dxl_id is not None:
            raise DynamixelError(f"{what}: motor id {dxl_id} does not answer{who}: {last}")
        raise DynamixelError(f"{what}{who}: {last}")

    def _write1(self, dxl_id: int, addr: int, value: int, what: str) -> None:
        self._call(
            f"{what} (address {addr}) of motor id {dxl_id}",
            lambda: self._ph.write1ByteTxRx(self._port, dxl_id, addr, value),
            dxl_id,
        )

    def _send_goal(self, ticks: np.ndarray) -> None:
        import dynamixel_sdk as sdk

        self._sync_write.clearParam()
        for dxl_id, t in zip(self.motor_ids, ticks, strict=True):
            v = int(t) & 0xFFFFFFFF
            self._sync_write.addParam(dxl_id, [v & 0xFF, (v >> 8) & 0xFF, (v >> 16) & 0xFF, (v >> 24) & 0xFF])
        for _ in range(self.comm_retries + 1):
            try:
                result = self._sync_write.txPacket()
            except Exception as e:
                raise DynamixelError(f"sync write of goal positions on '{self.port_name}' failed: {e}") from e
            if result == sdk.COMM_SUCCESS:
                return
        raise DynamixelError(
            f"sync write of goal positions on '{self.port_name}': {self._ph.getTxRxResult(result)}"
        )

    def _check_alerts(self) -> None:
        """Raise naming the motor and its hardware error (overload, overheating, ...) when a
        status packet of the last sync read had the alert bit set."""
        for dxl_id in self.motor_ids:
            if self._sync_read.errors.get(dxl_id, 0) & ERRBIT_ALERT:
                status = self._hardware_error_status(dxl_id)
                raise DynamixelError(
                    f"motor id {dxl_id} on '{self.port_name}' reports a hardware error: "
                    f"{hardware_error_text(status)} (status 0x{status:02x}); the motor has shut its "
                    "torque off and needs a reboot (python -m vlr_drake.hardware reboot)"
                )

    def _read_once(self) -> tuple[np.ndarray, np.ndarray]:
        import dynamixel_sdk as sdk

        what = ""
        for _ in range(self.comm_retries + 1):
            try:
                result = self._sync_read.txRxPacket()
            except Exception as e:
                raise DynamixelError(
                    f"sync read of present position on '{self.port_name}' failed: {e}"
                ) from e
            missing = [
                i
                for i in self.motor_ids
                if not self._sync_read.isAvailable(i, READ_BLOCK_START, READ_BLOCK_LENGTH)
                or len(self._sync_read.data_dict.get(i, [])) != READ_BLOCK_LENGTH
            ]
            # a status error other than the alert bit (e.g. a CRC error after line noise, with no
            # data): a failed attempt, retried and named; it had been read as data (a review)
            bad = {i: e & ~ERRBIT_ALERT for i, e in getattr(self._sync_read, "errors", {}).items()
                   if e & ~ERRBIT_ALERT}
            if result == sdk.COMM_SUCCESS and bad:
                i, e = next(iter(bad.items()))
                what = f"motor id {i} answered with status error {self._ph.getRxPacketError(e)} (0x{e:02x})"
                continue
            if result == sdk.COMM_SUCCESS and not missing:
                self._check_alerts()
                pos = [
                    _signed(self._sync_read.getData(i, ADDR_PRESENT_POSITION, 4), 32) for i in self.motor_ids
                ]
                cur = [
                    _signed(self._sync_read.getData(i, ADDR_PRESENT_CURRENT, 2), 16) for i in self.motor_ids
                ]
                return np.array(pos, np.int64), np.array(cur, np.int64)
            # The SDK stops at the first motor that fails; name it.
            failed = next(
                (i for i in self.motor_ids if len(self._sync_read.data_dict.get(i, [])) != READ_BLOCK_LENGTH),
                None,
            )
            what = f"{self._ph.getTxRxResult(result)}" + (
                f" (first failing motor id {failed})" if failed is not None else ""
            )
        raise DynamixelError(
            f"sync read of present position on '{self.port_name}' at {self.baud_rate} baud: {what}"
        )
