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

import numpy as np

from slipd.geometry import CONTACT_THRESHOLD_N


def near_limit(util: np.ndarray, mu: float | None, margin: float) -> np.ndarray:
    """Per-pillar closeness to the friction limit 0..1 (zeros without a friction estimate)."""
    u = np.asarray(util, np.float64)
    if mu is None or not mu > 0.0 or margin <= 0.0:
        return np.zeros_like(u)
    return np.clip((u / mu - (1.0 - margin)) / margin, 0.0, 1.0)


def contact_risk(fz: np.ndarray, util: np.ndarray, p_slip: np.ndarray, mu: float | None, margin: float) -> float:
    """The load-weighted share of the contact that slips or is within ``margin`` of its limit (0..1)."""
    fz = np.asarray(fz, np.float64)
    contact = fz > CONTACT_THRESHOLD_N
    if not contact.any():
        return 0.0
    share = np.maximum(np.asarray(p_slip, np.float64), near_limit(util, mu, margin))
    w = fz[contact]
    r = float(np.dot(w, share[contact]) / w.sum())
    return min(1.0, max(0.0, r)) if np.isfinite(r) else 1.0
