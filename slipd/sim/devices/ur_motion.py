"""The emulated UR arm's motion: the TCP pose along a straight line with a trapezoidal speed profile.

Apart from the controller (``slipd.sim.devices.ur_controller``), which runs it in its child process: the
motion is plain kinematics, the controller is protocol, scripts and safety state.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


class LinearMotion:
    """TCP pose moving along a straight line in pose space with a trapezoidal speed profile."""

    def __init__(self, pose: Sequence[float]) -> None:
        self.pose = [float(x) for x in pose]
        self.velocity = [0.0] * 6
        self._start = list(self.pose)
        self._dir = [0.0] * 6
        self._length = self._s = self._v = self._vmax = self._acc = 0.0
        self._stop_decel = 0.0
        self.active = False

    @property
    def speed(self) -> float:
        """Path speed (m/s, or rad/s for a pure rotation)."""
        return self._v

    def move_to(self, target: Sequence[float], speed: float, accel: float) -> None:
        """Start a linear move to ``target`` at up to ``speed`` with ``accel``; keeps the current speed's
        component along the new direction so a replacing move has no speed jump."""
        if len(target) != 6 or not all(math.isfinite(x) for x in target):
            raise ValueError(f"moveL target must be 6 finite numbers, got {list(target)!r}")
        if speed <= 0 or accel <= 0:
            raise ValueError(f"moveL speed and acceleration must be > 0, got speed={speed} accel={accel}")
        delta = [float(t) - p for t, p in zip(target, self.pose)]
        length = math.sqrt(sum(d * d for d in delta[:3]))
        if length < 1e-9:  # pure rotation: the path parameter is the rotation angle
            length = math.sqrt(sum(d * d for d in delta[3:]))
        if length < 1e-12:
            self.active, self._v, self.velocity = False, 0.0, [0.0] * 6
            return
        new_dir = [d / length for d in delta]
        carried = sum(v * d for v, d in zip(self.velocity, new_dir)) if self.active else 0.0
        self._start, self._dir, self._length, self._s = list(self.pose), new_dir, length, 0.0
        self._v, self._vmax, self._acc, self._stop_decel = max(0.0, carried), speed, accel, 0.0
        self.active = True

    def stop(self, decel: float) -> None:
        """Decelerate to rest at ``decel`` along the current path."""
        if decel <= 0:
            raise ValueError(f"stop deceleration must be > 0, got {decel}")
        if self.active:
            self._stop_decel = decel

    @property
    def stopping(self) -> bool:
        """True while a stop is decelerating the motion."""
        return self.active and self._stop_decel > 0

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds."""
        if not self.active:
            self.velocity = [0.0] * 6
            return
        remaining = self._length - self._s
        if self._stop_decel > 0:
            v_new = max(0.0, self._v - self._stop_decel * dt)
        else:
            v_brake = math.sqrt(max(0.0, 2.0 * self._acc * remaining))
            v_new = min(self._vmax, self._v + self._acc * dt, v_brake)
        # Trapezoidal integration of the distance covered this step.
        self._s = min(self._length, self._s + 0.5 * (self._v + v_new) * dt)
        self._v = v_new
        if self._s >= self._length - 1e-9 or (self._stop_decel > 0 and self._v <= 0.0):
            self._v, self.active = 0.0, False
        self.pose = [s + d * self._s for s, d in zip(self._start, self._dir)]
        self.velocity = [d * self._v for d in self._dir]
