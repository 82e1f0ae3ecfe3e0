"""Continuous slip risk 0..1: the load-weighted share of the contact that slips or is near its friction limit.

    risk = sum_i Fz_i * max(P_i, near_i) / sum_i Fz_i        over the pillars in contact
    near_i = clip((util_i / mu - (1 - margin)) / margin, 0, 1)

``P_i`` is pillar i's slip probability, ``util_i = |Ft_i| / Fz_i`` its utilisation and ``mu`` the friction
estimate (``slipd.detect.friction``): a pillar contributes nothing while it uses less than ``1 - margin``
of its friction cone, rises linearly to 1 as it reaches the limit, and counts fully once it slides.
Weighting by normal force makes the number the share of the *grip* at risk: a lightly touching corner
that slides matters less than the centre. Before any pillar was seen sliding ``mu`` is unknown and only
the slip probabilities count. 0: every pillar sticks well inside its cone; 1: the whole contact slides.
The binary alarm is unchanged (``slipd.detect.decision``); this is a separate, physical warning level.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from slipd.geometry import CONTACT_THRESHOLD_N


def contact_risk(fz: Sequence[float], util: Sequence[float], p_slip: Sequence[float], mu: float | None,
                 margin: float, slip_cut: float | None = None) -> float:
    """The load-weighted share of the contact that slips or is within ``margin`` of its limit (0..1). ``slip_cut``: a
    pillar's slip probability counts only where its utilisation is at least this (below it reads 0; the contact
    stream's ``RISK_TOP_SHARE`` rule), None: every pillar's.

    A loop over the nine pillars (once per decision on the hot path: cheaper than numpy on nine values; the cut is
    applied in the same pass rather than in a list of its own)."""
    thr = CONTACT_THRESHOLD_N
    limit = mu if mu is not None and mu > 0.0 and margin > 0.0 else None  # None: only the slip counts
    num = den = 0.0
    if limit is None:
        if slip_cut is None:
            for z, q in zip(fz, p_slip, strict=True):
                if z > thr:
                    num += z * float(q)
                    den += z
        else:
            for z, u, q in zip(fz, util, p_slip, strict=True):
                if z > thr:
                    num += z * (float(q) if u >= slip_cut else 0.0)
                    den += z
    else:
        below = 1.0 - margin
        for z, u, q in zip(fz, util, p_slip, strict=True):
            if z > thr:
                share = float(q) if slip_cut is None or u >= slip_cut else 0.0
                # max(share, min(1.0, max(0.0, near))) with comparisons in place of the calls (the same choices, NaN
                # included: each keeps its first operand unless the second compares strictly past it)
                near = (u / limit - below) / margin
                near = near if near > 0.0 else 0.0
                near = near if near < 1.0 else 1.0
                if near > share:
                    share = near
                num += z * share
                den += z
    if den == 0.0:
        return 0.0
    r = float(num / den)
    return min(1.0, max(0.0, r)) if math.isfinite(r) else 1.0
