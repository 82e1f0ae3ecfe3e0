"""The offline lab: training, export, evaluation and the reports' tools. Needs the ``train`` extra."""

import importlib.util

# The plain wheel carries this package (one wheel for every extra); without torch it stops here with the fix.
if importlib.util.find_spec("torch") is None:
    raise ImportError("sliplab needs the train extra: pip install 'slipd[train]'")
