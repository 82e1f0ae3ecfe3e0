"""Fuzz ``slipd.config`` with generated YAML documents: nothing but ``ConfigError`` may escape.

A launcher: the code lives in ``sliplab.fuzz_config`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.fuzz_config import main

if __name__ == "__main__":
    raise SystemExit(main())
