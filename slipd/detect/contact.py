"""The contact's state beside the alarm: per-pillar slip, friction estimate, continuous risk, grip and load.

One ``ContactStream`` per sensor runs the shared feature pipeline (``FeatureStream``: sanitise, tare, clip,
causal median) on all nine pillars' fx, fy, fz, with the detector's window and stride, so its windows end on
exactly the samples the detector decides on. Per window: ``PillarSlip`` (per-pillar P(slip)),
``FrictionEstimator`` (mu from the sliding pillars; reset when the contact is released) and
``contact_risk`` (load-weighted share slipping or near the limit). The result is a ``ContactState``
that the detector attaches to its ``Detection``; the grip-force policy (``slipd.daemon.grip_control``)
reads it, the recorder and ``slipd replay --json`` write it, metrics export it. A gripper with a sensor on each
finger has one grip: ``grasp_state`` makes the fingers' states of one decision the grasp's.

A model with an auxiliary per-pillar head would fill ``pillar_slip`` from its output instead (``source``
"model"); the shipped ensemble has none, so ``source`` is "features".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from slipd.detect.features import FeatureSpec, FeatureStream
from slipd.detect.friction import FrictionEstimator
from slipd.detect.pillar_slip import PillarSlip, PillarSlipParams
from slipd.detect.risk import contact_risk
from slipd.geometry import CONTACT_THRESHOLD_N, N_PILLARS

RISK_MARGIN = 0.3
"""Default margin of ``contact_risk``: a pillar starts to count at 70 % of its friction limit."""
RISK_TOP_SHARE = 0.9
"""A pillar marked sliding counts in the risk only at this share of the contact's top utilisation or above: a sliding
tip sits on the limit, so one well below the others' ratio is a misjudged sticking one."""
FRICTION_TOP_SHARE = 0.5
"""The friction samples' looser cut: with per-pillar friction spread a sliding pillar sits on its *own* limit, so the
top share alone keeps only the grippiest pillars and the estimate ran high; 0.5 still drops the misjudged pillars far
below the top. `python tools/evaluate.py --contact --sets robust`, spread family within 15 %: 52 % at 0.9, 68 % at
0.7 (median error +13.9 % and +9.9 %) while the pillar estimate marked only pillars near the top utilisation; once it
marks the pillars that stop at their own lower limit (``PillarSlipParams.far``), 88 % at 0.7 and 96 % at 0.5 on the
test split (92 % and 96 % on the train split: ``--split train``), the other families unchanged or better."""
FRICTION_FORGET = 0.9
"""Forgetting per decision with samples (a memory of about 0.1 s of sliding): the samples of the incipient phase, when
the pillar estimate marks pillars sliding before they reach the limit, are low ones, and a memory of seconds kept them
in the estimate at gross slip. With ``FRICTION_TOP_SHARE`` and samples from the contact threshold up (pillars of a
push carry 0.4-0.9 N), the robust test split within 15 % went from 74 % to 86 % and the transfer split from 91 % to
98 % (`python tools/evaluate.py --contact --sets transfer,robust`, measured when that command filtered with a median
of 21 instead of the daemon's 5)."""
FRICTION_PRESS_RISE = 0.05
"""No friction samples from a window over which the contact's summed normal force rose by more than this share: a
press, or a grip closing, splays the pillars (each carries a few per cent of its normal force sideways) and the pillar
estimate can judge one that stops following that splay sliding, at a utilisation of a few hundredths. Such a sample
set the estimate to 0.05 on contacts of 0.5-0.8 (the simulator's still presses), and the risk and grip control then
took a still hold for one at its friction limit."""
FRICTION_REFUTE = 2.0
"""An estimate that a pillar judged sticking uses more than this multiple of is refuted and forgotten: a sticking tip
carries at most mu_s, within a few tens of per cent of mu_k (per-pillar spread included), so a pillar sticking at four
times the estimate says the samples were misjudged ones (the first windows of a shear load, where the splay and the
load cross, left 0.06 on contacts of 0.5-0.8)."""
FRICTION_EDGE_SHARE = 0.2
"""Friction samples come from pillars above the contact threshold and above this share of the heaviest pillar's
normal force. The threshold alone (pillars of a push carry 0.4-0.9 N: transfer split within 15 % 98 % against 91 %
at 1 N) let the light edge pillars of a curved object (0.7 N beside 5-6 N on the rig's shampoo bottle) set the
estimate 20 % above the contact's sliding ratio, and grip control then held it too lightly (it slid 26 mm off
centre); with the share the robust and transfer figures held (94.1 % of 271 within 15 % when it came, 93.4 % without
it)."""


class ContactState(NamedTuple):
    """One window's contact state (forces in N, tared and median-filtered).

    Immutable (a named tuple, as ``Detection``: made once per decision and sensor on the hot path, where a frozen
    dataclass's construction costs several times a tuple's)."""

    pillar_slip: tuple[float, ...]
    """P(slip) of each of the nine pillars (SDK order)."""
    friction: float | None
    """Friction coefficient estimated from the sliding pillars; None until one was seen sliding."""
    friction_sd: float | None
    """Weighted standard deviation of the samples behind ``friction``."""
    risk: float
    """Load-weighted share of the contact that slips or is within the margin of its limit, 0..1."""
    grip_n: float
    """Total normal force (the grip on this finger)."""
    load_n: float
    """Magnitude of the total tangential force (the load the grip must hold)."""
    source: str = "features"
    shear_n: float | None = None
    """Sum of the pillars' tangential force magnitudes: the load with its twist. A torque (an off-centre object)
    loads pillars in opposite directions, which cancels in ``load_n``; the whole contact slides once this
    reaches ``friction * grip_n``. None where it was not computed."""
    pressed_n: float | None = None
    """Sum of the normal forces of all pillars pressed at all (above zero), without the contact threshold: unlike
    ``grip_n`` it does not step when a light pillar flickers across the threshold. None where it was not computed."""
    top_util: float | None = None
    """The highest utilisation of any pressed pillar (above zero), |Ft| / max(Fz, contact threshold): a light pillar's
    ratio is understated, never overstated, so the friction coefficient is at least this (with friction alike across
    the pillars). A contact whose shear / grip is far below it is not sliding as a whole. None where not computed."""

    @property
    def friction_use(self) -> float | None:
        """Share of the contact's friction capacity in use, |sum Ft| / (mu sum Fz); None without mu or grip."""
        if self.friction is None or self.friction <= 0.0 or self.grip_n <= CONTACT_THRESHOLD_N:
            return None
        return self.load_n / (self.friction * self.grip_n)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready (``slipd replay --json``; the recorder keeps the slip map, risk and friction of each decision)."""
        return {"pillar_slip": [round(p, 4) for p in self.pillar_slip], "friction": self.friction,
                "friction_sd": self.friction_sd, "contact_risk": round(self.risk, 4), "grip_n": round(self.grip_n, 4),
                "load_n": round(self.load_n, 4), "pillar_source": self.source,
                "shear_n": None if self.shear_n is None else round(self.shear_n, 4),
                "pressed_n": None if self.pressed_n is None else round(self.pressed_n, 4),
                "top_util": None if self.top_util is None else round(self.top_util, 4)}


def contact_spec(spec: FeatureSpec) -> FeatureSpec:
    """All nine pillars' three axes with ``spec``'s window, stride, median and rate (windows end together)."""
    return FeatureSpec(pillars=tuple(range(N_PILLARS)), channels=("fx", "fy", "fz"), window=spec.window,
                       median=spec.median, rate_hz=spec.rate_hz, stride=spec.step, tare_samples=spec.tare_samples)


class ContactStream:
    """Samples in, a ``ContactState`` at the end of every window (see the module docstring)."""

    def __init__(self, spec: FeatureSpec, offset: np.ndarray | None = None, *, risk_margin: float = RISK_MARGIN,
                 params: PillarSlipParams | None = None) -> None:
        self.spec = contact_spec(spec)
        self.features = FeatureStream(self.spec, offset)
        self.pillars = PillarSlip(params)
        self.friction = FrictionEstimator(min_fz_n=CONTACT_THRESHOLD_N, forget=FRICTION_FORGET,
                                          edge_share=FRICTION_EDGE_SHARE)
        self.risk_margin = float(risk_margin)
        self.latest: ContactState | None = None

    def shares_window(self, spec: FeatureSpec) -> bool:
        """Whether a detector on ``spec`` filters exactly this stream's columns (a derived spec on all nine pillars
        in SDK order with the same median: the shipped model's): its filtered window then serves both the model
        and ``state``, and this stream's own ``features`` stay unused (one median per window, not two)."""
        return spec.derived and spec.columns == self.spec.columns and spec.median == self.spec.median

    def set_offset(self, offset: np.ndarray | None) -> None:
        """The tare offset ([9, 3]) in use from the next sample."""
        self.features.set_offset(offset)

    def reset(self) -> None:
        """Forget history, slip states and the friction estimate (restart, new contact)."""
        self.features.reset()
        self.release()

    def release(self) -> None:
        """The contact ended (the detector's gate says so): forget the slip states and the friction estimate, keep
        the feature history (its windows stay aligned with the detector's)."""
        self.pillars.reset()
        self.friction.reset()
        self.latest = None

    def push(self, force: np.ndarray) -> ContactState | None:
        """One raw sample [9, 3]; the state when a window ends here."""
        window = self.features.push(force)
        return None if window is None else self.state(window)

    def push_many(self, force: np.ndarray) -> list[tuple[int, ContactState]]:
        """A block [k, 9, 3]; ``(i, state)`` for each sample that ends a window."""
        return [(i, self.state(w)) for i, w in self.features.push_many(force)]

    def state(self, window: np.ndarray, pillar_p: np.ndarray | None = None) -> ContactState:
        """The state at the end of one filtered window (fx, fy, fz of the nine pillars, [window, 27] or flattened); with
        ``pillar_p`` (a model's per-pillar P(slip), [9]) that is the slip map instead of the feature estimate."""
        w = window.reshape(self.spec.window, N_PILLARS * 3)
        # Nine pillars once per decision: plain floats (a numpy call on nine values costs more than its work), each
        # sample one flat list (a nested one makes a list per pillar).
        first, last = w[0].tolist(), w[-1].tolist()
        # ``utilisation(last)``, the contact's sums and the pillar estimate's largest rate in one pass (the same
        # operations, in the same order; the contact flags are left to the pillar estimate, which needs them only while
        # a pillar moves).
        thr = CONTACT_THRESHOLD_N
        hypot = math.hypot
        fz = last[2::3]  # (the pillars' normal forces: one slice, not an append per pillar)
        util: list[float] = []
        add_util = util.append
        grip = fx = fy = shear = pressed = top_pressed = 0.0
        top = ref = -1.0
        it, it0 = iter(last), iter(first)
        for x, y, z, x0, y0, _ in zip(it, it, it, it0, it0, it0):  # (a pillar's fx, fy, fz of each sample)
            ft = hypot(x, y)
            if z > thr:  # in contact (pressed too: the threshold is above zero)
                u = ft / z
                add_util(u)
                pressed += z
                if u > top_pressed:  # max(top_pressed, u)
                    top_pressed = u
                grip += z
                fx += x
                fy += y
                shear += ft
                if u > top:
                    top = u
                r = hypot(x - x0, y - y0)
                if r > ref:
                    ref = r
            else:
                u = ft / thr
                add_util(u)
                if z > 0.0:
                    pressed += z
                    if u > top_pressed:
                        top_pressed = u
        p: tuple[float, ...] | list[float]
        if pillar_p is None:
            p, source = self.pillars.step(first, last, (fz, util, None), (ref, top)), "features"
        else:
            p, source = np.asarray(pillar_p, np.float64).tolist(), "model"
        if top < 0.0:
            self.friction.reset()  # released: the next grasp may be another object
            top = 0.0
        load = hypot(fx, fy)
        # Only sliding pillars near the contact's top utilisation are samples of mu, and only they put the grip at
        # risk (``RISK_TOP_SHARE``, ``FRICTION_TOP_SHARE``).
        for q in p:
            if q >= 0.5:
                # Some pillar slides: a friction sample unless the window is a press. (Only then: a sample needs a
                # pillar at 0.5 or above, so a steady grasp skips the press test and the samples, decision after
                # decision.)
                # (sum over a list: a generator's frame switches cost more than the nine additions)
                pressing = grip > (1.0 + FRICTION_PRESS_RISE) * sum([z for z in first[2::3] if z > CONTACT_THRESHOLD_N])
                if pressing:
                    samples = [0.0] * N_PILLARS
                else:
                    cut = FRICTION_TOP_SHARE * top
                    samples = [q if u >= cut else 0.0 for q, u in zip(p, util, strict=True)]
                self.friction.add(util, fz, samples)
                break
        else:
            self.friction.keep(fz)  # no pillar slides: no sample, the normal forces kept for the next one
        est = self.friction.refute(util, fz, p, FRICTION_REFUTE)
        mu = None if est is None else est.mu
        # (positional, in the fields' order: keywords cost a named tuple three times as much)
        state = ContactState(tuple(p), mu, None if est is None else est.sd,
                             contact_risk(fz, util, p, mu, self.risk_margin, RISK_TOP_SHARE * top), grip, load, source,
                             shear, pressed,
                             top_pressed)
        self.latest = state
        return state


def grasp_state(states: Sequence[ContactState | None]) -> ContactState | None:
    """The grasp as the fingers of one gripper see it at one decision (one state per sensor), for the grip controller.

    The jaw presses every finger with the same force, so the grasp needs the grip of the finger nearest its friction
    limit (the highest shear / grip): that finger's state decides, whole, since its grip, shear and utilisation
    must stay consistent with each other (the controller takes the ratio of a sliding contact as a friction sample).
    Beside it: the highest risk of any finger (a slip on either finger is a slip of the grasp), the highest friction
    estimate (both fingers hold one object, and every estimate errs low: ``slipd.daemon.grip_control``), and the
    fingers' mean pressed force, the jaw's force whichever finger decides (the take-over waits for it to be steady;
    a pressed force that switched between two fingers' readings would never be). One sensor: its state as it is;
    a finger out of contact does not count; none in contact: None (released)."""
    if len(states) == 1:
        return states[0]
    touching = [s for s in states if s is not None and s.grip_n > CONTACT_THRESHOLD_N]
    if len(touching) <= 1:
        return touching[0] if touching else None
    decider = max(touching, key=lambda s: max(s.load_n, s.shear_n or 0.0) / s.grip_n)
    known = [s for s in touching if s.friction is not None]
    grippiest = max(known, key=lambda s: s.friction or 0.0) if known else decider
    pressed = [s.pressed_n if s.pressed_n is not None else s.grip_n for s in touching]
    return decider._replace(risk=max(s.risk for s in touching), friction=grippiest.friction,
                   friction_sd=grippiest.friction_sd, pressed_n=sum(pressed) / len(pressed))
