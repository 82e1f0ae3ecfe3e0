"""tools/tradeoff.py's plot: two panels, the held-out markers, and labels that never overlap (no model runs)."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest

from sliplab.paths import ROOT

pytest.importorskip("matplotlib")


def _tradeoff():
    spec = importlib.util.spec_from_file_location("tradeoff_tool", ROOT / "tools" / "tradeoff.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def _points(mod):
    """Crowded points: several share success and latency (as fp32 / fp16 do), one has no detected slip."""
    pts = []
    for i, (name, succ, lat, us) in enumerate([("Z=1", 0.78, None, 40), ("Z=2", 0.90, 0.012, 55),
                                               ("Z=3", 0.90, 0.012, 62), ("Z=5", 0.91, 0.008, 80),
                                               ("Z=5 fp16", 0.91, 0.008, 81), ("Z=5 int8", 0.905, 0.009, 61),
                                               ("Z=5 stride 10", 0.92, 0.006, 79)]):
        p = mod.Point(name, "ensemble", "members")
        p.figures = {"success": succ, "latency_median_s": lat, "step_median_us": us, "cpu_share": 0.01 + i * 1e-3,
                     "heldout": {"success": succ - 0.05, "latency_median_s": 0.03, "balanced": succ - 0.06}}
        pts.append(p)
    return pts


def test_plot_has_two_panels_and_no_overlapping_labels(tmp_path, monkeypatch):
    mod = _tradeoff()
    seen = []
    place = mod.place_labels

    from matplotlib.text import Text

    def spy(ax, items, avoid, fontsize=7.5):
        place(ax, items, avoid, fontsize)
        r = ax.figure.canvas.get_renderer()
        boxes, names = [], set()
        for t in ax.texts:
            if hasattr(t, "update_positions"):  # the annotations (the panel's note is a plain Text)
                t.update_positions(r)
                boxes.append(Text.get_window_extent(t, r))
                names.update(t.get_text().split(" / "))
        seen.append((ax, boxes, {text for _, _, text, _ in items} - names))

    monkeypatch.setattr(mod, "place_labels", spy)
    out = tmp_path / "t.png"
    mod.plot(_points(mod), out, "own", "held-out")
    assert out.stat().st_size > 10_000 and len(seen) == 2
    for _, boxes, unlabelled in seen:
        assert boxes and not unlabelled  # coinciding points share a label, none is lost
        assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    assert seen[0][0].get_xscale() == "log" and seen[1][0].get_xscale() == "linear"


def test_heldout_note_says_whether_the_families_were_trained_on(tmp_path):
    mod = _tradeoff()
    held = tmp_path / "robust_test"
    held.mkdir()
    (held / "index.json").write_text(json.dumps({"set": "robust"}))
    m = tmp_path / "m.json"
    m.write_text(json.dumps({"provenance": {"data": ["out/datasets/robust_train", "out/datasets/grips_train"]}}))
    assert "same physics families" in mod.heldout_note(str(m), held)
    m.write_text(json.dumps({"provenance": {"data": ["out/datasets/grips_train"]}}))
    assert "holds no `robust` set" in mod.heldout_note(str(m), held)


def test_held_out_families_are_run_by_the_fold_trained_without_them(tmp_path, monkeypatch):
    """--lofo: each family's held-out recordings go to that family's fold model; a family without a fold stops."""
    import sliplab.robustness as robustness

    mod = _tradeoff()
    calls = []

    def fake_evaluate(paths, kind, args, workers, progress):
        calls.append((sorted(p.stem for p in paths), args[0]))
        return [(None, None, type("T", (), {"name": p.stem})()) for p in paths]

    monkeypatch.setattr(mod, "evaluate_paths", fake_evaluate)
    monkeypatch.setattr(robustness, "figures", lambda results: {"success": len(results)})
    paths = [tmp_path / f"{name}.npz" for name in ("a1", "a2", "b1")]
    tag = {"a1": {"physics_family": "alpha"}, "a2": {"physics_family": "alpha"}, "b1": {"physics_family": "beta"}}
    pt = mod.Point("Z=1", "ensemble", "members", members=1, manifest="own.json",
                   folds={"alpha": "fold_alpha.json", "beta": "fold_beta.json"})
    out = mod.heldout_accuracy(pt, paths, tag, workers=1)
    assert sorted(calls) == [(["a1", "a2"], "fold_alpha.json"), (["b1"], "fold_beta.json")]
    assert out["success"] == 3 and out["families"] == {"alpha": 2, "beta": 1}
    pt.folds = {"alpha": "fold_alpha.json"}
    with pytest.raises(SystemExit, match="beta"):
        mod.heldout_accuracy(pt, paths, tag, workers=1)
    pt.folds = {}  # without folds the point's own model runs every family
    calls.clear()
    mod.heldout_accuracy(pt, paths, tag, workers=1)
    assert calls == [(["a1", "a2", "b1"], "own.json")]


def test_plot_only_redraws_from_the_reports_table(tmp_path):
    """Without the sweep's JSON, --plot-only reads the points back from the report's table: every ensemble point,
    the shipped one among them, with the figures the plot needs."""
    mod = _tradeoff()
    report = tmp_path / "tradeoff.md"
    report.write_text((ROOT / "reports" / "tradeoff.md").read_text())
    points = mod.points_from_report(report.read_text())
    names = [p.name for p in points]
    assert len(names) == 9 and mod.SHIPPED in names, names
    shipped = next(p for p in points if p.name == mod.SHIPPED)
    assert (shipped.members, shipped.precision, shipped.stride) == (5, "int8", 10)
    row = next(ln for ln in report.read_text().splitlines() if ln.startswith(f"| {mod.SHIPPED} |")).split("|")
    step_us, heldout = float(row[7].split("/")[0]), float(row[11].split("%")[0]) / 100  # (the table's own cells)
    assert shipped.figures["step_median_us"] == step_us and shipped.figures["heldout"]["success"] == heldout
    assert mod.main(["--plot-only", "--report", str(report)]) == 0
    assert (tmp_path / "tradeoff.png").stat().st_size > 10_000
