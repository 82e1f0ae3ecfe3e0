"""The method's metrics on hand-made truth/decision cases, and tools/evaluate.py end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slipd.detect.decision import Detection
from slipd.recording import Recording
from sliplab.metrics import (
    SceneResult,
    SceneTruth,
    Trace,
    d_norm_at,
    evaluate_scene,
    false_alarms_per_hour,
    gross_slip_time,
    motion_components,
    offline_outcome,
    online_outcome,
    summarize,
)


def slip_truth(onset: float = 1.0, gross: float = 1.5, **kw) -> SceneTruth:
    return SceneTruth(name="s", kind="slip", duration_s=4.0, onset_s=onset, gross_slip_s=gross, **kw)


def stop_truth(duration: float = 3.0) -> SceneTruth:
    return SceneTruth(name="h", kind="stop", duration_s=duration)


def trace(alarm_times: list[float], until: float = 4.0, dt: float = 0.04) -> Trace:
    """Decisions every ``dt``; the alarm is on during [t, t + dt) for each t in ``alarm_times``."""
    ts = list(np.round(np.arange(0.0, until, dt), 6))
    on = [any(abs(t - a) < dt / 2 for a in alarm_times) for t in ts]
    edges = [a and (i == 0 or not on[i - 1]) for i, a in enumerate(on)]
    return Trace(ts, [0.9 if a else 0.1 for a in on], on, edges)


# --------------------------------------------------------------------------- offline criterion
@pytest.mark.parametrize(
    ("alarm", "outcome"),
    [
        (1.2, "tp"),  # inside [onset, gross]
        (0.72, "tp"),  # within the 0.3 s tolerance before the onset
        (0.68, "early"),  # more than 0.3 s before the onset
        (1.52, "late"),  # after gross slip
        (None, "missed"),
    ],
)
def test_offline_outcome_of_a_slip_sequence(alarm, outcome) -> None:
    assert offline_outcome(slip_truth(), alarm) == outcome


def test_only_the_first_alarm_counts_and_latency_has_a_sign() -> None:
    # An early alarm followed by a well-timed one is still a failure: the first alarm would have reacted.
    r = evaluate_scene(slip_truth(), trace([0.4, 1.2]))
    assert r.offline_outcome == "early" and r.latency_s is None
    before = evaluate_scene(slip_truth(), trace([0.8]))
    after = evaluate_scene(slip_truth(), trace([1.12]))
    assert before.offline_outcome == after.offline_outcome == "tp"
    assert before.latency_s == pytest.approx(-0.2)
    assert after.latency_s == pytest.approx(0.12)


def test_stop_sequences() -> None:
    assert offline_outcome(stop_truth(), None) == "tn"
    assert offline_outcome(stop_truth(), 2.0) == "fp"
    r = evaluate_scene(stop_truth(), trace([1.0, 1.04, 2.0]))  # one alarm lasting two decisions, then another
    assert r.offline_outcome == "fp" and r.rising_edges == 2


def test_slip_without_onset_is_not_scored_offline() -> None:
    assert offline_outcome(slip_truth(onset=None), 1.0) is None
    rs = [evaluate_scene(slip_truth(onset=None), trace([1.0])), evaluate_scene(slip_truth(), trace([1.0]))]
    s = summarize(rs)
    assert (s.offline.n, s.offline.tp, s.offline_unlabelled) == (1, 1, 1)


# --------------------------------------------------------------------------- online criterion and D_norm
def _gripper_truth(motion: str, rate_mm_s: float = 4.0, rate_deg_s: float = 0.0) -> SceneTruth:
    t = np.arange(0, 2.0, 0.001)
    moving = np.clip(t - 0.5, 0, None)  # the object starts to move relative to the finger at 0.5 s
    om = np.stack([rate_mm_s * moving * 0.6, rate_mm_s * moving * 0.8, rate_deg_s * moving], axis=1)
    om += np.array([0.3, -0.2, 0.1])  # a settling offset before motion start is not slip
    return SceneTruth(
        name="g", kind="slip", duration_s=2.0, motion=motion, onset_s=0.55, gross_slip_s=None,
        motion_start_s=0.5, online_gross_s=gross_slip_time(t, om, 0.5), t_s=t, object_motion=om,
    )


def test_gross_slip_time_from_object_motion() -> None:
    tr = _gripper_truth("translation", rate_mm_s=4.0)
    assert tr.online_gross_s == pytest.approx(1.0, abs=0.002)  # 2 mm at 4 mm/s after 0.5 s
    rot = _gripper_truth("rotation", rate_mm_s=0.0, rate_deg_s=8.0)
    assert rot.online_gross_s == pytest.approx(0.75, abs=0.002)  # 2 deg at 8 deg/s
    t = np.arange(0, 1.0, 0.001)
    assert gross_slip_time(t, np.zeros((len(t), 3))) is None


def test_online_outcome() -> None:
    tr = _gripper_truth("translation")
    assert online_outcome(tr, 0.7) == "success"
    assert online_outcome(tr, 0.4) == "early"  # before the robot moved
    assert online_outcome(tr, 1.1) == "late"  # after 2 mm of relative motion
    assert online_outcome(tr, None) == "missed"
    assert online_outcome(stop_truth(), None) == "tn"
    assert online_outcome(slip_truth(), 1.0) is None  # no motion-start truth: not an online scene


def test_d_norm_translation_rotation_and_combined() -> None:
    tr = _gripper_truth("translation", rate_mm_s=4.0)
    assert d_norm_at(tr, 0.75) == pytest.approx(0.5, abs=0.01)  # 1 mm of 2 mm
    rot = _gripper_truth("rotation", rate_mm_s=0.0, rate_deg_s=4.0)
    assert d_norm_at(rot, 0.6) == pytest.approx(0.2, abs=0.01)  # 0.4 deg of 2 deg
    both = _gripper_truth("translation+rotation", rate_mm_s=4.0, rate_deg_s=2.0)
    assert d_norm_at(both, 1.0) == pytest.approx((1.0 + 0.5) / 2, abs=0.01)
    assert motion_components("rotation") == (False, True)
    assert motion_components("translation_rotation") == (True, True)
    assert motion_components("lift") == (True, False)
    assert d_norm_at(slip_truth(), 1.0) is None  # no object motion recorded


# --------------------------------------------------------------------------- aggregates
def test_false_alarms_per_hour_counts_edges_over_no_slip_time() -> None:
    rs = [evaluate_scene(stop_truth(1800.0), trace([1.0, 2.0], until=3.0)),
          evaluate_scene(stop_truth(1800.0), trace([0.52], until=3.0)),
          evaluate_scene(slip_truth(), trace([0.2, 1.0, 2.0]))]  # slip scenes do not count
    edges, hours, per_hour = false_alarms_per_hour(rs)
    assert (edges, hours, per_hour) == (3, 1.0, 3.0)


def test_summary_confusion_latency_and_json() -> None:
    rs = [evaluate_scene(slip_truth(), trace([a])) for a in (1.0, 1.04, 1.2, 0.2)]
    rs.append(evaluate_scene(slip_truth(), trace([])))
    rs += [evaluate_scene(stop_truth(), trace([])), evaluate_scene(stop_truth(), trace([2.0]))]
    s = summarize(rs)
    assert (s.offline.tp, s.offline.fn, s.offline.fp, s.offline.tn) == (3, 2, 1, 1)
    assert s.offline.success_rate == pytest.approx(4 / 7)
    assert s.offline.balanced_success == pytest.approx((3 / 5 + 1 / 2) / 2)
    assert s.offline_failures == {"early": 1, "missed": 1, "fp": 1}
    assert s.latency_s.n == 3 and s.latency_s.median == pytest.approx(0.04)
    assert s.latency_s.p90 == pytest.approx(np.percentile([0.0, 0.04, 0.2], 90))
    assert s.online is None and s.d_norm.n == 0
    back = json.loads(json.dumps({"summary": s.to_dict(), "scenes": [r.to_dict() for r in rs]}))
    assert back["summary"]["offline"]["tp"] == 3 and back["scenes"][0]["offline_outcome"] == "tp"


def test_trace_uses_the_sample_index_and_skips_invalid_decisions() -> None:
    t_us = 5_000_000 + np.arange(200, dtype=np.int64) * 1000
    dets = [Detection(39, 999, 0.1, 0.2, False, False),
            Detection(79, 999, float("nan"), 0.0, False, False, valid=False),
            Detection(119, 999, 0.8, 1.0, True, True)]
    tr = Trace.from_detections(dets, t_us)
    assert tr.t_s == [pytest.approx(0.039), pytest.approx(0.119)]
    assert tr.first_alarm_s() == pytest.approx(0.119) and tr.n_rising_edges() == 1


def test_truth_from_a_recording() -> None:
    n = 1000
    label = np.zeros(n, np.uint8)
    label[300:450] = 1
    rec = Recording(t_us=np.arange(n) * 1000, force=np.zeros((n, 9, 3)), disp=np.zeros((n, 9, 3)), label=label,
                    meta={"motion": "rotation", "events": {"motion_start": 0.2, "onset": 0.31}})
    tr = SceneTruth.from_recording(rec, "r")
    # The label is the truth; kind inferred from it when meta has none.
    assert (tr.kind, tr.onset_s, tr.gross_slip_s, tr.motion_start_s) == ("slip", 0.3, 0.45, 0.2)
    assert tr.duration_s == pytest.approx(1.0)
    rec.meta["kind"] = "wobble"
    with pytest.raises(ValueError, match="r: meta kind 'wobble'"):
        SceneTruth.from_recording(rec, "r")


def test_a_slip_without_an_incipient_stage_is_scored_online_only() -> None:
    """One pillar carried the grasp: it slid, and with it the whole contact, on one sample. The label is empty and
    the events put gross slip on the onset; the offline criterion has no window there, the online one does."""
    n = 1000
    rec = Recording(t_us=np.arange(n) * 1000, force=np.zeros((n, 9, 3)), disp=np.zeros((n, 9, 3)),
                    label=np.zeros(n, np.uint8),
                    meta={"kind": "slip", "motion": "lift", "events": {"motion_start": 0.2, "onset": 0.6,
                                                                      "gross_slip": 0.6, "gross_motion": 0.62}})
    tr = SceneTruth.from_recording(rec, "r")
    assert (tr.kind, tr.onset_s, tr.gross_slip_s, tr.online_gross_s) == ("slip", None, None, 0.62)
    assert offline_outcome(tr, 0.61) is None and online_outcome(tr, 0.61) == "success"
    rec.meta["events"]["gross_slip"] = 0.64  # a stage of 40 ms: scored offline again
    assert SceneTruth.from_recording(rec, "r").onset_s == 0.6


def test_a_partial_slip_that_stopped_by_itself_is_counted_apart() -> None:
    """Some pillars slid and stuck again, and the grasp held: neither criterion scores it, whether it alarmed or
    not, and the summary counts how many such recordings alarmed."""
    n = 1000
    rec = Recording(t_us=np.arange(n) * 1000, force=np.zeros((n, 9, 3)), disp=np.zeros((n, 9, 3)),
                    label=np.zeros(n, np.uint8), meta={"kind": "partial", "motion": "lift", "family": "engine",
                                                       "events": {"motion_start": 0.2}})
    tr = SceneTruth.from_recording(rec, "p")
    assert tr.is_partial and not tr.is_slip
    assert offline_outcome(tr, 0.5) is None and online_outcome(tr, 0.5) is None
    assert offline_outcome(tr, None) is None and online_outcome(tr, None) is None
    stop = SceneTruth(name="s", kind="stop", duration_s=1.0)
    dets = [Detection(t, t * 1000, float(t >= 500), float(t >= 500), t >= 500, t == 500) for t in range(0, n, 10)]
    alarmed = evaluate_scene(tr, Trace.from_detections(dets, rec.t_us))
    quiet = evaluate_scene(tr, Trace.from_detections([], rec.t_us))
    s = summarize([alarmed, quiet, evaluate_scene(stop, Trace.from_detections([], rec.t_us))])
    assert (s.partial, s.partial_alarmed, s.offline.n, s.offline.tn, s.offline_unlabelled) == (2, 1, 1, 1, 0)
    assert s.false_alarms == 0  # a partial slip's alarm is not a false alarm on a no-slip recording either


# --------------------------------------------------------------------------- tools/evaluate.py end to end
@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    from conftest import make_scene

    folder = tmp_path_factory.mktemp("scenes")
    make_scene(seed=1, duration_s=1.2).save(folder / "a_slip.npz")
    make_scene(motion="rotation", speed=20.0, seed=4, duration_s=1.2).save(folder / "b_rot.npz")
    make_scene(kind="stop", stop_s=0.7, seed=3, duration_s=1.2).save(folder / "c_stop.npz")
    return folder


def test_evaluate_baseline_end_to_end(scenes: Path, tmp_path: Path) -> None:
    from sliplab.evaluate import main

    out = tmp_path / "eval.json"
    assert main(["--baseline", "deceleration", "--baseline-params", str(_defaults(tmp_path)), "--recordings",
                 str(scenes), "--online", "--json", str(out), "--plots", str(tmp_path / "plots")]) == 0
    data = json.loads(out.read_text())
    s = data["summary"]
    assert s["n_scenes"] == 3
    assert (s["offline"]["tp"], s["offline"]["tn"]) == (2, 1) and s["offline"]["success_rate"] == 1.0
    # Online: the translation (2 mm/s) is caught well before 2 mm of motion; the 20 deg/s rotation passes
    # 2 deg at 0.70 s, only 17 ms after its first pillar slips, so its alarm is late by the online rule.
    assert (s["online"]["tp"], s["online"]["tn"], s["online_failures"]) == (1, 1, {"late": 1})
    assert s["d_norm"]["n"] == 1 and 0 < s["d_norm"]["median"] < 1
    assert s["latency_s"]["n"] == 2 and 0 <= s["latency_s"]["median"] < 0.1
    assert s["false_alarms"] == 0 and s["no_slip_hours"] == pytest.approx(1.2 / 3600)
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert {"confusion_offline.png", "confusion_online.png", "latency.png", "d_norm.png"} <= set(pngs)
    assert sum(p.startswith("trace_") for p in pngs) == 3


def _defaults(tmp_path: Path) -> Path:
    """Untuned defaults, so the test does not depend on a models/baselines.json in the working tree."""
    path = tmp_path / "defaults.json"
    path.write_text(json.dumps({"deceleration": {"params": {}, "frontend": {}},
                                "reference_pillar": {"params": {}, "frontend": {}}}))
    return path


def test_evaluate_model_end_to_end(scenes: Path, tmp_path: Path) -> None:
    """A tiny real ONNX ensemble (random weights) through the daemon's Detector: the figures are consistent."""
    torch = pytest.importorskip("torch")
    from slipd.detect.features import FeatureSpec
    from sliplab.evaluate import main
    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet

    spec = FeatureSpec(pillars=(0, 1, 2), window=8)
    nets = []
    for seed in range(2):
        torch.manual_seed(seed)
        nets.append(SlipNet(input_size=spec.input_size, hidden=8, enc=16, pred=(8, 8)).eval())
    export([fold_member(n.state_dict()) for n in nets], spec, tmp_path / "tiny.onnx", "trained", {}, threshold=0.5)
    out = tmp_path / "eval.json"
    assert main(["--model", str(tmp_path / "tiny.json"), "--recordings", str(scenes), "--json", str(out),
                 "--record-manifest"]) == 0
    data = json.loads(out.read_text())
    # The figures went into the manifest, which still loads (hash of the ONNX file unchanged).
    from slipd.detect.manifest import load_manifest

    metrics = load_manifest(tmp_path / "tiny.json").metrics
    recorded = metrics[f"eval_{scenes.name}"]
    assert recorded["offline"] == data["summary"]["offline"]
    # ... with its headline scalar (online success where the scenes have gripper trials, else offline), which
    # ``slipd models`` prints.
    online = data["summary"].get("online")
    key, head = (f"{scenes.name}_online_success", online) if online else (f"{scenes.name}_success",
                                                                           data["summary"]["offline"])
    assert metrics[key] == round(head["success_rate"], 4)
    results = [SceneResult(**r) for r in data["scenes"]]
    again = summarize(results).to_dict()
    assert again == data["summary"]
    assert data["summary"]["n_scenes"] == 3
    for r, tr in zip(results, data["truth"]):
        assert r.offline_outcome == offline_outcome(SceneTruth(**tr), r.first_alarm_s)


def test_stride_override_decides_more_often_and_tune_threshold_runs(scenes: Path, tmp_path: Path, capsys) -> None:
    """``--stride`` runs phase-shifted streams (a decision every 2 samples here, window 8); tune_threshold
    sweeps the same traces with either criterion."""
    torch = pytest.importorskip("torch")
    from slipd.detect.features import FeatureSpec
    from sliplab.evaluate import ModelRunner
    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet
    from sliplab.tune import main as tune

    spec = FeatureSpec(pillars=(0, 1, 2), window=8)
    torch.manual_seed(0)
    net = SlipNet(input_size=spec.input_size, hidden=8, enc=16, pred=(8, 8)).eval()
    export([fold_member(net.state_dict())], spec, tmp_path / "m.onnx", "trained", {}, threshold=0.5)
    rec = Recording.load(scenes / "a_slip.npz")
    every = ModelRunner(str(tmp_path / "m.json")).trace(rec)
    often = ModelRunner(str(tmp_path / "m.json"), stride=2).trace(rec)
    # Four times the decisions (less a few inside the tare stretch, where only the last is reported).
    assert 3.9 * len(every.t_s) <= len(often.t_s) <= 4 * len(every.t_s)
    assert np.median(np.diff(often.t_s)) == pytest.approx(0.002)
    assert tune(["--model", str(tmp_path / "m.json"), "--recordings", str(scenes), "--every", "1", "--workers", "1",
                 "--stride", "4", "--criterion", "online", "--grid", "0.2:0.8:0.3"]) == 0
    out = capsys.readouterr().out
    assert "3 train recordings" in out and "best threshold" in out


def test_noisy_displacements_touch_only_the_displacements(scenes: Path, tmp_path: Path) -> None:
    from sliplab.noisy_displacements import main as noisy

    assert noisy(["--sigma", "0.01", "--src", str(scenes), "--out", str(tmp_path / "n")]) == 0
    for path in sorted(scenes.glob("*.npz")):
        a, b = Recording.load(path), Recording.load(tmp_path / "n" / path.name)
        assert np.array_equal(a.force, b.force) and np.array_equal(a.label, b.label)
        d = (b.disp - a.disp).ravel()
        assert 0.008 < d.std() < 0.012 and abs(d.mean()) < 0.001
        assert b.meta["disp_noise_mm"] == 0.01


def test_by_motion_prints_each_motions_online_figures(capsys) -> None:
    """``--by-motion``: one line per motion, its slips caught in time, its stops alarmed and D_norm over the slips
    caught in time (a late alarm counts as a miss, not as a travel)."""
    from sliplab.evaluate import print_by_motion

    def scene(motion: str, kind: str, outcome: str, d: float | None) -> SceneResult:
        alarmed = outcome in ("success", "late", "fp")
        return SceneResult(name=f"{motion}_{kind}_{outcome}", kind=kind, motion=motion, duration_s=3.0,
                           first_alarm_s=1.0 if alarmed else None, offline_outcome=None, latency_s=None,
                           online_outcome=outcome, d_norm=d, rising_edges=int(alarmed))

    print_by_motion([scene("lift", "slip", "success", 0.1), scene("lift", "slip", "success", 0.3),
                     scene("lift", "stop", "tn", None), scene("push", "slip", "late", 1.2),
                     scene("push", "slip", "success", 0.5), scene("push", "stop", "fp", None)])
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[:4] for ln in lines[1:]] == [["lift", "2/2", "0/1", "0.20"], ["push", "1/2", "1/1", "0.50"]]
