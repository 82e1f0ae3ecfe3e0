"""How real does the simulator look to a model trained on real data?

Runs the authors' released ensemble (trained on their real hexapod recordings) on simulated
``offline`` test scenes through ``slipd.detect.features`` (the default FeatureSpec) and prints:
    * slip scenes detected: first alarm within [onset - 0.3 s, gross slip] (the method's metric),
    * stop scenes quiet: no alarm at all,
    * alarm timing against onset and motion start, and the plate travel at the alarm.

    python tools/realism.py [--count N] [--seed S] [--ckpt DIR]

Skips cleanly (exit 0) when torch or the checkpoints are absent.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from sliplab.paths import ROOT

DEFAULT_CKPT = ROOT.parent / "shared" / "reference" / "checkpoints" / "hexapod"


def ensemble_probabilities(members: list, windows: list[np.ndarray]) -> list[np.ndarray]:
    """Mean P(slip) per window for each sequence; all sequences advance together as one batch."""
    import torch

    torch.set_num_threads(1)  # one core: the batch is small and the machine is shared

    k_max = max(len(w) for w in windows)
    d = windows[0].shape[1]
    x = np.zeros((len(windows), k_max, d), np.float32)
    for i, w in enumerate(windows):
        x[i, : len(w)] = w
    xt = torch.from_numpy(x)
    total = torch.zeros(len(windows), k_max)
    with torch.no_grad():
        for net in members:
            h = torch.zeros(len(windows), net.hidden)
            for k in range(k_max):
                p, h = net(xt[:, k], h)
                total[:, k] += p[:, 1]
    mean = (total / len(members)).numpy()
    return [mean[i, : len(w)] for i, w in enumerate(windows)]


def evaluate(recs: list, probs: list[np.ndarray], ends: list[np.ndarray], threshold: float = 0.5) -> dict:
    """The method's offline metrics plus timing figures."""
    det, n_slip, quiet, n_stop = 0, 0, 0, 0
    lat, since_motion, travel = [], [], []
    by_motion: dict[str, list[int]] = {}
    for rec, p, e in zip(recs, probs, ends):
        ev = rec.events
        alarms = np.nonzero(p >= threshold)[0]
        t_alarm = (e[alarms[0]] / 1000.0) if len(alarms) else None
        if rec.meta["kind"] == "stop":
            n_stop += 1
            quiet += t_alarm is None
            by_motion.setdefault("stop_" + rec.meta["motion"], [0, 0])
            by_motion["stop_" + rec.meta["motion"]][0] += t_alarm is None
            by_motion["stop_" + rec.meta["motion"]][1] += 1
            continue
        if "onset" not in ev:
            continue
        n_slip += 1
        gross = ev.get("gross_slip", len(rec) / 1000.0)
        ok = t_alarm is not None and ev["onset"] - 0.3 <= t_alarm <= gross
        det += ok
        by_motion.setdefault(rec.meta["motion"], [0, 0])
        by_motion[rec.meta["motion"]][0] += ok
        by_motion[rec.meta["motion"]][1] += 1
        if t_alarm is not None:
            lat.append(t_alarm - ev["onset"])
            since_motion.append(t_alarm - ev["motion_start"])
            k = min(round(t_alarm * 1000), len(rec) - 1)
            travel.append(float(np.hypot(*(rec.object_motion[k, :2] - rec.object_motion[0, :2]))))
    return {
        "slip": n_slip, "detected": det, "stop": n_stop, "quiet": quiet,
        "latency_s": lat, "since_motion_s": since_motion, "travel_mm": travel, "by_motion": by_motion,
    }


def _q(v: list[float]) -> str:
    if not v:
        return "n/a"
    a = np.asarray(v)
    return f"median {np.median(a):+.3f}, p10 {np.percentile(a, 10):+.3f}, p90 {np.percentile(a, 90):+.3f}"


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=100, help="offline test scenes to simulate (default 100)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ckpt", default=str(DEFAULT_CKPT), help="folder of ckpt_final_model_*.pth")
    ap.add_argument("--threshold", type=float, default=0.5)
    args = ap.parse_args(argv)
    try:
        import torch  # noqa: F401

        from sliplab.model import load_reference_ensemble
    except ImportError:
        print("realism: torch is not installed; skipping")
        return 0
    ckpt = Path(args.ckpt)
    if not any(ckpt.glob("ckpt_final_model_*.pth")):
        print(f"realism: no checkpoints in {ckpt}; skipping")
        return 0
    from slipd.detect.features import FeatureSpec, batch_windows, tare_offset
    from slipd.sim.datasets import dataset_scenes
    from slipd.sim.scene import generate_batch, parse_scene

    t0 = time.perf_counter()
    items = dataset_scenes("offline", "test", args.count, args.seed)
    recs = generate_batch([parse_scene(d, d["name"]) for d, _ in items], [s for _, s in items])
    t_sim = time.perf_counter() - t0
    spec = FeatureSpec()
    windows, ends = [], []
    for rec in recs:
        a, b = rec.meta["tare_samples"]
        w, e = batch_windows(rec.force, spec, tare_offset(rec.force, a, b))
        windows.append(w)
        ends.append(e)
    members = load_reference_ensemble(ckpt)
    t1 = time.perf_counter()
    probs = ensemble_probabilities(members, windows)
    t_net = time.perf_counter() - t1
    r = evaluate(recs, probs, ends, args.threshold)
    print(f"simulated {len(recs)} offline test scenes in {t_sim:.1f} s; "
          f"ensemble ({len(members)} members) {t_net:.1f} s")
    if r["slip"]:
        print(f"slip scenes detected in [onset - 0.3 s, gross slip]: {r['detected']}/{r['slip']} "
              f"= {100 * r['detected'] / r['slip']:.1f} %")
    if r["stop"]:
        print(f"stop scenes with no alarm: {r['quiet']}/{r['stop']} = {100 * r['quiet'] / r['stop']:.1f} %")
    for name, (ok, n) in sorted(r["by_motion"].items()):
        print(f"  {name:>16}: {ok}/{n}")
    print(f"first alarm - onset (s):        {_q(r['latency_s'])}")
    print(f"first alarm - motion start (s): {_q(r['since_motion_s'])}")
    print(f"plate translation at first alarm (mm): {_q(r['travel_mm'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
