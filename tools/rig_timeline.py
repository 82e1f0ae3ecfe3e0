"""When the rig's alarms came, relative to incipient and gross slip, from a ``tools/stabilize.py --json`` report.

    python tools/rig_timeline.py reports/stabilize_onnx.json

Per scenario (and in all), over the runs with the reaction on and the given detector: the alarm's delay after the
onset of incipient slip (the method's label: some pillars in contact slip while others still stick) and how many alarms
came while the slip was still incipient (before every pillar in contact slipped, or when that never came).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def _line(name: str, runs: list[dict]) -> str:
    timed = [r for r in runs if r["alarm_s"] is not None and r["onset_s"] is not None]
    delays = sorted(1000 * (r["alarm_s"] - r["onset_s"]) for r in timed)
    incipient = sum(1 for r in timed if r["gross_slip_s"] is None or r["alarm_s"] < r["gross_slip_s"])
    phase = [1000 * (r["gross_slip_s"] - r["onset_s"]) for r in runs
             if r["gross_slip_s"] is not None and r["onset_s"] is not None]
    if not delays:
        return f"{name:<12} {len(runs)} runs, no alarm after a labelled onset"
    phase_txt = f"{statistics.median(phase):.0f} ms" if phase else "-"
    return (f"{name:<12} {len(runs):>3} runs  alarm after the onset: median {statistics.median(delays):.0f} ms "
            f"(range {delays[0]:.0f} to {delays[-1]:.0f})  during incipient slip: {incipient} of {len(timed)}  "
            f"incipient phase (onset to gross slip, where it came): median {phase_txt}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="JSON written by tools/stabilize.py")
    ap.add_argument("--detector", default="onnx")
    args = ap.parse_args(argv)
    runs = [r for r in json.loads(args.report.read_text())
            if r["reaction"] and r.get("detector", args.detector) == args.detector]
    for scenario in sorted({r["scenario"] for r in runs}):
        print(_line(scenario, [r for r in runs if r["scenario"] == scenario]))
    print(_line("all", runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
