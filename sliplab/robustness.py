"""Robustness benchmark: every detector on every physics family, long no-slip holds, leave-one-family-out, seeds.

    python tools/robustness.py --model slipd/models/slip_ensemble_int8.json
    python tools/robustness.py --model M.json --authors out/reference.json \\
        --lofo viscoelastic=out/lofo_visco.json stribeck=out/lofo_stribeck.json ... \\
        --seeds out/seed0.json out/seed1.json out/seed2.json

Data (``tools/make_dataset.py``): ``--robust`` (default ``out/datasets/robust_test``) and ``--holds`` (default
``out/datasets/holds_test``); each recording's ``physics_family`` and ``scenario`` come from the folder's
``index.json`` (else from the recording's meta). Detectors: the ``--model`` manifest, both heuristics with their
shipped parameters (``--baselines``, default ``slipd/models/baselines_transfer.json``), and optionally the authors'
checkpoints as a manifest (``--authors``). Everything is streamed through ``sliplab.evaluate.evaluate_paths``
and scored by ``sliplab.metrics`` (no second evaluation loop). Writes ``reports/robustness.md`` and ``.json``
(``--out``) and prints every figure.

Figures
    per family: offline success (TP+TN)/N, balanced success, stop-trial false alarms FP/(FP+TN), latency
    median / p90 (TP, from the labelled onset), false alarms per hour over the no-slip recordings.
    holds, per hold type: recordings, hours, alarms (rising edges), false alarms per hour, and where p_slip
    settles: p99 of p_slip over the last 80 % of each hold (worst recording) and the margin below the threshold.
    leave-one-family-out: each fold's model on its held-out family beside the better heuristic there.
    seeds: several manifests of one recipe -> mean and spread (sample standard deviation) of each figure.
    engine hold-out (``--engine DIR``): a model trained on our own families only (``--engine-model``, default
        ``--model``) on the engine's test split (``tools/make_dataset.py --set engine``), beside both heuristics:
        offline success, online success on the gripper lifts, the stop false-alarm rate (no-slip recordings), and
        the categories light grasps (grip < 3 N when the arm moves), few pillars in contact (<= 3), slow loads,
        secure lifts, stops and holds. ``--json`` key ``engine_holdout``.
    reverse hold-out (``--reverse MANIFEST``): a model trained on the engine only, on our families' robust test
        split, beside both heuristics; ``reverse_holdout``, the same figures.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from slipd.detect.baselines import BASELINES, load_params
from slipd.recording import Recording, list_recordings
from sliplab.evaluate import NO_LIMIT_GUARD_HELP, evaluate_paths
from sliplab.metrics import confusion, summarize
from sliplab.paths import ROOT

DEFAULT_BASELINES = ROOT / "slipd" / "models" / "baselines_transfer.json"
SETTLE_FRACTION = 0.8
"""p_slip settling is measured over the last 80 % of each hold."""


# --------------------------------------------------------------------------- data
def tags(folder: Path) -> dict[str, dict[str, str]]:
    """Recording stem -> {"physics_family", "scenario", "sensor"} from ``index.json`` (else the meta)."""
    out: dict[str, dict[str, str]] = {}
    index = folder / "index.json"
    if index.exists():
        for e in json.loads(index.read_text()).get("recordings", []):
            sensor = e.get("scene", {}).get("sensor", "")
            out[Path(e["file"]).stem] = {"physics_family": e.get("physics_family", ""),
                                         "scenario": e.get("scenario", ""), "sensor": sensor}
    for p in list_recordings(folder):
        if p.stem not in out:
            meta = Recording.load(p).meta or {}
            out[p.stem] = {"physics_family": meta.get("physics_family", ""), "scenario": meta.get("scenario", ""),
                           "sensor": (meta.get("sensor") or {}).get("name", "")}
    return out


def provenance() -> dict:
    """The commit and any uncommitted changes to the detector code and models the figures came from."""
    def git(*a: str) -> str:
        try:
            return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, timeout=10).stdout.rstrip()
        except (OSError, subprocess.SubprocessError):
            return ""
    dirty = git("status", "--porcelain", "--", "slipd/detect", "slipd/models", "sliplab/evaluate.py",
                "sliplab/metrics.py")
    return {"commit": git("rev-parse", "--short", "HEAD"),
            "uncommitted": [line[3:] for line in dirty.splitlines() if line.strip()]}


def _rel(path: Path) -> str:
    """A path relative to the repository when it lies inside it (reports stay machine-independent)."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def subset(paths: list[Path], limit: int, tag: dict | None = None, key: str = "") -> list[Path]:
    """``limit`` recordings spread over the set: taken in turn from each group of ``tag[stem][key]`` (physics family,
    hold type), in a fixed random order within a group, so every group gets its share. 0: all."""
    if not limit or limit >= len(paths):
        return paths
    rng = np.random.default_rng(0)
    groups: dict[str, list[Path]] = {}
    for p in paths:
        groups.setdefault((tag or {}).get(p.stem, {}).get(key, ""), []).append(p)
    queues = [[g[i] for i in rng.permutation(len(g))] for _, g in sorted(groups.items())]
    keep: list[Path] = []
    while len(keep) < limit:
        for q in queues:
            if q and len(keep) < limit:
                keep.append(q.pop(0))
    order = {p: i for i, p in enumerate(paths)}
    return sorted(keep, key=order.__getitem__)


def detectors(args) -> list[dict]:
    """[{name, kind, args, threshold}] for evaluate_paths: the model, both heuristics, optionally the authors'."""
    out = []
    if args.model:
        out.append(_model_entry("slipd", args.model, not args.no_limit_guard))
    src = Path(args.baselines)
    for name in sorted(BASELINES):
        if args.heuristics and name not in args.heuristics:  # the bare flag, as the flag's absence: both
            continue
        params, frontend = load_params(src, name) if src.exists() else ({}, {})
        out.append({"name": name, "kind": "baseline", "args": (name, params, frontend), "threshold": 0.5,
                    "source": f"{src.name if src.exists() else 'defaults'}"})
    if args.authors:
        out.append(_model_entry("authors", args.authors, not args.no_limit_guard))
    return out


def _model_entry(name: str, manifest: str, limit_guard: bool = True) -> dict:
    threshold = float(json.loads(Path(manifest).read_text()).get("threshold", 0.5))
    return {"name": name, "kind": "model", "args": (manifest, 0.0, None, None, limit_guard), "threshold": threshold,
            "source": str(manifest)}


def trained_sets(manifest: str) -> set[str]:
    """The data sets (``index.json``'s ``set``: robust, transfer, engine, ...) a model's manifest says it was trained
    on; empty for a manifest without provenance (the authors' checkpoints, a hand-made model)."""
    prov = json.loads(Path(manifest).read_text()).get("provenance") or {}
    return {str(i["set"]) for i in prov.get("index") or [] if isinstance(i, dict) and "set" in i}


# --------------------------------------------------------------------------- engine categories
LIGHT_GRIP_N = 3.0
"""A light grasp: the total grip when the arm starts to move is below this."""
FEW_PILLARS = 3
"""Few pillars in contact: this many or fewer carry more than the contact threshold when the arm starts to move."""
CATEGORIES = ("light_grasp", "few_pillars", "slow_load", "secure_lift", "stop", "hold")
HOLDOUT_KEYS = ("offline_success", "online_success", "stop_false_alarm_rate", "light_grasp_success",
                "slow_load_success")


def categories(paths: list[Path], tag: dict) -> dict[str, set[str]]:
    """Recording stem -> the report's categories it belongs to: its scenario tag (slow loads, secure lifts, stops,
    holds) and, from the engine's meta, a light grasp or few pillars in contact."""
    out: dict[str, set[str]] = {}
    for p in paths:
        cats = {c for c in CATEGORIES if tag.get(p.stem, {}).get("scenario") == c}
        eng = (Recording.load(p).meta or {}).get("engine") or {}
        if eng.get("grip_at_motion_n") is not None and eng["grip_at_motion_n"] < LIGHT_GRIP_N:
            cats.add("light_grasp")
        if eng.get("pillars_in_contact") is not None and eng["pillars_in_contact"] <= FEW_PILLARS:
            cats.add("few_pillars")
        out[p.stem] = cats
    return out


def holdout_figures(results: list, cats: dict[str, set[str]]) -> dict:
    """The hold-out figures of one detector: fractions 0..1 (None where a group is empty).

    offline_success: (TP + TN) / N under the offline criterion; online_success: the online criterion over the
    recordings whose motion includes a gripper lift; stop_false_alarm_rate: FP / (FP + TN) over the no-slip
    recordings; slip_recall: TP / (TP + FN), the scored slips caught in time; balanced_success: the mean of that and
    the no-slip recordings left quiet, which a detector that never alarms cannot raise above 0.5 however few slips
    a split holds; light_grasp_success / slow_load_success: offline success within those categories."""
    s = summarize([r[0] for r in results])
    off = s.offline
    lifts = [r[0] for r in results if "lift" in r[2].motion and r[2].family != "hexapod"]
    on = confusion(lifts, online=True)
    by_cat = {c: [r for r in results if c in cats.get(r[2].name, set())] for c in CATEGORIES}
    out = {
        "n": s.n_scenes,
        "offline_success": off.success_rate,
        "slip_recall": off.tp / (off.tp + off.fn) if off.tp + off.fn else None,
        "balanced_success": off.balanced_success,
        "online_success": on.success_rate,
        "online_lifts": on.n,
        "stop_false_alarm_rate": off.fp / (off.fp + off.tn) if off.fp + off.tn else None,
        "light_grasp_success": summarize([r[0] for r in by_cat["light_grasp"]]).offline.success_rate
        if by_cat["light_grasp"] else None,
        "slow_load_success": summarize([r[0] for r in by_cat["slow_load"]]).offline.success_rate
        if by_cat["slow_load"] else None,
        "all": figures(results),
        "categories": {c: figures(rs) for c, rs in by_cat.items() if rs},
    }
    return out


# --------------------------------------------------------------------------- figures
def figures(results: list) -> dict:
    """The benchmark's figures of a group of (SceneResult, Trace, SceneTruth) (``sliplab.metrics``)."""
    s = summarize([r[0] for r in results])
    off = s.offline
    stops = off.fp + off.tn
    return {
        "n": s.n_scenes, "slip": off.tp + off.fn, "stop": stops,
        "success": off.success_rate, "balanced": off.balanced_success,
        "stop_false_alarms": off.fp / stops if stops else None, "stop_alarmed": off.fp,
        "latency_median_s": s.latency_s.median, "latency_p90_s": s.latency_s.p90,
        "unscored_slips": s.offline_unlabelled,
        "partial": s.partial, "partial_alarmed": s.partial_alarmed,
        "false_alarms_per_hour": s.false_alarms_per_hour, "no_slip_hours": s.no_slip_hours,
    }


def settle(results: list, threshold: float) -> dict:
    """Where p_slip settles on holds: p99 over the last ``SETTLE_FRACTION`` of each recording."""
    p99 = []
    for _, trace, truth in results:
        p = np.asarray(trace.p_slip, np.float64)
        t = np.asarray(trace.t_s, np.float64)
        tail = p[t >= truth.duration_s * (1.0 - SETTLE_FRACTION)]
        if len(tail):
            p99.append(float(np.percentile(tail, 99)))
    if not p99:
        return {"p99_worst": None, "p99_median": None, "margin": None}
    worst = max(p99)
    return {"p99_worst": worst, "p99_median": float(np.median(p99)), "margin": threshold - worst}


def holds_figures(results: list, threshold: float | None) -> dict:
    """Hold figures; p_slip settling only for models (``threshold`` None: a heuristic, whose output is a flag)."""
    s = summarize([r[0] for r in results])
    settled = settle(results, threshold) if threshold is not None else {"p99_worst": None, "p99_median": None,
                                                                         "margin": None}
    return {"n": s.n_scenes, "hours": s.no_slip_hours, "alarms": s.false_alarms,
            "false_alarms_per_hour": s.false_alarms_per_hour, **settled}


def group(results: list, tag: dict, key: str) -> dict[str, list]:
    out: dict[str, list] = {}
    for r in results:
        out.setdefault(tag.get(r[2].name, {}).get(key, "") or "-", []).append(r)
    return dict(sorted(out.items()))


# --------------------------------------------------------------------------- run
def run(args) -> dict:
    robust_dir, holds_dir = Path(args.robust), Path(args.holds)
    robust = list_recordings(robust_dir) if robust_dir.is_dir() else []
    holds = list_recordings(holds_dir) if holds_dir.is_dir() and not args.engine_only else []
    engine_dir = Path(args.engine) if args.engine else None
    engine = list_recordings(engine_dir) if engine_dir is not None and engine_dir.is_dir() else []
    if engine_dir is not None and not engine:
        raise SystemExit(f"--engine {engine_dir}: no recordings; make them with tools/make_dataset.py --set engine "
                         "--split test --out DIR")
    if not robust and not holds and not engine:
        raise SystemExit(f"no recordings in {robust_dir} or {holds_dir}; make them with tools/make_dataset.py "
                         "--set robust|holds --split test --out DIR")
    rtag = tags(robust_dir) if robust else {}
    htag = tags(holds_dir) if holds else {}
    robust = subset(robust, args.limit, rtag, "physics_family")
    holds = subset(holds, args.holds_limit, htag, "scenario")
    report: dict = {"robust_data": _rel(robust_dir), "holds_data": _rel(holds_dir), "robust_recordings": len(robust),
                    "holds_recordings": len(holds), "limits": {"robust": args.limit, "holds": args.holds_limit},
                    "detectors": [], "families": {}, "holds": {}, "provenance": provenance()}
    t0 = time.perf_counter()
    w = max(1, args.workers)
    family_results: dict[str, list] = {}
    for det in detectors(args):
        report["detectors"].append({k: det[k] for k in ("name", "kind", "threshold", "source")})
        if robust and not args.engine_only:
            res = evaluate_paths(robust, det["kind"], det["args"], workers=w, progress=False)
            family_results[det["name"]] = res
            fams = {fam: figures(rs) for fam, rs in group(res, rtag, "physics_family").items()}
            fams["all"] = figures(res)
            report["families"][det["name"]] = fams
        if holds:
            res = evaluate_paths(holds, det["kind"], det["args"], workers=w, progress=False)
            thr = det["threshold"] if det["kind"] == "model" else None
            # Per hold type, then per hold type and sensor version (the issue asks for both v1 and v2).
            by_sensor = {stem: {"k": f"{t.get('scenario', '')} / {t.get('sensor', '') or '-'}"}
                         for stem, t in htag.items()}
            types = {}
            split = group(res, by_sensor, "k")
            for h, rs in group(res, htag, "scenario").items():
                types[h] = holds_figures(rs, thr)
                for k, rk in split.items():
                    if k.startswith(f"{h} / "):
                        types[k] = holds_figures(rk, thr)
            types["all"] = holds_figures(res, thr)
            report["holds"][det["name"]] = types
        print(f"  {det['name']}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if args.lofo and robust:
        report["lofo"] = {}
        for spec in args.lofo:
            fam, _, manifest = spec.partition("=")
            paths = [p for p in robust if rtag.get(p.stem, {}).get("physics_family") == fam]
            if not paths:
                raise SystemExit(f"--lofo {spec}: no {fam!r} recordings in {robust_dir}")
            det = _model_entry(f"lofo_{fam}", manifest, not args.no_limit_guard)
            fig = figures(evaluate_paths(paths, det["kind"], det["args"], workers=w, progress=False))
            heur = {b: report["families"].get(b, {}).get(fam, {}).get("balanced") for b in BASELINES}
            best = max((v for v in heur.values() if v is not None), default=None)
            report["lofo"][fam] = {"manifest": manifest, **fig, "best_heuristic_balanced": best,
                                   "margin_points": (fig["balanced"] - best) * 100
                                   if best is not None and fig["balanced"] is not None else None}
    if args.seeds and robust:
        per_seed = []
        for manifest in args.seeds:
            det = _model_entry("seed", manifest, not args.no_limit_guard)
            fig = figures(evaluate_paths(robust, det["kind"], det["args"], workers=w, progress=False))
            if holds:
                hf = holds_figures(evaluate_paths(holds, det["kind"], det["args"], workers=w, progress=False),
                                   det["threshold"])
                fig["holds_false_alarms_per_hour"] = hf["false_alarms_per_hour"]
                fig["holds_margin"] = hf["margin"]
            per_seed.append({"manifest": manifest, **fig})
        keys = ("success", "balanced", "stop_false_alarms", "latency_median_s", "holds_false_alarms_per_hour",
                "holds_margin")
        spread = {}
        for k in keys:
            vals = [s[k] for s in per_seed if s.get(k) is not None]
            if vals:
                spread[k] = {"mean": statistics.fmean(vals), "sd": statistics.stdev(vals) if len(vals) > 1 else 0.0,
                             "min": min(vals), "max": max(vals)}
        report["seeds"] = {"runs": per_seed, "summary": spread}
    if engine:
        etag = tags(engine_dir)
        engine = subset(engine, args.engine_limit, etag, "scenario")
        report["engine_data"] = _rel(engine_dir)
        report["engine_recordings"] = len(engine)
        ecats = categories(engine, etag)
        dets = [d for d in detectors(args) if d["kind"] == "baseline"]
        model = args.engine_model or args.model
        if model:
            dets.insert(0, _model_entry("slipd", model, not args.no_limit_guard))
        index = engine_dir / "index.json"
        engine_set = json.loads(index.read_text()).get("set") if index.is_file() else None
        # A report on an engine the model trained on is no hold-out: the report says so in its title.
        report["engine_in_training"] = bool(model and engine_set and engine_set in trained_sets(model))
        report["engine_holdout"] = {}
        for det in dets:
            res = evaluate_paths(engine, det["kind"], det["args"], workers=w, progress=False)
            report["engine_holdout"][det["name"]] = {"source": det["source"], **holdout_figures(res, ecats)}
        print(f"  engine hold-out: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if args.reverse:
        if not robust:
            raise SystemExit(f"--reverse needs our families' recordings (--robust {robust_dir})")
        rcats = categories(robust, rtag)
        report["reverse_holdout"] = {}
        dets = [_model_entry("slipd", args.reverse, not args.no_limit_guard),
                *[d for d in detectors(args) if d["kind"] == "baseline"]]
        for det in dets:
            res = family_results.get(det["name"]) if det["kind"] == "baseline" else None
            if res is None:
                res = evaluate_paths(robust, det["kind"], det["args"], workers=w, progress=False)
            report["reverse_holdout"][det["name"]] = {"source": det["source"], **holdout_figures(res, rcats)}
        print(f"  reverse hold-out: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    report["seconds"] = round(time.perf_counter() - t0, 1)
    return report


# --------------------------------------------------------------------------- report
def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _ms(v) -> str:
    return "-" if v is None else f"{1000 * v:.0f} ms"


def _num(v, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def tables(report: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) of every table; printed and written the same way."""
    out = []
    if report["families"]:
        head = ["detector", "family", "n (slip/stop)", "offline success", "balanced", "stop false alarms",
                "latency median", "latency p90", "FA/h no-slip"]
        rows = []
        for det, fams in report["families"].items():
            for fam, f in fams.items():
                rows.append([det, fam, f"{f['n']} ({f['slip']}/{f['stop']})", _pct(f["success"]), _pct(f["balanced"]),
                             f"{_pct(f['stop_false_alarms'])} ({f['stop_alarmed']}/{f['stop']})",
                             _ms(f["latency_median_s"]), _ms(f["latency_p90_s"]), _num(f["false_alarms_per_hour"], 0)])
        out.append(("Every detector on every physics family (robust test split)", head, rows))
    if report["holds"]:
        head = ["detector", "hold type", "recordings", "minutes", "alarms", "false alarms / h", "p99 p_slip (worst)",
                "p99 p_slip (median)", "margin below threshold"]
        rows = []
        for det, types in report["holds"].items():
            for h, f in types.items():
                rows.append([det, h, str(f["n"]), _num(f["hours"] * 60), str(f["alarms"]),
                             _num(f["false_alarms_per_hour"], 1), _num(f["p99_worst"], 3), _num(f["p99_median"], 3),
                             _num(f["margin"], 3)])
        out.append((f"Holds: false alarms per hour and where p_slip settles (last {SETTLE_FRACTION:.0%} of each hold)",
                    head, rows))
    if report.get("lofo"):
        head = ["held-out family", "offline success", "balanced", "stop false alarms", "latency median",
                "better heuristic balanced", "margin (points)", "manifest"]
        rows = [[fam, _pct(f["success"]), _pct(f["balanced"]), _pct(f["stop_false_alarms"]), _ms(f["latency_median_s"]),
                 _pct(f["best_heuristic_balanced"]), _num(f["margin_points"]), f["manifest"]]
                for fam, f in report["lofo"].items()]
        out.append(("Leave-one-family-out: each fold's model on the family it was trained without", head, rows))
    tested_on = report.get("engine_data") or "the engine"
    engine_title = (f"Engine in training (not held out): the model tested on {tested_on}"
                    if report.get("engine_in_training") else f"Engine held out: the model tested on {tested_on}")
    for key, title in (("engine_holdout", engine_title),
                       ("reverse_holdout", "Reverse: trained on the engine only, tested on our own families")):
        if not report.get(key):
            continue
        head = ["detector", "n", "offline success", "slips caught", "balanced", "online success (lifts)",
                "stop false alarms", "partial slips alarmed", "latency median", "light grasps", "slow loads",
                *[c.replace("_", " ") for c in CATEGORIES[1:]]]
        rows = []
        for det, f in report[key].items():
            cat, whole = f["categories"], f["all"]
            rows.append([det, str(f["n"]), _pct(f["offline_success"]),
                         f"{round((f['slip_recall'] or 0.0) * whole['slip'])}/{whole['slip']}",
                         _pct(f["balanced_success"]),
                         f"{_pct(f['online_success'])} ({f['online_lifts']})", _pct(f["stop_false_alarm_rate"]),
                         f"{whole.get('partial_alarmed', 0)}/{whole.get('partial', 0)}", _ms(whole["latency_median_s"]),
                         _pct(f["light_grasp_success"]), _pct(f["slow_load_success"]),
                         *[f"{_pct(cat[c]['success'])} ({cat[c]['n']})" if c in cat else "-" for c in CATEGORIES[1:]]])
        whole = next(iter(report[key].values()))["all"]
        scored = whole["slip"] + whole["stop"]
        if scored:
            # The floor every row stands on: the offline success of a detector that never alarms is the share of
            # no-slip recordings, which on a split of mostly quiet grasps is well above one half.
            rows.append(["(never alarms)", str(whole["n"]), _pct(whole["stop"] / scored), f"0/{whole['slip']}",
                         _pct(0.5), "-", _pct(0.0), "-", "-", *["-"] * (len(head) - 9)])
        out.append((title, head, rows))
    if report.get("seeds"):
        head = ["figure", "mean", "sd", "min", "max"]
        rows = []
        for k, v in report["seeds"]["summary"].items():
            fmt = _ms if k.endswith("_s") else _pct if k in ("success", "balanced", "stop_false_alarms") else _num
            rows.append([k, fmt(v["mean"]), fmt(v["sd"]), fmt(v["min"]), fmt(v["max"])])
        out.append((f"Seeds: {len(report['seeds']['runs'])} runs of the recipe", head, rows))
    return out


def markdown(report: dict) -> str:
    lines = ["# Robustness benchmark", "",
             "Generated by `python tools/robustness.py` (sliplab.robustness); every figure below is printed by that "
             "command. Metrics: `sliplab.metrics` (offline criterion: an alarm from 0.3 s before the labelled onset "
             "until gross slip is a hit; any alarm on a stop/hold is a false alarm).", "",
             f"- robust test split: `{report['robust_data']}` ({report['robust_recordings']} recordings"
             + (f", a spread subset of --limit {report['limits']['robust']})" if report["limits"]["robust"] else ")"),
             f"- holds: `{report['holds_data']}` ({report['holds_recordings']} recordings"
             + (f", a spread subset of --holds-limit {report['limits']['holds']})" if report["limits"]["holds"]
                else ")"),
             "- detectors: " + "; ".join(f"{d['name']} ({d['kind']}, threshold {d['threshold']:g}, {d['source']})"
                                          for d in report["detectors"]),
             *([f"- engine test split: `{report['engine_data']}` ({report['engine_recordings']} recordings)"]
               if report.get("engine_data") else []),
             f"- evaluation time: {report['seconds']} s"]
    prov = report.get("provenance") or {}
    if prov:
        lines.append(f"- code: commit {prov.get('commit') or '?'}" + (
            f", with uncommitted changes to {', '.join(prov['uncommitted'])}" if prov.get("uncommitted") else ""))
    lines.append("")
    for title, head, rows in tables(report):
        lines += [f"## {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        lines.append("")
    return "\n".join(lines)


def print_report(report: dict) -> None:
    prov = report.get("provenance") or {}
    if prov:
        print(f"code: commit {prov.get('commit')}; uncommitted: {', '.join(prov.get('uncommitted') or []) or 'none'}")
    for title, head, rows in tables(report):
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
        print(f"\n{title}")
        print("  ".join(h.ljust(w) for h, w in zip(head, widths)))
        for r in rows:
            print("  ".join(c.ljust(w) for c, w in zip(r, widths)))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", help="the model manifest to benchmark (slipd.detect.ensemble.Ensemble.load)")
    p.add_argument("--authors", help="the authors' checkpoints as a manifest (optional)")
    p.add_argument("--baselines", default=str(DEFAULT_BASELINES), help="shipped heuristic parameters JSON")
    p.add_argument("--robust", default=str(ROOT / "out" / "datasets" / "robust_test"))
    p.add_argument("--holds", default=str(ROOT / "out" / "datasets" / "holds_test"))
    p.add_argument("--lofo", nargs="*", default=[], metavar="FAMILY=MANIFEST",
                   help="per-fold manifests: the recipe trained without FAMILY")
    p.add_argument("--seeds", nargs="*", default=[], metavar="MANIFEST", help="several seeds of one recipe")
    p.add_argument("--workers", type=int, default=1, help="processes (2 at most on the shared machine)")
    p.add_argument("--heuristics", nargs="*", choices=sorted(BASELINES), default=None,
                   help="which heuristics (default, and the flag without a name: both)")
    p.add_argument("--limit", type=int, default=0,
                   help="evaluate N robust recordings, an equal share per family (0: all; a reduced run says so)")
    p.add_argument("--holds-limit", type=int, default=0, help="the same for the holds, per hold type")
    p.add_argument("--engine", default=None,
                   help="the engine's test split (tools/make_dataset.py --set engine): the engine hold-out")
    p.add_argument("--engine-model", default=None,
                   help="engine hold-out: a manifest trained without engine data (default: --model)")
    p.add_argument("--engine-limit", type=int, default=0, help="evaluate N engine recordings, spread over scenarios")
    p.add_argument("--reverse", default=None, metavar="MANIFEST",
                   help="a manifest trained on the engine only, tested on --robust (the reverse hold-out)")
    p.add_argument("--no-limit-guard", action="store_true", help=NO_LIMIT_GUARD_HELP)
    p.add_argument("--engine-only", action="store_true",
                   help="only the hold-outs: skip the per-family table and the holds")
    p.add_argument("--out", default=str(ROOT / "reports" / "robustness"),
                   help="report path without suffix (.md and .json are written)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the report's JSON here")
    p.add_argument("--record-manifest", action="store_true",
                   help="merge the --model's figures (all families, holds, folds) into its manifest's metrics")
    p.add_argument("--from-report", metavar="JSON",
                   help="with --record-manifest: record from this written report instead of running again")
    args = p.parse_args(argv)
    if args.record_manifest and not args.model:
        p.error("--record-manifest needs --model")
    if args.from_report:
        if not args.record_manifest:
            p.error("--from-report is for --record-manifest")
        report = json.loads(Path(args.from_report).read_text())
        if str(args.model) not in {d["source"] for d in report["detectors"]}:
            p.error(f"--from-report {args.from_report} did not benchmark {args.model}")
    else:
        report = run(args)
        print_report(report)
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
        out.with_suffix(".md").write_text(markdown(report))
        if args.json:
            Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
        print(f"\nwrote {out.with_suffix('.md')} and {out.with_suffix('.json')} ({report['seconds']} s)")
    if args.record_manifest:
        from slipd.detect.manifest import update_metrics

        update_metrics(args.model, manifest_figures(report, args.out if not args.from_report else args.from_report))
        print(f"recorded the robustness figures in {args.model}")
    return 0


def manifest_figures(report: dict, where: str) -> dict:
    """The model's figures as the manifest keeps them (``slipd models`` prints the scalars)."""
    fams = report["families"].get("slipd", {})
    holds = report["holds"].get("slipd", {})
    md = Path(where).with_suffix(".md").resolve()
    rob: dict = {"report": str(md.relative_to(ROOT)) if md.is_relative_to(ROOT) else str(md),
                 "robust_all": fams.get("all"), "holds_all": holds.get("all"),
                 "lofo": {fam: {k: f[k] for k in ("success", "balanced", "stop_false_alarms")}
                          for fam, f in (report.get("lofo") or {}).items()}}
    out: dict = {"robustness": rob}
    if fams.get("all"):
        out["robust_test_success"] = round(fams["all"]["success"], 4)
    if holds.get("all"):
        out["holds_false_alarms_per_hour"] = round(holds["all"]["false_alarms_per_hour"], 4)
        out["holds_p_slip_margin"] = round(holds["all"]["margin"], 4)
    return out


if __name__ == "__main__":
    sys.exit(main())
