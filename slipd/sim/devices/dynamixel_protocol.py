"""The Dynamixel wire protocol, both generations: packet framing, CRC-16 and checksum, byte stuffing.

Written from ROBOTIS' protocol e-manual, not from ``dynamixel_sdk``: the emulator is the independent peer
the real SDK talks to, so a shared misunderstanding cannot hide (``tests/io/test_gripper.py`` checks the CRC
and the framing against the vendor SDK).

* Protocol 2.0: ``FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS | CRC_L CRC_H``, CRC-16 with the
  Dynamixel polynomial 0x8005 over everything before the CRC, byte stuffing ``FF FF FD`` ->
  ``FF FF FD FD`` from the instruction byte on; status packets use instruction 0x55 and an error
  byte whose bit 7 (alert) says "read Hardware Error Status (70)".
* Protocol 1.0: ``FF FF | ID | LEN | INST | PARAMS | CHECKSUM`` with ``~sum & 0xFF``; status packets
  carry an error bit field (overload = 0x20, ...).

The parsers take packets off the front of a receive buffer in place and resynchronise on garbage.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

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
