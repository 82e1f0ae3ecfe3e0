"""The shipped detector stays quiet when nothing slips, for as long as a robot holds something.

A still press (0.6-1.4 mm against a flat plate, unloaded start, then perfectly still) held for two minutes
on the v2 sensor and one minute on v1, and free air (no contact) for a minute: the shipped int8 model, run
through the daemon's own decision path (``Detector`` at the manifest's stride), raises no alarm, and in free
air the contact gate keeps p_slip at exactly 0 (the model never runs without contact).

How far below the threshold p_slip settles is printed, not asserted: issue 14 asks for 0.2 and the shipped
model settles about 0.1 below it on these presses (p_slip about 0.41, with or without the gate), so that
target is not met yet. The issue's own still presses, from a simulator that shares no code with ours, did
set the old model off within 2 s; these tests guard against a regression on ours, they do not prove that.
Other still presses of the ``holds`` set do set the shipped model off (for example ``hold_00055``, v2, and
``hold_00035``, v2 with per-pillar spread): ``reports/robustness.md`` counts them.
"""

from __future__ import annotations

import numpy as np
import pytest

from slipd import models
from slipd.detect.build import build_detector
from slipd.detect.ensemble import Ensemble
from slipd.recording import Recording
from slipd.sim.datasets import hold_scene
from slipd.sim.scene import generate, parse_scene


def _hold(index: int, seconds: float, seed: int) -> Recording:
    d = hold_scene(np.random.default_rng(seed), index, hold_s=seconds)
    rec = generate(parse_scene({k: v for k, v in d.items() if k != "_tags"}, d["name"]), seed)
    assert not rec.label.any() and not rec.slip.any()  # the truth: nothing slips
    return rec


@pytest.fixture(scope="module")
def ens() -> Ensemble:
    return Ensemble.load(models.packaged(models.DEFAULT_MODEL))


@pytest.mark.slow
@pytest.mark.parametrize("index, seconds, what", [(5, 120.0, "still press v2"), (0, 60.0, "still press v1"),
                                                  (4, 30.0, "free air v1")])
def test_long_still_hold_raises_no_alarm(ens: Ensemble, index: int, seconds: float, what: str) -> None:
    rec = _hold(index, seconds, seed=7)
    ens.reset()
    det = build_detector(None, ens, offset=np.zeros((9, 3), np.float32))
    dets = [d for _, d in det.push_many(rec.force, rec.t_us)]
    p = np.array([d.p_slip for d in dets])
    assert len(p) > seconds * 50
    alarms = [d for d in dets if d.rising_edge]
    assert not alarms, f"{what}: alarm at {alarms[0].t_us / 1e6:.2f} s (p {alarms[0].p_slip:.2f})"
    settled = p[len(p) // 5 :]  # past the press
    p99 = float(np.percentile(settled, 99))
    print(f"{what}: {seconds:g} s, {len(p)} decisions, no alarm; p_slip p99 {p99:.3f}, "
          f"{ens.threshold - p99:.3f} below the threshold")
    assert p99 < ens.threshold
    if "free air" in what:
        assert not p.any()  # the gate: no contact, no slip, the model never ran
