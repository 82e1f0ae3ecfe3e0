"""The sensor's stream rate, measured from the controller's own clock and packet counter, and its timestamps' sanity.

A controller that streams at another rate than the model was trained at (it ignored the rate command, another
firmware, a second controller on the port) feeds windows of the right length in samples but not in time: at 500 Hz
each window spans twice the time the model learnt, at 2 kHz half. The rate is measured over ``WINDOW_S`` of device
time as packets counted (the counter, so a lost frame does not lower it) per second of the controller's clock
(``t_us``); outside ``sensor.rate_tolerance`` of the configured rate (which equals the model's: ``check-config``) the
daemon is blind with cause ``rate`` (``slipd.daemon.loop``), at start-up before ``READY=1`` and at any time after.

Timestamps: between two frames the controller's clock should advance by the packets counted times the period. One
that runs backwards or stands still, or jumps ahead by more than ``JUMP_S`` beyond that, is counted
(``slipd_timestamp_jumps_total{kind}``) and logged once per episode (an episode ends after a whole measuring window
of regular timestamps); the measurement restarts after it.
"""

from __future__ import annotations

import logging

import numpy as np

from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.rate")

WINDOW_S = 0.2
"""Device time per measurement: 200 frames at 1 kHz, 20 at 100 Hz; the counter and clock are exact, so a short
window is precise, and a wrong rate is known well before the start-up bias wait ends."""
JUMP_S = 0.05
"""A timestamp step this much beyond what the counter says is a jump (a 500 Hz stream's 1 ms extra per frame is not)."""
_MASK = 0xFFFFFFFF  # the packet counter wraps at 2**32
_JUMP_US = JUMP_S * 1e6
_WINDOW_US = WINDOW_S * 1e6
_SCALAR_MAX = 64
"""Blocks up to this many frames (a decision's, at any stride up to the window) are checked in plain Python: on a few
dozen timestamps a loop costs less than the numpy calls."""


class RateMonitor:
    """Fed every block of frames (``push``); ``measured`` is the latest window's rate, ``outside`` its verdict."""

    def __init__(self, rate_hz: float, tolerance: float, metrics: Metrics | None = None) -> None:
        self.rate_hz = float(rate_hz)
        self._tolerance = float(tolerance)
        self.measured: float | None = None
        """Frames per second of the controller's clock over the latest window (None before the first)."""
        self.outside = False
        """The latest measurement is beyond the tolerance (kept with ``measured`` and ``tolerance``: the loop reads it
        on every block)."""
        self.jumps = 0
        self._anchor: tuple[int, int] | None = None  # (counter, t_us) where the current window began
        self._last: tuple[int, int] | None = None  # the latest frame's (counter, t_us)
        self._jumping = False  # inside a timestamp episode (logged once)
        self._metrics = metrics
        if metrics is not None:
            metrics.sensor_rate.set_function(lambda: self.measured or 0.0)
            self._m_jumps = {k: metrics.timestamp_jumps.labels(kind=k) for k in ("backwards", "forward")}

    @property
    def tolerance(self) -> float:
        """The share by which the measured rate may differ from ``rate_hz`` (a reload may change it)."""
        return self._tolerance

    @tolerance.setter
    def tolerance(self, value: float) -> None:
        self._tolerance = float(value)
        if self.measured is not None:
            self._set_measured(self.measured)

    @property
    def known(self) -> bool:
        return self.measured is not None

    def describe(self) -> str:
        """The line of a ``rate`` episode: both rates."""
        return (f"the sensor streams at {self.measured or 0.0:.0f} Hz by its own clock and counter, the model's rate "
                f"is {self.rate_hz:.0f} Hz (sensor.rate_tolerance {self.tolerance:.0%})")

    def restart(self) -> None:
        """The stream broke (a reconnect, the counter went backwards): the next frame starts a new window."""
        self._anchor = self._last = None

    def push(self, counter: np.ndarray, t_us: np.ndarray, discontinuity: np.ndarray,
             broken: bool | None = None) -> None:
        """One block's counters and timestamps (``broken``: whether ``discontinuity`` has a frame set, where the caller
        knows it already).

        The common block, no break and every timestamp a step of 1 us to ``JUMP_S`` after the one before, costs a few
        scalar operations: a step no larger than ``JUMP_S`` cannot be a jump ahead, whatever the counter says, so only
        the block's first and last counter and timestamp matter. Anything else takes the vectorised check."""
        k = len(counter)
        if not k:
            return
        if broken is None:
            broken = bool(discontinuity.any())
        if not broken and k <= _SCALAR_MAX:
            prev = self._last
            jump = _JUMP_US
            t = t_us.tolist()
            before = t[0] - 1 if prev is None else prev[1]  # no frame before: the first step is not checked
            for v in t:
                if not 0 < v - before <= jump:
                    break
                before = v
            else:
                end = t[-1]
                anchor = self._anchor
                if prev is not None and anchor is not None and end - anchor[1] < _WINDOW_US:
                    # The window goes on, no measurement ends (``_advance``'s common case, without its call).
                    self._last = (int(counter[-1]), end)
                    return
                first = prev if prev is not None else (int(counter[0]), t[0])
                self._advance(first, (int(counter[-1]), end))
                return
        self._push_checked(counter, t_us, discontinuity, broken)

    def _push_checked(self, counter: np.ndarray, t_us: np.ndarray, discontinuity: np.ndarray, broken: bool) -> None:
        """``push`` frame by frame, vectorised: breaks, and timestamps that run backwards, stand still or jump."""
        c = counter.astype(np.int64)
        t = t_us.astype(np.int64)
        if broken:
            cut = int(np.flatnonzero(discontinuity)[-1])  # the window starts again at the last break
            self.restart()
            c, t = c[cut:], t[cut:]
        if self._last is not None:
            c = np.concatenate(([self._last[0]], c))
            t = np.concatenate(([self._last[1]], t))
        if len(c) > 1:
            dc = (c[1:] - c[:-1]) & _MASK
            dt = t[1:] - t[:-1]
            expected = dc * (1e6 / self.rate_hz)
            back = dt <= 0  # backwards, or not advancing while the counter does
            ahead = dt - expected > _JUMP_US
            if back.any() or ahead.any():
                self._jump(int(back.sum()), int(ahead.sum()), int(np.flatnonzero(back | ahead)[-1]) + 1, c, t)
                return
        self._advance((int(c[0]), int(t[0])), (int(c[-1]), int(t[-1])))

    def _advance(self, first: tuple[int, int], last: tuple[int, int]) -> None:
        """Regular frames from ``first`` (the frame before them, or their first) to ``last`` (counter, t_us): the
        window goes on, and a measurement ends once it spans ``WINDOW_S``."""
        self._last = last
        if self._anchor is None:
            self._anchor = first
            return
        span = last[1] - self._anchor[1]
        if span >= _WINDOW_US:
            self._set_measured(((last[0] - self._anchor[0]) & _MASK) / (span / 1e6))
            self._anchor = last
            self._jumping = False  # a whole window of regular timestamps: the episode is over

    def _set_measured(self, rate: float) -> None:
        self.measured = rate
        self.outside = abs(rate / self.rate_hz - 1.0) > self._tolerance

    def _jump(self, back: int, ahead: int, at: int, c: np.ndarray, t: np.ndarray) -> None:
        """Count and (once per episode) log timestamps that run backwards or jump; measure again after the last."""
        self.jumps += back + ahead
        if self._metrics is not None:
            if back:
                self._m_jumps["backwards"].inc(back)
            if ahead:
                self._m_jumps["forward"].inc(ahead)
        if not self._jumping:
            self._jumping = True
            step = (int(t[at]) - int(t[at - 1])) / 1e6
            log.warning("sensor: its timestamps %s (a step of %+.3f s over %d packet(s)); counted in "
                        "slipd_timestamp_jumps_total, logged once until they run regularly again",
                        "ran backwards" if back else "jumped ahead", step, int((c[at] - c[at - 1]) & _MASK))
        self._anchor = None
        self._last = (int(c[-1]), int(t[-1]))
        if at < len(c) - 1:
            self._anchor = (int(c[at]), int(t[at]))
