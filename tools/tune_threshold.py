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

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from slipd.evaluation import offline_outcome, online_outcome  # noqa: E402
from slipd.recording import list_recordings  # noqa: E402
from tools.evaluate import evaluate_paths  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Sweep the grid and print the table; returns 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True)
    p.add_argument("--recordings", type=Path, nargs="+", required=True, help="train-split folders")
    p.add_argument("--every", type=int, default=4, help="use every k-th recording (speed)")
    p.add_argument("--grid", default="0.3:0.85:0.05", help="start:stop:step")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--stride", type=int, default=None, help="decision stride override (phase-shifted streams)")
    p.add_argument("--criterion", choices=("auto", "offline", "online"), default="auto",
                   help="success criterion: auto = online for gripper trials, the offline one otherwise")
    args = p.parse_args(argv)
    paths = [q for folder in args.recordings for q in list_recordings(folder)][:: args.every]
    # The threshold passed here only sets the stored alarm flags; the sweep below re-thresholds p_slip.
    runs = evaluate_paths(paths, "model", (args.model, 0.0, 0.5, args.stride), workers=args.workers, progress=False)
    a, b, s = (float(x) for x in args.grid.split(":"))
    best = None
    print(f"{len(paths)} train recordings")
    print("threshold  success  slip TP/N  stop FP/N  median latency")
    for th in np.arange(a, b + 1e-9, s):
        outcomes, lats = [], []
        for _, trace, truth in runs:
            p_arr = np.asarray(trace.p_slip)
            hit = np.flatnonzero(p_arr >= th)
            first = trace.t_s[hit[0]] if len(hit) else None
            online = args.criterion == "online" or (args.criterion == "auto" and truth.family == "gripper")
            out = online_outcome(truth, first) if online else offline_outcome(truth, first)
            out = "tp" if out == "success" else out  # the online criterion's name for a hit
            if out is None:
                continue
            outcomes.append(out)
            if out == "tp" and truth.onset_s is not None:
                lats.append(first - truth.onset_s)
        n = len(outcomes)
        ok = sum(o in ("tp", "tn") for o in outcomes)
        slips = sum(o in ("tp", "early", "late", "missed") for o in outcomes)
        stops = n - slips
        fp = sum(o == "fp" for o in outcomes)
        med = float(np.median(lats)) if lats else float("nan")
        print(f"{th:9.2f}  {100 * ok / n:6.1f} %  {outcomes.count('tp'):4d}/{slips:<4d}  {fp:4d}/{stops:<4d}  "
              f"{med * 1e3:8.1f} ms")
        key = (ok / n, -abs(med) if lats else -1e9)
        if best is None or key > best[0]:
            best = (key, th)
    print(f"best threshold {best[1]:.2f} (train success {100 * best[0][0]:.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
