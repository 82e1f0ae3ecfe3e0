"""The limit guard on a slow slip: a cup being filled while held, replayed through the detector the daemon builds.

``data/cup_filling.npz`` is the rig's physics of ``config/scenes/cup_filling.yaml`` with the reaction off
(``run_rig(..., react=False, fill=(0.2, 0.5, 0.4), seed=1000)``, ``RigPhysics.force`` samples 600-2800: the grasp, the
lift at sample 700 and the fill from sample 1200 until the cup slides out). Replayed offline, the decisions do not
depend on the rig's timing, so the test holds on every run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import ROOT

from slipd.config import load_config, override
from slipd.detect.build import build_detector
from slipd.detect.detector import run_recording
from slipd.detect.ensemble import Ensemble
from slipd.recording import Recording

CUP = Path(__file__).parent / "data" / "cup_filling.npz"


def _alarms(overrides: dict, zero_error: np.ndarray | None = None) -> list[int]:
    cfg = override(load_config(ROOT / "config" / "sim.yaml"), overrides)
    rec = Recording.load(CUP)
    det = build_detector(cfg, Ensemble.load(cfg.model.manifest))
    force = rec.force if zero_error is None else rec.force - zero_error
    return [d.index for d in run_recording(det, force, rec.t_us) if d.rising_edge]


def test_the_guard_alarms_on_the_slow_slip_the_model_does_not_call() -> None:
    rec = Recording.load(CUP)
    fill = rec.meta["lift_index"] + 500  # the fill starts 0.5 s after the lift
    # The model's own threshold out of reach: only the guard can raise the alarm.
    guarded = _alarms({"decision.threshold": 0.99})
    assert guarded and guarded[0] > fill, guarded
    first_slide = int(rec.slip.any(axis=1).argmax())
    assert first_slide < guarded[0] < first_slide + 400  # while the pillars slide one by one, before the cup is gone
    assert _alarms({"decision.threshold": 0.99, "decision.limit_guard": None}) == []


def test_the_guard_still_alarms_when_the_outer_pillars_read_across_the_contact_flag() -> None:
    """The cup's outer pillars carry about the contact flag's 0.5 N; with their zero 0.025 N high they read 0.47-0.53 N
    and cross the flag from window to window. The pillar estimate holds their slip state while they read just under
    it (``PillarSlipParams.release_n``) instead of taking each crossing for a pillar that left the surface."""
    rec = Recording.load(CUP)
    first_slide = int(rec.slip.any(axis=1).argmax())
    zero_error = np.zeros((9, 3), np.float32)
    zero_error[[1, 7], 2] = 0.025  # the pillars beside the centre, which carries the cup
    guarded = _alarms({"decision.threshold": 0.99}, zero_error)
    assert guarded and first_slide < guarded[0] < first_slide + 400, guarded
