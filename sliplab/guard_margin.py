"""The limit guard's margin: how near the contact risk comes to raising the alarm where nothing slips, and which
slips it raises.

The limit guard (``decision.limit_guard``, ``slipd.detect.decision``) raises the alarm once the contact risk has stayed
at or above ``limit_guard`` for ``limit_guard_decisions`` decisions in a row. Per folder of recordings this streams each
one through the model's detector with the default config's decision rule (as ``tools/robustness.py`` and
``tools/evaluate.py`` do) and prints, by recording kind (slip, stop, hold, partial: the recording's ``meta["kind"]``):
how many there are, how many hold the risk at the guard for the run (the guard raises the alarm there), and the
highest level any of them holds for that run. For the kinds where nothing slips (stop, hold), that level below the
guard is the margin.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from sliplab.metrics import NO_SLIP_KINDS


def held_peak(risk: Sequence[float], run: int) -> float:
    """The highest level ``risk`` stays at or above for ``run`` decisions in a row (0 for fewer decisions; a NaN, a
    decision without a contact state, breaks a run as the guard's count does)."""
    r = np.nan_to_num(np.asarray(risk, np.float64), nan=-math.inf)
    if len(r) < run:
        return 0.0
    return float(max(0.0, np.lib.stride_tricks.sliding_window_view(r, run).min(axis=1).max()))


def scan(folder: Path, manifest: str) -> dict[str, Any]:
    """Every recording of ``folder`` through ``manifest``'s detector: per kind, the recordings, those the guard
    alarms on, and the highest level held for the guard's run."""
    from slipd.recording import Recording, list_recordings
    from sliplab.evaluate import ModelRunner

    runner = ModelRunner(manifest)
    rule = runner.decision  # (the default config's rule, as the evaluation scores it)
    if rule.limit_guard is None:
        raise SystemExit("decision.limit_guard is off in the default config: nothing to measure")
    kinds: dict[str, dict[str, Any]] = {}
    for path in tqdm(list_recordings(folder), desc=folder.name, unit="rec"):
        rec = Recording.load(path)
        peak = held_peak(runner.trace(rec).contact_risk, rule.limit_guard_decisions)
        k = kinds.setdefault(str(rec.meta.get("kind", "unknown")), {"recordings": 0, "guarded": 0, "peak": 0.0,
                                                                     "worst": None})
        k["recordings"] += 1
        k["guarded"] += peak >= rule.limit_guard
        if peak >= k["peak"]:
            k["peak"], k["worst"] = peak, path.name
    return {"data": str(folder), "model": manifest, "limit_guard": rule.limit_guard,
            "limit_guard_decisions": rule.limit_guard_decisions, "kinds": kinds}


def report(result: dict[str, Any]) -> str:
    """One folder's result as printed lines."""
    g, n = result["limit_guard"], result["limit_guard_decisions"]
    lines = [f"{result['data']}: limit guard {g} for {n} decisions in a row ({result['model']})"]
    for kind, k in sorted(result["kinds"].items()):
        line = (f"  {kind:8s} {k['recordings']:4d} recordings, the guard alarms on {k['guarded']}; highest risk held "
                f"for {n} decisions {k['peak']:.3f} ({k['worst']})")
        if kind in NO_SLIP_KINDS and k["peak"] < g:  # (where the guard alarms, the count says so)
            line += f", {g - k['peak']:.3f} below the guard"
        lines.append(line)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="slipd/models/slip_ensemble_int8.json", help="model manifest")
    p.add_argument("--data", type=Path, nargs="+", required=True, help="folders of recordings")
    p.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = p.parse_args(argv)
    results = []
    for folder in args.data:
        results.append(scan(folder, args.model))
        print(report(results[-1]), flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    return 0
