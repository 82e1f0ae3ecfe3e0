"""Robustness benchmark: every detector on every physics family, holds, leave-one-family-out, seeds.

A launcher: the code lives in ``sliplab.robustness`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.robustness import main

if __name__ == "__main__":
    raise SystemExit(main())
