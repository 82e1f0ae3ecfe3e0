"""Per-pillar slip probability from the filtered forces of the nine pillars (no model needed).

Physics behind it (Coulomb tips on compliant pillars): a pillar that sticks deflects with the surface,
so while the contact is being loaded its tangential force keeps changing; a pillar that slides sits on
its friction limit, |Ft| = mu Fz, and its tangential force stops following the load. Incipient slip is
therefore *asynchronous deceleration*: some pillars' tangential force rates fall behind the others'
while those pillars use the largest share of their friction cone (utilisation |Ft| / Fz). Per decision
window (the last ``window`` median-filtered samples, the shared feature pipeline's output):

    rate_i   = |Ft_i(end) - Ft_i(start)|                    tangential force change over the window
    ref      = max_j rate_j over the pillars in contact     how fast a sticking pillar is being loaded
    lag_i    = 1 - rate_i / ref                             1: pillar i stopped following the load
    near_i   = util_i / max_j util_j                        1: pillar i is the most utilised

Evidence of sliding: the contact is being loaded (``ref`` above the noise) and pillar i lags and is
near the top utilisation. Evidence of sticking: pillar i follows the load, or uses clearly less of its
cone than the top. Without either (no load change: a hold) the state decays slowly towards stick,
because a Coulomb contact that is not being loaded does not slide for long. While every pillar in
contact is at the same utilisation and the state says most of them slid, the contact is in gross slip
(they stay sliding). Each evidence moves a per-pillar log-odds state; the probability is its logistic.

The Detection field ``pillar_slip`` carries these nine probabilities; a model with an auxiliary
per-pillar head (manifest ``outputs`` naming ``p_pillar``) may fill the same field instead
(``ContactState.source``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slipd.geometry import CONTACT_THRESHOLD_N, N_PILLARS


@dataclass(frozen=True)
class PillarSlipParams:
    """Thresholds of the per-pillar estimator (forces in N over one decision window)."""

    rate_floor_n: float = 0.03
    """A reference rate below this is no load change (filtered noise is about 0.005 N)."""
    lag: float = 0.6
    """lag_i above this counts as 'stopped following the load'."""
    near: float = 0.85
    """near_i above this counts as 'at the top utilisation'."""
    far: float = 0.6
    """near_i below this is sticking evidence (uses clearly less of its cone than the top pillar)."""
    even: float = 0.95
    """near_i above this counts as 'at the same utilisation as the top'."""
    fz_ratio: float = 1.2
    """... and that evenness is informative when the normal forces of those pillars differ by this ratio."""
    step: float = 2.5
    """Log-odds added per window of evidence."""
    decay: float = 0.15
    """Log-odds moved towards stick per window without evidence."""
    limit: float = 6.0
    """Log-odds bound (the state stays finite and recovers within a few windows)."""


class PillarSlip:
    """Per-pillar slip log-odds over successive decision windows; ``update`` returns P(slip) [9]."""

    def __init__(self, params: PillarSlipParams | None = None) -> None:
        self.p = params or PillarSlipParams()
        self._logit = np.full(N_PILLARS, -self.p.limit)

    def reset(self) -> None:
        """A new contact: every pillar sticks."""
        self._logit[:] = -self.p.limit

    def update(self, window: np.ndarray) -> np.ndarray:
        """One window of filtered forces [W, 9, 3] (tared, finite); returns P(slip) per pillar [9]."""
        p = self.p
        w = np.asarray(window).reshape(-1, N_PILLARS, 3)
        # Only the window's first and last samples matter: convert those two, not the whole window (hot path).
        first, last = w[0].astype(np.float64), w[-1].astype(np.float64)
        fz = last[:, 2]
        contact = fz > CONTACT_THRESHOLD_N
        if not contact.any():
            self.reset()
            return self.probability()
        ft = last[:, :2]
        util = np.hypot(ft[:, 0], ft[:, 1]) / np.maximum(fz, CONTACT_THRESHOLD_N)
        d = ft - first[:, :2]
        rate = np.hypot(d[:, 0], d[:, 1])
        ref = float(rate[contact].max())
        top = float(util[contact].max())
        near = util / top if top > 0 else np.zeros(N_PILLARS)
        step = np.zeros(N_PILLARS)
        if ref > p.rate_floor_n:
            lag = 1.0 - rate / ref
            # Equal utilisation across pillars of different normal force: a sticking contact shares its
            # load by deflection (equal Ft, so unequal Ft / Fz); only the friction limit equalises Ft / Fz.
            even = contact & (near > p.even)
            informative = even.sum() > 1 and fz[even].max() > p.fz_ratio * fz[even].min()
            sliding = ((lag > p.lag) & (near > p.near)) | (even if informative else False)
            sticking = (lag < p.lag * 0.5) | (near < p.far)
            step = np.where(sliding, p.step, np.where(sticking, -p.step, 0.0))
        else:
            # No load change. Gross slip keeps the sliding pillars at one (the top) utilisation: they hold
            # their state; a pillar below the top decays towards stick (a Coulomb hold does not slide).
            top_set = contact & (near > p.near)
            held = top_set.sum() > 1 and bool((self._logit[top_set] > 0).mean() > 0.5)
            step = np.full(N_PILLARS, -p.decay)
            if held:
                step[top_set] = 0.0
            step[near < p.far] = -p.step
        step[~contact] = -p.step
        np.clip(self._logit + step, -p.limit, p.limit, out=self._logit)
        return self.probability()

    def probability(self) -> np.ndarray:
        """P(slip) per pillar [9] (a fresh array)."""
        out: np.ndarray = 1.0 / (1.0 + np.exp(-self._logit))
        return out
