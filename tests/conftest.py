"""Shared test fixtures: repository paths and the optional shared reference material."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REFERENCE_CKPT = SHARED / "reference" / "checkpoints" / "hexapod"

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # so tests can import tools.*


@pytest.fixture
def reference_ckpt_dir() -> Path:
    """The authors' checkpoints, or skip where ../shared is absent."""
    if not (REFERENCE_CKPT / "ckpt_final_model_0.pth").exists():
        pytest.skip("reference checkpoints not present (../shared/reference/checkpoints/hexapod)")
    return REFERENCE_CKPT
