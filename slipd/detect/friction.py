"""Online friction estimate from the pillars seen sliding.

A sliding Coulomb tip sits on its friction limit, so its utilisation |Ft| / Fz *is* the friction
coefficient of the surface (the kinetic one; with velocity-weakening friction, mu at that slip speed).
Each decision adds one sample per pillar that slides (P(slip) >= 0.5) with a normal force large enough
for the ratio to be meaningful (``min_fz_n``), weighted by its normal force (a heavily loaded pillar's
ratio is the least affected by noise and offsets). The estimate is the weighted mean with exponential
forgetting (``forget`` per decision, so a surface that changes is followed within a few hundred
decisions), its uncertainty the weighted standard deviation of those samples (pillar-to-pillar spread
and noise); both are None until a pillar has been seen sliding. ``reset`` on release: a new grasp may be
a new object.

A pillar needs a normal force above ``min_fz_n`` and above ``edge_share`` of the contact's heaviest pillar:
a pillar at the edge of a curved object carries a fraction of the load, and its ratio, noise and offsets
over a small force, runs above the contact's (a grip set from it holds too little).

A pillar whose normal force rose by more than ``max_fz_rise`` since the previous decision is no sample: a
tightening grip (the grip controller catching a slip) makes it stick below its limit while its slip state
lags for a few decisions, and those falling ratios would pull the estimate down just when the controller
relies on it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class FrictionEstimate:
    """The current estimate: mean coefficient, its weighted standard deviation, and samples behind it."""

    mu: float
    sd: float
    samples: int


class FrictionEstimator:
    """Weighted, forgetting mean of the sliding pillars' utilisation (see the module docstring)."""

    def __init__(self, min_fz_n: float = 1.0, forget: float = 0.995, max_mu: float = 3.0,
                 max_fz_rise: float = 0.05, edge_share: float = 0.0) -> None:
        self.min_fz_n = float(min_fz_n)
        self.edge_share = float(edge_share)
        self.max_fz_rise = float(max_fz_rise)
        self.forget = float(forget)
        self.max_mu = float(max_mu)
        self.reset()

    def reset(self) -> None:
        """Forget everything (release: the next grasp may be another object)."""
        self._w = 0.0
        self._m = 0.0
        self._s = 0.0  # weighted sum of squared deviations
        self.samples = 0
        self._fz: list[float] | None = None

    def update(self, util: Sequence[float], fz: Sequence[float], p_slip: Sequence[float]) -> FrictionEstimate | None:
        """Add this decision's sliding pillars; returns the estimate (None while none was seen sliding)."""
        self.add(util, fz, p_slip)
        return self.estimate()

    def add(self, util: Sequence[float], fz: Sequence[float], p_slip: Sequence[float]) -> None:
        """``update`` without building the estimate (the contact stream reads it after ``refute``)."""
        prev = self._fz if self._fz is not None else fz
        self._fz = list(fz)
        for q in p_slip:
            if q >= 0.5:
                break
        else:  # no pillar slides (a steady grasp, decision after decision): no sample, nothing more to look at
            if not len(util) == len(fz) == len(prev) == len(p_slip):
                raise ValueError("util, fz and p_slip must have one value per pillar")
            return
        floor = self._floor(fz)
        rise = 1.0 + self.max_fz_rise
        # A ratio beyond any real friction (max_mu) is a glitch, not a sample.
        use = [(float(u), float(w)) for u, w, w0, q in zip(util, fz, prev, p_slip, strict=True)
               if q >= 0.5 and w > floor and math.isfinite(u) and u < self.max_mu and w <= rise * w0]
        if use:
            self._w *= self.forget
            self._s *= self.forget
            for u, w in use:
                # West's weighted incremental mean and variance.
                self._w += w
                d = u - self._m
                self._m += d * w / self._w
                self._s += w * d * (u - self._m)
            self.samples += len(use)

    def keep(self, fz: list[float]) -> None:
        """``add`` for a decision where no pillar slides (no sample): its normal forces kept for the next decision's
        rise test. The list is kept as it is (the caller does not change it)."""
        self._fz = fz

    def refute(self, util: Sequence[float], fz: Sequence[float], p_slip: Sequence[float],
               factor: float) -> FrictionEstimate | None:
        """Forget the estimate when a pillar judged sticking (P(slip) < 0.5), among those that could be samples, uses
        more than ``factor`` times it: a sticking tip carries at most mu_s, so its samples were misjudged ones. Returns
        the estimate that stands (None: none, or refuted)."""
        est = self.estimate()
        if est is None:
            return None
        floor = self._floor(fz)
        if any(q < 0.5 and w > floor and u > factor * est.mu for u, w, q in zip(util, fz, p_slip, strict=True)):
            self.reset()
            return None
        return est

    def _floor(self, fz: Sequence[float]) -> float:
        """The normal force a pillar needs to count (``min_fz_n``, ``edge_share`` of the heaviest)."""
        return max(self.min_fz_n, self.edge_share * max(fz))

    def estimate(self) -> FrictionEstimate | None:
        """The current estimate, or None before any sliding pillar was seen."""
        if self._w <= 0.0:
            return None
        sd = math.sqrt(max(self._s, 0.0) / self._w)
        return FrictionEstimate(float(self._m), float(sd), self.samples)
