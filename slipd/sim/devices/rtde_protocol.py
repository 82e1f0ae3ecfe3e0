"""The server side of Universal Robots' RTDE wire protocol (version 2), as the emulated controller speaks it.

Every RTDE packet is ``uint16 size`` (header included), ``uint8 type``, then a big-endian payload. The
packet types, the variable names and their types follow UR's published "Real-Time Data Exchange (RTDE)
Guide"; only what a controller answers is implemented here (a client's side lives in ur_rtde).

Pure functions and small classes, no sockets: the controller feeds received bytes to
:class:`PacketReader` and writes what the ``encode_*`` functions return.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property

# Packet types (ASCII letters on the wire).
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")

HEADER = struct.Struct(">HB")

# RTDE type name -> struct format of one value (big-endian, no padding).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

# Controller variables and their RTDE types (RTDE guide, PolyScope 5.x). Registers are matched by pattern below.
_VARIABLE_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_qdd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_as_torque": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_moment": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    # Inputs a client may write.
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "external_force_torque": "VECTOR6D",
}

_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}
# Upper bound of register indices on PolyScope 5.x (0..47 int/double, 64..127 bit).
_REGISTER_LIMIT = {"int": 48, "double": 48, "bit": 128}

NOT_FOUND = "NOT_FOUND"


def variable_type(name: str) -> str:
    """RTDE type of a controller variable, or ``NOT_FOUND`` as a real controller answers for an unknown name."""
    m = _REGISTER.match(name)
    if m:
        kind, index = m.group(2), int(m.group(3))
        return _REGISTER_TYPES[kind] if index < _REGISTER_LIMIT[kind] else NOT_FOUND
    return _VARIABLE_TYPES.get(name, NOT_FOUND)


@dataclass(frozen=True)
class Recipe:
    """One set-up recipe: its id, variable names and the struct that packs its values."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    frequency: float = 0.0

    @property
    def valid(self) -> bool:
        """False when any variable was unknown (the controller then refuses to start the recipe)."""
        return NOT_FOUND not in self.types

    @cached_property
    def struct(self) -> struct.Struct:
        """Big-endian struct of the values (without the leading recipe id byte)."""
        return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in self.types))

    def pack(self, values: Sequence[object]) -> bytes:
        """A DATA_PACKAGE packet carrying ``values`` (one per variable; vectors as sequences)."""
        flat: list[object] = []
        for v, t in zip(values, self.types):
            if t.startswith("VECTOR"):
                flat.extend(v)  # type: ignore[arg-type]
            else:
                flat.append(v)
        return encode(DATA_PACKAGE, bytes([self.recipe_id]) + self.struct.pack(*flat))

    def unpack(self, body: bytes) -> dict[str, object]:
        """Decode the values of a client's DATA_PACKAGE body (after the recipe id byte) by variable name."""
        flat = list(self.struct.unpack(body[: self.struct.size]))
        out: dict[str, object] = {}
        for name, t in zip(self.names, self.types):
            n = int(TYPE_FORMATS[t][0]) if TYPE_FORMATS[t][0].isdigit() else 1
            out[name] = tuple(flat[:n]) if n > 1 else flat[0]
            del flat[:n]
        return out


def make_recipe(recipe_id: int, names: Sequence[str], frequency: float = 0.0) -> Recipe:
    """Resolve the types of ``names`` into a :class:`Recipe`."""
    names = tuple(n.strip() for n in names if n.strip())
    return Recipe(recipe_id, names, tuple(variable_type(n) for n in names), frequency)


def encode(packet_type: int, payload: bytes = b"") -> bytes:
    """Frame ``payload`` as an RTDE packet of ``packet_type``."""
    return HEADER.pack(HEADER.size + len(payload), packet_type) + payload


def encode_text_message(message: str, source: str = "slipd-urcontroller", level: int = 1) -> bytes:
    """A protocol-2 TEXT_MESSAGE (level 0 exception, 1 error, 2 warning, 3 info)."""
    m, s = message.encode()[:255], source.encode()[:255]
    return encode(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


class PacketReader:
    """Accumulates stream bytes and yields complete ``(type, payload)`` packets."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        """Add received bytes; yield every packet now complete. A size below the header size is a protocol error."""
        self._buf += data
        while len(self._buf) >= HEADER.size:
            size, ptype = HEADER.unpack_from(self._buf)
            if size < HEADER.size:
                raise ValueError(f"RTDE packet size {size} is smaller than its header")
            if len(self._buf) < size:
                return
            payload = bytes(self._buf[HEADER.size : size])
            del self._buf[:size]
            yield ptype, payload
