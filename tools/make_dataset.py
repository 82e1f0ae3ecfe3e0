"""Write a simulated data set: ``python tools/make_dataset.py --set offline --split test --out DIR``.

A launcher: the code lives in ``sliplab.make_dataset`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.make_dataset import main

if __name__ == "__main__":
    raise SystemExit(main())
