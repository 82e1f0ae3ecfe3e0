"""An emulated Dynamixel MX-28 gripper servo on a pseudo-terminal.

The emulator is the independent peer that the real ``dynamixel-sdk`` talks to in tests and in the
simulated rig, so it implements the wire protocol itself (it must not import ``dynamixel_sdk``):

* Protocol 2.0: ``FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS | CRC_L CRC_H``, CRC-16 with the
  Dynamixel polynomial 0x8005 over everything before the CRC, byte stuffing ``FF FF FD`` ->
  ``FF FF FD FD`` from the instruction byte on; status packets use instruction 0x55 and an error
  byte whose bit 7 (alert) says "read Hardware Error Status (70)".
* Protocol 1.0: ``FF FF | ID | LEN | INST | PARAMS | CHECKSUM`` with ``~sum & 0xFF``; status packets
  carry an error bit field (overload = 0x20, ...).

Instructions: ping, read, write, sync write, reboot (2.0 only). Control tables follow ROBOTIS'
e-manual for the MX-28 (model number 30 under 2.0, 29 under 1.0).

Behind the control table sits a small gripper model (:class:`JawModel`): Goal Position closes the jaw
(a first-order servo lag with a speed limit); once the jaw meets the object the grip force grows with
the position error, limited by Goal PWM (2.0) or Torque Limit (1.0); grip force follows its target
through a second first-order lag, and commands take effect on the servo's refresh ticks (the
method's rig refreshed the MX-28 at about 62 Hz). The model is integrated lazily up to "now"
whenever someone looks, so no physics thread spins.

Fault injection: an absent device (no reply at all), a talking-to-another-ID bus (the servo only
answers its own ID), overload (Hardware Error Status bit 5 and the alert bit; torque off as the
default Shutdown setting does), torque-off (goals are stored but ignored), not answering for N ms,
and reboot.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

BROADCAST_ID = 0xFE

# Instructions (shared numbering between protocols where both have them).
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REBOOT = 0x08
INST_STATUS = 0x55
INST_SYNC_WRITE = 0x83

# Protocol 2.0 status error numbers (low 7 bits) and the alert bit.
ERR2_RESULT_FAIL = 1
ERR2_INSTRUCTION = 2
ERR2_CRC = 3
ERR2_DATA_RANGE = 4
ERR2_DATA_LENGTH = 5
ERR2_DATA_LIMIT = 6
ERR2_ACCESS = 7
ERR2_ALERT = 0x80

# Protocol 1.0 status error bits.
ERR1_VOLTAGE = 0x01
ERR1_ANGLE = 0x02
ERR1_OVERHEAT = 0x04
ERR1_RANGE = 0x08
ERR1_CHECKSUM = 0x10
ERR1_OVERLOAD = 0x20
ERR1_INSTRUCTION = 0x40

# Hardware Error Status (2.0, address 70) bits.
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_ENCODER = 0x08
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20

MODEL_NUMBER_V2 = 30
MODEL_NUMBER_V1 = 29
FIRMWARE_VERSION = 41
PWM_MAX = 885  # MX-28(2.0) PWM Limit initial value and maximum (100 %)
TORQUE_MAX_V1 = 1023


# --------------------------------------------------------------------------------------------------
# Checksums and packet framing (our own implementation; tests check it against the vendor SDK).
# --------------------------------------------------------------------------------------------------
def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16_dxl(data: Iterable[int], crc: int = 0) -> int:
    """CRC-16 of Dynamixel Protocol 2.0: polynomial 0x8005, initial 0, no reflection, no final XOR."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def checksum_v1(data: Iterable[int]) -> int:
    """Protocol 1.0 checksum of ID, LENGTH, INSTRUCTION/ERROR and parameters: ``~sum & 0xFF``."""
    return (~sum(data)) & 0xFF


def stuff(body: bytes) -> bytes:
    """Protocol 2.0 byte stuffing: after every ``FF FF FD`` in ``body`` insert an extra ``FD``."""
    out = bytearray()
    for i, b in enumerate(body):
        out.append(b)
        if b == 0xFD and i >= 2 and body[i - 1] == 0xFF and body[i - 2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Undo :func:`stuff`: ``FF FF FD FD`` -> ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        if body[i : i + 4] == b"\xff\xff\xfd\xfd":
            out += b"\xff\xff\xfd"
            i += 4
        else:
            out.append(body[i])
            i += 1
    return bytes(out)


def encode_v2(dxl_id: int, instruction: int, params: bytes = b"", error: int | None = None) -> bytes:
    """One Protocol 2.0 packet; with ``error`` it is a status packet (instruction 0x55 + error byte)."""
    body = bytes([instruction]) + (bytes([error]) if error is not None else b"") + bytes(params)
    body = stuff(body)
    length = len(body) + 2
    head = bytes([0xFF, 0xFF, 0xFD, 0x00, dxl_id, length & 0xFF, length >> 8])
    crc = crc16_dxl(head + body)
    return head + body + bytes([crc & 0xFF, crc >> 8])


def encode_v1(dxl_id: int, instruction_or_error: int, params: bytes = b"") -> bytes:
    """One Protocol 1.0 packet (instruction packet, or status packet with the error byte)."""
    core = bytes([dxl_id, len(params) + 2, instruction_or_error]) + bytes(params)
    return b"\xff\xff" + core + bytes([checksum_v1(core)])


@dataclass(frozen=True)
class Packet:
    """A decoded instruction packet."""

    dxl_id: int
    instruction: int
    params: bytes
    valid: bool  # checksum/CRC matched


def parse_v2(buf: bytearray) -> Packet | None:
    """Take the next complete Protocol 2.0 packet off the front of ``buf`` (in place); None if incomplete."""
    while True:
        start = buf.find(b"\xff\xff\xfd\x00")
        if start < 0:
            # Keep a possible partial header at the end.
            keep = next((k for k in (3, 2, 1) if bytes(buf[-k:]) == b"\xff\xff\xfd"[:k]), 0)
            del buf[: len(buf) - keep]
            return None
        del buf[:start]
        if len(buf) < 7:
            return None
        length = buf[5] | (buf[6] << 8)
        if length < 3 or length > 1024:
            del buf[:1]  # not a real header: resynchronise
            continue
        total = 7 + length
        if len(buf) < total:
            return None
        raw = bytes(buf[:total])
        del buf[:total]
        crc = raw[-2] | (raw[-1] << 8)
        body = unstuff(raw[7:-2])
        return Packet(raw[4], body[0], body[1:], crc16_dxl(raw[:-2]) == crc)


def parse_v1(buf: bytearray) -> Packet | None:
    """Take the next complete Protocol 1.0 packet off the front of ``buf`` (in place); None if incomplete."""
    while True:
        start = buf.find(b"\xff\xff")
        if start < 0:
            keep = 1 if buf[-1:] == b"\xff" else 0
            del buf[: len(buf) - keep]
            return None
        del buf[:start]
        if len(buf) < 4:
            return None
        if buf[2] == 0xFF or buf[3] < 2:
            del buf[:1]
            continue
        total = 4 + buf[3]
        if len(buf) < total:
            return None
        raw = bytes(buf[:total])
        del buf[:total]
        return Packet(raw[2], raw[4], raw[5:-1], checksum_v1(raw[2:-1]) == raw[-1])


# --------------------------------------------------------------------------------------------------
# Control tables
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Register:
    """One control-table item."""

    name: str
    address: int
    size: int
    writable: bool
    initial: int = 0
    signed: bool = False
    eeprom: bool = False  # 2.0: writable only while torque is off


def _r(name: str, address: int, size: int, access: str, initial: int = 0, signed: bool = False) -> Register:
    return Register(name, address, size, access == "RW", initial, signed, eeprom=False)


def _e(name: str, address: int, size: int, initial: int = 0, access: str = "RW", signed: bool = False) -> Register:
    return Register(name, address, size, access == "RW", initial, signed, eeprom=True)


# MX-28(2.0): ROBOTIS e-manual, "MX-28(2.0) Control Table".
TABLE_V2: tuple[Register, ...] = (
    _e("model_number", 0, 2, MODEL_NUMBER_V2, "R"),
    _e("model_information", 2, 4, 0, "R"),
    _e("firmware_version", 6, 1, FIRMWARE_VERSION, "R"),
    _e("id", 7, 1, 1),
    _e("baud_rate", 8, 1, 1),
    _e("return_delay_time", 9, 1, 250),
    _e("drive_mode", 10, 1, 0),
    _e("operating_mode", 11, 1, 3),
    _e("secondary_id", 12, 1, 255),
    _e("protocol_type", 13, 1, 2),
    _e("homing_offset", 20, 4, 0, signed=True),
    _e("moving_threshold", 24, 4, 10),
    _e("temperature_limit", 31, 1, 80),
    _e("max_voltage_limit", 32, 2, 160),
    _e("min_voltage_limit", 34, 2, 95),
    _e("pwm_limit", 36, 2, PWM_MAX),
    _e("acceleration_limit", 40, 4, 32767),
    _e("velocity_limit", 44, 4, 380),
    _e("max_position_limit", 48, 4, 4095),
    _e("min_position_limit", 52, 4, 0),
    _e("shutdown", 63, 1, 52),
    _r("torque_enable", 64, 1, "RW"),
    _r("led", 65, 1, "RW"),
    _r("status_return_level", 68, 1, "RW", 2),
    _r("registered_instruction", 69, 1, "R"),
    _r("hardware_error_status", 70, 1, "R"),
    _r("velocity_i_gain", 76, 2, "RW", 1920),
    _r("velocity_p_gain", 78, 2, "RW", 100),
    _r("position_d_gain", 80, 2, "RW", 0),
    _r("position_i_gain", 82, 2, "RW", 0),
    _r("position_p_gain", 84, 2, "RW", 850),
    _r("feedforward_2nd_gain", 88, 2, "RW"),
    _r("feedforward_1st_gain", 90, 2, "RW"),
    _r("bus_watchdog", 98, 1, "RW"),
    _r("goal_pwm", 100, 2, "RW", PWM_MAX, signed=True),
    _r("goal_velocity", 104, 4, "RW", 0, signed=True),
    _r("profile_acceleration", 108, 4, "RW"),
    _r("profile_velocity", 112, 4, "RW"),
    _r("goal_position", 116, 4, "RW", 0, signed=True),
    _r("realtime_tick", 120, 2, "R"),
    _r("moving", 122, 1, "R"),
    _r("moving_status", 123, 1, "R"),
    _r("present_pwm", 124, 2, "R", signed=True),
    _r("present_load", 126, 2, "R", signed=True),
    _r("present_velocity", 128, 4, "R", signed=True),
    _r("present_position", 132, 4, "R", signed=True),
    _r("velocity_trajectory", 136, 4, "R", signed=True),
    _r("position_trajectory", 140, 4, "R", signed=True),
    _r("present_input_voltage", 144, 2, "R", 120),
    _r("present_temperature", 146, 1, "R", 35),
)

# MX-28 (Protocol 1.0): ROBOTIS e-manual, "MX-28 Control Table".
TABLE_V1: tuple[Register, ...] = (
    _r("model_number", 0, 2, "R", MODEL_NUMBER_V1),
    _r("firmware_version", 2, 1, "R", FIRMWARE_VERSION),
    _r("id", 3, 1, "RW", 1),
    _r("baud_rate", 4, 1, "RW", 34),
    _r("return_delay_time", 5, 1, "RW", 250),
    _r("cw_angle_limit", 6, 2, "RW", 0),
    _r("ccw_angle_limit", 8, 2, "RW", 4095),
    _r("temperature_limit", 11, 1, "RW", 80),
    _r("min_voltage_limit", 12, 1, "RW", 60),
    _r("max_voltage_limit", 13, 1, "RW", 160),
    _r("max_torque", 14, 2, "RW", TORQUE_MAX_V1),
    _r("status_return_level", 16, 1, "RW", 2),
    _r("alarm_led", 17, 1, "RW", 36),
    _r("shutdown", 18, 1, "RW", 36),
    _r("multi_turn_offset", 20, 2, "RW", 0, signed=True),
    _r("resolution_divider", 22, 1, "RW", 1),
    _r("torque_enable", 24, 1, "RW"),
    _r("led", 25, 1, "RW"),
    _r("d_gain", 26, 1, "RW", 0),
    _r("i_gain", 27, 1, "RW", 0),
    _r("p_gain", 28, 1, "RW", 32),
    _r("goal_position", 30, 2, "RW"),
    _r("moving_speed", 32, 2, "RW"),
    _r("torque_limit", 34, 2, "RW", TORQUE_MAX_V1),
    _r("present_position", 36, 2, "R"),
    _r("present_speed", 38, 2, "R"),
    _r("present_load", 40, 2, "R"),
    _r("present_voltage", 42, 1, "R", 120),
    _r("present_temperature", 43, 1, "R", 35),
    _r("registered", 44, 1, "R"),
    _r("moving", 46, 1, "R"),
    _r("lock", 47, 1, "RW"),
    _r("punch", 48, 2, "RW"),
    _r("realtime_tick", 50, 2, "R"),
    _r("goal_acceleration", 73, 1, "RW"),
)


class ControlTable:
    """A byte-addressed control table with named, typed registers (little endian)."""

    def __init__(self, registers: tuple[Register, ...], size: int) -> None:
        self.registers = {r.name: r for r in registers}
        self.size = size
        self.data = bytearray(size)
        self._owner: list[Register | None] = [None] * size
        for r in registers:
            for a in range(r.address, r.address + r.size):
                self._owner[a] = r
        self.reset(eeprom_too=True)

    def reset(self, eeprom_too: bool) -> None:
        """Load the initial values of the RAM area (and of the EEPROM area with ``eeprom_too``)."""
        for r in self.registers.values():
            if eeprom_too or not r.eeprom:
                self.set(r.name, r.initial)

    def get(self, name: str) -> int:
        r = self.registers[name]
        return int.from_bytes(self.data[r.address : r.address + r.size], "little", signed=r.signed)

    def set(self, name: str, value: int) -> None:
        r = self.registers[name]
        lo, hi = (-(1 << (8 * r.size - 1)), (1 << (8 * r.size - 1)) - 1) if r.signed else (0, (1 << (8 * r.size)) - 1)
        value = max(lo, min(hi, int(value)))
        self.data[r.address : r.address + r.size] = value.to_bytes(r.size, "little", signed=r.signed)

    def owners(self, address: int, length: int) -> list[Register | None]:
        """The register owning each byte of ``[address, address+length)``; None for reserved bytes."""
        return self._owner[address : address + length]

    def touched(self, address: int, length: int) -> list[Register]:
        """Registers overlapping a byte range, each once, in address order."""
        seen: dict[str, Register] = {}
        for r in self.owners(address, length):
            if r is not None:
                seen.setdefault(r.name, r)
        return list(seen.values())


# --------------------------------------------------------------------------------------------------
# The gripper model
# --------------------------------------------------------------------------------------------------
@dataclass
class JawParams:
    """Parameters of the emulated gripper behind the servo (positions in encoder ticks, 4096/rev)."""

    contact_position: float | None = 2048.0  # jaw meets the object here; None = nothing in the jaw
    closing_sign: int = 1  # +1: increasing ticks close the jaw
    stiffness_n_per_tick: float = 0.1  # grip force per tick of servo set-point past contact
    max_force_n: float = 40.0  # grip force at 100 % PWM / torque limit
    servo_tau_s: float = 0.03  # position set-point lag
    force_tau_s: float = 1.0 / 62.0  # grip force lag behind its target
    refresh_hz: float | None = 62.0  # commands take effect on these ticks (None = immediately)
    max_speed_ticks_s: float = 55.0 / 60.0 * 4096.0  # no-load speed at 12 V
    initial_position: float = 1024.0
    overload_after_s: float | None = None  # force held at its limit this long -> overload (None = never)
    step_s: float = 0.001  # integration step

    def __post_init__(self) -> None:
        if self.closing_sign not in (1, -1):
            raise ValueError(f"JawParams.closing_sign must be +1 or -1, got {self.closing_sign!r}")
        positive = ("stiffness_n_per_tick", "max_force_n", "servo_tau_s", "force_tau_s", "max_speed_ticks_s", "step_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"JawParams.{name} must be > 0, got {getattr(self, name)!r}")
        if self.refresh_hz is not None and not self.refresh_hz > 0:
            raise ValueError(f"JawParams.refresh_hz must be > 0 or None, got {self.refresh_hz!r}")


class JawModel:
    """Servo set-point, jaw position and grip force over (model) time; not thread-safe on its own."""

    def __init__(self, params: JawParams, t0: float) -> None:
        self.p = params
        self.t0 = self.t = t0
        self.setpoint = self.position = float(params.initial_position)
        self.velocity = 0.0  # ticks/s of the reported jaw position
        self.force = 0.0
        self.goal = float(params.initial_position)
        self.effort = 1.0  # fraction of full PWM / torque
        self.torque_on = False
        self.saturated_for = 0.0
        self.overloaded = False
        self._pending: deque[tuple[float, dict[str, float | bool]]] = deque()

    # Commands -------------------------------------------------------------------------------------
    def command(self, t: float, **changes: float | bool) -> float:
        """Schedule ``goal`` / ``effort`` / ``torque_on`` changes; returns the time they take effect."""
        t_apply = t
        hz = self.p.refresh_hz
        if hz:
            t_apply = self.t0 + math.ceil((t - self.t0) * hz - 1e-9) / hz
        self.advance(t)
        self._pending.append((max(t_apply, self.t), changes))
        return t_apply

    def _apply(self, changes: dict[str, float | bool]) -> None:
        if "torque_on" in changes:
            on = bool(changes["torque_on"])
            if on and not self.torque_on:
                self.setpoint = self.position  # a servo holds where it is when torque comes on
            self.torque_on = on
        if "goal" in changes:
            self.goal = float(changes["goal"])
        if "effort" in changes:
            self.effort = min(1.0, max(0.0, float(changes["effort"])))

    # Physics --------------------------------------------------------------------------------------
    def force_limit(self) -> float:
        return self.p.max_force_n * self.effort if self.torque_on else 0.0

    def _penetration(self, setpoint: float) -> float:
        c = self.p.contact_position
        return 0.0 if c is None else max(0.0, (setpoint - c) * self.p.closing_sign)

    def _force_target(self) -> tuple[float, bool]:
        if not self.torque_on:
            return 0.0, False
        want = self.p.stiffness_n_per_tick * self._penetration(self.setpoint)
        lim = self.force_limit()
        return min(want, lim), want > lim and lim > 0.0

    def _jaw_position(self) -> float:
        c = self.p.contact_position
        if c is None or self._penetration(self.setpoint) == 0.0:
            return self.setpoint
        # In contact the jaw stands at the object, compressed by the force it actually exerts.
        return c + self.p.closing_sign * self.force / self.p.stiffness_n_per_tick

    def _step(self, h: float) -> None:
        p = self.p
        if self.torque_on:
            a = 1.0 - math.exp(-h / p.servo_tau_s)
            vmax = p.max_speed_ticks_s * h
            self.setpoint += max(-vmax, min(vmax, (self.goal - self.setpoint) * a))
        else:
            # Limp: the object pushes the jaw back to the contact; the set-point follows the jaw.
            self.setpoint = self._jaw_position()
        target, saturated = self._force_target()
        self.force += (target - self.force) * (1.0 - math.exp(-h / p.force_tau_s))
        new_pos = self._jaw_position()
        self.velocity = (new_pos - self.position) / h
        self.position = new_pos
        if saturated and p.overload_after_s is not None:
            self.saturated_for += h
            if self.saturated_for >= p.overload_after_s:
                self.overloaded = True
        else:
            self.saturated_for = 0.0

    def advance(self, t: float) -> None:
        """Integrate up to time ``t`` (no-op for times in the past), applying due commands in order."""
        if t - self.t > 5.0 and not self._pending:
            self.t = t - 1.0  # long idle: the lags have long settled; integrate only the last second
        while self.t < t or (self._pending and self._pending[0][0] <= self.t):
            if self._pending and self._pending[0][0] <= self.t:
                self._apply(self._pending.popleft()[1])
                continue
            stop = t if not self._pending else min(t, self._pending[0][0])
            h = min(self.p.step_s, stop - self.t)
            if h <= 0:
                break
            self._step(h)
            self.t += h


# --------------------------------------------------------------------------------------------------
# The emulated device
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WriteRecord:
    """A write the emulator accepted: when (``time.monotonic()``), where, and the registers it set."""

    t: float
    instruction: str  # "write" or "sync_write"
    address: int
    data: bytes
    values: dict[str, int] = field(default_factory=dict)


def _mono() -> float:
    return time.monotonic()


class EmulatedMX28:
    """An MX-28 on a pty: open :attr:`port` with dynamixel-sdk (or any serial client).

    Thread-safe: the pty thread and callers of the public methods share one lock.
    """

    def __init__(
        self,
        protocol: float = 2.0,
        dxl_id: int = 1,
        *,
        jaw: JawParams | None = None,
        clock: Callable[[], float] = _mono,
        reply_delay_s: float = 0.0,
        boot_s: float = 0.1,
        start: bool = True,
    ) -> None:
        if protocol not in (1.0, 2.0):
            raise ValueError(f"EmulatedMX28: protocol must be 1.0 or 2.0, got {protocol!r}")
        if not 0 <= dxl_id <= 252:
            raise ValueError(f"EmulatedMX28: dxl_id must be 0..252, got {dxl_id!r}")
        self.protocol = float(protocol)
        self._v2 = self.protocol == 2.0
        self.clock = clock
        self.reply_delay_s = reply_delay_s
        self.boot_s = boot_s
        self.on_write: Callable[[WriteRecord], None] | None = None
        self._lock = threading.RLock()
        self.table = ControlTable(TABLE_V2 if self._v2 else TABLE_V1, 256)
        self.table.set("id", dxl_id)
        self.jaw = JawModel(jaw or JawParams(), clock())
        self._sync_goal_to_jaw()
        self._writes: list[WriteRecord] = []
        self._absent = False
        self._mute_until = 0.0
        self._hw_error = 0
        self.packets_received = 0
        self.replies_sent = 0
        self.bad_packets = 0
        self._buf = bytearray()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if start:
            self.start()

    # Lifecycle ------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the thread that answers on the pty."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"mx28-emu-{self.port}", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the thread and close the pty."""
        self._stop.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> EmulatedMX28:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # Observation (rig, benchmarks, tests) ---------------------------------------------------------
    @property
    def dxl_id(self) -> int:
        with self._lock:
            return self.table.get("id")

    @property
    def grip_force_n(self) -> float:
        """Grip force the jaw exerts on the object now (N)."""
        with self._lock:
            self._advance()
            return self.jaw.force

    @property
    def jaw_position(self) -> float:
        """Jaw position now (encoder ticks)."""
        with self._lock:
            self._advance()
            return self.jaw.position

    def register(self, name: str) -> int:
        """Current value of a named control-table register (present values brought up to date)."""
        with self._lock:
            self._refresh_present()
            if name not in self.table.registers:
                raise KeyError(f"EmulatedMX28: no register {name!r} in the protocol {self.protocol} table")
            return self.table.get(name)

    def writes(self) -> list[WriteRecord]:
        """A copy of the history of accepted writes, oldest first."""
        with self._lock:
            return list(self._writes)

    def clear_writes(self) -> None:
        with self._lock:
            self._writes.clear()

    def set_contact(self, position: float | None) -> None:
        """Place an object whose surface the jaw meets at ``position`` ticks (None: remove it)."""
        with self._lock:
            self._advance()
            self.jaw.p.contact_position = position

    # Fault injection ------------------------------------------------------------------------------
    @property
    def absent(self) -> bool:
        return self._absent

    @absent.setter
    def absent(self, value: bool) -> None:
        """True: the servo is unplugged; nothing is answered."""
        self._absent = bool(value)

    def mute_for(self, seconds: float) -> None:
        """Answer nothing (and ignore all packets) for ``seconds`` from now."""
        with self._lock:
            self._mute_until = time.monotonic() + seconds

    def inject_overload(self) -> None:
        """Raise an overload error as the servo's own protection would."""
        with self._lock:
            self._advance()
            self._set_overload()

    def reboot(self) -> None:
        """Power-cycle: RAM back to defaults, errors cleared, deaf for ``boot_s``."""
        with self._lock:
            self._advance()
            self._hw_error = 0
            self.jaw.overloaded = False
            self.jaw.saturated_for = 0.0
            self.table.reset(eeprom_too=False)
            self._sync_goal_to_jaw()
            self.jaw.command(self.clock(), torque_on=False, goal=self.jaw.position, effort=self._effort())
            self._mute_until = time.monotonic() + self.boot_s

    # Internals: model <-> table -------------------------------------------------------------------
    def _sync_goal_to_jaw(self) -> None:
        self.table.set("goal_position", round(self.jaw.position))

    def _effort(self) -> float:
        t = self.table
        if self._v2:
            return max(0, min(abs(t.get("goal_pwm")), t.get("pwm_limit"))) / PWM_MAX
        return min(t.get("torque_limit"), t.get("max_torque")) / TORQUE_MAX_V1

    def _advance(self) -> None:
        self.jaw.advance(self.clock())
        if self.jaw.overloaded and not self._hw_error & HW_OVERLOAD:
            self._set_overload()

    def _set_overload(self) -> None:
        self._hw_error |= HW_OVERLOAD
        self.jaw.overloaded = True
        if self._v2:
            self.table.set("hardware_error_status", self._hw_error)
            if self.table.get("shutdown") & HW_OVERLOAD:
                self.table.set("torque_enable", 0)
                self.jaw.command(self.clock(), torque_on=False)
        elif self.table.get("shutdown") & ERR1_OVERLOAD:
            # Protocol 1.0 MX: the alarm shutdown zeroes Torque Limit; writing it again recovers.
            self.table.set("torque_limit", 0)
            self.jaw.command(self.clock(), effort=0.0)

    def _refresh_present(self) -> None:
        self._advance()
        j, t, sign = self.jaw, self.table, self.jaw.p.closing_sign
        load_frac = sign * j.force / j.p.max_force_n  # + = torque towards increasing ticks (CCW)
        moving = abs(j.velocity) > 10 * 0.229 * 4096 / 60 or (j.torque_on and abs(j.goal - j.setpoint) > 2)
        tick = int((time.monotonic() * 1000) % 32768)
        if self._v2:
            t.set("present_position", round(j.position))
            t.set("present_velocity", round(j.velocity * 60 / 4096 / 0.229))
            t.set("present_load", round(1000 * max(-1.0, min(1.0, load_frac))))
            t.set("present_pwm", round(PWM_MAX * max(-1.0, min(1.0, load_frac))))
            t.set("position_trajectory", round(j.setpoint))
            t.set("moving", int(moving))
            t.set("realtime_tick", tick)
            t.set("hardware_error_status", self._hw_error)
        else:
            t.set("present_position", max(0, min(4095, round(j.position))))
            rpm = j.velocity * 60 / 4096 / 0.114
            t.set("present_speed", min(1023, round(abs(rpm))) | (1024 if rpm < 0 else 0))
            # 1.0 load: magnitude in about 0.1 % of max torque, bit 10 set for CW (decreasing ticks).
            t.set("present_load", min(1023, round(1000 * abs(load_frac))) | (1024 if load_frac < 0 else 0))
            t.set("moving", int(moving))
            t.set("realtime_tick", tick)

    def _status_error(self) -> int:
        if self._v2:
            return ERR2_ALERT if self._hw_error else 0
        return ERR1_OVERLOAD if self._hw_error & HW_OVERLOAD else 0

    # Internals: instructions ----------------------------------------------------------------------
    def _handle(self, pkt: Packet) -> bytes | None:
        """Execute one packet; returns the status packet to send (None: no reply)."""
        my_id = self.table.get("id")
        if pkt.dxl_id not in (my_id, BROADCAST_ID):
            return None
        self.packets_received += 1
        v2 = self._v2
        if not pkt.valid:
            self.bad_packets += 1
            if pkt.dxl_id == BROADCAST_ID:
                return None
            return self._status(ERR2_CRC if v2 else ERR1_CHECKSUM)
        broadcast = pkt.dxl_id == BROADCAST_ID
        inst, prm = pkt.instruction, pkt.params
        if inst == INST_SYNC_WRITE:
            self._sync_write(prm)
            return None
        if inst == INST_PING:
            if v2:
                m = self.table.get("model_number")
                return self._status(0, bytes([m & 0xFF, m >> 8, self.table.get("firmware_version")]))
            return None if broadcast else self._status(0)
        if broadcast:
            if inst == INST_WRITE:
                self._write(prm)
            return None
        if inst == INST_READ:
            return self._read(prm)
        if inst == INST_WRITE:
            return self._status(self._write(prm))
        if inst == INST_REBOOT and v2:
            reply = self._status(0)
            self.reboot()
            return reply
        return self._status(ERR2_INSTRUCTION if v2 else ERR1_INSTRUCTION)

    def _status(self, error: int, params: bytes = b"") -> bytes:
        my_id = self.table.get("id")
        if self._v2:
            err = error if error & 0x7F else 0
            return encode_v2(my_id, INST_STATUS, params, error=err | self._status_error())
        return encode_v1(my_id, error | self._status_error(), params)

    def _read(self, prm: bytes) -> bytes:
        v2 = self._v2
        if len(prm) != (4 if v2 else 2):
            return self._status(ERR2_DATA_LENGTH if v2 else ERR1_RANGE)
        addr, length = (prm[0] | prm[1] << 8, prm[2] | prm[3] << 8) if v2 else (prm[0], prm[1])
        if addr + length > self.table.size or length == 0:
            return self._status(ERR2_ACCESS if v2 else ERR1_RANGE)
        self._refresh_present()
        return self._status(0, bytes(self.table.data[addr : addr + length]))

    def _write(self, prm: bytes, instruction: str = "write") -> int:
        """Apply a write (params = address + data); returns the status error (0 = accepted)."""
        v2 = self._v2
        if len(prm) < (3 if v2 else 2):
            return ERR2_DATA_LENGTH if v2 else ERR1_RANGE
        addr, data = (prm[0] | prm[1] << 8, prm[2:]) if v2 else (prm[0], prm[1:])
        return self._write_at(addr, bytes(data), instruction)

    def _write_at(self, addr: int, data: bytes, instruction: str) -> int:
        v2, t = self._v2, self.table
        access_err = ERR2_ACCESS if v2 else ERR1_RANGE
        if addr + len(data) > t.size:
            return access_err
        owners = t.owners(addr, len(data))
        regs = t.touched(addr, len(data))
        # Every byte must belong to a writable register, and registers must be written whole.
        if any(r is None or not r.writable for r in owners) or any(
            r.address < addr or r.address + r.size > addr + len(data) for r in regs
        ):
            return access_err
        if v2 and t.get("torque_enable") and any(r.eeprom for r in regs):
            return ERR2_ACCESS  # EEPROM area is locked while torque is on
        values = {
            r.name: int.from_bytes(data[r.address - addr : r.address - addr + r.size], "little", signed=r.signed)
            for r in regs
        }
        err = self._check_limits(values)
        if err:
            return err
        self._advance()
        now_mono = time.monotonic()
        for name, value in values.items():
            t.set(name, value)
        self._apply_to_model(values)
        rec = WriteRecord(now_mono, instruction, addr, data, values)
        self._writes.append(rec)
        if self.on_write is not None:
            try:
                self.on_write(rec)
            except Exception:  # a broken observer must not take the servo down
                log.exception("EmulatedMX28.on_write callback failed")
        return 0

    def _check_limits(self, values: dict[str, int]) -> int:
        t = self.table
        if self._v2:
            if "goal_pwm" in values and abs(values["goal_pwm"]) > t.get("pwm_limit"):
                return ERR2_DATA_LIMIT
            if "goal_position" in values and t.get("operating_mode") == 3 and not (
                t.get("min_position_limit") <= values["goal_position"] <= t.get("max_position_limit")
            ):
                return ERR2_DATA_LIMIT
            if "torque_enable" in values and values["torque_enable"] not in (0, 1):
                return ERR2_DATA_RANGE
            return 0
        for name, hi in (("torque_limit", 1023), ("max_torque", 1023), ("goal_position", 4095), ("moving_speed", 2047)):
            if name in values and not 0 <= values[name] <= hi:
                return ERR1_RANGE
        if "torque_enable" in values and values["torque_enable"] not in (0, 1):
            return ERR1_RANGE
        return 0

    def _apply_to_model(self, values: dict[str, int]) -> None:
        t, now = self.table, self.clock()
        changes: dict[str, float | bool] = {}
        if "torque_enable" in values:
            on = bool(values["torque_enable"])
            if on and self._v2 and self._hw_error:
                # 2.0: torque cannot come back on until the error is cleared by a reboot.
                t.set("torque_enable", 0)
                on = False
            changes["torque_on"] = on
        if self._v2:
            if "goal_position" in values or "operating_mode" in values:
                changes["goal"] = float(t.get("goal_position"))
            if "goal_pwm" in values or "pwm_limit" in values:
                changes["effort"] = self._effort()
        else:
            if "torque_limit" in values and values["torque_limit"] > 0 and self._hw_error & HW_OVERLOAD:
                self._hw_error &= ~HW_OVERLOAD  # 1.0: re-writing Torque Limit recovers from the shutdown
                self.jaw.overloaded = False
                self.jaw.saturated_for = 0.0
            if "goal_position" in values:
                changes["goal"] = float(t.get("goal_position"))
            if "torque_limit" in values or "max_torque" in values:
                changes["effort"] = self._effort()
        if changes:
            self.jaw.command(now, **changes)

    def _sync_write(self, prm: bytes) -> None:
        v2 = self._v2
        head = 4 if v2 else 2
        if len(prm) < head:
            return
        addr, length = (prm[0] | prm[1] << 8, prm[2] | prm[3] << 8) if v2 else (prm[0], prm[1])
        my_id = self.table.get("id")
        body = prm[head:]
        for i in range(0, len(body) - length, length + 1):
            if body[i] == my_id:
                self._write_at(addr, bytes(body[i + 1 : i + 1 + length]), "sync_write")

    # Internals: the pty thread --------------------------------------------------------------------
    def _run(self) -> None:
        parse = parse_v2 if self._v2 else parse_v1
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master, self._wake_r], [], [], 0.5)
            except (OSError, ValueError):
                return
            if self._master not in ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:  # no client has the slave open: wait for one
                    time.sleep(0.01)
                    continue
                return
            if self._absent or time.monotonic() < self._mute_until:
                self._buf.clear()  # a deaf servo does not even buffer what it missed
                continue
            self._buf += chunk
            while True:
                pkt = parse(self._buf)
                if pkt is None:
                    break
                with self._lock:
                    reply = self._handle(pkt)
                if reply is not None:
                    self._send(reply)

    def _send(self, reply: bytes) -> None:
        if self.reply_delay_s > 0:
            time.sleep(self.reply_delay_s)
        try:
            os.write(self._master, reply)
            self.replies_sent += 1
        except (BlockingIOError, OSError):
            log.debug("EmulatedMX28: reply dropped, pty buffer full or closed")
