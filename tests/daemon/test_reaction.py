"""Reaction policy (unit level: recording doubles of the devices; the real drivers are tested end to end)."""

import threading
import time

from slipd.daemon.reaction import Reaction
from slipd.daemon.worker import DeviceWorker
from slipd.metrics import Metrics


class _Dev:
    def __init__(self, fail: bool = False) -> None:
        self.calls: list[tuple] = []
        self.fail = fail
        self.event = threading.Event()

    def stop(self, reason: str = "") -> None:
        self.calls.append(("stop", reason))
        self.event.set()

    def tighten(self, level: float | None = None) -> None:
        if self.fail:
            raise RuntimeError("no status packet")
        self.calls.append(("tighten", level))
        self.event.set()


class _Clock:
    t = 100.0

    def __call__(self) -> float:
        return self.t


def _reaction(**kw):
    arm, grip = _Dev(), _Dev(fail=kw.pop("grip_fail", False))
    clock = _Clock()
    r = Reaction(arm=arm, gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), clock=clock, **kw)
    return r, arm, grip, clock


def _wait(futs) -> None:
    for f in futs:
        f.exception(timeout=5)


def test_alarm_stops_arm_and_tightens_to_secure() -> None:
    r, arm, grip, _ = _reaction()
    _wait(r.on_alarm(0.7))
    assert arm.calls == [("stop", "slip alarm")]
    assert grip.calls == [("tighten", None)]
    assert set(r.records[0].done) == {"stop_arm", "tighten_gripper"}


def test_rearm_window_suppresses_repeats_but_graded_escalates() -> None:
    r, arm, grip, clock = _reaction(graded=True, rearm_after_s=1.0)
    _wait(r.on_alarm(0.4))
    clock.t += 0.04
    assert r.on_alarm(0.3) == []  # lower risk inside the re-arm window: nothing new
    clock.t += 0.04
    _wait(r.on_alarm(0.9))  # higher risk: tighten further, the arm is already stopping
    assert [c[0] for c in arm.calls] == ["stop"]
    assert grip.calls == [("tighten", 0.4), ("tighten", 0.9)]
    clock.t += 2.0
    _wait(r.on_alarm(0.5))
    assert len(arm.calls) == 2
    # Past the window the arm is stopped again, but the grip is never loosened: 0.5 would move the jaw back from 0.9.
    assert grip.calls[-1] == ("tighten", 0.9)


def test_graded_grip_never_loosens_after_a_secure_or_until_a_new_grasp() -> None:
    """A fail-safe's tighten (the secure setting) counts as level 1; a later graded alarm squeezes at that level, and
    so does the retry of a lower tighten owed from before. A new grasp (``reset``) starts from the alarm's level."""
    r, _arm, grip, clock = _reaction(graded=True, rearm_after_s=1.0, on_failsafe="stop_arm_and_tighten")
    _wait([f for f in [r.failsafe("sensor_stall")] if f is not None])
    assert _until(lambda: ("tighten", None) in grip.calls)
    clock.t += 2.0
    _wait(r.on_alarm(0.3))
    assert grip.calls[-1] == ("tighten", 1.0)
    r.reset()
    clock.t += 2.0
    _wait(r.on_alarm(0.3))
    assert grip.calls[-1] == ("tighten", 0.3)


def test_actions_order_and_selection() -> None:
    r, arm, grip, _ = _reaction(actions=["tighten_gripper"])
    _wait(r.on_alarm(1.0))
    assert arm.calls == [] and grip.calls == [("tighten", None)]


def test_gripper_failure_falls_back_to_arm_stop() -> None:
    r, arm, _grip, _ = _reaction(actions=["tighten_gripper"], grip_fail=True)
    _wait(r.on_alarm(1.0))
    assert arm.event.wait(5)
    assert arm.calls and arm.calls[0][1].startswith("fail-safe")
    assert r.failsafe_count == 1 and "tighten_gripper" in r.records[0].errors


def _until(cond, timeout: float = 5.0) -> bool:
    """Poll ``cond`` until true or ``timeout``: a future's done callbacks run in its worker after ``exception()``
    has returned in the caller, so what a callback sets is not there yet when the future is."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def test_failed_tighten_is_owed_and_retried_once_the_servo_answers() -> None:
    r, arm, grip, _ = _reaction(graded=True, grip_fail=True)
    _wait(r.on_alarm(0.6))
    assert arm.event.wait(5) and _until(lambda: r.tighten_owed == 0.6)
    grip.fail = False  # the servo answers again
    _wait([r.retry_tighten()])
    assert grip.calls == [("tighten", 0.6)]
    assert r.retry_tighten() is None  # paid: nothing owed any more
    grip.fail, arm.event = True, threading.Event()
    _wait(r.on_alarm(1.0))
    assert arm.event.wait(5)  # the failure was handled (owed, fail-safe stop)
    r.reset()  # a new grasp: a failed tighten of the old one is not sent again
    assert r.retry_tighten() is None


def test_a_tighten_that_fails_after_its_grasp_let_go_is_not_owed() -> None:
    """A tighten still on the gripper's thread when the grasp ends (``released``) and failing after it is owed to no
    one: the next grasp must not get it when the servo answers."""
    gate = threading.Event()

    class _Slow(_Dev):
        def tighten(self, level: float | None = None) -> None:
            gate.wait(5)
            raise RuntimeError("no status packet")

    arm, grip = _Dev(), _Slow()
    r = Reaction(arm=arm, gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics())
    futs = r.on_alarm(1.0)
    r.released()
    gate.set()
    _wait(futs)
    assert _until(lambda: r.failsafe_count == 1)  # the failure is still a device fault: fail safe
    assert not r._owed and r.retry_tighten() is None


def test_a_graded_tighten_never_goes_below_the_grip_found_at_start_up() -> None:
    """slipd restarted mid-grasp and the gripper kept the secure grip it found (``Gripper.take_over``): a graded alarm
    of low risk tightens at that level, not below it; a new grasp starts from nothing."""
    grip = _Dev()
    grip.level_found = 1.0
    r = Reaction(arm=_Dev(), gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), graded=True, rearm_after_s=0.0)
    _wait(r.on_alarm(0.3))
    assert grip.calls == [("tighten", 1.0)]
    r.released()
    _wait(r.on_alarm(0.3))
    assert grip.calls[-1] == ("tighten", 0.3)


def test_records_are_bounded() -> None:
    from slipd.daemon.reaction import MAX_RECORDS

    r, _arm, _grip, clock = _reaction(rearm_after_s=0.0)
    for _ in range(MAX_RECORDS + 50):
        clock.t += 1.0
        _wait(r.on_alarm(1.0))
    assert len(r.records) == MAX_RECORDS


def test_disabled_reaction_issues_nothing() -> None:
    r, arm, grip, _ = _reaction(enabled=False)
    assert r.on_alarm(1.0) == [] and r.failsafe("sensor stalled") is None
    assert arm.calls == grip.calls == []


def test_failsafe_policies() -> None:
    r, arm, grip, _ = _reaction(on_failsafe="stop_arm_and_tighten")
    f = r.failsafe("sensor_stall")
    f.exception(timeout=5)
    assert grip.event.wait(5)
    assert arm.calls[0][1] == "fail-safe: sensor_stall" and grip.calls == [("tighten", None)]
    r, arm, grip, _ = _reaction(on_failsafe="log_only")
    assert r.failsafe("sensor_stall") is None and arm.calls == grip.calls == []


def test_a_failsafe_under_grip_control_secures_at_the_objects_force_limit() -> None:
    """``stop_arm_and_tighten`` with ``policy: grip_control``: the grip goes to the object's force limit (8 N for a
    paper cup), not to the secure setting (the jaw's full force, which would crush it)."""
    from slipd.daemon.grip_control import GripControlSettings

    class _Jaw(_Dev):
        def grip_force(self, newtons: float) -> None:
            self.calls.append(("grip_force", newtons))
            self.event.set()

    arm, jaw = _Dev(), _Jaw()
    r = Reaction(arm=arm, gripper=jaw, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), on_failsafe="stop_arm_and_tighten", policy="grip_control",
                 grip=GripControlSettings(max_force_n=8.0))
    r.failsafe("sensor_stall").exception(timeout=5)
    assert jaw.event.wait(5)
    assert arm.calls[0][1] == "fail-safe: sensor_stall" and jaw.calls == [("grip_force", 8.0)]


class _Jaw(_Dev):
    """A gripper with force control (grip_control's)."""

    def grip_force(self, newtons: float) -> None:
        if self.fail:
            raise RuntimeError("no status packet")
        self.calls.append(("grip_force", newtons))
        self.event.set()


def test_grip_controls_failsafe_grip_is_owed_as_itself_not_as_a_tighten() -> None:
    """Under grip_control a fail-safe that tightens grips at the object's limit; when that command fails, what is
    owed is that grip: a tighten to the secure setting would squeeze past the limit (and a force is no level)."""
    from slipd.daemon.grip_control import GripControlSettings

    arm, grip = _Dev(), _Jaw(fail=True)
    r = Reaction(arm=arm, gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), clock=_Clock(), on_failsafe="stop_arm_and_tighten", policy="grip_control",
                 grip=GripControlSettings(max_force_n=8.0))
    r.failsafe("sensor_stall")
    assert _until(lambda: r._owed and r.tighten_owed == 8.0)
    grip.fail = False  # the servo answers again
    _wait([r.retry_tighten()])
    assert grip.calls == [("grip_force", 8.0)]
    assert r.retry_tighten() is None


class _RefusingArm(_Dev):
    """An arm whose controller refuses stops (``URArm.stop`` reports it in its result; it never raises)."""

    def __init__(self) -> None:
        super().__init__()
        self.refuse = True

    def stop(self, reason: str = ""):
        from slipd.io.arm import StopResult

        self.calls.append(("stop", reason))
        self.event.set()
        return StopResult(not self.refuse, "stopl", reason, 0.0, 0.0, error="" if not self.refuse else "refused")


def test_a_refused_arm_stop_is_a_failure_owed_until_the_controller_takes_one() -> None:
    arm, grip = _RefusingArm(), _Dev()
    r = Reaction(arm=arm, gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), clock=_Clock())
    _wait(r.on_alarm(1.0))
    assert _until(lambda: r.stop_owed == "slip alarm")
    assert "refused" in r.records[0].errors["stop_arm"] and "stop_arm" not in r.records[0].done
    _wait([r.retry_stop()])  # refused again: still owed
    assert r.stop_owed == "slip alarm" and len(arm.calls) == 2
    arm.refuse = False
    _wait([r.retry_stop()])
    assert _until(lambda: r.stop_owed is None) and arm.calls[-1] == ("stop", "retry: slip alarm")
    assert r.retry_stop() is None  # taken: nothing owed
    arm.refuse = True
    _wait(r.on_alarm(1.0) if False else [r.failsafe("sensor_stall")])
    assert _until(lambda: r.stop_owed == "fail-safe: sensor_stall")
    r.arm_halted()  # a protective stop halted it
    assert r.retry_stop() is None


def test_one_arm_stop_in_flight_however_many_fail_safes() -> None:
    """Fail-safes while a stop hangs (a dashboard fallback waiting on a controller that does not answer) join the
    stop in flight instead of queueing one each behind it."""
    gate = threading.Event()

    class _SlowArm(_Dev):
        def stop(self, reason: str = "") -> None:
            self.calls.append(("stop", reason))
            gate.wait(5)

    arm = _SlowArm()
    r, grip = None, _Dev()
    r = Reaction(arm=arm, gripper=grip, arm_worker=DeviceWorker("arm"), gripper_worker=DeviceWorker("grip"),
                 metrics=Metrics(), clock=_Clock())
    first = r.failsafe("sensor_stall")
    assert all(r.failsafe("grip_control failed") is first for _ in range(50))
    gate.set()
    _wait([first])
    assert len(arm.calls) == 1 and r.failsafe_count == 51
    _wait([r.failsafe("sensor_stall")])  # the first is done: a new stop goes out
    assert len(arm.calls) == 2


def test_grip_control_knows_the_fail_safe_gripped_at_the_limit() -> None:
    """The fail-safe's grip at the object's limit goes to the jaw behind the controller's back: the controller must take
    it as its sent target, or it keeps believing its older, lower target holds and never commands the jaw again."""
    from slipd.daemon.grip_control import GripControlSettings
    from slipd.detect.contact import ContactState

    arm, grip = _Dev(), _Jaw()
    r = Reaction(arm=arm, gripper=grip, arm_worker=None, gripper_worker=None, metrics=Metrics(), clock=_Clock(),
                 on_failsafe="stop_arm_and_tighten", policy="grip_control", grip=GripControlSettings(max_force_n=30.0))
    gc = r.grip_control
    assert gc is not None
    state = ContactState((0.0,) * 9, None, None, 0.0, 10.0, 1.0, shear_n=1.0)
    for k in range(30):  # the grasp settles and the controller takes it over at 10 N
        r.on_detection(state, 0.01 * k, False)
    assert gc.target == 10.0
    r.failsafe("sensor_stall")
    assert grip.calls[-1] == ("grip_force", 30.0) and gc.target == 30.0


def test_a_tighten_that_keeps_failing_on_retry_fails_safe_once() -> None:
    """The owed tighten is retried on every healthy gripper poll (twice a second): a servo that answers its status
    but fails the command must not fail safe on every retry."""
    r, _, grip, clock = _reaction(grip_fail=True)
    _wait(r.on_alarm(1.0))
    assert _until(lambda: r._owed) and r.failsafe_count == 1
    for _ in range(5):
        _wait([r.retry_tighten()])
        assert _until(lambda: r._owed)
    assert r.failsafe_count == 1
    grip.fail = False
    _wait([r.retry_tighten()])
    assert _until(lambda: not r._owed)
    grip.fail = True
    clock.t += 2.0  # past the re-arm window: a new alarm, a new tighten, a new run of failures
    _wait(r.on_alarm(1.0))
    assert _until(lambda: r.failsafe_count == 2)


def test_a_stop_refused_at_every_poll_is_logged_by_a_line_per_twenty_tries(caplog) -> None:
    """The owed stop is retried on every arm health poll (0.15 s): a controller that keeps refusing must not fill the
    journal at the poll rate."""
    import logging

    caplog.set_level(logging.WARNING, logger="slipd.daemon.reaction")
    arm = _RefusingArm()
    r = Reaction(arm=arm, gripper=None, arm_worker=None, gripper_worker=None, metrics=Metrics(), clock=_Clock(),
                 actions=["stop_arm"])
    r.on_alarm(1.0)
    for _ in range(45):
        r.retry_stop()
    assert len(arm.calls) == 46 and r.stop_owed == "slip alarm"
    failed = [m for m in caplog.messages if m.startswith("stop_arm failed")]
    retrying = [m for m in caplog.messages if m.startswith("arm: retrying")]
    assert len(failed) == 4 and len(retrying) == 3  # the alarm's stop; tries 1, 21 and 41


def test_device_outcomes_are_handled_on_the_loops_thread_while_the_daemon_runs() -> None:
    """A future's callbacks run on the device worker's thread: a failed tighten's fail-safe then queued an arm stop and
    set the grip controller's target there, beside the loop's own use of that state. With ``post`` (the daemon's loop)
    the outcome is handled on the loop's thread."""
    import asyncio
    import contextlib
    import threading

    r, arm, _grip, clock = _reaction(actions=["tighten_gripper"], grip_fail=True)
    threads: list[int] = []
    failsafe = r.failsafe

    def spy(reason: str):
        threads.append(threading.get_ident())
        return failsafe(reason)

    r.failsafe = spy  # type: ignore[method-assign]

    async def main() -> int:
        r.post = asyncio.get_running_loop().call_soon_threadsafe
        futs = r.on_alarm(1.0)
        with contextlib.suppress(RuntimeError):
            await asyncio.wrap_future(futs[0])  # the tighten fails on the gripper's thread
        for _ in range(100):
            if threads:
                break
            await asyncio.sleep(0.01)
        return threading.get_ident()

    loop_thread = asyncio.run(main())
    assert threads == [loop_thread] and r._owed
    assert arm.event.wait(5) and arm.calls[0][1].startswith("fail-safe")
    # A loop that has closed: the outcome is handled where it happens, not lost.
    threads.clear()
    r._tighten_failing = False
    clock.t += 2.0
    _wait(r.on_alarm(1.0))
    assert _until(lambda: len(threads) == 1) and threads[0] != loop_thread
