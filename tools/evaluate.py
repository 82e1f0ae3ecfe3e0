"""Evaluate a slip detector (the ONNX ensemble or a heuristic baseline) with the method's metrics.

A launcher: the code lives in ``sliplab.evaluate`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.evaluate import main

if __name__ == "__main__":
    raise SystemExit(main())
