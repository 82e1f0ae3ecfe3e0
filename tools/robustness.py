"""Robustness benchmark: every detector on every physics family, holds, leave-one-family-out, seeds.

A launcher: the code lives in ``slipd.lab.robustness`` (the offline lab; ``pip install -e '.[train]'``).
"""

from slipd.lab.robustness import main

if __name__ == "__main__":
    raise SystemExit(main())
