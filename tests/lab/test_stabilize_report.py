"""tools/stabilize.py's grip-control report on hand-made runs (no rig runs): the extras alone, and the command line
that regenerates them."""

from __future__ import annotations

import importlib.util
import json
import sys
from types import ModuleType

import pytest

from sliplab.paths import ROOT


def _stabilize() -> ModuleType:
    spec = importlib.util.spec_from_file_location("stabilize_tool", ROOT / "tools" / "stabilize.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _row(policy: str, rep: int, dropped: bool, stopped: bool, peak: float) -> dict:
    return {"policy": policy, "object": "cup_filling", "scenario": "extra", "rep": rep,
            "translation_mm": 36.0 if dropped else 0.3, "rotation_deg": 0.0, "dropped": dropped, "peak_grip_n": peak,
            "mean_grip_n": peak * 0.9, "arm_stopped": stopped, "alarm_s": None, "time_to_secure_s": None,
            "force_limit_n": 30.0 if policy == "grip_control" else None, "sensor_stalls": 0}


def _report(tmp_path, rows: list[dict], args: list[str]) -> str:
    """The report ``tools/stabilize.py ARGS --from-json`` writes from ``rows`` (no rig runs)."""
    runs = tmp_path / "runs.json"
    runs.write_text(json.dumps(rows))
    out = tmp_path / "report.md"
    assert _stabilize().main([*args, "--from-json", str(runs), "--out", str(out)]) == 0
    return out.read_text()


def test_the_filling_cup_alone_is_reported_with_the_command_that_repeats_it(tmp_path) -> None:
    rows = [_row("stop_and_secure", 0, True, False, 3.3), _row("grip_control", 0, False, False, 9.5),
            _row("stop_and_secure", 1, False, True, 40.0), _row("grip_control", 1, False, True, 12.0)]
    md = _report(tmp_path, rows, ["--policy", "grip_control", "--objects", "", "--extras", "cup_filling", "--seed",
                                  "2000", "--reps", "2"])
    assert "--objects '' --extras 'cup_filling' --seed 2000" in md
    # One line per policy for the cup: the drop and the arm stops as they were.
    assert "| cup_filling | extra | stop_and_secure | 18.15 | 0.00 | 1/2 |" in md
    assert "| cup_filling | extra | grip_control | 0.30 | 0.00 | 0/2 | 10.8 (max 12.0, limit 30) | 9.7 | 1/2 |" in md
    assert "Against" not in md  # no lifts of the six objects: no done-when table to judge


def test_an_unknown_extra_is_refused_before_the_rig_runs() -> None:
    mod = _stabilize()
    with pytest.raises(SystemExit, match="unknown"):
        mod.main(["--policy", "grip_control", "--objects", "", "--extras", "teapot"])


def test_extras_left_out_of_the_run_are_not_judged_as_missed(tmp_path) -> None:
    """``--extras ''`` (the six objects alone, e.g. other seeds): the done-when table says the cups were not run,
    rather than that they failed."""
    rows = [{**_row(policy, 0, False, policy == "stop_and_secure", 40.0 if policy == "stop_and_secure" else 25.0),
             "object": "wooden_box", "scenario": scenario,
             "force_limit_n": 40.0 if policy == "grip_control" else None}
            for policy in ("stop_and_secure", "grip_control") for scenario in ("undergrip", "offcentre")]
    md = _report(tmp_path, rows, ["--policy", "grip_control", "--objects", "wooden_box", "--extras", "", "--reps", "1"])
    assert "| the filling cup held | not run | - |" in md
    assert "| the fragile object never above its limit | not run | - |" in md
    assert "| mean translation <= 0.5 mm | 0.30 mm | yes |" in md


def test_a_run_reported_elsewhere_keeps_its_runs_beside_its_report(tmp_path, monkeypatch) -> None:
    """``--out`` elsewhere (a subset, other seeds): the per-run JSON goes beside that report, and the committed
    ``reports/grip_control.json`` is left alone (it was overwritten by any run without ``--json``)."""
    from types import SimpleNamespace

    mod = _stabilize()
    committed = ROOT / "reports" / "grip_control.json"
    before = committed.read_bytes() if committed.exists() else None

    def fake_rig(scene, config, **kw):  # the rig's result for one lift (the report is judged above, not this)
        return SimpleNamespace(final_translation_mm=0.3, final_rotation_deg=0.0, dropped=False, max_grip_n=20.0,
                               mean_grip_n=19.0,
                               arm_stopped=False, alarm_s=1.4, secure_s=1.5, lift_start_s=1.3, sensor_stalls=0), None

    monkeypatch.setattr(mod, "run_rig", fake_rig)
    out = tmp_path / "subset.md"
    assert mod.main(["--policy", "grip_control", "--objects", "", "--extras", "paper_cup_fragile", "--reps", "1",
                     "--out", str(out)]) == 0
    runs = json.loads((tmp_path / "subset.json").read_text())
    assert [r["policy"] for r in runs] == ["stop_and_secure", "grip_control"]
    assert (committed.read_bytes() if committed.exists() else None) == before
    # The report's own command writes it, and its runs, where they are.
    assert f"--out {out.resolve()} --json {(tmp_path / 'subset.json').resolve()}`" in out.read_text()


def test_the_rig_report_names_the_out_path_its_command_must_write_again() -> None:
    import argparse

    mod = _stabilize()
    assert mod._out_arg(argparse.Namespace(out=ROOT / "reports" / "stabilize.md")) == ""
    named = argparse.Namespace(out=ROOT / "reports" / "stabilize_onnx.md")
    assert mod._out_arg(named) == " --out reports/stabilize_onnx.md"


def test_a_stop_and_secure_run_is_repeated_by_its_own_policy(tmp_path) -> None:
    """The report's command line names the policy that ran: a stop-and-secure run of the cups is not repeated as a
    grip_control comparison."""
    md = _report(tmp_path, [_row("stop_and_secure", 0, False, True, 40.0)],
                 ["--policy", "stop_and_secure", "--objects", "", "--extras", "cup_filling", "--reps", "1"])
    assert "`python tools/stabilize.py --policy stop_and_secure --reps 1 --objects '' --extras 'cup_filling'" in md
    assert "--policy grip_control" not in md
