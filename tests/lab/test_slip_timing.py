"""The slip-timing diagnosis: its groups and the onset pillars it reads from a recording."""

import numpy as np

from slipd.recording import Recording
from sliplab.slip_timing import GROUPS, label_stats, onset_pillars, slip_group


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


def test_label_stats_count_sliding_that_the_slip_span_leaves_negative(tmp_path) -> None:
    n = 600
    force = np.zeros((n, 9, 3), np.float32)
    force[150:, 4, 2] = 3.0  # in contact from 150 ms
    force[300:500, 4, 0] = 1.2  # sliding at |Ft| / Fz = 0.4
    slip = np.zeros((n, 9), np.float32)
    slip[300:500, 4] = 1  # one pillar carried the grasp: it slides with no incipient stage
    rec = Recording(t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=np.zeros_like(force), slip=slip,
                    label=np.zeros(n, np.uint8),
                    meta={"kind": "slip", "tare_samples": [0, 100], "events": {"onset": 0.3, "gross_slip": 0.3}})
    rec.save(tmp_path / "a.npz")
    stats = label_stats(tmp_path)
    assert (stats["slips"], stats["slips_unlabelled"]) == (1, 1)
    # The slip span runs from the onset event to gross slip, here the same sample: the rest of the slide stays 0.
    assert stats["slip span, slip recordings"] == {"sliding labelled slip": 1, "sliding labelled no slip": 199}
    assert stats["sliding span, slip recordings"] == {"sliding labelled slip": 200, "sliding labelled no slip": 0}
    assert stats["sliding_utilisation_p10_p50_p90"] == [0.4, 0.4, 0.4]
    assert stats["partial_slips"] == 1  # no labelled sample, yet the loaded pillar slid for 200 ms
