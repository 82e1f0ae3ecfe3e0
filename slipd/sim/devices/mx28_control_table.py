"""The MX-28's control tables (ROBOTIS e-manual: model number 30 under Protocol 2.0, 29 under 1.0).

A ``ControlTable`` is the servo's byte-addressed memory with named, typed registers (little endian);
the emulator reads and writes it byte-exactly as the wire asks, so reads that straddle registers or
reserved bytes behave as on the device. EEPROM registers (2.0) are writable only while torque is off.
"""

from __future__ import annotations

from dataclasses import dataclass

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
