"""Where the offline tools find the checkout's data, reports and scene files.

The lab runs from a source checkout (``pip install -e '.[train]'``); its defaults name folders of that
checkout (``out/`` for generated data sets and runs, ``reports/``, ``config/``). Packaged models are found
through :mod:`slipd.models`, never through this path.
"""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout holding this package (``sliplab/paths.py`` -> the repository root)."""
