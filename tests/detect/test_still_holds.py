"""The shipped detector stays quiet when nothing slips, for as long as a robot holds something.

One hold of each type: a still press (0.6-1.4 mm against a flat plate, unloaded start, then perfectly
still) for two minutes on the v2 sensor and one on v1, a shear hold (a move that stops at 30-90 % of the first
pillar's stick limit, then held), a hold after a fast stop at 50-95 % of it, a hold after a release and regrasp, and
free air (no contact). The shipped int8 model, run through the daemon's own decision path (``Detector`` at the
manifest's stride), raises no alarm, and p_slip settles at least 0.2 below the threshold (the issue's margin:
p99 over the hold after its first fifth); in free air the contact gate keeps p_slip at exactly 0.

These are the first recordings of each type and sensor of ``slipd.sim.datasets.hold_scene`` (seed 7), not a
selection; ``reports/robustness.md`` counts the alarms over the whole ``holds`` test set.
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
                                                  (6, 60.0, "shear hold v2"), (2, 60.0, "hold after a stop v1"),
                                                  (8, 60.0, "hold after a regrasp v2"), (4, 30.0, "free air v1")])
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
    assert p99 <= ens.threshold - 0.2
    if "free air" in what:
        assert not p.any()  # the gate: no contact, no slip, the model never ran
