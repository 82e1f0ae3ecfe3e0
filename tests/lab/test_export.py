"""ONNX export: the fused graph equals the torch ensemble run the reference way, and stays finite."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from slipd.detect.features import FeatureSpec
from slipd.detect.manifest import load_manifest
from sliplab.export import ExportError, export, fold_member, load_reference, main
from sliplab.model import SlipNet, run_sequence

TOL = 1e-5


def _random_member(seed: int, input_size: int = 640, **kw) -> SlipNet:
    """A fresh SlipNet with non-trivial BatchNorm statistics and affine parameters (so folding matters)."""
    torch.manual_seed(seed)
    net = SlipNet(input_size=input_size, **kw)
    g = torch.Generator().manual_seed(seed + 1000)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                n = m.num_features
                m.running_mean.copy_(torch.randn(n, generator=g) * 0.3)
                m.running_var.copy_(torch.rand(n, generator=g) * 1.5 + 0.2)
                m.weight.copy_(torch.rand(n, generator=g) + 0.5)
                m.bias.copy_(torch.randn(n, generator=g) * 0.2)
    return net.eval()


def _walk(k: int, c: int = 16, t: int = 40, seed: int = 0) -> np.ndarray:
    """[k, t*c] windows of a smooth random walk of forces, about 0.01-2 N."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(0.0, 0.01, (k * t, c))
    x = np.cumsum(steps, axis=0) + rng.uniform(-0.5, 0.5, c)
    x = np.clip(x, -2.0, 2.0)
    return x.astype(np.float32).reshape(k, t * c)


def _onnx_sequence(path: Path, windows: np.ndarray, z: int, hidden: int) -> tuple[np.ndarray, np.ndarray]:
    """Run the exported graph one window at a time; ([K] p_slip, [Z, K] p_members)."""
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    h = np.zeros((z, 1, hidden), np.float32)
    ps, pms = [], []
    for w in windows:
        p, pm, h = s.run(None, {"window": w[None], "h": h})
        ps.append(p[0])
        pms.append(pm[:, 0])
    return np.array(ps), np.array(pms).T


def _export(nets: list[SlipNet], out: Path, spec: FeatureSpec | None = None, **kw) -> Path:
    spec = spec or FeatureSpec()
    export([fold_member(n.state_dict()) for n in nets], spec, out, "trained", {"test": True}, **kw)
    return out


@pytest.fixture(scope="module")
def random_ensemble(tmp_path_factory) -> tuple[list[SlipNet], Path]:
    nets = [_random_member(s) for s in range(3)]
    return nets, _export(nets, tmp_path_factory.mktemp("rand") / "rand.onnx")


@pytest.mark.parametrize("scale", [1.0, 10.0])
def test_parity_random_ensemble_with_batchnorm_stats(random_ensemble, scale: float) -> None:
    nets, path = random_ensemble
    windows = _walk(100, seed=int(scale)) * scale
    ref = run_sequence(nets, torch.from_numpy(windows)).numpy()  # [Z, K], the reference way
    p, pm = _onnx_sequence(path, windows, len(nets), 128)
    assert np.abs(pm - ref).max() <= TOL
    assert np.abs(p - ref.mean(axis=0)).max() <= TOL
    assert ref.std() > 0.01  # the sequence actually moves the outputs: parity is not trivially 0 vs 0


def test_parity_reference_checkpoints(reference_ckpt_dir: Path, tmp_path: Path) -> None:
    members, spec, prov = load_reference(reference_ckpt_dir)
    out = tmp_path / "reference.onnx"
    m = export(members, spec, out, "reference-hexapod", prov)
    assert m.members == 5 and m.hidden == 128 and m.pillars == [0, 1, 2, 3, 5, 6, 7, 8]
    assert len(m.provenance["files"]) == 5
    from sliplab.model import load_reference_ensemble

    nets = load_reference_ensemble(reference_ckpt_dir)
    for scale in (1.0, 10.0):
        windows = _walk(100, seed=7) * scale
        ref = run_sequence(nets, torch.from_numpy(windows)).numpy()
        p, pm = _onnx_sequence(out, windows, 5, 128)
        assert np.abs(pm - ref).max() <= TOL, scale
        assert np.abs(p - ref.mean(axis=0)).max() <= TOL, scale
    p, pm = _onnx_sequence(out, _walk(30, seed=8) * 100.0, 5, 128)
    assert np.isfinite(p).all() and np.isfinite(pm).all()


def test_huge_inputs_and_overflowing_logits_stay_finite(tmp_path: Path) -> None:
    net = _random_member(5)
    with torch.no_grad():
        # Logits of order 1e3: exp() overflows float32 in a naive softmax.
        net.predictor[6].weight.mul_(400.0)
        net.predictor[6].bias.copy_(torch.tensor([-300.0, 900.0]))
    path = _export([net, _random_member(6)], tmp_path / "big.onnx")
    windows = _walk(20, seed=2) * 100.0
    ref = run_sequence([net], torch.from_numpy(windows)).numpy()[0]
    p, pm = _onnx_sequence(path, windows, 2, 128)
    assert np.isfinite(p).all() and np.isfinite(pm).all()
    assert ((pm >= 0) & (pm <= 1)).all()
    assert np.abs(pm[0] - ref).max() <= TOL  # torch's softmax is stable too: both saturate the same way
    # Absurd but finite inputs: the graph's input clip keeps every intermediate finite.
    absurd = np.full((3, 640), 3e38, np.float32)
    absurd[1] *= -1
    p, pm = _onnx_sequence(path, absurd, 2, 128)
    assert np.isfinite(p).all() and np.isfinite(pm).all()


def test_fp16_and_int8_variants_load_and_stay_close(random_ensemble, tmp_path: Path) -> None:
    nets, fp32 = random_ensemble
    windows = _walk(30, seed=3)
    p32, _ = _onnx_sequence(fp32, windows, 3, 128)
    for flag in ("fp16", "int8"):
        out = _export(nets, tmp_path / f"m_{flag}.onnx", precision=flag)
        m = load_manifest(out.with_suffix(".json"))
        assert m.precision == flag
        p, _ = _onnx_sequence(out, windows, 3, 128)
        assert np.isfinite(p).all()
        assert np.abs(p - p32).max() < 0.05, flag  # an approximation, not a different model
        assert out.stat().st_size < 0.6 * fp32.stat().st_size


def _save_run(folder: Path, nets: list[SlipNet], specs: list[FeatureSpec]) -> None:
    folder.mkdir()
    for k, (net, spec) in enumerate(zip(nets, specs)):
        torch.save(
            {"state_dict": net.state_dict(), "config": net.config(), "feature_spec": spec.to_dict(),
             "provenance": {"generator_version": "0.1", "scene_set": "offline", "seed": 100 + k}},
            folder / f"member_{k}.pt",
        )


def test_cli_run_directory(tmp_path: Path) -> None:
    spec = FeatureSpec(window=10)  # another layout: 160 inputs
    nets = [_random_member(s, input_size=spec.input_size, hidden=16, enc=32, pred=(16, 8)) for s in (1, 2)]
    _save_run(tmp_path / "run", nets, [spec, spec])
    out = tmp_path / "models" / "slip_ensemble.onnx"
    assert main(["--run", str(tmp_path / "run"), "--out", str(out)]) == 0
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["source"] == "trained" and data["window"] == 10 and data["members"] == 2 and data["hidden"] == 16
    assert data["provenance"]["generator_version"] == "0.1" and data["provenance"]["scene_set"] == "offline"
    assert [m["seed"] for m in data["provenance"]["members"]] == [100, 101]
    windows = _walk(12, t=10, seed=4)
    ref = run_sequence(nets, torch.from_numpy(windows)).numpy()
    p, _ = _onnx_sequence(out, windows, 2, 16)
    assert np.abs(p - ref.mean(axis=0)).max() <= TOL


def test_run_directory_with_mixed_feature_specs_is_refused(tmp_path: Path) -> None:
    spec = FeatureSpec(window=10)
    nets = [_random_member(s, input_size=160, hidden=16, enc=32, pred=(16, 8)) for s in (1, 2)]
    _save_run(tmp_path / "run", nets, [spec, spec.with_(median=11)])
    with pytest.raises(ExportError, match="different feature specs"):
        from sliplab.export import load_run

        load_run(tmp_path / "run")
    assert main(["--run", str(tmp_path / "empty"), "--out", str(tmp_path / "x.onnx")]) == 1


def test_pillar_head_is_exported_only_when_asked_and_feeds_the_contact_state(tmp_path: Path) -> None:
    """``--pillar-head``: the members' per-pillar head becomes output ``p_pillars`` (member mean of the sigmoids,
    matching torch), the manifest declares it, ``Ensemble.step`` returns it and the detector's contact state takes
    it as its slip map (source "model"); without the flag the graph is the method's (three outputs)."""
    from slipd.detect.build import build_detector
    from slipd.detect.ensemble import Ensemble

    spec = FeatureSpec(pillars=tuple(range(9)), channels=("util",), median=5, stride=10)
    nets = [_random_member(s, input_size=spec.input_size, hidden=16, enc=32, pred=(16, 8), aux=9) for s in (1, 2)]
    _save_run(tmp_path / "run", nets, [spec, spec])
    plain, head = tmp_path / "plain.onnx", tmp_path / "head.onnx"
    assert main(["--run", str(tmp_path / "run"), "--out", str(plain), "--stride", "10"]) == 0
    assert main(["--run", str(tmp_path / "run"), "--out", str(head), "--stride", "10", "--pillar-head"]) == 0
    assert not Ensemble.load(plain.with_suffix(".json")).manifest.has_pillar_output
    ens = Ensemble.load(head.with_suffix(".json"))
    assert [t.name for t in ens.manifest.outputs] == ["p_slip", "p_members", "h_next", "p_pillars"]
    windows = np.abs(_walk(6, c=9, seed=5))
    with torch.no_grad():
        h = [torch.zeros(1, 16) for _ in nets]
        for w in windows:
            r = ens.step(w)
            ref = []
            for k, net in enumerate(nets):
                _, h[k] = net(torch.from_numpy(w[None]), h[k])
                ref.append(torch.sigmoid(net.aux_head(h[k]))[0].numpy())
            assert r.p_pillars is not None and r.p_pillars.shape == (9,)
            assert np.abs(r.p_pillars - np.mean(ref, axis=0)).max() <= TOL
    ens.reset()
    f = np.zeros((400, 9, 3), np.float32)
    f[:, :, 2] = 2.0
    f[:, :, 0] = np.linspace(0, 0.5, 400)[:, None]
    dets = [d for _, d in build_detector(None, ens, offset=np.zeros((9, 3), np.float32)).push_many(f, np.arange(400))]
    states = [d.contact for d in dets if d.valid and d.p_slip > 0]
    assert states and all(s is not None and s.source == "model" for s in states)
