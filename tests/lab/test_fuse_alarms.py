"""Fusing a model's alarms with the reference-pillar rule's: the fused stream on constructed decisions, and the tool
on a simulated slip scored by the same functions as its parts."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from sliplab.fuse_alarms import caught_by, fuse_traces, fused_results, main
from sliplab.metrics import Trace

MODEL = "slipd/models/slip_ensemble_int8.json"


def _trace(step_s: float, end_s: float, on: list[tuple[float, float]]) -> Trace:
    """Decisions every ``step_s`` until ``end_s`` with the alarm raised inside the [from, to) spans ``on``."""
    t = [round(i * step_s, 6) for i in range(round(end_s / step_s) + 1)]
    alarm = [any(a <= v < b for a, b in on) for v in t]
    rising = [x and (i == 0 or not alarm[i - 1]) for i, x in enumerate(alarm)]
    return Trace(t, [float(x) for x in alarm], alarm, rising)


def test_either_alarms_first_at_the_earlier_of_the_two_on_different_decision_grids() -> None:
    model = _trace(0.01, 1.0, [(0.43, 0.6)])
    rule = _trace(0.004, 1.0, [(0.412, 0.42), (0.8, 0.9)])
    fused = fuse_traces(model, rule, "either")
    assert fused.first_alarm_s() == pytest.approx(0.412)
    assert fuse_traces(rule, model, "either").first_alarm_s() == pytest.approx(0.412)  # symmetric
    assert fused.n_rising_edges() == 3  # the rule's blip, the model's span, the rule's late span
    assert fuse_traces(model, _trace(0.004, 1.0, []), "either").first_alarm_s() == pytest.approx(0.43)


def test_both_needs_the_other_alarm_within_the_window_in_either_order() -> None:
    model = _trace(0.01, 1.0, [(0.5, 0.52)])  # raised for two decisions, then dropped
    assert fuse_traces(model, _trace(0.004, 1.0, [(0.58, 0.7)]), "both", 0.1).first_alarm_s() == pytest.approx(0.58)
    assert fuse_traces(model, _trace(0.004, 1.0, [(0.64, 0.7)]), "both", 0.1).first_alarm_s() is None  # 120 ms on
    assert fuse_traces(model, _trace(0.004, 1.0, [(0.64, 0.7)]), "both", 0.2).first_alarm_s() == pytest.approx(0.64)
    # the rule first: the model's later alarm is the confirmation
    assert fuse_traces(model, _trace(0.004, 1.0, [(0.44, 0.448)]), "both", 0.1).first_alarm_s() == pytest.approx(0.5)
    assert fuse_traces(model, _trace(0.004, 1.0, []), "both", 0.1).first_alarm_s() is None
    with pytest.raises(ValueError, match="fusion mode 'and'"):
        fuse_traces(model, model, "and")


def test_the_tool_scores_fusions_with_the_parts_first_alarms(tmp_path, capsys) -> None:
    from slipd.detect.baselines import load_params
    from slipd.sim import parse_scene
    from slipd.sim.datasets import MEASUREMENT
    from slipd.sim.scene import generate_batch
    from sliplab.evaluate import evaluate_paths
    from sliplab.robustness import DEFAULT_BASELINES

    data = tmp_path / "data"
    data.mkdir()
    tl = [{"op": "press", "depth_mm": 1.0, "duration_s": 0.2}, {"op": "hold", "duration_s": 0.3},
          {"op": "move", "kind": "translation", "speed_mm_s": 3.0, "accel_mm_s2": 30.0, "duration_s": 0.6}]
    scenes = [parse_scene({"family": "hexapod", "sensor": "v1", "timeline": tl, "effects": list(MEASUREMENT)})]
    for i, rec in enumerate(generate_batch(scenes, [1])):
        rec.save(data / f"{i:05d}_slip.npz")
    paths = sorted(data.glob("*.npz"))
    rule = evaluate_paths(paths, "baseline", ("reference_pillar", *load_params(DEFAULT_BASELINES, "reference_pillar")),
                          progress=False)
    model = evaluate_paths(paths, "model", (MODEL, 0.0, None, None), progress=False)
    firsts = [r[0].first_alarm_s for r in (model[0], rule[0])]
    assert None not in firsts and firsts[0] != firsts[1]  # both alarm on this slip, at different decisions
    assert fused_results(model, rule, "either")[0][0].first_alarm_s == min(firsts)
    both = fused_results(model, rule, "both", 10.0)[0][0]  # a window longer than the recording: the later of the two
    assert both.first_alarm_s == max(firsts)
    with pytest.raises(ValueError, match="different recordings"):
        fused_results(model, [(rule[0][0], rule[0][1], replace(rule[0][2], name="other"))], "either")
    early = [(replace(model[0][0], offline_outcome="early"), *model[0][1:])]
    assert caught_by(early, rule) == {"both": 0, "model only": 0, "rule only": 1, "neither": 0}
    assert caught_by(early, early) == {"both": 0, "model only": 0, "rule only": 0, "neither": 1}
    js = tmp_path / "fused.json"
    assert main(["--data", str(data), "--model", MODEL, "--json", str(js)]) == 0
    report = json.loads(js.read_text())
    rows = report["detectors"]
    name = "models/slip_ensemble_int8"
    assert list(rows) == ["reference_pillar", name, f"{name} or reference_pillar",
                          f"{name} and reference_pillar within 100 ms", f"reference_pillar confirmed by {name} at 0.3"]
    assert report["slips_caught_by"] == {name: {"both": 1, "model only": 0, "rule only": 0, "neither": 0}}
    whole = rows[f"{name} or reference_pillar"]["all"]
    assert whole["n"] == 1 and whole["stop"] == 0
    assert np.isclose(rows["reference_pillar"]["offline_success"] or 0.0, float(rule[0][0].offline_success))
    printed = capsys.readouterr().out
    assert f"{name} or reference_pillar" in printed and "their fusions on" in printed


def test_the_tool_refuses_missing_inputs_with_one_line(tmp_path) -> None:
    with pytest.raises(SystemExit, match="no recordings"):
        main(["--data", str(tmp_path), "--model", MODEL])
    with pytest.raises(SystemExit) as exc:
        main(["--data", str(tmp_path), "--model", str(tmp_path / "none.json")])
    assert exc.value.code == 2  # argparse's usage error
