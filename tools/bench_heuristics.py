"""Benchmark the heuristic detectors (``model.detector: reference_pillar | deceleration``) as the daemon runs them.

    python tools/bench_heuristics.py [--recording FILE] [--rounds 4] [--block 10]

Each heuristic streams one recording (default: the packaged sample) through ``HeuristicDetector`` twice per round,
side by side: a push per sample (the baseline: how a loop that hands over every frame drives it) and a block of
``--block`` samples per call (how the daemon hands over a read at stride 10). Rounds alternate the two, so a noisy,
shared machine disturbs them alike. Prints the median microseconds per sample of each and the share of one core that
is at 1 kHz; both ways give the same detections (``tests/detect/test_baselines.py``). Figures are printed, never
asserted.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from slipd import models
from slipd.detect.baselines import BASELINES, baseline_offset
from slipd.detect.detector import HeuristicDetector
from slipd.recording import Recording
from sliplab.evaluate import tare_stretch
from sliplab.robustness import DEFAULT_BASELINES


def per_sample_us(name: str, rec: Recording, block: int) -> float:
    """Microseconds per sample of one pass over ``rec`` (``block`` 1: a push per sample)."""
    det = HeuristicDetector(name, DEFAULT_BASELINES, baseline_offset(rec.force, rec.disp, tare_stretch(rec)))
    f, t, d = rec.force, rec.t_us, rec.disp
    n = len(f) - len(f) % block
    t0 = time.perf_counter()
    if block == 1:
        for i in range(n):
            det.push(f[i], int(t[i]), d[i])
    else:
        for i in range(0, n, block):
            det.push_many(f[i : i + block], t[i : i + block], d[i : i + block])
    return (time.perf_counter() - t0) / n * 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recording", type=Path, default=models.SAMPLE_RECORDING, help="a recording (.npz)")
    p.add_argument("--rounds", type=int, default=4, help="alternating rounds of both ways")
    p.add_argument("--block", type=int, default=10, help="samples per call of the block way (the stride)")
    args = p.parse_args(argv)
    rec = Recording.load(args.recording)
    print(f"{args.recording.name}: {len(rec)} samples, {args.rounds} alternating rounds, median per sample")
    for name in sorted(BASELINES):
        got: dict[int, list[float]] = {1: [], args.block: []}
        for r in range(args.rounds):
            for block in ((1, args.block) if r % 2 == 0 else (args.block, 1)):
                got[block].append(per_sample_us(name, rec, block))
        one, many = (float(np.median(got[b])) for b in (1, args.block))
        print(f"  {name:16s} a push per sample {one:6.1f} us ({one / 10:.1f} % of a core at 1 kHz); blocks of "
              f"{args.block} {many:6.1f} us ({many / 10:.1f} %): {one / many:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
