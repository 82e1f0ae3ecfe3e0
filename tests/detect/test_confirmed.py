"""The reference-pillar rule confirmed by the model: the fused alarm against a brute-force fusion of a rule that ran
all along, blocks of any size alike, the rule at rest while the model is quiet, and the config around it."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pytest
from conftest import make_scene

from slipd.config import ConfigError, SlipdConfig, config_from_dict
from slipd.detect.baselines import ReferencePillarDetector, ReferencePillarParams, baseline_offset
from slipd.detect.confirmed import HISTORY, ConfirmedDetector
from slipd.detect.decision import Detection
from slipd.recording import Recording

STRIDE = 10
WITHIN_US = 100_000
LEVEL = 0.3
RULE = ReferencePillarParams(ratio=0.2, min_ref_speed=0.5, min_pillars=2, confirm=1)  # the shipped parameters


class ScriptedModel:
    """A stand-in for the members (unit test of the fusion alone): a decision every ``STRIDE`` samples with the
    P(slip) ``p_of(index)``, alarmed at 0.5; the index counts from the latest restart."""

    def __init__(self, p_of: Callable[[int], float]) -> None:
        self.p_of = p_of
        self.index = -1
        self.step_seconds: list[float | None] = []
        self.last_step_s: float | None = None
        self.clean_block = True
        self.windows = self.resets = 0
        self.features = None
        self._tared = True
        self.tare_samples = 0

    def push_many(self, force: np.ndarray, t_us: Sequence[int] | np.ndarray,
                  disp: np.ndarray | None = None) -> list[tuple[int, Detection]]:
        base = self.index + 1
        self.index += len(force)
        out = []
        for i in range(len(force)):
            if (base + i + 1) % STRIDE == 0:
                p = self.p_of(base + i)
                out.append((i, Detection(base + i, int(t_us[i]), p, p, p >= 0.5, False)))
        self.step_seconds = [1e-5] * len(out)
        return out

    def samples_to_decision(self) -> int:
        return STRIDE - (self.index + 1) % STRIDE

    def restart(self, retare: bool = False) -> None:
        self.resets += 1
        self.index = -1  # (the script runs again from its start)


def _rule(rec: Recording) -> ReferencePillarDetector:
    return ReferencePillarDetector(RULE, offset=baseline_offset(rec.force, rec.disp, (0, 100)))


def _confirmed(rec: Recording, p_of: Callable[[int], float]) -> ConfirmedDetector:
    return ConfirmedDetector(ScriptedModel(p_of), [_rule(rec)], LEVEL, WITHIN_US)  # type: ignore[arg-type]


def _stream(det: ConfirmedDetector, rec: Recording, sizes: Sequence[int]) -> list[tuple[int, bool, bool]]:
    """(sample index, alarm, rising edge) of every decision, the recording pushed in blocks of ``sizes`` in turn."""
    out, start, j = [], 0, 0
    while start < len(rec):
        end = min(len(rec), start + sizes[j % len(sizes)])
        dets = det.push_many(rec.force[start:end], rec.t_us[start:end], rec.disp[start:end])
        assert len(det.step_seconds) == len(dets)
        out += [(start + i, d.alarm, d.rising_edge) for i, d in dets]
        start, j = end, j + 1
    return out


def _expected(rec: Recording, p_of: Callable[[int], float]) -> list[tuple[int, bool, bool]]:
    """The fusion written out: a rule that ran over the whole recording, the model's decisions, and at every decision
    of either the model's alarm or the rule's while some model decision in (t - window, t] reached the level; each
    model decision, and a rule decision where the fused alarm changes."""
    rule = {i: d.alarm for i, d in _rule(rec).push_many(rec.force, rec.t_us, rec.disp)}
    model = {i: p_of(i) for i in range(len(rec)) if (i + 1) % STRIDE == 0}
    out, m_alarm, r_alarm, before = [], False, False, False
    for i in sorted(set(rule) | set(model)):
        t = int(rec.t_us[i])
        if i in model:
            m_alarm = model[i] >= 0.5
        r_alarm = rule.get(i, r_alarm)
        armed = any(p >= LEVEL and t - WITHIN_US < int(rec.t_us[m]) <= t for m, p in model.items())
        alarm = m_alarm or (r_alarm and armed)
        if i in model or alarm != before:
            out.append((i, alarm, alarm and not before))
        before = alarm
    return out


@pytest.fixture(scope="module")
def slip() -> Recording:
    return make_scene(seed=1, duration_s=2.0)


def _leaning(lo: int, hi: int, p: float = 0.35) -> Callable[[int], float]:
    """A model at ``p`` (below its threshold) from sample ``lo`` to ``hi``, 0 elsewhere."""
    return lambda i: p if lo <= i < hi else 0.0


def test_the_rule_alarms_only_within_the_window_after_the_model_reached_the_level(slip: Recording) -> None:
    rule_alarms = [i for i, d in _rule(slip).push_many(slip.force, slip.t_us, slip.disp) if d.alarm]
    assert rule_alarms, "the synthetic slip must alarm the rule"
    first = rule_alarms[0]
    # Leaning from well before the rule's first alarm: the fused alarm is the rule's, at that sample.
    got = _stream(_confirmed(slip, _leaning(first - 300, len(slip))), slip, [10])
    assert got == _expected(slip, _leaning(first - 300, len(slip)))
    assert next(i for i, _, r in got if r) == first
    # The model quiet throughout: no alarm at all, and the rule never ran.
    quiet = _confirmed(slip, lambda i: 0.0)
    assert not any(a for _, a, _ in _stream(quiet, slip, [10]))
    assert quiet.rule_blocks == 0
    # Leaning only until 150 ms before the rule's alarm: too long ago, no alarm; until 50 ms before: confirmed.
    assert not any(a for _, a, _ in _stream(_confirmed(slip, _leaning(first - 400, first - 150)), slip, [10]))
    late = _stream(_confirmed(slip, _leaning(first - 400, first - 50)), slip, [10])
    assert late == _expected(slip, _leaning(first - 400, first - 50))
    assert any(a for _, a, _ in late)


@pytest.mark.parametrize("sizes", [[1], [7], [10], [37, 3], [1000]])
@pytest.mark.parametrize("lo", [0, 401, 733, 998])
def test_any_blocks_and_any_start_of_the_rule_give_the_fusion_of_a_rule_that_ran_all_along(
        slip: Recording, sizes: list[int], lo: int) -> None:
    # The rule starts from the ring wherever the model first leans (before its history is full, on and off a multiple
    # of its stride), and stops and starts again (the model leans twice).
    def p_of(i: int) -> float:
        return 0.35 if lo <= i < lo + 250 or lo + 500 <= i < lo + 900 else 0.0

    assert _stream(_confirmed(slip, p_of), slip, sizes) == _expected(slip, p_of)


def test_the_models_own_alarm_stands_and_a_restart_forgets_the_rule(slip: Recording) -> None:
    alarmed = _confirmed(slip, lambda i: 0.9 if i >= 900 else 0.0)
    got = _stream(alarmed, slip, [10])
    assert got == _expected(slip, lambda i: 0.9 if i >= 900 else 0.0)
    assert all(a for i, a, _ in got if i >= 909)
    alarmed.restart()
    assert alarmed._seen == 0 and not any(alarmed._running) and alarmed.model.resets == 1  # type: ignore[attr-defined]
    assert _stream(alarmed, slip, [10]) == got  # the same recording again: the same decisions


def test_the_ring_holds_more_than_the_rule_reaches_back() -> None:
    # Median, speed lag, stride: the samples a rule decision depends on; the replay must reach back past them.
    fe = ReferencePillarDetector(RULE).frontend.params
    assert fe.median + fe.lag + 2 * fe.stride <= HISTORY


BASE = {"sensor": {"port": "/dev/ttyACM0"}, "model": {"manifest": "slip_ensemble_int8"},
        "gripper": {"port": "/dev/ttyUSB0", "hold_position": 2048, "secure_position": 2600, "hold_pwm": 300,
                    "secure_pwm": 700},
        "arm": {"host": "192.168.1.10"}}


def _cfg(decision: dict, **sections: dict) -> SlipdConfig:
    return config_from_dict({**BASE, "decision": decision,
                             **{k: {**BASE.get(k, {}), **v} for k, v in sections.items()}}, "c.yaml")


@pytest.mark.parametrize(("decision", "sections", "key", "reason"), [
    ({"confirm_within_ms": 50}, {}, "decision.confirm_within_ms", "without decision.confirm_rule"),
    ({"confirm_rule": 0.3}, {"model": {"detector": "reference_pillar"}}, "decision.confirm_rule", "onnx"),
    ({"confirm_rule": 0.0}, {}, "decision.confirm_rule", "greater than 0"),
])
def test_the_config_refuses_what_the_confirmed_rule_cannot_do(decision: dict, sections: dict, key: str,
                                                              reason: str) -> None:
    assert _cfg({"confirm_rule": 0.3}).decision.confirm_rule == 0.3
    with pytest.raises(ConfigError) as exc:
        _cfg(decision, **sections)
    assert any(key in p and reason in p for p in exc.value.problems), exc.value.problems


def test_build_detector_confirms_the_packaged_model_with_the_packaged_rule() -> None:
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble

    cfg = _cfg({"confirm_rule": 0.25, "confirm_within_ms": 80})
    det = build_detector(cfg, Ensemble.load(cfg.model.manifest))
    assert isinstance(det, ConfirmedDetector)
    assert (det.level, det.within_us) == (0.25, 80_000)
    # The parameters tuned on gripper lifts (the packaged baselines_transfer.json), those the figures were measured with
    assert det.rules[0].params == ReferencePillarParams(ratio=0.6, min_ref_speed=1.0, min_pillars=1, confirm=2)
    det.set_offset(np.full((9, 3), 0.5, np.float32))  # a re-zero: the model's forces, the rule's normal forces
    assert np.all(det.offset == 0.5)
    assert np.all(det.rules[0].frontend.offset[:, 2] == 0.5) and np.all(det.rules[0].frontend.offset[:, :2] == 0.0)


def test_a_reload_leaves_the_confirmed_rule_for_a_restart() -> None:
    from slipd.daemon.reload import changed_keys, is_live

    old, new = _cfg({"threshold": 0.5}), _cfg({"threshold": 0.6, "confirm_rule": 0.3})
    keys = changed_keys(old, new)
    assert [k for k in keys if is_live(k)] == ["decision.threshold"]
    assert [k for k in keys if not is_live(k)] == ["decision.confirm_rule"]


def test_samples_to_decision_is_the_members_next_or_the_running_rules(slip: Recording) -> None:
    # The loop holds reads back until the next deciding sample: the rule's too while it runs (its decisions fall on
    # every fifth sample from the tenth, as a rule that ran from the start).
    det = _confirmed(slip, _leaning(400, 700))
    stride = det.rules[0].frontend.spec.step
    ran = 0
    for i in range(1000):
        due = det.samples_to_decision()
        running = det._running[0]
        nxt = [j for j in range(i, i + 20) if (j + 1) % STRIDE == 0 or (running and j >= 10 and j % stride == 0)]
        assert due == nxt[0] - i + 1, i
        ran += det._running[0]
        det.push_many(slip.force[i : i + 1], slip.t_us[i : i + 1], slip.disp[i : i + 1])
    assert ran > 300


@pytest.fixture(scope="module")
def lift() -> Recording:
    """A simulated gripper lift on which the confirmed rule alarms before the model alone (the transfer test's)."""
    from slipd.sim.datasets import dataset_scenes
    from slipd.sim.scene import generate, parse_scene

    scene, seed = list(dataset_scenes("transfer", "test", 2, seed=7))[1]
    return generate(parse_scene(scene) if isinstance(scene, dict) else scene, seed)


def _decide(det: object, force: np.ndarray, rec: Recording, disp: np.ndarray, block: int = 10) -> list[tuple]:
    out = []
    for k in range(0, len(rec), block):
        dets = det.push_many(force[k : k + block], rec.t_us[k : k + block], disp[k : k + block])  # type: ignore[attr-defined]
        out += [(d.index, d.sensor, d.p_slip, d.alarm, d.rising_edge) for _, d in dets]
    return out


def test_two_fingers_each_confirm_their_own_rule_as_one_finger_alone(lift: Recording) -> None:
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble

    cfg = _cfg({"confirm_rule": 0.3}, sensor={"sensors": 2})
    ens = Ensemble.load(cfg.model.manifest)
    still = np.broadcast_to(lift.force[:1], lift.force.shape)  # the other finger: the lift's first sample throughout
    force = np.stack([lift.force, still], axis=1)
    disp = np.stack([lift.disp, np.broadcast_to(lift.disp[:1], lift.disp.shape)], axis=1)
    two = _decide(build_detector(cfg, ens), force, lift, disp)
    one = _cfg({"confirm_rule": 0.3})
    alone = []
    for s, (f, d) in enumerate(((lift.force, lift.disp), (force[:, 1], disp[:, 1]))):
        ens.reset()
        alone += [(i, s, p, a, r) for i, _, p, a, r in _decide(build_detector(one, ens), f, lift, d)]
    assert sorted(two) == sorted(alone)
    assert any(r for _, s, _, _, r in two if s == 0) and not any(a for _, s, _, a, _ in two if s == 1)


def test_the_start_up_tare_tares_the_rule_on_the_same_stretch(lift: Recording) -> None:
    from slipd.detect.build import baseline_params_path, build_detector, confirmed_detector
    from slipd.detect.detector import Detector
    from slipd.detect.ensemble import Ensemble
    from slipd.detect.features import tare_offset

    bias_f, bias_d = np.float32(0.4), np.float32(0.03)  # a sensor that was not zeroed
    force, disp = lift.force + bias_f, lift.disp + bias_d
    cfg = _cfg({"confirm_rule": 0.3}, sensor={"tare": "startup", "tare_samples": 300})
    ens = Ensemble.load(cfg.model.manifest)
    det = build_detector(cfg, ens)
    got = _decide(det, force, lift, disp, block=37)
    rule_offset = baseline_offset(force, disp, (0, 300))
    assert isinstance(det, ConfirmedDetector)
    assert np.array_equal(det.rules[0].frontend.offset, rule_offset) and abs(rule_offset[:, :2].mean() - 0.03) < 0.01
    # The same as the parts tared explicitly on that stretch (the evaluation's way).
    ens.reset()
    model = Detector(ens, det.model.decision, det.model.spec, offset=tare_offset(force, 0, 300),  # type: ignore[union-attr]
                     press_rise=det.model.press_rise)  # type: ignore[union-attr]
    explicit = confirmed_detector(model, baseline_params_path(cfg), 0.3, 100.0)
    explicit.rules[0].frontend.set_offset(rule_offset)
    # (the start-up tare reports one decision for its stretch, the explicit offset every one: compare after it)
    after = [d for d in got if d[0] >= 300]
    assert after == [d for d in _decide(explicit, force, lift, disp, block=37) if d[0] >= 300]
    assert any(r for *_, r in after)


def test_an_alarm_on_the_rule_alone_says_so_and_the_models_own_does_not(slip: Recording) -> None:
    # The model leaning below its threshold: every alarm is the rule's alone (grip control takes no friction sample
    # from it); the model alarmed: its own.
    leaning = _confirmed(slip, _leaning(0, len(slip)))
    dets = [d for k in range(0, len(slip), 10)
            for _, d in leaning.push_many(slip.force[k : k + 10], slip.t_us[k : k + 10], slip.disp[k : k + 10])]
    assert any(d.alarm for d in dets) and all(d.rule_only == d.alarm for d in dets)
    alarmed = _confirmed(slip, lambda i: 0.9)
    dets = [d for _, d in alarmed.push_many(slip.force, slip.t_us, slip.disp)]
    assert any(d.alarm for d in dets) and not any(d.rule_only for d in dets)

