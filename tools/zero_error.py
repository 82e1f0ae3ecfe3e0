"""How far the daemon's decisions move when the sensor's zero is a little off (a bias's residual, a drift).

A launcher: the code lives in ``sliplab.zero_error`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.zero_error import main

if __name__ == "__main__":
    raise SystemExit(main())
