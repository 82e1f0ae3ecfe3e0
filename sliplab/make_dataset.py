"""Write a simulated data set: ``python tools/make_dataset.py --set offline --split test --out DIR``.

Prints the physics speed relative to real time (simulated seconds / wall seconds of simulation).
"""

from __future__ import annotations

import argparse
import sys
import time

from tqdm import tqdm

from slipd.sim.datasets import HOLD_S, SETS, SPLITS, dataset_scenes, write_dataset


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--set", dest="set_name", choices=SETS, required=True)
    p.add_argument("--split", choices=SPLITS, required=True)
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--count", type=int, default=None,
                   help="number of scenes (default: 200 offline, 216 transfer, 200 robust, 100 holds, 200 grips, "
                   "200 twists, 200 engine, 200 bullet, 200 coulomb)")
    p.add_argument("--hold-s", type=float, default=HOLD_S,
                   help="holds: seconds of stillness per recording (5 types x 2 sensors, round-robin)")
    p.add_argument("--seed", type=int, default=0, help="data-set seed 0..999")
    p.add_argument("--batch", type=int, default=16, help="scenes simulated together in one time loop")
    args = p.parse_args(argv)
    if args.count is not None and args.count < 1:
        p.error("--count must be >= 1")
    total = len(dataset_scenes(args.set_name, args.split, args.count, args.seed, args.hold_s))
    t0 = time.perf_counter()
    with tqdm(total=total, unit="scene", desc=f"{args.set_name}/{args.split}") as bar:
        index = write_dataset(args.set_name, args.split, args.out, args.count, args.seed, args.batch, bar.update,
                              args.hold_s)
    wall = time.perf_counter() - t0
    print(f"{index['count']} recordings ({index['slip']} slip, {index['stop']} stop, "
          f"{index['count'] - index['slip'] - index['stop']} hold; "
          f"{index['slip_with_onset']} slip scenes with an onset) -> {args.out}")
    print(f"simulated {index['simulated_s']:.1f} s in {index['physics_wall_s']:.2f} s of physics: "
          f"{index['speed_ratio']}x real time (total with file writing {wall:.1f} s)")
    for key in ("physics_family", "scenario"):
        if key in index:
            print(f"{key}: " + ", ".join(f"{k} {v}" for k, v in index[key].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
