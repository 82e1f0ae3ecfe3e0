"""An emulated Dynamixel MX-28 gripper servo on a pseudo-terminal.

The emulator is the independent peer that the real ``dynamixel-sdk`` talks to in tests and in the
simulated rig, so it implements the wire protocol itself (it must not import ``dynamixel_sdk``). Its
parts, each in its own module:

* ``slipd.sim.devices.dynamixel_protocol``: the wire codec (Protocol 1.0 and 2.0 packets, CRC-16,
  checksum, byte stuffing, instruction and error numbers);
* ``slipd.sim.devices.mx28_control_table``: the MX-28's control tables and the register memory;
* ``slipd.sim.devices.jaw_model``: the gripper behind the servo (jaw position, grip force);
* this module: the device itself, answering on a pty (``EmulatedMX28``).

Every public name of those modules is importable from here too, as before the split.

Instructions: ping, read, write, sync write, reboot (2.0 only).

Fault injection: an absent device (no reply at all), a talking-to-another-ID bus (the servo only
answers its own ID), overload (Hardware Error Status bit 5 and the alert bit; torque off as the
default Shutdown setting does), torque-off (goals are stored but ignored), not answering for N ms,
and reboot.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from slipd.sim.devices.dynamixel_protocol import (
    BROADCAST_ID,
    ERR1_ANGLE,
    ERR1_CHECKSUM,
    ERR1_INSTRUCTION,
    ERR1_OVERHEAT,
    ERR1_OVERLOAD,
    ERR1_RANGE,
    ERR1_VOLTAGE,
    ERR2_ACCESS,
    ERR2_ALERT,
    ERR2_CRC,
    ERR2_DATA_LENGTH,
    ERR2_DATA_LIMIT,
    ERR2_DATA_RANGE,
    ERR2_INSTRUCTION,
    ERR2_RESULT_FAIL,
    INST_PING,
    INST_READ,
    INST_REBOOT,
    INST_STATUS,
    INST_SYNC_WRITE,
    INST_WRITE,
    Packet,
    checksum_v1,
    crc16_dxl,
    encode_v1,
    encode_v2,
    parse_v1,
    parse_v2,
    stuff,
    unstuff,
)
from slipd.sim.devices.jaw_model import (
    JawModel,
    JawParams,
)
from slipd.sim.devices.mx28_control_table import (
    FIRMWARE_VERSION,
    HW_ELECTRICAL_SHOCK,
    HW_ENCODER,
    HW_INPUT_VOLTAGE,
    HW_OVERHEATING,
    HW_OVERLOAD,
    MODEL_NUMBER_V1,
    MODEL_NUMBER_V2,
    PWM_MAX,
    TABLE_V1,
    TABLE_V2,
    TORQUE_MAX_V1,
    ControlTable,
    Register,
)

# The parts' public names stay importable from here (``from slipd.sim.devices.mx28 import JawParams``).
__all__ = [
    "BROADCAST_ID",
    "ERR1_ANGLE",
    "ERR1_CHECKSUM",
    "ERR1_INSTRUCTION",
    "ERR1_OVERHEAT",
    "ERR1_OVERLOAD",
    "ERR1_RANGE",
    "ERR1_VOLTAGE",
    "ERR2_ACCESS",
    "ERR2_ALERT",
    "ERR2_CRC",
    "ERR2_DATA_LENGTH",
    "ERR2_DATA_LIMIT",
    "ERR2_DATA_RANGE",
    "ERR2_INSTRUCTION",
    "ERR2_RESULT_FAIL",
    "FIRMWARE_VERSION",
    "HW_ELECTRICAL_SHOCK",
    "HW_ENCODER",
    "HW_INPUT_VOLTAGE",
    "HW_OVERHEATING",
    "HW_OVERLOAD",
    "INST_PING",
    "INST_READ",
    "INST_REBOOT",
    "INST_STATUS",
    "INST_SYNC_WRITE",
    "INST_WRITE",
    "MODEL_NUMBER_V1",
    "MODEL_NUMBER_V2",
    "PWM_MAX",
    "TABLE_V1",
    "TABLE_V2",
    "TORQUE_MAX_V1",
    "ControlTable",
    "EmulatedMX28",
    "JawModel",
    "JawParams",
    "Packet",
    "Register",
    "WriteRecord",
    "checksum_v1",
    "crc16_dxl",
    "encode_v1",
    "encode_v2",
    "parse_v1",
    "parse_v2",
    "stuff",
    "unstuff",
]

log = logging.getLogger(__name__)

MAX_WRITES = 1024
"""Accepted writes the emulator keeps (the oldest are dropped): tests and the rig read the latest few, and a soak of
hours must measure the daemon's memory, not this log's."""


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
        self._writes: deque[WriteRecord] = deque(maxlen=MAX_WRITES)
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
        """A copy of the latest ``MAX_WRITES`` accepted writes, oldest first."""
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
