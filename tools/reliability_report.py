"""Write reports/reliability.md: every fault slipd meets, what it does, what counts it, which test proves it.

A launcher: the code lives in ``sliplab.reliability`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.reliability import main

if __name__ == "__main__":
    raise SystemExit(main())
