"""What accuracy costs in time: sweep the knobs of the detector and measure both sides on the same scenes.

    python tools/tradeoff.py [--run out/util5m5] [--threshold 0.5] [--data out/datasets/transfer_test]
                             [--train-data out/datasets/offline_train out/datasets/transfer_train]
                             [--train-args "--channels util --label-span slip ..."] [--every 1] [--workers 2]
                             [--retrain-epochs 8] [--cache out/tradeoff] [--no-retrain]

Two groups of points, each compared within itself:

* **ensemble** (the trained members of ``--run``, no retraining): ensemble size Z = 1, 2, 3, 5; numeric
  precision fp32 / fp16 / int8 (onnxruntime dynamic quantisation, Z = 5); decision stride 40 / 20 / 10
  samples with the window fixed at 40 (``slipd.detect.detector`` runs window/stride phase-shifted GRU streams).
* **retrained** (one member per point, ``--retrain-epochs`` epochs on ``--train-data`` with the shipped
  recipe: Adam 1e-3, all pillars, plus ``--train-args``; each point's threshold tuned on ``--tune-data``,
  train recordings): window 10 / 20 / 40 samples and median width 1 / 5 / 11 / 21.
  Window and median change what the network sees, so each needs its own model; the point (40, 21) is
  retrained under the same budget so the group compares like with like. Checkpoints are cached in
  ``--cache`` and reused by later runs.

For every point: the method's success rate (online criterion on gripper trials, offline on hexapod
scenes), stop-scene false positives and false alarms per hour,
detection latency from the labelled onset (median, p90), inference time per decision (``Ensemble.step``,
one thread, B = 1: median and p99), and the CPU share of one core per second of 1 kHz sensor data
(per-sample feature cost x 1000 + decision cost x decisions per second, both measured here). The
reference implementation's decision (the authors' 5 checkpoints in torch eager mode, a Python loop over
members, one window at a time) is timed in rounds alternating with each point's own step, and every
point's speed-up over it is printed.

Writes ``reports/tradeoff.md`` (the table, the knee: the cheapest point within 1 point of the best
success rate) and ``reports/tradeoff.png`` (success rate against median latency, marker area = CPU
share, the Pareto front drawn), plus ``<cache>/tradeoff.json`` with every figure.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # timing is per thread; must precede the numpy/torch imports

import argparse
import json
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slipd.detect.features import FeatureSpec, FeatureStream
from slipd.recording import list_recordings
from sliplab.evaluate import evaluate_paths
from sliplab.metrics import summarize
from sliplab.timing import realistic_windows, time_calls, torch_eager_step

ROOT = Path(__file__).resolve().parents[1]

DEFAULT_REF = ROOT.parent / "shared" / "reference" / "checkpoints" / "hexapod"
RATE_HZ = 1000


@dataclass
class Point:
    """One configuration of the sweep and, once measured, its figures."""

    name: str
    group: str
    knob: str
    members: int = 5
    precision: str = "fp32"
    window: int = 40
    median: int = 21
    stride: int = 40
    threshold: float = 0.5
    manifest: str = ""
    figures: dict = field(default_factory=dict)


def sweep_points(threshold: float, retrain: bool) -> list[Point]:
    """The configurations the issue asks for (see the module docstring)."""
    pts = [Point(f"Z={z}", "ensemble", "members", members=z, threshold=threshold) for z in (1, 2, 3, 5)]
    pts += [Point(f"Z=5 {p}", "ensemble", "precision", precision=p, threshold=threshold) for p in ("fp16", "int8")]
    pts += [Point(f"Z=5 stride {s}", "ensemble", "stride", stride=s, threshold=threshold) for s in (20, 10)]
    pts += [Point("Z=5 int8 stride 10", "ensemble", "precision+stride", precision="int8", stride=10,
                  threshold=threshold)]
    if retrain:
        pts += [Point("1 member w40 m21", "retrained", "reference", members=1)]
        pts += [Point(f"1 member w{w} m21", "retrained", "window", members=1, window=w, stride=w) for w in (10, 20)]
        pts += [Point(f"1 member w40 m{m}", "retrained", "median", members=1, median=m) for m in (1, 5, 11)]
    return pts


# ------------------------------------------------------------------------------------------ models
def _export(run_dir: Path, out: Path, precision: str, threshold: float) -> Path:
    from sliplab.export import main as export_main

    args = ["--run", str(run_dir), "--out", str(out), "--threshold", str(threshold)]
    if precision != "fp32":
        args.append(f"--{precision}")
    if export_main(args) != 0:
        raise SystemExit(f"tradeoff: export of {run_dir} failed")
    return out.with_suffix(".json")


def build_models(points: list[Point], run: Path, args: argparse.Namespace) -> None:
    """Export (and for the retrained group, train) the model of every point; cached in ``args.cache``."""
    cache = args.cache
    members = sorted(run.glob("member_*.pt"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    for pt in points:
        if pt.group == "ensemble":
            sub = cache / f"ens_z{pt.members}"
            sub.mkdir(parents=True, exist_ok=True)
            for k, src in enumerate(members[: pt.members]):
                link = sub / f"member_{k}.pt"
                if not link.exists():
                    link.symlink_to(src.resolve())
            out = sub / f"z{pt.members}_{pt.precision}.onnx"
        else:
            sub = cache / f"train_w{pt.window}_m{pt.median}"
            if not (sub / "member_0.pt").exists():
                cmd = [sys.executable, str(ROOT / "tools" / "train.py"), "--data", *map(str, args.train_data),
                       "--out", str(sub), "--members", "1", "--epochs", str(args.retrain_epochs),
                       "--optimizer", "adam", "--lr", "1e-3", "--pillars", "all", "--threads", "2", "--no-eval",
                       "--quiet", "--window", str(pt.window), "--median", str(pt.median),
                       *shlex.split(args.train_args)]
                print(f"training {pt.name}: {' '.join(cmd[1:])}", flush=True)
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True)
                print(f"  {time.perf_counter() - t0:.0f} s", flush=True)
            out = sub / f"w{pt.window}_m{pt.median}_{pt.precision}.onnx"
        manifest = out.with_suffix(".json")
        if not manifest.exists():
            _export(sub, out, pt.precision, pt.threshold)
        pt.manifest = str(manifest)
        if pt.group == "retrained":
            pt.threshold = _tuned_threshold(pt, sub, args)


def _tuned_threshold(pt: Point, sub: Path, args: argparse.Namespace) -> float:
    """A retrained member's threshold, tuned on ``--tune-data`` (train recordings) at the point's stride.

    Single members of a recipe with a weighted loss do not centre on 0.5, so one fixed threshold would
    compare thresholds, not configurations. Cached in ``<sub>/threshold.json``.
    """
    from sliplab.tune import tune

    cached = sub / "threshold.json"
    if cached.exists():
        return float(json.loads(cached.read_text())["threshold"])
    paths = [q for folder in args.tune_data for q in list_recordings(folder)][:: args.tune_every]
    best, _ = tune(pt.manifest, paths, np.round(np.arange(0.3, 0.951, 0.05), 2), pt.stride, args.workers)
    cached.write_text(json.dumps({"threshold": best["threshold"], "train_success": best["success"],
                                  "recordings": len(paths)}) + "\n")
    print(f"  {pt.name}: threshold {best['threshold']:.2f} ({100 * best['success']:.1f} % on train)", flush=True)
    return float(best["threshold"])


# ------------------------------------------------------------------------------------------ accuracy
def accuracy(pt: Point, paths: list[Path], workers: int) -> dict:
    """The method's figures of one point over ``paths`` (the daemon's decision path)."""
    results = evaluate_paths(paths, "model", (pt.manifest, 0.0, pt.threshold, pt.stride), workers=workers,
                             progress=False)
    s = summarize([r[0] for r in results])
    c = s.online if s.online is not None else s.offline  # gripper trials: the online criterion
    return {"success": c.success_rate, "tp": c.tp, "fn": c.fn, "fp": c.fp,
            "tn": c.tn, "false_alarms_per_hour": s.false_alarms_per_hour,
            "criterion": "online" if s.online is not None else "offline",
            "latency_median_s": s.latency_s.median, "latency_p90_s": s.latency_s.p90, "scenes": s.n_scenes}


# ------------------------------------------------------------------------------------------ time
def _time_us(fn, n: int) -> np.ndarray:
    return np.asarray(time_calls(fn, n))


def step_time(manifest: str, n: int, reference=None, rounds: int = 4) -> tuple[np.ndarray, np.ndarray | None]:
    """Microseconds per ``Ensemble.step`` (one thread, B = 1, hidden state carried), and per decision of
    ``reference`` (a callable step) timed in alternating rounds, so a noisy machine disturbs both alike."""
    from slipd.detect.ensemble import Ensemble

    ens = Ensemble.load(manifest, threads=1)
    wins = realistic_windows(n, ens.feature_spec.input_size)
    _time_us(lambda i: ens.step(wins[i % n]), min(50, n))  # warm caches
    per = max(1, n // rounds)
    ours, ref = [], []
    for r in range(rounds):
        ours.append(_time_us(lambda i, r=r: ens.step(wins[(r * per + i) % n]), per))
        if reference is not None:
            ref.append(_time_us(lambda i, r=r: reference(r * per + i), per))
    return np.concatenate(ours), (np.concatenate(ref) if ref else None)


def feature_time(spec: FeatureSpec, n: int = 4000) -> float:
    """Mean microseconds per raw sample through ``FeatureStream.push`` (windows included)."""
    rng = np.random.default_rng(1)
    samples = rng.normal(0, 0.05, (n, 9, 3)).astype(np.float32)
    fs = FeatureStream(spec)
    return float(_time_us(lambda i: fs.push(samples[i]), n).mean())


def torch_reference_step(ref: Path, n: int):
    """The reference implementation's decision (``sliplab.timing.torch_eager_step`` on the authors'
    checkpoints) as a callable ``step(i)`` over ``n`` windows; None without torch or checkpoints."""
    try:
        import torch

        from sliplab.model import load_reference_ensemble
    except ImportError:
        return None
    if not ref.is_dir():
        return None
    torch.set_num_threads(1)
    nets = load_reference_ensemble(ref)
    step, _ = torch_eager_step(nets, realistic_windows(n, nets[0].input_size))
    _time_us(step, min(50, n))
    return lambda i: step(i % n)


# ------------------------------------------------------------------------------------------ report
def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _ms(v) -> str:
    return "-" if v is None else f"{1000 * v:.0f}"


def knee(points: list[Point]) -> tuple[Point, Point]:
    """(best, knee): the highest success, and the lowest-CPU point within 1 point of it."""
    scored = [p for p in points if p.figures.get("success") is not None]
    best = max(scored, key=lambda p: p.figures["success"])
    near = [p for p in scored if p.figures["success"] >= best.figures["success"] - 0.01]
    return best, min(near, key=lambda p: p.figures["cpu_share"])


def pareto(points: list[Point]) -> list[Point]:
    """Points no other point beats on both success (higher) and median latency (lower)."""
    pts = [p for p in points if p.figures.get("success") is not None and p.figures.get("latency_median_s") is not None]
    front = []
    for p in pts:
        s, lat = p.figures["success"], p.figures["latency_median_s"]
        if not any(q.figures["success"] >= s and q.figures["latency_median_s"] <= lat and
                   (q.figures["success"] > s or q.figures["latency_median_s"] < lat) for q in pts):
            front.append(p)
    return sorted(front, key=lambda p: p.figures["latency_median_s"])


def write_report(points: list[Point], torch_us: np.ndarray | None, args: argparse.Namespace, cmd: str) -> str:
    """The markdown report (also returned for printing)."""
    lines = ["# What accuracy costs in time", "",
             f"Generated by `{cmd}` on {time.strftime('%Y-%m-%d')} ({len(args.paths)} scenes of "
             f"`{args.data}`; the method's {points[0].figures.get('criterion', 'offline')} criterion). "
             "Speed: one thread, B = 1; CPU share = per-sample "
             "feature cost x 1000 + decision cost x decisions per second, as a share of one core.", ""]
    if torch_us is not None:
        lines += [f"Reference implementation (authors' 5 checkpoints, torch eager, Python loop over members), "
                  f"timed in rounds alternating with every point's own step: median {np.median(torch_us):.0f} us, "
                  f"p99 {np.percentile(torch_us, 99):.0f} us per decision over all points; each point's speed-up "
                  "uses the rounds timed beside it.", ""]
    for group, title in (("ensemble", "Trained ensemble (no retraining), threshold "
                          f"{args.threshold}"),
                         ("retrained", f"Retrained, 1 member, {args.retrain_epochs} epochs each, threshold "
                          "tuned per point on train recordings")):
        gp = [p for p in points if p.group == group]
        if not gp:
            continue
        lines += [f"## {title}", "",
                  "| point | success | TP/FN | FP/TN | false alarms/h | latency median / p90 (ms) | step median / "
                  "p99 (us) | features (us/sample) | CPU share | x faster than torch eager |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for p in gp:
            f = p.figures
            speed = f"{f['speedup']:.1f}" if f.get("speedup") else "-"
            fah = "-" if f.get("false_alarms_per_hour") is None else f"{f['false_alarms_per_hour']:.0f}"
            name = p.name if group == "ensemble" else f"{p.name}, threshold {p.threshold:.2f}"
            lines.append(f"| {name} | {_pct(f['success'])} | {f['tp']}/{f['fn']} | {f['fp']}/{f['tn']} | {fah} | "
                         f"{_ms(f['latency_median_s'])} / {_ms(f['latency_p90_s'])} | {f['step_median_us']:.0f} / "
                         f"{f['step_p99_us']:.0f} | {f['feature_us']:.1f} | {100 * f['cpu_share']:.1f} % | {speed} |")
        best, kp = knee(gp)
        lines += ["", f"Best success: **{best.name}** ({_pct(best.figures['success'])}). Knee (cheapest within 1 "
                  f"point of it): **{kp.name}** ({_pct(kp.figures['success'])}, CPU share "
                  f"{100 * kp.figures['cpu_share']:.1f} %, step {kp.figures['step_median_us']:.0f} us"
                  + (f", {kp.figures['speedup']:.1f}x faster than the torch eager reference" if kp.figures.get(
                      "speedup") else "") + ").", ""]
    lines += ["![trade-off](tradeoff.png)", ""]
    return "\n".join(lines)


def plot(points: list[Point], path: Path) -> None:
    """Success against median latency; marker area = CPU share; Pareto front per group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    colours = {"ensemble": "tab:blue", "retrained": "tab:orange"}
    for group, colour in colours.items():
        gp = [p for p in points if p.group == group and p.figures.get("latency_median_s") is not None]
        if not gp:
            continue
        xs = [1000 * p.figures["latency_median_s"] for p in gp]
        ys = [100 * p.figures["success"] for p in gp]
        sizes = [20 + 4000 * p.figures["cpu_share"] for p in gp]
        ax.scatter(xs, ys, s=sizes, alpha=0.5, color=colour, label=f"{group} (area = CPU share)")
        for p, x, y in zip(gp, xs, ys):
            ax.annotate(p.name, (x, y), fontsize=7, xytext=(4, 3), textcoords="offset points")
        front = pareto(gp)
        ax.plot([1000 * p.figures["latency_median_s"] for p in front], [100 * p.figures["success"] for p in front],
                "--", color=colour, lw=1)
    ax.set_xlabel("detection latency from labelled onset, median (ms)")
    ax.set_ylabel("success rate (%)")
    ax.set_title("slipd: accuracy against detection delay and compute (dashed: Pareto front)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run the sweep; prints the table and writes the report, plot and JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=ROOT / "out" / "util5m5", help="training run of the shipped members")
    ap.add_argument("--threshold", type=float, default=0.5, help="threshold of the ensemble group")
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "datasets" / "transfer_test",
                    help="test scenes; gripper trials are scored with the online criterion, hexapod scenes offline")
    ap.add_argument("--train-data", type=Path, nargs="+",
                    default=[ROOT / "out" / "datasets" / "offline_train", ROOT / "out" / "datasets" / "transfer_train"])
    ap.add_argument("--every", type=int, default=1, help="use every k-th scene of --data (speed)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--retrain-epochs", type=int, default=8)
    ap.add_argument("--tune-data", type=Path, nargs="+", default=[ROOT / "out" / "datasets" / "transfer_train"],
                    help="train recordings on which each retrained point's threshold is tuned")
    ap.add_argument("--tune-every", type=int, default=3,
                    help="use every k-th recording of --tune-data (not a multiple of 4: the transfer design "
                         "repeats 3 slip trials and 1 stop trial, so k = 4 would pick slips only)")
    ap.add_argument("--train-args", default="",
                    help="extra tools/train.py flags for the retrained points (the shipped recipe), one string")
    ap.add_argument("--no-retrain", action="store_true", help="only the ensemble group")
    ap.add_argument("--steps", type=int, default=400, help="timed decisions per point")
    ap.add_argument("--reference", type=Path, default=DEFAULT_REF, help="authors' checkpoints for the torch timing")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "tradeoff")
    ap.add_argument("--report", type=Path, default=ROOT / "reports" / "tradeoff.md")
    args = ap.parse_args(argv)
    args.paths = list_recordings(args.data)[:: args.every]
    if not args.paths:
        raise SystemExit(f"tradeoff: no recordings in {args.data}")
    if not list(args.run.glob("member_*.pt")):
        raise SystemExit(f"tradeoff: no member_<k>.pt in {args.run} (see models/MODEL_CARD.md to make them)")
    args.cache.mkdir(parents=True, exist_ok=True)
    cmd = "python tools/tradeoff.py " + shlex.join(argv if argv is not None else sys.argv[1:])

    points = sweep_points(args.threshold, not args.no_retrain)
    build_models(points, args.run, args)
    torch_step = torch_reference_step(args.reference, args.steps)
    all_torch: list[np.ndarray] = []
    feat_cache: dict[tuple, float] = {}
    for pt in points:
        t0 = time.perf_counter()
        fig = accuracy(pt, args.paths, args.workers)
        us, ref_us = step_time(pt.manifest, args.steps, torch_step)
        ref_med = float(np.median(ref_us)) if ref_us is not None else None
        if ref_us is not None:
            all_torch.append(ref_us)
        # The point's own feature layout (channels, pillars) from its manifest, at the point's stride.
        spec = FeatureSpec.from_dict(json.loads(Path(pt.manifest).read_text())["feature_spec"]).with_(
            stride=0 if pt.stride == pt.window else pt.stride)
        key = (pt.window, pt.median, pt.stride, spec.channels, spec.pillars)
        if key not in feat_cache:
            feat_cache[key] = feature_time(spec)
        step_med = float(np.median(us))
        cpu = (RATE_HZ * feat_cache[key] + RATE_HZ / pt.stride * float(us.mean())) / 1e6
        fig.update(step_median_us=step_med, step_p99_us=float(np.percentile(us, 99)), feature_us=feat_cache[key],
                   cpu_share=cpu, torch_median_us=ref_med, speedup=(ref_med / step_med) if ref_med else None)
        pt.figures = fig
        print(f"{pt.name:<22} success {_pct(fig['success']):>8}  FP {fig['fp']:>3}  latency "
              f"{_ms(fig['latency_median_s']):>5} ms  step {step_med:7.0f} us  CPU {100 * cpu:5.1f} %"
              + (f"  {fig['speedup']:.1f}x torch" if fig["speedup"] else "")
              + f"   ({time.perf_counter() - t0:.0f} s)", flush=True)
    torch_us = np.concatenate(all_torch) if all_torch else None
    report = write_report(points, torch_us, args, cmd)
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(report)
    plot(points, args.report.with_suffix(".png"))
    (args.cache / "tradeoff.json").write_text(json.dumps(
        {"command": cmd, "torch_reference_us": None if torch_us is None else
         {"median": float(np.median(torch_us)), "p99": float(np.percentile(torch_us, 99))},
         "points": [asdict(p) for p in points]}, indent=1) + "\n")
    print(report)
    print(f"wrote {args.report}, {args.report.with_suffix('.png')} and {args.cache / 'tradeoff.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
