"""What accuracy costs in time: sweep the knobs of the detector and measure both sides on the same scenes.

    python tools/tradeoff.py [--run out/util5m5] [--threshold 0.5] [--data out/datasets/transfer_test]
                             [--train-data out/datasets/offline_train out/datasets/transfer_train]
                             [--train-args "--channels util --label-span slip ..."] [--every 1] [--workers 2]
                             [--retrain-epochs 8] [--cache out/tradeoff] [--no-retrain]
                             [--heldout out/datasets/robust_test] [--heldout-limit 50]
                             [--lofo stick_slip=out/lofo5_stick_slip ...]

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

With ``--heldout DIR`` (a folder of robust test recordings, ``tools/make_dataset.py --set robust``) every
point is also run on those recordings (``--heldout-limit`` of them, spread over the physics families) and
scored with the offline criterion as ``tools/robustness.py`` does: success, balanced success, stop/hold false
alarms, latency, and success per physics family. The report says whether the run's training data held the
same families (then the figures are on unseen recordings of seen families, not on unseen families).
With ``--lofo FAMILY=RUN ...`` (the leave-one-family-out training runs of ``tools/robustness.py``, each with at
least as many members as the largest Z) every ensemble point is also built from each fold's members (its first Z,
its precision) and each family's held-out recordings are run by the fold trained without that family: the
held-out figures are then on unseen physics, beside the own-split figures of the same point.

Writes ``reports/tradeoff.md`` (the table, the knee: the cheapest point within 1 point of the best
success rate) and ``reports/tradeoff.png`` (two panels: success against compute per decision, log scale,
and success against detection delay, the median latency of the detected slips; the shipped point and the knee
marked; the held-out success as a hollow marker beside each point's own-split success), plus
``reports/tradeoff.json`` and ``<cache>/tradeoff.json`` with every figure. ``--plot-only`` redraws the plot from
``reports/tradeoff.json``, or, where that is missing, from the table in ``reports/tradeoff.md``.
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
    folds: dict = field(default_factory=dict)
    """Held-out family -> this point's model built from the members of the fold trained without it (``--lofo``)."""


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
    """The manifest of ``run_dir``'s members exported to ``out`` (cached: an existing manifest is reused)."""
    from sliplab.export import main as export_main

    if out.with_suffix(".json").exists():
        return out.with_suffix(".json")
    args = ["--run", str(run_dir), "--out", str(out), "--threshold", str(threshold)]
    if precision != "fp32":
        args.append(f"--{precision}")
    if export_main(args) != 0:
        raise SystemExit(f"tradeoff: export of {run_dir} failed")
    return out.with_suffix(".json")


def _members(run: Path) -> list[Path]:
    return sorted(run.glob("member_*.pt"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))


def _ensemble_model(run: Path, sub: Path, pt: Point) -> str:
    """The manifest of ``pt``'s ensemble point (its first Z members, its precision) from the members of ``run``,
    exported into ``sub`` (cached)."""
    sub.mkdir(parents=True, exist_ok=True)
    for k, src in enumerate(_members(run)[: pt.members]):
        link = sub / f"member_{k}.pt"
        if not link.exists():
            link.symlink_to(src.resolve())
    return str(_export(sub, sub / f"z{pt.members}_{pt.precision}.onnx", pt.precision, pt.threshold))


def build_models(points: list[Point], run: Path, args: argparse.Namespace) -> None:
    """Export (and for the retrained group, train) the model of every point; cached in ``args.cache``. With
    ``args.lofo`` (family -> fold run) each ensemble point is also built from every fold's members."""
    cache = args.cache
    for pt in points:
        if pt.group == "ensemble":
            pt.manifest = _ensemble_model(run, cache / f"ens_z{pt.members}", pt)
            pt.folds = {fam: _ensemble_model(fold, cache / f"lofo_{fam}" / f"ens_z{pt.members}", pt)
                        for fam, fold in args.lofo.items()}
            continue
        # The retrained group: one member per point, trained here.
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
        pt.manifest = str(_export(sub, sub / f"w{pt.window}_m{pt.median}_{pt.precision}.onnx", pt.precision,
                                  pt.threshold))
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


def heldout_accuracy(pt: Point, paths: list[Path], tag: dict, workers: int) -> dict:
    """Offline figures of one point on the held-out recordings, overall and per physics family
    (``sliplab.robustness.figures``: the robustness report's criterion). With ``pt.folds`` each family's
    recordings are run by that point's model from the fold trained without the family (held-out physics);
    otherwise by the point's own model."""
    from sliplab.robustness import figures, group

    if pt.folds:
        by_family: dict[str, list[Path]] = {}
        for q in paths:
            by_family.setdefault(str(tag.get(q.stem, {}).get("physics_family")), []).append(q)
        missing = sorted(set(by_family) - set(pt.folds))
        if missing:
            raise SystemExit(f"tradeoff: --lofo names no fold for the held-out families {', '.join(missing)}")
        results = [r for fam, qs in sorted(by_family.items()) for r in evaluate_paths(
            qs, "model", (pt.folds[fam], 0.0, pt.threshold, pt.stride), workers=workers, progress=False)]
    else:
        results = evaluate_paths(paths, "model", (pt.manifest, 0.0, pt.threshold, pt.stride), workers=workers,
                                 progress=False)
    out = figures(results)
    out["families"] = {fam: figures(rs)["success"] for fam, rs in group(results, tag, "physics_family").items()}
    return out


def heldout_note(manifest: str, folder: Path) -> str:
    """Whether the run's training data held the held-out folder's set (from the export's provenance)."""
    try:
        prov = json.loads(Path(manifest).read_text()).get("provenance", {})
        held = json.loads((folder / "index.json").read_text()).get("set", "")
    except (OSError, ValueError):
        return ""
    seen = [str(d) for d in prov.get("data", []) if held and Path(str(d)).name.startswith(f"{held}_")]
    if seen:
        return (f"the run was trained on {', '.join(seen)}: the same physics families, other recordings "
                "(unseen recordings, not unseen families)")
    if prov.get("data"):
        return f"the run's training data ({', '.join(map(str, prov['data']))}) holds no `{held}` set"
    return ""


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


def _heldout_cells(h: dict | None) -> str:
    if not h:
        return " - | - | - |"
    return (f" {_pct(h['success'])} / {_pct(h['balanced'])} | {h['stop_alarmed']}/{h['stop']} | "
            f"{_ms(h['latency_median_s'])} |")


def write_report(points: list[Point], torch_us: np.ndarray | None, args: argparse.Namespace, cmd: str) -> str:
    """The markdown report (also returned for printing)."""
    lines = ["# What accuracy costs in time", "",
             f"Generated by `{cmd}` on {time.strftime('%Y-%m-%d')} ({len(args.paths)} scenes of "
             f"`{args.data}`; the method's {points[0].figures.get('criterion', 'offline')} criterion). "
             "Speed: one thread, B = 1; CPU share = per-sample "
             "feature cost x 1000 + decision cost x decisions per second, as a share of one core.", ""]
    if args.heldout_paths and args.lofo:
        lines += [f"Held-out families: {len(args.heldout_paths)} recordings of `{args.heldout}` (a spread subset over "
                  f"the physics families, `--heldout-limit {args.heldout_limit}`), offline criterion as in "
                  "`tools/robustness.py`; each family's recordings are run by the same point (its first Z members, "
                  "its precision and stride) built from the fold trained without that family ("
                  + ", ".join(f"{fam}: `{run}`" for fam, run in args.lofo.items())
                  + "), so the held-out columns are on physics the point's members never saw.", ""]
    elif args.heldout_paths:
        note = heldout_note(points[0].manifest, args.heldout)
        lines += [f"Held-out: {len(args.heldout_paths)} recordings of `{args.heldout}` (a spread subset over the "
                  f"physics families, `--heldout-limit {args.heldout_limit}`), offline criterion as in "
                  "`tools/robustness.py`" + (f"; {note}" if note else "") + ".", ""]
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
        held = any(p.figures.get("heldout") for p in gp)
        lines += [f"## {title}", "",
                  "| point | success | TP/FN | FP/TN | false alarms/h | latency median / p90 (ms) | step median / "
                  "p99 (us) | features (us/sample) | CPU share | x faster than torch eager |"
                  + (" held-out success / balanced | held-out stop+hold alarmed | held-out latency median (ms) |"
                     if held else ""),
                  "|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if held else "")]
        for p in gp:
            f = p.figures
            speed = f"{f['speedup']:.1f}" if f.get("speedup") else "-"
            fah = "-" if f.get("false_alarms_per_hour") is None else f"{f['false_alarms_per_hour']:.0f}"
            name = p.name if group == "ensemble" else f"{p.name}, threshold {p.threshold:.2f}"
            lines.append(f"| {name} | {_pct(f['success'])} | {f['tp']}/{f['fn']} | {f['fp']}/{f['tn']} | {fah} | "
                         f"{_ms(f['latency_median_s'])} / {_ms(f['latency_p90_s'])} | {f['step_median_us']:.0f} / "
                         f"{f['step_p99_us']:.0f} | {f['feature_us']:.1f} | {100 * f['cpu_share']:.1f} % | {speed} |"
                         + (_heldout_cells(f.get("heldout")) if held else ""))
        if held:
            fams = sorted({k for p in gp for k in (p.figures.get("heldout") or {}).get("families", {})})
            lines += ["", "Held-out success per physics family:", "",
                      "| point | " + " | ".join(fams) + " |", "|---|" + "---|" * len(fams)]
            for p in gp:
                fam = (p.figures.get("heldout") or {}).get("families", {})
                lines.append(f"| {p.name} | " + " | ".join(_pct(fam.get(k)) for k in fams) + " |")
        best, kp = knee(gp)
        lines += ["", f"Best success: **{best.name}** ({_pct(best.figures['success'])}). Knee (cheapest within 1 "
                  f"point of it): **{kp.name}** ({_pct(kp.figures['success'])}, CPU share "
                  f"{100 * kp.figures['cpu_share']:.1f} %, step {kp.figures['step_median_us']:.0f} us"
                  + (f", {kp.figures['speedup']:.1f}x faster than the torch eager reference" if kp.figures.get(
                      "speedup") else "") + ").", ""]
    if args.no_retrain:
        lines += ["The retrained group (window 10 / 20 / 40 and median 1 / 5 / 11 / 21, one member per point) was not "
                  "run (`--no-retrain`): it needs its own training runs, and no figures of it are shown here.", ""]
    lines += ["![trade-off](tradeoff.png)", ""]
    return "\n".join(lines)


def place_labels(ax, items: list[tuple[float, float, str, str]], avoid: list[tuple[float, float]],
                 fontsize: float = 7.5) -> None:
    """Label every (x, y, text, colour) without overlaps. Points of one colour that (nearly) coincide on screen
    share one label ("a / b"). For each label try offsets around its point, nearest first,
    and keep the first whose box stays inside the axes and clear of earlier labels and of every marker in
    ``avoid`` (data coordinates); far offsets get a thin leader line. Greedy, like adjustText, no dependency."""
    from matplotlib.text import Text

    fig = ax.figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    marker_px = 9.0
    markers = [ax.transData.transform((x, y)) for x, y in avoid]
    merged: list[list] = []  # [x, y, [texts], colour, display position]
    for x, y, text, colour in items:
        d = ax.transData.transform((x, y))
        for m in merged:
            if m[3] == colour and float(np.hypot(*(m[4] - d))) < marker_px:
                m[2].append(text)
                break
        else:
            merged.append([x, y, [text], colour, d])
    items = [(m[0], m[1], " / ".join(m[2]), m[3]) for m in merged]
    taken: list = []
    dirs = [(1, 0.6), (1, -0.6), (-1, 0.6), (-1, -0.6), (0, 1), (0, -1), (1, 0), (-1, 0)]
    offsets = [(dx * r, dy * r) for r in (6, 12, 20, 30, 42, 56, 72, 90) for dx, dy in dirs]

    def clashes(bb) -> int:
        """0 when the box is clear; else how many things it hits (the frame counts 10)."""
        out = 10 * (bb.x0 < frame.x0 + 2 or bb.x1 > frame.x1 - 2 or bb.y0 < frame.y0 + 2 or bb.y1 > frame.y1 - 2)
        out += sum(bb.overlaps(t) for t in taken)
        return out + sum(bb.x0 - marker_px < mx < bb.x1 + marker_px and bb.y0 - marker_px < my < bb.y1 + marker_px
                         for mx, my in markers)

    def draw(x: float, y: float, text: str, colour: str, dx: float, dy: float):
        ha = "left" if dx > 0 else "right" if dx < 0 else "center"
        va = "bottom" if dy > 0 else "top" if dy < 0 else "center"
        far = abs(dx) > 12 or abs(dy) > 12
        ann = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", ha=ha, va=va,
                          fontsize=fontsize, zorder=5, color=colour,
                          bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
                          arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4"} if far else None)
        ann.update_positions(renderer)  # the text's own box, without the leader line (which ends at its marker)
        return ann, Text.get_window_extent(ann, renderer).padded(4.0)  # the white box around the text, and air

    for x, y, text, colour in sorted(items, key=lambda it: (-it[1], it[0])):
        best: tuple[int, int] | None = None
        for k, (dx, dy) in enumerate(offsets):
            ann, bb = draw(x, y, text, colour, dx, dy)
            ann.remove()
            n = clashes(bb)
            if best is None or n < best[0]:
                best = (n, k)
            if n == 0:
                break
        assert best is not None
        _, bb = draw(x, y, text, colour, *offsets[best[1]])  # the first clear offset, else the least crowded
        taken.append(bb)


SHIPPED = "Z=5 int8 stride 10"
"""The point the daemon runs (slipd/models/slip_ensemble_int8.json: 5 members, int8, a decision every 10 samples)."""


def points_from_report(text: str) -> list[Point]:
    """The ensemble group's points back from a written ``reports/tradeoff.md`` (for ``--plot-only`` where the
    sweep's JSON is not at hand): the figures the plot needs, parsed from the table."""
    rows = [line for line in text.splitlines() if line.startswith("| Z=")]
    points = []
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) < 10 or "/" not in cells[5]:
            continue  # the per-family table
        name = cells[0]
        words = name.split()
        pt = Point(name, "ensemble", "", members=int(words[0][2:]),
                   precision=next((w for w in words if w in ("fp16", "int8")), "fp32"),
                   stride=int(words[words.index("stride") + 1]) if "stride" in words else 40)
        lat = cells[5].split("/")[0].strip()
        fig: dict = {"success": float(cells[1].rstrip(" %")) / 100,
                     "latency_median_s": None if lat == "-" else float(lat) / 1000,
                     "step_median_us": float(cells[6].split("/")[0]),
                     "cpu_share": float(cells[8].rstrip(" %")) / 100,
                     "speedup": None if cells[9] == "-" else float(cells[9])}
        if len(cells) >= 13 and cells[10] != "-":
            held_lat = cells[12]
            fig["heldout"] = {"success": float(cells[10].split("/")[0].strip().rstrip(" %")) / 100,
                              "latency_median_s": None if held_lat == "-" else float(held_lat) / 1000}
        pt.figures = fig
        points.append(pt)
    return points


def plot(points: list[Point], path: Path, own_label: str = "own split", heldout_label: str = "held-out") -> None:
    """Two panels: success against compute per decision (log x, plain ticks) and against detection delay (median
    latency of the detected slips). Marker shape: the stride; colour: the precision; label: the ensemble size Z.
    Filled markers: the own split; hollow: the same point on the held-out recordings, joined by a dotted line. The
    shipped point and the knee are marked and named in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator

    shapes = {40: "o", 20: "^", 10: "D"}
    colours = {"fp32": "tab:blue", "fp16": "tab:orange", "int8": "tab:green"}
    fig, (ax_c, ax_d) = plt.subplots(1, 2, figsize=(14, 6.8), dpi=130)  # labels are measured at the saved dpi
    scored = [p for p in points if p.figures.get("success") is not None and p.group == "ensemble"]
    knee_pt = knee(scored)[1] if scored else None
    shipped = next((p for p in scored if p.name == SHIPPED), None)
    not_shown: list[str] = []
    deferred = []
    for ax, xkey, xscale in ((ax_c, "step_median_us", 1.0), (ax_d, "latency_median_s", 1000.0)):
        labels: list[tuple[float, float, str, str]] = []
        avoid: list[tuple[float, float]] = []
        xs_all: list[float] = []
        ys_all: list[float] = []
        for p in scored:
            f = p.figures
            shape, colour = shapes.get(p.stride, "s"), colours.get(p.precision, "tab:gray")
            y = 100 * f["success"]
            x = None if f.get(xkey) is None else xscale * f[xkey]
            h = f.get("heldout") or {}
            hx = None
            if h.get("success") is not None:
                hx = x if xkey == "step_median_us" else (
                    None if h.get("latency_median_s") is None else xscale * h["latency_median_s"])
            if x is None:
                not_shown.append(p.name)
                continue
            ax.scatter([x], [y], s=60, marker=shape, color=colour, edgecolor="black", lw=0.5, zorder=3)
            labels.append((x, y, f"Z={p.members}", "black"))
            avoid.append((x, y))
            xs_all.append(x)
            ys_all.append(y)
            if p is shipped:
                ax.scatter([x], [y], s=420, marker="*", facecolor="none", edgecolor="crimson", lw=1.4, zorder=4)
            if p is knee_pt and p is not shipped:
                ax.scatter([x], [y], s=300, facecolor="none", edgecolor="0.35", lw=1.2, ls="--", zorder=4)
            if hx is not None:
                hy = 100 * h["success"]
                ax.scatter([hx], [hy], s=50, marker=shape, facecolor="white", edgecolor=colour, lw=1.3, zorder=3)
                ax.plot([x, hx], [y, hy], ":", color=colour, lw=0.8, zorder=2)
                avoid.append((hx, hy))
                xs_all.append(hx)
                ys_all.append(hy)
        if not xs_all:
            continue
        lo, hi = min(ys_all), max(ys_all)
        ax.set_ylim(max(-2.0, lo - 0.15 * (hi - lo + 5)), min(hi + 0.2 * (hi - lo + 5), 110.0))
        ax.set_yticks([t for t in ax.get_yticks() if t <= 100.0 + 1e-9])
        if xkey == "step_median_us":
            ax.set_xscale("log")
            ax.set_xlim(min(xs_all) / 1.5, max(xs_all) * 1.5)
            ticks = [t for t in (20, 30, 50, 70, 100, 150, 200, 300, 500, 700, 1000, 2000)
                     if min(xs_all) / 1.5 <= t <= max(xs_all) * 1.5]
            ax.xaxis.set_major_locator(FixedLocator(ticks))
            ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_locator(NullLocator())
            ax.xaxis.set_minor_formatter(NullFormatter())
        else:
            span = max(xs_all) - min(xs_all) + 10
            ax.set_xlim(min(xs_all) - 0.15 * span, max(xs_all) + 0.15 * span)
        deferred.append((ax, labels, avoid))
        ax.grid(alpha=0.3)
    ax_c.set_xlabel("compute per decision: one step of the ensemble, median (us, one thread; log scale)")
    ax_d.set_xlabel("detection delay: median time from the labelled onset of slip to the alarm (ms)")
    for ax in (ax_c, ax_d):
        ax.set_ylabel("success rate (%)")
    ax_c.set_title("success against compute")
    ax_d.set_title("success against detection delay")
    if not_shown:
        ax_d.text(0.01, 0.01, "no detected slip, not shown: " + ", ".join(not_shown), transform=ax_d.transAxes,
                  fontsize=7, color="0.3", va="bottom")
    handles = [Line2D([], [], marker=m, ls="", color="0.6", markeredgecolor="black",
                      label=f"stride {s}: a decision every {s} samples ({s} ms)") for s, m in shapes.items()]
    handles += [Line2D([], [], marker="s", ls="", color=c, label=f"{prec} weights") for prec, c in colours.items()]
    handles += [Line2D([], [], marker="o", ls="", color="0.6", markeredgecolor="black", label=f"filled: {own_label}"),
                Line2D([], [], marker="o", ls=":", color="0.5", markerfacecolor="white",
                       label=f"hollow: {heldout_label}")]
    if shipped is not None:
        handles.append(Line2D([], [], marker="*", ls="", markersize=16, markerfacecolor="none",
                              markeredgecolor="crimson", label=f"shipped: {shipped.name}"))
    if knee_pt is not None and knee_pt is not shipped:
        handles.append(Line2D([], [], marker="o", ls="", markersize=14, markerfacecolor="none", markeredgecolor="0.35",
                              label=f"knee: {knee_pt.name}, the cheapest within 1 point of the best"))
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle("slipd: what accuracy costs (Z = networks in the ensemble)", fontsize=12)
    fig.tight_layout(rect=(0, 0.13, 1, 0.97))
    for ax, items, avoid in deferred:
        place_labels(ax, items, avoid)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_only(report: Path) -> int:
    """Redraw the plot beside ``report`` from its JSON (written by every sweep), else from the report's table."""
    data = report.with_suffix(".json")
    if data.exists():
        raw = json.loads(data.read_text())
        points = [Point(**{k: v for k, v in p.items()}) for p in raw["points"]]
        own, held = raw.get("own_label", "own split"), raw.get("heldout_label", "held-out")
    else:
        points = points_from_report(report.read_text())
        own = "216 transfer test trials (online criterion)"
        held = "held-out physics family (fold trained without it)"
    if not points:
        raise SystemExit(f"tradeoff: no points in {data if data.exists() else report}")
    out = report.with_suffix(".png")
    plot(points, out, own_label=own, heldout_label=held)
    print(f"wrote {out} ({len(points)} points from {data if data.exists() else report})")
    return 0


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
    ap.add_argument("--heldout", type=Path, default=None,
                    help="a folder of robust test recordings (out/datasets/robust_test): every point is also scored "
                         "on it (offline criterion), per physics family")
    ap.add_argument("--heldout-limit", type=int, default=50,
                    help="held-out recordings used, spread over the physics families (0: all)")
    ap.add_argument("--plot-only", action="store_true",
                    help="only redraw the plot beside --report from its JSON (else from the report's table)")
    ap.add_argument("--lofo", nargs="+", default=[], metavar="FAMILY=RUN",
                    help="leave-one-family-out training runs: each --heldout family is run by the point built from "
                         "the fold trained without it (needs --heldout)")
    args = ap.parse_args(argv)
    if args.plot_only:
        return plot_only(args.report)
    folds: dict[str, Path] = {}
    need = max(p.members for p in sweep_points(args.threshold, False))  # the largest Z of the ensemble group
    for item in args.lofo:
        fam, sep, fold = item.partition("=")
        if not sep or not fam or not fold:
            raise SystemExit(f"tradeoff: --lofo {item!r}: expected FAMILY=RUN")
        have = len(_members(Path(fold)))
        if have < need:
            raise SystemExit(f"tradeoff: --lofo {item}: {have} member_<k>.pt, the sweep needs {need}")
        folds[fam] = Path(fold)
    args.lofo = folds
    if args.lofo and args.heldout is None:
        raise SystemExit("tradeoff: --lofo needs --heldout")
    args.paths = list_recordings(args.data)[:: args.every]
    if not args.paths:
        raise SystemExit(f"tradeoff: no recordings in {args.data}")
    if not list(args.run.glob("member_*.pt")):
        raise SystemExit(f"tradeoff: no member_<k>.pt in {args.run} (see models/MODEL_CARD.md to make them)")
    args.heldout_paths, heldout_tag = [], {}
    if args.heldout is not None:
        from sliplab.robustness import subset, tags

        held = list_recordings(args.heldout) if args.heldout.is_dir() else []
        if not held:
            raise SystemExit(f"tradeoff: no recordings in {args.heldout}")
        heldout_tag = tags(args.heldout)
        args.heldout_paths = subset(held, args.heldout_limit, heldout_tag, "physics_family")
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
        if args.heldout_paths:
            fig["heldout"] = heldout_accuracy(pt, args.heldout_paths, heldout_tag, args.workers)
        pt.figures = fig
        h = fig.get("heldout")
        print(f"{pt.name:<22} success {_pct(fig['success']):>8}  FP {fig['fp']:>3}  latency "
              f"{_ms(fig['latency_median_s']):>5} ms  step {step_med:7.0f} us  CPU {100 * cpu:5.1f} %"
              + (f"  {fig['speedup']:.1f}x torch" if fig["speedup"] else "")
              + (f"  held-out {_pct(h['success'])} (balanced {_pct(h['balanced'])}, stop+hold alarmed "
                 f"{h['stop_alarmed']}/{h['stop']}, latency {_ms(h['latency_median_s'])} ms)" if h else "")
              + f"   ({time.perf_counter() - t0:.0f} s)", flush=True)
    torch_us = np.concatenate(all_torch) if all_torch else None
    report = write_report(points, torch_us, args, cmd)
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(report)
    crit = points[0].figures.get("criterion", "offline")
    own_label = f"{args.data.name} ({crit} criterion)"
    heldout_label = (f"held-out family (fold trained without it), {args.heldout.name}" if args.lofo else
                     f"{args.heldout.name} (offline criterion)") if args.heldout_paths else "held-out"
    plot(points, args.report.with_suffix(".png"), own_label=own_label, heldout_label=heldout_label)
    data = json.dumps({"command": cmd, "own_label": own_label, "heldout_label": heldout_label,
                       "torch_reference_us": None if torch_us is None else
                       {"median": float(np.median(torch_us)), "p99": float(np.percentile(torch_us, 99))},
                       "points": [asdict(p) for p in points]}, indent=1) + "\n"
    (args.cache / "tradeoff.json").write_text(data)
    args.report.with_suffix(".json").write_text(data)  # beside the report: --plot-only redraws from it
    print(report)
    print(f"wrote {args.report}, {args.report.with_suffix('.png')}, {args.report.with_suffix('.json')} and "
          f"{args.cache / 'tradeoff.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
