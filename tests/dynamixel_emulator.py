"""A Dynamixel protocol 2.0 bus emulator on a pseudo-terminal, for tests without hardware.

The emulator opens a pty pair (``os.openpty()``); the slave's device name is the serial port
handed to the Dynamixel SDK, which then talks to the emulated motors through pyserial exactly
as it would through a U2D2 adapter. A thread reads instruction packets from the master side,
checks their CRC, removes byte stuffing and answers like X-series servos:

- instructions PING (0x01), READ (0x02), WRITE (0x03), REBOOT (0x08), SYNC READ (0x82),
  SYNC WRITE (0x83); a reboot clears the hardware error and the torque and, taken as the
  cautious case, the multi-turn count (the present position within one turn);
- status packets (0x55) with CRC-16 (polynomial 0x8005, table driven, as in the protocol
  2.0 specification) and byte stuffing (FF FF FD -> FF FF FD FD);
- a control table per motor id (X-series addresses: model number 0, operating mode 11,
  torque enable 64, goal current 102, goal position 116, present current 126, present
  velocity 128, present position 132); EEPROM (address < 64) is read-only while torque is
  on (access error 7), as on the real servo;
- a present position that follows the goal position while torque is on, immediately or with
  a first-order lag (time constant ``lag_s``);
- hardware errors (:meth:`DynamixelEmulator.set_hardware_error`): torque off, the alert bit
  in every status packet, the cause at address 70.

Fault injection: ``missing_ids`` (motors that never answer), ``corrupt_ids`` (replies with a
broken CRC), ``corrupt_next`` (the next n replies are broken: a transient fault), ``silent``
(the whole bus stops answering), :meth:`disconnect` (the adapter is unplugged: the pty master
is closed, so the SDK's reads and writes fail).
"""

from __future__ import annotations

import math
import os
import select
import struct
import threading
import time
import tty

__all__ = ["DynamixelEmulator", "crc16", "CRC_TABLE"]

# Instructions and addresses (Dynamixel protocol 2.0, X-series control table).
PING, READ, WRITE, REBOOT, STATUS, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x08, 0x55, 0x82, 0x83
BROADCAST_ID = 0xFE
ERR_CRC, ERR_INSTRUCTION, ERR_DATA_LENGTH, ERR_ACCESS = 3, 2, 5, 7
ADDR_MODEL_NUMBER, ADDR_FIRMWARE, ADDR_ID, ADDR_OPERATING_MODE = 0, 6, 7, 11
ADDR_TORQUE_ENABLE, ADDR_GOAL_CURRENT, ADDR_GOAL_POSITION = 64, 102, 116
ADDR_HARDWARE_ERROR_STATUS = 70
ERRBIT_ALERT = 0x80
ADDR_PRESENT_CURRENT, ADDR_PRESENT_VELOCITY, ADDR_PRESENT_POSITION = 126, 128, 132
EEPROM_END = 64
TABLE_SIZE = 147


def _crc_table(poly: int = 0x8005) -> list[int]:
    """CRC-16 lookup table for the (non-reflected) polynomial ``poly``."""
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ poly) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray | list[int], crc: int = 0) -> int:
    """Protocol 2.0 CRC-16 (polynomial 0x8005, initial value 0, no reflection)."""
    for b in data:
        crc = ((crc << 8) ^ CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def _stuff(body: bytes) -> bytes:
    """Byte stuffing of a packet body: after every FF FF FD insert an extra FD."""
    out = bytearray()
    for b in body:
        out.append(b)
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def _unstuff(body: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # drop the stuffing byte
        i += 1
    return bytes(out)


def status_packet(dxl_id: int, error: int, params: bytes = b"", corrupt: bool = False) -> bytes:
    """A status packet with stuffing and CRC (the CRC is flipped when ``corrupt``)."""
    body = _stuff(bytes([STATUS, error]) + bytes(params))
    length = len(body) + 2
    pkt = bytes([0xFF, 0xFF, 0xFD, 0x00, dxl_id, length & 0xFF, length >> 8]) + body
    crc = crc16(pkt) ^ (0xFFFF if corrupt else 0)
    return pkt + bytes([crc & 0xFF, crc >> 8])


class _Motor:
    def __init__(self, dxl_id: int, model_number: int, position: int):
        self.table = bytearray(TABLE_SIZE)
        struct.pack_into("<H", self.table, ADDR_MODEL_NUMBER, model_number)
        self.table[ADDR_FIRMWARE] = 46
        self.table[ADDR_ID] = dxl_id
        self.table[ADDR_OPERATING_MODE] = 3  # factory default: position mode
        struct.pack_into("<i", self.table, ADDR_GOAL_POSITION, position)
        struct.pack_into("<i", self.table, ADDR_PRESENT_POSITION, position)
        self.position = float(position)

    def get(self, addr: int, fmt: str) -> int:
        return struct.unpack_from(fmt, self.table, addr)[0]


class DynamixelEmulator:
    """X-series servos on a pty; use :attr:`port_name` as the SDK's port.

    Args:
        motor_ids: ids of the emulated motors.
        initial_positions: present position [ticks] per id (default 0).
        lag_s: time constant of the present position following the goal (0: immediate).
        model_number: value at address 0 (1020 = XM430-W350).
    """

    def __init__(
        self,
        motor_ids: list[int] | tuple[int, ...] = (1, 2, 3),
        initial_positions: dict[int, int] | None = None,
        lag_s: float = 0.0,
        model_number: int = 1020,
    ):
        initial_positions = initial_positions or {}
        self.motors = {i: _Motor(i, model_number, int(initial_positions.get(i, 0))) for i in motor_ids}
        self.lag_s = float(lag_s)
        self.missing_ids: set[int] = set()
        self.corrupt_ids: set[int] = set()
        self.silent = False
        #: The next this-many status packets get a broken CRC (a transient fault).
        self.corrupt_next = 0
        #: Every instruction packet received with a good CRC: (time, id, instruction, params).
        self.log: list[tuple[float, int, int, bytes]] = []
        #: Number of instruction packets received with a bad CRC.
        self.bad_crc_count = 0
        #: Ids of the motors rebooted, in order.
        self.reboots: list[int] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port_name = os.ttyname(self._slave)
        self._thread: threading.Thread | None = None
        self._last_step = time.monotonic()
        self._connected = True
        self._idle_rounds = 0

    # --- life cycle -----------------------------------------------------------------------
    def start(self) -> DynamixelEmulator:
        self._thread = threading.Thread(target=self._run, name="dynamixel-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._connected = False

    def __enter__(self) -> DynamixelEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def disconnect(self) -> None:
        """Unplug the adapter: close the pty master, so the port's reads and writes fail."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._connected:
            os.close(self._master)
            self._connected = False

    def wait_idle(self, timeout: float = 2.0) -> None:
        """Wait until every byte written to the port so far has been handled (packets without
        a reply, like sync write, are otherwise handled a moment after the SDK returns)."""
        start = self._idle_rounds
        deadline = time.monotonic() + timeout
        while self._idle_rounds < start + 2:
            if time.monotonic() > deadline:
                raise TimeoutError("dynamixel emulator: not idle")
            time.sleep(0.001)

    # --- inspection -------------------------------------------------------------------------
    def goal_position(self, dxl_id: int) -> int:
        with self._lock:
            return self.motors[dxl_id].get(ADDR_GOAL_POSITION, "<i")

    def present_position(self, dxl_id: int) -> int:
        with self._lock:
            self._step()
            return self.motors[dxl_id].get(ADDR_PRESENT_POSITION, "<i")

    def torque_enabled(self, dxl_id: int) -> bool:
        with self._lock:
            return bool(self.motors[dxl_id].table[ADDR_TORQUE_ENABLE])

    def operating_mode(self, dxl_id: int) -> int:
        with self._lock:
            return self.motors[dxl_id].table[ADDR_OPERATING_MODE]

    def set_hardware_error(self, dxl_id: int, status: int) -> None:
        """Raise a hardware error (address 70 bits, e.g. 0x20 overload): like the real servo,
        the motor switches its torque off and flags the alert bit in every status packet."""
        with self._lock:
            m = self.motors[dxl_id]
            m.table[ADDR_HARDWARE_ERROR_STATUS] = status
            m.table[ADDR_TORQUE_ENABLE] = 0

    def set_present_position(self, dxl_id: int, ticks: int) -> None:
        with self._lock:
            m = self.motors[dxl_id]
            m.position = float(ticks)
            struct.pack_into("<i", m.table, ADDR_PRESENT_POSITION, int(ticks))

    def instructions(self, instruction: int, address: int | None = None) -> list[tuple[int, int, bytes]]:
        """Logged packets of one instruction (optionally at one start address), as (n, id,
        parameters) with n the packet's place in the log: their order of arrival, which a
        clock's stamps could tie."""
        with self._lock:
            out = []
            for n, (_, i, inst, p) in enumerate(self.log):
                if inst == instruction and (
                    address is None or (len(p) >= 2 and p[0] | (p[1] << 8) == address)
                ):
                    out.append((n, i, p))
            return out

    # --- the bus ----------------------------------------------------------------------------
    def _run(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.002)
                if not ready:
                    with self._lock:
                        self._step()
                    self._idle_rounds += 1
                    continue
                chunk = os.read(self._master, 4096)
            except OSError:
                return
            buf.extend(chunk)
            while True:
                pkt = self._take_packet(buf)
                if pkt is None:
                    break
                with self._lock:
                    self._step()
                    reply = self._handle(pkt)
                if reply:
                    try:
                        os.write(self._master, reply)
                    except OSError:
                        return

    def _take_packet(self, buf: bytearray) -> bytes | None:
        """Remove and return one complete raw packet from ``buf`` (None: need more bytes)."""
        while True:
            k = buf.find(b"\xff\xff\xfd\x00")
            if k < 0:
                del buf[: max(0, len(buf) - 3)]
                return None
            del buf[:k]
            if len(buf) < 7:
                return None
            total = 7 + (buf[5] | (buf[6] << 8))
            if len(buf) < total:
                return None
            pkt = bytes(buf[:total])
            del buf[:total]
            return pkt

    def _step(self) -> None:
        """Advance each torque-on motor's present position towards its goal."""
        now = time.monotonic()
        dt = now - self._last_step
        self._last_step = now
        for m in self.motors.values():
            goal = m.get(ADDR_GOAL_POSITION, "<i")
            if m.table[ADDR_TORQUE_ENABLE]:
                if self.lag_s <= 0.0:
                    m.position = float(goal)
                else:
                    m.position += (goal - m.position) * (1.0 - math.exp(-dt / self.lag_s))
            pos = int(round(m.position))
            struct.pack_into("<i", m.table, ADDR_PRESENT_POSITION, pos)
            current = max(-1000, min(1000, int(0.5 * (goal - pos)))) if m.table[ADDR_TORQUE_ENABLE] else 0
            struct.pack_into("<h", m.table, ADDR_PRESENT_CURRENT, current)

    def _answers(self, dxl_id: int) -> bool:
        return dxl_id in self.motors and dxl_id not in self.missing_ids and not self.silent

    def _status(self, dxl_id: int, error: int, params: bytes = b"") -> bytes:
        corrupt = dxl_id in self.corrupt_ids or self.corrupt_next > 0
        self.corrupt_next = max(0, self.corrupt_next - 1)
        if self.motors[dxl_id].table[ADDR_HARDWARE_ERROR_STATUS]:
            error |= ERRBIT_ALERT
        return status_packet(dxl_id, error, params, corrupt=corrupt)

    def _handle(self, pkt: bytes) -> bytes:
        dxl_id = pkt[4]
        crc = pkt[-2] | (pkt[-1] << 8)
        if crc16(pkt[:-2]) != crc:
            self.bad_crc_count += 1
            if dxl_id != BROADCAST_ID and self._answers(dxl_id):
                return self._status(dxl_id, ERR_CRC)
            return b""
        body = _unstuff(pkt[7:-2])
        inst, params = body[0], body[1:]
        if self.silent:
            return b""
        self.log.append((time.monotonic(), dxl_id, inst, bytes(params)))
        if inst == PING:
            ids = list(self.motors) if dxl_id == BROADCAST_ID else [dxl_id]
            out = b""
            for i in ids:
                if self._answers(i):
                    model = self.motors[i].get(ADDR_MODEL_NUMBER, "<H")
                    out += self._status(i, 0, struct.pack("<HB", model, self.motors[i].table[ADDR_FIRMWARE]))
            return out
        if inst == READ:
            if not self._answers(dxl_id):
                return b""
            addr, length = struct.unpack_from("<HH", params)
            if addr + length > TABLE_SIZE:
                return self._status(dxl_id, ERR_ACCESS)
            return self._status(dxl_id, 0, bytes(self.motors[dxl_id].table[addr : addr + length]))
        if inst == WRITE:
            if not self._answers(dxl_id):
                return b""
            addr = params[0] | (params[1] << 8)
            error = self._write(dxl_id, addr, params[2:])
            return self._status(dxl_id, error)
        if inst == REBOOT:
            if not self._answers(dxl_id):
                return b""
            reply = self._status(dxl_id, 0)
            m = self.motors[dxl_id]
            m.table[ADDR_HARDWARE_ERROR_STATUS] = 0
            m.table[ADDR_TORQUE_ENABLE] = 0
            m.position = float(int(round(m.position)) % 4096)
            struct.pack_into("<i", m.table, ADDR_PRESENT_POSITION, int(m.position))
            self.reboots.append(dxl_id)
            return reply
        if inst == SYNC_READ:
            addr, length = struct.unpack_from("<HH", params)
            out = b""
            for i in params[4:]:
                if self._answers(i) and addr + length <= TABLE_SIZE:
                    out += self._status(i, 0, bytes(self.motors[i].table[addr : addr + length]))
            return out
        if inst == SYNC_WRITE:
            addr, length = struct.unpack_from("<HH", params)
            data = params[4:]
            for k in range(0, len(data) - length + 1, length + 1):
                i = data[k]
                if self._answers(i):
                    self._write(i, addr, data[k + 1 : k + 1 + length])
            return b""
        return self._status(dxl_id, ERR_INSTRUCTION) if self._answers(dxl_id) else b""

    def _write(self, dxl_id: int, addr: int, data: bytes) -> int:
        m = self.motors[dxl_id]
        if addr + len(data) > TABLE_SIZE:
            return ERR_DATA_LENGTH
        if addr < EEPROM_END and m.table[ADDR_TORQUE_ENABLE]:
            return ERR_ACCESS  # EEPROM is locked while torque is on
        if addr <= ADDR_PRESENT_CURRENT < addr + len(data) or addr <= ADDR_PRESENT_POSITION < addr + len(
            data
        ):
            return ERR_ACCESS  # read-only area
        if addr == ADDR_TORQUE_ENABLE and data[0] and not m.table[ADDR_TORQUE_ENABLE]:
            m.position = float(m.get(ADDR_PRESENT_POSITION, "<i"))
        m.table[addr : addr + len(data)] = data
        return 0
