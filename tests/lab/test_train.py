"""Training and augmentation: each augmentation does what it claims; --tiny trains loadable members."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from slipd.detect.features import FeatureSpec, batch_windows, tare_offset
from slipd.geometry import N_PILLARS, OUTER
from slipd.recording import Recording, RecordingError
from sliplab import augment as A
from sliplab import train as T
from sliplab.model import SlipNet

TARE = (0, 100)


def synthetic_recording(rng: np.random.Generator, n: int = 1200, kind: str = "slip") -> Recording:
    """A crude stick-slip sequence: press, then a lateral ramp; pillars saturate at mu * fz one by one.

    Shorter pillars (corners, then edges) carry less normal force, so they reach the friction limit
    first: the incipient-slip span runs from the first to the last outer pillar sliding. A "stop"
    recording halts the ramp before any pillar slides.
    """
    t = np.arange(n)
    bias = rng.normal(0.0, 0.3, size=(N_PILLARS, 3)).astype(np.float32)  # an untared sensor offset
    press = np.clip((t - 150) / 200.0, 0.0, 1.0)
    base = np.array([0.5, 0.8, 0.5, 0.8, 1.2, 0.8, 0.5, 0.8, 0.5]) + rng.uniform(-0.15, 0.15, N_PILLARS)
    fz_peak = rng.uniform(1.0, 2.0) * base
    fz = press[:, None] * fz_peak[None, :]
    mu = 0.8 * rng.uniform(0.9, 1.1, N_PILLARS)
    theta = rng.uniform(0, 2 * np.pi)
    move0 = 400
    limit = mu * fz + 1e-9
    # Tangential force asked per sample (N): every outer pillar slides before the end of the recording.
    rate = rng.uniform(1.2, 2.5) * (mu * fz_peak)[list(OUTER)].max() / (n - move0)
    # A stop halts while the least-loaded pillar is at 60 % of its friction limit.
    stop_at = n if kind == "slip" else move0 + int(0.6 * (mu * fz_peak).min() / rate)
    travel = np.clip(t, move0, stop_at) - move0
    demand = travel[:, None] * rate * np.ones(N_PILLARS)
    slip = (demand >= limit) & (t[:, None] >= move0) & (t[:, None] < stop_at)
    slip[:, 4] = False  # the centre pillar (tallest, most loaded) sticks in this toy
    ft = np.where(slip, 0.85 * limit, np.minimum(demand, limit))
    force = np.zeros((n, N_PILLARS, 3), np.float32)
    force[..., 0] = ft * np.cos(theta)
    force[..., 1] = ft * np.sin(theta)
    force[..., 2] = fz
    force += bias + rng.normal(0.0, 0.01, size=force.shape).astype(np.float32)
    label = A.label_from_slip(slip)
    return Recording(t_us=t * 1000, force=force, disp=np.zeros_like(force), slip=slip, label=label,
                     meta={"kind": kind, "tare_samples": list(TARE)})


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("recs")
    for i in range(8):
        synthetic_recording(rng, kind="stop" if i % 4 == 3 else "slip").save(folder / f"rec_{i:03d}.npz")
    (folder / "index.json").write_text(json.dumps({"summary": {"recordings": 8, "generator": "test"}}))
    return folder


def _seq(rng: np.random.Generator, n: int = 1200, kind: str = "slip") -> A.Seq:
    rec = synthetic_recording(rng, n, kind)
    return A.Seq(rec.force - tare_offset(rec.force, *TARE), rec.label, rec.slip)


# ---------------------------------------------------------------------------------- augmentations
def test_synthetic_recordings_have_an_incipient_span() -> None:
    rec = synthetic_recording(np.random.default_rng(1))
    assert 0 < rec.label.sum() < len(rec) / 2
    assert not synthetic_recording(np.random.default_rng(1), kind="stop").label.any()


def test_taring_before_the_pipeline_equals_the_pipelines_own_tare() -> None:
    rec = synthetic_recording(np.random.default_rng(2))
    spec = FeatureSpec()
    offset = tare_offset(rec.force, *TARE)
    direct, ends_a = batch_windows(rec.force, spec, offset)
    pre, ends_b = batch_windows(rec.force - offset, spec, None)
    np.testing.assert_array_equal(direct, pre)
    np.testing.assert_array_equal(ends_a, ends_b)


def test_rotation_preserves_magnitude_and_rotates_fx_fy() -> None:
    seq = _seq(np.random.default_rng(3))
    theta = 1.1
    rot = A.rotate_forces(seq, theta)
    mag = np.hypot(seq.force[..., 0], seq.force[..., 1])
    np.testing.assert_allclose(np.hypot(rot.force[..., 0], rot.force[..., 1]), mag, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(rot.force[..., 2], seq.force[..., 2])
    big = mag > 0.5  # angle is well defined only for a clear tangential force
    turned = np.angle((rot.force[..., 0] + 1j * rot.force[..., 1])[big]) - np.angle(
        (seq.force[..., 0] + 1j * seq.force[..., 1])[big])
    np.testing.assert_allclose(np.angle(np.exp(1j * (turned - theta))), 0.0, atol=1e-5)
    np.testing.assert_array_equal(rot.label, seq.label)


def test_grid90_moves_pillars_with_their_forces() -> None:
    seq = _seq(np.random.default_rng(4))
    perm = A.grid90_permutation(1)
    assert perm[4] == 4 and sorted(perm) == list(range(9))
    # 90 degrees CCW: the pillar at (7, 7) (P0) moves to (-7, 7) (P2).
    assert perm[2] == 0
    rot = A.rotate_grid_90(seq, 1)
    np.testing.assert_allclose(rot.force[:, 2, 0], -seq.force[:, 0, 1], atol=1e-6)
    np.testing.assert_allclose(rot.force[:, 2, 1], seq.force[:, 0, 0], atol=1e-6)
    np.testing.assert_array_equal(rot.slip[:, 2], seq.slip[:, 0])
    four = A.rotate_grid_90(A.rotate_grid_90(rot, 1), 2)
    np.testing.assert_allclose(four.force, seq.force, atol=1e-5)


@pytest.mark.parametrize("rate", A.SPEED_RATES)
def test_speed_variation_shortens_by_the_rate_and_keeps_labels_aligned(rate: float) -> None:
    seq = _seq(np.random.default_rng(5))
    # Tag each sample so we can find where it came from: fz of pillar 4 = its original index.
    seq.force[:, 4, 2] = np.arange(len(seq))
    out = A.drop_samples(seq, rate, np.random.default_rng(0))
    assert len(out) == len(seq) - round(rate * len(seq))
    src = out.force[:, 4, 2].astype(int)
    assert np.all(np.diff(src) > 0)  # order kept, no repeats
    np.testing.assert_array_equal(out.label, seq.label[src])
    np.testing.assert_array_equal(out.slip, seq.slip[src])
    np.testing.assert_array_equal(out.force, seq.force[src])


def test_unloaded_pillars_become_small_noise_and_stop_slipping() -> None:
    seq = _seq(np.random.default_rng(6), n=4000)
    rng = np.random.default_rng(0)
    hits = 0
    trials = 400
    for _ in range(trials):
        out = A.unload_pillars(seq, rng)
        if out is seq:
            continue
        hits += 1
        gone = np.flatnonzero(~out.loaded)
        assert 1 <= len(gone) <= 3
        noise = out.force[:, gone]
        assert abs(noise.mean()) < 2e-4 and 0.0008 < noise.std() < 0.0012
        assert not out.slip[:, gone].any()
        kept = [p for p in OUTER if out.loaded[p]]
        np.testing.assert_array_equal(out.label, A.label_from_slip(out.slip, kept))
        np.testing.assert_array_equal(out.force[:, out.loaded], seq.force[:, out.loaded])
    assert 0.15 < hits / trials < 0.25  # p = 0.2


def test_a_contact_shape_keeps_its_pillars_and_the_slip_on_them() -> None:
    seq = _seq(np.random.default_rng(6), n=4000)
    rng = np.random.default_rng(1)
    seen = 0
    for _ in range(200):
        out = A.contact_shape(seq, rng)
        if out is seq:
            continue
        seen += 1
        kept = np.flatnonzero(out.loaded)
        assert tuple(kept) in A.CONTACT_SHAPES
        np.testing.assert_array_equal(out.force[:, kept], seq.force[:, kept])
        assert np.abs(out.force[:, ~out.loaded]).max() < 0.01 and not out.slip[:, ~out.loaded].any()
        sliding = out.slip.any(axis=1)
        # The label is the original one from the first sample a kept pillar slides, 0 before it.
        first = int(np.argmax(sliding)) if sliding.any() else len(seq)
        assert not out.label[:first].any()
        np.testing.assert_array_equal(out.label[first:], seq.label[first:])
    assert 30 < seen < 70  # p = 0.25


def test_the_sensor_model_scales_leaks_and_filters_but_keeps_the_truth() -> None:
    seq = _seq(np.random.default_rng(6), n=2000)
    out = A.sensor_model(seq, np.random.default_rng(2))
    assert out.force.shape == seq.force.shape and out.force.dtype == np.float32
    np.testing.assert_array_equal(out.label, seq.label)
    ratio = np.abs(out.force[:, :, 2]).sum(0) / np.abs(seq.force[:, :, 2]).sum(0)
    assert (ratio > 0.7).all() and (ratio < 1.4).all() and not np.allclose(ratio, 1.0)
    # A constant load stays a constant load (the filter starts at rest on the first sample).
    still = A.Seq(np.ones((300, 9, 3), np.float32), np.zeros(300, np.uint8), None)
    for k in range(6):
        o = A.sensor_model(still, np.random.default_rng(k))
        np.testing.assert_allclose(o.force, np.broadcast_to(o.force[:1], o.force.shape), rtol=1e-5)


def test_friction_scales_every_tangential_force_by_one_gain_and_keeps_the_rest() -> None:
    seq = _seq(np.random.default_rng(6), n=500)
    gains = []
    for k in range(40):
        out = A.friction_scale(seq, np.random.default_rng(k), p=1.0)
        np.testing.assert_array_equal(out.force[:, :, 2], seq.force[:, :, 2])
        np.testing.assert_array_equal(out.label, seq.label)
        g = out.force[:, :, :2] / np.where(seq.force[:, :, :2] == 0, 1.0, seq.force[:, :, :2])
        g = g[seq.force[:, :, :2] != 0]
        np.testing.assert_allclose(g, g[0], rtol=1e-5)  # one gain for every pillar, axis and sample
        gains.append(float(g[0]))
    assert min(gains) >= A.FRICTION_GAIN[0] and max(gains) <= A.FRICTION_GAIN[1]
    assert min(gains) < 1.0 < max(gains)  # both more and less friction are drawn
    assert A.friction_scale(seq, np.random.default_rng(3), p=0.0) is seq


def test_zero_offset_moves_each_pillar_and_axis_by_one_constant_at_the_noise_scale() -> None:
    seq = _seq(np.random.default_rng(6), n=500)
    errs = []
    for k in range(200):
        out = A.zero_offset(seq, np.random.default_rng(k), p=1.0)
        d = seq.force - out.force
        np.testing.assert_allclose(d, d[:1].repeat(len(d), 0), atol=1e-5)  # constant in time: a zero, not a drift
        np.testing.assert_array_equal(out.label, seq.label)
        errs.append(d[0])
    e = np.abs(np.stack(errs))  # [200, 9, 3]
    # Each axis at its own scale: the normal's error about twice the tangential's, both within a few noise samples.
    ratio = e[:, :, 2].mean() / e[:, :, :2].mean()
    assert 1.6 < ratio < 2.5, ratio
    assert e[:, :, 2].max() < 6 * A.ZERO_SCALE[1] * A.SENSOR_NOISE_N[0]
    assert 0.5 * A.SENSOR_NOISE_N[0] < e[:, :, 2].mean() / np.sqrt(2 / np.pi) < 2.0 * A.SENSOR_NOISE_N[0]
    assert A.zero_offset(seq, np.random.default_rng(3), p=0.0) is seq


def test_stretch_plays_a_sequence_slower_with_its_labels() -> None:
    seq = _seq(np.random.default_rng(6), n=1000)
    out = A.stretch(seq, np.random.default_rng(3), p=1.0)
    f = (len(out) - 1) / (len(seq) - 1)
    assert 1.5 <= f <= 3.0
    # The labelled span keeps its place in time, scaled by the same factor.
    on, on2 = int(np.argmax(seq.label > 0)), int(np.argmax(out.label > 0))
    assert abs(on2 - on * f) <= 1.0 and abs(out.label.sum() - seq.label.sum() * f) <= f + 1
    assert A.stretch(seq, np.random.default_rng(3), p=0.0) is seq


def test_mixing_takes_pillars_from_sources_and_relabels_from_slip_truth() -> None:
    rng = np.random.default_rng(8)
    sources = [_seq(rng, n=1000 + 50 * i, kind="stop" if i % 3 == 0 else "slip") for i in range(9)]
    for i, s in enumerate(sources):
        s.force[:, :, 2] += 1000.0 * (i + 1)  # fz identifies the source recording (before any scaling)
    for seed in range(20):
        out = A.mix_pillars(sources, np.random.default_rng(seed))
        assert len(out) == 1000  # cut to the shortest source
        np.testing.assert_array_equal(out.label, A.label_from_slip(out.slip, OUTER))
        # Every position holds a whole pillar sequence of one source, maybe scaled by [0.2, 2].
        used = set()
        for pos in range(N_PILLARS):
            col = out.force[:, pos]
            match = None
            for i, s in enumerate(sources):
                for p in range(N_PILLARS):
                    ref = s.force[:1000, p]
                    k = float(col[0, 2] / ref[0, 2])
                    if 0.2 - 1e-6 <= k <= 2.0 + 1e-6 and np.allclose(col, ref * k, rtol=1e-4, atol=1e-4):
                        match = (i, p)
                        np.testing.assert_array_equal(out.slip[:, pos], s.slip[:1000, p])
            assert match is not None
            used.add(match[0])
        assert len(used) == 9  # nine different recordings
    with pytest.raises(ValueError, match="slip truth"):
        A.mix_pillars([A.Seq(sources[0].force, sources[0].label, None)], np.random.default_rng(0))


def test_label_rule_some_but_not_all() -> None:
    slip = np.zeros((4, 9), bool)
    slip[1, 0] = True
    slip[2, list(OUTER)] = True
    slip[3, 4] = True  # only the centre: not considered
    np.testing.assert_array_equal(A.label_from_slip(slip), [0, 1, 0, 0])
    np.testing.assert_array_equal(A.label_from_slip(slip, []), [0, 0, 0, 0])


def test_bootstrap_is_forty_percent_with_replacement() -> None:
    rng = np.random.default_rng(0)
    idx = T.bootstrap_indices(300, 0.4, rng)
    assert len(idx) == 120 and idx.min() >= 0 and idx.max() < 300
    draws = [T.bootstrap_indices(300, 0.4, rng) for _ in range(20)]
    assert any(len(np.unique(d)) < len(d) for d in draws)  # repeats happen: with replacement
    assert not all(np.array_equal(draws[0], d) for d in draws[1:])  # re-drawn each time


def test_pack_lanes_resets_h_at_each_sequence_start() -> None:
    items = [T.Item(np.full((k, 3), i, np.float32), np.full(k, i % 2, np.int64)) for i, k in enumerate([5, 3, 4, 2])]
    lanes = T.pack_lanes(items, 2, np.random.default_rng(0))
    assert lanes.x.shape[0] == 2 and int(lanes.valid.sum()) == 14
    assert int((lanes.keep == 0).sum()) == 4
    # every window of every sequence is present exactly once
    got = sorted(lanes.x[..., 0][lanes.valid].tolist())
    assert got == sorted(float(i) for i, k in enumerate([5, 3, 4, 2]) for _ in range(k))


# ----------------------------------------------------------------------------------------- train
def test_tiny_training_writes_loadable_members(data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert T.main(["--data", str(data_dir), "--out", str(out), "--tiny", "--quiet", "--seed", "3",
                   "--threads", "1"]) == 0
    for k in range(2):
        ckpt = torch.load(out / f"member_{k}.pt", map_location="cpu", weights_only=False)
        assert set(ckpt) >= {"state_dict", "config", "feature_spec", "provenance", "history"}
        assert FeatureSpec.from_dict(ckpt["feature_spec"]) == FeatureSpec()
        net = SlipNet(**ckpt["config"])
        net.load_state_dict(ckpt["state_dict"])
        assert ckpt["config"]["input_size"] == 640 and ckpt["config"]["hidden"] == 16
        prov = ckpt["provenance"]
        assert prov["seed"] == 3 and prov["data"] == [str(data_dir)] and prov["member"] == k
        assert prov["index"] == [{"recordings": 8, "generator": "test"}]
        assert prov["args"]["augs"] == ["mixing", "rotation", "speed", "unloaded"]
        assert len(ckpt["history"]) == 2 and all(np.isfinite(e["loss"]) for e in ckpt["history"])
        p, _ = net.eval()(torch.zeros(3, 640), torch.zeros(3, 16))
        torch.testing.assert_close(p.sum(1), torch.ones(3))
    lines = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    assert sum(1 for e in lines if "epoch" in e) == 4
    assert sum(1 for e in lines if e.get("event") == "done") == 2

    # Resumable: an existing member is skipped (file untouched), a missing one is trained.
    (out / "member_1.pt").unlink()
    before = (out / "member_0.pt").stat().st_mtime_ns
    assert T.main(["--data", str(data_dir), "--out", str(out), "--tiny", "--quiet", "--seed", "3",
                   "--threads", "1", "--no-eval"]) == 0
    assert (out / "member_0.pt").stat().st_mtime_ns == before
    assert (out / "member_1.pt").exists()
    events = [json.loads(line).get("event") for line in (out / "train_log.jsonl").read_text().splitlines()]
    assert events[-4:] == ["skipped", None, None, "done"]


def test_training_lowers_the_loss_and_is_deterministic(data_dir: Path, tmp_path: Path) -> None:
    # Without augmentation and with the whole (tiny) set every epoch, the loss must fall clearly.
    common = ["--data", str(data_dir), "--tiny", "--quiet", "--seed", "5", "--threads", "1", "--members", "1",
              "--epochs", "8", "--aug", "none", "--bootstrap", "1", "--no-eval", "--lr", "0.01"]
    assert T.main([*common, "--out", str(tmp_path / "a")]) == 0
    ckpt = torch.load(tmp_path / "a" / "member_0.pt", weights_only=False)
    losses = [e["loss"] for e in ckpt["history"]]
    assert np.mean(losses[-2:]) < 0.8 * np.mean(losses[:2]), losses
    assert T.main([*common, "--out", str(tmp_path / "b")]) == 0
    other = torch.load(tmp_path / "b" / "member_0.pt", weights_only=False)
    for key, value in ckpt["state_dict"].items():
        torch.testing.assert_close(value, other["state_dict"][key], rtol=0, atol=0)


def test_no_advanced_aug_and_bad_input(data_dir: Path, tmp_path: Path) -> None:
    args = T.parse_args(["--data", str(data_dir), "--out", str(tmp_path), "--no-advanced-aug"])
    assert args.augs == ["rotation", "speed"] and args.members == 5 and args.enc == 1024
    with pytest.raises(SystemExit):
        T.parse_args(["--data", str(data_dir), "--out", str(tmp_path), "--aug", "rotation,flip"])
    empty = tmp_path / "empty"
    empty.mkdir()
    assert T.main(["--data", str(empty), "--out", str(tmp_path / "o"), "--tiny", "--quiet"]) == 2
    rec = synthetic_recording(np.random.default_rng(0))
    rec.label = None
    rec.save(empty / "nolabel.npz")
    with pytest.raises(RecordingError, match=r"nolabel\.npz.*label"):
        T.load_sequences(empty, FeatureSpec())


def test_lead_labels_extend_the_positive_span_backwards() -> None:
    label = np.zeros(100, np.uint8)
    label[50:60] = 1
    led = T.lead_labels(label, 15)
    assert led[35:60].all() and not led[:35].any() and not led[60:].any()
    assert np.array_equal(T.lead_labels(label, 0), label)
    assert not T.lead_labels(np.zeros(10, np.uint8), 5).any()


def test_shift_start_drops_fewer_than_a_window_and_keeps_alignment() -> None:
    rng = np.random.default_rng(3)
    seq = _seq(rng, 500)
    lengths = set()
    for _ in range(50):
        out = A.shift_start(seq, 40, rng)
        r = len(seq) - len(out)
        lengths.add(r)
        assert 0 <= r < 40
        assert np.array_equal(out.force, seq.force[r:]) and np.array_equal(out.label, seq.label[r:])
    assert len(lengths) > 10  # a spread of phases, not one
    assert A.shift_start(seq, 1, rng) is seq


def test_training_with_a_different_window_median_and_channels(data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert T.main(["--data", str(data_dir), "--out", str(out), "--tiny", "--quiet", "--members", "1",
                   "--window", "20", "--median", "5", "--channels", "fx,fy,fz", "--pos-weight", "3",
                   "--label-lead", "10", "--aug", "rotation,shift"]) == 0
    ck = torch.load(out / "member_0.pt", weights_only=True)
    spec = FeatureSpec.from_dict(ck["feature_spec"])
    assert (spec.window, spec.median, spec.channels) == (20, 5, ("fx", "fy", "fz"))
    assert ck["config"]["input_size"] == 20 * 3 * len(spec.pillars)


def test_slip_span_labels_run_from_onset_to_gross_motion() -> None:
    t = np.arange(2000) / 1000.0
    label = np.zeros(2000, np.uint8)
    label[900:930] = 1  # 30 ms of incipient slip, as in a gripper lift
    span = T.slip_span_labels(label, {"gross_slip": 0.93, "gross_motion": 1.2}, t)
    assert span[900:1200].all() and not span[:900].any() and not span[1200:].any()
    # Hexapod scenes have no gross_motion: the span ends at gross slip.
    span = T.slip_span_labels(label, {"gross_slip": 1.0}, t)
    assert span[900:1000].all() and not span[1000:].any()
    # No events: the incipient span itself; a stop trial stays silent.
    assert np.array_equal(T.slip_span_labels(label, {}, t), label)
    assert not T.slip_span_labels(np.zeros(2000, np.uint8), {"gross_motion": 1.0}, t).any()
    # A slip without an incipient stage (no labelled sample) still counts from its onset to gross motion.
    whole = T.slip_span_labels(np.zeros(2000, np.uint8), {"onset": 0.9, "gross_slip": 0.9, "gross_motion": 1.2}, t)
    assert np.array_equal(np.flatnonzero(whole), np.flatnonzero((t >= 0.9) & (t < 1.2)))
    # ... and for at least one sample when it moves 2 mm on the onset's sample.
    assert T.slip_span_labels(np.zeros(2000, np.uint8), {"onset": 0.9, "gross_motion": 0.9}, t).sum() == 1


def test_sliding_span_labels_last_while_a_pillar_slides() -> None:
    t = np.arange(2000) / 1000.0
    label = np.zeros(2000, np.uint8)
    label[900:930] = 1
    slip = np.zeros((2000, 9), np.float32)
    slip[905:1400, 2] = 1  # the object slides off for half a second after a 30 ms incipient stage
    slip[1410:1500, 4] = 1  # a 10 ms pause is the same stretch of sliding
    slip[1600:1700, 4] = 1  # after 100 ms without sliding: another event, not this slip
    events = {"onset": 0.9, "gross_slip": 0.93, "gross_motion": 0.95}
    span = T.sliding_span_labels(label, slip, events, t)
    assert span[900:1500].all() and not span[:900].any() and not span[1500:].any()
    # Never shorter than the 2 mm span; without per-pillar truth it is that span.
    assert T.sliding_span_labels(label, np.zeros_like(slip), {**events, "gross_motion": 1.2}, t)[900:1200].all()
    assert np.array_equal(T.sliding_span_labels(label, None, events, t), T.slip_span_labels(label, events, t))
    # One pillar carried the grasp: no labelled sample, the span starts at the onset event.
    single = T.sliding_span_labels(np.zeros(2000, np.uint8), slip, events, t)
    assert single[900:1500].all() and not single[:900].any() and not single[1500:].any()
    # A stop or a partial slip (no onset and gross slip) stays silent whatever its pillars did.
    assert not T.sliding_span_labels(np.zeros(2000, np.uint8), slip, {"motion_start": 0.5}, t).any()


def test_only_trains_the_listed_members_and_they_equal_a_full_run(data_dir: Path, tmp_path: Path) -> None:
    # Members depend on (--seed, index) alone, so --only splits a run across processes without changing it;
    # the derived util channel trains through the same pipeline.
    args = ["--data", str(data_dir), "--tiny", "--quiet", "--channels", "util", "--label-span", "slip",
            "--threads", "1"]
    assert T.main([*args, "--out", str(tmp_path / "full")]) == 0
    assert T.main([*args, "--out", str(tmp_path / "part"), "--only", "1"]) == 0
    assert sorted(p.name for p in (tmp_path / "part").glob("member_*.pt")) == ["member_1.pt"]
    full = torch.load(tmp_path / "full" / "member_1.pt", weights_only=True)
    part = torch.load(tmp_path / "part" / "member_1.pt", weights_only=True)
    assert FeatureSpec.from_dict(part["feature_spec"]).channels == ("util",)
    for key, value in full["state_dict"].items():
        assert torch.equal(value, part["state_dict"][key]), key
    with pytest.raises(SystemExit):
        T.main([*args, "--out", str(tmp_path / "bad"), "--only", "2"])


def test_early_weights_mark_the_first_windows_of_each_positive_run() -> None:
    # Two lanes: lane 0 has two positive runs (the second longer than the early span); lane 1 starts a new
    # sequence (keep 0) in the middle of positives, which starts a new run.
    y = torch.tensor([[0, 1, 1, 1, 0, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1, 0, 0, 0, 0]])
    keep = torch.ones(2, 10)
    keep[1, 3] = 0.0
    w = T.early_weights(y, keep, 2, 5.0)
    assert w[0].tolist() == [1, 5, 5, 1, 1, 5, 5, 1, 1, 1]
    assert w[1].tolist() == [5, 5, 1, 5, 5, 1, 1, 1, 1, 1]
    assert torch.equal(T.early_weights(y, keep, 0, 5.0), torch.ones(2, 10))


def test_catch_runs_split_at_sequences_and_chunks() -> None:
    y = torch.tensor([[0, 1, 1, 1, 0, 1, 1, 0], [1, 1, 1, 1, 0, 0, 0, 0]])
    keep = torch.ones(2, 8)
    keep[1, 2] = 0.0  # a new sequence inside a positive run starts a new run
    runs = T.catch_runs(y, keep, chunk=6)  # and so does a chunk boundary (window 6)
    assert runs[0].tolist() == [-1, 0, 0, 0, -1, 1, 2, -1]
    assert runs[1].tolist() == [3, 3, 4, 4, -1, -1, -1, -1]


def test_the_catch_loss_asks_one_alarm_per_run_not_every_window() -> None:
    def logits(p: list[float]) -> torch.Tensor:
        z = torch.logit(torch.tensor(p))
        return torch.stack([torch.zeros_like(z), z], 1)

    runs = torch.tensor([0, 0, 0, 0])
    one_alarm = T.catch_loss(logits([0.01, 0.99, 0.01, 0.01]), runs)
    all_high = T.catch_loss(logits([0.99, 0.99, 0.99, 0.99]), runs)
    none = T.catch_loss(logits([0.01, 0.01, 0.01, 0.01]), runs)
    # one confident window in the run is nearly as good as all of them; a silent run costs much more
    assert float(one_alarm) < 0.05 and float(all_high) < float(one_alarm)
    assert float(none) > 10 * float(one_alarm)
    # two runs: each needs its own alarm, weighted by its length
    two = T.catch_loss(logits([0.01, 0.99, 0.01, 0.01]), torch.tensor([0, 0, 1, 1]))
    assert float(two) == pytest.approx(2 * -np.log(1 - 0.99 * 0.01) + 2 * -np.log(1 - 0.99 ** 2), rel=1e-4)
    assert float(T.catch_loss(logits([0.5, 0.5]), torch.tensor([-1, -1]))) == 0.0
    z = logits([1e-9, 1e-9]).requires_grad_()
    T.catch_loss(z, torch.tensor([0, 0])).backward()
    assert z.grad is not None and torch.isfinite(z.grad).all()


def test_a_partial_slip_is_a_recording_without_a_label_whose_loaded_pillars_slide() -> None:
    n = 200
    force = np.zeros((n, 9, 3), np.float32)
    force[:, 0, 2] = 2.0  # pillar 0 loaded, pillar 1 barely touching
    force[:, 1, 2] = 0.1
    slip = np.zeros((n, 9), bool)
    label = np.zeros(n, np.uint8)
    assert not T.is_partial_slip(label, slip, force)
    slip[50:50 + T.PARTIAL_SLIP_SAMPLES - 1, 0] = True
    assert not T.is_partial_slip(label, slip, force)  # one sample short
    slip[100, 0] = True
    assert T.is_partial_slip(label, slip, force)
    assert not T.is_partial_slip(label, None, force)  # no truth: nothing to say
    light = np.zeros((n, 9), bool)
    light[:, 1] = True
    assert not T.is_partial_slip(label, light, force)  # an unloaded pillar sliding is not the contact slipping
    label[150] = 1
    assert not T.is_partial_slip(label, slip, force)  # a labelled slip is a slip


def _trained_tied_net(seed: int = 0) -> SlipNet:
    """A tied-encoder net after a few train-mode passes (BatchNorm statistics away from their defaults)."""
    torch.manual_seed(seed)
    net = SlipNet(40 * 9 * 2, hidden=16, enc=0, pred=(8, 8), aux=9, tied=(40, 9, 2, 6))
    x = torch.randn(64, 40 * 9 * 2) * 3 + 1
    net.train()
    with torch.no_grad():
        for _ in range(3):
            net(x, torch.zeros(64, 16))
    return net.eval()


def test_a_tied_encoder_is_written_in_the_dense_layout_with_the_same_outputs() -> None:
    net = _trained_tied_net()
    dense = SlipNet(**net.config())
    dense.load_state_dict(net.dense_state_dict())  # strict: every key of the method's layout, nothing more
    dense.eval()
    assert net.config()["enc"] == 9 * 6
    x, h = torch.randn(5, 720) * 2, torch.rand(5, 16) - 0.5
    with torch.no_grad():
        p_tied, h_tied = net(x, h)
        p_dense, h_dense = dense(x, h)
    torch.testing.assert_close(p_dense, p_tied, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(h_dense, h_tied, atol=1e-5, rtol=1e-5)


def test_a_tied_encoder_reads_every_pillar_by_the_same_rule() -> None:
    """Which pillar carries a load does not matter to the encoder: permuting the pillars of a window leaves
    its output unchanged, while moving a load from one time to another changes it."""
    net = _trained_tied_net(1)
    x = torch.randn(4, 40, 9, 2)
    perm = torch.tensor([4, 0, 8, 2, 6, 1, 3, 7, 5])
    with torch.no_grad():
        enc = net.projector(x.reshape(4, -1))
        enc_perm = net.projector(x[:, :, perm].reshape(4, -1))
        enc_time = net.projector(x.flip(1).reshape(4, -1))
    torch.testing.assert_close(enc_perm, enc, atol=1e-5, rtol=1e-5)
    assert (enc_time - enc).abs().max() > 1e-3


def test_tiny_training_with_a_tied_encoder_exports(data_dir: Path, tmp_path: Path) -> None:
    from sliplab.export import load_run

    out = tmp_path / "run"
    assert T.main(["--data", str(data_dir), "--out", str(out), "--tiny", "--quiet", "--seed", "3", "--threads", "1",
                   "--members", "1", "--pillars", "all", "--channels", "util", "--tied-units", "4",
                   "--aux-weight", "1"]) == 0
    ckpt = torch.load(out / "member_0.pt", map_location="cpu", weights_only=False)
    assert ckpt["config"]["enc"] == 9 * 4 and ckpt["provenance"]["args"]["tied_units"] == 4
    net = SlipNet(**ckpt["config"])
    net.load_state_dict(ckpt["state_dict"])
    members, spec, _ = load_run(out)
    assert members[0].input_size == spec.input_size == 40 * 9
