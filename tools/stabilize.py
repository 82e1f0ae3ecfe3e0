"""Grasp stabilisation on the closed-loop rig: the method's table 1 experiment, regenerated.

    python tools/stabilize.py [--reps 3] [--config config/sim.yaml] [--out reports/stabilize.md]

Six objects x two scenarios (under-gripped lift, off-centre lift) x ``--reps`` repetitions (different
seeds), each run through ``slipd.sim.rig.run_rig``: the real daemon as its own process against the
emulated PapillArray, MX-28 and UR controller with the physics in the loop. Every run is repeated with
the reaction disabled (the daemon detects but does nothing: what happens without slipd). Writes a
markdown report with the per-object table (object translation and rotation relative to the finger
when the grasp became secure, mean +- sd), next to the paper's figures, and the raw runs as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from slipd.sim.rig import DEFAULT_CONFIG, run_rig

ROOT = Path(__file__).resolve().parents[1]

OBJECTS = ("hard_paper_box", "wooden_box", "shampoo_bottle", "coffee_jar", "pringles_can", "thermos_flask")
SCENARIOS = ("undergrip", "offcentre")
PAPER = {  # method.md: translation mm / rotation deg when the grip was corrected
    "hard_paper_box": (4.5, 1.9), "wooden_box": (2.4, 1.5), "shampoo_bottle": (2.8, 2.1),
    "coffee_jar": (2.1, 1.6), "pringles_can": (1.4, 1.1), "thermos_flask": (2.1, 1.2),
}


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
                   help="comma list among onnx, deceleration, reference_pillar (each one a full set of runs)")
    p.add_argument("--policy", choices=("stop_and_secure", "grip_control"), default=None,
                   help="issue 16: run grip_control beside stop_and_secure (plus the filling cup and the fragile "
                   "object) and write reports/grip_control.md")
    p.add_argument("--json", type=Path, help="with --policy: one row per run")
    args = p.parse_args(argv)
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
                    res, _ = run_rig(scene, args.config, react=react, seed=1000 + rep, detector=detector,
                                     log=lambda *a: None)
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
        f"Regenerate: `python tools/stabilize.py --reps {args.reps} --detectors {args.detectors}` "
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


GRIP = {"reaction.policy": "grip_control", "reaction.grip_margin": 0.85, "reaction.grip_raise_risk": 0.6,
        "reaction.grip_stop_risk": 0.95}
"""The grip_control settings of the report (friction use 0.85 of the kinetic estimate is about 0.7 of the
static coefficient on these objects: mu_k / mu_s = 0.8)."""
EXTRAS = (  # (scene, extra settings, fill (kg/s, s after lift start, final kg))
    ("cup_filling", {}, (0.2, 0.5, 0.4)),
    ("paper_cup_fragile", {"reaction.grip_max_force_n": 8.0}, None),
)


def grip_main(args: argparse.Namespace) -> int:
    """grip_control beside stop_and_secure on the 6 objects x 2 scenarios x reps, plus the extras."""
    rows = []
    objects = args.objects.split(",")
    plan = [(f"{o}_{sc}", o, sc, {}, None) for o in objects for sc in SCENARIOS]
    plan += [(name, name, "extra", extra, fill) for name, extra, fill in EXTRAS]
    for scene, obj, scen, extra, fill in plan:
        for rep in range(args.reps):
            for policy in ("stop_and_secure", args.policy) if args.policy != "stop_and_secure" else (args.policy,):
                over = {**GRIP, **extra} if policy == "grip_control" else {}
                res, _ = run_rig(ROOT / "config" / "scenes" / f"{scene}.yaml", args.config, seed=1000 + rep,
                                 detector=None, log=lambda *a: None, overrides=over, fill=fill)
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
    out = args.json or ROOT / "reports" / "grip_control.json"
    out.write_text(json.dumps(rows, indent=1))
    md = ROOT / "reports" / "grip_control.md" if args.out == ROOT / "reports" / "stabilize.md" else args.out
    md.write_text(grip_report(rows, args))
    print(f"wrote {out} and {md}")
    return 0


def grip_report(rows: list[dict], args: argparse.Namespace) -> str:
    """The markdown table of the grip_control comparison."""
    lines = ["# Grip-force control beside stop-and-secure on the simulated rig", "",
             f"Regenerate: `python tools/stabilize.py --policy grip_control --reps {args.reps} --json "
             "reports/grip_control.json` (config `" + Path(args.config).name + "`, grip_control settings: "
             + ", ".join(f"{k.split('.')[1]} {v}" for k, v in GRIP.items() if k != "reaction.policy") + ").",
             "Object motion relative to the finger at the end of the run (after the lift and the hold); peak and",
             "mean grip from the lift to the end; 'no arm stop': the lift went on without the arm being stopped;",
             "time to secure: from the lift start to the object at rest after the first reaction reached a device.",
             "", "| policy | runs | translation (mm) | rotation (deg) | dropped | peak grip (N) | mean grip (N) | "
             "no arm stop | time to secure (s) |", "|---|---|---|---|---|---|---|---|---|"]
    main_rows = [r for r in rows if r["scenario"] != "extra"]
    for pol in dict.fromkeys(r["policy"] for r in main_rows):
        sel = [r for r in main_rows if r["policy"] == pol]
        ts = [r["time_to_secure_s"] for r in sel if r["time_to_secure_s"] is not None]
        lines.append(f"| {pol} | {len(sel)} | {_ms([r['translation_mm'] for r in sel])} | "
                     f"{_ms([r['rotation_deg'] for r in sel])} | {sum(r['dropped'] for r in sel)} | "
                     f"{_ms([r['peak_grip_n'] for r in sel])} | {_ms([r['mean_grip_n'] for r in sel])} | "
                     f"{sum(not r['arm_stopped'] for r in sel)}/{len(sel)} | {_ms(ts)} |")
    lines += ["", "Per object (grip_control):", "", "| object | scenario | translation (mm) | rotation (deg) | "
              "dropped | peak grip (N) | arm stopped |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if (r["policy"] == "grip_control" and r["rep"] == 0) or r["scenario"] == "extra":
            lines.append(f"| {r['object']} ({r['policy']}) | {r['scenario']} | {r['translation_mm']:.2f} | "
                         f"{r['rotation_deg']:.2f} | {r['dropped']} | {r['peak_grip_n']:.1f}"
                         + (f" (limit {r['force_limit_n']:g})" if r["force_limit_n"] else "")
                         + f" | {r['arm_stopped']} |")
    stalled = sum(r["sensor_stalls"] > 0 for r in rows)
    lines += ["", f"Runs in which the rig fell behind real time (sensor-stall fail-safe): {stalled} of {len(rows)}.",
              "Raw runs: `grip_control.json`.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
