"""Export a SlipNet ensemble as ONE fused ONNX graph plus its manifest.

    python tools/export_onnx.py --run DIR --out slipd/models/slip_ensemble.onnx
    python tools/export_onnx.py --reference ../shared/reference/checkpoints/hexapod --out out/reference.onnx

The graph is built directly with ``onnx.helper`` from numpy weights (no torch tracing), so its shape
is exactly what ``design.md`` section 3 asks for:

    inputs   window [B, T*C] float32, h [Z, B, H] float32
    outputs  p_slip [B] (member mean of P(slip)), p_members [Z, B], h_next [Z, B, H]

Every BatchNorm (eval mode) is folded into the Linear before it, the final BatchNorm1d(2) included.
The first layer of all members is one MatMul with the members' weights side by side ([D, Z*1024]):
at B = 1 the step is a matrix-vector product, bound by reading the weights once, and one wide
product reads them in a single pass. Later layers are batched MatMuls with stacked [Z, in, out]
weights. The GRU cell is written out (torch's gate order r, z, n;
n = tanh(W_in x + b_in + r * (W_hn h + b_hn)); h' = n + z * (h - n), which is (1 - z) n + z h).

Softmax over two classes: P(slip) = sigmoid(z1 - z0) exactly, and the last layer is folded further to
one output column (w1 - w0, b1 - b0), so no exp() can overflow. Inputs are clipped (window to
+-``INPUT_CLIP`` N, h to [-1, 1], the range a GRU state can reach) so that no finite input can make
an intermediate overflow to inf and an inf - inf produce a NaN; the clips are identities on real data
(features.py already clips forces to twice the sensor range).

``--fp16`` stores weights and computes in float16 (I/O stays float32; half the file, but onnxruntime's
x86 CPU kernels gain no speed from it: measured in tools/bench_inference.py); ``--int8`` applies
onnxruntime's dynamic quantisation to the fp32 graph (a quarter of the bytes, about 5x faster at B = 1
here, p_slip within about 1e-2 of fp32). Both are for the accuracy/speed trade-off study.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from slipd.detect.features import FeatureSpec
from slipd.detect.manifest import (
    BATCH_DIM,
    Manifest,
    atomic_write_bytes,
    io_infos,
    load_manifest,
    manifest_path_for,
    sha256_file,
    write_manifest,
)

OPSET = 17
BN_EPS = 1e-5  # torch BatchNorm1d default; SlipNet uses it everywhere
INPUT_CLIP = 1000.0
"""Bound (N) on window values inside the graph: far above the 8 N / 30 N the feature pipeline lets through."""
REFERENCE_MAPPING = (
    "authors' P1..P8 (their P0 = centre, excluded) = SDK P0, P1, P2, P3, P5, P6, P7, P8 in raster order; "
    "measured, not published: rotational slip is detected only with this order"
)
TRAINED_MAPPING = "SDK order (centre P4); features pillar-major in the order of `pillars`"


class ExportError(ValueError):
    """Checkpoints that cannot be exported; the message names the file and the reason."""


@dataclass
class FoldedMember:
    """One member with BatchNorm folded: ``layers`` are (W [in, out], b [out]) in float64, plus the GRU."""

    enc: list[tuple[np.ndarray, np.ndarray]]  # projector: 2 layers, each followed by ReLU
    w_ih: np.ndarray  # [3H, E] torch layout, gates r, z, n
    w_hh: np.ndarray  # [3H, H]
    b_ih: np.ndarray  # [3H]
    b_hh: np.ndarray  # [3H]
    pred: list[tuple[np.ndarray, np.ndarray]]  # predictor: 2 ReLU layers, then the 2-class output layer
    aux: tuple[np.ndarray, np.ndarray] | None = None  # per-pillar slip head on the GRU state (W [H, P], b [P])

    @property
    def input_size(self) -> int:
        return self.enc[0][0].shape[0]

    @property
    def hidden(self) -> int:
        return self.w_hh.shape[1]


def _np(state: dict[str, Any], key: str, where: str) -> np.ndarray:
    if key not in state:
        raise ExportError(f"{where}: state dict lacks {key!r}")
    v = state[key]
    v = v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)
    return v.astype(np.float64)


def fold_linear_bn(state: dict[str, Any], lin: str, bn: str, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Linear ``lin`` followed by eval-mode BatchNorm ``bn`` -> one affine map (W [in, out], b [out])."""
    w, b = _np(state, f"{lin}.weight", where), _np(state, f"{lin}.bias", where)
    gamma, beta = _np(state, f"{bn}.weight", where), _np(state, f"{bn}.bias", where)
    mean, var = _np(state, f"{bn}.running_mean", where), _np(state, f"{bn}.running_var", where)
    scale = gamma / np.sqrt(var + BN_EPS)
    return (w * scale[:, None]).T, (b - mean) * scale + beta


def fold_member(state: dict[str, Any], where: str = "member") -> FoldedMember:
    """Fold a SlipNet state dict (keys as in tools/slipnet.py and the authors' checkpoints)."""
    enc = [fold_linear_bn(state, "projector.0", "projector.1", where),
           fold_linear_bn(state, "projector.3", "projector.4", where)]
    pred = [fold_linear_bn(state, f"predictor.{i}", f"predictor.{i + 1}", where) for i in (0, 3, 6)]
    if pred[-1][0].shape[1] != 2:
        raise ExportError(f"{where}: the output layer has {pred[-1][0].shape[1]} classes, expected 2")
    m = FoldedMember(
        enc=enc,
        w_ih=_np(state, "rnn.weight_ih", where), w_hh=_np(state, "rnn.weight_hh", where),
        b_ih=_np(state, "rnn.bias_ih", where), b_hh=_np(state, "rnn.bias_hh", where),
        pred=pred,
        aux=(_np(state, "aux_head.weight", where).T, _np(state, "aux_head.bias", where))
        if "aux_head.weight" in state else None,
    )
    h = m.hidden
    if m.w_ih.shape != (3 * h, enc[1][0].shape[1]) or m.w_hh.shape != (3 * h, h):
        raise ExportError(f"{where}: GRU weights {m.w_ih.shape}, {m.w_hh.shape} do not fit hidden size {h}")
    return m


def _stack(arrs: list[np.ndarray], where: str) -> np.ndarray:
    shapes = {a.shape for a in arrs}
    if len(shapes) != 1:
        raise ExportError(f"{where}: members differ in shape {sorted(shapes)}")
    return np.stack(arrs)


class _Graph:
    """Small helper to add nodes and initialisers with unique names."""

    def __init__(self, dtype: np.dtype) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.dtype = dtype
        self._n = 0

    def const(self, name: str, value: np.ndarray, keep_dtype: bool = False) -> str:
        arr = np.asarray(value) if keep_dtype else np.asarray(value, dtype=self.dtype)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(arr), name))
        return name

    def op(self, op_type: str, inputs: list[str], out: str | None = None, **attrs: Any) -> str:
        self._n += 1
        out = out or f"{op_type.lower()}_{self._n}"
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=f"n{self._n}_{op_type}", **attrs))
        return out

    def split3(self, x: str, size: int, prefix: str) -> list[str]:
        outs = [f"{prefix}_{g}" for g in "rzn"]
        sizes = self.const(f"{prefix}_split", np.array([size] * 3, np.int64), keep_dtype=True)
        self._n += 1
        self.nodes.append(helper.make_node("Split", [x, sizes], outs, name=f"n{self._n}_Split", axis=-1))
        return outs


def pillar_head_size(members: list[FoldedMember]) -> int:
    """Pillars of the per-pillar head every member carries (0: none, or not all members have one)."""
    sizes = {0 if m.aux is None else m.aux[0].shape[1] for m in members}
    return sizes.pop() if len(sizes) == 1 else 0


def build_graph(members: list[FoldedMember], precision: str = "fp32", input_clip: float = INPUT_CLIP
                ) -> onnx.ModelProto:
    """The fused ensemble graph (fp32 or fp16 compute; I/O always float32); windows clipped to +-input_clip."""
    if not members:
        raise ExportError("no members to export")
    if precision not in ("fp32", "fp16"):
        raise ExportError(f"build_graph precision must be fp32 or fp16, got {precision!r}")
    dt = np.float32 if precision == "fp32" else np.float16
    onnx_dt = TensorProto.FLOAT if precision == "fp32" else TensorProto.FLOAT16
    z, d, hid = len(members), members[0].input_size, members[0].hidden
    e1 = members[0].enc[0][0].shape[1]
    g = _Graph(np.dtype(dt))

    def to_compute(name: str) -> str:
        return name if precision == "fp32" else g.op("Cast", [name], to=onnx_dt)

    def to_float(name: str, out: str) -> str:
        return g.op("Identity" if precision == "fp32" else "Cast", [name], out, **(
            {} if precision == "fp32" else {"to": TensorProto.FLOAT}))

    # Clip in float32 before any cast so a huge finite value cannot become fp16 inf.
    x = g.op("Clip", ["window", g.const("clip_lo", np.float32(-input_clip), True),
                      g.const("clip_hi", np.float32(input_clip), True)])
    x = to_compute(x)
    h = g.op("Clip", ["h", g.const("h_lo", np.float32(-1.0), True), g.const("h_hi", np.float32(1.0), True)])
    h = to_compute(h)

    # Layer 1, all members in one MatMul: [B, D] @ [D, Z*E] -> [B, Z, E] -> [Z, B, E].
    w1 = _stack([m.enc[0][0] for m in members], "enc0").transpose(1, 0, 2).reshape(d, z * e1)  # col = k*E + e
    b1 = np.concatenate([m.enc[0][1] for m in members])
    y = g.op("Add", [g.op("MatMul", [x, g.const("enc0_w", w1)]), g.const("enc0_b", b1)])
    y = g.op("Relu", [y])
    y = g.op("Reshape", [y, g.const("enc0_shape", np.array([-1, z, e1], np.int64), True)])
    y = g.op("Transpose", [y], perm=[1, 0, 2])

    def dense(inp: str, layers: list[tuple[np.ndarray, np.ndarray]], name: str, relu: bool = True) -> str:
        w = _stack([lw for lw, _ in layers], name)  # [Z, in, out]
        b = _stack([lb for _, lb in layers], name)[:, None, :]  # [Z, 1, out]
        out = g.op("Add", [g.op("MatMul", [inp, g.const(f"{name}_w", w)]), g.const(f"{name}_b", b)])
        return g.op("Relu", [out]) if relu else out

    y = dense(y, [m.enc[1] for m in members], "enc1")  # [Z, B, E2]

    # GRU cell, batched over members.
    gi = dense(y, [(m.w_ih.T, m.b_ih) for m in members], "gru_ih", relu=False)  # [Z, B, 3H]
    gh = dense(h, [(m.w_hh.T, m.b_hh) for m in members], "gru_hh", relu=False)
    i_r, i_z, i_n = g.split3(gi, hid, "gi")
    h_r, h_z, h_n = g.split3(gh, hid, "gh")
    r = g.op("Sigmoid", [g.op("Add", [i_r, h_r])])
    zg = g.op("Sigmoid", [g.op("Add", [i_z, h_z])])
    n = g.op("Tanh", [g.op("Add", [i_n, g.op("Mul", [r, h_n])])])
    h_new = g.op("Add", [n, g.op("Mul", [zg, g.op("Sub", [h, n])])])
    to_float(h_new, "h_next")

    y = dense(h_new, [m.pred[0] for m in members], "pred0")
    y = dense(y, [m.pred[1] for m in members], "pred1")
    # Two-class softmax: P(slip) = sigmoid(z1 - z0); fold the difference into the last layer.
    diff = [(m.pred[2][0][:, 1:2] - m.pred[2][0][:, 0:1], m.pred[2][1][1:2] - m.pred[2][1][0:1]) for m in members]
    logit = dense(y, diff, "pred2", relu=False)  # [Z, B, 1]
    p = g.op("Sigmoid", [logit])
    p = g.op("Squeeze", [p, g.const("squeeze_axes", np.array([2], np.int64), True)])
    p_members = to_float(p, "p_members")
    g.op("ReduceMean", [p_members], "p_slip", axes=[0], keepdims=0)
    n_aux = pillar_head_size(members)
    if n_aux:
        # The per-pillar head (training's auxiliary target): member mean of each pillar's P(slip), [B, P].
        pa = g.op("Sigmoid", [dense(h_new, [m.aux for m in members if m.aux is not None], "aux", relu=False)])
        g.op("ReduceMean", [to_float(pa, "p_pillars_members")], "p_pillars", axes=[0], keepdims=0)

    f = TensorProto.FLOAT
    graph = helper.make_graph(
        g.nodes,
        "slip_ensemble",
        [helper.make_tensor_value_info("window", f, [BATCH_DIM, d]),
         helper.make_tensor_value_info("h", f, [z, BATCH_DIM, hid])],
        [helper.make_tensor_value_info("p_slip", f, [BATCH_DIM]),
         helper.make_tensor_value_info("p_members", f, [z, BATCH_DIM]),
         helper.make_tensor_value_info("h_next", f, [z, BATCH_DIM, hid]),
         *([helper.make_tensor_value_info("p_pillars", f, [BATCH_DIM, n_aux])] if n_aux else [])],
        initializer=g.inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="slipd-export")
    model.ir_version = 8  # onnxruntime >= 1.18 reads IR 8 and opset 17 everywhere
    onnx.checker.check_model(model, full_check=True)
    return model


# ---------------------------------------------------------------- checkpoint sources


def _torch_load(path: Path) -> Any:
    import torch  # offline tool: torch is allowed here, never under slipd/

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ExportError(f"{path}: cannot load checkpoint: {exc}") from exc


def load_reference(folder: str | Path) -> tuple[list[FoldedMember], FeatureSpec, dict[str, Any]]:
    """The authors' ``ckpt_final_model_*.pth`` files: folded members, their feature spec, provenance."""
    folder = Path(folder)
    paths = sorted(folder.glob("ckpt_final_model_*.pth"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not paths:
        raise ExportError(f"{folder}: no ckpt_final_model_*.pth")
    members = [fold_member(_torch_load(p), str(p)) for p in paths]
    spec = FeatureSpec()  # 8 outer pillars in SDK raster order, fx fy, 40 x 16, causal median 21
    if members[0].input_size != spec.input_size:
        raise ExportError(f"{paths[0]}: input size {members[0].input_size}, expected {spec.input_size}")
    prov: dict[str, Any] = {
        "weights": "authors' released hexapod ensemble (Wang et al.), MIT licence",
        "training_data": "authors' real hexapod data set (Dev Kit v1), not available to slipd",
        "files": {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths},
    }
    info = folder / "reload_info.npy"
    if info.is_file():
        # A pickled dict of plain settings in the shared reference folder (trusted, read-only material).
        prov["reload_info"] = {str(k): v if isinstance(v, (int, float, str)) else str(v)
                               for k, v in np.load(info, allow_pickle=True).item().items()}
    return members, spec, prov


def load_run(folder: str | Path) -> tuple[list[FoldedMember], FeatureSpec, dict[str, Any]]:
    """A training run directory of ``member_<k>.pt`` files (tools/train.py)."""
    folder = Path(folder)
    paths = sorted(folder.glob("member_*.pt"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not paths:
        raise ExportError(f"{folder}: no member_<k>.pt files")
    members, specs, provs = [], [], []
    for p in paths:
        ck = _torch_load(p)
        if not isinstance(ck, dict) or not {"state_dict", "feature_spec"} <= set(ck):
            raise ExportError(f"{p}: expected a dict with state_dict and feature_spec")
        members.append(fold_member(ck["state_dict"], str(p)))
        try:
            specs.append(FeatureSpec.from_dict(ck["feature_spec"]))
        except (TypeError, ValueError) as exc:
            raise ExportError(f"{p}: feature_spec: {exc}") from exc
        provs.append(ck.get("provenance") or {})
    if any(s != specs[0] for s in specs):
        raise ExportError(f"{folder}: members were trained on different feature specs")
    if members[0].input_size != specs[0].input_size:
        raise ExportError(f"{paths[0]}: input size {members[0].input_size} != feature spec's {specs[0].input_size}")
    # Pass-through: settings shared by all members at the top, the per-member rest (seeds, subsets) in a list.
    common = {k: v for k, v in provs[0].items() if all(k in q and q[k] == v for q in provs)}
    prov: dict[str, Any] = {**common, "run_dir": folder.name,
                            "members": [{k: v for k, v in q.items() if k not in common} for q in provs]}
    return members, specs[0], _jsonable(prov)


def _jsonable(x: Any) -> Any:
    """Provenance from checkpoints as plain JSON types (tuples -> lists, unknown objects -> str)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x
    if isinstance(x, np.generic):
        return x.item()
    return str(x)


# ---------------------------------------------------------------- export


def export(
    members: list[FoldedMember],
    spec: FeatureSpec,
    out: str | Path,
    source: str,
    provenance: dict[str, Any],
    precision: str = "fp32",
    threshold: float = 0.5,
) -> Manifest:
    """Write ``out`` (.onnx) and its manifest beside it, atomically; verify them; return the manifest."""
    out = Path(out)
    if out.suffix != ".onnx":
        raise ExportError(f"{out}: output must end in .onnx")
    if members[0].input_size != spec.input_size:
        raise ExportError(f"input size {members[0].input_size} != feature spec's {spec.input_size}")
    # fp16 has a range of 65504: at +-1000 N inputs the hidden layers can overflow (found by the interval
    # check in tests/detect/test_numerics.py), so an fp16 graph clips to what slipd.detect.features can produce for its
    # channels (twice the sensor range), which leaves every real window unchanged.
    input_clip = INPUT_CLIP
    if precision == "fp16":
        from slipd.detect.features import channel_bound

        input_clip = max(channel_bound(c) for c in spec.channels)
    model = build_graph(members, "fp16" if precision == "fp16" else "fp32", input_clip)
    data = model.SerializeToString()
    if precision == "int8":
        data = _quantize_int8(data, out)
    atomic_write_bytes(out, data)
    inputs, outputs = io_infos(spec.input_size, len(members), members[0].hidden, pillar_head_size(members))
    final = onnx.load_model_from_string(data)  # int8 quantisation rewrites the graph: describe what was written
    opset = next(o.version for o in final.opset_import if o.domain in ("", "ai.onnx"))
    manifest = Manifest(
        onnx_file=out.name,
        sha256=sha256_file(out),
        opset=opset,
        ir_version=final.ir_version,
        precision=precision,
        inputs=inputs,
        outputs=outputs,
        sample_rate_hz=spec.rate_hz,
        window=spec.window,
        median=spec.median,
        stride=spec.step,
        pillars=list(spec.pillars),
        channels=list(spec.channels),
        members=len(members),
        hidden=members[0].hidden,
        threshold=threshold,
        input_clip=input_clip,
        feature_spec=spec.to_dict(),
        source=source,
        provenance=provenance,
        pillar_mapping=REFERENCE_MAPPING if source == "reference-hexapod" else TRAINED_MAPPING,
    )
    mpath = manifest_path_for(out)
    write_manifest(manifest, mpath)
    return load_manifest(mpath, expected_spec=spec)  # the daemon's own gate, run once here


def _quantize_int8(data: bytes, out: Path) -> bytes:
    """onnxruntime dynamic 8-bit quantisation of an fp32 graph (weights uint8, activations quantised per call)."""
    import tempfile

    from onnxruntime.quantization import QuantType, quantize_dynamic

    with tempfile.TemporaryDirectory(dir=out.parent if out.parent.exists() else None) as tmp:
        src, dst = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        src.write_bytes(data)
        # uint8 weights (u8u8 kernels): with int8 weights, x86 CPUs without VNNI use u8s8 AVX2 kernels whose
        # 16-bit intermediate sums saturate; measured on the precision test's fixture with onnxruntime 1.32:
        # max |dP| 0.21 with int8 weights, 0.09 with reduce_range, 0.03 with uint8 weights.
        quantize_dynamic(str(src), str(dst), weight_type=QuantType.QUInt8)
        return dst.read_bytes()


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", help="training run directory with member_<k>.pt files")
    src.add_argument("--reference", help="folder with the authors' ckpt_final_model_*.pth files")
    ap.add_argument("--out", required=True, help="output .onnx path; the manifest goes beside it (.json)")
    prec = ap.add_mutually_exclusive_group()
    prec.add_argument("--fp16", action="store_true", help="float16 weights and compute (I/O stays float32)")
    prec.add_argument("--int8", action="store_true", help="onnxruntime dynamic int8 quantisation")
    ap.add_argument("--threshold", type=float, default=0.5, help="decision threshold stored in the manifest")
    ap.add_argument("--pillar-head", action="store_true",
                    help="also export the members' per-pillar slip head (training's --aux-weight) as output "
                         "p_pillars, which the daemon then uses as its slip map instead of the feature estimate")
    ap.add_argument("--stride", type=int, default=None,
                    help="samples between decisions (default: the window; a divisor of the window runs "
                         "window/stride phase-shifted GRU streams)")
    args = ap.parse_args(argv)
    try:
        if args.reference:
            members, spec, prov = load_reference(args.reference)
            source = "reference-hexapod"
        else:
            members, spec, prov = load_run(args.run)
            source = "trained"
            if not args.pillar_head:
                members = [replace(m, aux=None) for m in members]
        if args.stride is not None:
            if args.stride < 1 or spec.window % args.stride:
                raise ExportError(f"--stride {args.stride} must be a divisor of the window ({spec.window})")
            spec = spec.with_(stride=0 if args.stride == spec.window else args.stride)
        precision = "fp16" if args.fp16 else "int8" if args.int8 else "fp32"
        m = export(members, spec, args.out, source, prov, precision, args.threshold)
    except ExportError as exc:
        print(f"export_onnx: {exc}", file=sys.stderr)
        return 1
    size = Path(args.out).stat().st_size
    print(f"wrote {args.out} ({size / 1e6:.1f} MB, {m.members} members, {m.precision}, sha256 {m.sha256[:12]}) "
          f"and {manifest_path_for(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
