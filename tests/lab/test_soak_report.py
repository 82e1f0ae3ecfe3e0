"""The live soak's JSON line as the reliability report reads it: a soak with the emulators in a process of their own
round-trips and says so; the committed JSON of an older soak (emulators in the soak's process) still reads, and its
figures are described as the whole process's."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from sliplab.paths import ROOT
from sliplab.reliability import soak_command, soak_from_json
from sliplab.soak_live import SoakReport


def test_a_soak_with_the_emulators_apart_round_trips_through_its_json_line(tmp_path: Path) -> None:
    rep = SoakReport(seconds=5100.0, model="m.json", frames_sent=10, frames_processed=10, slip_every_s=3.0,
                     failsafe_every_s=60.0, recordings=4, warmup_s=1500.0, fds=(48, 48), threads=(7, 7), samples=3,
                     emulator_cpu_share=0.1, emulators_own_process=True)
    out = tmp_path / "soak.log"
    out.write_text("soak ...\n" + json.dumps({**asdict(rep), "ok": rep.ok}) + "\nOK: no frame lost\n")
    back = soak_from_json(out)
    assert back == rep
    assert "emulated sensor and servo (own process) 10.0 %" in back.lines()[-1]
    assert soak_command(back) == ("tools/soak_live.py --seconds 5100 --slip-every 3 --failsafe-every 60 --record "
                                  "--warmup 1500")


def test_an_older_soak_json_reads_as_emulators_in_the_soak_process() -> None:
    old = soak_from_json(ROOT / "reports" / "soak_live_80min.json")
    assert not old.emulators_own_process and old.emulator_cpu_share == 0.0
    assert old.frames_lost == 181
    assert "whole process (with the sensor and servo emulators)" in old.lines()[-1]
