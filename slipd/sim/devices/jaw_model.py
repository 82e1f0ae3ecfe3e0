"""The gripper behind the emulated servo: jaw position and grip force over time.

Goal Position closes the jaw (a first-order servo lag with a speed limit); once the jaw meets the
object the grip force grows with the position error, limited by Goal PWM (2.0) or Torque Limit (1.0);
grip force follows its target through a second first-order lag, and commands take effect on the
servo's refresh ticks (the method's rig refreshed the MX-28 at about 62 Hz). The model is integrated
lazily up to "now" whenever someone looks, so no physics thread spins. Positions are encoder ticks
(4096 per revolution).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass
class JawParams:
    """Parameters of the emulated gripper behind the servo (positions in encoder ticks, 4096/rev)."""

    contact_position: float | None = 2048.0  # jaw meets the object here; None = nothing in the jaw
    closing_sign: int = 1  # +1: increasing ticks close the jaw
    stiffness_n_per_tick: float = 0.1  # grip force per tick of servo set-point past contact
    max_force_n: float = 40.0  # grip force at 100 % PWM / torque limit
    servo_tau_s: float = 0.03  # position set-point lag
    force_tau_s: float = 1.0 / 62.0  # grip force lag behind its target
    refresh_hz: float | None = 62.0  # commands take effect on these ticks (None = immediately)
    max_speed_ticks_s: float = 55.0 / 60.0 * 4096.0  # no-load speed at 12 V
    initial_position: float = 1024.0
    overload_after_s: float | None = None  # force held at its limit this long -> overload (None = never)
    step_s: float = 0.001  # integration step

    def __post_init__(self) -> None:
        if self.closing_sign not in (1, -1):
            raise ValueError(f"JawParams.closing_sign must be +1 or -1, got {self.closing_sign!r}")
        positive = ("stiffness_n_per_tick", "max_force_n", "servo_tau_s", "force_tau_s", "max_speed_ticks_s", "step_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"JawParams.{name} must be > 0, got {getattr(self, name)!r}")
        if self.refresh_hz is not None and not self.refresh_hz > 0:
            raise ValueError(f"JawParams.refresh_hz must be > 0 or None, got {self.refresh_hz!r}")


class JawModel:
    """Servo set-point, jaw position and grip force over (model) time; not thread-safe on its own."""

    def __init__(self, params: JawParams, t0: float) -> None:
        self.p = params
        self.t0 = self.t = t0
        self.setpoint = self.position = float(params.initial_position)
        self.velocity = 0.0  # ticks/s of the reported jaw position
        self.force = 0.0
        self.goal = float(params.initial_position)
        self.effort = 1.0  # fraction of full PWM / torque
        self.torque_on = False
        self.saturated_for = 0.0
        self.overloaded = False
        self._pending: deque[tuple[float, dict[str, float | bool]]] = deque()

    # Commands -------------------------------------------------------------------------------------
    def command(self, t: float, **changes: float | bool) -> float:
        """Schedule ``goal`` / ``effort`` / ``torque_on`` changes; returns the time they take effect."""
        t_apply = t
        hz = self.p.refresh_hz
        if hz:
            t_apply = self.t0 + math.ceil((t - self.t0) * hz - 1e-9) / hz
        self.advance(t)
        self._pending.append((max(t_apply, self.t), changes))
        return t_apply

    def _apply(self, changes: dict[str, float | bool]) -> None:
        if "torque_on" in changes:
            on = bool(changes["torque_on"])
            if on and not self.torque_on:
                self.setpoint = self.position  # a servo holds where it is when torque comes on
            self.torque_on = on
        if "goal" in changes:
            self.goal = float(changes["goal"])
        if "effort" in changes:
            self.effort = min(1.0, max(0.0, float(changes["effort"])))

    # Physics --------------------------------------------------------------------------------------
    def force_limit(self) -> float:
        return self.p.max_force_n * self.effort if self.torque_on else 0.0

    def _penetration(self, setpoint: float) -> float:
        c = self.p.contact_position
        return 0.0 if c is None else max(0.0, (setpoint - c) * self.p.closing_sign)

    def _force_target(self) -> tuple[float, bool]:
        if not self.torque_on:
            return 0.0, False
        want = self.p.stiffness_n_per_tick * self._penetration(self.setpoint)
        lim = self.force_limit()
        return min(want, lim), want > lim and lim > 0.0

    def _jaw_position(self) -> float:
        c = self.p.contact_position
        if c is None or self._penetration(self.setpoint) == 0.0:
            return self.setpoint
        # In contact the jaw stands at the object, compressed by the force it actually exerts.
        return c + self.p.closing_sign * self.force / self.p.stiffness_n_per_tick

    def _step(self, h: float) -> None:
        p = self.p
        if self.torque_on:
            a = 1.0 - math.exp(-h / p.servo_tau_s)
            vmax = p.max_speed_ticks_s * h
            self.setpoint += max(-vmax, min(vmax, (self.goal - self.setpoint) * a))
        else:
            # Limp: the object pushes the jaw back to the contact; the set-point follows the jaw.
            self.setpoint = self._jaw_position()
        target, saturated = self._force_target()
        self.force += (target - self.force) * (1.0 - math.exp(-h / p.force_tau_s))
        new_pos = self._jaw_position()
        self.velocity = (new_pos - self.position) / h
        self.position = new_pos
        if saturated and p.overload_after_s is not None:
            self.saturated_for += h
            if self.saturated_for >= p.overload_after_s:
                self.overloaded = True
        else:
            self.saturated_for = 0.0

    def advance(self, t: float) -> None:
        """Integrate up to time ``t`` (no-op for times in the past), applying due commands in order."""
        if t - self.t > 5.0 and not self._pending:
            self.t = t - 1.0  # long idle: the lags have long settled; integrate only the last second
        while self.t < t or (self._pending and self._pending[0][0] <= self.t):
            if self._pending and self._pending[0][0] <= self.t:
                self._apply(self._pending.popleft()[1])
                continue
            stop = t if not self._pending else min(t, self._pending[0][0])
            h = min(self.p.step_s, stop - self.t)
            if h <= 0:
                break
            self._step(h)
            self.t += h
