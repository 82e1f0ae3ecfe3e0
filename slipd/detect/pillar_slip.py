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

Evidence of sliding: the contact is being loaded (``ref`` above the noise) and pillar i lags and does not
use clearly less of its cone than the top (with per-pillar friction spread a sliding pillar sits on its own
limit, not necessarily the top utilisation). Evidence of sticking: pillar i follows the load, or uses clearly
less of its cone than the top. Without either (no load change: a hold) the state decays slowly towards stick,
because a Coulomb contact that is not being loaded does not slide for long. While every pillar in
contact is at the same utilisation and the state says most of them slid, the contact is in gross slip
(they stay sliding). Each evidence moves a per-pillar log-odds state; the probability is its logistic.

The Detection field ``pillar_slip`` carries these nine probabilities; a model with an auxiliary
per-pillar head (manifest ``outputs`` naming ``p_pillar``) may fill the same field instead
(``ContactState.source``).
"""

from __future__ import annotations

import math
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
    """near_i above this counts as 'at the top utilisation' (the hold rule's gross-slip set)."""
    far: float = 0.6
    """near_i below this is sticking evidence (uses clearly less of its cone than the top pillar); a lagging pillar
    above it is sliding evidence. That evidence once asked for ``near`` (the top utilisation), which holds for one
    friction coefficient across the pillars only: with per-pillar spread the pillars that stopped at their own lower
    limit were never marked, the friction samples came from the grippiest pillars alone and the estimate ran high
    (`python tools/evaluate.py --contact --sets transfer,robust [--split train]`, spread family within 15 % on the
    test / train splits 68 % / 73 % at ``near``, 88 % / 92 % at ``far``; per-pillar F1 0.536 -> 0.555 robust, 0.752 ->
    0.757 transfer)."""
    even: float = 0.95
    """near_i above this counts as 'at the same utilisation as the top'."""
    fz_ratio: float = 1.2
    """... and that evenness is informative when the normal forces of those pillars differ by this ratio."""
    step: float = 2.5
    """Log-odds added per window of evidence."""
    decay: float = 0.15
    """Log-odds moved towards stick per window without evidence."""
    limit: float = 6.0
    """Log-odds bound (the state stays finite and recovers within a few windows). A bound of 4 (two windows of
    evidence to slide instead of three) scored better offline (per-pillar F1 0.793 / 0.538 on the test splits
    against 0.752 / 0.536) and moved less on the rig (0.56 mm against 0.60), but grip control then dropped the
    filling cup in 2 of 20 runs (`python tools/stabilize.py --policy grip_control --objects '' --extras cup_filling
    --reps 20 --seed 2000`) against 0 of 20 at 6: not kept."""
    release_n: float = 0.25
    """A pillar under the contact flag counts as off the surface (sticking evidence: its slip state resets) only below
    this normal force; between it and the flag its state is held. A light grasp loads the pillars beside the one that
    carries it with about the flag's 0.5 N, and their readings cross the flag from window to window with the noise and
    a zero a few hundredths off. Were each crossing taken for a pillar leaving the surface, it would wipe the sliding
    evidence of the windows before: with its outer pillars' zero 0.025 N high, the filling cup's pillars sliding at
    their limit would never be marked and the limit guard would not alarm (``tests/detect/test_limit_guard.py``). A
    pillar that has left the surface reads the noise around zero."""
    fall: float = 0.1
    """A pillar whose utilisation fell by this share over the window while its normal force rose (by more than
    ``rate_floor_n``) sticks: a sliding tip carries mu * Fz, so a tighter grip raises its tangential force with it
    (the grip that caught a slip must clear the slip state, or the hold rule below keeps it sliding). The
    floor keeps the noise out: on a slippery object (mu 0.08, 0.12 N of shear per pillar) the filtered noise moves
    the ratio by 10 % and Fz by a few mN, and without it the pillars of a steady slide were cleared one by one until
    the hold rule let them all decay (transfer split recall 0.62 -> 0.78, per-pillar F1 0.757 -> 0.864; robust 0.555
    -> 0.565; `python tools/evaluate.py --contact --sets transfer,robust [--split train]`)."""


def triples(flat: list[float]) -> list[tuple[float, float, float]]:
    """A sample's ``[fx, fy, fz, fx, ...]`` as one ``(fx, fy, fz)`` per pillar."""
    it = iter(flat)
    return list(zip(it, it, it))


def utilisation(last: list[float]) -> tuple[list[float], list[float], list[bool]]:
    """Normal forces, utilisations |Ft| / Fz and contact flags of the nine pillars from one sample's
    ``[fx, fy, fz, fx, ...]`` (plain floats and one loop: nine-element numpy calls cost more than the arithmetic,
    and this runs on the hot path once per decision)."""
    thr = CONTACT_THRESHOLD_N
    fz, util, contact = [], [], []
    for fx, fy, z in triples(last):
        fz.append(z)
        util.append(math.hypot(fx, fy) / (z if z > thr else thr))
        contact.append(z > thr)
    return fz, util, contact


class PillarSlip:
    """Per-pillar slip log-odds over successive decision windows; ``update`` returns P(slip) [9]."""

    def __init__(self, params: PillarSlipParams | None = None) -> None:
        self.p = params or PillarSlipParams()
        self._logit = [-self.p.limit] * N_PILLARS
        # The probabilities of the latest logits: a hold leaves the logits where they are decision after decision.
        self._probs: tuple[list[float], tuple[float, ...]] = ([], ())

    def reset(self) -> None:
        """A new contact: every pillar sticks."""
        self._logit = [-self.p.limit] * N_PILLARS

    def update(self, window: np.ndarray) -> np.ndarray:
        """One window of filtered forces [W, 9, 3] (tared, finite); returns P(slip) per pillar [9]."""
        w = np.asarray(window).reshape(-1, N_PILLARS * 3)
        return np.array(self.step(w[0].tolist(), w[-1].tolist()))

    def step(self, first: list[float], last: list[float],
             ends: tuple[list[float], list[float], list[bool] | None] | None = None,
             peaks: tuple[float, float] | None = None) -> tuple[float, ...]:
        """``update`` on a window's first and last samples (``[fx, fy, fz, fx, ...]``, nine pillars: only those two
        matter); P(slip) per pillar. Plain loops over the nine pillars: this runs on the hot path once per decision and
        sensor.
        ``ends``: ``utilisation(last)`` (its contact flags may be None: made here when needed), and ``peaks`` the
        largest rate and utilisation of the pillars in contact (-1 for none), where the caller has them already."""
        p = self.p
        fz, util, contact = ends or utilisation(last)
        if peaks is None:
            if contact is None:
                contact = [z > CONTACT_THRESHOLD_N for z in fz]
            ref = top = -1.0
            for (ax, ay, _), (bx, by, _), c, u in zip(triples(first), triples(last), contact, util):
                if c:  # the largest rate and utilisation in contact (``max`` keeps the first of equals, as here)
                    r = math.hypot(bx - ax, by - ay)
                    if r > ref:
                        ref = r
                    if u > top:
                        top = u
        else:
            ref, top = peaks
        if ref < 0.0:  # no pillar in contact
            self.reset()
            return self.probabilities()
        if ref <= p.rate_floor_n and self._logit.count(-p.limit) == N_PILLARS:
            # No load change, every pillar at the stick bound (a steady grasp, decision after decision): every step
            # below is towards stick or none (holding needs a pillar that slid), so every logit stays at the bound.
            return self.probabilities()
        if contact is None:  # (made only now: a steady grasp returned above without them)
            contact = [z > CONTACT_THRESHOLD_N for z in fz]
        pillars = triples(first)  # (the first sample's (fx, fy, fz) per pillar, likewise only now)
        near = [u / top for u in util] if top > 0 else [0.0] * N_PILLARS
        if ref > p.rate_floor_n:
            # Equal utilisation across pillars of different normal force: a sticking contact shares its
            # load by deflection (equal Ft, so unequal Ft / Fz); only the friction limit equalises Ft / Fz.
            rate = [math.hypot(bx - ax, by - ay) for (ax, ay, _), (bx, by, _) in zip(pillars, triples(last))]
            step = [0.0] * N_PILLARS
            even = [contact[i] and near[i] > p.even for i in range(N_PILLARS)]
            fz_even = [fz[i] for i in range(N_PILLARS) if even[i]]
            informative = len(fz_even) > 1 and max(fz_even) > p.fz_ratio * min(fz_even)
            for i in range(N_PILLARS):
                lag = 1.0 - rate[i] / ref
                if (lag > p.lag and near[i] > p.far) or (informative and even[i]):
                    step[i] = p.step  # stopped following the load, not clearly below the top: sliding
                elif lag < p.lag * 0.5 or near[i] < p.far:
                    step[i] = -p.step  # follows the load, or uses clearly less of its cone: sticking
        else:
            # No load change. Gross slip keeps the sliding pillars at one (the top) utilisation: they hold
            # their state; a pillar below the top decays towards stick (a Coulomb hold does not slide).
            top_set = [c and q > p.near for c, q in zip(contact, near)]
            n_top = sum(top_set)
            held = False
            if n_top > 1:
                slid = sum([1 for t, lg in zip(top_set, self._logit) if t and lg > 0])
                held = slid / n_top > 0.5
            stick, decay = -p.step, -p.decay
            step = [stick if q < p.far else 0.0 if held and t else decay for q, t in zip(near, top_set)]
        lim, logit, thr = p.limit, self._logit, CONTACT_THRESHOLD_N
        keep, floor, stick, release = 1.0 - p.fall, p.rate_floor_n, -p.step, p.release_n
        for i, ((x0, y0, z0), c, u, z, s) in enumerate(zip(pillars, contact, util, fz, step)):
            if not c:
                s = stick if z < release else 0.0  # off the surface; just under the flag: held (``release_n``)
            elif z > z0 + floor and u < keep * (math.hypot(x0, y0) / (z0 if z0 > thr else thr)):
                s = stick  # its utilisation fell while its normal force rose (``fall``): sticks
            # min(lim, max(-lim, logit + s)), without the two calls
            v = logit[i] + s
            v = v if v > -lim else -lim
            logit[i] = v if v < lim else lim
        return self.probabilities()

    def probabilities(self) -> tuple[float, ...]:
        """P(slip) per pillar, as plain floats (a tuple: the states of a hold share it, decision after decision)."""
        logits, probs = self._probs
        if logits != self._logit:
            logits, probs = list(self._logit), tuple([1.0 / (1.0 + math.exp(-lg)) for lg in self._logit])
            self._probs = (logits, probs)
        return probs

    def probability(self) -> np.ndarray:
        """P(slip) per pillar [9] (a fresh array)."""
        return np.array(self.probabilities())
