"""Soak test of the recurrent state: many consecutive windows on steady hold, noise only and a periodic load.

A launcher: the code lives in ``slipd.lab.soak`` (the offline lab; ``pip install -e '.[train]'``).
"""

from slipd.lab.soak import main

if __name__ == "__main__":
    raise SystemExit(main())
