"""The zero-error tool: every pillar's zero a little off after the tare, and how the verdicts move."""

from __future__ import annotations

import numpy as np
from conftest import make_scene, slip_and_hold_folder

from sliplab.augment import zero_errors
from sliplab.evaluate import ModelRunner
from sliplab.zero_error import main


def test_zero_errors_draw_each_axis_at_its_own_scale() -> None:
    e = zero_errors(np.random.default_rng(0), (0.03, 0.01), 4000)
    assert e.shape == (4000, 9, 3) and e.dtype == np.float32
    sd = e.reshape(-1, 3).std(axis=0)
    assert np.allclose(sd, [0.01, 0.01, 0.03], rtol=0.05)


def test_a_zero_error_moves_the_tare_and_none_leaves_the_decisions_bit_identical(tiny_model_json) -> None:
    rec = make_scene("slip", seed=1)
    runner = ModelRunner(str(tiny_model_json))
    tared = runner.trace(rec)
    assert runner.trace(rec, zero_error=np.zeros((9, 3), np.float32)).p_slip == tared.p_slip
    off = np.zeros((9, 3), np.float32)
    off[:, 2] = 0.4  # every pillar's zero 0.4 N high: each reads 0.4 N less load
    assert runner.trace(rec, zero_error=off).p_slip != tared.p_slip


def test_the_tool_reports_each_kind_as_tared_and_over_the_draws(tmp_path, tiny_model_json, capsys) -> None:
    data = slip_and_hold_folder(tmp_path / "recs")
    args = ["--model", str(tiny_model_json), "--data", str(data), "--draws", "2"]
    assert main([*args, "--sigma", "0", "0", "--json", str(tmp_path / "z.json")]) == 0
    out = capsys.readouterr().out
    (hold_line,) = [line for line in out.splitlines() if line.strip().startswith("hold")]
    assert "1 recordings, alarmed: 0 as tared, 0.0% of the draws (0/2)" in hold_line
    assert "changes in some draw for 0" in hold_line  # no error, no change
    (slip_line,) = [line for line in out.splitlines() if line.strip().startswith("slip")]
    assert "1 recordings, caught in time:" in slip_line
