"""One short closed-loop scene on the simulated rig (physics + emulated devices + `slipd run` as a process).

With the reaction, the daemon's stop and tighten reach the devices before gross slip and the object is
held; the control run (reaction disabled) shows the object slipping further.
"""

from __future__ import annotations

import pytest
from conftest import ROOT

from slipd.sim.rig import run_rig

SCENE = ROOT / "config" / "scenes" / "wooden_box_undergrip.yaml"
CONFIG = ROOT / "config" / "sim.yaml"

pytestmark = pytest.mark.skipif(not (ROOT / "slipd" / "models" / "slip_ensemble.json").exists(),
                                reason="no shipped model")


@pytest.fixture(scope="module")
def runs():
    # The reacting run with a servo at another bus ID: the emulated servo answers where the daemon's config says.
    on, _ = run_rig(SCENE, CONFIG, duration_s=3.0, react=True, host="127.0.0.4", log=lambda *a: None,
                    overrides={"gripper.id": 7})
    off, _ = run_rig(SCENE, CONFIG, duration_s=3.0, react=False, host="127.0.0.4", log=lambda *a: None)
    return on, off


def test_reaction_arrives_before_gross_slip_and_the_object_is_held(runs) -> None:
    on, _ = runs
    assert on.alarm_s is not None and on.onset_s is not None
    assert on.tighten_reached_s is not None and on.stop_reached_s is not None
    reached = max(on.tighten_reached_s, on.stop_reached_s)
    # Before the object has moved 2 mm relative to the finger (the method's online gross slip).
    assert on.gross_motion_s is None or reached < on.gross_motion_s, on.lines()
    assert on.secure_s is not None and not on.dropped, on.lines()


def test_without_reaction_the_object_slips_further(runs) -> None:
    on, off = runs
    assert off.alarm_s is not None  # it still detects: only the reaction is off
    assert off.stop_reached_s is None and off.tighten_reached_s is None
    assert off.translation_mm > on.translation_mm + 2.0, (on.lines(), off.lines())


def test_slipd_sim_turns_a_broken_config_scene_or_duration_into_one_line(tmp_path, capsys) -> None:
    """A config error exits 3 and a scene error or a duration that is not positive exits 2, one line each (they were
    tracebacks, exit 1); nothing runs."""
    from slipd.cli import main

    bad_cfg = tmp_path / "sim.yaml"
    bad_cfg.write_text(CONFIG.read_text().replace("rate_hz: 1000", "rate_hz: 7", 1))
    bad_scene = tmp_path / "scene.yaml"
    bad_scene.write_text("name: nothing\n")
    cases = [(["--config", str(bad_cfg)], 3, "sensor.rate_hz"), (["--scene", str(bad_scene)], 2, "family: required"),
             (["--duration", "-1"], 2, "--duration -1.0: must be > 0")]
    for extra, code, part in cases:
        assert main(["sim", "--plot", "", *extra]) == code
        out = capsys.readouterr()
        assert out.out == "" and part in out.err, out.err


def test_slipd_sim_without_the_sim_extra_exits_2_at_once_in_one_line(monkeypatch, capsys) -> None:
    """The rig draws its plot with matplotlib at the end: without the extra, `slipd sim` ran the whole rig and then
    died with a traceback. Now it stops before anything runs (None in sys.modules: the import fails)."""
    import sys

    from slipd.cli import main

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["sim"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err == "slipd sim: install slipd[sim] (missing: matplotlib)\n", out.err


def test_the_summary_puts_the_events_on_one_time_line_and_says_when_the_alarm_came() -> None:
    from slipd.sim.rig import RigResult

    def result(alarm: float | None, gross: float | None) -> RigResult:
        return RigResult(scene="s", reaction=True, lift_start_s=1.3, onset_s=1.4, gross_slip_s=gross,
                         gross_motion_s=None, alarm_s=alarm, stop_reached_s=None, tighten_reached_s=None,
                         secure_s=None, translation_mm=0.0, rotation_deg=0.0, dropped=False, max_grip_n=40.0,
                         frames=4000)

    assert result(1.42, None).verdict() == "alarm during incipient slip (20 ms after it began); gross slip never came"
    assert result(1.42, 1.45).verdict() == "alarm during incipient slip (20 ms after it began, 30 ms before gross slip)"
    assert result(1.46, 1.45).verdict().startswith("alarm after gross slip (10 ms after every pillar slipped)")
    assert result(None, 1.45).verdict() == "no alarm although the object slipped"
    lines = result(1.46, 1.45).lines()
    timed = [line.split("ms")[0].strip() for line in lines[2:] if line.strip().split(" ")[0].startswith(("+", "-"))]
    assert timed == ["-100", "+0", "+50", "+60"], lines  # lift, onset, gross slip, alarm: in time order
