"""Zero the sensor again, in software, once the jaw lets go of a grasp that its bias was taken under.

A PapillArray controller that is power-cycled forgets its bias, so with ``sensor.tare: bias_command`` the daemon
sends the bias again on the reconnect. If the jaw held an object then, the bias took that object's load for the
zero: once the jaw lets go, every pillar reads minus the load it carried, and every later grasp reads low by as
much (its shear offset by the old load's) until slipd restarts. The contact gate's free-air baseline follows a
drift, not a step of newtons, and the model reads the tared forces themselves. Sending the bias again at the
release would blind the daemon while the sensor zeroes itself (``sensor.bias_timeout_s``), which its stall rule
turns into a fail-safe between grasps.

So after such a reconnect ``LoadedZero`` watches the raw frames: once no finger is in contact and every pillar has
stayed steady for ``STEADY_S`` with some finger's summed normal force below its zero by at least ``RELEASE_SHARE``
of the grip it read when the sensor went (the load the bias took has gone, not merely eased), the mean of that
stretch becomes the tare offset, the same subtraction a start-up tare makes (``Detector.set_offset``). Nothing is
held back, so the daemon is not blind for it. Any later bias zeroes the sensor itself, so the daemon drops the
software zero then (``Daemon._on_reconnect``).

Limit: steadiness is judged against the stretch's first chunk within ``STEADY_N``, so a release slower than about
0.17 N/s per pillar (a jaw opening over ten seconds) can pass for still while load remains, and leaves part of the
error; a gripper lets go within a fraction of a second.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slipd.geometry import N_PILLARS

STEADY_S = 0.3
"""The free air must stay still this long (a jaw opening, an object pulled out, settle within ~0.1 s)."""
STEADY_N = 0.05
"""Every pillar's force (each axis, as a ``CHUNK`` mean) within this of the stretch's first chunk (sensor noise about
0.01 N): still, not moving."""
CHUNK = 10
"""Frames per steadiness check, whatever the blocks' sizes (a block after a stall may hold hundreds of frames: each
chunk is judged); a mean of ten keeps the sensor's noise well inside ``STEADY_N``."""
RELEASE_SHARE = 0.5
"""A finger reads released once its summed normal force is this share of its grip at the loss below the zero: a
grip that only eased (the object still held, lighter) must not become the zero."""
BELOW_N = 1.0
"""... and at least this far below (twice the SDK's contact threshold: more than noise and drift)."""


class LoadedZero:
    """Finds the free-air offsets of a sensor zeroed under a grasp (see the module docstring); bounded state."""

    def __init__(self, sensors: int, rate_hz: float) -> None:
        self.sensors = int(sensors)
        self.need = max(1, round(STEADY_S * rate_hz))
        self.armed = False
        self._below = np.full(self.sensors, BELOW_N)
        self._sum = np.zeros((self.sensors, N_PILLARS, 3), np.float64)
        self._first = np.zeros((self.sensors, N_PILLARS, 3), np.float64)
        self._chunk_sum = np.zeros((self.sensors, N_PILLARS, 3), np.float64)
        self._chunk_n = 0
        self._n = 0

    def arm(self, grips: Sequence[float]) -> None:
        """The sensor was zeroed under a grasp that read ``grips`` (N, per finger) when it went: watch for the free
        air."""
        self._below = np.maximum(BELOW_N, RELEASE_SHARE * np.nan_to_num(np.asarray(grips, np.float64)))
        self.armed = True
        self._new_stretch()

    def disarm(self) -> None:
        self.armed = False
        self._new_stretch()

    def _new_stretch(self) -> None:
        """Forget the still stretch so far, the part-filled chunk included (its frames came before the break)."""
        self._n = self._chunk_n = 0
        self._chunk_sum[:] = 0.0

    def push(self, force: np.ndarray, offset: np.ndarray, in_contact: bool) -> np.ndarray | None:
        """One block of raw forces ([k, S, 9, 3]) with the offset in use ([S, 9, 3] or [9, 3]); ``in_contact``: some
        finger is in contact at the latest decision. Returns the new offsets ([S, 9, 3]) once found (and disarms)."""
        if not self.armed:
            return None
        x = np.asarray(force, np.float64).reshape(-1, self.sensors, N_PILLARS, 3)
        if in_contact or not np.isfinite(x).all():
            self._new_stretch()  # a grasp, or a value the pipeline would bridge: the stretch starts again
            return None
        i = 0
        while i < len(x):  # whole chunks of CHUNK frames, whatever the blocks' sizes
            take = min(CHUNK - self._chunk_n, len(x) - i)
            self._chunk_sum += x[i : i + take].sum(axis=0)
            self._chunk_n += take
            i += take
            if self._chunk_n < CHUNK:
                break
            mean = self._chunk_sum / CHUNK
            self._chunk_sum[:] = 0.0
            self._chunk_n = 0
            if self._n and np.abs(mean - self._first).max() > STEADY_N:
                self._n = 0  # moving: a new stretch from this chunk
            if self._n == 0:
                self._first[:] = mean
                self._sum[:] = 0.0
            self._sum += mean * CHUNK
            self._n += CHUNK
        if self._n < self.need:
            return None
        mean = self._sum / self._n
        zero = np.asarray(offset, np.float64).reshape(self.sensors, N_PILLARS, 3)
        if ((mean - zero)[..., 2].sum(axis=-1) > -self._below).all():
            self._n = 0  # still, but not below the zero (the load is still on): judge the next stretch afresh
            return None
        self.disarm()
        return mean.astype(np.float32)
