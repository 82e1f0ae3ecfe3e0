"""Grip-force control: hold with the least force that keeps a friction margin (``reaction.policy: grip_control``).

Per decision the detector's ``ContactState`` gives the grip on the finger (sum Fz), the load it carries
(|sum Ft|), the friction coefficient estimated from pillars seen sliding, and the contact risk. The grip
this finger needs so that the friction in use stays at ``margin`` of the capacity is

    required = |sum Ft| / (mu * margin)

(unknown until a pillar was seen sliding: incipient slip is what tells the friction, before the object
moves). The target grip rises to ``required * (1 + risk - raise_risk)`` (before the friction is known:
``grip * (1 + max(risk - raise_risk, 0.1))``) whenever the risk is above ``raise_risk`` (or the detector's
alarm is up), and to ``required`` whenever that exceeds the target, at most ``rise_n_s`` (the servo's rate), never
beyond ``max_force_n`` (the object's limit); once the risk stayed below ``raise_risk`` for
``relax_after_s`` it relaxes at ``relax_n_s`` towards ``max(required, holding force)``, the grip the hold
setting produced before the controller first acted. The arm is stopped (once per grasp) when the risk
stayed at ``stop_risk`` for ``stop_after_s``, or when the target sits at the force limit while more is needed.

Commands go to the gripper's worker thread at most ``update_hz`` times a second (the MX-28 refreshes at
about 62 Hz), and only when the previous one has finished: a slow servo gets the newest target, never a
queue. Fail safe as the reaction: a grip command that fails stops the arm (``Reaction.failsafe``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from slipd.geometry import CONTACT_THRESHOLD_N

if TYPE_CHECKING:
    from slipd.config import ReactionConfig
    from slipd.daemon.worker import DeviceWorker
    from slipd.detect.contact import ContactState
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.grip_control")


@dataclass(frozen=True)
class GripControlSettings:
    """The policy's parameters (``reaction.grip_*`` in the config)."""

    margin: float = 0.7
    max_force_n: float = 30.0
    rise_n_s: float = 200.0
    relax_n_s: float = 2.0
    relax_after_s: float = 1.0
    raise_risk: float = 0.3
    stop_risk: float = 0.9
    stop_after_s: float = 0.15
    """The risk must stay at ``stop_risk`` this long: the grip had its chance to catch the slip."""
    update_hz: float = 62.0
    resolution_n: float = 0.05
    """Target changes smaller than this are not sent (about one PWM step of a 40 N jaw)."""

    @classmethod
    def from_config(cls, cfg: ReactionConfig) -> GripControlSettings:
        return cls(margin=cfg.grip_margin, max_force_n=cfg.grip_max_force_n, rise_n_s=cfg.grip_rise_n_s,
                   relax_n_s=cfg.grip_relax_n_s, relax_after_s=cfg.grip_relax_after_s,
                   raise_risk=cfg.grip_raise_risk, stop_risk=cfg.grip_stop_risk, update_hz=cfg.grip_update_hz)


class GripController:
    """Turns contact states into grip-force commands (see the module docstring); one per gripper."""

    def __init__(self, settings: GripControlSettings, *, gripper: Any, gripper_worker: DeviceWorker | None,
                 stop_arm: Callable[[str], Any], failsafe: Callable[[str], Any], metrics: Metrics | None = None
                 ) -> None:
        self.s = settings
        self.gripper, self.worker = gripper, gripper_worker
        self.stop_arm, self.failsafe = stop_arm, failsafe
        self.metrics = metrics
        self.reset()
        self.commands = 0
        self.stops = 0

    def reset(self) -> None:
        """A new grasp (or none): the controller has not acted."""
        self.target: float | None = None
        self.hold_n = 0.0
        self._t: float | None = None
        self._low_since: float | None = None
        self._high_since: float | None = None
        self._sent: float | None = None
        self._sent_t = -math.inf
        self._pending: Future[Any] | None = None
        self.arm_stopped = False
        if getattr(self, "metrics", None) is not None:
            self.metrics.grip_target.set(0.0)  # type: ignore[union-attr]

    def update(self, state: ContactState | None, now: float, *, alarm: bool = False) -> None:
        """One decision's contact state at monotonic time ``now``; ``alarm``: the detector's alarm is up
        (counts as a risk above ``raise_risk``)."""
        s = self.s
        if state is None or state.grip_n <= CONTACT_THRESHOLD_N:
            if self.target is not None or self.arm_stopped:
                self.reset()  # released: the next grasp starts from its hold setting
            return
        dt = 0.0 if self._t is None else max(0.0, now - self._t)
        self._t = now
        mu = state.friction
        required = state.load_n / (mu * s.margin) if mu is not None and mu > 0 else 0.0
        risky = state.risk > s.raise_risk or alarm
        if self.target is None:
            self.hold_n = max(self.hold_n, state.grip_n)  # what the hold setting produces, until we act
            if not risky and required <= state.grip_n:
                return
            self.target = state.grip_n
        if risky:
            self._low_since = None
            # A contact at risk needs more margin: the requirement grows with the risk. Before the friction is
            # known (no pillar seen sliding yet) the grip itself grows with it.
            boost = 1.0 + max(state.risk - s.raise_risk, 0.0 if mu is not None else 0.1)
            want = required * boost if mu is not None else state.grip_n * boost
        else:
            self._low_since = now if self._low_since is None else self._low_since
            want = required
        target = self.target
        if want > target:
            target = min(want, target + s.rise_n_s * dt)
        elif not risky and now - self._low_since >= s.relax_after_s:  # type: ignore[operator]
            target = max(want, self.hold_n, target - s.relax_n_s * dt)
        target = min(target, s.max_force_n)
        if not math.isfinite(target):
            return  # a NaN never reaches the servo; the last command stands
        self.target = target
        at_limit = target >= s.max_force_n - 1e-9 and (want > s.max_force_n or risky)
        if state.risk >= s.stop_risk:
            self._high_since = now if self._high_since is None else self._high_since
        else:
            self._high_since = None
        high = self._high_since is not None and now - self._high_since >= s.stop_after_s
        if not self.arm_stopped and (high or at_limit):
            self.arm_stopped = True
            self.stops += 1
            why = "risk" if high else "grip at its limit"
            log.warning("grip control: stopping the arm (%s: risk %.2f, target %.1f N)", why, state.risk, target)
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
            if exc is not None:
                log.error("grip command failed: %s", exc)
                if self.metrics is not None:
                    self.metrics.device_errors.labels(device="gripper", kind="grip_control").inc()
                self._sent = None  # send again once it answers
                self.failsafe("grip_control failed")

        fut.add_done_callback(done)
