"""What slipd does on an alarm: stop the arm, tighten the gripper (configurable order and grading).

Each device has its own worker thread (``slipd.daemon.worker.DeviceWorker``): the reaction hands the
vendor calls to them and returns at once, so the arm stop and the gripper tighten run in parallel
and the control loop never waits on a serial or TCP round trip. Within one device, calls run in the
order submitted.

Policies:
- ``actions``: which of ``stop_arm`` / ``tighten_gripper`` run, in this order of submission;
- ``graded``: tighten to a level proportional to the risk (0..1 between hold and secure) instead of
  straight to the secure setting, and tighten further when a later alarm carries a higher risk;
- ``rearm_after_s``: after a reaction, further alarms within this time do not re-issue the same
  commands (the grasp is being secured already), except a graded escalation.
- ``policy``: ``stop_and_secure`` (the above) or ``grip_control``: the grip follows every decision's contact
  state (``slipd.daemon.grip_control``: least grip that keeps a friction margin, a slip caught at once; the
  arm stops only at a held high risk, at the force limit, or for a twist); alarms then raise the grip instead
  of running the actions.
Fail-safe (sensor stall, model failure, a device error while reacting): stop the arm, keep the grip.

A tighten that failed (the servo did not answer) stays owed until the grasp ends: ``retry_tighten``
sends it again, and the daemon calls it whenever the gripper's health poll hears the servo, so a servo
that was silent during the alarm still secures the grasp once it is back. When no finger is in contact
any more the daemon calls ``released``: the owed tighten is void (and so is one of that grasp that fails
later), and the next grasp starts from nothing (no re-arm window, no graded level).

An arm stop the controller refused (``StopResult.ok`` False: the configured method and its fallback both
failed) or that raised is a failure like a device error: recorded, logged, counted, and owed; the daemon
sends it again on every arm health poll that reaches the controller (``retry_stop``) until one is taken or
the controller reports the arm halted by a protective stop. One stop is in flight at a time: a request while
one is queued or running joins it, so a storm of fail-safes cannot queue stops without bound behind a call
that hangs.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slipd.daemon.grip_control import GripController, GripControlSettings
    from slipd.daemon.worker import DeviceWorker
    from slipd.detect.contact import ContactState
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.reaction")

ACTIONS = ("stop_arm", "tighten_gripper")
STOP_RETRY_LOG_EVERY = 20
"""An owed arm stop is retried on every arm health poll (0.15 s); one log line per this many tries."""
MAX_RECORDS = 256
"""Reactions kept in ``Reaction.records`` (the oldest are dropped): bounded state for a long-running daemon. A
recording's context reads only the reactions of its own few seconds; the metrics count them all."""


@dataclass
class ReactionRecord:
    """What was issued for one alarm, with monotonic times (seconds)."""

    t_decision: float
    risk: float
    issued: dict[str, float] = field(default_factory=dict)
    done: dict[str, float] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)


class Reaction:
    """Turns alarms into device commands on the devices' worker threads."""

    def __init__(
        self,
        *,
        actions: tuple[str, ...] | list[str] = ACTIONS,
        arm: Any = None,
        gripper: Any = None,
        arm_worker: DeviceWorker | None = None,
        gripper_worker: DeviceWorker | None = None,
        metrics: Metrics | None = None,
        graded: bool = False,
        rearm_after_s: float = 1.0,
        enabled: bool = True,
        on_failsafe: str = "stop_arm",
        clock: Callable[[], float] = time.monotonic,
        policy: str = "stop_and_secure",
        grip: GripControlSettings | None = None,
    ) -> None:
        unknown = [a for a in actions if a not in ACTIONS]
        if unknown:
            raise ValueError(f"unknown reaction action(s) {unknown}; known: {ACTIONS}")
        self.actions = tuple(actions)
        self.arm, self.gripper = arm, gripper
        self.arm_worker, self.gripper_worker = arm_worker, gripper_worker
        self.metrics = metrics
        self.graded = graded
        self.rearm_after_s = rearm_after_s
        self.enabled = enabled
        if on_failsafe not in ("stop_arm", "stop_arm_and_tighten", "log_only"):
            raise ValueError(f"unknown on_failsafe policy {on_failsafe!r}")
        self.on_failsafe = on_failsafe
        self.clock = clock
        self.records: deque[ReactionRecord] = deque(maxlen=MAX_RECORDS)
        self.tighten_owed: float | None = None
        """The argument of a gripper command that failed and was not yet sent again (``retry_tighten``): a tighten's
        level (None: secure), or the force in N of grip_control's fail-safe grip at the object's limit."""
        self._owed = False
        self.stop_owed: str | None = None
        """The reason of an arm stop that failed or was refused and was not yet taken (``retry_stop``)."""
        self._stop_pending: Future[Any] | None = None
        self._stop_retries = 0  # retries of the owed stop so far (their log lines are thinned)
        self._tighten_failing = False  # the latest gripper command of the reaction failed (one fail-safe per run)
        self._owed_call: Callable[..., Any] | None = None
        """The gripper call owed: the one that failed (a retry of grip_control's limit grip as a tighten would go to
        the secure setting, past the object's limit, and a force is no tighten level)."""
        self.post: Callable[[Callable[[Future[Any]], None], Future[Any]], Any] | None = None
        """Where a device call's outcome is handled: the daemon sets its loop's ``call_soon_threadsafe`` while it runs,
        so that the reaction's state (the stop in flight, what is owed, the grip controller's target after a fail-safe)
        changes on the loop's thread alone; a future's callbacks otherwise run on the device worker's thread, beside
        the loop's own use of that state. None: on the worker's thread (no loop)."""
        self._last_t: float | None = None
        self._last_level = 0.0
        self._grasp_level = float(getattr(gripper, "level_found", 0.0))
        """The highest tighten level sent for this grasp (1: the secure setting, as a fail-safe's tighten; at start-up
        the level the gripper found in place, ``Gripper.take_over``): a later graded tighten never goes below it, since
        securing never loosens. ``reset`` (a new grasp) clears it."""
        self._grasp_id = 0
        """Counts grasps (``reset``): a gripper command that fails is owed only to the grasp it was sent for."""
        self.failsafe_count = 0
        if policy not in ("stop_and_secure", "grip_control"):
            raise ValueError(f"unknown reaction policy {policy!r}")
        self.policy = policy
        self.grip_control: GripController | None = None
        """``policy: grip_control``: the grip follows the contact state (``on_detection``); alarms raise it."""
        if policy == "grip_control" and gripper is not None:
            from slipd.daemon.grip_control import GripController, GripControlSettings

            self.grip_control = GripController(grip or GripControlSettings(), gripper=gripper,
                                               gripper_worker=gripper_worker, stop_arm=self._grip_stop,
                                               failsafe=self.failsafe, metrics=metrics)

    def on_alarm(self, risk: float, t_decision: float | None = None) -> list[Future[Any]]:
        """React to an alarm decided at ``t_decision`` (monotonic); returns the futures of the issued calls."""
        t0 = self.clock() if t_decision is None else t_decision
        if not self.enabled or self.grip_control is not None:
            return []  # grip_control: the controller reacts to the alarm with the decision's contact state
        level = min(1.0, max(0.0, float(risk))) if self.graded else 1.0
        recent = self._last_t is not None and t0 - self._last_t < self.rearm_after_s
        if recent and level <= self._last_level:
            return []
        rec = ReactionRecord(t_decision=t0, risk=float(risk))
        self.records.append(rec)
        futures: list[Future[Any]] = []
        for action in self.actions:
            if action == "stop_arm" and self.arm is not None and not recent:
                futures.append(self._submit(rec, action, self.arm_worker, self.arm.stop, "slip alarm"))
            elif action == "tighten_gripper" and self.gripper is not None:
                # Past the re-arm window an alarm of lower risk must not move the jaw back from where it was secured.
                arg = max(level, self._grasp_level) if self.graded else None
                self._grasp_level = 1.0 if arg is None else arg
                futures.append(self._submit(rec, action, self.gripper_worker, self.gripper.tighten, arg))
        self._last_t, self._last_level = t0, max(level, self._last_level if recent else 0.0)
        return futures

    def on_detection(self, contact: ContactState | None, alarm: bool, t_decision: float,
                     sampled: bool | None = None) -> None:
        """``policy: grip_control``: every valid decision's contact state goes to the grip controller; ``sampled``:
        the alarm may give a friction sample (not one of the confirmed heuristic alone; None: as ``alarm``)."""
        if self.grip_control is not None and self.enabled:
            self.grip_control.update(contact, t_decision, alarm=alarm, sampled=sampled)

    def _grip_stop(self, why: str) -> None:
        if "stop_arm" not in self.actions or self.arm is None:
            return
        rec = ReactionRecord(t_decision=self.clock(), risk=1.0)
        self.records.append(rec)
        self._submit(rec, "stop_arm", self.arm_worker, self.arm.stop, why)

    def failsafe(self, reason: str, logged: bool = False) -> Future[Any] | None:
        """Fail safe (sensor stalled, model failed, reaction failed): by default stop the arm, keep the grip.

        ``on_failsafe="stop_arm_and_tighten"`` also tightens to the secure setting; ``"log_only"`` only
        logs and counts (for bench tests, never production). ``logged``: the caller's own line says so (a blind
        episode's, which names the policy), so none here.
        """
        self.failsafe_count += 1
        if not logged:
            log.warning("fail-safe: %s: policy %s", reason, self.on_failsafe)
        if self.metrics is not None:
            self.metrics.failsafe.labels(reason=reason).inc()
        if not self.enabled or self.on_failsafe == "log_only":
            return None
        rec = ReactionRecord(t_decision=self.clock(), risk=1.0)
        self.records.append(rec)
        if self.on_failsafe == "stop_arm_and_tighten" and self.gripper is not None and "tighten" not in reason:
            if self.grip_control is not None:
                # grip_control: secure at the object's force limit, not the secure setting (a fragile object's
                # limit is far below the jaw's full force).
                self._submit(rec, "tighten_gripper", self.gripper_worker, self.gripper.grip_force,
                             self.grip_control.s.max_force_n)
                self.grip_control.secured(self.grip_control.s.max_force_n)
            else:
                self._grasp_level = 1.0
                self._submit(rec, "tighten_gripper", self.gripper_worker, self.gripper.tighten, None)
        if self.arm is None:
            return None
        return self._submit(rec, "stop_arm", self.arm_worker, self.arm.stop, f"fail-safe: {reason}")

    def last_arm_stop(self) -> float | None:
        """When slipd last issued an arm stop (monotonic; an alarm's, a fail-safe's or grip control's), or None."""
        for rec in reversed(self.records):
            if "stop_arm" in rec.issued:
                return rec.issued["stop_arm"]
        return None

    def retry_tighten(self) -> Future[Any] | None:
        """Send a tighten that failed again (the servo answers again); None when none is owed."""
        if not self._owed or self.gripper is None or not self.enabled:
            return None
        arg, self._owed = self.tighten_owed, False
        call = self._owed_call or self.gripper.tighten
        if not self._tighten_failing:  # a run of failed retries (twice a second) is logged once, by its first
            log.warning("gripper answers again: retrying the tighten that failed")
        if call == self.gripper.tighten and arg is not None:
            arg = max(arg, self._grasp_level)  # owed from before a secure: the grip stays where it was secured
        level = None if call != self.gripper.tighten else arg
        rec = ReactionRecord(t_decision=self.clock(), risk=1.0 if level is None else level)
        self.records.append(rec)
        return self._submit(rec, "tighten_gripper", self.gripper_worker, call, arg)

    def retry_stop(self) -> Future[Any] | None:
        """Send an arm stop that failed or was refused again (the controller answers); None when none is owed
        or one is in flight."""
        if self.stop_owed is None or self.arm is None or not self.enabled:
            return None
        if self._stop_pending is not None and not self._stop_pending.done():
            return None
        self._stop_retries += 1
        if self._stop_retry_logged():
            log.warning("arm: retrying the stop that failed (%s), try %d", self.stop_owed, self._stop_retries)
        rec = ReactionRecord(t_decision=self.clock(), risk=1.0)
        self.records.append(rec)
        return self._submit(rec, "stop_arm", self.arm_worker, self.arm.stop, f"retry: {self.stop_owed}")

    def _stop_retry_logged(self) -> bool:
        """The owed stop is retried at every arm poll (0.15 s): its first failure and every ``STOP_RETRY_LOG_EVERY``-th
        retry are logged, a line per 3 s, not per try."""
        return self._stop_retries % STOP_RETRY_LOG_EVERY == 1 or self._stop_retries == 0

    def arm_halted(self) -> None:
        """The controller reports the arm halted (a protective stop): an owed stop is no longer needed."""
        self.stop_owed, self._stop_retries = None, 0

    def released(self) -> None:
        """The grasp let go (no finger in contact): ``reset``. An owed arm stop stays owed (what stopped the arm is
        not undone by the object leaving the jaw)."""
        if self._owed:
            log.warning("contact released: the tighten owed to that grasp is dropped")
        self.reset()

    def reset(self) -> None:
        """Forget the last reaction (a new grasp); a failed tighten is no longer owed, nor one in flight that fails."""
        self._grasp_id += 1
        if self.grip_control is not None:
            self.grip_control.reset()
        self._last_t = None
        self._last_level = self._grasp_level = 0.0
        self._owed, self.tighten_owed, self._owed_call, self._tighten_failing = False, None, None, False

    def _submit(self, rec: ReactionRecord, action: str, worker: DeviceWorker | None, fn: Callable[..., Any],
                arg: Any) -> Future[Any]:
        if action == "stop_arm" and self._stop_pending is not None and not self._stop_pending.done():
            return self._stop_pending  # the stop in flight halts the arm: no second one queued behind it

        def call() -> None:
            rec.issued[action] = self.clock()
            result = fn(arg) if arg is not None else fn()
            if action == "stop_arm" and getattr(result, "ok", True) is False:
                # ``Arm.stop`` never raises for a refused stop: it says so in its result.
                raise RuntimeError(f"stop refused by the controller: {getattr(result, 'error', '') or 'no reason'}")
            rec.done[action] = self.clock()

        grasp = self._grasp_id
        fut: Future[Any] = worker.submit(call) if worker is not None else _run_inline(call)
        if action == "stop_arm":
            self._stop_pending = fut

        def finished(f: Future[Any]) -> None:
            exc = f.exception()
            if exc is not None:
                rec.errors[action] = str(exc)
                # A run of failed retries is logged by its first, not at the poll rate.
                if self._stop_retry_logged() if action == "stop_arm" else not self._tighten_failing:
                    log.error("%s failed: %s", action, exc)
                if self.metrics is not None:
                    self.metrics.device_errors.labels(device=action.split("_")[1], kind="reaction").inc()
                if action == "stop_arm":
                    # Owed until a stop is taken (``retry_stop``, from the arm's health poll).
                    self.stop_owed = self.stop_owed or str(arg)
                else:
                    # A gripper that cannot tighten leaves the object at risk: halt the arm whatever the policy,
                    # and owe the tighten until the servo answers again (retry_tighten), unless its grasp has let
                    # go meanwhile. ``_owed`` last: the loop thread reads it first.
                    if grasp == self._grasp_id:
                        self.tighten_owed, self._owed_call = arg, fn
                        self._owed = True
                    if not self._tighten_failing:
                        # One fail-safe per run of failures: the retry on every healthy poll (a servo that answers
                        # its status but fails the command) would otherwise fail safe twice a second.
                        self._tighten_failing = True
                        self.failsafe(f"{action} failed")
            else:
                if action == "tighten_gripper":
                    self._owed = self._tighten_failing = False  # the grasp is secured: nothing owed any more
                else:
                    self.stop_owed, self._stop_retries = None, 0  # the arm took a stop
                if self.metrics is not None and action in rec.done:
                    self.metrics.reaction_seconds.observe(rec.done[action] - rec.t_decision)

        fut.add_done_callback(lambda f: self._handle(finished, f))
        return fut

    def _handle(self, finished: Callable[[Future[Any]], None], fut: Future[Any]) -> None:
        post = self.post
        if post is not None:
            try:
                post(finished, fut)
                return
            except RuntimeError:  # the loop has closed (shut down): handled here, not lost
                pass
        finished(fut)


def _run_inline(call: Callable[[], None]) -> Future[Any]:
    fut: Future[Any] = Future()
    try:
        call()
        fut.set_result(None)
    except Exception as exc:  # reported through the future like a worker would
        fut.set_exception(exc)
    return fut
