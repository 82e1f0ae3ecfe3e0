"""Fuzz the PTSCOM 2.0 decoder: random streams of valid, corrupted and junk bytes, in random splits.

A launcher: the code lives in ``sliplab.fuzz_pts`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.fuzz_pts import main

if __name__ == "__main__":
    raise SystemExit(main())
