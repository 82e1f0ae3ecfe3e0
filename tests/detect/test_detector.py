"""The Detector (the daemon's decision path) against the batch pipeline, and `slipd replay`."""

import json

import numpy as np
import pytest
import yaml

from slipd.cli import main
from slipd.detect.decision import Decision
from slipd.detect.detector import Detector, run_recording
from slipd.detect.ensemble import Ensemble
from slipd.detect.features import batch_windows, tare_offset
from slipd.recording import Recording


def _force(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.cumsum(rng.normal(0, 0.01, (n, 9, 3)), axis=0).astype(np.float32)
    f[:, :, 2] += 3.0  # in contact throughout
    f += np.float32(0.7)  # an unzeroed sensor
    return f


@pytest.fixture(scope="module")
def ens(tiny_model_json) -> Ensemble:
    return Ensemble.load(tiny_model_json)


def test_startup_tare_gives_exactly_the_batch_windows(ens: Ensemble) -> None:
    force = _force(1000)
    ens.reset()
    dets = run_recording(Detector(ens, Decision(), tare_samples=100, contact_gate=False), force)
    windows, ends = batch_windows(force, ens.feature_spec, tare_offset(force, 0, 100))
    ref = ens.step_batch([windows])[0].p_slip
    got = np.array([d.p_slip for d in dets])
    # The tare stretch is held back, then replayed: the first two windows end inside it and only the
    # last of them is reported (when the tare completes, with the index of the sample that ended it).
    assert [d.index for d in dets] == ends[1:].tolist()
    np.testing.assert_allclose(got, ref[1:], atol=1e-6)


def test_phase_shifted_streams_make_a_decision_every_stride(ens: Ensemble) -> None:
    force = _force(800, seed=1)
    spec = ens.feature_spec.with_(stride=10)
    ens.reset()
    dets = run_recording(Detector(ens, Decision(), spec, offset=np.zeros((9, 3)), contact_gate=False), force)
    assert np.all(np.diff([d.index for d in dets]) == 10)
    # Stream j sees every fourth window: the same sequence the single-stream model sees, shifted.
    windows, _ = batch_windows(force, spec)
    for j in range(4):
        ref = ens.step_batch([windows[j::4]])[0].p_slip
        np.testing.assert_allclose([d.p_slip for d in dets[j::4]], ref, atol=1e-6)


def test_contact_loss_resets_the_state(ens: Ensemble) -> None:
    force = _force(600, seed=2)
    force[300:, :, 2] = 0.0  # the object is released at sample 300
    det = Detector(ens, Decision(), offset=np.zeros((9, 3)))
    ens.reset()
    run_recording(det, force)
    assert det.resets == 1


def test_nonfinite_input_never_reaches_the_state(ens: Ensemble) -> None:
    force = _force(400, seed=3)
    force[100:140, 2, :] = np.nan
    force[200, :, :] = np.inf
    ens.reset()
    dets = run_recording(Detector(ens, Decision(), offset=np.zeros((9, 3))), force)
    assert all(d.valid and np.isfinite(d.p_slip) for d in dets)
    assert np.isfinite(ens.hidden_state(0)).all()


def test_replay_cli_prints_alarms(tiny_model_json, tmp_path, capsys) -> None:
    n = 2000
    rec = Recording(t_us=np.arange(n) * 1000, force=_force(n, 4), disp=np.zeros((n, 9, 3)),
                    meta={"tare_samples": [0, 100]})
    path = rec.save(tmp_path / "r.npz")
    assert main(["replay", str(path), "--model", str(tiny_model_json), "--json", str(tmp_path / "o.json")]) == 0
    out = capsys.readouterr().out
    assert "2000 samples, 49 decisions" in out
    decisions = json.loads((tmp_path / "o.json").read_text())["decisions"]
    assert len(decisions) == 49
    # Every decision carries its contact state (slip map, friction estimate, contact risk, grip, load).
    for d in decisions:
        assert len(d["pillar_slip"]) == 9 and 0.0 <= d["contact_risk"] <= 1.0 and "friction" in d
        assert "grip_n" in d and "load_n" in d and 0.0 <= d["risk"] <= 1.0  # (tared on this stretch: no grip)
    assert main(["replay", str(tmp_path / "missing.npz"), "--model", str(tiny_model_json)]) == 1
    # A config that does not fit the model is refused as check-config and run refuse it (exit 3, no traceback).
    from conftest import ROOT

    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["model"].update(manifest=str(tiny_model_json), stride=7)
    (tmp_path / "misfit.yaml").write_text(yaml.safe_dump(cfg))
    capsys.readouterr()
    assert main(["replay", str(path), "--config", str(tmp_path / "misfit.yaml")]) == 3
    assert "model.stride: must divide the model's window" in capsys.readouterr().err


@pytest.mark.parametrize("stride, tare", [(0, 0), (10, 0), (0, 100), (20, 57)])
def test_samples_to_decision_predicts_the_next_deciding_sample(ens: Ensemble, stride: int, tare: int) -> None:
    # The loop pauses the sensor reader on this prediction: a wrong one would delay a decision.
    force = _force(400, seed=2)
    spec = ens.feature_spec.with_(stride=stride)
    ens.reset()
    kwargs = {"tare_samples": tare} if tare else {"offset": np.zeros((9, 3))}
    det = Detector(ens, Decision(), spec, **kwargs)
    predicted = det.samples_to_decision()
    assert predicted >= 1
    since = 0
    for sample in force:
        since += 1
        decided = det.push(sample) is not None
        if since < predicted:
            assert not decided, f"decided {predicted - since} samples before the predicted one"
        if since == predicted:
            assert decided
            predicted, since = det.samples_to_decision(), 0


@pytest.mark.parametrize("stride, tare, sizes", [(0, 100, [4]), (10, 0, [1, 7, 150]), (20, 57, [3, 40, 5])])
def test_push_many_equals_push(ens: Ensemble, stride: int, tare: int, sizes: list[int]) -> None:
    # Blocks (the daemon's reads) give the detections push gives sample by sample: same index, t_us,
    # p_slip and alarm; returned with the block position of the sample that produced them. A contact
    # release and non-finite samples happen inside blocks.
    force = _force(900, seed=5)
    force[200:203, 4, :] = np.nan
    force[600:, :, 2] = 0.0
    t_us = np.arange(900, dtype=np.int64) * 1000 + 17
    spec = ens.feature_spec.with_(stride=stride)
    kwargs = {"tare_samples": tare} if tare else {"offset": np.zeros((9, 3))}
    ens.reset()
    one = Detector(ens, Decision(), spec, contact_gate=False, **kwargs)
    ref = [(i, d) for i in range(900) if (d := one.push(force[i], int(t_us[i]))) is not None]
    ens.reset()
    many = Detector(ens, Decision(), spec, contact_gate=False, **kwargs)
    got, pos, k = [], 0, 0
    while pos < 900:
        size = sizes[k % len(sizes)]
        block = many.push_many(force[pos : pos + size], t_us[pos : pos + size])
        assert len(many.step_seconds) == len(block) and all(s is not None for s in many.step_seconds)
        got += [(pos + i, d) for i, d in block]
        pos, k = pos + size, k + 1
    assert [i for i, _ in got] == [i for i, _ in ref]
    assert [d for _, d in got] == [d for _, d in ref]  # the dataclass compares every field
    assert (many.index, many.windows, many.resets) == (one.index, one.windows, one.resets)
    assert many.features.nonfinite_count == one.features.nonfinite_count > 0


def test_free_air_for_minutes_stays_quiet_and_a_new_contact_starts_from_h0(ens: Ensemble) -> None:
    """No contact, no slip: three minutes of sensor noise (with a drift past the contact threshold and
    single-sample spikes above it) give p_slip 0 and no alarm, the GRU states stay at h0, and the grasp that follows
    is decided exactly as by a detector that only ever saw that grasp."""
    rng = np.random.default_rng(11)
    n_air = 180_000
    air = rng.normal(0.0, 1.0, (n_air, 9, 3)).astype(np.float32) * np.array([0.01, 0.01, 0.02], np.float32)
    # The tare drifts past the SDK's 0.5 N contact threshold (0.8 N in 3 min): the gate's free-air baseline
    # follows it, so drift alone never looks like a grasp.
    air[:, :, 2] += np.linspace(0.0, 0.8, n_air, dtype=np.float32)[:, None]
    air[rng.integers(0, n_air, 200), 4, 2] = 5.0  # glitches: one sample each
    grasp = _force(2000, seed=12) - np.float32(0.7)
    grasp[:50] = 0.0  # the grasp starts unloaded
    spec = ens.feature_spec.with_(stride=10)
    ens.reset()
    det = Detector(ens, Decision(), spec, offset=np.zeros((9, 3)))
    dets = [d for _, d in det.push_many(air, np.arange(n_air))]
    assert len(dets) > 17_000 and all(d.p_slip == 0.0 and not d.alarm for d in dets)
    assert all(np.all(ens.hidden_state(z) == 0) for z in range(4))
    after = [d.p_slip for _, d in det.push_many(grasp, np.arange(len(grasp)))]
    ens.reset()
    fresh = Detector(ens, Decision(), spec, offset=np.zeros((9, 3)))
    # The fresh detector sees the grasp at the same phase of its windows as the long one.
    lead = np.zeros(((n_air - spec.window) % spec.step + spec.window, 9, 3), np.float32)
    fresh.push_many(lead, np.arange(len(lead)))
    ref = [d.p_slip for _, d in fresh.push_many(grasp, np.arange(len(grasp)))]
    assert max(after) > 0
    np.testing.assert_allclose(after, ref, atol=1e-6)


def _press(seed: int = 3) -> np.ndarray:
    """Free air for 300 ms, then every pillar pressed from 0 to 5 N over 500 ms, then held for 700 ms."""
    rng = np.random.default_rng(seed)
    n = 1500
    f = rng.normal(0, 0.01, (n, 9, 3)).astype(np.float32)
    ramp = np.clip((np.arange(n) - 300) / 500, 0, 1) * 5.0
    f[:, :, 2] += ramp[:, None].astype(np.float32)
    return f


@pytest.mark.parametrize("sensors", [1, 2])
def test_a_press_holds_the_alarm_down_and_leaves_the_model_as_it_is(ens: Ensemble, sensors: int) -> None:
    from slipd.config.schema import DecisionConfig
    from slipd.detect.build import build_detector

    PRESS_RISE = DecisionConfig().press_rise
    force = _press()
    spec = ens.feature_spec.with_(stride=10)
    runs = {}
    for rise in (PRESS_RISE, None):
        ens.reset()
        # A threshold so low that every stepped window alarms: the hold alone keeps the alarm down.
        if sensors == 1:
            det = Detector(ens, Decision(threshold=1e-6), spec, offset=np.zeros((9, 3)), press_rise=rise)
            runs[rise] = run_recording(det, force)
        else:
            multi = build_detector(None, ens, offset=np.zeros((9, 3)), sensors=2)
            for d in multi.detectors:  # type: ignore[attr-defined]
                d.decision, d.press_rise = Decision(threshold=1e-6), rise
            both = run_recording(multi, np.stack([force, force], axis=1))
            runs[rise] = [d for d in both if d.sensor == 1]
    held, free = runs[PRESS_RISE], runs[None]
    first = {k: next(d.index for d in v if d.rising_edge) for k, v in runs.items()}
    assert first[None] < 300 + 120  # without the hold: soon after the contact is made (0.5 N at 350)
    # With it: not while the load rises by more than 10 % per 40 ms (a linear 0 -> 45 N ramp over 500 ms does
    # until 440 ms in), and at once after.
    assert 300 + 420 <= first[PRESS_RISE] <= 300 + 480
    # The model stepped alike: the hold acts on the decision only.
    np.testing.assert_allclose([d.p_slip for d in held], [d.p_slip for d in free], atol=1e-6)


def test_without_a_config_the_detector_and_evaluation_take_the_default_configs_rule(ens: Ensemble,
                                                                                 tiny_model_json) -> None:
    from slipd.config.schema import DecisionConfig
    from slipd.detect.build import build_detector
    from sliplab.evaluate import ModelRunner

    rule = DecisionConfig()
    assert rule.min_consecutive == 2 and rule.press_rise == 0.1
    det = build_detector(None, ens, offset=np.zeros((9, 3)))
    assert isinstance(det, Detector)
    assert (det.decision.min_consecutive, det.press_rise) == (rule.min_consecutive, rule.press_rise)
    runner = ModelRunner(str(tiny_model_json))
    assert (runner.decision.min_consecutive, runner.press_rise) == (rule.min_consecutive, rule.press_rise)
    # The limit guard too: evaluation scores the decisions the daemon makes.
    assert rule.limit_guard == 0.9
    for d in (det.decision, runner.decision):
        assert (d.limit_guard, d.limit_guard_decisions) == (rule.limit_guard, rule.limit_guard_decisions)
    # --no-limit-guard: the model's own rule, everything else as the default config's.
    own = ModelRunner(str(tiny_model_json), limit_guard=False)
    assert own.decision.limit_guard is None and own.decision.min_consecutive == rule.min_consecutive
    assert own.label.endswith("(without the limit guard)")


# ------------------------------------------------------------------------------------- the contact gate, restarts
def _free_air(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.normal(0, 0.005, size=(n, 9, 3)).astype(np.float32)


def test_one_glitch_does_not_hold_the_contact_gate_open() -> None:
    """A finite -1e6 N on one pillar at a window end (the features clip it, the gate read it raw) moved the free-air
    baseline by 2000 N: the gate opened and never closed, the model ran in free air."""
    from slipd import models
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble

    ens = Ensemble.load(models.packaged(models.DEFAULT_MODEL))
    x = _free_air(np.random.default_rng(0), 3000)
    x[499, 4, 2] = -1e6  # sample 499 ends a window (39 + 46 x 10)
    det = build_detector(None, ens, tare_samples=0)
    dets = det.push_many(x, np.arange(len(x)) * 1000)
    assert not det.gate.open and abs(det.gate._baseline[4]) < 0.01
    assert all(d.p_slip == 0.0 for i, d in dets if i > 520)  # the model never ran in free air


def test_a_restart_keeps_the_drift_the_gate_followed_and_a_tare_under_way_starts_again() -> None:
    """A restart on the same tare (a counter gap; the loop passes retare only after the sensor's bias) kept the offset
    but zeroed the gate's free-air baseline: after 60 s of drift (0.01 N/s) the gate opened in free air. A restart
    during the start-up tare kept the samples from before the gap, another stream's."""
    from slipd import models
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble
    from slipd.recording import Recording

    ens = Ensemble.load(models.packaged(models.DEFAULT_MODEL))
    rng = np.random.default_rng(0)
    n = 60000
    x = _free_air(rng, n)
    x[:, :, 2] += (np.arange(n) * 1e-5)[:, None].astype(np.float32)
    det = build_detector(None, ens, tare_samples=0)
    det.push_many(x, np.arange(n) * 1000)
    det.restart()
    y = _free_air(rng, 5000) + np.float32(0.6) * np.array([0, 0, 1], np.float32)
    out = det.push_many(y, np.arange(5000) * 1000)
    assert not det.gate.open and not any(d.p_slip != 0 for _, d in out)
    det.restart(retare=True)  # zeroed again: the baseline starts at 0
    assert not det.gate._baseline.any()

    rec = Recording.load(models.SAMPLE_RECORDING)
    pre = (rng.normal(0, 0.005, (60, 9, 3)) + np.array([0.3, -0.2, 2.0])).astype(np.float32)  # another bias
    ens.reset()
    restarted = build_detector(None, ens, tare_samples=100)
    restarted.push_many(pre, np.arange(60) * 1000)
    restarted.restart()
    a = [(i, d.rising_edge) for i, d in restarted.push_many(rec.force, rec.t_us)]
    ens.reset()
    fresh = build_detector(None, ens, tare_samples=100)
    b = [(i, d.rising_edge) for i, d in fresh.push_many(rec.force, rec.t_us)]
    assert a == b and np.array_equal(restarted.offset, fresh.offset)


def test_a_release_forgets_the_friction_estimate_even_after_a_drift() -> None:
    """The contact state forgot the friction only once no pillar read above 0.5 N: after the tare drifted that far,
    a released object's estimate was carried into the next grasp. The gate (which follows the drift) releases it."""
    from slipd import models
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble
    from slipd.detect.features import stretch_offset
    from slipd.recording import Recording

    ens = Ensemble.load(models.packaged(models.DEFAULT_MODEL))
    rec = Recording.load(models.SAMPLE_RECORDING)
    grasp = (rec.force - stretch_offset(rec.force, (20, 300))).astype(np.float32)
    rng = np.random.default_rng(0)
    drift = np.float32(0.6) * np.array([0, 0, 1], np.float32)
    n = 60000
    ramp = _free_air(rng, n)
    ramp[:, :, 2] += (np.arange(n) * 1e-5)[:, None].astype(np.float32)
    x = np.concatenate([ramp, grasp[300:] + drift, _free_air(rng, 2000) + drift])
    det = build_detector(None, ens, tare_samples=0)
    out = det.push_many(x, np.arange(len(x)) * 1000)
    assert any(d.contact is not None and d.contact.friction is not None for _, d in out)  # the slip gave one
    last = out[-1][1]
    assert not det.gate.open and last.contact is not None and last.contact.friction is None


def test_the_gates_top_rise_is_fmax_of_the_rises_wherever_that_is_finite() -> None:
    # The contact gate reads the largest rise over the free-air baseline in plain floats; it must be numpy's fmax
    # reduction bit for bit where that is finite, and not finite where it is not (the exact path takes over there).
    from slipd.detect.detector import top_rise

    rng = np.random.default_rng(5)
    for _ in range(3000):
        fz = rng.normal(1.0, 2.0, 9).astype(np.float32)
        fz[rng.random(9) < 0.15] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0])
        if rng.random() < 0.05:
            fz[:] = np.nan
        base = rng.normal(0.0, 0.3, 9)
        want = float(np.fmax.reduce(np.subtract(fz, base)))
        got = top_rise(fz.tolist(), base.tolist())
        assert (got == want) if np.isfinite(want) else not np.isfinite(got)
