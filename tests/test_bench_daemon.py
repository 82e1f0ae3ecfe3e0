"""tools/bench_daemon.py's hot-path line on the shipped model (a few decisions, no timing asserted): the figures its
JSON carries, the per-stage breakdown, and the daemon's code left as it was after the stage timers."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from types import ModuleType

import pytest

from sliplab.paths import ROOT

MODEL = ROOT / "slipd" / "models" / "slip_ensemble_int8.json"


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_daemon_tool", ROOT / "tools" / "bench_daemon.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("sensors", [1, 2])
def test_hot_path_reports_each_stage_and_restores_the_timed_code(sensors: int) -> None:
    from slipd.daemon.loop import Daemon
    from slipd.detect.detector import Detector
    from slipd.detect.ensemble import Ensemble

    mod = _bench()
    before = (Daemon.__dict__["_on_frames"], Detector.__dict__["contact_state"], Ensemble.__dict__["step_rows"])
    h = mod.hot_path_cost(MODEL, sensors, decisions=12, sleep_s=0.0)
    assert (Daemon.__dict__["_on_frames"], Detector.__dict__["contact_state"], Ensemble.__dict__["step_rows"]) == before
    # The Python alone (onnxruntime's call skipped) is less than the path with the call.
    assert h["python_back_to_back_us"] < h["back_to_back_us"]
    for key in ("back_to_back_us", "after_sleep_us", "back_to_back_p10_us", "model_back_to_back_us",
                "model_after_sleep_us", "model_back_to_back_p10_us", "python_back_to_back_us",
                "python_back_to_back_p10_us"):
        assert h[key] > 0
    stages = h["stages_us"]
    assert list(stages) == [name for name, _ in mod.STAGES if name != "confirmed rule"] + ["total", "untimed"]
    # Every stage runs on each decision of a quiet hold (the recorder keeps the frames; no alarm, no file).
    assert all(v > 0 for v in stages.values()), stages
    # Exclusive times: the stages share out the instrumented total, nothing counted twice.
    assert sum(v for k, v in stages.items() if k not in ("total", "untimed")) <= stages["total"]
    line = mod._stages_line(stages)
    assert "contact state" in line and "instrumented total" in line and "untimed" in line


def test_a_ratio_to_a_loop_that_read_no_cpu_time_is_not_printed_as_a_number() -> None:
    # A two-second run of the bare event loop can read 0 % CPU (clock ticks of 10 ms); the summary must still print.
    mod = _bench()
    assert mod.times(6.0, 1.5) == "4.0x"
    assert mod.times(6.0, 0.0).startswith("n/a")


def test_the_instruction_counts_child_runs_each_kind_and_the_totals_parse() -> None:
    # ``--instructions`` runs this child under callgrind (not here: valgrind is slow and optional); each kind must run
    # on the same set-up, and a callgrind file's total must be read from its summary (or totals) line.
    mod = _bench()
    for kind in ("none", *mod.INSTR_KINDS):
        mod.instructions_child(MODEL, 1, kind, 3)
    assert mod.callgrind_total("# callgrind format\nevents: Ir\nsummary: 12345\n") == 12345
    assert mod.callgrind_total("events: Ir\ntotals: 678\n") == 678
    with pytest.raises(ValueError, match="no summary"):
        mod.callgrind_total("events: Ir\n")



@pytest.mark.slow
def test_the_full_run_measures_reaction_latency_and_cpu(tmp_path) -> None:
    """The full run, as the docs give it, at a few seconds: its latency part patches the decision so that every
    window alarms, and that patch must take the decision's whole call (the limit guard's contact risk included);
    every alarm must reach the servo as a tighten, and the JSON must carry each figure."""
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_daemon.py"), "--seconds", "2", "--sensors", "1",
                        "--strides", "10", "--cpu-runs", "1", "--json", str(out)],
                       capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    run = json.loads(out.read_text())["runs"][0]
    assert run["alarms"] > 50  # a decision every 10 ms for about two seconds, each one an alarm
    assert 0.0 < run["decision_p50_ms"] <= run["latency_p50_ms"] <= run["latency_max_ms"]
    assert run["frames_lost"] == 0 and run["frames_sent"] >= 2000
    assert run["cpu_percent"] > 0.0 and set(run["hot_path_us"]) >= {"back_to_back", "after_sleep"}


def test_the_hot_path_with_the_confirmed_rule_running_shows_its_stage() -> None:
    # A level the still hold's P(slip) reaches: the rule runs on every read, and its stage is timed.
    mod = _bench()
    h = mod.hot_path_cost(MODEL, 1, decisions=12, sleep_s=0.0, confirm_rule=1e-6)
    stages = h["stages_us"]
    assert list(stages) == [name for name, _ in mod.STAGES] + ["total", "untimed"]
    assert stages["confirmed rule"] > 0

