"""The limit guard's margin tool: the level a contact risk holds for the guard's run, per recording kind."""

from __future__ import annotations

import math

import pytest
from conftest import slip_and_hold_folder

from sliplab.guard_margin import held_peak, main


def test_the_held_peak_is_the_highest_level_kept_for_a_whole_run() -> None:
    assert held_peak([0.2, 0.95, 0.91, 0.99, 0.5], 3) == pytest.approx(0.91)
    assert held_peak([0.2, 0.95, 0.91, 0.99, 0.5], 1) == pytest.approx(0.99)
    # A decision without a contact state (NaN) breaks the run, as the guard's count does.
    assert held_peak([0.95, 0.95, math.nan, 0.95, 0.95], 3) == 0.0
    assert held_peak([0.9, 0.9], 3) == 0.0  # fewer decisions than the run


def test_the_tool_reports_each_kind_and_the_margin_where_nothing_slips(tmp_path, tiny_model_json, capsys) -> None:
    data = slip_and_hold_folder(tmp_path / "recs")
    assert main(["--model", str(tiny_model_json), "--data", str(data), "--json", str(tmp_path / "g.json")]) == 0
    out = capsys.readouterr().out
    assert "limit guard 0.9 for 3 decisions in a row" in out
    (hold_line,) = [line for line in out.splitlines() if line.strip().startswith("hold")]
    assert "1 recordings, the guard alarms on 0" in hold_line and "below the guard" in hold_line
    (slip_line,) = [line for line in out.splitlines() if line.strip().startswith("slip")]
    assert "below the guard" not in slip_line  # a slip has no margin to keep
