"""Choose the alarm threshold of a model on TRAIN recordings only (never the test split).

A launcher: the code lives in ``slipd.lab.tune`` (the offline lab; ``pip install -e '.[train]'``).
"""

from slipd.lab.tune import main

if __name__ == "__main__":
    raise SystemExit(main())
