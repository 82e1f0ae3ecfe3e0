"""Copy a folder of recordings with Gaussian noise added to the pillar tip displacements.

    python tools/noisy_displacements.py --sigma 0.002 --src out/datasets/transfer_test --out out/noisy_0.002
    python tools/evaluate.py --baseline deceleration --recordings out/noisy_0.002 --online

The simulator reports tip displacements without noise (``slipd.sim.effects`` perturbs forces only), while
the published heuristics read exactly those displacements. This tool measures how much their figures rest
on that: the same scenes, forces untouched, displacements with N(0, sigma) mm added per sample and axis.
For scale: the simulated force noise (0.03 N) over the v2 tip stiffness (3.5 N/mm) is about 0.009 mm.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from slipd.recording import Recording, list_recordings


def main(argv: list[str] | None = None) -> int:
    """Write the noisy copies; returns 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sigma", type=float, required=True, help="displacement noise, mm (standard deviation)")
    p.add_argument("--src", type=Path, required=True, help="folder of recordings")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.sigma < 0:
        p.error("--sigma must be >= 0")
    paths = list_recordings(args.src)
    if not paths:
        p.error(f"no recordings in {args.src}")
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    for path in paths:
        rec = Recording.load(path)
        rec.disp = (rec.disp + rng.normal(0.0, args.sigma, rec.disp.shape)).astype(np.float32)
        rec.meta = {**rec.meta, "disp_noise_mm": args.sigma}
        rec.save(args.out / path.name)
    print(f"wrote {len(paths)} recordings with displacement noise {args.sigma} mm to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
