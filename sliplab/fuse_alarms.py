"""Two detectors together: a model's alarms fused with the reference-pillar rule's, scored as robustness.py scores.

    python tools/fuse_alarms.py --data out/datasets/engine_test --model slipd/models/slip_ensemble_int8.json
    python tools/fuse_alarms.py --data out/datasets/bullet_test --model M.json [M2.json ...] --within-ms 100

Each model (``--model``) and the reference-pillar heuristic with its shipped parameters (``--baselines``, as
``tools/robustness.py`` uses) are streamed once through ``sliplab.evaluate.evaluate_paths``; their alarm streams
are then fused per recording and every row is scored by the same ``sliplab.metrics.evaluate_scene`` and
``sliplab.robustness.holdout_figures`` (no second scoring). Three fusions, none with a parameter fitted to the split
it is scored on:

either
    an alarm whenever either detector's alarm is raised: its first alarm is the earlier of the two.
both within W
    an alarm when one detector's alarm is raised and the other's was raised at some moment in the last W
    (``--within-ms``, default 100 ms, set before any measurement): a confirmation in either order.
rule confirmed at L
    the model's own alarm, and also the rule's alarm while the model's P(slip) reached ``L`` (``--confirm-level``)
    at some decision in the last W: the rule's speed where the members lean towards a slip without calling it. This
    row is the daemon's own detector (``decision.confirm_rule``: ``slipd.detect.confirmed``), streamed through
    ``sliplab.evaluate.ConfirmedRunner``, not a fusion of the two parts' traces. The default level, 0.3, was chosen on
    MuJoCo's test split before Bullet was scored with it (``CONFIRM_LEVEL``, ``docs/engine.md``).

A detector's alarm state holds from one of its decisions to its next, so the fused stream of the first two has a
decision at every moment either detector decides. Prints the hold-out table of ``tools/robustness.py`` (offline
success, slips caught, online success on the lifts, no-slip recordings alarmed, partial slips, latency, light grasps,
slow loads, the scenario categories) with each model, the rule and the three fusions, then per model the scored slips
caught in time by both parts, by one only and by neither; ``--json`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from slipd.detect.baselines import CONFIRMED_RULE, load_params
from slipd.recording import list_recordings
from sliplab.evaluate import NO_LIMIT_GUARD_HELP, evaluate_paths
from sliplab.metrics import SceneResult, SceneTruth, Trace, evaluate_scene
from sliplab.paths import ROOT
from sliplab.robustness import DEFAULT_BASELINES, categories, holdout_figures, tables, tags

RULE = CONFIRMED_RULE
WITHIN_S = 0.1
"""Default confirmation window of the "both" fusion: set before measuring, never fitted to a split."""
MODES = ("either", "both")
CONFIRM_LEVEL = 0.3
"""Default level of the "confirmed" fusion: of 0.1-0.4, the one with the best offline success on MuJoCo's test split,
chosen there before Bullet was scored with it (the transfer test alarms on a stop at every lower level tried)."""

Result = tuple[SceneResult, Trace, SceneTruth]


def _held(t: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """A detector's value (alarm state, p_slip) at the moments ``at``: that of its last decision at or before each
    (False or 0 before its first decision)."""
    if not len(t):
        return np.zeros(len(at), values.dtype)
    i = np.searchsorted(t, at, side="right") - 1
    return np.where(i >= 0, values[np.clip(i, 0, None)], values.dtype.type(0))


def _raised_within(t: np.ndarray, alarm: np.ndarray, at: np.ndarray, within_s: float) -> np.ndarray:
    """Whether the alarm was raised at some moment in [at - within_s, at]: held at the window's start, or raised
    by a decision inside it."""
    if not len(t):
        return np.zeros(len(at), bool)
    raised = np.concatenate([[0], np.cumsum(alarm)])
    inside = raised[np.searchsorted(t, at, side="right")] - raised[np.searchsorted(t, at - within_s, side="right")]
    return (inside > 0) | _held(t, alarm, at - within_s)


def fuse_traces(a: Trace, b: Trace, mode: str, within_s: float = WITHIN_S) -> Trace:
    """One alarm stream from two detectors' decisions on one recording (``MODES``, see the module's docstring).

    The fused p_slip is the larger held p_slip of the two (a heuristic's is its score); it is not thresholded again.
    """
    if mode not in MODES:
        raise ValueError(f"fusion mode {mode!r}: one of {', '.join(MODES)}")
    ta, aa, pa = np.asarray(a.t_s, float), np.asarray(a.alarm, bool), np.asarray(a.p_slip, float)
    tb, ab, pb = np.asarray(b.t_s, float), np.asarray(b.alarm, bool), np.asarray(b.p_slip, float)
    t = np.union1d(ta, tb)
    on_a, on_b = _held(ta, aa, t), _held(tb, ab, t)
    if mode == "either":
        alarm = on_a | on_b
    else:
        alarm = (on_a & _raised_within(tb, ab, t, within_s)) | (on_b & _raised_within(ta, aa, t, within_s))
    p = np.maximum(_held(ta, pa, t), _held(tb, pb, t))
    rising = alarm & ~np.concatenate([[False], alarm[:-1]])
    return Trace([float(v) for v in t], [float(v) for v in p], [bool(v) for v in alarm], [bool(v) for v in rising])


def fused_results(first: list[Result], second: list[Result], mode: str, within_s: float = WITHIN_S) -> list[Result]:
    """Two detectors' results on the same recordings (``evaluate_paths``), fused and scored again per recording."""
    out = []
    for (_, ta, truth), (_, tb, other) in zip(first, second, strict=True):
        if truth.name != other.name:
            raise ValueError(f"fusing results of different recordings: {truth.name} and {other.name}")
        trace = fuse_traces(ta, tb, mode, within_s)
        out.append((evaluate_scene(truth, trace), trace, truth))
    return out


def caught_by(model: list[Result], rule: list[Result]) -> dict[str, int]:
    """The scored slips each part catches in time (offline criterion): by both, the model only, the rule only,
    neither. An "either" fusion catches at most the first three; fewer where one part's alarm comes too early."""
    out = {"both": 0, "model only": 0, "rule only": 0, "neither": 0}
    for (m, _, truth), (r, _, _) in zip(model, rule, strict=True):
        if truth.kind != "slip" or m.offline_outcome is None:
            continue
        hit = (m.offline_outcome == "tp", r.offline_outcome == "tp")
        out[{(True, True): "both", (True, False): "model only", (False, True): "rule only"}.get(hit, "neither")] += 1
    return out


def model_name(manifest: str) -> str:
    """A short row name: the manifest's folder and stem."""
    p = Path(manifest)
    return f"{p.parent.name}/{p.stem}"


def run(data: Path, models: list[str], baselines: Path = DEFAULT_BASELINES, within_s: float = WITHIN_S,
        limit_guard: bool = True, level: float = CONFIRM_LEVEL) -> dict:
    """Every model, the rule and both fusions of each model with the rule, as ``holdout_figures`` on ``data``
    (``limit_guard`` False: each model on its own decision rule, ``--no-limit-guard``)."""
    paths = list_recordings(data)
    cats = categories(paths, tags(data))
    params, frontend = load_params(baselines, RULE)
    rule = evaluate_paths(paths, "baseline", (RULE, params, frontend), progress=False)
    rows = {RULE: holdout_figures(rule, cats)}
    caught = {}
    for m in models:
        res = evaluate_paths(paths, "model", (m, 0.0, None, None, limit_guard), progress=False)
        name = model_name(m)
        rows[name] = holdout_figures(res, cats)
        caught[name] = caught_by(res, rule)
        rows[f"{name} or {RULE}"] = holdout_figures(fused_results(res, rule, "either"), cats)
        rows[f"{name} and {RULE} within {1000 * within_s:.0f} ms"] = holdout_figures(
            fused_results(res, rule, "both", within_s), cats)
        confirmed = evaluate_paths(paths, "confirmed", (m, level, within_s, params, frontend, limit_guard),
                                   progress=False)
        rows[f"{RULE} confirmed by {name} at {level:g}"] = holdout_figures(confirmed, cats)
    src = Path(baselines).resolve()
    return {"data": str(data), "recordings": len(paths),
            "baselines": str(src.relative_to(ROOT) if src.is_relative_to(ROOT) else src), "within_s": within_s,
            "confirm_level": level,
            "models": models, "detectors": rows,
            "slips_caught_by": caught}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a test split (tools/make_dataset.py)")
    p.add_argument("--model", nargs="+", required=True, help="model manifests, each fused with the rule")
    p.add_argument("--baselines", type=Path, default=DEFAULT_BASELINES, help="the rule's shipped parameters JSON")
    p.add_argument("--within-ms", type=float, default=1000 * WITHIN_S,
                   help="the 'both' and 'confirmed' fusions' window (default %(default)g ms)")
    p.add_argument("--confirm-level", type=float, default=CONFIRM_LEVEL,
                   help="the model's P(slip) that confirms the rule's alarm (default %(default)g)")
    p.add_argument("--no-limit-guard", action="store_true", help=NO_LIMIT_GUARD_HELP)
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = p.parse_args(argv)
    names = [model_name(m) for m in args.model]
    if len(set(names)) < len(names):
        p.error(f"--model: two manifests share a row name (folder/stem): {', '.join(names)}")
    missing = [m for m in args.model if not Path(m).is_file()]
    if missing:
        p.error(f"--model: no such manifest: {', '.join(missing)}")
    if not list_recordings(args.data):
        raise SystemExit(f"--data {args.data}: no recordings (make a test split with tools/make_dataset.py)")
    try:
        load_params(args.baselines, RULE)
    except ValueError as exc:
        raise SystemExit(f"--baselines {exc}") from None
    if not 0.0 < args.confirm_level <= 1.0:
        p.error(f"--confirm-level: a probability in (0, 1], got {args.confirm_level}")
    report = run(args.data, args.model, args.baselines, args.within_ms / 1000, not args.no_limit_guard,
                 args.confirm_level)
    # The hold-out table of tools/robustness.py, one row per detector and fusion.
    _, head, rows = tables({"families": {}, "holds": {}, "engine_holdout": {
        k: {"source": "", **v} for k, v in report["detectors"].items()}})[0]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    print(f"Each model, the {RULE} rule and their fusions on {args.data} ({report['recordings']} recordings)")
    for r in [head, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
    for name, counts in report["slips_caught_by"].items():
        print(f"slips caught in time by {name} and {RULE}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0
