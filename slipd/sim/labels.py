"""The method's label rule, shared by every physics family: which pillars count, and when slip is incipient.

Incipient slip (1) runs from the first sample after a motion's start at which a *considered* pillar slides until
all considered pillars slide at once (gross slip, 0 again). Considered: the pillars in contact at the motion's
start. Contact is the sensor's own flag (``CONTACT_THRESHOLD_N``), except in a light grasp: where fewer than two
pillars pass it, the pillars above ``LIGHT_CONTACT_N`` count. A grasp of a few newtons on a flat object puts
most of its load on the tallest pillar and a few tenths of a newton on its neighbours; those neighbours are in
contact and slide first, and that is the grasp's incipient slip. With the flag alone the one loaded pillar would
be the whole contact, onset and gross slip would fall on the same sample, and such a slip would carry no
incipient label at all.
"""

from __future__ import annotations

import numpy as np

from slipd.geometry import CONTACT_THRESHOLD_N, N_PILLARS, OUTER

LIGHT_CONTACT_N = 0.05
"""Normal force above which a pillar is in contact for the labels of a light grasp (about twice the sensor's
normal-force noise)."""


def considered_pillars(fz_at_start: np.ndarray, rotation: bool = False) -> np.ndarray:
    """[9] bool: the pillars the labels consider, from each pillar's normal force at the motion's start.

    ``rotation``: a rotation about the centre leaves the centre pillar without tangential load (it never slides),
    so only the outer eight count.
    """
    fz = np.asarray(fz_at_start)
    mask = fz > CONTACT_THRESHOLD_N
    if int(mask.sum()) < 2:
        mask = fz > LIGHT_CONTACT_N
    if rotation:
        outer = np.zeros(N_PILLARS, bool)
        outer[list(OUTER)] = True
        mask &= outer
    return mask


def incipient_labels(slip: np.ndarray, considered: np.ndarray, motion_start: int,
                     end_limit: int | None = None) -> tuple[np.ndarray, int | None, int | None]:
    """The method's labels from per-pillar slip: (label [N] uint8, onset index, gross index).

    Onset: first sample at or after ``motion_start`` where a considered pillar slides. Gross: first
    later sample where all considered pillars slide at once (or ``end_limit`` if earlier).
    """
    n = len(slip)
    label = np.zeros(n, np.uint8)
    if not considered.any():
        return label, None, None
    s = slip[:, considered]
    after = np.arange(n) >= motion_start
    anyv = s.any(1) & after
    if not anyv.any():
        return label, None, None
    onset = int(np.argmax(anyv))
    allv = s.all(1) & (np.arange(n) >= onset)
    gross = int(np.argmax(allv)) if allv.any() else None
    if end_limit is not None and end_limit >= onset and (gross is None or end_limit < gross):
        gross = end_limit
    label[onset: gross if gross is not None else n] = 1
    return label, onset, gross


def motion_labels(slip: np.ndarray, fz_at_start: np.ndarray, motion_start: int,
                  rotation: bool = False) -> tuple[np.ndarray, int | None, int | None]:
    """The labels of one motion from the pillars' normal forces at its start: ``incipient_labels`` over
    ``considered_pillars``, as every scene and the closed-loop rig label theirs."""
    return incipient_labels(slip, considered_pillars(fz_at_start, rotation), motion_start)
