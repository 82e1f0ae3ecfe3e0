"""The engine hold-out and its reverse in tools/robustness.py, on a tiny engine set and one recording of ours."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("mujoco")

from slipd.sim import parse_scene
from slipd.sim.datasets import MEASUREMENT, write_dataset
from slipd.sim.scene import generate_batch

MODEL = "slipd/models/slip_ensemble_int8.json"
DETECTORS = {"slipd", "deceleration", "reference_pillar"}


def _ours(folder):
    """One slip on our own stick-slip family, tagged like the robust set."""
    folder.mkdir()
    tl = [{"op": "press", "depth_mm": 1.0, "duration_s": 0.2}, {"op": "hold", "duration_s": 0.3},
          {"op": "move", "kind": "translation", "speed_mm_s": 3.0, "accel_mm_s2": 30.0, "duration_s": 0.6}]
    sc = parse_scene({"family": "hexapod", "sensor": "v1", "timeline": tl, "effects": list(MEASUREMENT)})
    rec = generate_batch([sc], [1])[0]
    rec.meta.update({"physics_family": "stick_slip", "scenario": "slip"})
    rec.save(folder / "00000_robust_stick_slip_slip.npz")


def _manifest(tmp_path, name, *, engine):
    """The shipped manifest with the engine's set in its provenance or taken out of it, beside the shipped graph."""
    manifest = json.loads(Path(MODEL).read_text())
    index = [e for e in manifest["provenance"]["index"] if e.get("set") != "engine"]
    if engine:
        index.append({"set": "engine", "split": "train", "count": 320})
    manifest["provenance"]["index"] = index
    manifest["onnx_file"] = str(Path(MODEL).resolve().with_name(manifest["onnx_file"]))
    path = tmp_path / name
    path.write_text(json.dumps(manifest))
    return str(path)


def test_engine_holdout_report_shape(tmp_path, capsys):
    from sliplab.robustness import CATEGORIES, HOLDOUT_KEYS, main

    engine = tmp_path / "engine"
    index = write_dataset("engine", "test", engine, count=4)  # a lift that slips, a secure one, a light one, a curved
    assert index["physics_family"] == {"engine": 4}
    assert [e["scenario"] for e in index["recordings"]] == ["lift_slip", "secure_lift", "light_grasp", "curved"]
    _ours(tmp_path / "robust")
    out, js = tmp_path / "report", tmp_path / "report_copy.json"
    # The shipped graph stands in for both members here: the test is about the report, not the figures. Its
    # manifest says no engine data was in training, so the report calls it a hold-out.
    held_out = _manifest(tmp_path, "held_out.json", engine=False)
    rc = main(["--model", held_out, "--engine", str(engine), "--reverse", MODEL, "--robust", str(tmp_path / "robust"),
               "--holds", str(tmp_path / "none"), "--engine-only", "--out", str(out), "--json", str(js)])
    assert rc == 0
    report = json.loads(js.read_text())
    assert report == json.loads(out.with_suffix(".json").read_text())
    assert report["engine_recordings"] == 4 and not report["families"] and not report["holds"]
    for key, n in (("engine_holdout", 4), ("reverse_holdout", 1)):
        assert set(report[key]) == DETECTORS
        for fig in report[key].values():
            assert fig["n"] == n
            for k in HOLDOUT_KEYS:
                assert fig[k] is None or 0.0 <= fig[k] <= 1.0, (key, k, fig[k])
            assert set(fig["categories"]) <= set(CATEGORIES)
    eng = report["engine_holdout"]["slipd"]
    # Every recording here lifts; a partial slip that stopped by itself has no outcome under either criterion.
    partial = sum(e["kind"] == "partial" for e in index["recordings"])
    assert eng["offline_success"] is not None and eng["online_lifts"] == 4 - partial
    assert eng["all"]["partial"] == partial and 0 <= eng["all"]["partial_alarmed"] <= partial
    assert "light_grasp" in eng["categories"] and eng["light_grasp_success"] is not None
    assert eng["slow_load_success"] is None  # no slow load among the four
    whole = eng["all"]
    if whole["slip"]:
        assert eng["slip_recall"] == pytest.approx(
            (eng["offline_success"] * (whole["slip"] + whole["stop"]) - whole["stop"] + whole["stop_alarmed"])
            / whole["slip"])
    assert eng["balanced_success"] is None or 0.0 <= eng["balanced_success"] <= 1.0
    rev = report["reverse_holdout"]["slipd"]
    assert rev["online_success"] is None and rev["light_grasp_success"] is None  # a hexapod slip: offline only
    printed = capsys.readouterr().out
    # No engine data in the manifest's provenance: a true hold-out.
    assert report["engine_in_training"] is False
    for title in ("Engine held out", "Reverse: trained on the engine only"):
        assert title in printed and title in out.with_suffix(".md").read_text()
    # The floor beside the detectors: a detector that never alarms leaves every no-slip recording quiet.
    quiet = whole["stop"] / (whole["slip"] + whole["stop"]) if whole["slip"] + whole["stop"] else None
    if quiet is not None:
        assert "(never alarms)" in printed and f"{100 * quiet:.1f} %" in printed


def test_trained_sets_reads_the_manifest_provenance(tmp_path):
    from sliplab.robustness import trained_sets

    without = _manifest(tmp_path, "without.json", engine=False)
    assert {"robust", "transfer"} <= trained_sets(without) and "engine" not in trained_sets(without)
    with_engine = _manifest(tmp_path, "with_engine.json", engine=True)
    assert "engine" in trained_sets(with_engine)
    manifest = json.loads(Path(with_engine).read_text())
    del manifest["provenance"]
    Path(with_engine).write_text(json.dumps(manifest))
    assert trained_sets(with_engine) == set()


def test_a_report_on_an_engine_in_training_says_so(tmp_path, capsys):
    """A model whose manifest lists the engine's set among its training data gets no "Engine held out" title."""
    from sliplab.robustness import main

    engine = tmp_path / "engine"
    write_dataset("engine", "test", engine, count=1)
    model = _manifest(tmp_path, "m.json", engine=True)
    out = tmp_path / "report"
    assert main(["--model", model, "--engine", str(engine), "--engine-only", "--out", str(out)]) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["engine_in_training"] is True
    text = out.with_suffix(".md").read_text()
    assert "Engine in training (not held out)" in text and "Engine held out" not in text
