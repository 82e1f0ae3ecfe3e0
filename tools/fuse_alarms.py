"""Two detectors together: a model's alarms fused with the reference-pillar rule's, scored as robustness.py scores.

A launcher: the code lives in ``sliplab.fuse_alarms`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.fuse_alarms import main

if __name__ == "__main__":
    raise SystemExit(main())
