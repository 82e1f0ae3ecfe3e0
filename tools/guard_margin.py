"""The limit guard's margin: the highest contact risk held where nothing slips, and the slips the guard raises.

A launcher: the code lives in ``sliplab.guard_margin`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.guard_margin import main

if __name__ == "__main__":
    raise SystemExit(main())
