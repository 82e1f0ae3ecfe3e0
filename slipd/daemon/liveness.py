"""Liveness, defined once: the daemon's blind causes, its fail-safe per episode, and the supervision task.

Live means a valid decision on a window of fresh samples within the stall timeout (``sensor.stall_timeout_ms``) and
no blind cause (``blind_cause``; the causes are listed in ``slipd.daemon.loop``). The supervision task (``run``) runs
on absolute deadlines (``next = start + k * period``; a late tick is counted as an overrun and the schedule is not
shifted); while live it skips the ticks before the earliest moment a blind cause can arise (the fresh-data and
decision deadlines, the next ping or kick), and the hot path wakes it at once for a non-finite burst or a rate out of
tolerance (``wake``). Only while live is the systemd watchdog pinged and the arm's controller-side watchdog kicked;
``READY=1`` goes out with the first live decision (``on_live``), which at start-up also waits for the stream's rate to
be measured. The daemon's state (fresh times, the decision deadline) is the hot path's, read here through ``d``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from typing import Any

import numpy as np

log = logging.getLogger("slipd.daemon.loop")  # the daemon's lines, as before the split


def _settle(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


SUPERVISION_PERIOD_S = 0.005
"""Supervision tick for short stall timeouts (up to 25 ms); longer ones allow up to SUPERVISION_MAX_PERIOD_S."""
SUPERVISION_MAX_PERIOD_S = 0.010


def supervision_period(stall_s: float) -> float:
    """Supervision tick for a stall timeout: a fifth of it (a stall is seen at most 20 % late), kept within
    [SUPERVISION_PERIOD_S, SUPERVISION_MAX_PERIOD_S]: 5 ms as before for timeouts up to 25 ms, 10 ms (half
    the wake-ups) from 50 ms, the real sensor's default."""
    return min(max(stall_s / 5, SUPERVISION_PERIOD_S), SUPERVISION_MAX_PERIOD_S)

KICKS_PER_WATCHDOG = 4
"""The arm's controller-side watchdog is kicked this many times per ``arm.watchdog_s`` while live: a
late kick or two (a busy arm thread, a slow machine) must not halt the arm."""


class Liveness:
    """Blind causes, episodes and the supervision task of one daemon, on the loop's thread."""

    def __init__(self, daemon: Any) -> None:
        # The ``slipd.daemon.loop.Daemon`` that owns this part of it; not imported for its type, which would tie the
        # two modules in an import cycle.
        self.d = daemon
        self._wake: asyncio.Future[None] | None = None  # the supervision task's nap, while it naps

    def go_blind(self, cause: str, detail: str) -> None:
        """Liveness lost: one log line and one fail-safe per episode, whatever follows inside it."""
        self.d.live = False
        self.d.metrics.live.set(0)
        self.d._decided_t = None  # live again only after a new valid decision on fresh data
        if self.d.blind is not None:
            return
        self.d.blind = cause
        # The episode's one line at its start (its end: "live again after"); the reaction adds none.
        log.error("blind: %s; fail-safe (%s)", detail, self.d.reaction.on_failsafe)
        self.d._fail_safe(cause, logged=True)
        if self.d.recorder is not None and self.d._last_t_us is not None:
            # What led to the fault, written now: the frames after it may never come (a stalled or lost sensor).
            self.d._note_offset()
            self.d.recorder.trigger(self.d._last_t_us, "failsafe", wait_after=False, cause=cause, detail=detail)

    def blind_cause(self, now: float) -> tuple[str, str] | None:
        """Liveness, defined once: (cause, detail) when the daemon cannot see, else None. Live means no
        cause and a valid decision on fresh data since the last episode (``_decided_t``)."""
        stall = self.d._stall_s
        sensor = self.d.sensor
        if sensor is not None and not sensor.connected:
            return "sensor_lost", "sensor port closed"
        if self.d.rate.outside:
            return "rate", self.d.rate.describe()
        if self.d._nonfinite_burst or (self.d._nonfinite_run > self.d._nonfinite_bridge).any():
            worst = int(np.argmax(self.d._nonfinite_run)) if not self.d._nonfinite_burst else self.d._nonfinite_sensor
            return "sensor_nonfinite", (f"non-finite samples for more than {self.d._nonfinite_bridge} frames"
                                        + self.which(worst))
        if now - self.d._fresh_t > stall:
            ms = (now - self.d._fresh_t) * 1e3
            last = sensor.last_frame_time if sensor is not None else None
            if last is None:
                return "sensor_silent", f"no frame for {ms:.0f} ms since start-up"
            if now - last > stall:
                return "sensor_stall", f"no frame for {(now - last) * 1e3:.0f} ms"
            repeat = sensor.last_repeat_time
            if repeat is not None and repeat >= self.d._fresh_t:
                return "sensor_counter_stuck", f"packet counter not advancing for {ms:.0f} ms"
            return "sensor_frozen", f"bit-identical frames for {ms:.0f} ms" + self.which(
                int(np.argmin(self.d._fresh_ts)))
        if now > self.d._decision_due:
            if sensor is not None and sensor.frames < self.d._decision_frames:
                # The stream stopped short of the frame that decision needed. Its last frames were stamped fresh when
                # they were read, which on a busy machine can be well after they arrived, so the decision's
                # deadline may pass first: it is still a stall (once seen as no_decisions in a CI run).
                last = sensor.last_frame_time
                since = "" if last is None else f" (none for {(now - last) * 1e3:.0f} ms)"
                return "sensor_stall", f"the frames of the decision due never came{since}"
            return "no_decisions", "frames arrive but no valid decision came when due"
        return None

    def which(self, sensor: int) -> str:
        """`` on sensor N`` when there are several (the log line says which finger is blind)."""
        return f" on sensor {sensor}" if self.d.sensors > 1 else ""

    async def run(self) -> None:
        stall_s = self.d._stall_s
        period = supervision_period(stall_s)
        max_late = self.d.cfg.control.max_overrun_ms / 1e3
        start = time.monotonic()
        # The first frame, and the first decision, are due from now on (the tare wait is over).
        self.d._fresh_t = start
        self.d._fresh_ts[:] = start
        self.d._expect_decision(start)
        k = 0
        last_ping = 0.0
        ping_every = None
        if self.d.notifier is not None and self.d.cfg.control.watchdog:
            from slipd.daemon.sdnotify import watchdog_interval

            wd = watchdog_interval()
            ping_every = wd / 2 if wd else None
        kick = self.d.arm if self.d.arm_worker is not None and self.d.arm is not None else None
        kick_every = self.d.cfg.arm.watchdog_s / KICKS_PER_WATCHDOG
        kicking: concurrent.futures.Future[None] | None = None
        last_kick = 0.0
        while not self.d._stop.is_set():
            k += 1
            deadline = start + k * period
            if self.d.live and self.d.blind is None:
                # Live: no cause can arise before the earliest of the fresh-data and decision deadlines (a
                # disconnect and a non-finite burst wake this task themselves), so sleep until then, or until
                # the next ping or kick, rather than every period: 1 wake-up per stall timeout, not 5.
                due = min(self.d._fresh_t + stall_s, self.d._decision_due)
                if ping_every:
                    due = min(due, last_ping + ping_every)
                if kick is not None:
                    due = min(due, last_kick + kick_every)
                if due > deadline:
                    k = int((due - start) / period)
                    deadline = max(deadline, due)
            delay = deadline - time.monotonic()
            if delay > 0:
                await self.nap(delay)
            now = time.monotonic()
            if now - deadline > max_late:
                self.d.stats.overruns += 1
                self.d.metrics.overruns.inc()
                # Absolute schedule: skip the ticks that are already past instead of bunching them.
                k = int((now - start) / period)
            fault = self.blind_cause(now)
            self.d._nonfinite_burst = False
            if fault is not None:
                self.go_blind(*fault)
                continue
            if self.d._decided_t is None or not (self.d.started_live or self.d.rate.known):
                continue  # starting (or the rate not measured yet), or an episode not over
            if not self.d.live:
                self.on_live()
            if ping_every and now - last_ping >= ping_every:
                self.d.notifier.watchdog()
                last_ping = now
            if kick is not None and now - last_kick >= kick_every and (kicking is None or kicking.done()):
                assert self.d.arm_worker is not None
                kicking = self.d.arm_worker.submit(kick.kick_watchdog)
                last_kick = now

    async def nap(self, delay: float) -> None:
        """Sleep ``delay`` seconds, or until ``wake``."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        self._wake = fut
        handle = loop.call_later(delay, _settle, fut)
        try:
            await fut
        finally:
            handle.cancel()
            self._wake = None

    def wake(self) -> None:
        """A cause arose between two deadlines (a non-finite burst): let the supervision task look now."""
        if self._wake is not None:
            _settle(self._wake)

    def on_live(self) -> None:
        """The first valid decision on fresh data: at start-up READY=1, after an episode one log line."""
        self.d.live = True
        self.d.metrics.live.set(1)
        if self.d.blind is not None:
            log.warning("live again after %s", self.d.blind)
            self.d.blind = None
        if not self.d.started_live:
            # Also after a blind episode before it (a sensor that starts streaming late): under Type=notify systemd
            # kills a daemon that never says READY=1.
            self.d.started_live = True
            if self.d.sensor is not None:
                self.d.sensor.starting = False  # counter gaps from now on are losses (slipd_dropped_frames_total)
            if self.d.notifier is not None:
                self.d.notifier.ready(f"running: model {self.d.cfg.model.manifest.name}")
