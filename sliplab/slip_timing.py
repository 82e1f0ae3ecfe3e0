"""Per scored slip: when each detector first alarmed against the offline window, and what the label rests on.

    python tools/slip_timing.py --data out/datasets/engine_test --model M.json [M2.json ...] [--json PATH]
    python tools/slip_timing.py --labels out/datasets/engine_train

For every slip the offline criterion scores (``sliplab.metrics``: a labelled onset before gross slip) it prints
the incipient stage (gross slip - onset), the pillars that slide at the onset with their normal force, each
model's outcome, first alarm (ms after the onset) and largest P(slip) inside ``[onset - 0.3 s, gross slip]``,
and the reference-pillar heuristic's outcome and first alarm (its shipped parameters). Then per slip group
(``slip_group``) how many each detector caught in time, and the no-slip recordings each alarmed.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from slipd.detect.baselines import load_params
from slipd.detect.features import stretch_offset
from slipd.geometry import CONTACT_THRESHOLD_N
from slipd.recording import Recording, list_recordings
from sliplab.evaluate import NO_LIMIT_GUARD_HELP, evaluate_paths
from sliplab.metrics import EARLY_TOLERANCE_S, NO_SLIP_KINDS
from sliplab.robustness import DEFAULT_BASELINES
from sliplab.train import is_partial_slip, sliding_span_labels, slip_span_labels

LIGHT_ONSET_N = CONTACT_THRESHOLD_N
"""The SDK's contact flag: below it a pillar reads as out of contact to every detector's input (the model's
utilisation divides by at least 0.5 N; the heuristics' speeds skip such pillars)."""
SHORT_INCIPIENT_S = 0.03
"""Incipient stages shorter than this end before a decision every 10 ms can confirm twice on its evidence."""

GROUPS = ("onset on light pillars", "incipient under 30 ms", "other")


def slip_group(onset_fz: list[float], incipient_s: float) -> str:
    """Which group a scored slip falls in: the label's onset rests only on pillars under the contact flag, or the
    incipient stage is too short for a confirmed decision, or neither."""
    if not onset_fz or max(onset_fz) < LIGHT_ONSET_N:
        return GROUPS[0]
    if incipient_s < SHORT_INCIPIENT_S:
        return GROUPS[1]
    return GROUPS[2]


def onset_pillars(rec: Recording, onset_s: float) -> tuple[list[int], list[float]]:
    """SDK indices of the pillars sliding at the onset sample and their tared normal force (N)."""
    t_s = (np.asarray(rec.t_us, np.int64) - int(rec.t_us[0])) / 1e6
    i = int(min(np.searchsorted(t_s, onset_s), len(t_s) - 1))
    if rec.slip is None:
        return [], []
    stretch = rec.meta.get("tare_samples", [0, 100])
    fz = rec.force[i, :, 2] - stretch_offset(rec.force, stretch)[:, 2]
    idx = [int(k) for k in np.flatnonzero(np.nan_to_num(rec.slip[i]) > 0)]
    return idx, [round(float(fz[k]), 3) for k in idx]


def _ms(first: float | None, onset: float) -> int | None:
    return None if first is None else round(1000 * (first - onset))


def run(data: Path, models: list[str], limit_guard: bool = True) -> dict:
    """Every scored slip with each detector's timing, the group counts and the no-slip alarms (``limit_guard``
    False: each model on its own decision rule, ``--no-limit-guard``)."""
    paths = list_recordings(data)
    params, frontend = load_params(DEFAULT_BASELINES, "reference_pillar")
    runs = {"reference_pillar": evaluate_paths(paths, "baseline", ("reference_pillar", params, frontend),
                                               progress=False)}
    for m in models:
        runs[m] = evaluate_paths(paths, "model", (m, 0.0, None, None, limit_guard), progress=False)
    slips, alarmed = [], Counter()
    for i, path in enumerate(paths):
        truth = runs["reference_pillar"][i][2]
        if truth.kind in NO_SLIP_KINDS:
            alarmed.update(name for name, res in runs.items() if res[i][0].first_alarm_s is not None)
        if truth.kind != "slip" or truth.onset_s is None or truth.gross_slip_s is None:
            continue
        rec = Recording.load(path)
        pillars, fz = onset_pillars(rec, truth.onset_s)
        incipient = truth.gross_slip_s - truth.onset_s
        row = {"recording": path.stem, "scenario": rec.meta.get("scenario", ""),
               "incipient_ms": round(1000 * incipient), "onset_pillars": pillars, "onset_fz_n": fz,
               "group": slip_group(fz, incipient), "detectors": {}}
        for name, res in runs.items():
            result, trace = res[i][0], res[i][1]
            t, p = np.asarray(trace.t_s), np.asarray(trace.p_slip)
            win = (t >= truth.onset_s - EARLY_TOLERANCE_S) & (t <= truth.gross_slip_s)
            row["detectors"][name] = {"outcome": result.offline_outcome,
                                      "first_alarm_ms": _ms(result.first_alarm_s, truth.onset_s),
                                      "p_max_in_window": round(float(p[win].max()), 3) if win.any() else None}
        slips.append(row)
    groups = {g: {name: dict(Counter(s["detectors"][name]["outcome"] for s in slips if s["group"] == g))
                  for name in runs} | {"slips": sum(s["group"] == g for s in slips)} for g in GROUPS}
    no_slip = sum(1 for r in runs["reference_pillar"] if r[2].kind in NO_SLIP_KINDS)
    return {"data": str(data), "slips": slips, "groups": groups,
            "no_slip_alarmed": {name: alarmed[name] for name in runs}, "no_slip": no_slip}


def label_stats(data: Path) -> dict:
    """How a training split's labels treat sliding: its slips, those without a labelled sample (no incipient stage),
    and the samples where a pillar slides while the grasp is in contact (a pillar above the contact flag), labelled
    slip or not under the training spans ``slip`` and ``sliding`` (``sliplab.train``), by recording kind; the partial
    slips ``sliplab.train --skip-partial`` leaves out; and where the sliding pillars' friction utilisation |Ft| / Fz
    lies (percentiles 10, 50 and 90 over the samples in which a pillar in contact slides): a sliding pillar carries
    its friction coefficient, so this is the range of friction the split's slips teach."""
    out: dict = {"recordings": 0, "slips": 0, "slips_unlabelled": 0, "partial_slips": 0}
    utils = []
    for path in list_recordings(data):
        rec = Recording.load(path)
        if rec.label is None or rec.slip is None:
            continue
        out["recordings"] += 1
        kind = str(rec.meta.get("kind", "stop"))
        if kind == "slip":
            out["slips"] += 1
            out["slips_unlabelled"] += int(not np.any(rec.label))
        stretch = rec.meta.get("tare_samples", [0, 100])
        force = rec.force - stretch_offset(rec.force, stretch)
        fz = force[:, :, 2]
        slides = np.nan_to_num(rec.slip) > 0
        sliding = slides.any(axis=1) & (fz > LIGHT_ONSET_N).any(axis=1)
        out["partial_slips"] += int(is_partial_slip(rec.label, slides, force))
        loaded = slides & (fz > LIGHT_ONSET_N)
        utils.append(np.hypot(force[:, :, 0], force[:, :, 1])[loaded] / fz[loaded])
        events, t_s = rec.meta.get("events") or {}, rec.t_us / 1e6
        for span, lab in (("slip", slip_span_labels(rec.label, events, t_s)),
                          ("sliding", sliding_span_labels(rec.label, rec.slip, events, t_s))):
            d = out.setdefault(f"{span} span, {kind} recordings", {"sliding labelled slip": 0,
                                                                   "sliding labelled no slip": 0})
            d["sliding labelled slip"] += int((sliding & (lab > 0)).sum())
            d["sliding labelled no slip"] += int((sliding & (lab == 0)).sum())
    u = np.concatenate(utils) if utils else np.zeros(0)
    out["sliding_utilisation_p10_p50_p90"] = [round(float(v), 2) for v in np.percentile(u, [10, 50, 90])] \
        if len(u) else None
    return out


def print_report(report: dict) -> None:
    """The per-slip table, then the group counts."""
    names = list(report["no_slip_alarmed"])
    print("recording | scenario | incipient ms | onset pillars (N) | " + " | ".join(
        f"{Path(n).parent.name or n}: outcome, first alarm ms, p max" for n in names))
    for s in report["slips"]:
        cells = []
        for n in names:
            d = s["detectors"][n]
            cells.append(f"{d['outcome']} {d['first_alarm_ms']} {d['p_max_in_window']}")
        print(f"{s['recording']} | {s['scenario']} | {s['incipient_ms']} | "
              f"{dict(zip(s['onset_pillars'], s['onset_fz_n']))} | " + " | ".join(cells))
    for g, counts in report["groups"].items():
        print(f"{g} ({counts['slips']} slips): " + "; ".join(
            f"{Path(n).parent.name or n} {counts[n]}" for n in names))
    print(f"no-slip recordings alarmed (of {report['no_slip']}): " + "; ".join(
        f"{Path(n).parent.name or n} {k}" for n, k in report["no_slip_alarmed"].items()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=None, help="a test split (tools/make_dataset.py)")
    p.add_argument("--model", nargs="+", default=[], help="model manifests")
    p.add_argument("--json", type=Path, default=None, help="also write the report here")
    p.add_argument("--no-limit-guard", action="store_true", help=NO_LIMIT_GUARD_HELP)
    p.add_argument("--labels", type=Path, default=None,
                   help="a training split: print how its labels treat sliding pillars (samples) instead")
    args = p.parse_args(argv)
    if args.labels is not None:
        print(json.dumps(label_stats(args.labels), indent=1))
        return 0
    if args.data is None or not list_recordings(args.data):
        raise SystemExit(f"--data {args.data}: no recordings (a test split, or --labels TRAIN_SPLIT)")
    report = run(args.data, args.model, not args.no_limit_guard)
    print_report(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0
