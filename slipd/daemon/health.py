"""Device health: the arm and gripper polled on their worker threads, their reconnects, and what a change means.

Polls the arm (``read_state``, every ``HEALTH_PERIOD_S``) and the gripper (``read_status``, every
``GRIPPER_HEALTH_PERIOD_S``) on their own worker threads; the loop only looks at finished futures, so a slow or dead
device never blocks it. An arm link that drops is logged and reconnected with backoff (the arm's own metrics count
``disconnected`` / ``protective_stop``); a protective stop is logged, never unlocked automatically. A control script
that ended because slipd stopped the arm (an alarm, a fail-safe, a blind daemon that stopped kicking the controller's
watchdog) is routine: logged at INFO, and so is its re-upload; one that ended otherwise (the pendant, the watchdog of a
live daemon) is an ERROR. A gripper that stops answering or reports a hardware error or torque off fails safe (stop
the arm) once per occurrence and is counted as ``slipd_device_errors{device="gripper", kind="unhealthy"}``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import time
from typing import Any

from slipd.daemon.worker import DeviceWorker

log = logging.getLogger("slipd.daemon.loop")  # the daemon's lines, as before the split

HEALTH_PERIOD_S = 0.15
"""Arm health poll period (100-200 ms asked for): ``read_state`` reads ur_rtde's cached receive values."""
GRIPPER_HANG_S = 2.0
"""A gripper call (a status poll, a grip command) still running after this long has hung: the gripper is not answering.
One status read with its retries takes at most (retries + 1) x packet timeout (80 ms at the defaults); without this
rule a call stuck in the vendor library left the gripper "ok" for good, the grip frozen where it was."""
GRIPPER_HEALTH_PERIOD_S = 0.5
"""Slower for the gripper: its status block (83 bytes) takes ~20 ms at 57.6 kBd, and a tighten submitted
while a status read is on the wire waits for it; 0.5 s keeps that chance small."""
ARM_RECONNECT_INITIAL_S = 0.25
ARM_RECONNECT_MAX_S = 5.0
"""Back-off of the arm's reconnects, and of the gripper's (its port reopened after an unplugged adapter)."""
OWN_STOP_S = 10.0
"""A control script that ends this soon after slipd issued an arm stop ended because of it (an INFO line, not an
ERROR): a stop and the health poll that sees its end are well under a second apart."""


class _Reconnects:
    """One device's reconnects on its worker thread: at most one in flight, the back-off doubling after each failure
    (``ARM_RECONNECT_INITIAL_S`` to ``ARM_RECONNECT_MAX_S``) and starting over after a success."""

    def __init__(self, worker: DeviceWorker, reconnect: Any) -> None:
        self._worker, self._reconnect = worker, reconnect
        self._fut: concurrent.futures.Future[Any] | None = None
        self._delay = ARM_RECONNECT_INITIAL_S
        self._next = 0.0

    @property
    def pending(self) -> bool:
        return self._fut is not None

    def outcome(self, now: float) -> bool | None:
        """Whether the reconnect in flight succeeded, once it has ended (None until then, or with none in flight)."""
        if self._fut is None or not self._fut.done():
            return None
        fut, self._fut = self._fut, None
        ok = fut.exception() is None and bool(fut.result())
        if ok:
            self._delay = ARM_RECONNECT_INITIAL_S
        else:
            self._next = now + self._delay
            self._delay = min(2 * self._delay, ARM_RECONNECT_MAX_S)
        return ok

    def due(self, now: float) -> bool:
        """None in flight and the back-off has passed."""
        return self._fut is None and now >= self._next

    def attempt(self, now: float) -> None:
        """Start one when it is due."""
        if self.due(now):
            self._fut = self._worker.submit(self._reconnect)


class DeviceHealth:
    """The health task of one daemon (``run``) and its reactions, on the loop's thread."""

    def __init__(self, daemon: Any) -> None:
        # The ``slipd.daemon.loop.Daemon`` that owns this part of it; not imported for its type, which would tie the
        # two modules in an import cycle.
        self.d = daemon
        self.gripper_lost = False
        """The gripper's port was dropped (an I/O error): the health task reopens it."""
        self.own_stop = False
        """The arm's control script ended because slipd stopped the arm: its re-upload is routine (INFO)."""

    async def run(self) -> None:
        """Poll arm (every ``health_period_s``) and gripper (every ``gripper_health_period_s``) state on
        their worker threads; react to changes on the loop thread.

        At most one poll per device is in flight: a device that hangs delays only its own next poll.
        A poll queued on the gripper thread can delay a tighten submitted behind it by one status read.
        """
        arm = self.d.arm if self.d.arm_worker is not None and hasattr(self.d.arm, "read_state") else None
        grip = self.d.gripper if self.d.gripper_worker is not None and hasattr(self.d.gripper, "read_status") else None
        if arm is None and grip is None:
            return
        arm_poll: Any = None
        grip_poll: Any = None
        arm_reconnect = grip_reconnect = None
        if arm is not None and self.d.arm_worker is not None:
            arm_reconnect = _Reconnects(self.d.arm_worker, arm.reconnect)
        if grip is not None and self.d.gripper_worker is not None and hasattr(grip, "reconnect"):
            grip_reconnect = _Reconnects(self.d.gripper_worker, grip.reconnect)
        next_grip = grip_sent = 0.0
        while not self.d._stop.is_set():
            now = time.monotonic()
            if arm is not None:
                if arm_poll is not None and arm_poll.done():
                    self.on_arm_health(arm_poll)
                    arm_poll = None
                assert arm_reconnect is not None
                if arm_reconnect.outcome(now):
                    self.d.metrics.reconnects.labels(device="arm").inc()
                    # Uploading the control script again after slipd's own stop is routine; after a lost link, news.
                    log.log(logging.INFO if self.own_stop else logging.WARNING, "arm: reconnected")
                    self.d.health["arm"] = "reconnected"  # the next poll says whether it is healthy
                # A control script the watchdog ended (blind, frozen) is re-uploaded only while live: a blind
                # daemon would let it expire again at once.
                state = self.d.health.get("arm")
                lost = state == "disconnected" or (self.d.live and state == "script_stopped")
                if lost and arm_reconnect.due(now):
                    arm_reconnect.attempt(now)
                elif arm_poll is None and not arm_reconnect.pending:
                    assert self.d.arm_worker is not None
                    arm_poll = self.d.arm_worker.submit(self.probe_arm)
            if grip is not None:
                if grip_reconnect is not None and grip_reconnect.outcome(now):
                    self.gripper_lost = False
                    self.d.metrics.reconnects.labels(device="gripper").inc()
                    next_grip = now  # the next poll says how it holds
                if grip_poll is not None and grip_poll.done():
                    self.on_gripper_health(grip_poll)
                    grip_poll = None
                elif grip_poll is not None and now - grip_sent > GRIPPER_HANG_S:
                    # The poll queues behind whatever the gripper thread runs: either has hung.
                    self.gripper_condition(f"not answering: a call has not returned for {now - grip_sent:.1f} s")
                reconnecting = grip_reconnect is not None and grip_reconnect.pending
                if self.gripper_lost and grip_reconnect is not None and grip_poll is None:
                    # Its port was dropped (an unplugged adapter): reopen it, with back-off; nothing else is sent.
                    grip_reconnect.attempt(now)
                elif grip_poll is None and not reconnecting and now >= next_grip:
                    assert self.d.gripper_worker is not None
                    grip_poll = self.d.gripper_worker.submit(grip.read_status)
                    grip_sent = now
                    next_grip = now + self.d.gripper_health_period_s
            self.d.stats.health_polls += 1
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self.d._stop.wait(), self.d.health_period_s)

    def probe_arm(self) -> str:
        """On the arm thread: ``ok``, ``disconnected``, ``protective_stop`` or ``script_stopped`` (read_state
        counts the metrics)."""
        arm = self.d.arm
        assert arm is not None
        st = arm.read_state()
        if not st.connected or not arm.is_connected():
            return "disconnected"
        if st.protective_stop:
            return "protective_stop"
        return "ok" if arm.control_script_running() else "script_stopped"

    def on_arm_health(self, fut: Any) -> None:
        exc = fut.exception()
        if exc is not None:
            self.d.metrics.device_errors.labels(device="arm", kind="health").inc()
            log.error("arm: health poll failed: %s", exc)
            return
        state, before = fut.result(), self.d.health.get("arm")
        self.d.health["arm"] = state
        if state == "protective_stop":
            self.d.reaction.arm_halted()  # the controller halted it: a stop it refused is no longer owed
        elif state != "disconnected":
            self.d.reaction.retry_stop()  # a stop the controller refused or that failed, until one is taken
        if state == before:
            return
        if state == "disconnected":
            log.error("arm: RTDE link lost; reconnecting (slipd cannot stop the arm until the link is back)")
        elif state == "protective_stop":
            log.error("arm: protective stop; slipd does not unlock it: inspect the cell, unlock from the pendant")
        elif state == "script_stopped":
            stopped = self.d.reaction.last_arm_stop()
            self.own_stop = self.d.blind is not None or (stopped is not None
                                                         and time.monotonic() - stopped < OWN_STOP_S)
            if self.own_stop:
                # slipd's own doing: a blind daemon stops kicking the controller's watchdog, and its stops end the
                # control script. Nothing to alarm anyone about beyond the episode's own line.
                log.info("arm: control script ended after slipd's stop; re-uploading it once decisions are live")
            else:
                log.error("arm: control script ended (watchdog expired or stopped from the pendant); "
                          "re-uploading it once decisions are live")
        elif before is not None:
            routine = before == "reconnected" and self.own_stop
            log.log(logging.INFO if routine else logging.WARNING, "arm: healthy again (after: %s)", before)
        if state == "ok":
            self.own_stop = False

    def on_gripper_health(self, fut: Any) -> None:
        exc = fut.exception()
        if exc is not None:
            problem = f"not answering: {exc}"
            # A port the driver dropped after an I/O error, or never had: reconnected by the health task.
            self.gripper_lost = getattr(exc, "kind", None) in ("io", "not_connected")
        else:
            st = fut.result()
            if st.healthy:
                problem = ""
            elif st.hardware_error:
                problem = f"hardware error {', '.join(st.hardware_errors)}"
            else:
                problem = "torque off"
        self.gripper_condition(problem)

    def gripper_condition(self, problem: str) -> None:
        """The gripper's condition ("" healthy): one fail-safe when it turns bad, an owed tighten sent when healthy."""
        before = self.d.health.get("gripper")
        self.d.health["gripper"] = problem or "ok"
        if problem and (before is None or before == "ok"):
            self.d.metrics.device_errors.labels(device="gripper", kind="unhealthy").inc()
            log.error("gripper: %s; fail-safe (%s)", problem, self.d.reaction.on_failsafe)
            self.d._fail_safe("gripper_fault", logged=True)
        elif not problem:
            if before not in (None, "ok"):
                log.warning("gripper: healthy again (after: %s)", before)
            # A tighten that failed is still owed, whether or not a poll saw the servo silent: a silence shorter
            # than the poll period fails a tighten (its retries) unseen.
            self.d.reaction.retry_tighten()
