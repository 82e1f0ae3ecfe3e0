"""Shared test fixtures: repository paths and the optional shared reference material."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REFERENCE_CKPT = SHARED / "reference" / "checkpoints" / "hexapod"


@pytest.fixture
def reference_ckpt_dir() -> Path:
    """The authors' checkpoints, or skip where ../shared is absent."""
    if not (REFERENCE_CKPT / "ckpt_final_model_0.pth").exists():
        pytest.skip("reference checkpoints not present (../shared/reference/checkpoints/hexapod)")
    return REFERENCE_CKPT


@pytest.fixture(scope="session")
def tiny_model_json(tmp_path_factory) -> Path:
    """A small randomly initialised ensemble (default feature layout, 3 members, hidden 16) exported to ONNX.

    Random weights with non-trivial BatchNorm statistics: enough to exercise the runtime paths quickly.
    """
    torch = pytest.importorskip("torch")
    from slipd.detect.features import FeatureSpec
    from slipd.lab.export import export, fold_member
    from slipd.lab.model import SlipNet

    spec = FeatureSpec()
    nets = []
    for seed in range(3):
        torch.manual_seed(seed)
        net = SlipNet(input_size=spec.input_size, hidden=16, enc=32, pred=(16, 8))
        with torch.no_grad():
            for m in net.modules():
                if isinstance(m, torch.nn.BatchNorm1d):
                    m.running_var.uniform_(0.5, 1.5)
                    m.running_mean.normal_(0, 0.2)
        nets.append(net.eval())
    out = tmp_path_factory.mktemp("tiny_model") / "tiny.onnx"
    export([fold_member(n.state_dict()) for n in nets], spec, out, "trained", {"note": "test fixture"})
    return out.with_suffix(".json")


@pytest.fixture(scope="session")
def detect_model_json(tmp_path_factory) -> Path:
    """A model that really detects slip: the shipped one, else the authors' checkpoints converted (or skip)."""
    shipped = ROOT / "slipd" / "models" / "slip_ensemble.json"
    if shipped.exists():
        return shipped
    if not (REFERENCE_CKPT / "ckpt_final_model_0.pth").exists():
        pytest.skip("no shipped model and no reference checkpoints")
    pytest.importorskip("torch")
    from slipd.lab.export import export, load_reference

    members, spec, prov = load_reference(REFERENCE_CKPT)
    out = tmp_path_factory.mktemp("reference") / "reference.onnx"
    export(members, spec, out, "reference-hexapod", prov)
    return out.with_suffix(".json")
