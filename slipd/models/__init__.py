"""The models shipped inside the package, found by name.

A config names a packaged model by its bare name (``model.manifest: slip_ensemble_int8``) or any
model by a path (``/opt/models/mine.json``, ``../models/x.json``). A bare name is a manifest stem
in this folder; anything with a path separator or a ``.json`` suffix is a path.
"""

from __future__ import annotations

import re
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
"""Where the packaged manifests, ONNX graphs and tuned heuristic parameters live."""

DEFAULT_MODEL = "slip_ensemble_int8"
"""The daemon's default: the int8 variant of the shipped ensemble."""

SAMPLE_RECORDING = PACKAGE_DIR / "sample_slip.npz"
"""A 1.5 s simulated slip trial (hexapod translation, seed 0) that ships with the package so that
``slipd replay`` can be tried, and tested, on an installed daemon; written by ``make sample``."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def is_name(text: str) -> bool:
    """Whether ``text`` names a packaged model rather than a path."""
    return bool(_NAME.match(text)) and not text.endswith(".json")


def packaged(name: str) -> Path:
    """The manifest of the packaged model ``name``; ``FileNotFoundError`` listing the known names."""
    path = PACKAGE_DIR / f"{name}.json"
    if not path.is_file() or name not in names():
        known = ", ".join(names()) or "none"
        raise FileNotFoundError(f"no packaged model named {name!r} (packaged: {known})")
    return path


def names() -> list[str]:
    """The packaged models: every manifest here that has its ONNX graph beside it."""
    return sorted(p.stem for p in PACKAGE_DIR.glob("*.json") if p.with_suffix(".onnx").is_file())


def packaged_file(filename: str) -> Path:
    """Another packaged file by name (``baselines_transfer.json``)."""
    return PACKAGE_DIR / filename
