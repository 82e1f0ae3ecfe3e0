"""Soak test of the recurrent state: many consecutive windows on steady hold, noise only and a periodic load.

    python tools/soak.py --windows 1000000 [--model out/reference.json] [--hysteresis 0.0] [--seed 0]

The three cases run as B = 3 parallel sequences of one ``Ensemble`` stream, so each session step advances
all three (the daemon's own step path: IOBinding, finiteness checks, state kept between calls). 10^6
windows are 40 000 s (11.1 h) of sensor time per case.

Windows come from the real feature pipeline: a pool of raw 1 kHz force samples per case (sensor noise
0.01 N on fx, fy and 0.02 N on fz, as the simulator's ``noise`` effect) is turned into windows by
``slipd.detect.features.batch_windows``. The noise cases draw pool windows at random for every step (a fresh
noise sequence, not a loop); the periodic case walks its pool in order, which holds a whole number of
periods, so the load is exactly periodic.

Printed per case: the largest |h| reached (the GRU state must stay finite and within [-1, 1]), steps whose
output was non-finite, the mean P(slip) just after settling (windows 10-20 % of the run) and over the last
10 %, their difference (drift: positive means creeping towards an alarm), the largest P(slip) after
settling, and alarms (rising edges of ``slipd.detect.decision.Decision`` at the manifest's threshold) per hour.
None of these cases holds slip, so every alarm is a false alarm.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # must precede the numpy import

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipd.detect.decision import Decision
from slipd.detect.ensemble import Ensemble
from slipd.detect.features import FeatureSpec, batch_windows
from sliplab.paths import ROOT

CASES = ("steady_hold", "noise_only", "periodic_load")
NOISE_N = np.array([0.01, 0.01, 0.02], np.float32)
"""Sensor noise per axis (fx, fy, fz), N: the simulator's default."""
PERIOD_S = 2.0
"""Period of the periodic load (a slow 0.5 Hz shear cycle well inside the friction limit)."""


@dataclass(frozen=True)
class CaseResult:
    """Soak figures of one case."""

    name: str
    h_max_abs: float
    nonfinite_steps: int
    p_settled: float
    p_final: float
    p_max: float
    alarms: int
    alarm_windows: int
    windows: int
    hours: float

    @property
    def drift(self) -> float:
        """Mean P(slip) over the last 10 % minus that just after settling (10-20 %)."""
        return self.p_final - self.p_settled

    @property
    def alarm_fraction(self) -> float:
        """Share of windows spent with the alarm raised."""
        return self.alarm_windows / self.windows

    @property
    def alarms_per_hour(self) -> float:
        """Rising alarm edges per hour of sensor time (all false: no case holds slip)."""
        return self.alarms / self.hours if self.hours > 0 else float("nan")


def raw_case(name: str, n_samples: int, rng: np.random.Generator, rate_hz: int = 1000) -> np.ndarray:
    """[n, 9, 3] float32 raw forces of one case (sensor zeroed, so no tare offset is needed)."""
    noise = rng.normal(0.0, 1.0, (n_samples, 9, 3)).astype(np.float32) * NOISE_N
    if name == "noise_only":
        return noise
    # A firm grasp: 3 N normal per pillar, a steady shear of 0.2-0.6 N that differs per pillar.
    load = np.zeros((9, 3), np.float32)
    load[:, 2] = 3.0
    load[:, 0] = np.linspace(0.2, 0.6, 9, dtype=np.float32)
    load[:, 1] = np.linspace(-0.3, 0.3, 9, dtype=np.float32)
    force = noise + load
    if name == "periodic_load":
        t = np.arange(n_samples) / rate_hz
        force[:, :, 0] += (0.5 * np.sin(2 * np.pi * t / PERIOD_S)).astype(np.float32)[:, None]
        force[:, :, 2] += (1.0 * np.sin(2 * np.pi * t / PERIOD_S + 0.5)).astype(np.float32)[:, None]
    elif name != "steady_hold":
        raise ValueError(f"unknown soak case {name!r}; expected one of {CASES}")
    return force


def window_pools(spec: FeatureSpec, pool_windows: int = 2500, seed: int = 0) -> dict[str, np.ndarray]:
    """Per case, [P, T*C] windows made by the feature pipeline (P a whole number of load periods)."""
    rng = np.random.default_rng(seed)
    per_period = round(PERIOD_S * spec.rate_hz / spec.step)
    pool_windows = max(per_period, pool_windows // per_period * per_period)
    # Extra leading samples so every pooled window has a full median history (no start-up padding).
    lead = spec.median - 1 + spec.window
    n = lead + pool_windows * spec.step + spec.window
    pools = {}
    for name in CASES:
        wins, ends = batch_windows(raw_case(name, n, rng, spec.rate_hz), spec)
        keep = ends >= lead
        pools[name] = np.ascontiguousarray(wins[keep][:pool_windows])
    return pools


def soak(
    ens: Ensemble,
    n_windows: int,
    hysteresis: float = 0.0,
    seed: int = 0,
    pool_windows: int = 2500,
    stream: int = 0,
) -> list[CaseResult]:
    """Run the three cases as B = 3 sequences of ``stream`` for ``n_windows`` steps; return their figures."""
    if n_windows < 10:
        raise ValueError(f"n_windows must be >= 10 (settle and final stretches), got {n_windows}")
    spec = ens.feature_spec
    pools = window_pools(spec, pool_windows, seed)
    rng = np.random.default_rng(seed + 1)
    decisions = [Decision(ens.threshold, hysteresis) for _ in CASES]
    alarms = [0, 0, 0]
    alarm_windows = [0, 0, 0]
    p_all = np.empty((len(CASES), n_windows), np.float32)
    h_max = np.zeros(len(CASES))
    nonfinite = [0, 0, 0]
    x = np.empty((len(CASES), spec.input_size), np.float32)
    hold, noise, periodic = pools["steady_hold"], pools["noise_only"], pools["periodic_load"]
    chunk = 10_000
    ens.reset(stream)
    for c0 in range(0, n_windows, chunk):
        c1 = min(n_windows, c0 + chunk)
        ih = rng.integers(0, len(hold), c1 - c0)
        inn = rng.integers(0, len(noise), c1 - c0)
        for j, k in enumerate(range(c0, c1)):
            x[0] = hold[ih[j]]
            x[1] = noise[inn[j]]
            x[2] = periodic[k % len(periodic)]
            res = ens.step(x, stream=stream)
            if not res.valid:
                # Counted, and the case continues from the state the ensemble's policy left.
                for i in range(len(CASES)):
                    nonfinite[i] += 1
                p_all[:, k] = np.nan
                continue
            p = res.p_slip
            p_all[:, k] = p
            np.maximum(h_max, np.abs(ens.hidden_state(stream)).max(axis=(0, 2)), out=h_max)
            for i, d in enumerate(decisions):
                r = d.update(float(p[i]))
                alarms[i] += r.rising_edge
                alarm_windows[i] += r.alarm
    hours = n_windows * spec.step / spec.rate_hz / 3600.0
    a, b = n_windows // 10, n_windows // 5
    out = []
    for i, name in enumerate(CASES):
        p = p_all[i]
        out.append(CaseResult(
            name=name,
            h_max_abs=float(h_max[i]),
            nonfinite_steps=nonfinite[i],
            p_settled=float(np.nanmean(p[a:b])),
            p_final=float(np.nanmean(p[n_windows - a:])),
            p_max=float(np.nanmax(p[a:])),
            alarms=alarms[i],
            alarm_windows=alarm_windows[i],
            windows=n_windows,
            hours=hours,
        ))
    return out


def _default_model() -> Path:
    for cand in (ROOT / "slipd" / "models" / "slip_ensemble.json", ROOT / "out" / "reference.json"):
        if cand.exists():
            return cand
    raise SystemExit("no model: pass --model (slipd/models/slip_ensemble.json and out/reference.json are absent)")


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; prints one line per case."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--windows", type=int, default=1_000_000, help="consecutive windows per case")
    ap.add_argument("--model", type=Path, default=None, help="model manifest (default: shipped, else reference)")
    ap.add_argument("--hysteresis", type=float, default=0.0, help="decision hysteresis (0: the method's rule)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    model = args.model or _default_model()
    ens = Ensemble.load(model)
    t0 = time.perf_counter()
    results = soak(ens, args.windows, args.hysteresis, args.seed)
    wall = time.perf_counter() - t0
    print(f"model {model}  windows {args.windows} per case ({results[0].hours:.2f} h of sensor time each), "
          f"threshold {ens.threshold}, hysteresis {args.hysteresis}, wall {wall:.1f} s "
          f"({wall / args.windows * 1e6:.1f} us per B=3 step)")
    print(f"{'case':<14} {'max|h|':>8} {'nonfinite':>9} {'p_settled':>10} {'p_final':>10} {'drift':>10} "
          f"{'p_max':>8} {'alarms':>7} {'FA/h':>8} {'in_alarm':>9}")
    for r in results:
        print(f"{r.name:<14} {r.h_max_abs:8.5f} {r.nonfinite_steps:9d} {r.p_settled:10.6f} {r.p_final:10.6f} "
              f"{r.drift:+10.2e} {r.p_max:8.5f} {r.alarms:7d} {r.alarms_per_hour:8.3f} {r.alarm_fraction:9.2%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
