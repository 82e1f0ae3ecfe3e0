"""Choose the alarm threshold of a model on TRAIN recordings only (never the test split).

A launcher: the code lives in ``sliplab.tune`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.tune import main

if __name__ == "__main__":
    raise SystemExit(main())
