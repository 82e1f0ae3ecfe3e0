"""From ensemble probabilities to a decision: a binary alarm with optional hysteresis, and a risk level.

Alarm: raised when the ensemble mean ``p_slip >= threshold`` (the method's rule, 0.5 by default). With
``hysteresis > 0`` a raised alarm clears only once ``p_slip < threshold - hysteresis``, so a probability
wandering around the threshold does not make the alarm chatter (and re-trigger the reaction). With
``hysteresis = 0`` the decision is exactly the method's per-window rule.

Limit guard: the alarm is raised too when the contact state's risk (``slipd.detect.contact``: the load-weighted share
of the contact that slides or sits at its friction limit) stays at or above ``limit_guard`` for
``limit_guard_decisions`` decisions in a row, whatever p_slip says, and it holds while the risk does. The model calls
the slips it learned, whose load rises within tens of milliseconds; a load that grows over seconds (a cup being
filled) slides the pillars one by one at the limit with P(slip) well below the threshold, and the contact state sees
every pillar there.

Risk (0..1), a continuous warning level beside the alarm, chosen as ``min(1, p_slip / threshold)``:
  * it is the same signal the alarm uses: risk reaches 1 exactly when p_slip crosses the threshold; the alarm
    rises then too where one window decides (``min_consecutive`` 1, no hysteresis, no press hold), and
    otherwise follows once its confirmation rules are met (risk 1 with the alarm still down is "about to");
  * scaling by the threshold makes graded reaction levels (e.g. "pre-tighten at risk 0.6") keep their
    meaning when the threshold is re-tuned;
  * the alternative, the fraction of members alarming, takes only Z + 1 values (0, 0.2, ... for Z = 5)
    and discards how close each member is; ``DecisionResult.members_alarming`` keeps it, a measure of how
    much the members agree (evaluation; the daemon's ``Detection`` does not carry it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from slipd.detect.contact import ContactState


@dataclass(frozen=True)
class DecisionResult:
    """One decision: ``alarm`` (state), ``rising_edge`` (alarm raised on this update), ``risk`` 0..1,
    ``members_alarming`` (fraction of members with P(slip) >= threshold; None when not given)."""

    alarm: bool
    rising_edge: bool
    risk: float
    members_alarming: float | None


class Decision:
    """Stateful thresholding of ensemble outputs. ``update`` once per model step; ``reset`` on a new contact."""

    def __init__(self, threshold: float = 0.5, hysteresis: float = 0.0, min_consecutive: int = 1,
                 limit_guard: float | None = None, limit_guard_decisions: int = 3) -> None:
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold must be in (0, 1), got {threshold}")
        if not 0.0 <= hysteresis < threshold:
            raise ValueError(f"hysteresis must be in [0, threshold), got {hysteresis} (threshold {threshold})")
        if min_consecutive < 1:
            raise ValueError(f"min_consecutive must be >= 1, got {min_consecutive}")
        if limit_guard is not None and not 0.0 < limit_guard <= 1.0:
            raise ValueError(f"limit_guard must be in (0, 1] or None, got {limit_guard}")
        if limit_guard_decisions < 1:
            raise ValueError(f"limit_guard_decisions must be >= 1, got {limit_guard_decisions}")
        self.threshold = float(threshold)
        self.hysteresis = float(hysteresis)
        self.min_consecutive = int(min_consecutive)
        self.limit_guard = limit_guard
        self.limit_guard_decisions = int(limit_guard_decisions)
        self.alarm = False
        self.guarded = False
        """The limit guard holds (its run of decisions is complete): the alarm is up whatever p_slip says."""
        self._above = 0  # consecutive decisions at or above the threshold
        self._at_limit = 0  # consecutive decisions with the contact risk at or above the limit guard

    def reset(self) -> None:
        """Clear the alarm state."""
        self.alarm = False
        self.guarded = False
        self._above = 0
        self._at_limit = 0

    def update(self, p_slip: float, p_members: np.ndarray | None = None, may_raise: bool = True) -> DecisionResult:
        """Feed one step's mean P(slip) (and optionally the members' [Z]); return the decision.

        ``may_raise`` False holds a lowered alarm down on this update (the detector's press hold): the count of
        decisions above the threshold goes on, and a raised alarm is kept or cleared as usual.
        A non-finite or out-of-range ``p_slip`` raises ``ValueError`` and leaves the state unchanged.
        """
        p = float(p_slip)
        alarm, rising = self.advance(p, may_raise)
        frac = None
        if p_members is not None:
            # Five members once per decision: plain floats (float32 values compared exactly as float64).
            pm = np.asarray(p_members).reshape(-1).tolist()
            frac = sum(1 for v in pm if v >= self.threshold) / len(pm) if pm else 0.0
        return DecisionResult(alarm, rising, self.risk(p), frac)

    def advance(self, p_slip: float, may_raise: bool = True, contact_risk: float | None = None) -> tuple[bool, bool]:
        """``update`` without its result object: (alarm, rising edge). The detector's call, once per decision and
        sensor. ``contact_risk``: the window's contact risk, for the limit guard (None: no contact state, the run
        starts again)."""
        p = p_slip
        if not (math.isfinite(p) and 0.0 <= p <= 1.0):
            raise ValueError(f"p_slip must be a probability in [0, 1], got {p_slip!r}")
        # Raised at the threshold; once raised, held down to threshold - hysteresis.
        self._above = self._above + 1 if p >= self.threshold else 0
        guard = self.limit_guard
        if guard is not None:
            # (NaN compares False: no run)
            self._at_limit = self._at_limit + 1 if contact_risk is not None and contact_risk >= guard else 0
            self.guarded = self._at_limit >= self.limit_guard_decisions
        elif self.guarded:  # (a reload switched the guard off while it held: it lets go)
            self._at_limit, self.guarded = 0, False
        if self.alarm:
            alarm = p >= self.threshold - self.hysteresis or self.guarded
        else:
            # Raising needs min_consecutive decisions in a row at or above the threshold, or the limit guard.
            alarm = may_raise and (self._above >= self.min_consecutive or self.guarded)
        rising = alarm and not self.alarm
        self.alarm = alarm
        return alarm, rising

    def risk(self, p_slip: float) -> float:
        """The risk level of a probability (see the module docstring); 1 while the limit guard holds (the grasp is at
        its friction limit: the full reaction)."""
        return 1.0 if self.guarded else min(1.0, p_slip / self.threshold)


class Detection(NamedTuple):
    """One decision: made after sample ``index`` (counted since the detector started), on sensor ``sensor``
    (0, or 1 for the second finger's array).

    Immutable: the loop hands it to other threads (taps, scrape-time metrics), which read it whole. A named tuple, not a
    frozen dataclass: it is made once per decision and sensor on the hot path, and a frozen dataclass's construction
    (one ``object.__setattr__`` per field) costs several times a tuple's."""

    index: int  # type: ignore[assignment]  # (the field hides tuple.index, which nothing here calls)
    t_us: int
    p_slip: float
    risk: float
    alarm: bool
    rising_edge: bool
    valid: bool = True
    sensor: int = 0
    contact: ContactState | None = None
    """Per-pillar slip, friction estimate, continuous contact risk (``slipd.detect.contact``); None where the
    detector keeps no contact state."""
    rule_only: bool = False
    """The alarm stands on the heuristic the model confirms alone (``decision.confirm_rule``): the model's own alarm
    is down. Grip control takes no friction sample from such an alarm (it comes while some pillars still stick)."""

    def with_contact(self, contact: ContactState | None) -> Detection:
        """This decision with its contact state."""
        return Detection(self.index, self.t_us, self.p_slip, self.risk, self.alarm, self.rising_edge, self.valid,
                         self.sensor, contact)
