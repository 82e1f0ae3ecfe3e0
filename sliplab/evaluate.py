"""Evaluate a slip detector (the ONNX ensemble or a heuristic baseline) with the method's metrics.

    python tools/evaluate.py --model out/reference.json --set offline --split test
    python tools/evaluate.py --baseline deceleration --baseline-params slipd/models/baselines.json --set transfer
    python tools/evaluate.py --model slipd/models/slip_ensemble.json --recordings DIR \
        --json out/eval.json --plots out/eval
    python tools/evaluate.py --tune-baselines --set offline          # grid search on <set>_train only

Every recording is streamed sample by sample through the daemon's own decision path
(``slipd.detect.detector.Detector``: features -> ensemble -> decision) or through the baseline detector, and
scored by ``sliplab.metrics`` (offline success, confusion matrix, latency, online success and D_norm
for gripper scenes, false alarms per hour on no-slip scenes).

Data sets follow ``tools/make_dataset.py``'s layout: ``<data-root>/<set>_<split>/*.npz``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

from slipd.detect.baselines import (
    BASELINES,
    CONFIRMED_RULE,
    DecelerationParams,
    FrontEndParams,
    ReferencePillarParams,
    SpeedFrontEnd,
    baseline_offset,
    baseline_samples,
    confirm_flags,
    deceleration_flags,
    load_params,
    make_baseline,
    recent_max,
    reference_pillar_flags,
    save_params,
)
from slipd.detect.features import FeatureSpec, stretch_offset
from slipd.recording import Recording, list_recordings
from sliplab.metrics import (
    SceneResult,
    SceneTruth,
    Summary,
    Trace,
    confusion,
    evaluate_scene,
    scored_outcome,
    summarize,
)
from sliplab.paths import ROOT

DEFAULT_BASELINES_JSON = ROOT / "slipd" / "models" / "baselines.json"


# --------------------------------------------------------------------------- data
def dataset_dir(root: Path, set_name: str, split: str) -> Path:
    """``<root>/<set>_<split>``; if missing, ask the simulator to make it, else explain how."""
    folder = Path(root) / f"{set_name}_{split}"
    if folder.is_dir() and list_recordings(folder):
        return folder
    try:
        from slipd.sim.datasets import write_dataset  # the simulator is optional for evaluation
    except ImportError:
        write_dataset = None
    if write_dataset is not None:
        print(f"{folder} is missing: generating it (slipd.sim.datasets.write_dataset) ...", file=sys.stderr)
        index = write_dataset(set_name, split, folder)
        print(f"  {index['count']} recordings written", file=sys.stderr)
        if list_recordings(folder):
            return folder
    raise SystemExit(
        f"no recordings in {folder}; make them with:\n"
        f"  python tools/make_dataset.py --set {set_name} --split {split} --out {folder}"
    )


def tare_args(rec: Recording, spec: FeatureSpec) -> dict:
    """Detector tare arguments: ``tare_samples=n`` for a meta stretch [0, n], else an explicit offset."""
    a, b = (int(v) for v in rec.meta.get("tare_samples", spec.tare_samples))
    if a == 0 and b > 0:
        return {"tare_samples": min(b, len(rec))}
    return {"offset": stretch_offset(rec.force, (a, b))}


def tare_stretch(rec: Recording, spec: FeatureSpec | None = None) -> tuple[int, int]:
    """The unloaded stretch [start, stop) of a recording (meta ``tare_samples``, else the spec's default)."""
    default = (spec or FeatureSpec()).tare_samples
    a, b = (int(v) for v in rec.meta.get("tare_samples", default))
    return a, min(b, len(rec))


# --------------------------------------------------------------------------- detectors
NO_LIMIT_GUARD_HELP = ("score a model on its own decision rule, without the limit guard (decision.limit_guard, on in "
                       "the default config): what its members learned")
"""The ``--no-limit-guard`` option's help, the same in every tool that scores models."""


class ModelRunner:
    """Streams recordings through ``Detector`` with the ensemble of a manifest."""

    def __init__(self, manifest: str, hysteresis: float = 0.0, threshold: float | None = None,
                 stride: int | None = None, limit_guard: bool = True) -> None:
        from slipd.config.schema import DecisionConfig
        from slipd.detect.build import build_decision  # onnxruntime only when a model is evaluated
        from slipd.detect.ensemble import Ensemble

        self.ensemble = Ensemble.load(manifest)
        self.spec = self.ensemble.feature_spec
        if stride is not None:  # decisions every `stride` samples through window/stride phase-shifted streams
            self.spec = self.spec.with_(stride=0 if stride == self.spec.window else stride)
        # The daemon's default decision rule (the config's defaults), the threshold and hysteresis as given;
        # ``limit_guard`` False: the model's own rule without the limit guard (what the members learned).
        rule = DecisionConfig(threshold=threshold, hysteresis=hysteresis)
        if not limit_guard:
            rule = rule.model_copy(update={"limit_guard": None})
        self.decision = build_decision(rule, self.ensemble.threshold)
        self.threshold = self.decision.threshold
        self.press_rise = rule.press_rise
        self.label = f"model {manifest}" + ("" if limit_guard else " (without the limit guard)")

    def trace(self, rec: Recording, zero_error: np.ndarray | None = None) -> Trace:
        """Decisions of one recording; ``zero_error`` [9, 3]: every reading after the tare's stretch that much low, as
        from a zero taken that much high (``sliplab.zero_error``; the stretch itself is left as it is, so the tare and
        the decisions it holds back are the same as without it)."""
        from slipd.detect.detector import Detector, run_recording

        self.ensemble.reset()
        self.decision.reset()
        force = rec.force
        if zero_error is not None:
            force = force.copy()
            force[tare_stretch(rec, self.spec)[1]:] -= np.asarray(zero_error, np.float32)
        det = Detector(self.ensemble, self.decision, self.spec, press_rise=self.press_rise, **tare_args(rec, self.spec))
        return Trace.from_detections(run_recording(det, force, rec.t_us), rec.t_us)


class ConfirmedRunner(ModelRunner):
    """Streams recordings through ``ConfirmedDetector``: the model's decisions and the reference-pillar rule (the
    shipped parameters of ``params``, ``frontend``) confirmed at ``level`` within ``within_s`` (the daemon's
    ``decision.confirm_rule``); each part tared on the recording's unloaded stretch as when evaluated alone."""

    def __init__(self, manifest: str, level: float, within_s: float, params: dict, frontend: dict,
                 limit_guard: bool = True) -> None:
        super().__init__(manifest, limit_guard=limit_guard)
        make_baseline(CONFIRMED_RULE, params, frontend)  # validates the parameters up front
        self.level, self.within_us = float(level), round(within_s * 1e6)
        self.params, self.frontend = params, frontend
        self.label = f"reference_pillar confirmed by {self.label} at {level:g}"

    def trace(self, rec: Recording, zero_error: np.ndarray | None = None) -> Trace:
        """Decisions of one recording (``zero_error`` is not supported: the rule has no such input)."""
        from slipd.detect.baselines import ReferencePillarDetector
        from slipd.detect.confirmed import ConfirmedDetector
        from slipd.detect.detector import Detector

        if zero_error is not None:
            raise ValueError("ConfirmedRunner: zero_error is not supported")
        self.ensemble.reset()
        self.decision.reset()
        model = Detector(self.ensemble, self.decision, self.spec, press_rise=self.press_rise,
                         **tare_args(rec, self.spec))
        offset = baseline_offset(rec.force, rec.disp, tare_stretch(rec))
        rule = make_baseline(CONFIRMED_RULE, self.params, self.frontend, offset)
        assert isinstance(rule, ReferencePillarDetector)
        return _trace_in_blocks(ConfirmedDetector(model, [rule], self.level, self.within_us), rec)


TRACE_BLOCK = 1000
"""Samples a heuristic takes per call when a recording is streamed through it (``_HeuristicDetector.push_many``)."""


def _trace_in_blocks(det, rec: Recording) -> Trace:
    """A recording through a detector with the tip displacements, ``TRACE_BLOCK`` samples a call (the same detections
    as a push per sample)."""
    dets = []
    for start in range(0, len(rec), TRACE_BLOCK):
        end = start + TRACE_BLOCK
        dets += [d for _, d in det.push_many(rec.force[start:end], rec.t_us[start:end], rec.disp[start:end])]
    return Trace.from_detections(dets, rec.t_us)


class BaselineRunner:
    """Streams recordings through a heuristic baseline detector (with the recorded tip displacements)."""

    def __init__(self, name: str, params: dict | None = None, frontend: dict | None = None) -> None:
        make_baseline(name, params, frontend)  # validates the parameters up front
        self.name, self.params, self.frontend = name, params or {}, frontend or {}
        self.threshold = 0.5
        self.label = f"baseline {name} {json.dumps(self.params, sort_keys=True)}"

    def trace(self, rec: Recording) -> Trace:
        """Decisions of one recording."""
        offset = baseline_offset(rec.force, rec.disp, tare_stretch(rec))
        return _trace_in_blocks(make_baseline(self.name, self.params, self.frontend, offset), rec)


RUNNERS = {"model": ModelRunner, "baseline": BaselineRunner, "confirmed": ConfirmedRunner}
"""``evaluate_paths``' kinds of detector."""
_RUNNER = None


def _init_worker(kind: str, args: tuple) -> None:
    global _RUNNER
    _RUNNER = RUNNERS[kind](*args)


def _eval_one(path: str) -> tuple[SceneResult, Trace, SceneTruth]:
    rec = Recording.load(path)
    truth = SceneTruth.from_recording(rec, Path(path).stem)
    trace = _RUNNER.trace(rec)
    return evaluate_scene(truth, trace), trace, truth


def evaluate_paths(
    paths: list[Path], kind: str, args: tuple, workers: int = 1, progress: bool = True
) -> list[tuple[SceneResult, Trace, SceneTruth]]:
    """Evaluate every recording; ``kind`` one of ``RUNNERS`` ("model": manifest, hysteresis, threshold, stride,
    limit guard; "baseline": name, params, frontend; "confirmed": ``ConfirmedRunner``'s)."""
    strs = [str(p) for p in paths]
    if workers <= 1:
        _init_worker(kind, args)
        out = []
        for i, p in enumerate(strs):
            out.append(_eval_one(p))
            if progress and (i + 1) % 20 == 0:
                print(f"  {i + 1}/{len(strs)}", file=sys.stderr)
        return out
    with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(kind, args)) as pool:
        return list(pool.map(_eval_one, strs, chunksize=4))


# --------------------------------------------------------------------------- report
def _fmt(v, unit: str = "", scale: float = 1.0, digits: int = 1) -> str:
    if v is None:
        return "-"
    return f"{v * scale:.{digits}f}{unit}"


def report_rows(summary: Summary, online: bool) -> list[tuple[str, str]]:
    """(figure, value) rows of the printed table."""
    off = summary.offline
    rows = [
        ("scenes", str(summary.n_scenes)),
        ("offline success (TP+TN)/N", _fmt(off.success_rate, " %", 100)),
        ("balanced success", _fmt(off.balanced_success, " %", 100)),
        ("confusion slip: TP / FN", f"{off.tp} / {off.fn}"),
        ("confusion stop: FP / TN", f"{off.fp} / {off.tn}"),
        ("failures", ", ".join(f"{k} {v}" for k, v in sorted(summary.offline_failures.items())) or "-"),
        ("slip scenes without onset (not scored)", str(summary.offline_unlabelled)),
        ("latency median (TP)", _fmt(summary.latency_s.median, " ms", 1000)),
        ("latency p90 (TP)", _fmt(summary.latency_s.p90, " ms", 1000)),
        ("latency mean (TP)", _fmt(summary.latency_s.mean, " ms", 1000)),
    ]
    if online and summary.online is not None:
        on = summary.online
        rows += [
            ("online success", _fmt(on.success_rate, " %", 100)),
            ("online confusion slip: TP / FN", f"{on.tp} / {on.fn}"),
            ("online confusion stop: FP / TN", f"{on.fp} / {on.tn}"),
            ("online failures", ", ".join(f"{k} {v}" for k, v in sorted(summary.online_failures.items())) or "-"),
            ("D_norm at detection median", _fmt(summary.d_norm.median, "", 1, 2)),
            ("D_norm p10 - p90", f"{_fmt(summary.d_norm.p10, '', 1, 2)} - {_fmt(summary.d_norm.p90, '', 1, 2)}"),
        ]
    rows += [
        ("no-slip time", _fmt(summary.no_slip_hours, " s", 3600)),
        ("false alarms (rising edges)", str(summary.false_alarms)),
        ("false alarms per hour", _fmt(summary.false_alarms_per_hour, "", 1, 0)),
    ]
    return rows


def print_table(title: str, rows: list[tuple[str, str]]) -> None:
    """Print with rich when available, else plain text."""
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        print(title)
        for k, v in rows:
            print(f"  {k:<34} {v}")
        return
    table = Table(title=title)
    table.add_column("figure")
    table.add_column("value", justify="right")
    for k, v in rows:
        table.add_row(k, v)
    Console().print(table)


# --------------------------------------------------------------------------- plots
def write_plots(folder: Path, results, threshold: float, online: bool, n_traces: int = 4) -> list[Path]:
    """Probability traces (figure 4a style), the confusion matrix and the latency histogram as PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    slips = [r for r in results if r[2].is_slip][: max(1, n_traces - 1)]
    stops = [r for r in results if not r[2].is_slip][:1]
    for res, trace, truth in slips + stops:
        fig, ax = plt.subplots(figsize=(7, 3))
        ax.plot(trace.t_s, trace.p_slip, drawstyle="steps-post", label="P(slip)")
        ax.axhline(threshold, color="k", ls="--", lw=0.8, label="threshold")
        if truth.onset_s is not None:
            ax.axvline(truth.onset_s, color="tab:orange", label="incipient-slip onset")
        gross = truth.online_gross_s if online else truth.gross_slip_s
        if gross is not None:
            ax.axvline(gross, color="tab:red", label="gross slip")
        if truth.motion_start_s is not None:
            ax.axvline(truth.motion_start_s, color="tab:gray", ls=":", label="motion start")
        if res.first_alarm_s is not None:
            ax.plot([res.first_alarm_s], [threshold], "kv", label="first alarm")
        ax.set(xlabel="time (s)", ylabel="P(slip)", ylim=(-0.02, 1.02),
               title=f"{truth.name} ({truth.kind}, {truth.motion or '-'}): {res.offline_outcome}")
        ax.legend(fontsize=7, loc="upper left")
        fig.tight_layout()
        path = folder / f"trace_{truth.name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    scenes = [r[0] for r in results]
    mats = [("offline", confusion(scenes))] + ([("online", confusion(scenes, online=True))] if online else [])
    for name, c in mats:
        m = np.array([[c.tp, c.fn], [c.fp, c.tn]])
        fig, ax = plt.subplots(figsize=(3.6, 3.2))
        ax.imshow(m, cmap="Blues")
        for (i, j), v in np.ndenumerate(m):
            ax.text(j, i, str(v), ha="center", va="center", color="white" if v > m.max() / 2 else "black")
        ax.set_xticks([0, 1], ["detected", "not detected"])
        ax.set_yticks([0, 1], ["slip", "stop"])
        ax.set_title(f"{name}: success {_fmt(c.success_rate, ' %', 100)}")
        fig.tight_layout()
        path = folder / f"confusion_{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    lat = [r.latency_s * 1000 for r in scenes if r.latency_s is not None]
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.hist(lat, bins=30, color="tab:blue")
    ax.set(xlabel="first alarm - labelled onset (ms)", ylabel="slip sequences (TP)", title=f"latency, n={len(lat)}")
    fig.tight_layout()
    path = folder / "latency.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    if online:
        dn = [r.d_norm for r in scenes if r.d_norm is not None and r.online_outcome == "success"]
        fig, ax = plt.subplots(figsize=(5, 3))
        ax.hist(dn, bins=20, range=(0, 1), color="tab:green")
        ax.set(xlabel="D_norm at detection", ylabel="slip trials (success)", title=f"D_norm, n={len(dn)}")
        fig.tight_layout()
        path = folder / "d_norm.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


# --------------------------------------------------------------------------- baseline tuning
REFERENCE_GRID = {
    "ratio": [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
    "min_ref_speed": [0.1, 0.25, 0.5, 1.0, 2.0],
    "min_pillars": [1, 2, 3],
    "confirm": [1, 2, 4, 6],
}
DECELERATION_GRID = {
    "drop": [0.1, 0.15, 0.2, 0.3, 0.4, 0.5],
    "min_peak_speed": [0.25, 0.5, 1.0, 2.0],
    "moving_speed": [0.25, 0.5, 1.0, 2.0],
    "memory_s": [0.05, 0.1, 0.2, 0.4],
    "confirm": [2, 4, 6, 8],
}


def _tuning_features(paths: list[Path], frontend: FrontEndParams, pad: int) -> dict:
    """Speeds, normal forces and decision times of every recording, computed once for the whole grid.

    The recordings are concatenated with ``pad`` rows of no contact between them: a row out of contact
    flags nothing and resets ``confirm``, and zero speeds keep a recording's ``recent_max`` from seeing
    the previous one, so one vectorised pass over the concatenation equals one pass per recording.
    """
    speeds, fzs, times, starts, truths = [], [], [], [], []
    at = 0
    for p in paths:
        rec = Recording.load(p)
        truths.append(SceneTruth.from_recording(rec, p.stem))
        fe = SpeedFrontEnd(frontend, baseline_offset(rec.force, rec.disp, tare_stretch(rec)))
        speed, fz, ends = fe.batch(baseline_samples(rec.force, rec.disp))
        speeds += [np.zeros((pad, speed.shape[1]), np.float32), speed]
        fzs += [np.zeros((pad, fz.shape[1]), np.float32), fz]
        times += [np.full(pad, np.nan), (rec.t_us[ends] - rec.t_us[0]) / 1e6]
        starts.append(at + pad)
        at += pad + len(speed)
    return {"speed": np.concatenate(speeds), "fz": np.concatenate(fzs), "t_s": np.concatenate(times),
            "start": np.array([*starts, at]), "truth": truths}


def _grid_memory(grid: dict, frontend: FrontEndParams) -> int:
    return max(max(1, round(m * frontend.rate_hz / frontend.stride)) for m in grid.get("memory_s", [0.0]))


def tune_baseline(name: str, feats: dict, frontend: FrontEndParams, grid: dict | None = None,
                  objective: str = "balanced") -> dict:
    """Grid search of one baseline's thresholds; objective: balanced success (the online criterion on gripper
    trials, the offline one on hexapod scenes), then median |latency|.

    Uses the same vectorised rule functions as the detectors' batch path (proved equal to streaming).
    """
    grid = grid or (REFERENCE_GRID if name == "reference_pillar" else DECELERATION_GRID)
    pcls = ReferencePillarParams if name == "reference_pillar" else DecelerationParams
    keys = sorted(grid)
    truths = feats["truth"]
    starts, ends = feats["start"][:-1], feats["start"][1:]
    # Slips the criterion cannot score (no onset offline, no motion start online) are left out.
    n_slip = sum(t.is_slip and (t.motion_start_s if t.family == "gripper" else t.onset_s) is not None for t in truths)
    n_stop = sum(not t.is_slip for t in truths)
    best = None
    peaks_cache: dict[int, np.ndarray] = {}
    for values in itertools.product(*(grid[k] for k in keys)):
        params = pcls(**dict(zip(keys, values)))
        if name == "reference_pillar":
            flag, _ = reference_pillar_flags(feats["speed"], feats["fz"], params, frontend.contact_n)
        else:
            mem = max(1, round(params.memory_s * frontend.rate_hz / frontend.stride))
            if mem not in peaks_cache:
                peaks_cache[mem] = recent_max(feats["speed"], mem)
            flag, _ = deceleration_flags(feats["speed"], peaks_cache[mem], feats["fz"], params, frontend.contact_n)
        idx = np.flatnonzero(confirm_flags(flag, params.confirm))
        pos = np.searchsorted(idx, starts)
        tp = tn = 0
        latencies = []
        for k, truth in enumerate(truths):
            first = None
            if pos[k] < len(idx) and idx[pos[k]] < ends[k]:
                first = float(feats["t_s"][idx[pos[k]]])
            o = scored_outcome(truth, first)  # online for gripper trials, offline for hexapod scenes
            tp += o == "tp"
            tn += o == "tn"
            if o == "tp" and truth.onset_s is not None:
                latencies.append(abs(first - truth.onset_s))
        rates = [r for r in (tp / n_slip if n_slip else None, tn / n_stop if n_stop else None) if r is not None]
        balanced, plain = sum(rates) / len(rates), (tp + tn) / (n_slip + n_stop)
        score = balanced if objective == "balanced" else plain
        lat = float(np.median(latencies)) if latencies else float("inf")
        key = (score, -lat)
        if best is None or key > best[0]:
            best = (key, params, {"balanced_success": balanced, "success_rate": plain,
                                  "median_abs_latency_s": lat if latencies else None})
    _, params, figures = best
    return {"params": asdict(params), "frontend": asdict(frontend), "train_figures": figures}


def run_tuning(args) -> int:
    """``--tune-baselines``: tune on ``<set>_train`` only and write the JSON."""
    folder = Path(args.recordings) if args.recordings else dataset_dir(Path(args.data_root), args.set, "train")
    paths = list_recordings(folder)
    frontend = FrontEndParams()
    t0 = time.perf_counter()
    feats = _tuning_features(paths, frontend, pad=_grid_memory(DECELERATION_GRID, frontend) + 1)
    names = [args.baseline] if args.baseline else sorted(BASELINES)
    out_path = Path(args.baseline_params or DEFAULT_BASELINES_JSON)
    tuned = json.loads(out_path.read_text()) if out_path.exists() else {}
    for name in names:
        entry = tune_baseline(name, feats, frontend, objective=args.objective)
        entry["tuned_on"] = {"folder": str(folder), "recordings": len(paths),
                             "objective": f"{args.objective} success (online criterion on gripper trials)",
                             "grid": REFERENCE_GRID if name == "reference_pillar" else DECELERATION_GRID}
        index = folder / "index.json"
        if index.exists():
            meta = json.loads(index.read_text())
            entry["tuned_on"].update({k: meta.get(k) for k in ("set", "split", "seed", "generator")})
        tuned[name] = entry
        print(f"{name}: {entry['params']}  train {entry['train_figures']}")
    save_params(out_path, tuned)
    print(f"wrote {out_path} ({time.perf_counter() - t0:.1f} s)")
    return 0


# --------------------------------------------------------------------------- main
def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = p.add_mutually_exclusive_group()
    what.add_argument("--model", help="model manifest (.json) loadable by slipd.detect.ensemble.Ensemble.load")
    what.add_argument("--baseline", choices=sorted(BASELINES), help="a heuristic baseline instead of a model")
    p.add_argument("--baseline-params", help=f"tuned parameters JSON (default {DEFAULT_BASELINES_JSON} if present)")
    p.add_argument("--set", choices=("offline", "transfer"), default="offline")
    p.add_argument("--split", choices=("train", "test"), default="test")
    p.add_argument("--data-root", default=str(ROOT / "out" / "datasets"))
    p.add_argument("--recordings", help="a folder of recordings instead of --set/--split")
    p.add_argument("--online", action="store_true", help="report online metrics (default for --set transfer)")
    p.add_argument("--threshold", type=float, default=None, help="override the manifest's threshold")
    p.add_argument("--hysteresis", type=float, default=0.0)
    p.add_argument("--no-limit-guard", action="store_true", help=NO_LIMIT_GUARD_HELP)
    p.add_argument("--stride", type=int, default=None,
                   help="override the manifest's decision stride (a divisor of the window)")
    p.add_argument("--workers", type=int, default=1, help="processes (2 at most on the shared machine)")
    p.add_argument("--json", help="write every figure and per-scene result here")
    p.add_argument("--plots", help="write PNG plots into this folder")
    p.add_argument("--tune-baselines", action="store_true", help="grid-search the baselines on the train split")
    p.add_argument("--objective", choices=("balanced", "success"), default="balanced",
                   help="--tune-baselines: maximise balanced success (mean of slip and stop rates) or plain success "
                        "(TP+TN)/N, the figure the results table reports and tune_threshold maximises for models")
    p.add_argument("--contact", action="store_true",
                   help="score the contact state instead: per-pillar slip F1 and the friction estimate against the "
                        "simulator's truth (sliplab.contact_eval; --sets, --split, --count, --model, --json)")
    p.add_argument("--record-manifest", action="store_true",
                   help="with --model: merge the summary into the manifest's metrics (key eval_<data folder>)")
    p.add_argument("--by-motion", action="store_true",
                   help="also one line per motion (lift, push, ...): online success and D_norm at detection")
    return p


def print_by_motion(scenes: list[SceneResult]) -> None:
    """One line per motion of the recordings: the online figures of its slip and stop trials, and how far the object
    had travelled towards the late criterion when the alarm came (D_norm, caught slips)."""
    print(f"{'motion':<16} {'slips in time':>14} {'stops alarmed':>14} {'D_norm median':>14} {'p90':>6}")
    for motion in sorted({r.motion for r in scenes}):
        sub = summarize([r for r in scenes if r.motion == motion])
        on = sub.online
        if on is None:
            continue
        print(f"{motion:<16} {f'{on.tp}/{on.tp + on.fn}':>14} {f'{on.fp}/{on.fp + on.tn}':>14} "
              f"{_fmt(sub.d_norm.median, '', 1, 2):>14} {_fmt(sub.d_norm.p90, '', 1, 2):>6}")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--contact" in argv:
        # The contact state against the simulator's truth (per-pillar slip F1, friction): its own options.
        from sliplab.contact_eval import main as contact_main

        return contact_main([a for a in argv if a != "--contact"])
    args = _parser().parse_args(argv)
    if args.tune_baselines:
        return run_tuning(args)
    if not args.model and not args.baseline:
        _parser().error("give --model PATH.json, --baseline NAME or --tune-baselines")
    folder = Path(args.recordings) if args.recordings else dataset_dir(Path(args.data_root), args.set, args.split)
    paths = list_recordings(folder)
    if not paths:
        raise SystemExit(f"no recordings (.npz / .csv) in {folder}")
    if args.model:
        kind, rargs = "model", (args.model, args.hysteresis, args.threshold, args.stride, not args.no_limit_guard)
        label = f"model {args.model}"
        threshold = args.threshold
        if threshold is None:
            threshold = json.loads(Path(args.model).read_text()).get("threshold", 0.5)
    else:
        params, frontend = {}, {}
        src = Path(args.baseline_params) if args.baseline_params else DEFAULT_BASELINES_JSON
        if args.baseline_params or src.exists():
            params, frontend = load_params(src, args.baseline)
        kind, rargs = "baseline", (args.baseline, params, frontend)
        label = f"baseline {args.baseline} {json.dumps(params, sort_keys=True)}"
        threshold = 0.5
    t0 = time.perf_counter()
    results = evaluate_paths(paths, kind, rargs, workers=max(1, args.workers))
    elapsed = time.perf_counter() - t0
    # Online figures for gripper trials (or when asked); hexapod scenes have no online criterion.
    online = args.online or (args.set == "transfer" and not args.recordings)
    online = online or any(r[2].family == "gripper" for r in results)
    summary = summarize([r[0] for r in results])
    print_table(f"{label} on {folder} ({len(paths)} recordings, {elapsed:.1f} s)", report_rows(summary, online))
    if args.by_motion and online:
        print_by_motion([r[0] for r in results])
    if args.json:
        out = {
            "detector": label,
            "data": str(folder),
            "threshold": threshold,
            "online_reported": online,
            "seconds": elapsed,
            "summary": summary.to_dict(),
            "scenes": [r[0].to_dict() for r in results],
            "truth": [r[2].to_dict() for r in results],
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {args.json}")
    if args.plots:
        for path in write_plots(Path(args.plots), results, threshold, online):
            print(f"wrote {path}")
    if args.record_manifest:
        if not args.model:
            _parser().error("--record-manifest needs --model")
        from slipd.detect.manifest import update_metrics

        key = f"eval_{folder.name}"
        rec = summary.to_dict()
        # The headline scalar beside the full summary (``slipd models`` prints scalars): online success where the
        # set has gripper trials, else offline success.
        online = rec.get("online")
        name, head = (f"{folder.name}_online_success", online) if online else (f"{folder.name}_success",
                                                                               rec.get("offline"))
        scalar = {name: round(head["success_rate"], 4)} if head and head.get("success_rate") is not None else {}
        update_metrics(args.model, {key: {"data": str(folder), "threshold": threshold, **rec}, **scalar})
        print(f"recorded {key} in {args.model}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
