"""Grasp stabilisation on the closed-loop rig: the method's table 1 experiment, regenerated.

    python tools/stabilize.py [--reps 3] [--config config/sim.yaml] [--out reports/stabilize.md]

Six objects x two scenarios (under-gripped lift, off-centre lift) x ``--reps`` repetitions (different
seeds), each run through ``slipd.sim.rig.run_rig``: the real daemon as its own process against the
emulated PapillArray, MX-28 and UR controller with the physics in the loop. Every run is repeated with
the reaction disabled (the daemon detects but does nothing: what happens without slipd). Writes a
markdown report with the per-object table (object translation and rotation relative to the finger
when the grasp became secure, mean +- sd), next to the paper's figures, and the raw runs as JSON.

    python tools/stabilize.py --holding [--out reports/holding.md]

The physics' own bound on any reaction policy (``slipd.sim.holding``): the least constant grip that lifts each
object through the rig's lift and holds it, open loop, beside the force limit; ``--policy grip_control`` puts the
same figure beside its runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from slipd.sim.rig import DEFAULT_CONFIG, run_rig
from sliplab.fuse_alarms import CONFIRM_LEVEL

ROOT = Path(__file__).resolve().parents[1]

OBJECTS = ("hard_paper_box", "wooden_box", "shampoo_bottle", "coffee_jar", "pringles_can", "thermos_flask")
SCENARIOS = ("undergrip", "offcentre")
DEFAULT_SEED = 1000
"""The first repetition's seed (``--seed``); the n-th runs DEFAULT_SEED + n."""
PAPER = {  # method.md: translation mm / rotation deg when the grip was corrected
    "hard_paper_box": (4.5, 1.9), "wooden_box": (2.4, 1.5), "shampoo_bottle": (2.8, 2.1),
    "coffee_jar": (2.1, 1.6), "pringles_can": (1.4, 1.1), "thermos_flask": (2.1, 1.2),
}


DETECTORS: dict[str, tuple[str, dict[str, Any]]] = {"confirmed": ("onnx", {"decision.confirm_rule": CONFIRM_LEVEL})}
"""``--detectors`` names that are a config of another detector: (model.detector, the other keys)."""


def _ms(values: list[float]) -> str:
    if not values:
        return "-"
    a = np.asarray(values, float)
    return f"{a.mean():.2f} ± {a.std(ddof=1) if len(a) > 1 else 0.0:.2f}"


def main(argv: list[str] | None = None) -> int:
    """Run the experiment and write the report; returns the exit status."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--out", type=Path, default=ROOT / "reports" / "stabilize.md")
    p.add_argument("--objects", default=",".join(OBJECTS))
    p.add_argument("--no-control", action="store_true", help="skip the runs with the reaction disabled")
    p.add_argument("--detectors", default="onnx",
                   help="comma list among onnx, confirmed (onnx with decision.confirm_rule: "
                   f"{CONFIRM_LEVEL}), deceleration and reference_pillar (each one a full set of runs); with --policy "
                   "onnx or confirmed")
    p.add_argument("--policy", choices=("stop_and_secure", "grip_control"), default=None,
                   help="run grip_control beside stop_and_secure (plus the filling cup and the fragile "
                   "object) and write reports/grip_control.md")
    p.add_argument("--extras", default=",".join(EXTRA_NAMES),
                   help="with --policy: which extra scenes run beside the objects (comma list; '' none); with "
                        "--objects '' the extras alone, e.g. many filling cups")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help="the first repetition's seed (the n-th runs seed + n)")
    p.add_argument("--json", type=Path, help="with --policy: one row per run (default: beside the report, "
                   "reports/grip_control.json without --out)")
    p.add_argument("--from-json", type=Path, help="with --policy: write the report from these runs instead of "
                   "running the rig again")
    p.add_argument("--holding", action="store_true",
                   help="the least grip that holds each object through the lift, open loop (reports/holding.md)")
    args = p.parse_args(argv)
    if args.holding:
        return holding_main(args)
    if args.policy is not None:
        return grip_main(args)
    runs = []
    objects = args.objects.split(",")
    conditions = [(d, True) for d in args.detectors.split(",")] + ([] if args.no_control else [("onnx", False)])
    for obj in objects:
        for scen in SCENARIOS:
            scene = ROOT / "config" / "scenes" / f"{obj}_{scen}.yaml"
            for rep in range(args.reps):
                for detector, react in conditions:
                    name, overrides = DETECTORS.get(detector, (detector, None))
                    res, _ = run_rig(scene, args.config, react=react, seed=args.seed + rep, detector=name,
                                     log=lambda *a: None, overrides=overrides)
                    row = {"object": obj, "scenario": scen, "rep": rep, "detector": detector, **asdict(res)}
                    runs.append(row)
                    print(f"{obj:15s} {scen:9s} rep {rep} {detector:16s} reaction {'on ' if react else 'off'}: "
                          f"{res.translation_mm:6.2f} mm {res.rotation_deg:6.2f} deg "
                          f"alarm {res.alarm_s} dropped {res.dropped}"
                          + (f"  STALLS {res.sensor_stalls}" if res.sensor_stalls else ""), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(runs, indent=1))
    args.out.write_text(report(runs, args))
    print(f"wrote {args.out}")
    return 0


def report(runs: list[dict], args: argparse.Namespace) -> str:
    """The markdown report: one table per detector, plus the runs without a reaction."""
    lines = [
        "# Grasp stabilisation on the simulated rig",
        "",
        f"Regenerate: `python tools/stabilize.py --reps {args.reps} --detectors {args.detectors}{_out_arg(args)}` "
        f"(config `{Path(args.config).name}`).",
        "Object motion relative to the finger when the grasp became secure (object at rest after the",
        "reaction reached the devices), mean ± sd over both scenarios (under-gripped lift, off-centre lift)",
        "and all repetitions. 'No reaction': the same runs with the reaction disabled (motion at the end).",
        "",
    ]
    groups = [(d, True) for d in dict.fromkeys(r["detector"] for r in runs if r["reaction"])]
    groups += [("onnx", False)] if any(not r["reaction"] for r in runs) else []
    for detector, react in groups:
        sel = [r for r in runs if r["detector"] == detector and r["reaction"] == react]
        title = f"detector `{detector}`" + ("" if react else ", **no reaction** (what happens without slipd)")
        lines += [f"## {title}", "",
                  "| object | translation (mm) | rotation (deg) | alarms | dropped | paper (mm / deg) |",
                  "|---|---|---|---|---|---|"]
        for obj in dict.fromkeys(r["object"] for r in sel):
            rows = [r for r in sel if r["object"] == obj]
            paper = PAPER.get(obj, ("-", "-"))
            lines.append(f"| {obj} | {_ms([r['translation_mm'] for r in rows])} | "
                         f"{_ms([r['rotation_deg'] for r in rows])} | {sum(r['alarm_s'] is not None for r in rows)}"
                         f"/{len(rows)} | {sum(r['dropped'] for r in rows)} | {paper[0]} / {paper[1]} |")
        lines.append(f"| **all** | **{_ms([r['translation_mm'] for r in sel])}** | "
                     f"**{_ms([r['rotation_deg'] for r in sel])}** | {sum(r['alarm_s'] is not None for r in sel)}"
                     f"/{len(sel)} | {sum(r['dropped'] for r in sel)} | **2.5 ± 0.7 / 1.9 ± 0.5** |")
        lines.append("")
    stalled = sum(r.get("sensor_stalls", 0) > 0 for r in runs)
    lines += [f"Runs in which the rig fell behind real time (sensor-stall fail-safe): {stalled} of {len(runs)}.",
              "", "Raw runs: `" + args.out.with_suffix(".json").name + "`.", ""]
    return "\n".join(lines)


GRIP = {"reaction.policy": "grip_control", "reaction.grip_margin": 0.85, "reaction.grip_max_force_n": 40.0}
"""The grip_control settings of the report; the rest are the config's defaults. The margin applies to the sliding
pillars' (kinetic) friction estimate: 0.85 of it is 0.68 of the static coefficient on these objects
(mu_k / mu_s = 0.8). The six objects' force limit is the servo's full force, 40 N: stop-and-secure grips every one
of them with it."""
EXTRAS = (  # (scene, extra settings, fill (kg/s, s after lift start, final kg))
    ("cup_filling", {"reaction.grip_max_force_n": 30.0}, (0.2, 0.5, 0.4)),
    ("paper_cup_fragile", {"reaction.grip_max_force_n": 8.0}, None),
)
EXTRA_NAMES = tuple(name for name, _, _ in EXTRAS)
TARGETS = "grip_control's targets"


HOLD_LIMIT_N = GRIP["reaction.grip_max_force_n"]


def _report_path(args: argparse.Namespace, name: str) -> Path:
    """``--out`` where given, else ``reports/<name>`` (the default ``--out`` is the stabilisation report's)."""
    return ROOT / "reports" / name if args.out == ROOT / "reports" / "stabilize.md" else args.out


def holding_table(objects: list[str], limit_n: float = HOLD_LIMIT_N) -> dict[tuple[str, str], dict[str, Any]]:
    """Per (object, scenario): the scene's grip, the least grip that holds it through the lift (open loop, up to
    1.5 x the limit; None beyond) and the object's motion at the limit (``slipd.sim.holding``)."""
    from slipd.sim.holding import least_holding_grip
    from slipd.sim.scene import load_scene

    table = {}
    for obj in objects:
        for scen in SCENARIOS:
            scene = load_scene(ROOT / "config" / "scenes" / f"{obj}_{scen}.yaml")
            res = least_holding_grip(scene, max_n=1.5 * limit_n)  # type: ignore[arg-type]
            at = int(np.argmin(np.abs(res.grips_n - limit_n)))
            table[(obj, scen)] = {"scene_grip_n": scene.grip.force_n, "least_n": res.least_n,  # type: ignore[union-attr]
                                  "holds_at_limit": res.least_n is not None and res.least_n <= limit_n,
                                  "translation_at_limit_mm": float(res.translation_mm[at]),
                                  "rotation_at_limit_deg": float(res.rotation_deg[at])}
    return table


def holding_main(args: argparse.Namespace) -> int:
    """``--holding``: the physics' bound, per object and scenario, as a markdown table (and JSON beside it)."""
    table = holding_table(args.objects.split(","))
    out = _report_path(args, "holding.md")
    lines = ["# What grip holds each rig object through the lift (the physics, no detector)", "",
             f"Regenerate: `python tools/stabilize.py --holding` (`slipd.sim.holding`). Each scene's object is lifted "
             "open loop through the rig's lift (table under it, the scene's UR speed and acceleration, 100 mm, then "
             "1 s still) at constant grips of 0.5 to 60 N in 0.5 N steps; 'least holding grip' is the least from "
             "which on every grip keeps it within the labels' gross motion (2 mm and 2 deg: the elastic twist of a "
             "stuck contact is part of holding). The force limit of the rig's grip_control runs is "
             f"{HOLD_LIMIT_N:g} N (the servo's full force). '-': no grip up to 60 N holds it.", "",
             "| object | scenario | scene's grip (N) | least holding grip (N) | holds at the limit | "
             "motion at the limit (mm / deg) |", "|---|---|---|---|---|---|"]
    for (obj, scen), r in table.items():
        least = "-" if r["least_n"] is None else f"{r['least_n']:.1f}"
        lines.append(f"| {obj} | {scen} | {r['scene_grip_n']:.1f} | {least} | {'yes' if r['holds_at_limit'] else 'no'}"
                     f" | {r['translation_at_limit_mm']:.2f} / {r['rotation_at_limit_deg']:.1f} |")
    n_ok = sum(r["holds_at_limit"] for r in table.values())
    lines += ["", f"{n_ok} of {len(table)} object-scenario pairs can be lifted and held within the limit at all; "
              "a lift of any other one cannot be completed without stopping the arm, whatever the policy (the "
              "arm stop leaves the object's weight on the table). The off-centre scenes put the centre of mass "
              "4 mm beside the grasp (generator slipd.sim/3): at 15 mm, the offset until slipd.sim/2, no grip up to "
              "60 N held any of the six objects.", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    out.with_suffix(".json").write_text(json.dumps(
        [{"object": o, "scenario": s, **r} for (o, s), r in table.items()], indent=1))
    print("\n".join(lines))
    print(f"wrote {out}")
    return 0


def grip_main(args: argparse.Namespace) -> int:
    """grip_control beside stop_and_secure on the 6 objects x 2 scenarios x reps, plus the extras."""
    rows = []
    objects = [o for o in args.objects.split(",") if o]
    extras = [e for e in args.extras.split(",") if e]
    unknown = set(extras) - set(EXTRA_NAMES)
    if unknown:
        raise SystemExit(f"--extras: unknown {sorted(unknown)} (known: {', '.join(EXTRA_NAMES)})")
    if args.from_json is not None:
        rows = json.loads(args.from_json.read_text())
        md = _report_path(args, "grip_control.md")
        md.write_text(grip_report(rows, args, args.from_json))
        print(f"wrote {md} from {args.from_json}")
        return 0
    if args.detectors not in ("onnx", *DETECTORS):
        raise SystemExit(f"--policy runs one detector of the model: --detectors onnx, {', '.join(DETECTORS)}")
    detector, confirm = DETECTORS.get(args.detectors, ("onnx", {}))
    plan = [(f"{o}_{sc}", o, sc, {}, None) for o in objects for sc in SCENARIOS]
    plan += [(name, name, "extra", extra, fill) for name, extra, fill in EXTRAS if name in extras]
    for scene, obj, scen, extra, fill in plan:
        for rep in range(args.reps):
            for policy in ("stop_and_secure", args.policy) if args.policy != "stop_and_secure" else (args.policy,):
                over = {**GRIP, **extra} if policy == "grip_control" else {}
                res, _ = run_rig(ROOT / "config" / "scenes" / f"{scene}.yaml", args.config, seed=args.seed + rep,
                                 detector=detector, log=lambda *a: None, overrides={**over, **confirm}, fill=fill)
                limit = over.get("reaction.grip_max_force_n")
                row = {"policy": policy, "object": obj, "scenario": scen, "rep": rep,
                       "translation_mm": round(res.final_translation_mm, 4),
                       "rotation_deg": round(res.final_rotation_deg, 4), "dropped": res.dropped,
                       "peak_grip_n": round(res.max_grip_n, 3), "mean_grip_n": round(res.mean_grip_n, 3),
                       "arm_stopped": res.arm_stopped, "alarm_s": res.alarm_s,
                       "time_to_secure_s": None if res.secure_s is None else round(res.secure_s - res.lift_start_s, 4),
                       "force_limit_n": limit, "sensor_stalls": res.sensor_stalls}
                rows.append(row)
                print(json.dumps(row), flush=True)
    md = _report_path(args, "grip_control.md")
    out = args.json or md.with_suffix(".json")  # beside the report: a subset run never overwrites the committed runs
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    md.write_text(grip_report(rows, args, out))
    print(f"wrote {out} and {md}")
    return 0


def _out_arg(args: argparse.Namespace) -> str:
    """``--out PATH`` where the report does not go to the default path (the command must write it there again)."""
    default = ROOT / "reports" / "stabilize.md"
    if Path(args.out).resolve() == default.resolve():
        return ""
    return f" --out {_shown(Path(args.out))}"


def _shown(path: Path) -> Path:
    """A path as a command line in a report names it: from the checkout's root where it lies inside it."""
    path = path.resolve()
    return path.relative_to(ROOT) if path.is_relative_to(ROOT) else path


def _mx(values: list[float]) -> str:
    return f"{max(values):.2f}" if values else "-"


def _subset(args: argparse.Namespace) -> str:
    """The command line's --objects / --extras where they are not the full report's."""
    out = ""
    if args.objects != ",".join(OBJECTS):
        out += f" --objects '{args.objects}'"
    if args.extras != ",".join(EXTRA_NAMES):
        out += f" --extras '{args.extras}'"
    if args.seed != DEFAULT_SEED:
        out += f" --seed {args.seed}"
    if args.detectors != "onnx":
        out += f" --detectors {args.detectors}"
    return out


def grip_report(rows: list[dict], args: argparse.Namespace, json_path: Path) -> str:
    """The markdown report of the grip_control comparison: every figure is computed here from ``rows``."""
    settings = ", ".join(f"{k.split('.')[1]} {v}" for k, v in GRIP.items() if k != "reaction.policy")
    lines = ["# Grip-force control beside stop-and-secure on the simulated rig", "",
             f"Regenerate: `python tools/stabilize.py --policy {args.policy} --reps {args.reps}{_subset(args)}"
             f"{_out_arg(args)} --json {_shown(json_path)}` (config `{Path(args.config).name}`; grip_control with "
             f"{settings}, the other "
             "reaction.grip_* at their defaults; the extras' force limits below).", "",
             "Object motion relative to the finger at the end of the run (after the lift and the hold); peak and "
             "mean grip from the servo (the peak over the whole run, the mean from the lift start to the end); 'no "
             "arm stop': the lift went on without the arm being stopped; time to secure: from the lift start to the "
             "object at rest after the first reaction reached a device (mean over the runs that have one).", "",
             "| policy | runs | translation mean ± sd (max), mm | rotation mean ± sd (max), deg | dropped | "
             "peak grip (N) | mean grip (N) | lifts without an arm stop | time to secure (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    main_rows = [r for r in rows if r["scenario"] != "extra"]
    stats: dict[str, dict[str, float]] = {}
    for pol in dict.fromkeys(r["policy"] for r in main_rows):
        sel = [r for r in main_rows if r["policy"] == pol]
        ts = [r["time_to_secure_s"] for r in sel if r["time_to_secure_s"] is not None]
        tr, rot = [r["translation_mm"] for r in sel], [r["rotation_deg"] for r in sel]
        free = sum(not r["arm_stopped"] for r in sel)
        stats[pol] = {"tr": float(np.mean(tr)), "rot": float(np.mean(rot)), "drop": sum(r["dropped"] for r in sel),
                      "peak": float(np.mean([r["peak_grip_n"] for r in sel])), "free": free / len(sel)}
        lines.append(f"| {pol} | {len(sel)} | {_ms(tr)} ({_mx(tr)}) | {_ms(rot)} ({_mx(rot)}) | "
                     f"{sum(r['dropped'] for r in sel)} | {_ms([r['peak_grip_n'] for r in sel])} | "
                     f"{_ms([r['mean_grip_n'] for r in sel])} | {free}/{len(sel)} ({100 * free / len(sel):.0f} %) | "
                     f"{_ms(ts)} |")
    for scen in SCENARIOS:
        lines += ["", f"Scenario `{scen}` only:", "", "| policy | translation (mm) | rotation (deg) | dropped | "
                  "peak grip (N) | mean grip (N) | without an arm stop |", "|---|---|---|---|---|---|---|"]
        for pol in stats:
            sel = [r for r in main_rows if r["policy"] == pol and r["scenario"] == scen]
            lines.append(f"| {pol} | {_ms([r['translation_mm'] for r in sel])} | "
                         f"{_ms([r['rotation_deg'] for r in sel])} | {sum(r['dropped'] for r in sel)} | "
                         f"{_ms([r['peak_grip_n'] for r in sel])} | {_ms([r['mean_grip_n'] for r in sel])} | "
                         f"{sum(not r['arm_stopped'] for r in sel)}/{len(sel)} |")
    # The physics' bound (--holding): which lifts any policy can complete without an arm stop within the limit.
    hold = holding_table(list(dict.fromkeys(r["object"] for r in main_rows)))
    holdable = [r for r in main_rows if r["policy"] == "grip_control" and hold[(r["object"], r["scenario"])]
                ["holds_at_limit"]]
    n_gc = sum(r["policy"] == "grip_control" for r in main_rows)
    lines += ["", f"The physics' bound (`python tools/stabilize.py --holding`, `reports/holding.md`): {len(holdable)} "
              f"of the {n_gc} grip_control lifts are of an object that any constant grip within {HOLD_LIMIT_N:g} N "
              "holds through the lift at all; no policy completes the others without stopping the arm. Of the holdable "
              "lifts, "
              f"{sum(not r['arm_stopped'] for r in holdable)}/{len(holdable)} went on without an arm stop."]
    lines += ["", "Per object (mean over the repetitions):", "",
              "| object | scenario | policy | translation (mm) | rotation (deg) | dropped | peak grip (N) | "
              "mean grip (N) | arm stopped |", "|---|---|---|---|---|---|---|---|---|"]
    keys = dict.fromkeys((r["object"], r["scenario"], r["policy"]) for r in rows)
    extra_rows = [r for r in rows if r["scenario"] == "extra"]
    for obj, scen, pol in keys:
        sel = [r for r in rows if (r["object"], r["scenario"], r["policy"]) == (obj, scen, pol)]
        limit = sel[0]["force_limit_n"]
        lines.append(f"| {obj} | {scen} | {pol} | {np.mean([r['translation_mm'] for r in sel]):.2f} | "
                     f"{np.mean([r['rotation_deg'] for r in sel]):.2f} | {sum(r['dropped'] for r in sel)}/{len(sel)} | "
                     f"{np.mean([r['peak_grip_n'] for r in sel]):.1f} (max {max(r['peak_grip_n'] for r in sel):.1f}"
                     + (f", limit {limit:g}" if limit else "")
                     + f") | {np.mean([r['mean_grip_n'] for r in sel]):.1f} | "
                     f"{sum(r['arm_stopped'] for r in sel)}/{len(sel)} |")
    gc, ss = stats.get("grip_control"), stats.get("stop_and_secure")
    if gc is not None and ss is not None:
        cup = [r for r in extra_rows if r["object"] == "cup_filling" and r["policy"] == "grip_control"]
        fragile = [r for r in extra_rows if r["object"] == "paper_cup_fragile" and r["policy"] == "grip_control"]
        checks = [
            ("none dropped (6 objects x 2 scenarios)", f"{gc['drop']:.0f} dropped", gc["drop"] == 0),
            ("mean translation <= 0.5 mm", f"{gc['tr']:.2f} mm", gc["tr"] <= 0.5),
            ("mean rotation <= 0.5 deg", f"{gc['rot']:.2f} deg", gc["rot"] <= 0.5),
            ("mean peak grip <= 60 % of stop-and-secure's",
             f"{gc['peak']:.1f} N = {100 * gc['peak'] / ss['peak']:.0f} % of {ss['peak']:.1f} N",
             gc["peak"] <= 0.6 * ss["peak"]),
            (">= 90 % of lifts without an arm stop",
             f"{100 * gc['free']:.0f} % (at most {100 * len(holdable) / max(n_gc, 1):.0f} % can be held within the "
             "limit)", gc["free"] >= 0.9),
        ]
        # An extra left out of the run (--extras) is not judged: "not run", not a miss.
        not_run: tuple[str, bool | None] = ("not run", None)
        cup_check = (f"{sum(not r['dropped'] for r in cup)}/{len(cup)} held",
                     not any(r["dropped"] for r in cup)) if cup else not_run
        fragile_check = (f"peak {max(r['peak_grip_n'] for r in fragile):.2f} N, limit {fragile[0]['force_limit_n']} N; "
                         f"dropped {sum(r['dropped'] for r in fragile)}",
                         all(r["peak_grip_n"] <= r["force_limit_n"] for r in fragile)) if fragile else not_run
        checks += [("the filling cup held", *cup_check), ("the fragile object never above its limit", *fragile_check)]
        lines += ["", f"Against {TARGETS} (grip_control):", "", "| target | measured | met |", "|---|---|---|"]
        lines += [f"| {name} | {value} | {'-' if ok is None else 'yes' if ok else '**no**'} |"
                  for name, value, ok in checks]
    stalled = sum(r["sensor_stalls"] > 0 for r in rows)
    lines += ["", f"Runs in which the rig fell behind real time (sensor-stall fail-safe): {stalled} of {len(rows)}.",
              f"Raw runs: `{json_path.name}`.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
