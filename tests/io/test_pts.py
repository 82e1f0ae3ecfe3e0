"""PTSCOM 2.0 codec: round trips, resync, corrupt frames counted not raised, split reads, commands."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from slipd.io.pts import (
    CMD_BIAS,
    CMD_SLIP_OFF,
    CMD_SLIP_ON,
    END,
    MAX_FRAME_BYTES,
    START,
    Command,
    Frame,
    FrameDecoder,
    checksum,
    encode_frame,
    parse_command,
    rate_command,
)

f32 = hnp.arrays(np.float32, (9, 3), elements=st.floats(width=32, allow_nan=True, allow_infinity=True))


@st.composite
def frames(draw: st.DrawFn) -> Frame:
    f = Frame(
        counter=draw(st.integers(0, 2**32 - 1)),
        t_us=draw(st.integers(0, 2**64 - 1)),
        force=draw(f32),
        disp=draw(f32),
    )
    if draw(st.booleans()):
        f.wrench = draw(hnp.arrays(np.float32, (6,), elements=st.floats(width=32, allow_nan=False)))
    if draw(st.booleans()):
        f.slip_state = draw(hnp.arrays(np.int8, (9,), elements=st.integers(-2, 3)))
        f.friction = draw(hnp.arrays(np.float32, (9,), elements=st.floats(-1, 2, width=32)))
    if draw(st.booleans()):
        f.sensor_state = draw(st.integers(0, 2))
        f.friction_est = draw(st.floats(-1, 2, width=32))
        f.target_grip_force = draw(st.floats(-1, 40, width=32))
    return f


def simple_frame(counter: int, seed: int | None = None) -> Frame:
    rng = np.random.default_rng(counter if seed is None else seed)
    return Frame(
        counter, counter * 1000, rng.normal(size=(9, 3)).astype(np.float32),
        rng.normal(size=(9, 3)).astype(np.float32), wrench=rng.normal(size=6).astype(np.float32),
        slip_state=np.zeros(9, np.int8), friction=np.full(9, -1, np.float32), sensor_state=0,
    )


def assert_same(a: Frame, b: Frame) -> None:
    assert (a.counter, a.t_us) == (b.counter, b.t_us)
    for name in ("force", "disp", "wrench", "slip_state", "friction"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(np.asarray(x).view(np.uint8), np.asarray(y).view(np.uint8)), name  # bit-exact
    assert a.sensor_state == b.sensor_state
    if a.sensor_state is not None:
        assert np.float32(a.friction_est) == np.float32(b.friction_est)
        assert np.float32(a.target_grip_force) == np.float32(b.target_grip_force)


# ---------------------------------------------------------------------- layout
def test_full_frame_is_433_bytes_with_markers_and_checksum() -> None:
    data = encode_frame(simple_frame(7))
    assert len(data) == 433  # the size the public protocol material quotes for one sensor
    assert data[:4] == START and data[-4:] == END
    payload = data[4:-6]
    assert struct.unpack("<H", data[-6:-4])[0] == sum(payload) & 0xFFFF == checksum(payload)
    assert payload[0] == 2  # index size
    types = [struct.unpack_from("<HH", payload, 1 + 4 * k)[0] for k in range(5)]
    assert types == [1, 3, 4, 5, 6]
    hub = struct.unpack_from("<H", payload, 3)[0]
    assert struct.unpack_from("<IQ", payload, hub) == (7, 7000)


def test_minimal_frame_without_optional_blocks() -> None:
    f = Frame(1, 2, np.ones((9, 3), np.float32), np.zeros((9, 3), np.float32))
    out = FrameDecoder().feed(encode_frame(f))
    assert len(out) == 1
    assert out[0].wrench is None and out[0].slip_state is None and out[0].sensor_state is None


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(frames(), min_size=1, max_size=5))
def test_round_trip(fs: list[Frame]) -> None:
    out = FrameDecoder().feed(b"".join(encode_frame(f) for f in fs))
    assert len(out) == len(fs)
    for a, b in zip(fs, out):
        assert_same(a, b)
        assert b.force.dtype == np.float32 and b.force.shape == (9, 3) and b.disp.shape == (9, 3)


def test_encode_rejects_what_the_wire_cannot_carry() -> None:
    good = simple_frame(1)
    with pytest.raises(ValueError, match="counter"):
        encode_frame(Frame(2**32, 0, good.force, good.disp))
    with pytest.raises(ValueError, match="force"):
        encode_frame(Frame(0, 0, np.zeros((8, 3)), good.disp))


# ---------------------------------------------------------------------- stream handling
@settings(max_examples=60, deadline=None)
@given(st.data())
def test_split_reads_anywhere(data: st.DataObject) -> None:
    stream = b"".join(encode_frame(simple_frame(i)) for i in range(6))
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=40)))
    dec = FrameDecoder()
    out: list[Frame] = []
    prev = 0
    for c in [*cuts, len(stream)]:
        out += dec.feed(stream[prev:c])
        prev = c
    assert [f.counter for f in out] == list(range(6))
    assert dec.garbage_bytes == 0 and dec.errors() == dict.fromkeys(FrameDecoder.ERROR_KINDS, 0)


def test_byte_by_byte() -> None:
    stream = b"".join(encode_frame(simple_frame(i)) for i in range(3))
    dec = FrameDecoder()
    out = [f for b in stream for f in dec.feed(bytes([b]))]
    assert [f.counter for f in out] == [0, 1, 2]


junk = st.lists(
    st.one_of(
        st.binary(max_size=200),
        st.just(START),
        st.just(END),
        st.sampled_from([START[:1], START[:2], START[:3]]),
        # Truncated frames, cut before their end marker: a copy cut inside the marker followed by junk that
        # happens to be the marker (``st.just(END)``) would be a whole, valid frame 999.
        st.integers(1, 433 - len(END) - 1).map(lambda n: encode_frame(simple_frame(999, seed=1))[:n]),
    ),
    max_size=6,
).map(b"".join)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(junk, st.integers(0, 2**32 - 1)), min_size=1, max_size=6), junk)
def test_every_valid_frame_inside_garbage_is_found(parts: list[tuple[bytes, int]], tail: bytes) -> None:
    stream = b""
    sent = []
    for garbage, counter in parts:
        f = simple_frame(counter % 100_000)
        sent.append(f.counter)
        stream += garbage + encode_frame(f)
    stream += tail
    dec = FrameDecoder()
    out = dec.feed(stream)
    # A truncated copy of frame 999 directly before a frame may not swallow it; only sent frames come out.
    assert [f.counter for f in out] == sent


def test_garbage_bytes_are_counted_exactly() -> None:
    rng = np.random.default_rng(1)
    garbage = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes().replace(b"\x55", b"\x00")
    dec = FrameDecoder()
    out = dec.feed(garbage + encode_frame(simple_frame(1)) + garbage[:100] + encode_frame(simple_frame(2)))
    assert [f.counter for f in out] == [1, 2]
    assert dec.garbage_bytes == 5100
    assert dec.errors() == dict.fromkeys(FrameDecoder.ERROR_KINDS, 0)


def test_bad_checksum_is_counted_and_skipped() -> None:
    bad = bytearray(encode_frame(simple_frame(1)))
    bad[50] ^= 0x01  # a value byte: structure intact, sum wrong
    dec = FrameDecoder()
    out = dec.feed(encode_frame(simple_frame(0)) + bytes(bad) + encode_frame(simple_frame(2)))
    assert [f.counter for f in out] == [0, 2]
    assert dec.bad_checksum == 1 and dec.bad_length == 0
    assert dec.garbage_bytes == len(bad)


def test_checksum_error_in_checksum_bytes() -> None:
    bad = bytearray(encode_frame(simple_frame(1)))
    bad[-6] ^= 0xFF
    dec = FrameDecoder()
    assert dec.feed(bytes(bad)) == [] and dec.bad_checksum == 1


def test_wrong_length_is_counted_and_skipped() -> None:
    good = encode_frame(simple_frame(1))
    longer = good[:-6] + b"\x00" + good[-6:]  # stray byte: end marker one byte late
    shorter = good[:-7] + good[-6:]  # lost last payload byte: end marker one byte early
    dec = FrameDecoder()
    out = dec.feed(longer + encode_frame(simple_frame(2)) + shorter + encode_frame(simple_frame(3)))
    assert [f.counter for f in out] == [2, 3]
    assert dec.bad_length == 2


def test_truncated_frame_followed_by_a_good_one() -> None:
    dec = FrameDecoder()
    out = dec.feed(encode_frame(simple_frame(1))[:300] + encode_frame(simple_frame(2)))
    assert [f.counter for f in out] == [2]
    assert dec.bad_length + dec.bad_structure + dec.bad_checksum >= 1


@pytest.mark.parametrize(
    "mangle",
    [
        lambda p: p.__setitem__(0, 3),  # index size 3 does not exist
        lambda p: struct.pack_into("<H", p, 1, 0),  # block type 0
        lambda p: struct.pack_into("<H", p, 3, 3),  # hub offset points into the table
        lambda p: struct.pack_into("<H", p, 9, 3),  # two blocks of type 3
        lambda p: struct.pack_into("<H", p, 3, 3000),  # offset beyond the largest frame
        lambda p: struct.pack_into("<H", p, 33, 2),  # Ns = 2 sensors but the data has one
        lambda p: struct.pack_into("<H", p, 37, 8),  # Np = 8 pillars on sensor 0
        lambda p: struct.pack_into("<H", p, 57, 0x0005),  # wrong pillar record tag
        lambda p: struct.pack_into("<H", p, 39, 900),  # pillar offset outside the payload
    ],
)
def test_structure_errors_are_counted_not_raised(mangle) -> None:
    frame = bytearray(encode_frame(simple_frame(1)))
    payload = bytearray(frame[4:-6])
    mangle(payload)
    bad = START + bytes(payload) + struct.pack("<H", checksum(payload)) + END
    dec = FrameDecoder()
    out = dec.feed(encode_frame(simple_frame(0)) + bad + encode_frame(simple_frame(2)))
    assert [f.counter for f in out] == [0, 2]
    assert dec.bad_structure + dec.bad_length == 1


def test_oversized_frame_is_bad_length() -> None:
    dec = FrameDecoder()
    # A header announcing a pillar block too big for 2048 bytes: 64 pillars per sensor on 8 sensors.
    payload = bytearray(b"\x02") + struct.pack("<HHHH", 1, 9, 3, 21) + bytes(12) + struct.pack("<H", 8) + bytes(2000)
    out = dec.feed(START + bytes(payload) + encode_frame(simple_frame(5)))
    assert [f.counter for f in out] == [5]
    assert dec.bad_length + dec.bad_structure >= 1


def _frame_with_unknown_last_block(counter: int, extra: bytes) -> bytes:
    """A valid frame with a trailing type 7 block (unknown to us): its length must come from the end marker."""
    plain = encode_frame(Frame(counter, 5, np.full((9, 3), 1.5, np.float32), np.zeros((9, 3), np.float32)))
    payload = bytearray(plain[4:-6])
    # Rebuild the table with a third entry: every offset moves 4 bytes on.
    hub_off, pil_off = struct.unpack_from("<H", payload, 3)[0], struct.unpack_from("<H", payload, 7)[0]
    body = payload[hub_off:]
    table = struct.pack("<HHHHHH", 1, hub_off + 4, 3, pil_off + 4, 7, len(payload) + 4)
    # Sub-offsets inside the pillar block are absolute: shift them too.
    body = bytearray(body)
    rel = pil_off - hub_off
    struct.pack_into("<H", body, rel + 2, struct.unpack_from("<H", body, rel + 2)[0] + 4)
    for k in range(9):
        o = rel + 6 + 2 * k
        struct.pack_into("<H", body, o, struct.unpack_from("<H", body, o)[0] + 4)
    new = b"\x02" + table + bytes(body) + extra
    return START + new + struct.pack("<H", sum(new) & 0xFFFF) + END


def test_unknown_trailing_block_ends_at_the_end_marker() -> None:
    dec = FrameDecoder()
    tricky = b"\x01" + END + b"\x07\x08"  # an end marker inside the unknown block must not end the frame
    out = dec.feed(_frame_with_unknown_last_block(3, tricky) + encode_frame(simple_frame(4)))
    assert [f.counter for f in out] == [3, 4]
    assert np.all(out[0].force == 1.5)


def test_buffer_is_reused_not_grown() -> None:
    dec = FrameDecoder()
    buf = dec._buf
    size = len(buf)
    stream = b"".join(encode_frame(simple_frame(i)) for i in range(400))  # 173 kB in one feed
    out = dec.feed(stream)
    assert len(out) == 400 and dec._buf is buf and len(buf) == size
    assert dec.buffered == 0


def test_reset_drops_partial_frame() -> None:
    dec = FrameDecoder()
    data = encode_frame(simple_frame(1))
    assert dec.feed(data[:200]) == []
    dec.reset()
    assert [f.counter for f in dec.feed(data)] == [1]


def test_max_frame_constant() -> None:
    assert MAX_FRAME_BYTES == 2048


# ---------------------------------------------------------------------- commands
def test_commands() -> None:
    assert CMD_BIAS == b"z\n" and CMD_SLIP_ON == b"S\n" and CMD_SLIP_OFF == b"s\n"
    assert [rate_command(hz) for hz in (100, 250, 500, 1000)] == [b"f100\n", b"f250\n", b"f500\n", b"f1000\n"]
    with pytest.raises(ValueError, match="200"):
        rate_command(200)
    assert parse_command(CMD_BIAS) == Command("bias")
    assert parse_command(b"f500") == Command("rate", 500)
    assert parse_command(CMD_SLIP_ON) == Command("slip", True)
    assert parse_command(CMD_SLIP_OFF) == Command("slip", False)
    for bad in (b"f123\n", b"x\n", b"", b"fabc"):
        with pytest.raises(ValueError, match="unknown PapillArray command"):
            parse_command(bad)


# ---------------------------------------------------------------------- fuzz (short)
def test_short_fuzz_run() -> None:
    from sliplab.fuzz_pts import fuzz

    rep = fuzz(1500, seed=1)
    assert rep.exceptions == 0, rep.first_exception
    assert rep.intact_sent > 1000 and rep.intact_missed == 0 and rep.wrong_values == 0
    assert sum(rep.errors.values()) > 0  # the corruptions were really exercised


def _fields(f: Frame) -> tuple:
    return (f.counter, f.t_us, f.force.tobytes(), f.disp.tobytes(), f.wrench.tobytes(), f.slip_state.tobytes(),
            f.friction.tobytes(), f.sensor_state, f.friction_est, f.target_grip_force)


def test_block_decode_equals_frame_by_frame() -> None:
    # A read of many frames is decoded as one block while they share a layout; corrupt frames inside a
    # block (bad checksum, a changed structure byte, a truncated frame, garbage, a different layout)
    # end the block there and are judged as single frames. One big read and frame-sized reads must
    # give the same frames and the same counters.
    parts = [encode_frame(simple_frame(i)) for i in range(40)]
    bad = bytearray(parts[5])
    bad[-len(END) - 2] ^= 0x01  # checksum
    parts[5] = bytes(bad)
    bad = bytearray(parts[12])
    bad[len(START) + 1] ^= 0x40  # index table: a structure byte
    parts[12] = bytes(bad)
    parts[20] = parts[20][:200]  # truncated
    parts[25] = b"\x00\x55\x66" + parts[25]  # garbage before
    parts[30] = encode_frame(Frame(30, 30_000, np.ones((9, 3), np.float32), np.zeros((9, 3), np.float32)))
    stream = b"".join(parts)
    whole = FrameDecoder()
    got = whole.feed(stream)
    single = FrameDecoder()
    ref = [f for p in parts for f in single.feed(p)]
    assert [f.counter for f in got] == [f.counter for f in ref]
    assert 5 not in [f.counter for f in got] and 12 not in [f.counter for f in got]
    assert [_fields(f) for f in got if f.counter != 30] == [_fields(f) for f in ref if f.counter != 30]
    assert (whole.frames, whole.garbage_bytes, whole.errors()) == (single.frames, single.garbage_bytes,
                                                                    single.errors())
    # The frames of one block own views of one array: writing to one frame's force leaves the others.
    a, b = got[2], got[3]
    assert a.force.base is b.force.base  # decoded as one block
    a.force[0, 0] = 123.0
    assert np.array_equal(b.force, simple_frame(3).force) and np.array_equal(b.disp, simple_frame(3).disp)


def test_a_block_whose_byte_sums_pass_65535_decodes_as_frame_by_frame() -> None:
    # A read of whole frames is checked at once, its checksums summed in a 16-bit accumulator that wraps: frames
    # whose payload bytes sum far beyond 2**16 (values of mostly 0xFF bytes) decode as they do one at a time, and a
    # checksum off by one in the middle of such a read is still refused.
    big = np.full((9, 3), np.finfo(np.float32).min, np.float32)  # bytes ff ff 7f ff
    parts = []
    for i in range(8):
        f = simple_frame(i)
        low = float(np.finfo(np.float32).min)
        f.force, f.disp, f.wrench = big.copy(), big.copy(), np.full(6, low, np.float32)
        f.slip_state, f.friction = np.full(9, -1, np.int8), np.full(9, low, np.float32)
        f.sensor_state, f.friction_est, f.target_grip_force = 255, low, low
        parts.append(encode_frame(f))
    assert all(sum(p[len(START) : -len(END) - 2]) > 65536 for p in parts)
    bad = bytearray(parts[4])
    bad[-len(END) - 2] ^= 0x01
    parts[4] = bytes(bad)
    whole, single = FrameDecoder(), FrameDecoder()
    got = whole.feed_block(b"".join(parts))
    ref = [f for p in parts for f in single.feed(p)]
    assert got.counter.tolist() == [f.counter for f in ref] == [0, 1, 2, 3, 5, 6, 7]
    assert np.array_equal(got.force[:, 0].view(np.uint32), np.array([f.force for f in ref]).view(np.uint32))
    assert whole.errors() == single.errors() == {"bad_checksum": 1, "bad_length": 0, "bad_structure": 0}


# ---------------------------------------------------------------------- two arrays
def two_sensor_frame(counter: int) -> Frame:
    f = simple_frame(counter)
    f.friction_est, f.target_grip_force = 0.5, 3.0
    rng = np.random.default_rng(1000 + counter)
    f.others = ((rng.normal(size=(9, 3)).astype(np.float32), rng.normal(size=(9, 3)).astype(np.float32)),)
    return f


def test_two_sensor_frames_round_trip_as_frames_and_as_a_block() -> None:
    fs = [two_sensor_frame(c) for c in range(5)]
    data = b"".join(encode_frame(f) for f in fs)
    assert len(encode_frame(fs[0])) > 433  # the second array's records are on the wire
    out = FrameDecoder(sensors=2).feed(data)
    assert len(out) == 5
    for a, b in zip(fs, out):
        assert_same(a, b)
        assert np.array_equal(a.others[0][0], b.others[0][0]) and np.array_equal(a.others[0][1], b.others[0][1])
    dec = FrameDecoder(sensors=2)
    block = dec.feed_block(data[:-10])  # the last frame incomplete: four now ...
    assert len(block) == 4 and block.force.shape == (4, 2, 9, 3) and block.sensors == 2
    assert block.counter.tolist() == [0, 1, 2, 3]
    assert np.array_equal(block.force[3, 1], fs[3].others[0][0]) and np.array_equal(block.disp[2, 0], fs[2].disp)
    block = dec.feed_block(data[-10:])  # ... and the fifth with the rest
    assert block.counter.tolist() == [4] and np.array_equal(block.force[0, 1], fs[4].others[0][0])


def test_one_sensor_decoder_reads_sensor_0_of_a_two_sensor_frame() -> None:
    f = two_sensor_frame(3)
    out = FrameDecoder().feed(encode_frame(f))
    assert len(out) == 1 and out[0].others == () and np.array_equal(out[0].force, f.force)


def test_a_configured_sensor_the_frames_lack_reads_nan_and_is_counted() -> None:
    dec = FrameDecoder(sensors=2)
    block = dec.feed_block(b"".join(encode_frame(simple_frame(c)) for c in range(3)))
    assert len(block) == 3 and dec.missing_sensor == 3
    assert np.isfinite(block.force[:, 0]).all() and np.isnan(block.force[:, 1]).all()


def test_stashed_bytes_decode_as_if_fed() -> None:
    # A reader holding frames back stashes raw bytes and decodes them later in one pass: the same frames,
    # in order, whatever the split; the undecoded bytes stay bounded (a stash that does not fit is refused);
    # each stash counts the frames its bytes complete (end markers, one split across stashes included).
    rng = np.random.default_rng(0)
    data = b"".join(encode_frame(simple_frame(i)) + (b"\x55\x66" if i % 7 == 0 else b"") for i in range(3000))
    ref = FrameDecoder().feed_block(data).counter.tolist()
    dec, got, pos, refused = FrameDecoder(), [], 0, 0
    while pos < len(data):
        step = int(rng.integers(1, 30000))
        chunk, pos = data[pos : pos + step], pos + step
        if rng.random() < 0.6:
            if dec.stash(chunk) is not None:
                continue
            refused += 1
        got += dec.feed_block(chunk).counter.tolist()
    got += dec.feed_block(b"").counter.tolist()
    assert got == ref and refused > 0 and dec.garbage_bytes == 2 * len(range(0, 3000, 7))
    dec = FrameDecoder()
    frame = encode_frame(simple_frame(1))
    assert dec.stash(frame[:-2]) == 0 and dec.stash(frame[-2:] + frame) == 2  # the split marker counts
    assert dec.feed_block(b"").counter.tolist() == [1, 1]


def test_a_decoder_reading_read_after_read_gives_each_reads_own_frames() -> None:
    # The daemon's reads land at the buffer's start one after the other, the same size again and again: the decoder
    # keeps the views it reads them through. Each read must still give its own frames, across a layout change (a frame
    # without the optional blocks), a read that ends mid-frame, garbage, and reads of other sizes.
    plain = [Frame(c, c * 1000, np.full((9, 3), c, np.float32), np.zeros((9, 3), np.float32)) for c in range(500, 520)]
    frames = [simple_frame(c) for c in range(200)]
    reads = [frames[i : i + 10] for i in range(0, 100, 10)] + [plain[:10], frames[100:110], plain[10:13]]
    reads += [frames[i : i + k] for i, k in ((110, 7), (117, 10), (127, 10), (137, 3), (140, 10))]
    dec = FrameDecoder()
    cut = b""
    for n, read in enumerate(reads):
        data = cut + b"".join(encode_frame(f) for f in read)
        want = ([reads[n - 1][-1]] if cut else []) + read
        cut = b""
        if n == 12:
            data = b"\x00\x55\x66" + data  # garbage first: the frames start elsewhere in the buffer
        if n == 14:  # the read ends 5 bytes short of its last frame's end: the next read brings them
            data, cut, want = data[:-5], data[-5:], want[:-1]
        block = dec.feed_block(data)
        assert block.counter.tolist() == [f.counter for f in want], n
        assert np.array_equal(block.force[:, 0], np.stack([f.force for f in want])), n
        assert np.array_equal(block.disp[:, 0], np.stack([f.disp for f in want])), n
        assert not block.dropped_before.any() and not block.discontinuity.any()
    assert dec.errors() == {"bad_checksum": 0, "bad_length": 0, "bad_structure": 0} and dec.garbage_bytes == 3
