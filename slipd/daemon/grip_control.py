"""Grip-force control: hold with the least force that keeps a friction margin (``reaction.policy: grip_control``).

Per decision the detector's ``ContactState`` gives the grip on the finger (sum Fz), the shear it carries (the
pillars' tangential forces, twist included: ``shear_n``, else the net load ``load_n``), the friction coefficient
estimated from the pillars seen sliding, and the contact risk (with a sensor on each finger, the grasp's state:
``slipd.detect.contact.grasp_state``). The grip this finger needs so that the friction in use stays at ``margin``
of the capacity is

    required = shear / (mu * margin)

with mu the highest estimate of the grasp: a pillar's utilisation never exceeds the friction coefficient, so
the estimate's errors are low ones (a pillar judged sliding before it reached the limit, or one whose slip state
lags after the grip made it stick below the limit), and the margin is against the *kinetic* coefficient that
sliding pillars show.

Take-over: once the grasp has settled (the pressed pillars' normal force steady within 2 % for ``takeover_after_s``)
the controller commands the grip it has (that force: ``grip_n`` leaves out light pillars at the contact threshold),
by force: the servo then holds it with its effort limit and the goal past the object,
so a later raise is one effort change instead of a goal the jaw must travel to first. Nothing changes for the
object.

A slip: the contact *slips* while the detector's alarm is up or the risk is at ``raise_risk`` or above. While it
slides the measured shear is the kinetic friction, mu * grip, not the load, so the load it needs to hold is
unknown; a new slip is therefore caught at once: the target jumps to ``catch`` x the grip it slipped at (and at
least to the requirement) and stays there while the slip lasts, and the requirement, which grows with the grip
while the contact slides, takes it further if needed. A slip whose friction use first rules a whole-contact slide
out (see below) is caught once the use reaches the limit, from the grip it has then: a load that grows slowly (a
cup being filled) slides the whole contact off while the requirement creeps up with the grip at the servo's pace.
A slip that resumes within ``relax_after_s`` of the last one is the same slip (an alarm or a risk flickering as the
contact settles): no new catch. Once the contact holds, the requirement comes from the real load again: after it
stayed quiet for ``relax_after_s`` the target relaxes at ``relax_n_s`` down to it, never below the grip the hold
setting produced (``hold_n``). Every increase is bounded by ``rise_n_s`` (a faster jump splays the pillars and makes
a loaded contact slip all at once) and the target never exceeds ``max_force_n`` (the object's force limit).

A twist (only where ``twist`` is set): a slip whose shear is ``twist`` x the net load or more is an off-centre object
turning. The pillars' lever arms are a few millimetres, so grip buys little torque: the arm stops at once (the lift
no longer adds load), the catch is called off and the requirement is the net load's from then on. Off by default: on
the rig every off-centre object (centre of mass 4 mm out) is held within the servo's force, and the rule stopped
lifts the grip finishes; a torque the grip cannot hold still stops the arm at the force limit.

A contact on one pillar never shows the asynchronous deceleration the pillar estimator reads, so its friction
stays unknown. While the alarm is up and the catch has not yet raised the grip, the whole contact slides on its
limit, so its utilisation shear / grip is a sample of the friction coefficient (a lower bound where the alarm
comes early): the controller feeds it to its own ``FrictionEstimator`` (the estimator the contact stream uses)
and uses it until the contact's own estimate exists. Not where a pressed pillar already uses clearly more of its
cone (``ContactState.top_util``): no friction is below a pillar's utilisation, so that contact is not sliding as a
whole and the alarm's ratio is no sample (the catch still answers the alarm). Without the contact's own estimate
the target does not relax below the grip that ended the last slip.

The arm is stopped (once per grasp) for a twist (where set), when the risk stayed at ``stop_risk`` for
``stop_after_s`` (the grip had its chance to catch the slip), or at the force limit: the object needs more than it
may take, or it still slips with the grip there. Commands go to the gripper's worker thread at most ``update_hz``
times a second (the MX-28 refreshes at about 62 Hz), and only when the previous one has finished: a slow servo gets
the newest target, never a queue. Fail safe as the reaction: a grip command that fails stops the arm
(``Reaction.failsafe``).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from slipd.detect.friction import FrictionEstimator
from slipd.geometry import CONTACT_THRESHOLD_N

if TYPE_CHECKING:
    from slipd.config import ReactionConfig
    from slipd.daemon.worker import DeviceWorker
    from slipd.detect.contact import ContactState
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.grip_control")

ALARM_SAMPLE_RISE = 1.02
"""The alarm's friction samples are taken only while the grip is within 2 % of the one the slip started at:
once the catch raised the grip the contact sticks again and shear / grip falls below the friction."""

ALARM_SAMPLE_SLACK = 1.5
"""... and only while no pressed pillar shows a utilisation above this multiple of the contact's shear / grip. A
pillar's utilisation never exceeds the friction coefficient, so a contact sliding as a whole at that ratio is ruled out
(a static coefficient up to 1.5 x the kinetic one; the rig's objects 1.2-1.25): the alarm is the lift's, on a cup
that sticks at 0.04 on its one loaded pillar while its light pillars sit at 0.2-0.3, and taking its ratio for the
friction set a requirement that climbed to the force limit as the cup was filled (arm stopped in 11 of 30 runs)."""

MIN_TWIST_SHEAR_N = 0.3
"""Below this shear the ratio to the net load is the pillars' noise, not a twist."""
STEADY_SHARE = 0.02
"""The grip counts as steady while it stays within 2 % (the grasp has stopped closing)."""
LIMIT_REACHED = 0.97
"""The grip counts as at the force limit from this share of it (the servo's force settles within a few %)."""


@dataclass(frozen=True)
class GripControlSettings:
    """The policy's parameters (``reaction.grip_*`` in the config)."""

    margin: float = 0.7
    max_force_n: float = 30.0
    catch: float = 2.0
    """At the start of a slip the target jumps to this multiple of the grip (the load is unknown while it slides)."""
    takeover_after_s: float = 0.1
    """The controller takes the grip over (by force, at the force it has) once it stayed steady this long."""
    twist: float | None = None
    """A slip whose shear is this multiple of the net load or more is a twist (an off-centre object turning): the
    pillars' short lever arms need far more grip against a torque than against a load, so the arm stops at once.
    None: no twist rule (a twist is a slip the grip catches; the force limit stops the arm)."""
    rise_n_s: float = 800.0
    """Fastest increase of the target (N/s): within the jaw's rate when it closes by position
    (``reaction.grip_rise_n_s`` says what slower and faster did on the rig)."""
    relax_n_s: float = 2.0
    relax_after_s: float = 1.0
    raise_risk: float = 0.5
    stop_risk: float = 0.9
    stop_after_s: float = 0.15
    """The risk must stay at ``stop_risk`` this long: the grip had its chance to catch the slip."""
    update_hz: float = 62.0
    resolution_n: float = 0.05
    """Target changes smaller than this are not sent (about one PWM step of a 40 N jaw)."""

    @classmethod
    def from_config(cls, cfg: ReactionConfig) -> GripControlSettings:
        return cls(margin=cfg.grip_margin, max_force_n=cfg.grip_max_force_n, catch=cfg.grip_catch,
                   takeover_after_s=cfg.grip_takeover_after_s, twist=cfg.grip_twist, rise_n_s=cfg.grip_rise_n_s,
                   relax_n_s=cfg.grip_relax_n_s, relax_after_s=cfg.grip_relax_after_s,
                   raise_risk=cfg.grip_raise_risk, stop_risk=cfg.grip_stop_risk, stop_after_s=cfg.grip_stop_after_s,
                   update_hz=cfg.grip_update_hz)


class GripController:
    """Turns contact states into grip-force commands (see the module docstring); one per gripper."""

    def __init__(self, settings: GripControlSettings, *, gripper: Any, gripper_worker: DeviceWorker | None,
                 stop_arm: Callable[[str], Any], failsafe: Callable[[str], Any], metrics: Metrics | None = None
                 ) -> None:
        self.s = settings
        self.gripper, self.worker = gripper, gripper_worker
        self.stop_arm, self.failsafe = stop_arm, failsafe
        self.metrics = metrics
        self.alarm_friction = FrictionEstimator(min_fz_n=CONTACT_THRESHOLD_N)
        """Friction from the alarm (whole-contact samples) for contacts the pillar estimate cannot read."""
        self.reset()
        self.commands = 0
        self.stops = 0
        self._failing = False  # the latest grip command failed (one fail-safe per run of failures)

    def reset(self) -> None:
        """A new grasp (or none): the controller has not acted."""
        self.target: float | None = None
        self.hold_n = 0.0
        self._t: float | None = None
        self._low_since: float | None = None
        self._high_since: float | None = None
        self._slipping = False
        self._slip_end: float | None = None
        self._steady_n, self._steady_since = 0.0, math.inf
        self._slip_grip = 0.0
        self._catch_n = 0.0  # the catch's level, held while the slip lasts
        self._caught = False  # this slip (with the flickers that belong to it) has had its catch
        self._mu: float | None = None  # the highest friction estimate of the grasp
        self._twist = False
        self._grasp_mu: float | None = None  # the contact's friction estimate at the take-over (the closing's)
        self._risk_armed = False
        self._own_mu = False  # the contact's own estimate (not only the alarm's) is behind the friction in use
        self._caught_n = 0.0  # the grip that ended the last slip (the floor while no friction is known)
        self._sent: float | None = None
        self._sent_t = -math.inf
        self._pending: Future[Any] | None = None
        self.arm_stopped = False
        self.alarm_friction.reset()
        if getattr(self, "metrics", None) is not None:
            self.metrics.grip_target.set(0.0)  # type: ignore[union-attr]

    def secured(self, newtons: float) -> None:
        """The fail-safe gripped at ``newtons`` behind the controller's back (``on_failsafe: stop_arm_and_tighten``):
        that is the grip now, sent. Once decisions come again the controller relaxes from it as from its own target;
        without this it kept its older, lower target as sent and never commanded it again, so the jaw stayed at the
        limit while the controller believed it held less."""
        if self.target is not None:
            self.target = self._sent = float(newtons)

    def update(self, state: ContactState | None, now: float, *, alarm: bool = False,
               sampled: bool | None = None) -> None:
        """One decision's contact state at monotonic time ``now``; ``alarm``: the detector's alarm is up
        (the contact slips, whatever the risk); ``sampled``: the alarm may give a friction sample (None: as
        ``alarm``). The model's alarm comes once the contact slides on its limit; the confirmed heuristic's
        (``decision.confirm_rule``) while some pillars still stick, where the contact's shear / grip is below its
        friction: taken as a sample, it asked for more grip than the object needs (on the rig, heavy objects went to
        the 40 N limit and the arm stopped)."""
        s = self.s
        if state is None or state.grip_n <= CONTACT_THRESHOLD_N:
            if self.target is not None or self.arm_stopped or self.alarm_friction.samples:
                self.reset()  # released: the next grasp starts from its hold setting
            return
        dt = 0.0 if self._t is None else max(0.0, now - self._t)
        self._t = now
        grip = state.grip_n
        shear = max(state.load_n, state.shear_n or 0.0)
        if self.target is None:
            # Hands off while the jaw closes: pillars splay and slide as the grip builds up, which says nothing about
            # the load (the slip states and friction samples they leave are the closing's, not the object's). The
            # detector's alarm alone counts (its model has seen grasps close).
            # The grip the hold setting produces, until we act: the pressed pillars' whole normal force. A light pillar
            # at the contact threshold flickers in and out of ``grip_n`` (0.5 N steps on the rig's filling cup, held at
            # 3.3 N): steadiness judged on ``grip_n`` kept the grasp from ever counting as settled, so the controller
            # never took over and the cup slid out unanswered; and a take-over at ``grip_n`` commanded 2.8 N where the
            # jaw held 3.3, which left the cup on its one loaded pillar, with nothing that could show it slide.
            pressed = state.pressed_n if state.pressed_n is not None else grip
            self.hold_n = max(self.hold_n, pressed)
            if abs(pressed - self._steady_n) > STEADY_SHARE * self._steady_n:
                self._steady_n, self._steady_since = pressed, now
            if not alarm and now - self._steady_since < s.takeover_after_s:
                return
            # The grasp has settled (or slips): take the grip over at the force it has. The servo then holds it by
            # its effort limit with the goal past the object, so a later catch is one effort change instead of a
            # goal the jaw must travel to first.
            self.target = pressed
            self._grasp_mu = state.friction
            self._risk_armed = state.risk < s.raise_risk
        # A risk still up from the closing counts once it has been down; a friction estimate that has not moved
        # since the take-over is the closing's.
        self._risk_armed = self._risk_armed or state.risk < s.raise_risk
        slipping = alarm or (self._risk_armed and state.risk >= s.raise_risk)
        # A slip that resumes soon after the last one ended (an alarm or risk flickering as the contact settles)
        # is the same slip: it is not caught again from an already raised grip.
        new_slip = slipping and not self._slipping and (
            self._slip_end is None or now - self._slip_end >= s.relax_after_s)
        if new_slip:
            self._slip_grip = grip
            self._caught = False
        ratio = shear / grip
        sample = alarm if sampled is None else sampled
        if (sample and state.friction is None and grip <= self._slip_grip * ALARM_SAMPLE_RISE
                and (state.top_util is None or state.top_util <= ALARM_SAMPLE_SLACK * ratio)):
            # The alarm says the contact slides: a sliding contact sits on its friction limit (unless a pillar
            # already uses more of its cone than that: ``ALARM_SAMPLE_SLACK``).
            self.alarm_friction.update([ratio], [grip], [1.0])
        # A pillar's utilisation never exceeds the friction coefficient, so every sample of an estimate is at most
        # mu; its errors are low ones (a pillar judged sliding before it reached the limit, or one whose slip state
        # lags after the catch made it stick below the limit). The highest estimate of the grasp is the best one.
        own = state.friction if state.friction is not None and state.friction != self._grasp_mu else None
        from_alarm = self.alarm_friction.estimate()
        if self._own_mu and state.friction is None:
            # The contact forgot its estimate in contact: refuted (a sticking pillar uses far more than it,
            # ``slipd.detect.contact.FRICTION_REFUTE``). The highest estimate is the best one only among valid ones.
            self._mu, self._own_mu = None, False
        for est in (own, None if from_alarm is None else from_alarm.mu):
            if est is not None and est > 0 and math.isfinite(est):
                self._mu = max(est, self._mu or 0.0)
        self._own_mu = self._own_mu or own is not None
        mu = self._mu
        # A twist (the arm has stopped for it) is carried by the pillars' lever arms, which grip cannot scale up
        # usefully: from then on the requirement is the net load's.
        load = state.load_n if self._twist else shear
        required = load / (mu * s.margin) if mu is not None else 0.0
        target = self.target
        if slipping:
            self._low_since = None
            # While it slides the shear is mu * grip, so the requirement grows with the grip by itself (1 / margin
            # per servo response) until the contact holds; a new slip is caught at once.
            # Every friction estimate errs low, so the use computed with it errs high: a contact whose computed use
            # is below halfway from the margin to the limit cannot be sliding as a whole (an alarm on a load that
            # changes, or on the pillars splaying under a rising grip). It keeps its requirement, without a catch.
            # The computed use can also be low where the estimate comes from pillars whose ratio exceeds the contact's
            # (light edge pillars of a curved object, a load off-centre): the alarm and the risk agreeing is a slip.
            plausible = (mu is None or shear / (mu * grip) >= (1.0 + s.margin) / 2
                         or (alarm and state.risk >= s.raise_risk))
            if plausible and not self._caught:
                # One catch per slip: at its start from the grip it slipped at; a slip that only became plausible
                # later (a load growing slowly to the limit, as a cup being filled: the requirement alone then creeps
                # up with the grip at the servo's pace while the whole contact slides) from the grip it has now.
                self._catch_n = (self._slip_grip if new_slip else grip) * s.catch
                self._caught = True
            want = max(required, self._catch_n)
        else:
            if self._slipping:
                self._caught_n = max(self._caught_n, grip)
                self._slip_end = now
                self._catch_n = 0.0
            self._low_since = now if self._low_since is None else self._low_since
            want = required
        self._slipping = slipping
        if want > target:
            target = min(want, target + s.rise_n_s * dt)
        elif not slipping and now - self._low_since >= s.relax_after_s:  # type: ignore[operator]
            # Without the contact's own estimate the friction is the alarm's rough one (or none): never below the
            # grip that ended the last slip, as a slide the detector misses on one pillar would go on unseen.
            floor = self.hold_n if self._own_mu else max(self.hold_n, self._caught_n)
            target = max(want, floor, target - s.relax_n_s * dt)
        target = min(target, s.max_force_n)
        if not math.isfinite(target):
            return  # a NaN never reaches the servo; the last command stands
        self.target = target
        # At the limit: the object needs more than it may take, or it still slips with the grip there.
        at_limit = target >= s.max_force_n - 1e-9 and (
            required > s.max_force_n or (slipping and grip >= LIMIT_REACHED * s.max_force_n))
        if state.risk >= s.stop_risk:
            self._high_since = now if self._high_since is None else self._high_since
        else:
            self._high_since = None
        high = self._high_since is not None and now - self._high_since >= s.stop_after_s
        twisting = (s.twist is not None and slipping and shear >= s.twist * state.load_n
                    and shear > MIN_TWIST_SHEAR_N)
        if twisting and not self._twist:
            self._twist = True
            self._catch_n = 0.0  # the arm stop holds a twist; a grip jump would make the pillars slip all at once
            self._caught = True
            self.target = target = min(max(min(target, grip), state.load_n / (mu * s.margin) if mu else 0.0),
                                       s.max_force_n)  # never beyond the object's force limit
        if not self.arm_stopped and (high or at_limit or twisting):
            self.arm_stopped = True
            self.stops += 1
            why = "risk" if high else "grip at its limit" if at_limit else "twist"
            log.warning("grip control: stopping the arm (%s: risk %.2f, target %.1f N)", why, state.risk, target)
            if self.metrics is not None:
                self.metrics.grip_stops.labels(reason="risk" if high else "limit" if at_limit else "twist").inc()
            self.stop_arm(f"grip control: {why}")
        self._send(now)

    def _send(self, now: float) -> None:
        target = self.target
        if target is None or self.gripper is None:
            return
        if self._sent is not None and abs(target - self._sent) < self.s.resolution_n:
            return
        if now - self._sent_t < 1.0 / self.s.update_hz or (self._pending is not None and not self._pending.done()):
            return
        self._sent, self._sent_t = target, now
        self.commands += 1
        if self.metrics is not None:
            self.metrics.grip_target.set(target)
        call = self.gripper.grip_force
        fut: Future[Any]
        if self.worker is not None:
            fut = self.worker.submit(lambda: call(target))
        else:
            fut = Future()
            try:
                fut.set_result(call(target))
            except Exception as exc:  # reported like a worker would
                fut.set_exception(exc)
        self._pending = fut

        def done(f: Future[Any]) -> None:
            exc = f.exception()
            if exc is None:
                self._failing = False
                return
            if self.metrics is not None:
                self.metrics.device_errors.labels(device="gripper", kind="grip_control").inc()
            self._sent = None  # send again once it answers
            if not self._failing:
                # One fail-safe per run of failures: a silent servo fails every command at the servo rate, and a
                # fail-safe each time would log and queue an arm stop 60 times a second.
                self._failing = True
                log.error("grip command failed: %s", exc)
                self.failsafe("grip_control failed")

        fut.add_done_callback(done)
