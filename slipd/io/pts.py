"""PapillArray PTSCOM 2.0 codec: frames (decode with resync and checksum, encode) and ASCII commands.

Wire format (Contactile PTSCOM_2.0_SPEC_SEP22, little-endian)::

    55 66 77 88 | payload (L bytes) | u16 checksum | AA BB CC DD        whole frame <= 2048 bytes

The checksum is the sum of the payload bytes truncated to 16 bits. Payload indices count from the
first byte after the start marker.

Payload::

    byte 0            index size ISZ (bytes per offset; the controller sends 2)
    table             (type u16, offset ISZ) entries; the table ends where the first block begins
    type 1  hub       u32 packet counter, u64 timestamp (us)
    type 3  pillars   Ns u16, Ns sensor offsets; per sensor: Np u16, Np pillar offsets;
                      per pillar: u16 0x0002, Fx Fy Fz (N) Dx Dy Dz (mm) float32
    type 4  global    Ns u16, Ns sensor offsets; per sensor: u16 0x0002, Fx Fy Fz (N) Tx Ty Tz (N mm) float32
    type 5  pillar slip  Ns u16, Ns sensor offsets; per sensor: Np u16, Np pillar offsets;
                      per pillar: u16 0x0001, slip state int8, friction float32
    type 6  sensor slip  Ns u16, Ns sensor offsets; per sensor: u16 0x0001, state u8,
                      friction estimate float32, target grip force float32

With all blocks and one sensor a frame is 433 bytes, which is the figure the public material quotes;
that count only works out if types 4, 5 and 6 carry the same sensor (and, for 5, pillar) offset tables
as type 3, so that is the layout used here.

Choices where the public text is ambiguous (encoder and decoder agree on all of them):

- Sensor and pillar offsets are absolute payload indices (like the top-level table). The encoder
  writes records contiguously in order; the decoder reads them sequentially (as the vendor's layout is
  contiguous) and only checks that every offset lies inside the payload, so a device that used
  block-relative offsets would still decode.
- Block sizes follow from their counts; a known block must end at or before the next block's offset.
  The payload ends where the last block ends, so the end marker must sit exactly there: a frame whose
  end marker is elsewhere is ``bad_length``. When the last block's type is unknown (not 1, 3-6) its
  size cannot be computed; then the first end marker after it whose checksum matches ends the frame.
- Types 1 and 3 are required (no counter or no forces: ``bad_structure``); 4, 5, 6 are optional.
- A controller with two arrays (one per finger) sends both in every frame: every per-sensor block then
  holds one record set per sensor. The decoder is built for ``sensors`` arrays (1 by default): it decodes
  that many (sensor 0 must have 9 pillars, or the frame is ``bad_structure``); further sensors are checked
  for structure and skipped. A configured sensor that a frame lacks (or that has other than 9 pillars)
  reads NaN and is counted in ``missing_sensor``: the consumer sees that finger blind instead of a
  silently shifted stream. The encoder writes ``1 + len(frame.others)`` sensors; the optional blocks of
  the further sensors carry neutral values (wrench 0, slip state 0, friction -1, sensor state as sensor 0).
- ISZ 1, 2 and 4 are accepted; anything else is ``bad_structure``.
- Type 6 state: 0 slip detection off, 1 on, 2 on with the reference loaded (the vendor's reading).

Error accounting of :class:`FrameDecoder`: every byte that is not part of a valid frame is counted in
``garbage_bytes``; each rejected start marker is counted once under its reason (``bad_checksum``,
``bad_length``, ``bad_structure``), after which the search resumes one byte further on, so a valid
frame that begins inside a corrupt one is still found. Nothing in here raises on bad input.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from slipd.geometry import N_PILLARS

START = b"\x55\x66\x77\x88"
END = b"\xaa\xbb\xcc\xdd"
MAX_FRAME_BYTES = 2048
"""Largest whole frame (markers and checksum included) the protocol allows."""
MAX_PAYLOAD_BYTES = MAX_FRAME_BYTES - len(START) - 2 - len(END)

TYPE_HUB = 1
TYPE_PILLARS = 3
TYPE_GLOBAL = 4
TYPE_PILLAR_SLIP = 5
TYPE_SENSOR_SLIP = 6
_KNOWN_TYPES = (TYPE_HUB, TYPE_PILLARS, TYPE_GLOBAL, TYPE_PILLAR_SLIP, TYPE_SENSOR_SLIP)
_MAX_TABLE_ENTRIES = 32
_MAX_SENSORS = 8

_PILLAR_TAG = 0x0002
_GLOBAL_TAG = 0x0002
_PILLAR_SLIP_TAG = 0x0001
_SENSOR_SLIP_TAG = 0x0001
_PILLAR_REC = 2 + 6 * 4  # tag + 6 float32
_GLOBAL_REC = 2 + 6 * 4
_PILLAR_SLIP_REC = 2 + 1 + 4
_SENSOR_SLIP_REC = 2 + 1 + 4 + 4
_HUB_SIZE = 4 + 8

_ISZ_FORMAT = {1: "<B", 2: "<H", 4: "<I"}
_U16 = struct.Struct("<H")
_HUB = struct.Struct("<IQ")
_SENSOR_SLIP = struct.Struct("<HBff")

SLIP_INELIGIBLE, SLIP_LOST_CONTACT, SLIP_NONE, SLIP_CONTACT_AT_START, SLIP_TLOADING, SLIP_SLIPPED = -2, -1, 0, 1, 2, 3
"""Per-pillar slip states of the controller's own slip detection (type 5)."""


# ---------------------------------------------------------------------- frame
@dataclass(slots=True)
class Frame:
    """One decoded sample: sensor 0, and the further sensors of the frame in ``others``.

    ``force`` and ``disp`` are [9, 3] float32 in SDK pillar order (fx fy fz in N; dx dy dz in mm).
    ``wrench`` is the global [6] Fx Fy Fz (N) Tx Ty Tz (N mm) of type 4; ``slip_state`` [9] int8 and
    ``friction`` [9] float32 come from type 5; ``sensor_state``, ``friction_est`` and
    ``target_grip_force`` from type 6. Each optional part is None when its block is absent.

    ``dropped_before`` and ``discontinuity`` are not on the wire: the serial reader sets them from the
    packet counter (frames missing before this one; counter went backwards or the link was re-opened,
    so the consumer should reset its filter and model state).
    """

    counter: int
    t_us: int
    force: np.ndarray
    disp: np.ndarray
    wrench: np.ndarray | None = None
    slip_state: np.ndarray | None = None
    friction: np.ndarray | None = None
    sensor_state: int | None = None
    friction_est: float | None = None
    target_grip_force: float | None = None
    dropped_before: int = 0
    discontinuity: bool = False
    others: tuple[tuple[np.ndarray, np.ndarray], ...] = field(default=())
    """(force, disp) [9, 3] of each further sensor (sensor 1, 2, ...): the second finger's array."""


@dataclass(slots=True)
class FrameBlock:
    """The frames of one read as arrays (the hot path's form: no object per frame).

    ``counter`` [k] int64 and ``t_us`` [k] uint64 (the wire's u64); ``force`` and ``disp`` [k, S, 9, 3]
    float32 (S = the decoder's ``sensors``; a sensor a frame lacks reads NaN). The serial reader fills
    ``dropped_before`` [k] and ``discontinuity`` [k] from the packet counter (see ``slipd.io.sensor``).
    The arrays are views of the decoder's preallocated storage, valid until its next ``feed_block``: copy
    what must outlive the call.
    """

    counter: np.ndarray
    t_us: np.ndarray
    force: np.ndarray
    disp: np.ndarray
    dropped_before: np.ndarray
    discontinuity: np.ndarray

    def __len__(self) -> int:
        return len(self.counter)

    @property
    def sensors(self) -> int:
        """Sensors per frame (S)."""
        return int(self.force.shape[1])

    def select(self, keep: np.ndarray) -> FrameBlock:
        """The frames where ``keep`` (bool [k]) is set (copies; a rare path: repeated counters)."""
        return FrameBlock(self.counter[keep], self.t_us[keep], self.force[keep], self.disp[keep],
                          self.dropped_before[keep], self.discontinuity[keep])

    def frames(self) -> list[Frame]:
        """The block as Frame objects (tests and tools; the daemon reads the arrays)."""
        force = self.force.copy()
        disp = self.disp.copy()
        out = []
        for i in range(len(self)):
            others = tuple((force[i, s], disp[i, s]) for s in range(1, self.sensors))
            f = Frame(int(self.counter[i]), int(self.t_us[i]), force[i, 0], disp[i, 0], others=others)
            f.dropped_before = int(self.dropped_before[i])
            f.discontinuity = bool(self.discontinuity[i])
            out.append(f)
        return out


# ---------------------------------------------------------------------- encoder
class _Layout(NamedTuple):
    template: bytes
    payload_len: int
    hub: int
    pillars: tuple[int, ...]  # payload index of the first pillar record, per sensor
    glob: tuple[int, ...]  # per sensor; empty when the block is absent
    pillar_slip: tuple[int, ...]
    sensor_slip: tuple[int, ...]


_LAYOUTS: dict[tuple[int, bool, bool, bool], _Layout] = {}


def _build_layout(sensors: int, has_global: bool, has_pillar_slip: bool, has_sensor_slip: bool) -> _Layout:
    """Lay out one payload of ``sensors`` arrays (ISZ 2, records contiguous) and return a zero-filled template."""
    types = [TYPE_HUB, TYPE_PILLARS]
    if has_global:
        types.append(TYPE_GLOBAL)
    if has_pillar_slip:
        types.append(TYPE_PILLAR_SLIP)
    if has_sensor_slip:
        types.append(TYPE_SENSOR_SLIP)
    isz = 2
    ns = sensors
    sizes = {
        TYPE_HUB: _HUB_SIZE,
        TYPE_PILLARS: 2 + ns * isz + ns * (2 + N_PILLARS * isz + N_PILLARS * _PILLAR_REC),
        TYPE_GLOBAL: 2 + ns * isz + ns * _GLOBAL_REC,
        TYPE_PILLAR_SLIP: 2 + ns * isz + ns * (2 + N_PILLARS * isz + N_PILLARS * _PILLAR_SLIP_REC),
        TYPE_SENSOR_SLIP: 2 + ns * isz + ns * _SENSOR_SLIP_REC,
    }
    offsets: dict[int, int] = {}
    pos = 1 + len(types) * (2 + isz)
    for t in types:
        offsets[t] = pos
        pos += sizes[t]
    payload = bytearray(pos)
    payload[0] = isz
    for k, t in enumerate(types):
        struct.pack_into("<HH", payload, 1 + k * (2 + isz), t, offsets[t])

    def per_pillar(block: int, rec: int, tag: int) -> tuple[int, ...]:
        """Write the sensor/pillar tables of a per-pillar block; return each sensor's first record index."""
        _U16.pack_into(payload, block, ns)
        sensor = block + 2 + ns * isz
        firsts = []
        for k in range(ns):
            first = sensor + 2 + N_PILLARS * isz
            _U16.pack_into(payload, block + 2 + k * isz, sensor)
            _U16.pack_into(payload, sensor, N_PILLARS)
            for p in range(N_PILLARS):
                _U16.pack_into(payload, sensor + 2 + p * isz, first + p * rec)
                _U16.pack_into(payload, first + p * rec, tag)
            firsts.append(first)
            sensor = first + N_PILLARS * rec
        return tuple(firsts)

    def per_sensor(block: int, rec_len: int, tag: int) -> tuple[int, ...]:
        _U16.pack_into(payload, block, ns)
        recs = []
        for k in range(ns):
            rec = block + 2 + ns * isz + k * rec_len
            _U16.pack_into(payload, block + 2 + k * isz, rec)
            _U16.pack_into(payload, rec, tag)
            recs.append(rec)
        return tuple(recs)

    pillars = per_pillar(offsets[TYPE_PILLARS], _PILLAR_REC, _PILLAR_TAG)
    glob = per_sensor(offsets[TYPE_GLOBAL], _GLOBAL_REC, _GLOBAL_TAG) if has_global else ()
    pslip = per_pillar(offsets[TYPE_PILLAR_SLIP], _PILLAR_SLIP_REC, _PILLAR_SLIP_TAG) if has_pillar_slip else ()
    sslip = per_sensor(offsets[TYPE_SENSOR_SLIP], _SENSOR_SLIP_REC, _SENSOR_SLIP_TAG) if has_sensor_slip else ()
    frame = START + bytes(payload) + b"\x00\x00" + END
    return _Layout(frame, len(payload), offsets[TYPE_HUB], pillars, glob, pslip, sslip)


def _layout(sensors: int, has_global: bool, has_pillar_slip: bool, has_sensor_slip: bool) -> _Layout:
    key = (sensors, has_global, has_pillar_slip, has_sensor_slip)
    lay = _LAYOUTS.get(key)
    if lay is None:
        if not 1 <= sensors <= _MAX_SENSORS:
            raise ValueError(f"a frame carries 1..{_MAX_SENSORS} sensors; got {sensors}")
        lay = _LAYOUTS[key] = _build_layout(*key)
    return lay


def _as_f32(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float32)
    if arr.shape != shape:
        raise ValueError(f"Frame.{name} must have shape {shape}; got {arr.shape}")
    return arr


def encode_frame(frame: Frame) -> bytes:
    """Encode one frame as the controller sends it (ISZ 2; sensor 0 and ``frame.others``).

    Blocks 4, 5 and 6 are written when ``wrench``, ``slip_state``/``friction`` and ``sensor_state``
    are set (a missing half of type 5 is sent as state 0 / friction -1; missing type 6 values as -1);
    further sensors get neutral values there (module docstring).
    Raises ValueError for shapes or counter/timestamp values the wire format cannot carry.
    """
    if not 0 <= frame.counter < 2**32:
        raise ValueError(f"Frame.counter must fit u32; got {frame.counter}")
    if not 0 <= frame.t_us < 2**64:
        raise ValueError(f"Frame.t_us must fit u64; got {frame.t_us}")
    has_pslip = frame.slip_state is not None or frame.friction is not None
    ns = 1 + len(frame.others)
    lay = _layout(ns, frame.wrench is not None, has_pslip, frame.sensor_state is not None)
    buf = bytearray(lay.template)
    p0 = len(START)
    _HUB.pack_into(buf, p0 + lay.hub, frame.counter, frame.t_us)
    values = [(frame.force, frame.disp), *frame.others]
    for k, (force, disp) in enumerate(values):
        name = "" if k == 0 else f"others[{k - 1}]."
        rec = np.ndarray(
            (N_PILLARS, 6), dtype="<f4", buffer=buf, offset=p0 + lay.pillars[k] + 2, strides=(_PILLAR_REC, 4)
        )
        rec[:, :3] = _as_f32(name + "force", force, (N_PILLARS, 3))
        rec[:, 3:] = _as_f32(name + "disp", disp, (N_PILLARS, 3))
    if lay.glob:
        g = np.ndarray((6,), dtype="<f4", buffer=buf, offset=p0 + lay.glob[0] + 2)
        g[:] = _as_f32("wrench", frame.wrench, (6,))
    for k, at in enumerate(lay.pillar_slip):
        base = p0 + at + 2
        st = np.ndarray((N_PILLARS,), dtype="i1", buffer=buf, offset=base, strides=(_PILLAR_SLIP_REC,))
        fr = np.ndarray((N_PILLARS,), dtype="<f4", buffer=buf, offset=base + 1, strides=(_PILLAR_SLIP_REC,))
        if frame.slip_state is None or k > 0:
            st[:] = 0
        else:
            states = np.asarray(frame.slip_state)
            if states.shape != (N_PILLARS,):
                raise ValueError(f"Frame.slip_state must have shape (9,); got {states.shape}")
            st[:] = states.astype(np.int8)
        fr[:] = -1.0 if frame.friction is None or k > 0 else _as_f32("friction", frame.friction, (N_PILLARS,))
    for k, at in enumerate(lay.sensor_slip):
        state = int(frame.sensor_state)  # type: ignore[arg-type]
        if not 0 <= state < 256:
            raise ValueError(f"Frame.sensor_state must fit u8; got {state}")
        fe = -1.0 if frame.friction_est is None or k > 0 else float(frame.friction_est)
        tg = -1.0 if frame.target_grip_force is None or k > 0 else float(frame.target_grip_force)
        _SENSOR_SLIP.pack_into(buf, p0 + at, _SENSOR_SLIP_TAG, state, fe, tg)
    total = int(np.frombuffer(buf, dtype=np.uint8, count=lay.payload_len, offset=p0).sum()) & 0xFFFF
    _U16.pack_into(buf, p0 + lay.payload_len, total)
    return bytes(buf)


def checksum(payload: bytes | bytearray | memoryview) -> int:
    """PTSCOM checksum of a payload: the byte sum truncated to 16 bits."""
    return int(np.frombuffer(payload, dtype=np.uint8).sum()) & 0xFFFF


# ---------------------------------------------------------------------- decoder
class _Reject(Exception):
    """Internal: a start marker does not begin a valid frame (kind is the counter to bump)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind


class _NeedMore(Exception):
    """Internal: the buffer ends before the frame can be judged."""


_BUFFER_BYTES = 1 << 16
_CHUNK_BYTES = _BUFFER_BYTES - MAX_FRAME_BYTES
_MAX_VIEWS = 64
"""Runs whose views ``FrameDecoder`` keeps (a few recur: a read's frames, at the buffer's start)."""
_LE_U16 = np.dtype("<u2")
_LE_U32 = np.dtype("<u4")
_LE_U64 = np.dtype("<u8")
_LE_F32 = np.dtype("<f4")


class FrameDecoder:
    """Incremental PTSCOM 2.0 decoder: feed it whatever the serial port gave, get whole frames back.

    Frames split across reads are joined, garbage is skipped by searching for the start marker, and a
    corrupt frame is counted and skipped (never raised). Bytes live in one preallocated buffer that is
    compacted in place. The first frame (and any frame whose layout changes) is validated by walking its
    structure; the frames after it that lie back to back with the same layout are checked and decoded as
    one block per read (see ``_decode_run``). Values go straight from the byte buffer into preallocated
    arrays (strided views, one copy per run of frames): ``feed_block`` hands them out as a ``FrameBlock``
    (the daemon's path: no Python object per frame); ``feed`` wraps them in ``Frame`` objects.

    ``sensors``: how many arrays the consumer reads from each frame (module docstring).

    Counters (cumulative): ``frames``, ``garbage_bytes``, ``bad_checksum``, ``bad_length``,
    ``bad_structure``, ``missing_sensor`` (frames lacking a configured sensor); ``errors()`` returns the
    three error counters by kind.
    """

    ERROR_KINDS = ("bad_checksum", "bad_length", "bad_structure")

    def __init__(self, sensors: int = 1) -> None:
        if not 1 <= sensors <= _MAX_SENSORS:
            raise ValueError(f"sensors must be 1..{_MAX_SENSORS}, got {sensors}")
        self.sensors = sensors
        self._buf = bytearray(_BUFFER_BYTES)
        self._u8 = np.frombuffer(self._buf, dtype=np.uint8)
        self._start = 0
        self._end = 0
        # (frame length, payload length, fixed byte indices, their values, block record positions, the fixed-byte
        # mask and the fixed bytes, each tiled for as many back-to-back frames as the buffer holds) of the last fully
        # validated frame: the controller sends one layout, so later frames are checked against it.
        self._run: tuple[int, int, np.ndarray, np.ndarray, dict[int, tuple[int, ...]], np.ndarray, bytes] | None = None
        self._scratch = np.zeros(_BUFFER_BYTES, np.uint8)
        # ``_emit``'s reading positions for the layout it last copied (``_layout_plan``), keyed by its record positions.
        self._plan: tuple[Any, int, tuple[int, ...], int | None] = (None, 0, (), None)
        self._views: dict[tuple[int, ...], tuple[Any, ...]] = {}
        """The strided views of the byte buffer and the output slices that ``_decode_run`` and ``_emit`` read and write,
        by where a run starts and how many frames it holds: ``_rewind`` puts every read's frames at the buffer's start,
        so the same few runs recur read after read and a read makes no new array for them. Dropped with the layout or
        the output storage they were cut for; at most ``_MAX_VIEWS``."""
        self._block: FrameBlock | None = None  # ``block``'s views, kept for the next read of as many frames
        self._value_ranges: list[tuple[int, int]] = []
        # Output storage, reused across feeds (grown only when one feed completes more frames than ever
        # before; a serial read is bounded, so is this). _vals is [force|disp, frame, sensor, pillar, axis]: a block's
        # forces are one contiguous array (the ufuncs of the hot path run their fast loop on them).
        self._cap = 0
        self._n = 0
        self._counter = np.zeros(0, np.int64)
        self._t = np.zeros(0, np.uint64)
        self._vals = np.zeros((2, 0, sensors, N_PILLARS, 3), np.float32)
        self._dropped = np.zeros(0, np.int64)
        self._disc = np.zeros(0, bool)
        self._frames_out: list[Frame] | None = None  # set while ``feed`` builds Frame objects
        self.frames = 0
        self.missing_sensor = 0
        self.garbage_bytes = 0
        self.bad_checksum = 0
        self.bad_length = 0
        self.bad_structure = 0

    def errors(self) -> dict[str, int]:
        """Error counters by kind (the ``kind`` label of the frame_errors metric)."""
        return {"bad_checksum": self.bad_checksum, "bad_length": self.bad_length, "bad_structure": self.bad_structure}

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a frame (or a possible start marker)."""
        return self._end - self._start

    def reset(self) -> None:
        """Drop buffered bytes (after a reconnect the old tail belongs to a dead stream). Counters stay."""
        self._start = self._end = 0
        self._n = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Add bytes from the port; return the frames completed by them, in order."""
        out: list[Frame] = []
        self._frames_out = out
        try:
            self._feed(data)
        finally:
            self._frames_out = None
        return out

    def feed_block(self, data: bytes | bytearray | memoryview) -> FrameBlock:
        """Add bytes from the port; return the frames completed by them (and by bytes ``stash`` kept) as
        arrays (views, valid until the next call; see ``FrameBlock``)."""
        self._feed(data)
        return self.block()

    def stash(self, data: bytes | bytearray | memoryview) -> int | None:
        """Keep bytes from the port without decoding them yet (the next ``feed``/``feed_block`` decodes them
        with its own): a reader that holds frames back until its consumer wants them decodes them all in
        one pass. Returns how many end markers these bytes complete (the frames they complete, unless
        corrupt input or a value that happens to spell the marker says otherwise), or None (nothing kept)
        when the buffer has no room for them: feed them instead."""
        self._rewind()
        view = memoryview(data).cast("B")
        n = self._end - self._start
        if n + len(view) > _CHUNK_BYTES:
            return None  # undecoded bytes stay below a chunk: ``_feed`` always has room for the next one
        if self._end + len(view) > _BUFFER_BYTES:
            self._buf[:n] = self._buf[self._start : self._end]
            self._start, self._end = 0, n
        old = self._end
        self._buf[old : old + len(view)] = view
        self._end += len(view)
        # A marker may straddle the previous bytes: look from len(END) - 1 bytes back.
        return self._buf.count(END, max(self._start, old - len(END) + 1), self._end)

    def block(self) -> FrameBlock:
        """The frames completed by the latest ``feed`` or ``feed_block`` as arrays (views; see ``FrameBlock``)."""
        n = self._n
        block = self._block
        if block is None or len(block.counter) != n:
            block = FrameBlock(self._counter[:n], self._t[:n], self._vals[0, :n], self._vals[1, :n], self._dropped[:n],
                               self._disc[:n])
            self._block = block
        block.dropped_before.fill(0)
        block.discontinuity.fill(False)
        return block

    def _rewind(self) -> None:
        """Move what is buffered, when it is at most a partial frame, to the buffer's start: every read then lands on
        the same few KiB, which the cache still holds at the next decision, instead of walking the whole buffer (a
        cold line costs more than this copy of a frame's bytes at most)."""
        n = self._end - self._start
        if self._start and n <= MAX_FRAME_BYTES:
            if n:
                self._buf[:n] = self._buf[self._start : self._end]  # same length: no resize, views stay valid
            self._start, self._end = 0, n

    def _feed(self, data: bytes | bytearray | memoryview) -> None:
        self._n = 0
        self._rewind()
        view = memoryview(data).cast("B")
        i = 0
        while i < len(view):
            if self._end + min(len(view) - i, _CHUNK_BYTES) > _BUFFER_BYTES:
                n = self._end - self._start
                self._buf[:n] = self._buf[self._start : self._end]  # same length: no resize, views stay valid
                self._start, self._end = 0, n
            # What fits (a scan leaves at most a partial frame behind, so there is always room after one).
            take = min(len(view) - i, _CHUNK_BYTES, _BUFFER_BYTES - self._end)
            self._buf[self._end : self._end + take] = view[i : i + take]
            self._end += take
            i += take
            self._scan()
        if not len(view):
            self._scan()  # stashed bytes only

    # The scan keeps its state in self._start so that a _NeedMore leaves everything in place for the
    # next feed.
    def _scan(self) -> None:
        buf = self._buf
        while True:
            s = buf.find(START, self._start, self._end)
            if s < 0:
                # Keep a tail that might be the first bytes of a start marker split across reads.
                keep = min(len(START) - 1, self._end - self._start)
                drop = self._end - self._start - keep
                self.garbage_bytes += drop
                self._start += drop
                return
            if s > self._start:
                self.garbage_bytes += s - self._start
                self._start = s
            if self._run is not None and self._decode_run(s):
                continue
            try:
                found, length = self._decode_at(s)
            except _NeedMore:
                return
            except _Reject as rej:
                setattr(self, rej.kind, getattr(self, rej.kind) + 1)
                self.garbage_bytes += 1
                self._start = s + 1
                continue
            self._emit(s + len(START), found, 1, length)
            self.frames += 1
            self._start = s + length

    # ------------------------------------------------------------ runs of frames
    def _decode_run(self, s: int) -> int:
        """Decode the frames lying back to back from ``s`` that have the cached layout, all in one pass.

        The controller sends one layout, so a read of k frames is k copies of one template whose value
        bytes differ: the fixed bytes (markers and structure) of all k are compared at once, the checksums
        summed at once, and the values copied out with strided views. Accepts exactly the frames that a
        full decode would (same structure, end marker, checksum); the run stops before the first frame
        that differs or is incomplete, which the full decoder then judges. Returns the frames added.
        """
        flen, plen, chk_idx, chk_vals, found, mask, tiled = self._run  # type: ignore[misc]
        k = (self._end - s) // flen
        if k == 0:
            return 0
        views = self._views.get((s, k))
        if views is None:
            nb = k * flen
            seg = self._u8[s : s + nb]
            rows = seg.reshape(k, flen)
            sent = np.ndarray((k,), dtype=_LE_U16, buffer=self._buf, offset=s + len(START) + plen, strides=(flen,))
            views = self._keep_views((s, k), (seg, rows, rows[:, len(START) : len(START) + plen], sent, mask[:nb],
                                               self._scratch[:nb], tiled[:nb]))
        seg, rows, payloads, sent, mask_k, scratch_k, tiled_k = views
        # The checksum is the payload's byte sum mod 2**16: a 16-bit accumulator wraps to exactly that.
        sums = np.add.reduce(payloads, axis=1, dtype=_LE_U16)  # (ndarray.sum's own call)
        # The common read, every frame whole: the frames' bytes with their values masked out against the template,
        # and the checksums, each in one byte comparison (memcmp) instead of per-frame reductions.
        fixed = np.bitwise_and(seg, mask_k, out=scratch_k)
        if fixed.tobytes() == tiled_k and sums.tobytes() == sent.tobytes():
            n = k
        else:
            ok = (rows[:, chk_idx] == chk_vals).all(axis=1) & (sums == sent)
            n = k if ok.all() else int(np.argmin(ok))
        if n == 0:
            return 0
        self._emit(s + len(START), found, n, flen)
        self.frames += n
        self._start = s + n * flen
        return n

    # ------------------------------------------------------------ one frame
    def _decode_at(self, s: int) -> tuple[dict[int, tuple[int, ...]], int]:
        """Validate the frame starting at buffer index ``s`` (its start marker), walking its structure.
        Returns its record positions and its length; remembers its layout for ``_decode_run``."""
        total, found = self._decode_full(s + len(START))
        self._remember_layout(s + len(START), total - len(START) - 2 - len(END), found)
        return found, total

    def _remember_layout(self, p0: int, payload_len: int, found: dict[int, tuple[int, ...]]) -> None:
        """Cache which frame bytes are fixed (markers and structure: everything but values and checksum)."""
        mask = np.ones(payload_len, dtype=bool)
        for a, b in self._value_ranges:
            mask[a:b] = False
        flen = len(START) + payload_len + 2 + len(END)
        fixed = np.concatenate([
            np.arange(len(START)), len(START) + np.flatnonzero(mask), np.arange(flen - len(END), flen)
        ]).astype(np.intp)
        vals = self._u8[p0 - len(START) + fixed].copy()
        # As many back-to-back frames as the buffer holds, for ``_decode_run``'s one comparison: a mask that keeps the
        # fixed bytes, and those bytes (values and checksums zero).
        one = np.zeros(flen, np.uint8)
        one[fixed] = 0xFF
        mask = np.tile(one, _BUFFER_BYTES // flen + 1)
        one[fixed] = vals
        tiled = np.tile(one, _BUFFER_BYTES // flen + 1).tobytes()
        self._run = (flen, payload_len, fixed, vals, dict(found), mask, tiled)
        self._views.clear()

    def _decode_full(self, p0: int) -> tuple[int, dict[int, tuple[int, ...]]]:
        """Validate a frame whose payload starts at buffer index ``p0``, walking its structure: its length and
        the payload index of each block's first record, per sensor."""
        buf = self._buf
        avail = self._end - p0  # payload bytes (and beyond) present so far
        self._value_ranges = []

        def need(n: int) -> None:
            """Payload bytes [0, n) must be present; beyond the protocol's maximum the frame is bad."""
            if n > MAX_PAYLOAD_BYTES:
                raise _Reject("bad_length")
            if n > avail:
                raise _NeedMore

        need(1)
        isz = buf[p0]
        ifmt = _ISZ_FORMAT.get(isz)
        if ifmt is None:
            raise _Reject("bad_structure")
        entry = 2 + isz

        # ---- index table: entries until the first block begins
        offsets: dict[int, int] = {}
        pos = 1
        first_block = MAX_PAYLOAD_BYTES
        while pos < first_block:
            if len(offsets) >= _MAX_TABLE_ENTRIES:
                raise _Reject("bad_structure")
            need(pos + entry)
            typ = _U16.unpack_from(buf, p0 + pos)[0]
            off = struct.unpack_from(ifmt, buf, p0 + pos + 2)[0]
            pos += entry
            if typ == 0 or typ in offsets or off < pos or off >= MAX_PAYLOAD_BYTES:
                raise _Reject("bad_structure")
            offsets[typ] = off
            first_block = min(first_block, off)
        if pos != first_block or TYPE_HUB not in offsets or TYPE_PILLARS not in offsets:
            raise _Reject("bad_structure")

        # ---- block extents (sequential layout) and where the payload ends
        blocks = sorted(offsets.items(), key=lambda kv: kv[1])
        found: dict[int, tuple[int, ...]] = {}  # type -> payload index of each sensor's first record (-1: unusable)
        payload_len = -1
        for k, (typ, off) in enumerate(blocks):
            nxt = blocks[k + 1][1] if k + 1 < len(blocks) else None
            if nxt is not None and nxt == off:
                raise _Reject("bad_structure")
            if typ not in _KNOWN_TYPES:
                if nxt is None:
                    payload_len = self._unknown_tail_length(p0, off)
                self._value_ranges.append((off, nxt if nxt is not None else payload_len))
                continue
            end, first_rec = self._block_extent(p0, typ, off, isz, need)
            if nxt is not None and end > nxt:
                raise _Reject("bad_structure")
            found[typ] = first_rec
            if nxt is None:
                payload_len = end

        total = len(START) + payload_len + 2 + len(END)
        if total > MAX_FRAME_BYTES:
            raise _Reject("bad_length")
        need(payload_len + 2 + len(END))
        if buf[p0 + payload_len + 2 : p0 + payload_len + 2 + len(END)] != END:
            raise _Reject("bad_length")
        # Sub-table offsets are only required to point inside the payload (see the module docstring).
        self._check_sub_offsets(p0, offsets, isz, payload_len)
        if (int(self._u8[p0 : p0 + payload_len].sum()) & 0xFFFF) != _U16.unpack_from(buf, p0 + payload_len)[0]:
            raise _Reject("bad_checksum")
        return total, found

    def _block_extent(
        self, p0: int, typ: int, off: int, isz: int, need: Callable[[int], None]
    ) -> tuple[int, tuple[int, ...]]:
        """End (payload index) of a known block and the index of each sensor's first record (-1 for a
        sensor whose pillar count is not 9: it cannot be read as a [9, 3] array)."""
        buf = self._buf
        if typ == TYPE_HUB:
            need(off + _HUB_SIZE)
            self._value_ranges.append((off, off + _HUB_SIZE))
            return off + _HUB_SIZE, (off,)
        need(off + 2)
        ns = _U16.unpack_from(buf, p0 + off)[0]
        if not 1 <= ns <= _MAX_SENSORS:
            raise _Reject("bad_structure")
        pos = off + 2 + ns * isz
        if typ in (TYPE_GLOBAL, TYPE_SENSOR_SLIP):
            rec = _GLOBAL_REC if typ == TYPE_GLOBAL else _SENSOR_SLIP_REC
            tag = _GLOBAL_TAG if typ == TYPE_GLOBAL else _SENSOR_SLIP_TAG
            end = pos + ns * rec
            need(end)
            for k in range(ns):
                if _U16.unpack_from(buf, p0 + pos + k * rec)[0] != tag:
                    raise _Reject("bad_structure")
                self._value_ranges.append((pos + k * rec + 2, pos + (k + 1) * rec))
            return end, tuple(pos + k * rec for k in range(ns))
        rec = _PILLAR_REC if typ == TYPE_PILLARS else _PILLAR_SLIP_REC
        tag = _PILLAR_TAG if typ == TYPE_PILLARS else _PILLAR_SLIP_TAG
        firsts = []
        for k in range(ns):
            need(pos + 2)
            npil = _U16.unpack_from(buf, p0 + pos)[0]
            if (k == 0 and npil != N_PILLARS) or not 1 <= npil <= 64:
                raise _Reject("bad_structure")
            recs = pos + 2 + npil * isz
            end = recs + npil * rec
            need(end)
            tags = np.ndarray((npil,), dtype="<u2", buffer=buf, offset=p0 + recs, strides=(rec,))
            if not (tags == tag).all():
                raise _Reject("bad_structure")
            self._value_ranges.extend((recs + j * rec + 2, recs + (j + 1) * rec) for j in range(npil))
            firsts.append(recs if npil == N_PILLARS else -1)
            pos = end
        return pos, tuple(firsts)

    def _unknown_tail_length(self, p0: int, off: int) -> int:
        """Payload length when the last block's type is unknown: the first end marker with a valid checksum."""
        buf = self._buf
        search = p0 + off
        limit = min(self._end, p0 + MAX_PAYLOAD_BYTES + 2 + len(END))
        while True:
            e = buf.find(END, search, limit)
            if e < 0:
                if self._end >= p0 + MAX_PAYLOAD_BYTES + 2 + len(END):
                    raise _Reject("bad_length")
                raise _NeedMore
            plen = e - 2 - p0
            if plen > off and (int(self._u8[p0 : p0 + plen].sum()) & 0xFFFF) == _U16.unpack_from(buf, p0 + plen)[0]:
                return plen
            search = e + 1

    def _check_sub_offsets(self, p0: int, offsets: dict[int, int], isz: int, payload_len: int) -> None:
        buf = self._buf
        dt = {1: "u1", 2: "<u2", 4: "<u4"}[isz]
        for typ in (TYPE_PILLARS, TYPE_GLOBAL, TYPE_PILLAR_SLIP, TYPE_SENSOR_SLIP):
            off = offsets.get(typ)
            if off is None:
                continue
            ns = _U16.unpack_from(buf, p0 + off)[0]
            sensor_offs = np.ndarray((ns,), dtype=dt, buffer=buf, offset=p0 + off + 2)
            if (sensor_offs >= payload_len).any():
                raise _Reject("bad_structure")
            if typ in (TYPE_PILLARS, TYPE_PILLAR_SLIP):
                rec = _PILLAR_REC if typ == TYPE_PILLARS else _PILLAR_SLIP_REC
                pos = off + 2 + ns * isz
                for _ in range(ns):
                    npil = _U16.unpack_from(buf, p0 + pos)[0]
                    pill_offs = np.ndarray((npil,), dtype=dt, buffer=buf, offset=p0 + pos + 2)
                    if (pill_offs >= payload_len).any():
                        raise _Reject("bad_structure")
                    pos += 2 + npil * isz + npil * rec

    def _emit(self, p0: int, found: dict[int, tuple[int, ...]], n: int, stride: int) -> None:
        """Copy ``n`` payloads of one layout (the first at buffer index ``p0``, ``stride`` bytes apart) into the
        output arrays: strided views of the byte buffer, one copy per array for the whole run."""
        m = self._n
        if m + n > self._cap:
            self._grow(m + n)
        buf = self._buf
        if self._plan[0] is not found:
            self._plan = (found, *self._layout_plan(found))
            self._views.clear()
        _, hub_off, recs, step = self._plan
        missing = False
        if step is not None:
            views = self._views.get((p0, n, stride, m))
            if views is None:
                hub = p0 + hub_off
                # Every configured sensor's records the same distance apart (always, for one sensor): one view and one
                # copy for all of them.
                src = np.ndarray(
                    (n, self.sensors, N_PILLARS, 2, 3), dtype=_LE_F32, buffer=buf, offset=p0 + recs[0] + 2,
                    strides=(stride, step, _PILLAR_REC, 12, 4),
                )
                counter = np.ndarray((n,), dtype=_LE_U32, buffer=buf, offset=hub, strides=(stride,))
                t = np.ndarray((n,), dtype=_LE_U64, buffer=buf, offset=hub + 4, strides=(stride,))
                views = self._keep_views((p0, n, stride, m), (self._counter[m : m + n], counter, self._t[m : m + n], t,
                                                               self._vals[:, m : m + n], src.transpose(3, 0, 1, 2, 4)))
            counter, counter_src, t, t_src, vals, vals_src = views
            # (slice assignment: the copy np.copyto makes, without its Python-level dispatcher)
            counter[...] = counter_src
            t[...] = t_src
            vals[...] = vals_src
        else:
            hub = p0 + hub_off
            self._counter[m : m + n] = np.ndarray((n,), dtype=_LE_U32, buffer=buf, offset=hub, strides=(stride,))
            self._t[m : m + n] = np.ndarray((n,), dtype=_LE_U64, buffer=buf, offset=hub + 4, strides=(stride,))
            missing = self._emit_each(p0, recs, m, n, stride)
        if missing:
            self.missing_sensor += n
        if self._frames_out is not None:
            self._frames_out.extend(self._build(p0, found, m, n, stride))
        self._n = m + n

    def _layout_plan(self, found: dict[int, tuple[int, ...]]) -> tuple[int, tuple[int, ...], int | None]:
        """Where ``_emit`` reads a layout's values: the hub's payload index, the configured sensors' first pillar
        records, and the distance between those records when they are evenly spaced (None: copied sensor by sensor)."""
        recs = found[TYPE_PILLARS][: self.sensors]
        step = recs[1] - recs[0] if len(recs) > 1 else 0
        even = len(recs) == self.sensors and min(recs) >= 0 and step >= 0 and \
            all(recs[k] - recs[k - 1] == step for k in range(1, len(recs)))
        return found[TYPE_HUB][0], recs, step if even else None

    def _emit_each(self, p0: int, recs: tuple[int, ...], m: int, n: int, stride: int) -> bool:
        """``_emit``'s copy sensor by sensor (a sensor missing from the frames, records not evenly spaced); whether a
        configured sensor was missing."""
        buf = self._buf
        missing = False
        for k in range(self.sensors):
            dst = self._vals[:, m : m + n, k]  # [2, n, 9, 3]
            if k < len(recs) and recs[k] >= 0:
                src = np.ndarray(
                    (n, N_PILLARS, 2, 3), dtype="<f4", buffer=buf, offset=p0 + recs[k] + 2,
                    strides=(stride, _PILLAR_REC, 12, 4),
                )
                np.copyto(dst, src.transpose(2, 0, 1, 3))
            else:
                dst[...] = np.nan  # the configured finger is not in these frames: blind, not shifted
                missing = True
        return missing

    def _keep_views(self, key: tuple[int, ...], views: tuple[Any, ...]) -> tuple[Any, ...]:
        """Keep a run's views for the next read (``_views``)."""
        if len(self._views) >= _MAX_VIEWS:
            self._views.clear()
        self._views[key] = views
        return views

    def _grow(self, need: int) -> None:
        self._views.clear()  # (the output slices kept there are of the storage replaced here)
        self._block = None
        cap = max(need, 2 * self._cap, 64)
        counter, t, vals, dropped, disc = self._counter, self._t, self._vals, self._dropped, self._disc
        self._counter = np.zeros(cap, np.int64)
        self._t = np.zeros(cap, np.uint64)
        self._vals = np.zeros((2, cap, self.sensors, N_PILLARS, 3), np.float32)
        self._dropped = np.zeros(cap, np.int64)
        self._disc = np.zeros(cap, bool)
        m = self._n  # frames already in the output move along
        self._counter[:m], self._t[:m], self._vals[:, :m] = counter[:m], t[:m], vals[:, :m]
        self._dropped[:m], self._disc[:m] = dropped[:m], disc[:m]
        self._cap = cap

    def _build(self, p0: int, found: dict[int, tuple[int, ...]], m: int, n: int, stride: int) -> list[Frame]:
        """Frame objects for the ``n`` frames just copied to output rows ``m..m+n`` (``feed``'s form), with the
        optional blocks of sensor 0 read through strided views of the buffer."""
        buf = self._buf
        counters = self._counter[m : m + n].tolist()
        stamps = self._t[m : m + n].tolist()
        fd = np.moveaxis(self._vals[:, m : m + n], 0, 2).copy()  # [n, S, 2, 9, 3]: the frames own their values
        none = itertools.repeat(None)
        wrench: Iterable[Any] = none
        states: Iterable[Any] = none
        friction: Iterable[Any] = none
        sensor: Iterable[Any] = none
        f_est: Iterable[Any] = none
        target: Iterable[Any] = none
        g = found.get(TYPE_GLOBAL)
        if g is not None:
            wrench = np.ndarray((n, 6), dtype="<f4", buffer=buf, offset=p0 + g[0] + 2, strides=(stride, 4)).astype(
                np.float32
            )
        ps = found.get(TYPE_PILLAR_SLIP)
        if ps is not None:
            base = p0 + ps[0] + 2
            states = np.ndarray(
                (n, N_PILLARS), dtype="i1", buffer=buf, offset=base, strides=(stride, _PILLAR_SLIP_REC)
            ).copy()
            friction = np.ndarray(
                (n, N_PILLARS), dtype="<f4", buffer=buf, offset=base + 1, strides=(stride, _PILLAR_SLIP_REC)
            ).astype(np.float32)
        ss = found.get(TYPE_SENSOR_SLIP)
        if ss is not None:
            base = p0 + ss[0] + 2
            sensor = np.ndarray((n,), dtype="u1", buffer=buf, offset=base, strides=(stride,)).tolist()
            f_est = np.ndarray((n,), dtype="<f4", buffer=buf, offset=base + 1, strides=(stride,)).tolist()
            target = np.ndarray((n,), dtype="<f4", buffer=buf, offset=base + 5, strides=(stride,)).tolist()
        others = [tuple((fd[i, k, 0], fd[i, k, 1]) for k in range(1, self.sensors)) for i in range(n)]
        return list(map(Frame, counters, stamps, fd[:, 0, 0], fd[:, 0, 1], wrench, states, friction, sensor, f_est,
                        target, itertools.repeat(0), itertools.repeat(False), others))


# ---------------------------------------------------------------------- commands
CMD_BIAS = b"z\n"
CMD_SLIP_ON = b"S\n"
CMD_SLIP_OFF = b"s\n"
RATES_HZ = (100, 250, 500, 1000)


def rate_command(hz: int) -> bytes:
    """The sample-rate command, e.g. ``rate_command(1000) == b"f1000\\n"``; only 100/250/500/1000 Hz exist."""
    if hz not in RATES_HZ:
        raise ValueError(f"sample rate {hz!r} Hz not supported by the PapillArray; choose one of {RATES_HZ}")
    return f"f{hz}\n".encode("ascii")


class Command(NamedTuple):
    """A parsed controller command: kind is "bias", "rate" (value = Hz) or "slip" (value = on/off)."""

    kind: str
    value: int | bool | None = None


def parse_command(line: bytes) -> Command:
    """Parse one command line (trailing newline optional) as the controller would; ValueError if unknown."""
    text = bytes(line).rstrip(b"\r\n")
    if text == b"z":
        return Command("bias")
    if text == b"S":
        return Command("slip", True)
    if text == b"s":
        return Command("slip", False)
    if text[:1] == b"f" and text[1:].isdigit():
        hz = int(text[1:])
        if hz in RATES_HZ:
            return Command("rate", hz)
    raise ValueError(f"unknown PapillArray command {bytes(line)!r}")
