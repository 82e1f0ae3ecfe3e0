"""The slip-timing diagnosis: its groups and the onset pillars it reads from a recording."""

import numpy as np

from slipd.recording import Recording
from sliplab.slip_timing import GROUPS, onset_pillars, slip_group


def test_slip_group_separates_light_onsets_short_stages_and_the_rest() -> None:
    assert slip_group([0.08, 0.3], 0.4) == GROUPS[0]  # the label's onset rests on pillars under the contact flag
    assert slip_group([], 0.4) == GROUPS[0]
    assert slip_group([0.3, 2.1], 0.011) == GROUPS[1]  # loaded, but over within one confirmed decision
    assert slip_group([0.3, 2.1], 0.2) == GROUPS[2]


def test_onset_pillars_are_the_sliding_ones_with_their_tared_normal_force() -> None:
    n = 400
    force = np.zeros((n, 9, 3), np.float32)
    force[:, :, 2] = 0.1  # the unloaded reading the tare removes
    force[200:, 4, 2] += 3.0
    force[200:, 1, 2] += 0.2
    slip = np.zeros((n, 9), np.float32)
    slip[250:, 1] = 1
    rec = Recording(t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=np.zeros_like(force), slip=slip,
                    meta={"tare_samples": [0, 100]})
    idx, fz = onset_pillars(rec, 0.25)
    assert idx == [1] and np.allclose(fz, [0.2], atol=1e-3)
    assert onset_pillars(rec, 0.1) == ([], [])
