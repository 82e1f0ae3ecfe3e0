"""Heuristic baselines: they detect a synthetic slip, stay quiet on holds and stops, stream == batch, tuning."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import K_T, make_scene

from slipd.detect.baselines import (
    DecelerationDetector,
    DecelerationParams,
    FrontEndParams,
    ReferencePillarDetector,
    baseline_offset,
    confirm_flags,
    load_params,
    make_baseline,
    recent_max,
)
from slipd.recording import Recording
from sliplab.metrics import SceneTruth, offline_outcome


def _stream(det, rec: Recording, use_disp: bool = True) -> list:
    out = []
    for i in range(len(rec)):
        d = det.push(rec.force[i], int(rec.t_us[i]), rec.disp[i] if use_disp else None)
        if d is not None:
            out.append(d)
    return out


def _first_alarm_s(dets) -> float | None:
    for d in dets:
        if d.alarm:
            return d.index / 1000.0
    return None


def _detectors(rec: Recording, use_disp: bool = True):
    off = baseline_offset(rec.force, rec.disp if use_disp else None, (0, 100))
    return [ReferencePillarDetector(offset=off), DecelerationDetector(offset=off)]


@pytest.fixture(scope="module")
def slip_scene() -> Recording:
    return make_scene(seed=1)


def test_synthetic_scene_truth_is_sane(slip_scene: Recording) -> None:
    truth = SceneTruth.from_recording(slip_scene, "s")
    # Corners (1 N, limit 0.286 mm at 2 mm/s) slip ~143 ms after motion start, the centre ~429 ms after.
    assert truth.onset_s == pytest.approx(0.6 + 1 / K_T / 2, abs=0.003)
    assert truth.gross_slip_s == pytest.approx(0.6 + 3 / K_T / 2, abs=0.003)


@pytest.mark.parametrize("use_disp", [True, False])
def test_both_baselines_detect_translational_slip(slip_scene: Recording, use_disp: bool) -> None:
    truth = SceneTruth.from_recording(slip_scene, "s")
    for det in _detectors(slip_scene, use_disp):
        first = _first_alarm_s(_stream(det, slip_scene, use_disp))
        assert offline_outcome(truth, first) == "tp", (det.name, first, truth.onset_s, truth.gross_slip_s)
        # Not before the motion even started: the alarm is a reaction to the slip, not to the press.
        assert first > truth.motion_start_s


def test_both_baselines_quiet_on_a_steady_hold() -> None:
    rec = make_scene(kind="stop", duration_s=3.0, move_s=10.0, seed=2)  # pressed and held, never moved
    for det in _detectors(rec):
        dets = _stream(det, rec)
        assert dets and not any(d.alarm for d in dets), det.name


def test_both_baselines_quiet_on_a_stop_before_slip() -> None:
    rec = make_scene(kind="stop", stop_s=0.7, seed=3)  # 0.2 mm of travel: no tip reaches its limit
    assert not rec.label.any()
    for det in _detectors(rec):
        assert not any(d.alarm for d in _stream(det, rec)), det.name


def test_rotation_about_the_centre_only_the_deceleration_rule_sees_it() -> None:
    # Wang et al.: the reference-pillar method cannot see rotations about the centre pillar (the reference).
    rec = make_scene(motion="rotation", speed=20.0, seed=4)
    truth = SceneTruth.from_recording(rec, "r")
    ref, dec = _detectors(rec)
    assert offline_outcome(truth, _first_alarm_s(_stream(dec, rec))) == "tp"
    assert _first_alarm_s(_stream(ref, rec)) is None


def test_streaming_equals_batch(slip_scene: Recording) -> None:
    for det in _detectors(slip_scene):
        dets = _stream(det, slip_scene)
        batch_det = type(det)(offset=det.frontend.offset)
        ends, alarm, score = batch_det.run(slip_scene.force, slip_scene.disp)
        np.testing.assert_array_equal([d.index for d in dets], ends)
        np.testing.assert_array_equal([d.alarm for d in dets], alarm)
        np.testing.assert_allclose([d.p_slip for d in dets], score, rtol=1e-6)
        edges = [d.rising_edge for d in dets]
        assert sum(edges) >= 1 and edges.index(True) == int(np.argmax(alarm))


def test_confirm_and_recent_max() -> None:
    flag = np.array([1, 0, 1, 1, 1, 0, 1, 1], bool)
    np.testing.assert_array_equal(confirm_flags(flag, 1), flag)
    np.testing.assert_array_equal(confirm_flags(flag, 2), [0, 0, 0, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(confirm_flags(flag, 3), [0, 0, 0, 0, 1, 0, 0, 0])
    s = np.array([[1.0], [3.0], [2.0], [0.5], [0.2]])
    np.testing.assert_array_equal(recent_max(s, 2)[:, 0], [1, 3, 3, 2, 0.5])


def test_parameters_are_validated_and_loaded(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown baseline 'nope'"):
        make_baseline("nope")
    with pytest.raises(ValueError, match=r"deceleration: unknown parameter\(s\) \['ratio'\]"):
        make_baseline("deceleration", {"ratio": 0.5})
    det = make_baseline("deceleration", {"drop": 0.3, "memory_s": 0.1}, {"stride": 10, "lag": 20})
    assert det.params == DecelerationParams(drop=0.3, memory_s=0.1)
    assert det.frontend.params == FrontEndParams(stride=10, lag=20)
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"deceleration": {"params": {"drop": 0.3}, "frontend": {}}}))
    assert load_params(path, "deceleration") == ({"drop": 0.3}, {})
    with pytest.raises(ValueError, match="no entry 'reference_pillar'"):
        load_params(path, "reference_pillar")
    with pytest.raises(ValueError, match="cannot read"):
        load_params(tmp_path / "missing.json", "deceleration")


def test_tuner_uses_the_train_split_and_writes_json(tmp_path: Path) -> None:
    from sliplab.evaluate import main

    train = tmp_path / "data" / "offline_train"
    for i, (kind, kw) in enumerate([("slip", {}), ("slip", {"direction_deg": 200.0, "speed": 3.0}),
                                    ("slip", {"motion": "rotation", "speed": 20.0}),
                                    ("stop", {"stop_s": 0.7}), ("stop", {"move_s": 10.0})]):
        make_scene(kind=kind, seed=10 + i, duration_s=1.2, **kw).save(train / f"s{i}.npz")
    out = tmp_path / "baselines.json"
    small = {"--tune-baselines": None, "--data-root": str(tmp_path / "data"), "--baseline-params": str(out)}
    argv = [x for k, v in small.items() for x in ([k] if v is None else [k, v])]
    assert main([*argv, "--baseline", "reference_pillar"]) == 0
    tuned = json.loads(out.read_text())
    entry = tuned["reference_pillar"]
    assert entry["tuned_on"]["folder"].endswith("offline_train")
    # Two translations caught, the rotation about the centre is invisible to this rule, both stops quiet.
    assert entry["train_figures"]["balanced_success"] == pytest.approx((2 / 3 + 1) / 2)
    # The tuned parameters load back into a working detector, and streaming that detector over the same
    # recordings gives the figure the (vectorised, concatenated) tuner computed.
    params, frontend = load_params(out, "reference_pillar")
    assert make_baseline("reference_pillar", params, frontend).params.ratio == params["ratio"]
    report = tmp_path / "train_eval.json"
    assert main(["--baseline", "reference_pillar", "--baseline-params", str(out), "--recordings", str(train),
                 "--json", str(report)]) == 0
    summary = json.loads(report.read_text())["summary"]
    assert summary["offline"]["balanced_success"] == pytest.approx(entry["train_figures"]["balanced_success"])
    assert summary["latency_s"]["median"] == pytest.approx(entry["train_figures"]["median_abs_latency_s"])


@pytest.mark.parametrize("name", ["reference_pillar", "deceleration"])
def test_replay_feeds_the_heuristics_the_recorded_displacements(name: str) -> None:
    """The heuristics were tuned on the recorded tip displacements (sliplab.evaluate); `slipd replay` and the daemon
    must feed them the same, not forces over the pillar stiffness (they once dropped the displacements)."""
    from conftest import ROOT

    from slipd.config import load_config, override
    from slipd.detect.ensemble import Ensemble
    from slipd.detect.replay import detector_for, replay
    from slipd.models import SAMPLE_RECORDING, packaged

    rec = Recording.load(SAMPLE_RECORDING)
    cfg = override(load_config(ROOT / "config" / "sim.yaml"), {"model.detector": name})
    ens = Ensemble.load(packaged("slip_ensemble_int8"))

    def direct(disp: np.ndarray | None) -> list[tuple[int, float]]:
        return [(i, d.p_slip) for i, d in detector_for(rec, ens, cfg).push_many(rec.force, rec.t_us, disp)]

    replayed = [(d.index, d.p_slip) for d in replay(rec, ens, cfg)]
    assert replayed == direct(rec.disp)
    assert replayed != direct(None)  # the displacements make a difference the test can see


@pytest.mark.parametrize("name", ["reference_pillar", "deceleration"])
def test_a_block_at_a_time_gives_the_detections_of_a_push_per_sample(slip_scene: Recording, name: str) -> None:
    """The daemon hands the heuristic a block per read (``push_many``); evaluation pushes sample by sample. Blocks of
    uneven lengths (1 to 37 samples: across decisions and the deceleration rule's memory) give the same detections,
    contact states included, bit for bit."""
    from slipd.detect.detector import HeuristicDetector
    from sliplab.robustness import DEFAULT_BASELINES

    rec = slip_scene
    off = baseline_offset(rec.force, rec.disp, (0, 100))
    one, blocks = HeuristicDetector(name, DEFAULT_BASELINES, off), HeuristicDetector(name, DEFAULT_BASELINES, off)
    want = [(i, d) for i in range(len(rec)) if (d := one.push(rec.force[i], int(rec.t_us[i]), rec.disp[i])) is not None]
    rng = np.random.default_rng(7)
    got, start = [], 0
    while start < len(rec):
        end = min(len(rec), start + int(rng.integers(1, 38)))
        got += [(start + i, d) for i, d in blocks.push_many(rec.force[start:end], rec.t_us[start:end],
                                                            rec.disp[start:end])]
        start = end
    assert len(want) > 50 and any(d.alarm for _, d in want)
    assert [(i, d.index, d.t_us, d.p_slip, d.alarm, d.rising_edge, d.contact) for i, d in got] == \
        [(i, d.index, d.t_us, d.p_slip, d.alarm, d.rising_edge, d.contact) for i, d in want]
    assert blocks.windows == one.windows == len(want)
