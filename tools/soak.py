"""Soak test of the recurrent state: many consecutive windows on steady hold, noise only and a periodic load.

A launcher: the code lives in ``sliplab.soak`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.soak import main

if __name__ == "__main__":
    raise SystemExit(main())
