"""How far the daemon's decisions move when the sensor's zero is a little off.

A sensor's zero is never exact: its bias command averages noise, and the pillars drift once it is taken (temperature,
the elastomer's creep). Per folder of recordings, each recording streams through the model's detector with the default
config's decision rule (as ``tools/evaluate.py`` scores it), once as tared and ``--draws`` times more with every
pillar's zero off by a draw of N(0, sigma) on each axis (``--sigma FZ FT``: along the normal, along each tangential
axis; the default is one sample of the sensor's noise, the upper bound of the PapillArray's, which is what a bias taken
from a single sample leaves). Per recording kind (``meta["kind"]``) it prints the scored outcomes as tared and over the
draws: slips caught in time, recordings where nothing slips that alarm, and the recordings whose verdict changes in
some draw, the worst first.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from sliplab.augment import SENSOR_NOISE_N, zero_errors
from sliplab.metrics import NO_SLIP_KINDS, SLIP_KINDS, SceneTruth, scored_outcome


@dataclass
class KindTally:
    """One recording kind's outcomes: as tared, and summed over the draws."""

    recordings: int = 0
    hits: int = 0
    """As tared: slips caught in time (scored "tp"), or, for the kinds where nothing slips, recordings that alarm."""
    draw_hits: int = 0
    """The same over every draw."""
    draws: int = 0
    changed: list[tuple[str, float]] = field(default_factory=list)
    """(recording, share of its draws whose verdict differs from the tared one), for those where some draw differs."""


def verdicts(path: str, errors: np.ndarray) -> tuple[str, bool, list[bool]] | None:
    """One recording (in a worker) as tared and under each zero error: (kind, verdict as tared, verdict per error).
    A verdict is "caught in time" for a slip (scored "tp") and "alarmed" where nothing slips; None for a recording the
    scoring leaves out (a partial slip, a slip without a labelled onset)."""
    from slipd.recording import Recording
    from sliplab import evaluate

    runner = evaluate._RUNNER  # (the evaluation's worker runner: ``evaluate._init_worker``)
    assert isinstance(runner, evaluate.ModelRunner)
    rec = Recording.load(path)
    truth = SceneTruth.from_recording(rec, Path(path).stem)
    kind = str(rec.meta.get("kind", "unknown"))

    def verdict(first_alarm_s: float | None) -> bool | None:
        if kind in SLIP_KINDS:
            out = scored_outcome(truth, first_alarm_s)
            return None if out is None else out == "tp"
        return None if kind not in NO_SLIP_KINDS else first_alarm_s is not None

    tared = verdict(runner.trace(rec).first_alarm_s())
    if tared is None:
        return None
    return kind, tared, [bool(verdict(runner.trace(rec, zero_error=e).first_alarm_s())) for e in errors]


def scan(folder: Path, manifest: str, limit_guard: bool, sigma: tuple[float, float], draws: int, seed: int,
         limit: int = 0, workers: int = 1) -> dict[str, Any]:
    """Every recording of ``folder`` (the first ``limit``, 0: all) as tared and under ``draws`` zero errors each."""
    from concurrent.futures import ProcessPoolExecutor

    from slipd.recording import list_recordings
    from sliplab.evaluate import _init_worker

    paths = list_recordings(folder)
    paths = paths[:limit] if limit else paths
    errors = [zero_errors(np.random.default_rng([seed, i]), sigma, draws) for i in range(len(paths))]
    tally: dict[str, KindTally] = {}
    runner_args = (manifest, 0.0, None, None, limit_guard)  # (ModelRunner's: the default rule, the model's threshold)
    with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=("model", runner_args)) as pool:
        done = pool.map(verdicts, [str(p) for p in paths], errors)
        for path, out in zip(paths, tqdm(done, total=len(paths), desc=folder.name, unit="rec")):
            if out is None:
                continue
            kind, tared, drawn = out
            t = tally.setdefault(kind, KindTally())
            t.recordings += 1
            t.hits += tared
            t.draw_hits += sum(drawn)
            t.draws += len(drawn)
            differ = sum(v != tared for v in drawn)
            if differ:
                t.changed.append((path.stem, differ / len(drawn)))
    label = f"model {manifest}" + ("" if limit_guard else " (without the limit guard)")
    return {"data": str(folder), "model": label, "sigma_n": list(sigma), "draws": draws, "seed": seed,
            "kinds": {k: {"recordings": t.recordings, "hits": t.hits, "draw_hits": t.draw_hits, "draws": t.draws,
                          "changed": sorted(t.changed, key=lambda c: -c[1])} for k, t in sorted(tally.items())}}


def report(result: dict[str, Any]) -> str:
    """One folder's result as printed lines."""
    sz, st = result["sigma_n"]
    lines = [f"{result['data']}: {result['draws']} zero errors per recording, sigma {sz:g} N normal, {st:g} N "
             f"tangential ({result['model']})"]
    for kind, k in result["kinds"].items():
        what = "caught in time" if kind in SLIP_KINDS else "alarmed"
        n, d = k["recordings"], k["draws"]
        share = k["draw_hits"] / d if d else 0.0
        worst = ", ".join(f"{name} {s:.0%}" for name, s in k["changed"][:3])
        lines.append(f"  {kind:8s} {n:4d} recordings, {what}: {k['hits']} as tared, {share:.1%} of the draws "
                     f"({k['draw_hits']}/{d}); the verdict changes in some draw for {len(k['changed'])}"
                     + (f" (most often: {worst})" if worst else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from sliplab.evaluate import NO_LIMIT_GUARD_HELP

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="slipd/models/slip_ensemble_int8.json", help="model manifest")
    p.add_argument("--data", type=Path, nargs="+", required=True, help="folders of recordings")
    p.add_argument("--sigma", type=float, nargs=2, default=SENSOR_NOISE_N, metavar=("FZ", "FT"),
                   help="the zero errors' standard deviation in N, normal and tangential (default: one sample's noise)")
    p.add_argument("--draws", type=int, default=10, help="zero errors per recording")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--limit", type=int, default=0, help="the first N recordings of each folder (0: all)")
    p.add_argument("--workers", type=int, default=1, help="processes")
    p.add_argument("--no-limit-guard", action="store_true", help=NO_LIMIT_GUARD_HELP)
    p.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = p.parse_args(argv)
    if args.draws < 1 or min(args.sigma) < 0:
        p.error("--draws must be at least 1 and --sigma not negative")
    results = []
    for folder in args.data:
        results.append(scan(folder, args.model, not args.no_limit_guard, tuple(args.sigma), args.draws, args.seed,
                            args.limit, args.workers))
        print(report(results[-1]), flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    return 0
