"""Benchmark one ensemble decision: the fused ONNX step vs the reference way of running, side by side.

    python tools/bench_inference.py [--manifest out/reference.json] [--reference DIR] [--steps 2000]

Both run on one thread, B = 1, one 40 x 16 window per decision, hidden states carried:
  * onnx: ``Ensemble.step`` (what the daemon calls: IOBinding, preallocated buffers, finiteness checks)
    and a plain ``session.run`` (the same graph without the buffer reuse);
  * torch: the authors' way: 5 SlipNet modules in eager mode, a Python loop over members, one window
    at a time, ``torch.set_num_threads(1)``.
Rounds alternate between the implementations so that a noisy, shared machine disturbs them alike.

It also prints the machine's limit for the model: at B = 1 every weight is read once per decision, so
the step cannot be faster than weight bytes / memory read bandwidth, nor than FLOPs / matmul rate (both
measured here, one thread). Figures are printed, never asserted: speed belongs here, not in tests.
Extra manifests (``--extra out/reference_fp16.json ...``) are timed too, for the precision trade-off.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # must precede the numpy/torch imports

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sliplab.timing import model_cost, realistic_windows, time_calls, torch_eager_step

ROOT = Path(__file__).resolve().parents[1]

DEFAULT_REF = ROOT.parent / "shared" / "reference" / "checkpoints" / "hexapod"


def _stats(us: list[float]) -> tuple[float, float, float]:
    a = np.asarray(us)
    return float(np.median(a)), float(np.percentile(a, 99)), float(a.mean())


def measure_read_bandwidth(nbytes: int, repeats: int = 5) -> float:
    """Best single-thread read bandwidth (bytes/s) over a float32 buffer of ``nbytes`` (a vectorised sum)."""
    a = np.ones(nbytes // 4, np.float32)
    a.sum()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        a.sum()
        best = min(best, time.perf_counter() - t0)
    return a.nbytes / best


def measure_matmul_rate(n: int = 1024, repeats: int = 5) -> float:
    """Best single-thread float32 GEMM rate (FLOP/s), n x n times n x n, with torch (MKL/oneDNN)."""
    import torch

    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * n**3 / best


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", default=str(ROOT / "out" / "reference.json"), help="exported reference model")
    ap.add_argument("--reference", default=str(DEFAULT_REF), help="the authors' checkpoints (torch side)")
    ap.add_argument("--steps", type=int, default=2000, help="decisions per implementation")
    ap.add_argument("--rounds", type=int, default=10, help="alternating rounds the steps are split into")
    ap.add_argument("--extra", nargs="*", default=[], help="more manifests to time (fp16, int8 variants)")
    args = ap.parse_args(argv)

    import torch

    from slipd.detect.ensemble import Ensemble, session_options
    from slipd.detect.manifest import onnx_path_of
    from slipd.detect.ort import onnxruntime as ort
    from sliplab.model import load_reference_ensemble

    torch.set_num_threads(1)
    ens = Ensemble.load(args.manifest, threads=1)
    d, z, hid = ens.feature_spec.input_size, ens.members, ens.hidden
    onnx_path = onnx_path_of(ens.manifest, args.manifest)
    sess = ort.InferenceSession(str(onnx_path), session_options(1), providers=["CPUExecutionProvider"])
    nets = load_reference_ensemble(args.reference)
    if len(nets) != z or nets[0].input_size != d:
        print(f"bench_inference: {args.reference} does not match {args.manifest}", file=sys.stderr)
        return 1
    wins = realistic_windows(args.steps, d)

    h_run = [np.zeros((z, 1, hid), np.float32)]

    def onnx_run(i: int) -> float:
        p, _, h_run[0] = sess.run(None, {"window": wins[i][None], "h": h_run[0]})
        return float(p[0])

    torch_loop, torch_reset = torch_eager_step(nets, wins)

    def ens_step(i: int) -> float:
        return ens.step(wins[i]).p_slip

    impls: dict[str, Callable[[int], object]] = {"onnx Ensemble.step": ens_step, "onnx session.run": onnx_run}
    extras = {}
    extra_wins: dict[str, np.ndarray] = {}
    for path in args.extra:
        e = Ensemble.load(path, threads=1)
        extras[path] = e
        # A model with another feature layout (other channels or pillars) gets windows of its own size;
        # its parity line below is then left out (its inputs differ from the reference's).
        w = wins if e.feature_spec.input_size == d else realistic_windows(args.steps, e.feature_spec.input_size)
        extra_wins[path] = w
        label = f"onnx {e.manifest.precision} step" + ("" if w is wins else f" ({Path(path).stem})")
        impls[label] = (lambda ee, ww: lambda i: ee.step(ww[i]).p_slip)(e, w)
    impls["torch eager loop"] = torch_loop

    # Parity over the same sequence (fresh states), so the table compares equal work.
    p_onnx = np.array([ens_step(i) for i in range(min(200, args.steps))])
    p_torch = np.array([torch_loop(i) for i in range(min(200, args.steps))])
    ens.reset()
    torch_reset()
    print(f"parity over {len(p_onnx)} decisions: max |p_slip onnx - torch| = {np.abs(p_onnx - p_torch).max():.2e}")
    for path, e in extras.items():
        if extra_wins[path] is not wins:
            print(f"  {Path(path).name}: feature layout {e.feature_spec.input_size} != {d}, timed only")
            continue
        p_x = np.array([e.step(wins[i]).p_slip for i in range(len(p_onnx))])
        e.reset()
        print(f"  {e.manifest.precision} ({Path(path).name}): max |p_slip - fp32| = {np.abs(p_x - p_onnx).max():.2e}")

    times: dict[str, list[float]] = {k: [] for k in impls}
    per_round = max(1, args.steps // args.rounds)
    for r in range(args.rounds):
        for name, fn in impls.items():
            times[name] += time_calls(fn, per_round, r * per_round)

    n_each = per_round * args.rounds
    print(f"\nper decision (B=1, one thread, {n_each} decisions each, {args.rounds} alternating rounds)")
    print(f"{'implementation':<24}{'median us':>12}{'p99 us':>12}{'mean us':>12}")
    for name, us in times.items():
        med, p99, mean = _stats(us)
        print(f"{name:<24}{med:>12.1f}{p99:>12.1f}{mean:>12.1f}")
    t_med, t_p99, _ = _stats(times["torch eager loop"])
    o_med, o_p99, _ = _stats(times["onnx Ensemble.step"])
    print(f"ratio torch / onnx Ensemble.step: median {t_med / o_med:.2f}x, p99 {t_p99 / o_p99:.2f}x")

    wbytes, flops = model_cost(onnx_path)
    bw_dram = measure_read_bandwidth(512 << 20)
    bw_model = measure_read_bandwidth(max(wbytes, 1 << 20))
    rate = measure_matmul_rate()
    print("\nmachine limit for this model (one thread)")
    print(f"  weights {wbytes / 1e6:.1f} MB, {flops / 1e6:.1f} MFLOP per decision")
    print(f"  read bandwidth: {bw_dram / 1e9:.1f} GB/s (512 MB buffer, DRAM), "
          f"{bw_model / 1e9:.1f} GB/s (model-sized buffer, may sit in cache)")
    print(f"  float32 GEMM rate: {rate / 1e9:.1f} GFLOP/s (1024^3, torch)")
    print(f"  bound: bytes/DRAM {wbytes / bw_dram * 1e6:.0f} us, bytes/cached {wbytes / bw_model * 1e6:.0f} us, "
          f"FLOPs/GEMM {flops / rate * 1e6:.0f} us")
    limit = max(wbytes / bw_model, flops / rate)
    print(f"  onnx Ensemble.step median is {o_med / (limit * 1e6):.2f}x the tighter (cached) limit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
