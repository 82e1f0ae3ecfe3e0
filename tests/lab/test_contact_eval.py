"""``tools/evaluate.py --contact``: the contact state (per-pillar slip, friction) against the simulator's truth,
from the feature estimate and from a model's detector."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import make_scene

from slipd.models import DEFAULT_MODEL, packaged
from sliplab.evaluate import main


def test_contact_scores_the_feature_estimate_and_a_models_detector(tmp_path: Path) -> None:
    folder = tmp_path / "robust_test"
    folder.mkdir()
    for seed in range(2):
        make_scene(seed=seed, speed=3.0).save(folder / f"{seed:05d}_slip.npz")
    figures = []
    for extra in ([], ["--model", str(packaged(DEFAULT_MODEL))]):
        out = tmp_path / f"contact{len(extra)}.json"
        assert main(["--contact", "--sets", "robust", "--data-root", str(tmp_path), "--workers", "1",
                     "--json", str(out), *extra]) == 0
        figures.append(json.loads(out.read_text())["robust"]["pillar"])
    for f in figures:
        assert 0.0 < f["f1"] <= 1.0 and len(f["f1_per_pillar"]) == 9
