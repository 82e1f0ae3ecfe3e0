"""Train the method's GRU ensemble (Z members, bootstrap subsets, the method's augmentations).

A launcher: the code lives in ``sliplab.train`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.train import main

if __name__ == "__main__":
    raise SystemExit(main())
