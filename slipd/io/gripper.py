"""The gripper: a small interface and its Dynamixel MX-28 implementation (dynamixel-sdk).

The gripper holds an object at a *hold* setting and, on a slip alarm, tightens to a *secure* setting
(or to a level in between). Under Protocol 2.0 the setting is Goal PWM (force limit) + Goal Position;
under 1.0 it is Torque Limit + Goal Position. The jaw's force grows with how far the goal lies past
the object's surface, capped by the PWM / torque limit, so both are raised together.

Every call blocks (the vendor library polls the serial port). The control loop runs them on the
gripper's own :class:`slipd.daemon.worker.DeviceWorker` thread; a lock makes each call atomic anyway, so a
status read from another thread can never interleave with a tighten on the bus.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import math
import os
import select
import termios
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import serial
from dynamixel_sdk import (
    COMM_NOT_AVAILABLE,
    COMM_PORT_BUSY,
    COMM_RX_CORRUPT,
    COMM_RX_FAIL,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    COMM_TX_ERROR,
    COMM_TX_FAIL,
    PacketHandler,
    PortHandler,
)

from slipd.config import DYNAMIXEL_BAUDRATES, GripperConfig

if TYPE_CHECKING:
    from slipd.metrics import Metrics

log = logging.getLogger(__name__)

# Control-table addresses (ROBOTIS e-manual, MX-28(2.0) and MX-28 Protocol 1.0).
V2_OPERATING_MODE = 11
V2_TORQUE_ENABLE = 64
V2_HARDWARE_ERROR = 70
V2_GOAL_PWM = 100
V2_PWM_LIMIT = 36  # EEPROM: PWM Limit (2), ..., Max Position Limit (48, 4), Min Position Limit (52, 4)
V2_MAX_POSITION = 48
V2_MIN_POSITION = 52
V2_LIMITS_END = 56
V1_CW_ANGLE_LIMIT = 6  # EEPROM: CW Angle Limit (6, 2), CCW Angle Limit (8, 2)
V2_PROFILE_ACCELERATION = 108
V2_PROFILE_VELOCITY = 112
V2_GOAL_POSITION = 116
V2_STATUS_BLOCK = (64, 146 - 64 + 1)  # torque enable .. present temperature, one read
V1_TORQUE_ENABLE = 24
V1_GOAL_BLOCK = 30  # goal position(30) + moving speed(32) + torque limit(34): one 6-byte write
V1_STATUS_BLOCK = (24, 46 - 24 + 1)  # torque enable .. moving
POSITION_MODE = 3
PWM_MAX = 885
GRIP_FOUND_LOAD_PCT = 5.0
"""A servo found at start-up loaded this much (% of its maximum torque) in the closing direction presses on an object
(2 N of the rig's 40 N jaw); an empty jaw at rest reads about 0."""
TORQUE_LIMIT_MAX = 1023
MX28_MODELS = {29: "MX-28 (Protocol 1.0)", 30: "MX-28 (Protocol 2.0)"}

# Hardware error bits; Protocol 1.0 status-packet error bits for the same faults have the same values.
HARDWARE_ERRORS = {
    0x01: "input_voltage",
    0x04: "overheating",
    0x08: "motor_encoder",
    0x10: "electrical_shock",
    0x20: "overload",
}
V1_HARDWARE_BITS = 0x01 | 0x04 | 0x20
V2_ALERT = 0x80

BAUDRATES = DYNAMIXEL_BAUDRATES  # what dynamixel-sdk's PortHandler accepts; one list, in the config schema

_NO_RETRY = (COMM_TX_ERROR, COMM_NOT_AVAILABLE)
_COMM_KIND = {
    COMM_RX_TIMEOUT: "rx_timeout",
    COMM_RX_CORRUPT: "rx_corrupt",
    COMM_RX_FAIL: "rx_fail",
    COMM_TX_FAIL: "tx_fail",
    COMM_TX_ERROR: "tx_error",
    COMM_PORT_BUSY: "port_busy",
    COMM_NOT_AVAILABLE: "not_available",
}


class GripperError(RuntimeError):
    """A gripper command failed: which device, which control-table address, and why."""

    def __init__(
        self,
        device: str,
        reason: str,
        address: int | None = None,
        *,
        kind: str = "error",
        comm_result: int | None = None,
        error_byte: int = 0,
    ) -> None:
        where = f" at address {address}" if address is not None else ""
        super().__init__(f"gripper {device}{where}: {reason}")
        self.device, self.reason, self.address = device, reason, address
        self.kind, self.comm_result, self.error_byte = kind, comm_result, error_byte


@dataclass(frozen=True)
class GripperStatus:
    """One snapshot of the gripper servo."""

    load: float  # percent of the servo's maximum torque; positive = towards closing
    position: int  # present position (ticks)
    goal_position: int
    hardware_error: int  # bit field, see HARDWARE_ERRORS (0 = healthy)
    hardware_errors: tuple[str, ...]
    torque_enabled: bool
    moving: bool
    temperature_c: int
    t_monotonic: float  # when the status was read

    @property
    def healthy(self) -> bool:
        """Torque on and no hardware error."""
        return self.torque_enabled and not self.hardware_error


def decode_hardware_error(bits: int) -> tuple[str, ...]:
    """Names of the hardware error bits set in ``bits``."""
    names = tuple(name for bit, name in HARDWARE_ERRORS.items() if bits & bit)
    unknown = bits & ~sum(HARDWARE_ERRORS)
    return (*names, f"unknown_0x{unknown:02x}") if unknown else names


class Gripper(ABC):
    """What the reaction needs from a gripper. All methods block; call them on a device worker."""

    last_tighten_monotonic: float | None = None  # when the last tighten command left for the device
    level_found: float = 0.0
    """The grip level ``take_over`` found in place and kept (0: the hold setting): the grasp's level so far."""
    gripping_found: bool = False
    """``take_over`` found the jaw pressing on an object (torque on, the goal at or past the hold position, loaded):
    slipd restarted mid-grasp, so the sensor's zero from before must stand
    (``slipd.daemon.loop.Daemon._set_up_sensor``). An empty jaw left at the hold setting by a clean exit is no grip:
    the next start zeroes the sensor as usual."""

    @abstractmethod
    def connect(self) -> None:
        """Open the link, check the device, enable torque (the jaw does not move yet)."""

    @abstractmethod
    def hold(self) -> None:
        """Grip at the hold setting."""

    def take_over(self) -> float:
        """At start-up: grip at the hold setting, unless the device already grips tighter (slipd restarted mid-grasp),
        which stands. Returns the level kept, 0 (hold) .. 1 (secure). Without a way to read the grip: ``hold``."""
        self.hold()
        return 0.0

    @abstractmethod
    def tighten(self, level: float | None = None) -> float:
        """Tighten to ``level`` in 0..1 between hold (0) and secure (1); None = secure.

        Returns the ``time.monotonic()`` at which the command's bytes were written.
        """

    def grip_force(self, newtons: float) -> float:
        """Grip with ``newtons`` (force control); returns the send time. Grippers without it refuse."""
        raise NotImplementedError(f"{type(self).__name__} has no force control")

    def reconnect(self) -> bool:
        """Open the link again after it was lost (an unplugged adapter); True when the device answers. It must not
        move the jaw or switch torque on: a servo that lost its power comes back with torque off, and switching it
        on unasked would be a restart after a stop (the daemon restarts only on a person's request)."""
        return False

    @abstractmethod
    def release(self) -> None:
        """Let go of the object."""

    @abstractmethod
    def read_status(self) -> GripperStatus:
        """Load, position, hardware error and friends."""

    @abstractmethod
    def close(self) -> None:
        """Close the link (idempotent)."""

    def __enter__(self) -> Gripper:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class DynamixelSettings:
    """How to reach and drive the gripper servo (``from_config`` reads ``slipd.config.GripperConfig``).

    ``hold_pwm`` / ``secure_pwm`` are the effort settings: Goal PWM (0..885) under Protocol 2.0,
    Torque Limit (0..1023) under 1.0. Positions are in ticks (4096 per turn); the closing direction is
    the direction from ``hold_position`` to ``secure_position``.
    """

    port: str
    hold_position: int
    secure_position: int
    hold_pwm: int
    secure_pwm: int
    baudrate: int = 57600
    dxl_id: int = 1
    protocol: float = 2.0
    open_position: int | None = None  # release() goes here; None: release() turns torque off
    retries: int = 3  # extra attempts after a missing/corrupt status packet
    packet_timeout_ms: float = 20.0  # wait for a status packet, on top of its transmission time
    profile_velocity: int | None = None  # 2.0 Profile Velocity (0 = fastest); None: leave as is
    profile_acceleration: int | None = None  # 2.0 Profile Acceleration; None: leave as is
    moving_speed: int = 0  # 1.0 Moving Speed (0 = fastest)
    low_latency: bool = True  # ask the USB-serial driver for low-latency mode
    reboot_on_hardware_error: bool = True  # connect(): reboot (2.0) a servo that reports one
    reboot_wait_s: float = 0.5  # how long a rebooted servo needs before it answers
    torque_off_on_close: bool = False  # False keeps the grip when the daemon exits
    max_force_n: float = 40.0  # grip force at full effort (grip_force's calibration)
    force_limit_n: float | None = None
    """The object's force limit (``reaction.grip_max_force_n`` under grip_control): every command's effort is capped
    at the effort that gives this force, the start-up hold, a tighten and a recovery's hold included. The hold
    setting's force follows from its position until the effort binds, so a hold effort above the limit squeezes an
    object that is smaller or sits farther in than expected with more than it may take. None: no cap."""

    def __post_init__(self) -> None:
        def bad(key: str, why: str) -> ValueError:
            return ValueError(f"DynamixelSettings.{key}: {why} (got {getattr(self, key)!r})")

        if self.protocol not in (1.0, 2.0):
            raise bad("protocol", "must be 1.0 or 2.0")
        if not 0 <= self.dxl_id <= 252:
            raise bad("dxl_id", "must be 0..252")
        if self.baudrate not in BAUDRATES:
            raise bad("baudrate", f"must be one of {BAUDRATES}")
        for key in ("hold_position", "secure_position", "open_position"):
            v = getattr(self, key)
            if v is not None and not 0 <= v <= 4095:
                raise bad(key, "must be 0..4095 ticks")
        top = PWM_MAX if self.protocol == 2.0 else TORQUE_LIMIT_MAX
        for key in ("hold_pwm", "secure_pwm"):
            if not 0 <= getattr(self, key) <= top:
                raise bad(key, f"must be 0..{top} under protocol {self.protocol:g}")
        if self.secure_pwm < self.hold_pwm:
            raise bad("secure_pwm", f"must be >= hold_pwm ({self.hold_pwm}): securing never loosens")
        if self.secure_position == self.hold_position:
            raise bad("secure_position", "must differ from hold_position (tightening must move the jaw)")
        if self.open_position is not None and (self.hold_position - self.open_position) * self.closing_sign <= 0:
            raise bad("open_position", "must lie on the open side of hold_position")
        if self.retries < 0:
            raise bad("retries", "must be >= 0")
        if not self.packet_timeout_ms > 0:
            raise bad("packet_timeout_ms", "must be > 0")
        if self.force_limit_n is not None and not 0 < self.force_limit_n <= self.max_force_n:
            raise bad("force_limit_n", f"must be in (0, max_force_n = {self.max_force_n:g}] N")

    @property
    def effort_cap(self) -> int:
        """The largest effort any command may carry: the one that gives ``force_limit_n`` (rounded down, so the
        force stays at or below the limit), else the protocol's full effort."""
        top = PWM_MAX if self.protocol == 2.0 else TORQUE_LIMIT_MAX
        if self.force_limit_n is None:
            return top
        return min(top, math.floor(self.force_limit_n / self.max_force_n * top + 1e-9))

    @classmethod
    def from_config(cls, cfg: GripperConfig, force_limit_n: float | None = None) -> DynamixelSettings:
        """The settings of the config's ``gripper`` section (the other fields keep their defaults); ``force_limit_n``
        as the field says."""
        if cfg.port is None or cfg.hold_position is None or cfg.secure_position is None:
            raise ValueError("gripper.port, hold_position and secure_position: required when the gripper is enabled")
        return cls(port=cfg.port, baudrate=cfg.baudrate, dxl_id=cfg.id, protocol=float(cfg.protocol),
                   hold_position=cfg.hold_position, secure_position=cfg.secure_position,
                   hold_pwm=cfg.hold_effort, secure_pwm=cfg.secure_effort,
                   retries=cfg.retries, packet_timeout_ms=cfg.packet_timeout_ms, max_force_n=cfg.max_force_n,
                   force_limit_n=force_limit_n)

    @property
    def closing_sign(self) -> int:
        """+1 when closing increases the position, -1 when it decreases it."""
        return 1 if self.secure_position > self.hold_position else -1

    @property
    def device(self) -> str:
        return f"MX-28 id {self.dxl_id} on {self.port} (protocol {self.protocol:g})"


class _TimedPortHandler(PortHandler):  # type: ignore[misc]  # the vendor SDK is untyped
    """dynamixel-sdk's PortHandler with our packet timeout and a stamp of the last write."""

    def __init__(self, port_name: str, packet_timeout_ms: float) -> None:
        super().__init__(port_name)
        self.packet_timeout_ms = packet_timeout_ms
        self.last_write_monotonic = 0.0

    def setPacketTimeout(self, packet_length: int) -> None:  # vendor API name
        # The SDK adds 2 x a hard-coded 16 ms FTDI latency timer; ours comes from the settings.
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.packet_timeout_ms

    def writePort(self, packet: Any) -> int:  # vendor API name
        self.last_write_monotonic = time.monotonic()
        return int(self.ser.write(bytes(packet)))

    def readPort(self, length: int) -> bytes:  # vendor API name
        # The SDK polls a non-blocking port in a tight loop while it waits for a status packet: that burns a
        # core and holds the GIL against the control loop. Wait in select() (GIL released) for the next bytes
        # instead, in short slices so the SDK's own timeout check still runs on time.
        data: bytes = self.ser.read(length)
        if data:
            return data
        left_s = (self.packet_timeout - self.getTimeSinceStart()) / 1000.0
        if left_s > 0:
            select.select([self.ser.fileno()], [], [], min(left_s, 0.002))
            data = self.ser.read(length)
        return data


def _usb_latency_timer_ms(port: str) -> int | None:
    """The FTDI latency timer of a /dev/ttyUSB* port (ms), or None where there is none to read."""
    name = os.path.basename(os.path.realpath(port))
    path = f"/sys/bus/usb-serial/devices/{name}/latency_timer"
    try:
        with open(path) as fh:
            return int(fh.read().strip())
    except (OSError, ValueError):
        return None


class DynamixelGripper(Gripper):
    """An MX-28 gripper servo over dynamixel-sdk, Protocol 2.0 or 1.0."""

    def __init__(self, settings: DynamixelSettings | GripperConfig, metrics: Metrics | None = None) -> None:
        if not isinstance(settings, DynamixelSettings):
            settings = DynamixelSettings.from_config(settings)
        self.settings = settings
        self.metrics = metrics
        self.model_number: int | None = None
        self.last_tighten_monotonic: float | None = None
        self._lock = threading.RLock()
        self._port: _TimedPortHandler | None = None
        self._packet: Any = PacketHandler(settings.protocol)
        self._v2 = settings.protocol == 2.0
        self._effort_sent: int | None = None  # 2.0: skip rewriting an unchanged Goal PWM
        self._goal_sent: int | None = None  # grip_force: the goal position it set (others clear it)
        self._pwm_limit = PWM_MAX  # 2.0: the servo's own PWM Limit (EEPROM), read at connect; grip_force stays within
        self._found: tuple[int, int] | None = None
        """(goal position, effort) the servo was gripping with when ``connect`` found its torque on in position mode, or
        None (torque off, another mode, rebooted): what ``take_over`` must not loosen."""
        self._torque_off = False
        """The servo said its torque is off (a status read, or the check after a tighten): until ``connect`` or
        ``recover`` switch it on, commands are refused, so a tighten fails (and stays owed) instead of passing for
        done while the jaw applies nothing (a power blip on the servo's supply resets it with torque off)."""

    # Public API ---------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, ping the servo, put it in position mode and enable torque."""
        with self._lock:
            if self._port is None:
                self._open()
            self._effort_sent = None
            self.model_number = self._ping()
            if self.model_number not in MX28_MODELS:
                log.warning("%s: model number %s is not an MX-28 (29/30); carrying on", self.device, self.model_number)
            if self._v2:
                hw = self._read(V2_HARDWARE_ERROR, 1, allow_hw_error=True)[0][0]
                if hw:
                    if not self.settings.reboot_on_hardware_error:
                        raise self._error(
                            f"hardware error {', '.join(decode_hardware_error(hw))}; reboot the servo",
                            V2_HARDWARE_ERROR, kind="hardware_error",
                        )
                    log.warning("%s: hardware error %s at connect: rebooting", self.device, decode_hardware_error(hw))
                    self._reboot()
                self._check_limits_v2()
                self._found = self._grip_found_v2()
                self._setup_v2()
            else:
                self._check_limits_v1()
                self._found = self._grip_found_v1()
                self._write(V1_TORQUE_ENABLE, bytes([1]))
            self._torque_off = False

    def _grip_found_v2(self) -> tuple[int, int] | None:
        """The goal and effort in force when torque is on in position mode (a grip slipd's setup leaves as it is)."""
        if not self._read(V2_TORQUE_ENABLE, 1)[0][0] or self._read(V2_OPERATING_MODE, 1)[0][0] != POSITION_MODE:
            return None
        data = self._read(V2_GOAL_PWM, V2_GOAL_POSITION + 4 - V2_GOAL_PWM)[0]  # Goal PWM .. Goal Position, one read
        goal = int.from_bytes(data[V2_GOAL_POSITION - V2_GOAL_PWM :], "little", signed=True)
        return goal, int.from_bytes(data[:2], "little")

    def _grip_found_v1(self) -> tuple[int, int] | None:
        """1.0: the goal block (Goal Position, Moving Speed, Torque Limit) when torque is on."""
        data = self._read(V1_TORQUE_ENABLE, V1_GOAL_BLOCK + 6 - V1_TORQUE_ENABLE)[0]
        if not data[0]:
            return None
        block = data[V1_GOAL_BLOCK - V1_TORQUE_ENABLE :]
        return int.from_bytes(block[:2], "little"), int.from_bytes(block[4:6], "little")

    def reconnect(self) -> bool:
        """Reopen the port after an I/O error dropped it (an unplugged USB adapter, the same device path back) and
        ping the servo. Nothing is written: torque, goal and effort stay as the servo has them, and the next status
        read says whether it still holds (``Gripper.reconnect``). The effort and goal written before are forgotten,
        so the next command writes both."""
        with self._lock:
            if self._port is not None:
                return True
            try:
                self._open()
                self.model_number = self._ping()
            except GripperError as exc:
                log.debug("%s: reconnect failed: %s", self.device, exc)
                self._drop_port()
                return False
            self._effort_sent = self._goal_sent = None
            log.warning("%s: port reopened, servo answers (model %s)", self.device, self.model_number)
            return True

    def hold(self) -> None:
        """Goal and effort at the hold setting."""
        s = self.settings
        with self._lock:
            self._command(s.hold_position, s.hold_pwm)

    def take_over(self) -> float:
        """At start-up, after ``connect``: the hold setting, unless connect found the jaw gripping an object (torque on,
        the goal at or past the hold position, loaded at least ``GRIP_FOUND_LOAD_PCT`` in the closing direction: slipd
        restarted, by systemd or a person, while it held the object). Then goal (up to the secure position) and effort
        stay as found: setting the hold loosened a grasp that had needed the secure force, and raising a grip control's
        lower effort to the hold setting squeezed the object to its force limit. ``gripping_found`` says so (the
        sensor's zero from before must then stand). An empty jaw gets the hold setting. Returns the level kept, 0
        (hold) .. 1 (secure), for the reaction (a graded tighten never goes below it)."""
        s = self.settings
        with self._lock:
            position, effort, level = s.hold_position, s.hold_pwm, 0.0
            found, self._found = self._found, None
            self.gripping_found = False
            if found is not None:
                goal, got = found
                span = s.secure_position - s.hold_position or 1
                beyond = (goal - s.hold_position) / span  # >= 0: at or past the hold position
                load = self.read_status().load if beyond >= 0.0 else 0.0
                if load >= GRIP_FOUND_LOAD_PCT:  # pressing on an object: its grip stands
                    self.gripping_found = True
                    position = s.hold_position + round(min(1.0, beyond) * span)
                    effort = min(got, max(s.secure_pwm, s.hold_pwm))
                    spread = s.secure_pwm - s.hold_pwm
                    by_effort = (effort - s.hold_pwm) / spread if spread else 0.0
                    level = max(0.0, min(1.0, max(beyond, by_effort)))
                    log.warning("%s: found gripping (goal %d, effort %d, load %.1f %%): kept as it is (slipd "
                                "restarted mid-grasp?), level %.2f", self.device, goal, got, load, level)
            self._command(position, effort)
            self.level_found = level
            return level

    def tighten(self, level: float | None = None) -> float:
        """Tighten to the secure setting, or to ``level`` (0 = hold .. 1 = secure). Returns the send time."""
        s = self.settings
        if level is None:
            level = 1.0
        if not math.isfinite(level):
            raise ValueError(f"tighten(level): level must be finite in 0..1, got {level!r}")
        level = min(1.0, max(0.0, float(level)))
        position = round(s.hold_position + level * (s.secure_position - s.hold_position))
        effort = round(s.hold_pwm + level * (s.secure_pwm - s.hold_pwm))
        with self._lock:
            t_sent = self._command(position, effort)
            self.last_tighten_monotonic = t_sent
            # After the bytes left (the reaction's latency is unchanged): a servo that lost its power took the command
            # and applies nothing. One byte read on the worker thread makes that tighten a failure, owed, not done.
            if not self._read(V2_TORQUE_ENABLE if self._v2 else V1_TORQUE_ENABLE, 1, allow_hw_error=True)[0][0]:
                self._torque_off = True
                raise self._error("tighten sent, but the servo's torque is off (power lost?): it grips nothing",
                                  kind="torque_off")
            return t_sent

    def grip_force(self, newtons: float) -> float:
        """Grip with ``newtons`` (force control for ``reaction.policy: grip_control``); returns the send time.

        The goal position is the secure setting, well past the object, so the jaw presses until the effort
        limit (Goal PWM under 2.0, Torque Limit under 1.0) balances it: the force is the effort's share of
        ``max_force_n`` (the jaw stalls on the object, where force follows motor current). Only a changed
        effort is written after the first command: one packet per update.
        """
        s = self.settings
        if not math.isfinite(newtons):
            raise ValueError(f"grip_force: newtons must be finite, got {newtons!r}")
        top = PWM_MAX if self._v2 else TORQUE_LIMIT_MAX
        cap = min(s.effort_cap, self._pwm_limit) if self._v2 else s.effort_cap
        effort = min(cap, max(0, round(float(newtons) / s.max_force_n * top)))
        with self._lock:
            port = self._require_port()
            if not self._v2:
                return self._command(s.secure_position, effort)
            self._refuse_torque_off()
            if effort != self._effort_sent:
                self._write(V2_GOAL_PWM, effort.to_bytes(2, "little"))
                self._effort_sent = effort
            if self._goal_sent != s.secure_position:
                self._write(V2_GOAL_POSITION, s.secure_position.to_bytes(4, "little", signed=True))
                self._goal_sent = s.secure_position
            return float(port.last_write_monotonic)

    def release(self) -> None:
        """Open to ``open_position`` at the hold effort (or turn torque off where there is none)."""
        s = self.settings
        with self._lock:
            if s.open_position is None:
                self._write(V2_TORQUE_ENABLE if self._v2 else V1_TORQUE_ENABLE, bytes([0]))
                self._effort_sent = None
            else:
                self._command(s.open_position, s.hold_pwm)

    def read_status(self) -> GripperStatus:
        """Read load, position, torque, moving, temperature and hardware error in one packet."""
        with self._lock:
            if self._v2:
                base, n = V2_STATUS_BLOCK
                data, _err = self._read(base, n, allow_hw_error=True)

                def u(addr: int, size: int, signed: bool = False) -> int:
                    return int.from_bytes(data[addr - base : addr - base + size], "little", signed=signed)

                hw = u(V2_HARDWARE_ERROR, 1)
                load_pct = u(126, 2, signed=True) / 10.0
                self._torque_off = not u(V2_TORQUE_ENABLE, 1) and not hw  # a hardware error answers for itself
                return GripperStatus(
                    load=load_pct * self.settings.closing_sign,
                    position=u(132, 4, signed=True),
                    goal_position=u(V2_GOAL_POSITION, 4, signed=True),
                    hardware_error=hw,
                    hardware_errors=decode_hardware_error(hw),
                    torque_enabled=bool(u(V2_TORQUE_ENABLE, 1)),
                    moving=bool(u(122, 1)),
                    temperature_c=u(146, 1),
                    t_monotonic=time.monotonic(),
                )
            base, n = V1_STATUS_BLOCK
            data, err = self._read(base, n, allow_hw_error=True)

            def w(addr: int) -> int:
                return data[addr - base] | (data[addr - base + 1] << 8)

            raw_load = w(40)
            # Bit 10 marks a CW load, i.e. towards decreasing positions.
            load_pct = (raw_load & 0x3FF) / 10.0 * (-1 if raw_load & 0x400 else 1)
            hw = err & V1_HARDWARE_BITS
            self._torque_off = not data[V1_TORQUE_ENABLE - base] and not hw
            return GripperStatus(
                load=load_pct * self.settings.closing_sign,
                position=w(36),
                goal_position=w(30),
                hardware_error=hw,
                hardware_errors=decode_hardware_error(hw),
                torque_enabled=bool(data[V1_TORQUE_ENABLE - base]),
                moving=bool(data[46 - base]),
                temperature_c=data[43 - base],
                t_monotonic=time.monotonic(),
            )

    def recover(self) -> None:
        """Clear a hardware error and grip again: reboot (2.0) or re-arm the torque limit (1.0), then hold."""
        with self._lock:
            if self._v2:
                self._reboot()
                self._setup_v2()
            else:
                self._write(V1_TORQUE_ENABLE, bytes([1]))
            self._effort_sent = None
            self._torque_off = False
            self.hold()

    def close(self) -> None:
        """Close the port; with ``torque_off_on_close`` switch torque off first (drops the object)."""
        with self._lock:
            if self._port is None:
                return
            if self.settings.torque_off_on_close:
                try:
                    self._write(V2_TORQUE_ENABLE if self._v2 else V1_TORQUE_ENABLE, bytes([0]))
                except GripperError as exc:
                    log.warning("%s: torque off at close failed: %s", self.device, exc)
            self._drop_port()

    def _drop_port(self) -> None:
        """Forget the port (closed quietly): ``reconnect`` opens it again."""
        if self._port is not None:
            with contextlib.suppress(Exception):
                self._port.closePort()
        self._port = None

    @property
    def device(self) -> str:
        return self.settings.device

    # Setup ----------------------------------------------------------------------------------------
    def _open(self) -> None:
        s = self.settings
        port = _TimedPortHandler(s.port, s.packet_timeout_ms)
        try:
            port.baudrate = s.baudrate
            if not port.openPort():
                raise self._error(f"baud rate {s.baudrate} not supported by dynamixel-sdk", kind="open_failed")
        except (serial.SerialException, OSError) as exc:
            raise self._error(f"cannot open the serial port: {exc}", kind="open_failed") from exc
        try:
            # Another process talking on the same bus would corrupt every transaction.
            fcntl.flock(port.ser.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            port.closePort()
            raise self._error("serial port is in use by another process", kind="open_failed") from exc
        if s.low_latency:
            try:
                port.ser.set_low_latency_mode(True)
            except (AttributeError, ValueError, OSError) as exc:  # ptys and some adapters have no such mode
                log.debug("%s: low-latency mode unavailable: %s", self.device, exc)
        timer = _usb_latency_timer_ms(s.port)
        if timer is not None and timer * 2 > s.packet_timeout_ms:
            log.warning(
                "%s: USB latency timer is %d ms; status packets may time out at %.0f ms and every command "
                "waits up to %d ms (echo 1 > /sys/bus/usb-serial/devices/<tty>/latency_timer)",
                self.device, timer, s.packet_timeout_ms, timer,
            )
        self._port = port

    def _positions(self) -> list[tuple[str, int]]:
        s = self.settings
        named = [("hold_position", s.hold_position), ("secure_position", s.secure_position)]
        return named + ([("open_position", s.open_position)] if s.open_position is not None else [])

    def _refuse(self, reason: str, address: int) -> GripperError:
        return self._error(f"{reason}: the servo would refuse it when it matters (at a slip alarm); change the key or "
                           "the servo's EEPROM limit (Dynamixel Wizard)", address, kind="limits")

    def _check_limits_v2(self) -> None:
        """The servo's own EEPROM limits against the settings, at start-up: a goal or effort beyond them is refused
        by the servo (data limit error), and the first command to pass them is the tighten a slip alarm sends."""
        data, _ = self._read(V2_PWM_LIMIT, V2_LIMITS_END - V2_PWM_LIMIT, allow_hw_error=True)
        pwm_limit = int.from_bytes(data[0:2], "little")
        hi = int.from_bytes(data[V2_MAX_POSITION - V2_PWM_LIMIT : V2_MAX_POSITION - V2_PWM_LIMIT + 4], "little")
        lo = int.from_bytes(data[V2_MIN_POSITION - V2_PWM_LIMIT : V2_MIN_POSITION - V2_PWM_LIMIT + 4], "little")
        s = self.settings
        for key, pwm in (("hold_pwm", s.hold_pwm), ("secure_pwm", s.secure_pwm)):
            if min(pwm, s.effort_cap) > pwm_limit:
                raise self._refuse(f"gripper.{key} {pwm} is above the servo's PWM Limit {pwm_limit}", V2_PWM_LIMIT)
        self._pwm_limit = pwm_limit
        if pwm_limit < s.effort_cap:
            # grip_control's force commands reach up to effort_cap: beyond the limit the servo would refuse them.
            log.warning("%s: the servo's PWM Limit %d caps the grip at %.1f N (gripper.max_force_n %.1f N at PWM %d)",
                        self.device, pwm_limit, pwm_limit / PWM_MAX * s.max_force_n, s.max_force_n, PWM_MAX)
        for key, pos in self._positions():
            if not lo <= pos <= hi:
                raise self._refuse(f"gripper.{key} {pos} lies outside the servo's position limits [{lo}, {hi}]",
                                   V2_MAX_POSITION)

    def _check_limits_v1(self) -> None:
        """As ``_check_limits_v2`` for Protocol 1.0: joint mode (CW and CCW Angle Limit both 0 is wheel mode, where
        a goal position means nothing) and the positions within the angle limits."""
        data, _ = self._read(V1_CW_ANGLE_LIMIT, 4, allow_hw_error=True)
        cw, ccw = int.from_bytes(data[0:2], "little"), int.from_bytes(data[2:4], "little")
        if cw == 0 and ccw == 0:
            raise self._refuse("the servo is in wheel mode (CW and CCW Angle Limit 0): no goal position holds",
                               V1_CW_ANGLE_LIMIT)
        for key, pos in self._positions():
            if not cw <= pos <= ccw:
                raise self._refuse(f"gripper.{key} {pos} lies outside the servo's angle limits [{cw}, {ccw}]",
                                   V1_CW_ANGLE_LIMIT)

    def _setup_v2(self) -> None:
        s = self.settings
        mode = self._read(V2_OPERATING_MODE, 1)[0][0]
        if mode != POSITION_MODE:
            # Operating Mode lives in EEPROM: only writable with torque off. Write it only when it differs.
            self._write(V2_TORQUE_ENABLE, bytes([0]))
            self._write(V2_OPERATING_MODE, bytes([POSITION_MODE]))
        if s.profile_acceleration is not None:
            self._write(V2_PROFILE_ACCELERATION, s.profile_acceleration.to_bytes(4, "little"))
        if s.profile_velocity is not None:
            self._write(V2_PROFILE_VELOCITY, s.profile_velocity.to_bytes(4, "little"))
        self._write(V2_TORQUE_ENABLE, bytes([1]))

    def _reboot(self) -> None:
        port = self._require_port()
        result, _err = self._packet.reboot(port, self.settings.dxl_id)
        if result != COMM_SUCCESS:
            self._count(_COMM_KIND.get(result, "comm"))
            log.warning("%s: reboot: %s", self.device, self._packet.getTxRxResult(result))
        time.sleep(self.settings.reboot_wait_s)
        self._effort_sent = None
        self._ping()

    # Transactions ---------------------------------------------------------------------------------
    def _command(self, position: int, effort: int) -> float:
        """Write effort and goal position; returns the monotonic time the first packet was written."""
        port = self._require_port()
        self._refuse_torque_off()
        self._goal_sent = None
        effort = min(effort, self.settings.effort_cap)  # the one place every position command passes
        if self._v2:
            t_first: float | None = None
            if effort != self._effort_sent:
                self._write(V2_GOAL_PWM, effort.to_bytes(2, "little"))
                t_first = port.last_write_monotonic
                self._effort_sent = effort
            self._write(V2_GOAL_POSITION, position.to_bytes(4, "little", signed=True))
            return t_first if t_first is not None else port.last_write_monotonic
        data = position.to_bytes(2, "little") + self.settings.moving_speed.to_bytes(2, "little") + effort.to_bytes(
            2, "little"
        )
        self._write(V1_GOAL_BLOCK, data)
        return port.last_write_monotonic

    def _refuse_torque_off(self) -> None:
        """Every grip command, while the servo is known to have its torque off (``_torque_off``)."""
        if self._torque_off:
            raise self._error("the servo's torque is off (power lost?): check the gripper, then restart slipd",
                              kind="torque_off")

    def _ping(self) -> int:
        model, _result, _err = self._txrx("ping", None, self._packet.ping)
        return int(model)

    def _read(self, address: int, length: int, allow_hw_error: bool = False) -> tuple[bytes, int]:
        attempts = self.settings.retries + 1
        for _ in range(attempts):
            data, _result, err = self._txrx("read", address, self._packet.readTxRx, address, length,
                                            allow_hw_error=allow_hw_error)
            if len(data) == length:
                return bytes(data), err
            # A whole status packet of another size: the late answer to an earlier request that gave up waiting (the
            # servo answered after the timeout), read as this one's. Its own answer is queued behind it; drop both
            # and ask again rather than fail safe on a bus that works.
            self._count("rx_corrupt")
            self._require_port().clearPort()
        raise self._error(f"read returned {len(data)} of {length} bytes after {attempts} attempt(s)", address,
                          kind="rx_corrupt")

    def _write(self, address: int, data: bytes) -> None:
        self._txrx("write", address, self._packet.writeTxRx, address, len(data), list(data))

    def _txrx(self, op: str, address: int | None, fn: Callable[..., tuple[Any, ...]], *args: Any,
              allow_hw_error: bool = False) -> tuple[Any, ...]:
        """One SDK transaction with bounded retries on missing/corrupt status packets."""
        port = self._require_port()
        attempts = self.settings.retries + 1
        for attempt in range(1, attempts + 1):
            try:
                out = fn(port, self.settings.dxl_id, *args)
            except (serial.SerialException, OSError, termios.error) as exc:
                # A hung-up tty (the adapter unplugged) raises termios.error from the SDK's clearPort. The port is
                # dropped: a file handle on a vanished device never works again, ``reconnect`` opens the path anew.
                port.is_using = False  # the SDK leaves its busy flag set when the port raises
                self._count("io")
                self._drop_port()
                raise self._error(f"{op} failed: serial I/O error: {exc}", address, kind="io") from exc
            result, err = out[-2], out[-1]
            if result == COMM_SUCCESS:
                break
            kind = _COMM_KIND.get(result, "comm")
            self._count(kind)
            port.is_using = False  # we hold the lock: nobody else can be mid-transaction
            if result in _NO_RETRY or attempt == attempts:
                raise self._error(
                    f"{op} failed after {attempt} attempt(s): {self._packet.getTxRxResult(result)}",
                    address, kind=kind, comm_result=result,
                )
            log.debug("%s: %s at %s: %s, retrying", self.device, op, address, self._packet.getTxRxResult(result))
        self._check_error_byte(op, address, err, allow_hw_error)
        return out

    def _check_error_byte(self, op: str, address: int | None, err: int, allow_hw_error: bool) -> None:
        if not err:
            return
        if self._v2:
            instruction_err, hw = err & 0x7F, err & V2_ALERT
        else:
            instruction_err, hw = err & ~V1_HARDWARE_BITS, err & V1_HARDWARE_BITS
        if instruction_err:
            self._count("status_error")
            reason = self._packet.getRxPacketError(instruction_err)
            raise self._error(f"{op} refused by the servo: {reason}", address, kind="status_error", error_byte=err)
        if hw and not allow_hw_error:
            self._count("hardware_error")
            names = self._hardware_error_names(err)
            raise self._error(
                f"{op} answered with a hardware error ({names}): torque is off or limited; call recover()",
                address, kind="hardware_error", error_byte=err,
            )

    def _hardware_error_names(self, err: int) -> str:
        if not self._v2:
            return ", ".join(decode_hardware_error(err & V1_HARDWARE_BITS))
        try:  # 2.0 status packets only carry an alert bit: the details are in Hardware Error Status
            data, _ = self._read(V2_HARDWARE_ERROR, 1, allow_hw_error=True)
            return ", ".join(decode_hardware_error(data[0])) or "alert bit set"
        except GripperError:
            return "alert bit set"

    def _require_port(self) -> _TimedPortHandler:
        if self._port is None:
            raise self._error("not connected (call connect() first)", kind="not_connected")
        return self._port

    def _error(self, reason: str, address: int | None = None, **kw: Any) -> GripperError:
        return GripperError(self.device, reason, address, **kw)

    def _count(self, kind: str) -> None:
        if self.metrics is not None:
            self.metrics.device_errors.labels(device="gripper", kind=kind).inc()
