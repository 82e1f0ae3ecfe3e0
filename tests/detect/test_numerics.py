"""Hard cases stay numerically sound: faults, saturation, long runs, resets, precision, extremes.

Each test names in its docstring the naive behaviour it would catch. Documented policy under test
(``slipd.detect.features`` and ``slipd.detect.ensemble``): a non-finite sample value is replaced by the channel's
last finite value (0 before any) and counted; tared forces are clipped to twice the sensor range; the causal median
of 21 removes any run of up to 10 bad samples; a window whose median history (the last ``median - 1 + window``
samples) holds no faulty sample is bit-identical to the clean stream's window, i.e. the features recover
within one window (plus the median's 20-sample memory) after clean data returns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from onnx import numpy_helper

from slipd.detect.decision import Decision
from slipd.detect.detector import Detector, run_recording
from slipd.detect.ensemble import Ensemble
from slipd.detect.features import (
    CLIP_N,
    FeatureSpec,
    FeatureStream,
    _hold_last_finite,
    batch_windows,
    causal_median,
    tare_offset,
)
from slipd.geometry import FT_RANGE_N, FZ_RANGE_N

SPEC = FeatureSpec()  # the method's layout: 8 outer pillars, fx fy, window 40, median 21
HIST = SPEC.median - 1 + SPEC.window  # samples a window's values depend on
DENORMAL = np.float32(1e-40)
FAULTS = {"nan": np.nan, "+inf": np.inf, "-inf": -np.inf, "denormal": DENORMAL, "huge": 1e6, "-huge": -1e6}


def _hold(n: int, seed: int = 0, shear: float = 0.4, normal: float = 3.0) -> np.ndarray:
    """[n, 9, 3] a firm grasp with the sensor's noise (0.01 N fx fy, 0.02 N fz)."""
    rng = np.random.default_rng(seed)
    f = rng.normal(0.0, 1.0, (n, 9, 3)).astype(np.float32) * np.array([0.01, 0.01, 0.02], np.float32)
    f[:, :, 0] += np.linspace(-shear, shear, 9, dtype=np.float32)
    f[:, :, 1] += shear / 2
    f[:, :, 2] += normal
    return f


@pytest.fixture(scope="module")
def ens(tiny_model_json: Path) -> Ensemble:
    return Ensemble.load(tiny_model_json)


# ----------------------------------------------------------------- 1. non-finite, denormal and absurd values


@st.composite
def _faults(draw) -> list[tuple[str, int, int, tuple[int, ...], tuple[int, ...]]]:
    """Fault episodes: (kind, start, length, pillars, axes): single samples, bursts and whole pillars."""
    out = []
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(sorted(FAULTS)))
        start = draw(st.integers(0, 560))
        length = draw(st.sampled_from([1, 1, 5, 10, 30, 200]))
        shape = draw(st.sampled_from(["one", "pillar", "all"]))
        if shape == "one":
            pillars, axes = (draw(st.integers(0, 8)),), (draw(st.integers(0, 2)),)
        elif shape == "pillar":
            pillars, axes = (draw(st.integers(0, 8)),), (0, 1, 2)
        else:
            pillars, axes = tuple(range(9)), (0, 1, 2)
        out.append((kind, start, length, pillars, axes))
    return out


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(faults=_faults(), seed=st.integers(0, 1000))
def test_faulty_samples_never_reach_the_state_and_features_recover_within_one_window(ens, faults, seed) -> None:
    """NaN, +-Inf, denormals and 1e6 N (single samples, bursts, whole pillars) never reach the GRU state or
    the output, every non-finite value is counted, and every window whose median history is fault-free is
    bit-identical to the clean stream's.

    Catches: passing NaN to the model (one NaN poisons the GRU state for ever); dropping bad samples (every
    later window shifts); zero- or mean-filling without a median (a 1e6 spike or a burst of zeros survives
    into the windows); not counting non-finite values; a filter whose memory outlasts its width."""
    n = 800
    clean = _hold(n, seed)
    dirty = clean.copy()
    bad = np.zeros(n, bool)
    n_nonfinite = 0
    for kind, start, length, pillars, axes in faults:
        stop = min(n, start + length)
        for p in pillars:
            for a in axes:
                dirty[start:stop, p, a] = FAULTS[kind]
        bad[start:stop] = True
    n_nonfinite = int((~np.isfinite(dirty)).sum())  # overlapping episodes: count what is really there
    ens.reset()
    det_clean = Detector(ens, Decision(), offset=np.zeros((9, 3), np.float32), contact_gate=False)
    ref = {d.index: d for d in run_recording(det_clean, clean)}
    ref_windows, ends = batch_windows(clean, SPEC)
    ens.reset()
    det = Detector(ens, Decision(), offset=np.zeros((9, 3), np.float32), contact_gate=False)
    fs = det.features
    seen = []
    for i in range(n):
        d = det.push(dirty[i], i * 1000)
        if d is None:
            continue
        assert d.valid and np.isfinite(d.p_slip) and 0.0 <= d.p_slip <= 1.0
        h = ens.hidden_state(0)
        assert np.isfinite(h).all() and np.abs(h).max() <= 1.0
        seen.append(d.index)
    assert seen == list(ends)  # no window dropped, none shifted
    assert fs.nonfinite_count == n_nonfinite
    # Clipped: the 1e6 N values, and non-finite ones whose held last finite value was such a value.
    held, _ = _hold_last_finite(dirty.reshape(n, 27))
    assert fs.clipped_count == int((np.abs(held) > np.tile(CLIP_N, 9)).sum())
    assert det.step_errors == 0 and ens.refused_inputs == 0 and ens.nonfinite_outputs == 0
    # Recovery: windows whose history holds no faulty sample equal the clean run's windows exactly.
    dirty_windows, _ = batch_windows(dirty, SPEC)
    assert np.isfinite(dirty_windows).all() and np.abs(dirty_windows).max() <= 2 * FZ_RANGE_N
    recovered = 0
    for k, e in enumerate(ends):
        if not bad[max(0, e - HIST + 1): e + 1].any():
            assert np.array_equal(dirty_windows[k], ref_windows[k]), f"window {k} not recovered"
            recovered += 1
    assert recovered or bad.sum() > n - 2 * HIST
    assert len(ref) == len(seen)


def test_denormal_windows_behave_like_zero(ens) -> None:
    """A window of denormals gives the zero window's output within 1e-6 and finite states.

    Catches: a graph or runtime that turns subnormal arithmetic into NaN or Inf (e.g. a reciprocal or a
    normalisation by a tiny norm), and the silent slowdown path being mistaken for a fault."""
    zero = np.zeros((4, SPEC.input_size), np.float32)
    tiny = np.full_like(zero, DENORMAL)
    tiny[1::2] *= -1
    ens.reset()
    p0 = [ens.step(w, stream=1).p_slip for w in zero]
    h0 = ens.hidden_state(1)
    ens.reset()
    p1 = [ens.step(w, stream=1).p_slip for w in tiny]
    assert np.allclose(p0, p1, atol=1e-6, rtol=0) and np.allclose(h0, ens.hidden_state(1), atol=1e-6, rtol=0)


def test_dead_pillar_from_the_start_reads_as_no_load_and_is_counted(ens) -> None:
    """A pillar that never reports a finite value reads 0 N (no load) on every window, and every value counts.

    Catches: a hold-last-value buffer initialised with NaN/garbage (np.empty), which leaks into the first
    windows when no finite value was ever seen."""
    f = _hold(400, seed=3)
    f[:, 5, :] = np.nan
    fs = FeatureStream(SPEC)
    wins = [w for w in (fs.push(s) for s in f) if w is not None]
    col = SPEC.pillars.index(5) * 2
    assert all(np.all(w.reshape(SPEC.window, -1)[:, col:col + 2] == 0.0) for w in wins)
    assert fs.nonfinite_count == 400 * 3
    assert all(ens.step(w, stream=2).valid for w in wins)


@pytest.mark.parametrize("glitch", ["dropout_frame", "negative_burst", "ten_zero_frames"])
def test_a_glitch_on_every_normal_force_does_not_reset_the_state_mid_grasp(ens, glitch: str) -> None:
    """During a firm grasp, one all-zero frame, a 5-sample burst of -1e6 N on every fz, or 10 zero frames
    (runs the median removes) neither reset the GRU state nor change any decision; a real release does.

    Catches: contact-loss detection on the raw sample (one dropout frame looks like a release and wipes
    the model's memory in the middle of a grasp, exactly when slip may be building up)."""
    clean = _hold(1200, seed=8)
    dirty = clean.copy()
    # Each glitch covers sample 519, the last sample of window 12, where the contact check looks.
    if glitch == "dropout_frame":
        dirty[519] = 0.0
    elif glitch == "negative_burst":
        dirty[517:522, :, 2] = -1e6
    else:
        dirty[510:520] = 0.0
    out = {}
    for name, samples in (("clean", clean), ("dirty", dirty)):  # only the glitch differs
        ens.reset()
        det = Detector(ens, Decision(), offset=np.zeros((9, 3), np.float32))
        out[name] = (np.array([d.p_slip for d in run_recording(det, samples)]), det.resets)
    assert out["dirty"][1] == 0
    # The gate opens at the second check and never closes again: the state is carried through the glitch.
    assert out["dirty"][0][0] == 0.0 and (out["dirty"][0][1:] > 0).all()
    assert np.abs(out["dirty"][0] - out["clean"][0]).max() < 1e-3
    released = clean.copy()
    released[600:, :, 2] = 0.0
    ens.reset()
    det = Detector(ens, Decision(), offset=np.zeros((9, 3), np.float32))
    run_recording(det, released)
    assert det.resets == 1


# ----------------------------------------------------------------- 2. saturation and glitch spikes


def test_saturation_for_seconds_gives_exact_bounded_features_and_valid_decisions(ens) -> None:
    """Seconds at the sensor limits (+-4 N tangential, 15 N normal), with 1e6 N spikes on top, give windows
    that sit exactly at the limits, and every decision is valid.

    Catches: clipping before the tare (a saturated reading then tares to a wrong value), clipping at the
    sensor range instead of twice it (a tared saturated reading loses its sign information), and a GRU fed
    constant extreme inputs drifting to a non-finite state."""
    n = 3000
    f = np.zeros((n, 9, 3), np.float32)
    f[:, :, 0] = FT_RANGE_N
    f[:, :, 1] = -FT_RANGE_N
    f[:, :, 2] = FZ_RANGE_N
    f[1000::97, :, 0] = 1e6  # isolated spikes: the median must remove them exactly
    wins, _ = batch_windows(f, SPEC)
    w = wins.reshape(len(wins), SPEC.window, -1)
    assert np.all(w[:, :, 0::2] == FT_RANGE_N) and np.all(w[:, :, 1::2] == -FT_RANGE_N)
    ens.reset()
    det = Detector(ens, Decision(), offset=np.zeros((9, 3), np.float32))
    dets = run_recording(det, f)
    assert len(dets) == len(wins) and all(d.valid and 0.0 <= d.p_slip <= 1.0 for d in dets)
    assert np.isfinite(ens.hidden_state(0)).all()


@settings(max_examples=40, deadline=None)
@given(
    level=st.floats(-4.0, 4.0, width=32),
    spikes=st.lists(st.tuples(st.integers(0, 30), st.sampled_from([1, 5, 6, 7, 8, 9, 10]),
                              st.floats(-1e6, 1e6, width=32)), min_size=1, max_size=6),
)
def test_median_removes_spikes_of_1_and_5_to_10_samples_exactly(level, spikes) -> None:
    """On a steady level, spikes of 1 and 5-10 samples (any height) vanish exactly; 11 samples do not.

    Catches: an even or narrower median, a mean or low-pass filter (which smears spikes), and an
    off-by-one in the window (an 11-sample run must survive, so the bound is tight).
    (``tests/detect/test_features.py::test_median_removes_short_glitches_exactly`` covers one fixed case.)"""
    n = 400
    x = np.full((n, 1), level, np.float32)
    pos = 25
    for gap, length, height in spikes:
        x[pos:pos + length, 0] = height
        pos += length + SPEC.median + gap  # spikes farther apart than the median's width
    assert np.array_equal(causal_median(x, SPEC.median), np.full_like(x, level))
    y = np.full((100, 1), level, np.float32)
    y[40:51, 0] = level + 1.0
    assert np.any(causal_median(y, SPEC.median) != level)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n_spikes=st.integers(1, 10))
def test_median_output_stays_within_the_clean_signal_on_a_moving_load(seed, n_spikes) -> None:
    """On a moving (noisy) load with up to 10 spike samples in any 21, each output lies within the clean
    samples' range of its history.

    Catches: a filter that lets any part of a spike through when the load is not constant."""
    rng = np.random.default_rng(seed)
    clean = np.cumsum(rng.normal(0, 0.05, 300)).astype(np.float32)
    dirty = clean.copy()
    starts = rng.choice(np.arange(30, 280, 25), size=3, replace=False)
    for s in starts:
        dirty[s:s + n_spikes] = rng.choice([-1e6, 1e6])
    y = causal_median(dirty[:, None], SPEC.median)[:, 0]
    pad = np.concatenate([np.repeat(clean[:1], SPEC.median - 1), clean])
    for k in range(len(clean)):
        hist = pad[k:k + SPEC.median]
        assert hist.min() <= y[k] <= hist.max()


# ----------------------------------------------------------------- 3. long runs (short variant of tools/soak.py)


def test_soak_short_hidden_state_bounded_probability_does_not_drift(ens) -> None:
    """20 000 consecutive windows on steady hold, noise only and a periodic load (B = 3 in one stream): the
    state stays finite and within [-1, 1], P(slip) on the steady hold settles and does not creep upward,
    and false alarms are counted.

    Catches: an unclipped or unstable recurrence (|h| growing, NaN after hours), a state shared between the
    batched sequences, and a bias that accumulates window after window."""
    from sliplab.soak import CASES, soak

    res = {r.name: r for r in soak(ens, 20_000, pool_windows=500)}
    assert set(res) == set(CASES)
    for r in res.values():
        assert r.nonfinite_steps == 0 and 0.0 < r.h_max_abs <= 1.0
        assert np.isfinite([r.p_settled, r.p_final, r.p_max]).all()
        assert r.hours == pytest.approx(20_000 * 0.04 / 3600)
        assert r.alarms >= 0 and np.isfinite(r.alarms_per_hour)
    hold = res["steady_hold"]
    assert hold.drift < 1e-3  # settled: no upward creep over the last 80 % of the run


# ----------------------------------------------------------------- 4. streaming == batch across resets


@pytest.mark.parametrize("stride", [0, 20])
def test_restart_gives_the_batch_windows_and_probabilities(ens, stride: int) -> None:
    """Across ``Detector.restart`` (a reconnect, with re-tare), the detections equal a batch run of each
    segment from a zero state: same windows, probabilities within 1e-6.

    Catches: a feature history or GRU state that survives a reset (the first windows after a reconnect mix
    two connections), a tare not retaken, and phase streams that are not restarted in step."""
    spec = SPEC.with_(stride=stride)
    a, b = _hold(700, seed=1), _hold(900, seed=2, shear=0.8)
    b += np.float32(0.7)  # the sensor came back with another offset: re-tare must absorb it
    ens.reset()
    det = Detector(ens, Decision(), spec=spec, tare_samples=100, contact_gate=False)
    got_a = run_recording(det, a)
    det.restart(retare=True)
    got_b = [d for d in (det.push(s, 0) for s in b) if d is not None]
    k = spec.window // spec.step
    for seg, got in ((a, got_a), (b, got_b)):
        wins, ends = batch_windows(seg, spec, tare_offset(seg, 0, 100))
        # Windows inside the tare stretch step the model but only the last of them is reported.
        first = max(0, int(np.searchsorted(ends, 99, side="right")) - 1)
        seqs = [wins[j::k] for j in range(k)]
        out = ens.step_batch(seqs)
        p = np.empty(len(wins), np.float32)
        for j in range(k):
            p[j::k] = out[j].p_slip
        assert [d.index - (len(a) if seg is b else 0) for d in got] == list(ends[first:])
        assert np.abs(np.array([d.p_slip for d in got]) - p[first:]).max() <= 1e-6


def test_ensemble_reset_mid_stream_equals_batch_from_zero(ens) -> None:
    """``Ensemble.reset`` in the middle of a stream makes the following steps equal a fresh batch run.

    Catches: a reset that clears only one of the two ping-pong state buffers, or leaves a stale binding."""
    wins, _ = batch_windows(_hold(4000, seed=4), SPEC)
    ens.reset()
    for w in wins[:37]:
        ens.step(w, stream=3)
    ens.reset(3)
    p = np.array([ens.step(w, stream=3).p_slip for w in wins[37:]])
    ref = ens.step_batch([wins[37:]])[0].p_slip
    assert np.abs(p - ref).max() <= 1e-6


# ----------------------------------------------------------------- 5. fp16 and int8 vs fp32


@pytest.fixture(scope="module")
def variants(tmp_path_factory) -> dict[str, Ensemble]:
    torch = pytest.importorskip("torch")
    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet

    nets = []
    for seed in range(3):
        torch.manual_seed(100 + seed)
        net = SlipNet(input_size=SPEC.input_size, hidden=32, enc=64, pred=(32, 16))
        with torch.no_grad():
            # Small running variances amplify each layer (as training does): the output really moves.
            for m in net.modules():
                if isinstance(m, torch.nn.BatchNorm1d):
                    m.running_var.uniform_(0.01, 0.05)
                    m.running_mean.normal_(0, 0.1)
        nets.append(net.eval())
    folder = tmp_path_factory.mktemp("precision")
    out = {}
    for prec in ("fp32", "fp16", "int8"):
        export([fold_member(n.state_dict()) for n in nets], SPEC, folder / f"m_{prec}.onnx", "trained", {},
               precision=prec)
        out[prec] = Ensemble.load(folder / f"m_{prec}.json")
    return out


PRECISION_TOL = {"fp16": 5e-3, "int8": 6e-2}
"""Largest |P(slip) - P_fp32(slip)| allowed per variant (measured on this fixture: fp16 2.2e-3, int8 4.4e-2;
on the authors' checkpoints: fp16 4.9e-4, int8 3.8e-2); the alarm decisions
must agree wherever P_fp32 is farther than this from the threshold."""


def _slip_like_windows(n: int, seed: int) -> np.ndarray:
    """Windows of a hold that starts to shear (a slip-like ramp), through the real pipeline."""
    f = _hold(n, seed, shear=0.2)
    ramp = np.clip((np.arange(n) - n // 3) / n, 0, None).astype(np.float32) * 3.0
    f[:, :, 0] += ramp[:, None]
    return batch_windows(f, SPEC)[0]


def test_fp16_and_int8_match_fp32_within_tolerance_and_decide_alike(variants) -> None:
    """fp16 and int8 probabilities stay within a stated tolerance of fp32, and alarms agree except within
    that margin of the threshold (set at the fp32 median so decisions really split).

    Catches: a variant that overflows in fp16 (inputs cast before the clip), a quantisation that shifts
    the output systematically, and state drift that grows along the sequence."""
    wins = _slip_like_windows(8000, seed=5)
    p = {}
    for prec, e in variants.items():
        e.reset()
        p[prec] = np.array([e.step(w).p_slip for w in wins])
    assert np.isfinite(np.stack(list(p.values()))).all()
    thr = float(np.median(p["fp32"]))
    assert p["fp32"].std() > 1e-3  # the sequence moves the output: the comparison is not trivial
    for prec in ("fp16", "int8"):
        err = np.abs(p[prec] - p["fp32"])
        print(f"{prec}: max abs error vs fp32 {err.max():.2e}")
        assert err.max() <= PRECISION_TOL[prec], (prec, err.max())
        far = np.abs(p["fp32"] - thr) > PRECISION_TOL[prec]
        assert np.array_equal((p[prec] >= thr)[far], (p["fp32"] >= thr)[far]), prec


def test_hysteresis_stops_chattering_near_the_threshold_in_every_precision(variants) -> None:
    """A steady hold whose P(slip) sits at the threshold (set to the fp32 median) makes the plain rule chatter;
    with hysteresis above the precision tolerance plus the noise the alarm rises at most once, in every variant.

    Catches: hysteresis that compares against the wrong side, or a margin smaller than the variants' error."""
    wins = batch_windows(_hold(20_000, seed=6), SPEC)[0]
    p = {}
    for prec, e in variants.items():
        e.reset()
        p[prec] = np.array([e.step(w).p_slip for w in wins])[20:]  # past the initial transient
    thr = float(np.median(p["fp32"]))
    spread = float(p["fp32"].max() - p["fp32"].min())
    plain = Decision(min(max(thr, 1e-3), 0.999))
    assert sum(plain.update(float(x)).rising_edge for x in p["fp32"]) > 5  # chatter without hysteresis
    hyst = spread + PRECISION_TOL["int8"]
    assert hyst < thr
    for prec, ps in p.items():
        d = Decision(thr, hysteresis=hyst)
        assert sum(d.update(float(x)).rising_edge for x in ps) <= 1, prec


# ----------------------------------------------------------------- 6. softmax extremes, parity, graph audit

SAFE_OPS = {"Clip", "Cast", "MatMul", "Add", "Sub", "Mul", "Relu", "Sigmoid", "Tanh", "Reshape", "Transpose",
            "Split", "Squeeze", "ReduceMean", "Identity"}
"""Ops that give a finite result from finite inputs as long as no intermediate overflows (checked below by
interval bounds). Absent on purpose: Div, Log, Sqrt, Pow, Exp, Softmax, LogSoftmax, Reciprocal, ..."""
UNSAFE_OPS = {"Div", "Log", "Sqrt", "Pow", "Exp", "Softmax", "LogSoftmax", "Reciprocal", "Acos", "Asin",
              "ReduceLogSumExp", "Mod", "Atanh", "Acosh"}


def _attr(node: onnx.NodeProto, name: str, default=None):
    for a in node.attribute:
        if a.name == name:
            return onnx.helper.get_attribute_value(a)
    return default


def _gru_update(node: onnx.NodeProto, producer: dict[str, onnx.NodeProto]) -> str | None:
    """For ``Add(n, Mul(z, Sub(h, n)))`` with z a Sigmoid, the name of h; else None."""
    if node.op_type != "Add":
        return None
    n, m = node.input
    mul = producer.get(m)
    if mul is None or mul.op_type != "Mul":
        return None
    z, sub = (producer.get(x) for x in mul.input)
    if z is None or sub is None or z.op_type != "Sigmoid" or sub.op_type != "Sub" or sub.input[1] != n:
        return None
    return sub.input[0]


def interval_bounds(model: onnx.ModelProto, window_bound: float) -> dict[str, float]:
    """Bound on |value| of every tensor (batch 1) for ANY window in [-window_bound, window_bound] and ANY
    finite h: interval arithmetic per element (each op maps the box [lo, hi] to a box that contains every
    value it can produce), so a finite bound below the compute type's maximum proves no overflow."""
    inits = {t.name: numpy_helper.to_array(t).astype(np.float64) for t in model.graph.initializer}
    fmax = float(np.finfo(np.float32).max)
    shapes = {i.name: [d.dim_value or 1 for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    iv: dict[str, tuple[np.ndarray, np.ndarray]] = {
        "window": (np.full(shapes["window"], -window_bound), np.full(shapes["window"], window_bound)),
        "h": (np.full(shapes["h"], -fmax), np.full(shapes["h"], fmax)),
    }
    for name, arr in inits.items():
        iv[name] = (arr, arr)
    producer: dict[str, onnx.NodeProto] = {}
    for node in model.graph.node:
        for out in node.output:
            producer[out] = node
    for node in model.graph.node:
        op, ins = node.op_type, node.input
        assert op in SAFE_OPS, f"op {op} ({node.name}) not audited"
        lo, hi = iv[ins[0]]
        if op == "Clip":
            outs = [(np.clip(lo, inits[ins[1]], inits[ins[2]]), np.clip(hi, inits[ins[1]], inits[ins[2]]))]
        elif op == "MatMul":
            w = inits[ins[1]]
            wp, wn = np.maximum(w, 0.0), np.minimum(w, 0.0)
            outs = [(lo @ wp + hi @ wn, hi @ wp + lo @ wn)]
        elif op in ("Add", "Sub", "Mul"):
            blo, bhi = iv[ins[1]]
            gru = _gru_update(node, producer)
            if gru is not None:
                # h_new = n + z (h - n) = (1 - z) n + z h with z in [0, 1]: a convex combination, so it lies
                # in the hull of n's and h's boxes (plain interval arithmetic would lose that and give 3x).
                hlo, hhi = iv[gru]
                outs = [(np.minimum(lo, hlo), np.maximum(hi, hhi))]
            elif op == "Add":
                outs = [(lo + blo, hi + bhi)]
            elif op == "Sub":
                outs = [(lo - bhi, hi - blo)]
            else:
                prods = np.stack(np.broadcast_arrays(lo * blo, lo * bhi, hi * blo, hi * bhi))
                outs = [(prods.min(axis=0), prods.max(axis=0))]
        elif op in ("Relu", "Sigmoid", "Tanh"):  # monotone: the box maps end to end
            f = {"Relu": lambda v: np.maximum(v, 0.0), "Sigmoid": lambda v: 1.0 / (1.0 + np.exp(-v)),
                 "Tanh": np.tanh}[op]
            with np.errstate(over="ignore"):
                outs = [(f(lo), f(hi))]
        elif op == "Reshape":
            shape = inits[ins[1]].astype(np.int64)
            outs = [(lo.reshape(shape), hi.reshape(shape))]
        elif op == "Transpose":
            perm = _attr(node, "perm")
            outs = [(lo.transpose(perm), hi.transpose(perm))]
        elif op == "Split":
            cuts = np.cumsum(inits[ins[1]].astype(np.int64))[:-1]
            ax = _attr(node, "axis", 0)
            outs = list(zip(np.split(lo, cuts, axis=ax), np.split(hi, cuts, axis=ax)))
        elif op == "Squeeze":
            ax = tuple(int(a) for a in inits[ins[1]])
            outs = [(lo.squeeze(ax), hi.squeeze(ax))]
        elif op == "ReduceMean":
            ax, keep = tuple(_attr(node, "axes")), bool(_attr(node, "keepdims", 1))
            outs = [(lo.mean(axis=ax, keepdims=keep), hi.mean(axis=ax, keepdims=keep))]
        else:  # Cast, Identity: the values are unchanged (fp16 rounding is far below the margin kept)
            outs = [(lo, hi)]
        for out, (olo, ohi) in zip(node.output, outs):
            iv[out] = (olo, ohi)
    return {k: float(max(np.abs(v[0]).max(), np.abs(v[1]).max())) for k, v in iv.items()
            if k not in inits and k not in ("window", "h")}


@pytest.mark.parametrize("prec", ["fp32", "fp16"])
def test_exported_graph_cannot_make_nan_from_finite_inputs(variants, prec: str) -> None:
    """Walk the exported graph: only audited ops, and per-element interval bounds show that no intermediate
    can overflow the compute type, so no inf (and no inf - inf or 0 * inf = NaN) can arise. fp32: for ANY
    finite window and state. fp16: for any window the feature pipeline can produce (tared forces clipped to
    twice the sensor range, ``slipd.detect.features.CLIP_N``) and any state.

    Catches: a naive softmax (Exp), a Div or Log added by a later edit, a missing input or state clip (then
    3e38 inputs overflow MatMul), and an fp16 graph whose activations can exceed 65504 on real windows."""
    from slipd.detect.features import channel_bound

    model = onnx.load(str(variants[prec].manifest_path.with_name(variants[prec].manifest.onnx_file)))
    if prec == "fp32":
        dtype_max, window_bound = float(np.finfo(np.float32).max), float(np.finfo(np.float32).max)
    else:
        dtype_max = float(np.finfo(np.float16).max)
        window_bound = max(channel_bound(c) for c in SPEC.channels)
    bounds = interval_bounds(model, window_bound)
    worst = max(bounds.values())
    assert np.isfinite(worst) and worst < dtype_max / 2, (prec, worst)  # half: room for rounding
    assert bounds["p_slip"] <= 1.0 and bounds["p_members"] <= 1.0 and bounds["h_next"] <= 1.0


def test_fp16_overflow_beyond_the_feature_range_is_caught_by_the_runtime_policy(variants) -> None:
    """Adversarial windows (each the sign pattern of one first-layer weight column): at the feature pipeline's
    bound (8 N) every fp16 step is valid; at the graph's own input clip (1000 N) an fp16 overflow to inf/NaN
    may happen, and then the step is refused, counted and the stream reset, and the state stays finite.

    Catches: an fp16 NaN stored as the recurrent state (every later decision lost), or reported as a
    probability."""
    e = variants["fp16"]
    model = onnx.load(str(e.manifest_path.with_name(e.manifest.onnx_file)))
    w1 = next(numpy_helper.to_array(t) for t in model.graph.initializer if t.name == "enc0_w").astype(np.float32)
    cols = range(0, w1.shape[1], max(1, w1.shape[1] // 48))
    for bound, must_be_valid in ((8.0, True), (1000.0, False)):
        e.reset()
        before = e.nonfinite_outputs
        n_bad = 0
        for j in cols:
            r = e.step(np.sign(w1[:, j]) * np.float32(bound), stream=0)
            h = e.hidden_state(0)
            assert np.isfinite(h).all() and np.abs(h).max() <= 1.0
            if r.valid:
                assert np.isfinite(r.p_slip) and 0.0 <= r.p_slip <= 1.0
            else:
                n_bad += 1
                assert r.status == "nonfinite_output" and np.isnan(r.p_slip) and not h.any()
        assert e.nonfinite_outputs - before == n_bad
        if must_be_valid:
            assert n_bad == 0


def test_int8_graph_holds_no_op_that_makes_nan(variants) -> None:
    """The int8 graph (rewritten by the quantiser) holds none of the ops that produce NaN from finite inputs.

    Catches: a quantiser pass that brings a Div/Log/Exp into the runtime graph."""
    model = onnx.load(str(variants["int8"].manifest_path.with_name(variants["int8"].manifest.onnx_file)))
    ops = {n.op_type for n in model.graph.node}
    assert not ops & UNSAFE_OPS, ops & UNSAFE_OPS


def test_parity_with_torch_at_10x_and_100x_and_overflowing_logits(tmp_path: Path) -> None:
    """ONNX vs torch at 10x and 100x realistic inputs within 1e-5, and logits of +-1e3 (exp overflows float32
    in a naive softmax) give probabilities in [0, 1] equal to torch's.

    (10x parity and one overflowing-logit case are in ``tests/lab/test_export.py``; this adds 100x, which
    reaches the non-linear regions of every layer, and negative overflow.)"""
    torch = pytest.importorskip("torch")
    import onnxruntime as ort

    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet, run_sequence

    torch.manual_seed(7)
    nets = [SlipNet(input_size=SPEC.input_size, hidden=32, enc=64, pred=(32, 16)).eval() for _ in range(2)]
    with torch.no_grad():
        nets[1].predictor[6].weight.mul_(500.0)
        nets[1].predictor[6].bias.copy_(torch.tensor([800.0, -800.0]))
    export([fold_member(n.state_dict()) for n in nets], SPEC, tmp_path / "p.onnx", "trained", {})
    sess = ort.InferenceSession(str(tmp_path / "p.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(9)
    base = np.clip(np.cumsum(rng.normal(0, 0.01, (30 * SPEC.window, 16)), axis=0), -2, 2).astype(np.float32)
    base = base.reshape(30, SPEC.input_size)
    for scale in (10.0, 100.0):
        wins = base * np.float32(scale)
        ref = run_sequence(nets, torch.from_numpy(wins)).numpy()  # [Z, K]
        h = np.zeros((2, 1, 32), np.float32)
        pm = []
        for w in wins:
            _, m, h = sess.run(None, {"window": w[None], "h": h})
            pm.append(m[:, 0])
        pm = np.array(pm).T
        assert np.isfinite(pm).all() and ((pm >= 0) & (pm <= 1)).all()
        assert np.abs(pm - ref).max() <= 1e-5, scale


# ----------------------------------------------------------------- 7. tare and filter arithmetic


def test_tare_over_a_long_stretch_is_exact_to_float32_rounding() -> None:
    """A tare over 300 000 samples of a 1234.5678 N offset (sensor not zeroed) equals the float64 mean to
    float32 rounding.

    Catches: accumulating the offset in float32 sequentially (after ~10^5 samples each addition loses the
    noise's low bits and the offset is biased by many ulp)."""
    rng = np.random.default_rng(11)
    n = 300_000
    f = (np.float32(1234.5678) + rng.normal(0, 0.01, (n, 9, 3))).astype(np.float32)
    off = tare_offset(f, 0, n)
    exact = f.astype(np.float64).mean(axis=0)
    assert np.all(np.abs(off - exact) <= np.spacing(np.float32(1234.5678)))
    naive = np.zeros((9, 3), np.float32)
    for chunk in np.array_split(f, 3000):  # running float32 total, chunk by chunk as a naive stream would
        naive += chunk.sum(axis=0, dtype=np.float32)
    assert np.abs(naive / np.float32(n) - exact).max() > 4 * np.spacing(np.float32(1234.5678))


def test_a_glitch_in_the_tare_stretch_does_not_shift_the_offset(ens) -> None:
    """A 1e6 N spike (and a NaN) inside the detector's 100-sample start-up tare leave the offset within 1 mN
    of the clean one, and the decisions equal the clean run's; on clean noise the tare is the plain mean.

    Catches: a plain mean over the tare stretch (one spike shifts every later feature by 1e6 / 100 N, so
    the model sees saturated forces for the whole session)."""
    clean = _hold(1000, seed=13, shear=0.0, normal=0.0) + np.float32(0.7)  # unloaded, sensor not zeroed
    clean[300:, :, 0] += 0.5  # then a load
    dirty = clean.copy()
    dirty[50, 3, 0] = 1e6
    dirty[60, 4, 1] = np.nan
    out = {}
    for name, f in (("clean", clean), ("dirty", dirty)):
        ens.reset()
        det = Detector(ens, Decision(), tare_samples=100, contact_gate=False)
        out[name] = (np.array([d.p_slip for d in run_recording(det, f)]), det.offset)
    assert np.abs(out["dirty"][1] - out["clean"][1]).max() < 1e-3
    assert np.abs(out["dirty"][0] - out["clean"][0]).max() < 1e-3
    plain = clean[:100].astype(np.float64).mean(axis=0)
    assert np.abs(out["clean"][1] - plain).max() <= 1e-7  # nothing left out of clean noise


def test_slow_drift_passes_through_unbiased_with_exactly_the_median_lag() -> None:
    """A slow linear drift on top of a large offset comes out tared, unbiased and delayed by exactly
    (median - 1) / 2 = 10 samples (the median of an arithmetic run is its middle element).

    Catches: a tare that subtracts in float32 before removing the offset's own rounding (bias), a filter
    with a non-causal or fractional lag, and an averaging filter (exact only by luck)."""
    n, d = 3000, np.float32(2.0 ** -17)  # about 7.6 uN per sample: 23 mN over 3 s
    k = np.arange(n, dtype=np.float32)
    f = np.zeros((n, 9, 3), np.float32)
    f[:, :, 0] = np.float32(2.0) + k[:, None] * d
    off = np.zeros((9, 3), np.float32)
    off[:, 0] = 2.0
    wins, ends = batch_windows(f, SPEC, off)
    w = wins.reshape(len(wins), SPEC.window, -1)
    for j, e in enumerate(ends):
        idx = np.arange(e - SPEC.window + 1, e + 1)
        expect = np.maximum(idx - (SPEC.median - 1) // 2, 0).astype(np.float32) * d
        expect[idx < (SPEC.median - 1) // 2] = 0.0  # edge padding: the first samples' median is sample 0
        assert np.array_equal(w[j, :, 0], expect), j


def test_long_stream_has_no_accumulating_state() -> None:
    """After 100 000 samples (many ring-buffer shifts) the stream's windows are still bit-identical to batch.

    Catches: a running sum or index kept in float32 (loses integer precision), a ring buffer whose shift
    drops or duplicates a row after wrapping."""
    rng = np.random.default_rng(12)
    n = 100_000
    f = (rng.normal(0, 0.5, (n, 9, 3)) + 1000.0).astype(np.float32)
    off = tare_offset(f, 0, 100)
    fs = FeatureStream(SPEC, off)
    wins, _ = batch_windows(f, SPEC, off)
    k = 0
    for s in f:
        w = fs.push(s)
        if w is not None:
            if k % 97 == 0 or k >= len(wins) - 3:
                assert np.array_equal(w, wins[k]), k
            k += 1
    assert k == len(wins)


# ----------------------------------------------------------------- 8. simulator edge case not covered elsewhere


def test_single_pillar_at_high_speed_and_maximum_depth_is_finite_and_within_friction() -> None:
    """One pillar in contact, 45 mm/s, the deepest press: finite, no negative normal force, no pillar past its
    static friction limit. (Zero speed, 60 mm/s, zero and maximum depth, single pillar at 3 mm/s and the
    gripper at the friction limit are in ``tests/sim/test_sim_physics.py``.)

    Catches: a stick-slip step that overshoots the friction cone when the whole load sits on one pillar."""
    from slipd.geometry import CENTRE
    from slipd.sim.physics import normal_force, sensor_params
    from slipd.sim.scene import generate, parse_scene

    v1 = sensor_params("v1")
    off = [p for p in range(9) if p != CENTRE]
    scene = parse_scene({"family": "hexapod", "contact": {"depth_mm": 3.0},
                         "motion": {"kind": "translation", "speed_mm_s": 45.0, "accel_mm_s2": 500.0},
                         "friction": {"mu_s": 0.7, "mu_k": 0.6},
                         "effects": [{"name": "partial_contact", "pillars": off}]})
    rec = generate(scene)
    assert np.isfinite(rec.force).all() and np.isfinite(rec.disp).all()
    assert rec.force[..., 2].min() >= 0.0
    ft = v1.kt_n_mm * np.hypot(rec.disp[:, CENTRE, 0], rec.disp[:, CENTRE, 1])
    fz = normal_force(rec.disp[:, CENTRE, 2], v1)
    assert np.all(ft <= 0.7 * fz * (1 + 1e-5) + 1e-6)
    assert rec.slip[:, CENTRE].any()
