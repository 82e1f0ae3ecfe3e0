"""Timing helpers shared by the inference benchmark and the trade-off sweep.

One implementation of "how long does a decision take": realistic input windows, a per-call timer and the
authors' way of running the ensemble (torch eager, a Python loop over members), so that every figure that
compares slipd's step with the reference is timed the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def realistic_windows(k: int, d: int, seed: int = 0) -> np.ndarray:
    """Realistic windows: a smooth random walk of forces, clipped to +-2 N."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0.0, 0.01, (k, d)), axis=0)
    return np.clip(x, -2.0, 2.0).astype(np.float32)


def time_calls(fn: Callable[[int], object], n: int, offset: int = 0) -> list[float]:
    """Microseconds of each of ``fn(offset)``, ..., ``fn(offset + n - 1)``."""
    out = []
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn(offset + i)
        out.append((time.perf_counter_ns() - t0) / 1e3)
    return out


def torch_eager_step(nets: list, wins: np.ndarray) -> tuple[Callable[[int], float], Callable[[], None]]:
    """The reference implementation's decision on window ``i``: every member in eager mode, a Python loop
    over members, one window at a time, hidden states carried. Returns (step, reset of the states)."""
    import torch

    wins_t = torch.from_numpy(wins)
    h = [torch.zeros(1, net.hidden) for net in nets]

    @torch.no_grad()
    def step(i: int) -> float:
        x = wins_t[i : i + 1]
        acc = 0.0
        for k, net in enumerate(nets):
            p, h[k] = net(x, h[k])
            acc += float(p[0, 1])
        return acc / len(nets)

    def reset() -> None:
        h[:] = [torch.zeros(1, net.hidden) for net in nets]

    return step, reset


def model_cost(onnx_path: Path) -> tuple[int, int]:
    """(bytes of weights, FLOPs per decision at B = 1) of an exported graph.

    FLOPs count 2 per weight element of every MatMul (a matrix-vector product at B = 1); the element-wise
    work (biases, gates) is a few thousand operations and left out.
    """
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(onnx_path))
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    weight_bytes = sum(a.nbytes for a in inits.values())
    flops = 0
    for node in model.graph.node:
        if node.op_type in ("MatMul", "MatMulInteger") and node.input[1] in inits:
            flops += 2 * inits[node.input[1]].size
    return weight_bytes, flops
