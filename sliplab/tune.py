"""Choose the alarm threshold of a model on TRAIN recordings only (never the test split).

    python tools/tune_threshold.py --model out/train_main/ensemble.json --recordings out/datasets/offline_train \
        [--every 4] [--grid 0.3:0.8:0.05]

The model's probabilities do not depend on the threshold, so each recording is streamed once through
the daemon's decision path (``tools/evaluate.py``'s runner: ``Detector``) and the threshold is then
applied to the stored traces: the first window with ``p_slip >= threshold`` is the first alarm. Prints,
for every threshold of the grid, the method's offline success rate, the stop-scene false positives
and the median latency, and the best threshold (highest success; ties: the lower |median latency|).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from slipd.recording import list_recordings
from sliplab.evaluate import evaluate_paths
from sliplab.metrics import scored_outcome


def sweep(runs: list, thresholds: np.ndarray, criterion: str = "auto") -> list[dict]:
    """Re-threshold stored traces: one row per threshold with success, slip TP/N, stop FP/N, median latency.

    ``runs``: ``evaluate_paths`` output; ``criterion``: "online", "offline" or "auto" (online for gripper
    trials, the offline criterion otherwise).
    """
    rows = []
    for th in thresholds:
        outcomes, lats = [], []
        for _, trace, truth in runs:
            p_arr = np.asarray(trace.p_slip)
            hit = np.flatnonzero(p_arr >= th)
            first = trace.t_s[hit[0]] if len(hit) else None
            out = scored_outcome(truth, first, criterion)
            if out is None:
                continue
            outcomes.append(out)
            if out == "tp" and truth.onset_s is not None:
                lats.append(first - truth.onset_s)
        n = len(outcomes)
        slips = sum(o in ("tp", "early", "late", "missed") for o in outcomes)
        rows.append({"threshold": float(th), "success": sum(o in ("tp", "tn") for o in outcomes) / n if n else 0.0,
                     "tp": outcomes.count("tp"), "slips": slips, "fp": outcomes.count("fp"), "stops": n - slips,
                     "median_latency_s": float(np.median(lats)) if lats else None})
    return rows


def best_row(rows: list[dict]) -> dict:
    """Highest success; ties: the lower |median latency|."""
    def key(r: dict) -> tuple:
        lat = r["median_latency_s"]
        return r["success"], -abs(lat) if lat is not None else -1e9
    return max(rows, key=key)


def tune(model: str, paths: list[Path], grid: np.ndarray, stride: int | None = None, workers: int = 2,
         criterion: str = "auto") -> tuple[dict, list[dict]]:
    """Stream ``paths`` once through ``model`` and sweep ``grid``: (best row, all rows)."""
    # The threshold passed here only sets the stored alarm flags; the sweep re-thresholds p_slip.
    runs = evaluate_paths(paths, "model", (model, 0.0, 0.5, stride), workers=workers, progress=False)
    rows = sweep(runs, grid, criterion)
    return best_row(rows), rows


def main(argv: list[str] | None = None) -> int:
    """Sweep the grid and print the table; returns 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True)
    p.add_argument("--recordings", type=Path, nargs="+", required=True, help="train-split folders")
    p.add_argument("--every", type=int, default=3,
                   help="use every k-th recording (speed); not a multiple of 4 on transfer sets, whose design "
                        "repeats 3 slip trials and 1 stop trial")
    p.add_argument("--grid", default="0.3:0.85:0.05", help="start:stop:step")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--stride", type=int, default=None, help="decision stride override (phase-shifted streams)")
    p.add_argument("--criterion", choices=("auto", "offline", "online"), default="auto",
                   help="success criterion: auto = online for gripper trials, the offline one otherwise")
    args = p.parse_args(argv)
    paths = [q for folder in args.recordings for q in list_recordings(folder)][:: args.every]
    a, b, s = (float(x) for x in args.grid.split(":"))
    best, rows = tune(args.model, paths, np.arange(a, b + 1e-9, s), args.stride, args.workers, args.criterion)
    print(f"{len(paths)} train recordings")
    print("threshold  success  slip TP/N  stop FP/N  median latency")
    for r in rows:
        med = float("nan") if r["median_latency_s"] is None else r["median_latency_s"]
        print(f"{r['threshold']:9.2f}  {100 * r['success']:6.1f} %  {r['tp']:4d}/{r['slips']:<4d}  "
              f"{r['fp']:4d}/{r['stops']:<4d}  {med * 1e3:8.1f} ms")
    print(f"best threshold {best['threshold']:.2f} (train success {100 * best['success']:.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
