"""How real does the simulator look to a model trained on real data?

A launcher: the code lives in ``sliplab.realism`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.realism import main

if __name__ == "__main__":
    raise SystemExit(main())
