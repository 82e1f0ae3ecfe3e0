"""Timing helpers shared by the inference benchmark and the trade-off sweep.

One implementation of "how long does a decision take": realistic input windows, a per-call timer and the
authors' way of running the ensemble (torch eager, a Python loop over members), so that every figure that
compares slipd's step with the reference is timed the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable

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
