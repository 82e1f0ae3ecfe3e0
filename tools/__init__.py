"""Offline tools (simulated data sets, training, export, evaluation, benchmarks).

Scripts here run as ``python tools/NAME.py``; each puts the repository root on ``sys.path`` first so
``import slipd`` and ``import tools.x`` work without installing anything extra.
"""
