"""The feature pipeline: streaming equals batch bit for bit, median and tare arithmetic."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.detect.features import (
    FeatureSpec,
    FeatureStream,
    batch_windows,
    causal_median,
    stream_windows,
    tare_offset,
    window_labels,
)


def _signal(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n)[:, None, None] / 1000.0
    base = np.sin(2 * np.pi * 3 * t + rng.uniform(0, 6, (1, 9, 3))) * rng.uniform(0.1, 1, (1, 9, 3))
    return (base + rng.normal(0, 0.01, (n, 9, 3))).astype(np.float32)


@pytest.mark.parametrize("stride", [0, 10, 20])
def test_stream_equals_batch_exactly(stride: int) -> None:
    spec = FeatureSpec(stride=stride)
    force = _signal(1337)
    off = tare_offset(force, 0, 100)
    batch, ends = batch_windows(force, spec, off)
    streamed = np.array(stream_windows(force, spec, off))
    assert streamed.shape == batch.shape
    assert np.array_equal(streamed, batch)  # bit-identical, not merely close
    assert ends[0] == spec.window - 1 and np.all(np.diff(ends) == spec.step)


def test_stream_equals_batch_with_nonfinite_and_absurd_values() -> None:
    spec = FeatureSpec()
    force = _signal(800, seed=3)
    force[5, 2, 0] = np.nan
    force[100:130, 4, :] = np.inf
    force[300, :, 1] = -np.inf
    force[400, 1, 0] = 1e6
    force[0, 7, 1] = np.nan  # non-finite on the very first sample: held at 0
    batch, _ = batch_windows(force, spec)
    fs = FeatureStream(spec)
    streamed = [w for s in force if (w := fs.push(s)) is not None]
    assert np.array_equal(np.array(streamed), batch)
    assert np.isfinite(batch).all()
    assert fs.nonfinite_count == 1 + 30 * 3 + 9 + 1


def test_window_is_time_major_and_pillar_major() -> None:
    # A ramp whose value encodes (sample, pillar, channel) so the layout can be read back.
    spec = FeatureSpec(median=1)
    n = 40
    force = np.zeros((n, 9, 3), np.float32)
    for p in range(9):
        for c in range(3):
            # Kept below the 8 N clip bound: sample * 0.1 + pillar * 0.01 + channel * 0.001.
            force[:, p, c] = np.arange(n) * 0.1 + p * 0.01 + c * 0.001
    (win,), _ = batch_windows(force, spec)
    w = win.reshape(40, 16)

    def code(sample: int, pillar: int, ch: int) -> np.float32:
        return np.float32(sample * 0.1 + pillar * 0.01 + ch * 0.001)

    assert w[0, 0] == code(0, 0, 0)  # sample 0, pillar P0, fx
    assert w[0, 1] == code(0, 0, 1)  # sample 0, pillar P0, fy
    assert w[0, 6] == code(0, 3, 0)  # fourth pillar in OUTER order is P3
    assert w[0, 8] == code(0, 5, 0)  # then P5: the centre P4 is skipped
    assert w[39, 15] == code(39, 8, 1)


def test_median_removes_short_glitches_exactly() -> None:
    # A naive (non-median or even-width) filter would leave part of the spike in the output.
    x = np.full((200, 1), 0.5, np.float32)
    x[50:60, 0] = 4.0  # a 10-sample spike: shorter than half of the 21-sample window
    x[120, 0] = -3.0
    y = causal_median(x, 21)
    assert np.array_equal(y, np.full_like(x, 0.5))


@pytest.mark.parametrize("width", [7, 21, 4])
def test_every_width_gives_np_medians_values(width: int) -> None:
    """The selection for odd widths other than 3 and 5, and np.median itself for even ones: the values of np.median
    over the same runs, bit for bit (ties, repeated values and a block shorter than a run's width included)."""
    from numpy.lib.stride_tricks import sliding_window_view

    from slipd.detect.features import sliding_median

    rng = np.random.default_rng(width)
    hist = np.round(rng.normal(size=(60, 27)), 1).astype(np.float32)  # (rounded: many ties)
    hist[10:30, 3] = 0.25
    for rows in (hist, hist[: width + 2]):
        want = np.median(sliding_window_view(rows, width, axis=0), axis=-1).astype(np.float32)
        assert np.array_equal(sliding_median(rows, width), want)
        out = np.empty_like(want)
        assert sliding_median(rows, width, out) is out and np.array_equal(out, want)


def test_median_start_of_stream_is_edge_padded() -> None:
    x = np.arange(30, dtype=np.float32)[:, None]
    y = causal_median(x, 21)
    # Sample k's history is 20-k copies of x[0] and x[0..k]; its median is x[max(0, k - 10)].
    assert [float(v) for v in y[:12, 0]] == [0.0] * 11 + [1.0]
    assert float(y[25, 0]) == 15.0


def test_tare_with_large_offset_does_not_bias() -> None:
    force = _signal(2000, seed=5) * 0.01
    force += np.float32(1234.5)  # sensor not zeroed
    off = tare_offset(force, 0, 2000)
    assert off.dtype == np.float32
    tared = force.astype(np.float64) - off
    assert abs(tared.mean()) < 1e-3


def test_window_labels_take_last_sample() -> None:
    spec = FeatureSpec()
    label = np.zeros(200, np.uint8)
    label[79] = 1
    _, ends = batch_windows(np.zeros((200, 9, 3), np.float32), spec)
    assert window_labels(label, ends).tolist() == [0, 1, 0, 0, 0]


def test_util_channel_is_friction_utilisation_of_filtered_forces() -> None:
    # util = |Ft| / max(Fz, 0.5 N) of the median-filtered forces, in the spec's channel order, pillar-major.
    spec = FeatureSpec(pillars=(4, 0), channels=("util", "fx"), median=5, window=10)
    n = 30
    force = np.zeros((n, 9, 3), np.float32)
    force[:, 4] = [0.3, 0.4, 2.0]  # |Ft| 0.5 over Fz 2: 0.25
    force[:, 0] = [0.06, 0.08, 0.1]  # off the surface: |Ft| 0.1 over the 0.5 N floor: 0.2
    force[17, 4, 2] = 100.0  # one glitch: the median removes it before the division
    win, _ = batch_windows(force, spec)
    rows = win.reshape(len(win), spec.window, 4)
    assert np.allclose(rows[..., 0], 0.25) and np.allclose(rows[..., 1], 0.3)
    assert np.allclose(rows[..., 2], 0.2) and np.allclose(rows[..., 3], 0.06)
    assert spec.n_base == 6 and spec.input_size == 40
    logs, _ = batch_windows(force, spec.with_(channels=("lutil",)))
    assert np.allclose(logs.reshape(-1, 2), np.log([0.25, 0.2]))
    vec, _ = batch_windows(force, spec.with_(channels=("ux", "uy")))
    assert np.allclose(vec.reshape(-1, 2, 2), [[0.15, 0.2], [0.12, 0.16]])  # (fx, fy) / max(Fz, 0.5 N)
    force[:, 0] = 0.0  # no load at all: the floor, not -inf
    logs, _ = batch_windows(force, spec.with_(channels=("lutil",)))
    assert np.allclose(logs.reshape(-1, 2), np.log([0.25, 0.01]))


def test_grasp_normalised_channels_divide_by_the_whole_grasps_normal_load() -> None:
    # gft = |Ft| / max(sum of Fz over the spec's pillars, 0.5 N); gfz = Fz / the same sum.
    spec = FeatureSpec(pillars=(4, 0), channels=("gft", "gfz"), median=5, window=10)
    force = np.zeros((30, 9, 3), np.float32)
    force[:, 4] = [0.3, 0.4, 1.5]
    force[:, 0] = [0.06, 0.08, 0.5]
    force[:, 8] = [1.0, 1.0, 9.0]  # not among the spec's pillars: not in the sum
    win, _ = batch_windows(force, spec)
    assert np.allclose(win.reshape(-1, 2, 2), [[0.25, 0.75], [0.05, 0.25]])
    light = force * np.float32(0.5)  # a grasp half as strong (still above the floor) reads the same
    assert np.allclose(batch_windows(light, spec)[0], win)
    force[:] = 0.0  # unloaded: the floor, not a division by zero
    assert np.all(np.isfinite(batch_windows(force, spec)[0]))


def test_rspeed_is_each_pillars_deflection_speed_over_the_fastest_pillars() -> None:
    # Pillar 4 loads at 0.01 N per sample along x, pillar 0 at a quarter of that, pillar 8 (not in the spec) faster:
    # over the 10-sample lag 0.1 N and 0.025 N, so 1 and 0.25 once a window holds ten samples of history.
    spec = FeatureSpec(pillars=(4, 0), channels=("rspeed",), median=1, window=20, stride=10)
    n = 60
    ramp = np.arange(n, dtype=np.float32)
    force = np.zeros((n, 9, 3), np.float32)
    force[:, 4, 0] = 0.01 * ramp
    force[:, 0, 1] = 0.0025 * ramp
    force[:, 8, 0] = 0.5 * ramp
    win, _ = batch_windows(force, spec)
    rows = win.reshape(len(win), spec.window, 2)
    assert np.allclose(rows[:, 10:], [1.0, 0.25], atol=1e-5)
    assert np.allclose(rows[:, 0], 0.0)  # the window's first sample has no earlier one within the window
    # Scale-free: ten times the loads, the same ratios; a still grasp: changes over the floor, near 0.
    strong = batch_windows(force * np.float32(10), spec)[0].reshape(len(win), spec.window, 2)
    assert np.allclose(strong[:, 10:], rows[:, 10:], atol=1e-5)
    force[:] = 0.3
    assert np.allclose(batch_windows(force, spec)[0], 0.0)


def test_spec_roundtrip_and_validation() -> None:
    spec = FeatureSpec(stride=20)
    assert FeatureSpec.from_dict(spec.to_dict()) == spec
    with pytest.raises(ValueError):
        FeatureSpec(median=20)
    with pytest.raises(ValueError):
        FeatureSpec(pillars=(0, 9))
    with pytest.raises(TypeError):
        FeatureSpec.from_dict({**spec.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="distinct"):
        FeatureSpec(channels=("fx", "fx"))
    with pytest.raises(ValueError):
        FeatureSpec(channels=("dx",))
    derived = FeatureSpec(channels=("fx", "fy", "util"))
    assert FeatureSpec.from_dict(derived.to_dict()) == derived


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 300),
    window=st.sampled_from([10, 20, 40]),
    median=st.sampled_from([1, 5, 11, 21]),
    seed=st.integers(0, 2**16),
    channels=st.sampled_from([("fx", "fy"), ("fx", "fy", "util"), ("util", "fz"), ("lutil",), ("ux", "uy", "util"),
                              ("util", "rspeed"), ("rspeed",), ("util", "gft", "gfz"), ("gutil",),
                              ("gutil", "gfz")]),
)
def test_stream_equals_batch_property(n: int, window: int, median: int, seed: int, channels: tuple) -> None:
    spec = FeatureSpec(window=window, median=median, channels=channels)
    force = _signal(n, seed) if n else np.zeros((0, 9, 3), np.float32)
    batch, _ = batch_windows(force, spec)
    streamed = stream_windows(force, spec)
    assert len(streamed) == len(batch)
    if streamed:
        assert np.array_equal(np.array(streamed), batch)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 300),
    stride=st.sampled_from([0, 10, 20]),
    median=st.sampled_from([1, 5, 21]),
    blocks=st.lists(st.integers(1, 150), min_size=1, max_size=20),
    seed=st.integers(0, 2**16),
    glitches=st.booleans(),
    derived=st.booleans(),
)
def test_push_many_equals_push_and_batch(n: int, stride: int, median: int, blocks: list[int], seed: int,
                                         glitches: bool, derived: bool) -> None:
    # Blocks of any size (1 to more than the history) give the windows, at the same samples, and the
    # counters that push gives sample by sample, and the batch windows.
    channels = ("fx", "fy", "util") if derived else ("fx", "fy")
    if derived and seed % 2:
        channels = ("util", "rspeed")  # a channel that reads earlier samples of its window
    spec = FeatureSpec(stride=stride, median=median, channels=channels)
    force = _signal(n, seed) if n else np.zeros((0, 9, 3), np.float32)
    if glitches and n > 10:
        rng = np.random.default_rng(seed)
        for v in (np.nan, np.inf, -np.inf, 1e6, -1e6):
            force[rng.integers(0, n), rng.integers(0, 9), rng.integers(0, 3)] = v
        force[: rng.integers(1, 6), 3, 1] = np.nan  # non-finite from the first sample: held at 0
    one, many = FeatureStream(spec), FeatureStream(spec)
    ref = [(i, w) for i, s in enumerate(force) if (w := one.push(s)) is not None]
    got, pos, k = [], 0, 0
    while pos < n:
        size = blocks[k % len(blocks)]
        got += [(pos + i, w) for i, w in many.push_many(force[pos : pos + size])]
        pos, k = pos + size, k + 1
    assert [i for i, _ in got] == [i for i, _ in ref]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(got, ref, strict=True))
    assert (many.nonfinite_count, many.clipped_count, many.samples_seen) == (
        one.nonfinite_count, one.clipped_count, one.samples_seen)
    batch, ends = batch_windows(force, spec)
    assert [i for i, _ in got] == ends.tolist()
    if got:
        assert np.array_equal(np.array([w for _, w in got]), batch)


def test_push_many_then_push_continue_one_stream() -> None:
    spec = FeatureSpec(stride=10)
    force = _signal(200, seed=7)
    fs = FeatureStream(spec)
    got = [w for _, w in fs.push_many(force[:73])]
    got += [w for s in force[73:] if (w := fs.push(s)) is not None]
    assert np.array_equal(np.array(got), batch_windows(force, spec)[0])
    assert fs.push_many(np.zeros((0, 9, 3), np.float32)) == []


def test_util_alone_derives_the_same_values_as_beside_other_channels() -> None:
    """The shipped layout (``util`` alone) takes a shorter path on the hot path: the same float32 values, bit for
    bit, as ``util`` computed beside another channel, and a NaN-free floor under the normal force."""
    from slipd.detect.features import UTIL_FLOOR_N

    rng = np.random.default_rng(3)
    filtered = rng.normal(0, 1, (40, 27)).astype(np.float32)
    filtered[5, 2] = 0.0  # a pillar with no normal force: the floor applies
    nine = tuple(range(9))
    alone = FeatureSpec(window=40, stride=10, pillars=nine, channels=("util",)).derive(filtered)
    beside = FeatureSpec(window=40, stride=10, pillars=nine, channels=("util", "fz")).derive(filtered)
    beside = beside.reshape(40, 9, 2)[:, :, 0]
    assert alone.dtype == np.float32 and alone.shape == (40, 9)
    assert np.array_equal(alone, beside)
    f = filtered.reshape(40, 9, 3)
    assert alone[5, 0] == np.float32(np.hypot(f[5, 0, 0], f[5, 0, 1]) / np.float32(UTIL_FLOOR_N))


def _not_the_short_path(*_: object) -> None:
    raise AssertionError("the general per-channel path ran where the kept calls should")


KEPT = [("gutil",), ("gutil", "gfz")]
"""The kept paths of ``gutil`` (alone, and with the contact's spread beside it), each checked against the general
per-channel path on the same channels with ``fz`` after them."""


@pytest.mark.parametrize("channels", KEPT)
@pytest.mark.parametrize("rows", [1, 7, 40, 333])
def test_gutil_kept_path_derives_the_same_values_as_the_general_path(rows: int, channels: tuple, monkeypatch) -> None:
    """``gutil`` alone, or with ``gfz``, takes the shorter path ``util`` alone takes: the same float32 values, bit for
    bit, as the same channels computed beside another, on grasps from under the floor's minimum to firm ones."""
    rng = np.random.default_rng(rows)
    filtered = rng.normal(0, 0.2, (rows, 27)).astype(np.float32)
    filtered[:, 2::3] = np.abs(filtered[:, 2::3]) * rng.uniform(0.01, 20, (rows, 1)).astype(np.float32)
    filtered[0, 2::3] = 0.0  # no normal load at all: every floor applies
    nine, c = tuple(range(9)), len(channels)
    beside = FeatureSpec(window=40, stride=10, pillars=nine, channels=(*channels, "fz")).derive(filtered)
    monkeypatch.setattr(FeatureSpec, "_derive_parts", _not_the_short_path)
    kept = FeatureSpec(window=40, stride=10, pillars=nine, channels=channels).derive(filtered)
    assert kept.dtype == np.float32 and kept.shape == (rows, 9 * c)
    assert np.array_equal(kept, beside.reshape(rows, 9, c + 1)[:, :, :c].reshape(rows, 9 * c))


@pytest.mark.parametrize("channels", KEPT)
def test_gutil_kept_path_streams_the_windows_of_the_general_path(channels: tuple, monkeypatch) -> None:
    """The feature stream's prepared calls for ``gutil`` alone or with ``gfz`` (one block position after another)
    give the windows of the general path, bit for bit."""
    force = _signal(900, seed=4) * np.geomspace(0.02, 8, 900, dtype=np.float32)[:, None, None]
    nine, c = tuple(range(9)), len(channels)
    beside = np.array(stream_windows(force, FeatureSpec(stride=10, pillars=nine, channels=(*channels, "fz"))))
    monkeypatch.setattr(FeatureSpec, "_derive_parts", _not_the_short_path)
    kept = np.array(stream_windows(force, FeatureSpec(stride=10, pillars=nine, channels=channels)))
    assert len(kept) > 50
    assert np.array_equal(kept, beside.reshape(len(beside), -1, 9, c + 1)[..., :c].reshape(len(beside), -1))


@pytest.mark.parametrize("channels", KEPT)
def test_gutil_kept_path_for_two_fingers_at_once_gives_each_fingers_windows(channels: tuple) -> None:
    """A gripper's two fingers through one ``StreamGroup`` (the rows of both side by side, one pass): on ``gutil``
    (and ``gfz``) each finger's floor and load come from its own grasp, so the group's windows are each finger's own,
    bit for bit."""
    from slipd.detect.features import StreamGroup

    spec = FeatureSpec(stride=10, median=5, pillars=tuple(range(9)), channels=channels)
    light = _signal(700, seed=1) * np.float32(0.05)  # a light grasp on one finger, a firm one on the other
    force = np.stack([light, _signal(700, seed=2) * np.float32(4.0)], axis=1)
    alone = [FeatureStream(spec, np.zeros((9, 3), np.float32)) for _ in range(2)]
    together = [FeatureStream(spec, np.zeros((9, 3), np.float32)) for _ in range(2)]
    group = StreamGroup(together)
    cuts = [0, 60, *range(70, 700, 13), 700]
    grouped_windows = 0
    for a, b in itertools.pairwise(cuts):
        want = [[w.copy() for _, w, _, _ in st.push_views(force[a:b, s])] for s, st in enumerate(alone)]
        got = group.push_views(force[a:b])
        if got is None:  # (not the common block: each stream on its own, as the detectors do)
            got_each = [[w.copy() for _, w, _, _ in st.push_views(force[a:b, s])] for s, st in enumerate(together)]
            assert all(np.array_equal(x, y) for g, w in zip(got_each, want) for x, y in zip(g, w, strict=True))
            continue
        for m, (_, windows, _, _) in enumerate(got):
            rows = windows.reshape(spec.window, 2, -1)
            for s in range(2):
                assert np.array_equal(rows[:, s].reshape(-1), want[s][m])
            grouped_windows += 1
    assert grouped_windows > 40


def test_gutil_is_util_on_a_firm_grasp_and_a_light_grasps_friction_on_light_pillars() -> None:
    # Floor: min(0.5 N, mean Fz over the spec's pillars), at least 0.05 N.
    spec = FeatureSpec(pillars=(4, 0), channels=("gutil", "util"), median=5, window=10)
    force = np.zeros((30, 9, 3), np.float32)
    force[:, 4] = [0.3, 0.4, 4.0]  # firm: mean 2.05 N, the contact threshold's floor
    force[:, 0] = [0.06, 0.08, 0.1]
    firm, _ = batch_windows(force, spec)
    assert np.allclose(firm.reshape(-1, 2, 2)[..., 0], firm.reshape(-1, 2, 2)[..., 1])  # util
    light = np.zeros_like(force)
    light[:, 4] = [0.12, 0.16, 0.25]  # a light grasp sliding at 0.8 on both pillars: mean 0.225 N
    light[:, 0] = [0.096, 0.128, 0.2]
    win, _ = batch_windows(light, spec)
    rows = win.reshape(-1, 2, 2)
    # pillar 4 over its own 0.25 N: the friction, 0.8; pillar 0 (0.2 N, under the mean) over the mean: understated,
    # never overstated
    assert np.allclose(rows[..., 0], [0.8, 0.16 / 0.225], atol=1e-5)
    assert np.allclose(rows[..., 1], [0.4, 0.32])  # util reads |Ft| / 0.5 N
    light[:] = 0.0
    assert np.all(np.isfinite(batch_windows(light, spec)[0]))
