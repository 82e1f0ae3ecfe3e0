"""Per scored slip: each detector's first alarm against the offline window, and what the label rests on.

A launcher: the code lives in ``sliplab.slip_timing`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.slip_timing import main

if __name__ == "__main__":
    raise SystemExit(main())
