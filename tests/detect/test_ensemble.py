"""Runtime ensemble and the manifest gate: per-stream state, non-finite policy, every refusal names file/field."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from slipd.detect.ensemble import Ensemble, NonFiniteInput, NonFiniteOutput
from slipd.detect.features import FeatureSpec
from slipd.detect.manifest import ModelError, load_manifest, sha256_file
from sliplab.export import export, fold_member
from sliplab.model import SlipNet, run_sequence

SPEC = FeatureSpec(pillars=(0, 1, 2), window=8)  # 48 inputs: a small, fast model
Z = 3


def _net(seed: int, input_size: int = SPEC.input_size) -> SlipNet:
    torch.manual_seed(seed)
    net = SlipNet(input_size=input_size, hidden=16, enc=32, pred=(16, 8))
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_var.uniform_(0.5, 1.5)
                m.running_mean.normal_(0, 0.2)
    return net.eval()


def _export(folder: Path, name: str, nets: list[SlipNet], spec: FeatureSpec = SPEC) -> Path:
    export([fold_member(n.state_dict()) for n in nets], spec, folder / f"{name}.onnx", "trained", {})
    return folder / f"{name}.json"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> tuple[Path, list[SlipNet]]:
    nets = [_net(s) for s in range(Z)]
    return _export(tmp_path_factory.mktemp("ens"), "small", nets), nets


@pytest.fixture
def model_copy(model, tmp_path: Path) -> Path:
    """A private copy of the model files, free to corrupt."""
    src = model[0]
    for suffix in (".onnx", ".json"):
        shutil.copy(src.with_suffix(suffix), tmp_path / f"m{suffix}")
    _edit(tmp_path / "m.json", onnx_file="m.onnx")
    return tmp_path / "m.json"


def _seq(k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.normal(0, 0.05, (k, SPEC.input_size)), axis=0).astype(np.float32)


def test_step_matches_torch_and_keeps_state_per_stream(model) -> None:
    path, nets = model
    ens = Ensemble.load(path)
    assert ens.feature_spec == SPEC and ens.members == Z and ens.threshold == 0.5
    a, b = _seq(12, 1), _seq(12, 2)
    ref_a = run_sequence(nets, torch.from_numpy(a)).numpy().mean(axis=0)
    ref_b = run_sequence(nets, torch.from_numpy(b)).numpy().mean(axis=0)
    got_a, got_b = [], []
    for k in range(12):  # interleaved: each stream must carry only its own state
        got_a.append(ens.step(a[k], stream=0).p_slip)
        got_b.append(ens.step(b[k], stream=7).p_slip)
    assert np.abs(np.array(got_a) - ref_a).max() <= 1e-5
    assert np.abs(np.array(got_b) - ref_b).max() <= 1e-5
    assert ens.streams == [0, 7]
    r = ens.step(a[0], stream=7)
    assert r.valid and isinstance(r.p_slip, float) and r.p_members.shape == (Z,)
    assert r.p_slip == pytest.approx(float(r.p_members.mean()), abs=1e-6)

    ens.reset(7)  # only stream 7 restarts
    assert ens.step(b[0], stream=7).p_slip == pytest.approx(got_b[0], abs=1e-6)
    assert ens.step(a[0], stream=0).p_slip != pytest.approx(got_a[0], abs=1e-4)  # stream 0 kept its history
    ens.reset()
    assert ens.streams == []
    assert ens.step(a[0], stream=0).p_slip == pytest.approx(got_a[0], abs=1e-6)


def test_batched_stream_and_step_batch(model) -> None:
    path, nets = model
    ens = Ensemble.load(path)
    seqs = [_seq(10, 3), _seq(4, 4), _seq(7, 5)]
    refs = [run_sequence(nets, torch.from_numpy(s)).numpy() for s in seqs]
    for res, ref in zip(ens.step_batch(seqs), refs):
        assert res.p_slip.shape == (len(ref[0]),) and res.p_members.shape == ref.shape
        assert np.abs(res.p_members - ref).max() <= 1e-5
    # One stream holding two parallel sequences ([B, T*C] windows).
    two = np.stack([seqs[0][:4], seqs[1]], axis=1)  # [K, 2, D]
    out = np.array([ens.step(w, stream=3).p_slip for w in two])  # [K, 2]
    assert np.abs(out[:, 0] - refs[0][:, :4].mean(axis=0)).max() <= 1e-5
    assert np.abs(out[:, 1] - refs[1].mean(axis=0)).max() <= 1e-5
    with pytest.raises(ValueError, match="holds 2 sequences"):
        ens.step(seqs[0][0], stream=3)
    with pytest.raises(ValueError, match="window must be"):
        ens.step(np.zeros(5, np.float32))
    bad = [seqs[0].copy()]
    bad[0][2, 3] = np.inf
    with pytest.raises(NonFiniteInput, match="sequence 0, window 2"):
        ens.step_batch(bad)


def test_nonfinite_window_is_refused_and_state_untouched(model) -> None:
    path, _ = model
    ens = Ensemble.load(path)
    s = _seq(5, 6)
    clean = [ens.step(w, stream=1).p_slip for w in s]
    ens.reset()
    for k, w in enumerate(s):
        if k == 2:
            before = ens.hidden_state(1)
            for poison in (np.nan, np.inf, -np.inf):
                bad = w.copy()
                bad[k] = poison
                r = ens.step(bad, stream=1)
                assert not r.valid and r.status == "nonfinite_input" and np.isnan(r.p_slip)
                assert np.array_equal(ens.hidden_state(1), before)
            r = ens.step(np.stack([w, bad]), stream=9)  # one bad row refuses the whole batch
            assert not r.valid and r.p_slip.shape == (2,) and r.p_members.shape == (Z, 2)
            assert ens.refused_inputs == 4 and 9 not in ens.streams
        assert ens.step(w, stream=1).p_slip == pytest.approx(clean[k], abs=1e-7)


def test_nonfinite_output_resets_the_stream(tmp_path: Path, model) -> None:
    nets = [_net(s) for s in range(2)]
    with torch.no_grad():
        nets[1].predictor[3].weight[0, 0] = float("nan")  # a broken model: finite state, NaN output
    ens = Ensemble.load(_export(tmp_path, "nan", nets))
    good = Ensemble.load(_export(tmp_path, "good", [_net(0), _net(1)]))
    good.step(_seq(1, 8)[0], stream=0)
    assert np.abs(good.hidden_state(0)).max() > 0  # a real step does move the state
    s = _seq(3, 8)
    ens.step(s[0], stream=4)  # NaN in the predictor only: the state stays finite but the output is NaN
    r = ens.step(s[1], stream=4)
    assert not r.valid and r.status == "nonfinite_output" and ens.nonfinite_outputs == 2
    assert np.array_equal(ens.hidden_state(4), np.zeros((2, 1, 16), np.float32))  # reset, not the NaN step's h
    with pytest.raises(NonFiniteOutput, match="window 0"):
        ens.step_batch([s])


# ---------------------------------------------------------------- the manifest gate


def _edit(path: Path, **changes) -> None:
    data = json.loads(path.read_text())
    data.update(changes)
    path.write_text(json.dumps(data))


def _raises(path: Path, field: str, file: Path | None = None, **kw) -> ModelError:
    with pytest.raises(ModelError) as info:
        load_manifest(path, **kw)
    err = info.value
    assert err.field == field, str(err)
    assert err.file == str(file or path)
    assert err.reason and str(file or path) in str(err) and field in str(err)
    return err


def test_manifest_roundtrip(model) -> None:
    m = load_manifest(model[0], expected_spec=SPEC)
    assert m.inputs[0].shape == ["B", SPEC.input_size] and m.outputs[2].shape == [Z, "B", 16]
    assert m.units == "N" and m.stride == SPEC.window and m.metrics == {}


def test_wrong_hash(model_copy: Path) -> None:
    _edit(model_copy, sha256="0" * 64)
    _raises(model_copy, "sha256", model_copy.with_suffix(".onnx"))


def test_truncated_onnx(model_copy: Path) -> None:
    onnx_path = model_copy.with_suffix(".onnx")
    onnx_path.write_bytes(onnx_path.read_bytes()[:5000])
    _raises(model_copy, "sha256", onnx_path)
    _edit(model_copy, sha256=sha256_file(onnx_path))  # even with a matching hash, the graph is unreadable
    err = _raises(model_copy, "onnx", onnx_path)
    assert "cannot load" in err.reason


def test_missing_files(model_copy: Path, tmp_path: Path) -> None:
    _raises(tmp_path / "absent.json", "manifest")
    model_copy.with_suffix(".onnx").unlink()
    _raises(model_copy, "onnx_file", model_copy.with_suffix(".onnx"))


def test_wrong_shapes_and_unknown_keys(model_copy: Path) -> None:
    original = model_copy.read_text()
    data = json.loads(original)
    data["inputs"][1]["shape"] = [Z, "B", 32]
    model_copy.write_text(json.dumps(data))
    _raises(model_copy, "inputs.h.shape")
    model_copy.write_text(original)
    _edit(model_copy, surprise=1)
    _raises(model_copy, "surprise")
    model_copy.write_text(original)
    _edit(model_copy, window=40)
    _raises(model_copy, "window")


def test_manifest_for_another_model_or_feature_layout(model_copy: Path, tmp_path: Path) -> None:
    # The configured pipeline produces another layout: refused before the model is touched.
    _raises(model_copy, "feature_spec", expected_spec=SPEC.with_(pillars=[0, 1, 3]))
    _raises(model_copy, "feature_spec", expected_spec=FeatureSpec())
    # A consistent manifest whose graph is another model (5 members): the graph check catches it.
    (tmp_path / "o").mkdir()
    other = _export(tmp_path / "o", "other", [_net(s) for s in range(5)])
    _edit(model_copy, onnx_file=str(Path("o") / "other.onnx"), sha256=sha256_file(other.with_suffix(".onnx")))
    _raises(model_copy, "inputs.h", model_copy.parent / "o" / "other.onnx")
    # A manifest claiming a different feature layout than the graph was built for (window 10, not 8).
    spec10 = SPEC.with_(window=10)
    _edit(model_copy, onnx_file="m.onnx", sha256=sha256_file(model_copy.with_suffix(".onnx")),
          feature_spec=spec10.to_dict(), window=10, stride=10,
          inputs=[{"name": "window", "shape": ["B", spec10.input_size]}, {"name": "h", "shape": [Z, "B", 16]}])
    _raises(model_copy, "inputs.window", model_copy.with_suffix(".onnx"))
    with pytest.raises(ModelError):
        Ensemble.load(model_copy)


def test_update_metrics_keeps_the_model_valid(model_copy: Path) -> None:
    from slipd.detect.manifest import update_metrics

    update_metrics(model_copy, {"offline_success": 0.95})
    update_metrics(model_copy, {"step_median_us": 830.0})
    m = load_manifest(model_copy)
    assert m.metrics == {"offline_success": 0.95, "step_median_us": 830.0}
    with pytest.raises(TypeError):
        update_metrics(model_copy, {"bad": object()})
    assert load_manifest(model_copy).metrics == m.metrics
