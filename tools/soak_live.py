"""Soak the live daemon: 1 kHz frames for N seconds against the emulated devices; nothing may be lost.

A launcher: the code lives in ``sliplab.soak_live`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.soak_live import main

if __name__ == "__main__":
    raise SystemExit(main())
