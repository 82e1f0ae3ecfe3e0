"""How real does the simulator look to a model trained on real data?

Runs the authors' released ensemble (trained on their real hexapod recordings) on simulated
``offline`` test scenes through ``slipd.detect.features`` (the default FeatureSpec) and prints:
    * slip scenes detected: first alarm within [onset - 0.3 s, gross slip] (the method's metric),
    * stop scenes quiet: no alarm at all,
    * alarm timing against onset and motion start, and the plate travel at the alarm.

    python tools/realism.py [--count N] [--seed S] [--ckpt DIR]

With ``--recordings DIR`` (a folder written by ``tools/make_dataset.py``, e.g. ``out/datasets/robust_test``)
it runs on those recordings instead and prints the same shares per physics family (``physics_family`` from
the folder's ``index.json``, else the recording's meta) and overall, scored by ``sliplab.metrics`` (the
offline criterion of ``tools/robustness.py``: onset from the per-pillar label, stop and hold recordings must
stay quiet). ``--limit N`` keeps N recordings spread over the families (``sliplab.robustness.subset``).

    python tools/realism.py --recordings out/datasets/robust_test [--limit N]

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


def ensemble_probabilities(members: list, windows: list[np.ndarray], chunk: int = 0) -> list[np.ndarray]:
    """Mean P(slip) per window for each sequence; the sequences advance together as one batch, or with
    ``chunk`` > 0 in batches of up to ``chunk`` sequences of similar length (long recordings: less padding
    and memory). Each sequence's result does not depend on its batch (eval mode, row-independent layers)."""
    import torch

    torch.set_num_threads(1)  # one core: the batch is small and the machine is shared

    if chunk > 0 and len(windows) > chunk:
        order = sorted(range(len(windows)), key=lambda i: len(windows[i]))
        out: list[np.ndarray] = [np.zeros(0, np.float32)] * len(windows)
        for s in range(0, len(order), chunk):
            idx = order[s : s + chunk]
            for i, p in zip(idx, ensemble_probabilities(members, [windows[i] for i in idx])):
                out[i] = p
        return out
    if not any(len(w) for w in windows):
        return [np.zeros(0, np.float32) for _ in windows]
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


def evaluate_recordings(recs: list, names: list[str], families: list[str], probs: list[np.ndarray],
                        ends: list[np.ndarray], threshold: float = 0.5) -> dict[str, dict]:
    """Per physics family and ``"all"``: slip recordings detected under the offline criterion of
    ``sliplab.metrics`` (tp / early / late / missed; slips without a labelled onset are counted apart) and
    no-slip recordings (stop, hold) quiet, plus the first alarm against the labelled onset."""
    from sliplab.metrics import SceneTruth, offline_outcome

    def empty() -> dict:
        return {"slip": 0, "detected": 0, "early": 0, "late": 0, "missed": 0, "unscored": 0,
                "no_slip": 0, "quiet": 0, "latency_s": []}

    out: dict[str, dict] = {}
    for rec, name, fam, p, e in zip(recs, names, families, probs, ends):
        truth = SceneTruth.from_recording(rec, name)
        alarms = np.nonzero(p >= threshold)[0]
        t_us = np.asarray(rec.t_us, np.int64)
        first = float(t_us[e[alarms[0]]] - t_us[0]) / 1e6 if len(alarms) else None
        outcome = offline_outcome(truth, first)
        for key in (fam or "(untagged)", "all"):
            g = out.setdefault(key, empty())
            if not truth.is_slip:
                g["no_slip"] += 1
                g["quiet"] += outcome == "tn"
                continue
            if outcome is None:
                g["unscored"] += 1
                continue
            g["slip"] += 1
            g["detected" if outcome == "tp" else outcome] += 1
            if first is not None and truth.onset_s is not None:
                g["latency_s"].append(first - truth.onset_s)
    return dict(sorted(out.items(), key=lambda kv: (kv[0] == "all", kv[0])))


def _share(a: int, n: int) -> str:
    return f"{a}/{n} = {100 * a / n:5.1f} %" if n else "-"


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
    ap.add_argument("--recordings", type=Path, default=None,
                    help="run on this folder of recordings (e.g. out/datasets/robust_test) instead of simulating; "
                         "figures per physics family")
    ap.add_argument("--limit", type=int, default=0,
                    help="with --recordings: keep this many recordings, spread over the families (0: all)")
    ap.add_argument("--chunk", type=int, default=32, help="with --recordings: sequences per batch (by length)")
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
    if args.recordings is not None:
        return run_recordings(args, ckpt)
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


def run_recordings(args: argparse.Namespace, ckpt: Path) -> int:
    """``--recordings``: the reference ensemble on a folder of recordings, figures per physics family."""
    from slipd.detect.features import FeatureSpec, batch_windows, stretch_offset
    from slipd.recording import Recording, list_recordings
    from sliplab.model import load_reference_ensemble
    from sliplab.robustness import subset, tags

    folder = Path(args.recordings)
    paths = list_recordings(folder) if folder.is_dir() else []
    if not paths:
        print(f"realism: no recordings in {folder}")
        return 2
    tag = tags(folder)
    total = len(paths)
    paths = subset(paths, args.limit, tag, "physics_family")
    t0 = time.perf_counter()
    spec = FeatureSpec()
    recs, windows, ends = [], [], []
    for p in paths:
        rec = Recording.load(p)
        # The recording's unloaded stretch; [0, 0] (a recording that starts in contact): offset 0, as the daemon.
        stretch = rec.meta.get("tare_samples", spec.tare_samples)
        w, e = batch_windows(rec.force, spec, stretch_offset(rec.force, stretch))
        recs.append(rec)
        windows.append(w)
        ends.append(e)
    t_feat = time.perf_counter() - t0
    members = load_reference_ensemble(ckpt)
    t1 = time.perf_counter()
    probs = ensemble_probabilities(members, windows, args.chunk)
    t_net = time.perf_counter() - t1
    n_win = sum(len(w) for w in windows)
    fams = [tag.get(p.stem, {}).get("physics_family", "") for p in paths]
    r = evaluate_recordings(recs, [p.stem for p in paths], fams, probs, ends, args.threshold)
    seconds = sum(len(rec) for rec in recs) / 1000.0
    print(f"{len(paths)} of {total} recordings in {folder} ({seconds:.0f} s of data, {n_win} windows); "
          f"features {t_feat:.1f} s, ensemble ({len(members)} members, batches of {args.chunk}) {t_net:.1f} s "
          f"= {1e3 * t_net / max(1, n_win):.2f} ms per window")
    print("offline criterion (sliplab.metrics): slip detected = first alarm in [onset - 0.3 s, gross slip]; "
          "quiet = no alarm on a stop / hold recording")
    _table("physics family", r)
    scen = [tag.get(p.stem, {}).get("scenario", "") for p in paths]
    if any(scen):
        _table("scenario", evaluate_recordings(recs, [p.stem for p in paths], scen, probs, ends, args.threshold))
    return 0


def _table(title: str, r: dict[str, dict]) -> None:
    print(f"{title:>14} | {'slip detected':>19} | {'early/late/missed':>17} | {'stop+hold quiet':>19} | "
          "first alarm - onset (s)")
    for key, g in r.items():
        elm = f"{g['early']}/{g['late']}/{g['missed']}"
        extra = f" ({g['unscored']} slips without a labelled onset left out)" if g["unscored"] else ""
        print(f"{key:>14} | {_share(g['detected'], g['slip']):>19} | {elm:>17} | "
              f"{_share(g['quiet'], g['no_slip']):>19} | {_q(g['latency_s'])}{extra}")


if __name__ == "__main__":
    sys.exit(main())
