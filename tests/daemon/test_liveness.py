"""Never blind and alive: every way of going blind fails safe once, and only a live loop says it is alive.

The real ``Daemon`` (pyserial reader, ONNX ensemble, dynamixel-sdk, ur_rtde) runs in-process against the
emulated PapillArray (pty), MX-28 (pty) and UR controller (own process). Frames are hand-made and written
to the sensor's pty in real time by a writer thread, so a test can switch the stream into one fault: a
silent sensor, a packet counter that never advances, non-finite values, bit-identical frames. systemd is a
real AF_UNIX datagram socket (``$NOTIFY_SOCKET``) that records ``READY=1`` and ``WATCHDOG=1``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ROOT

from slipd.config import load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.daemon.sdnotify import Notifier
from slipd.detect.ensemble import Ensemble
from slipd.io.pts import Frame
from slipd.metrics import Metrics
from slipd.sim.devices.mx28 import EmulatedMX28
from slipd.sim.devices.papillarray import EmulatedPapillArray
from slipd.sim.devices.ur_controller import URControllerProcess

HOST = "127.0.0.6"  # test_faults uses .5
STALL_MS = 150
WATCHDOG_S = 0.1  # systemd's WatchdogSec= (pings every half)

pytestmark = pytest.mark.timeout(120)


class Writer:
    """Writes hand-made frames to the emulated sensor in real time (blocks of 10 every 10 ms) in ``mode``:
    ``ok`` (a noisy still grasp, counter advancing), ``stuck`` (the counter never advances), ``nan`` (every
    value NaN), ``frozen`` (bit-identical frames, counter advancing)."""

    def __init__(self, sensor: EmulatedPapillArray) -> None:
        self.sensor = sensor
        self.mode = "ok"
        self.rng = np.random.default_rng(0)
        self.counter = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._frozen = self._still()

    def _still(self) -> np.ndarray:
        force = np.zeros((9, 3), np.float32)
        force[:, 2] = 1.5
        return force + self.rng.normal(0.0, 0.01, force.shape).astype(np.float32)

    def _frame(self, i: int) -> Frame:
        disp = np.zeros((9, 3), np.float32)
        force = self._still()
        if self.mode == "nan":
            force[:] = np.nan
        elif self.mode == "frozen":
            force = self._frozen.copy()
        if self.mode != "stuck":
            self.counter += 1
        return Frame(counter=self.counter, t_us=i * 1000, force=force, disp=disp)

    def _run(self) -> None:
        t0, i = time.monotonic(), 0
        while not self._stop.is_set():
            self.sensor.write_frames([self._frame(i + k) for k in range(10)], timeout=10.0)
            i += 10
            delay = t0 + i / 1000 - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)


class Systemd:
    """The notify socket: records every datagram with its arrival time."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.05)
        self.got: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.got.append((time.monotonic(), self.sock.recv(4096).decode()))
            except TimeoutError:
                continue

    def count(self, what: str, since: float = 0.0) -> int:
        return sum(1 for t, msg in list(self.got) if t >= since and what in msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


@pytest.fixture(scope="module")
def controller():
    ur = URControllerProcess(HOST)
    ur.start()
    yield ur
    ur.stop()


@pytest.fixture(scope="module")
def base_cfg(tiny_model_json):
    cfg = load_config(ROOT / "config" / "sim.yaml")
    return override(cfg, {
        "model.manifest": str(tiny_model_json), "model.detector": "onnx", "decision.threshold": 0.999,
        "model.stride": 10, "sensor.tare": "startup", "sensor.tare_samples": 100, "recorder.enabled": False,
        "sensor.stall_timeout_ms": STALL_MS, "reaction.rearm_after_s": 0.0, "control.watchdog": True,
        "arm.enabled": True, "arm.host": HOST, "arm.watchdog_s": 0.3,
    })


def metric(m: Metrics, name: str, **labels: str) -> float:
    v = m.registry.get_sample_value(name, labels or None)
    return 0.0 if v is None else v


def failsafes(m: Metrics) -> dict[str, float]:
    out = {}
    for fam in m.registry.collect():
        if fam.name == "slipd_failsafe_stops":
            out = {s.labels["reason"]: s.value for s in fam.samples if s.name.endswith("_total")}
    return out


async def until(pred, timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for: {what}")
        await asyncio.sleep(0.01)


def run_daemon(cfg, ur: URControllerProcess, tmp_path, monkeypatch, scenario) -> tuple[Daemon, Systemd]:
    """Fresh sensor and servo emulators, a notify socket and the daemon; ``scenario(daemon, writer,
    systemd)`` runs while the daemon does (the writer is not started: the scenario decides)."""
    monkeypatch.setenv("WATCHDOG_USEC", str(int(WATCHDOG_S * 1e6)))
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    systemd = Systemd(str(tmp_path / "notify.sock"))
    sensor, servo = EmulatedPapillArray(), EmulatedMX28()
    cfg = override(cfg, {"sensor.port": sensor.port, "gripper.port": servo.port})
    writer = Writer(sensor)
    metrics = Metrics()
    daemon = None
    try:
        arm, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=metrics, arm=arm, gripper=gripper,
                        notifier=Notifier(systemd.path))

        async def main() -> None:
            task = asyncio.create_task(daemon.run())
            await daemon.ready.wait()
            try:
                await scenario(daemon, writer, systemd)
            finally:
                daemon.stop()
                await task

        asyncio.run(main())
    finally:
        writer.stop()
        if daemon is not None:
            daemon.close()
        sensor.close()
        servo.close()
        systemd.close()
    return daemon, systemd


def test_silent_sensor_from_start_up_fails_safe_and_never_reports_ready(controller, base_cfg, tmp_path,
                                                                         monkeypatch, caplog) -> None:
    caplog.set_level(logging.ERROR, logger="slipd.daemon.loop")
    seen: dict[str, object] = {}

    async def scenario(d: Daemon, w: Writer, sd: Systemd) -> None:
        stops0 = controller.state().stop_count
        await until(lambda: failsafes(d.metrics).get("sensor_silent", 0) == 1, timeout=3.0,
                    what="sensor_silent fail-safe")
        await until(lambda: controller.state().stop_count > stops0, what="the stop reached the UR controller")
        await asyncio.sleep(0.5)  # still silent: no second stop, no sign of life
        seen["gauges"] = (metric(d.metrics, "slipd_ready"), metric(d.metrics, "slipd_live"))

    d, sd = run_daemon(base_cfg, controller, tmp_path, monkeypatch, scenario)
    assert failsafes(d.metrics) == {"sensor_silent": 1.0}
    assert seen["gauges"] == (1.0, 0.0)  # the loop runs (slipd_ready) but is not live
    assert sd.count("READY=1") == 0 and sd.count("WATCHDOG=1") == 0
    assert not d.live and d.started_live is False and d.stats.decisions == 0
    blind = [r.getMessage() for r in caplog.records if r.getMessage().startswith("blind:")]
    assert len(blind) == 1 and "since start-up" in blind[0], blind


def test_a_sensor_that_starts_late_still_gets_ready_reported_once_live(controller, base_cfg, tmp_path,
                                                                        monkeypatch) -> None:
    """A blind episode before the first live decision (the sensor starts streaming after the stall timeout) must not
    cost READY=1: under Type=notify systemd would kill a daemon that works, after TimeoutStartSec."""

    async def scenario(d: Daemon, w: Writer, sd: Systemd) -> None:
        await until(lambda: failsafes(d.metrics).get("sensor_silent", 0) == 1, timeout=3.0,
                    what="sensor_silent fail-safe")
        w.start()
        await until(lambda: d.live, what="live on the first frames")
        await until(lambda: sd.count("READY=1") == 1, what="READY=1 after the first live decision")
        await until(lambda: sd.count("WATCHDOG=1") >= 1, what="watchdog pings once ready")

    d, sd = run_daemon(base_cfg, controller, tmp_path, monkeypatch, scenario)
    assert d.started_live and sd.count("READY=1") == 1


@pytest.mark.parametrize("mode, reason", [("stuck", "sensor_counter_stuck"), ("nan", "sensor_nonfinite"),
                                          ("frozen", "sensor_frozen")])
def test_blind_stream_fails_safe_once_stops_the_pings_and_the_arm_watchdog_then_recovers(
        controller, base_cfg, tmp_path, monkeypatch, caplog, mode: str, reason: str) -> None:
    caplog.set_level(logging.WARNING, logger="slipd.daemon.loop")
    seen: dict[str, object] = {}

    async def scenario(d: Daemon, w: Writer, sd: Systemd) -> None:
        w.start()
        await until(lambda: sd.count("READY=1") == 1, what="READY=1 after the first live decision")
        assert d.stats.decisions > 0  # READY waited for a decision
        await until(lambda: sd.count("WATCHDOG=1") >= 2, what="watchdog pings while live")
        await until(lambda: controller.state().watchdog_hz > 0, what="the arm's watchdog armed by a kick")
        stops0 = controller.state().stop_count
        w.mode = mode
        t_fault = time.monotonic()
        await until(lambda: failsafes(d.metrics).get(reason, 0) == 1, timeout=3.0, what=f"{reason} fail-safe")
        seen["detected_s"] = time.monotonic() - t_fault
        t_blind = time.monotonic()
        await until(lambda: controller.state().stop_count > stops0, what="the stop reached the UR controller")
        # No kicks while blind: the controller ends the control script (and halts the arm) by itself.
        s = await asyncio.to_thread(controller.wait_for, lambda s: not s.control_script_running, 3.0,
                                    "the arm's watchdog expiring")
        seen["expired_kind"] = s.last_stop_kind
        await asyncio.sleep(0.3)
        seen["pings_blind"] = sd.count("WATCHDOG=1", since=t_blind + WATCHDOG_S / 2 + 0.02)
        seen["failsafes_blind"] = dict(failsafes(d.metrics))
        w.mode = "ok"
        seen["live_gauge_blind"] = metric(d.metrics, "slipd_live")
        await until(lambda: d.live, what="live again on fresh frames")
        t_live = time.monotonic()
        await until(lambda: sd.count("WATCHDOG=1", since=t_live) >= 2, what="pings resume")
        # Live again: the control script is re-uploaded and the watchdog armed again.
        await asyncio.to_thread(controller.wait_for, lambda s: s.control_script_running and s.watchdog_hz > 0,
                                5.0, "the control script back with its watchdog")

    d, sd = run_daemon(base_cfg, controller, tmp_path, monkeypatch, scenario)
    assert seen["failsafes_blind"] == {reason: 1.0}  # one fault, one stop, one label
    assert failsafes(d.metrics) == {reason: 1.0}
    assert seen["pings_blind"] == 0  # systemd hears nothing from a blind loop
    assert seen["live_gauge_blind"] == 0.0
    assert seen["detected_s"] < 2.0  # generous: the stall timeout is 0.15 s
    assert sd.count("READY=1") == 1
    blind = [r.getMessage() for r in caplog.records if r.getMessage().startswith("blind:")]
    assert len(blind) == 1, blind
    assert any(r.getMessage() == f"live again after {reason}" for r in caplog.records)
    assert not d.stats.alarms


def test_a_stream_that_stops_short_of_a_decision_is_a_stall_even_when_its_last_frames_were_read_late(base_cfg) -> None:
    # On a busy machine the frames after a decision can be read, and stamped fresh, well after they arrived. When the
    # stream then stops before the frame that completes the next window, the decision's deadline passes before the
    # fresh-data one: the cause is still the stream (sensor_stall), not the detector (no_decisions). A clean-clone CI
    # run once counted test_deploy's stall as no_decisions.

    daemon = Daemon(base_cfg, Ensemble.load(base_cfg.model.manifest), metrics=Metrics())
    sensor = SimpleNamespace(connected=True, frames=5000, last_frame_time=None, last_repeat_time=None)
    daemon.sensor = sensor
    daemon._restart()  # the next valid decision is due once the detector has its samples again
    t = time.monotonic()
    need = daemon.detector.samples_to_decision()
    sensor.frames += need - 3  # all but the last three came, read 50 ms late
    read = t + need / base_cfg.sensor.rate_hz + 0.05
    sensor.last_frame_time = daemon._fresh_t = read
    daemon._fresh_ts[:] = read
    now = daemon._decision_due + 0.001
    assert now - daemon._fresh_t < daemon._stall_s  # by its stamp the data is not stale yet
    cause = daemon.liveness.blind_cause(now)
    assert cause is not None and cause[0] == "sensor_stall", cause
    sensor.frames += 3  # every frame it needed came, and still no decision: the detector's fault
    cause = daemon.liveness.blind_cause(now)
    assert cause is not None and cause[0] == "no_decisions", cause


class _SilentServo:
    """A gripper whose tighten fails (no status packet) until ``fail`` is cleared; counts its calls."""

    def __init__(self) -> None:
        self.fail, self.calls = True, 0

    def tighten(self, level: float | None = None) -> None:
        self.calls += 1
        if self.fail:
            raise RuntimeError("no status packet")


class _RefusingArm:
    """An arm whose controller refuses the stop until ``refuse`` is cleared; counts its calls."""

    def __init__(self) -> None:
        self.refuse, self.calls = True, 0

    def stop(self, reason: str) -> object:
        from slipd.io.arm import StopResult

        self.calls += 1
        return StopResult(not self.refuse, "stopl", reason, 0.0, 0.0, error="refused" if self.refuse else "")


def test_the_health_polls_retry_an_owed_tighten_and_an_owed_arm_stop(base_cfg) -> None:
    """A tighten that failed in a silence shorter than the gripper's poll period is sent again on the next healthy
    poll (no 'healthy again' transition is ever seen); a stop the controller refused is sent again on every arm poll
    that reaches it, and a protective stop (the arm halted) clears it."""
    from concurrent.futures import Future

    Grip, Arm = _SilentServo, _RefusingArm

    def done(value: object) -> Future[object]:
        f: Future[object] = Future()
        f.set_result(value)
        return f

    healthy = SimpleNamespace(healthy=True, hardware_error=0, hardware_errors=())
    grip, arm = Grip(), Arm()
    cfg = override(base_cfg, {"arm.enabled": False, "reaction.on_failsafe": "log_only",
                              "reaction.actions": ["tighten_gripper"]})
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics())
    daemon.reaction.gripper, daemon.reaction.gripper_worker = grip, None  # calls run inline
    daemon.reaction.arm, daemon.reaction.arm_worker = arm, None
    daemon.reaction.actions, daemon.reaction.on_failsafe = ("stop_arm", "tighten_gripper"), "stop_arm"
    daemon.health["gripper"] = "ok"
    daemon.reaction.on_alarm(1.0)
    # The alarm's stop, and the fail-safe's for the failed tighten: both refused.
    assert daemon.reaction._owed and grip.calls == 1 and arm.calls == 2 and daemon.reaction.stop_owed
    grip.fail = False
    daemon.device_health.on_gripper_health(done(healthy))  # healthy before and after: no transition
    assert grip.calls == 2 and not daemon.reaction._owed
    daemon.device_health.on_arm_health(done("ok"))
    assert arm.calls == 3 and daemon.reaction.stop_owed  # refused again
    daemon.device_health.on_arm_health(done("disconnected"))
    assert arm.calls == 3  # nothing to send it to
    arm.refuse = False
    daemon.device_health.on_arm_health(done("ok"))
    assert arm.calls == 4 and daemon.reaction.stop_owed is None
    arm.refuse = True
    daemon.reaction.failsafe("sensor_stall")
    assert daemon.reaction.stop_owed
    daemon.device_health.on_arm_health(done("protective_stop"))
    assert daemon.reaction.stop_owed is None


def test_a_tighten_owed_to_a_grasp_that_let_go_is_not_sent_to_the_next(base_cfg) -> None:
    """An alarm's tighten fails (the servo is silent), then the object leaves the jaw (no finger in contact at the
    following decisions): when the servo answers again nothing is sent, where the owed tighten once closed the jaw
    at the secure setting on whatever was there (the next object, a hand). Without the release it is still sent;
    an owed arm stop survives the release."""
    from concurrent.futures import Future

    Grip, Arm = _SilentServo, _RefusingArm

    done: Future[object] = Future()
    done.set_result(SimpleNamespace(healthy=True, hardware_error=0, hardware_errors=()))
    cfg = override(base_cfg, {"arm.enabled": False, "reaction.on_failsafe": "log_only",
                              "reaction.actions": ["tighten_gripper"]})
    rng = np.random.default_rng(0)

    def frames(n: int, fz: float) -> np.ndarray:
        force = rng.normal(0.0, 0.01, (n, 1, 9, 3)).astype(np.float32)
        force[:, :, :, 2] += fz
        return force

    for release in (False, True):
        grip, arm = Grip(), Arm()
        daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics())
        daemon.reaction.gripper, daemon.reaction.gripper_worker = grip, None  # calls run inline
        daemon.reaction.arm, daemon.reaction.arm_worker = arm, None
        daemon.reaction.actions, daemon.reaction.on_failsafe = ("stop_arm", "tighten_gripper"), "stop_arm"
        daemon.health["gripper"] = "ok"
        force = np.concatenate([frames(300, 0.0), frames(300, 1.5)] + ([frames(300, 0.0)] if release else []))
        t_us = np.arange(len(force), dtype=np.int64) * 1000
        for k in range(0, len(force), 10):
            daemon._on_block(t_us[k : k + 10], force[k : k + 10], np.zeros_like(force[k : k + 10]))
            if k == 500:  # in contact: an alarm whose tighten fails, and whose arm stop is refused
                assert daemon._grasp_held
                daemon.reaction.on_alarm(1.0)
                assert daemon.reaction._owed and grip.calls == 1 and daemon.reaction.stop_owed
        assert daemon._grasp_held is not release
        grip.fail = False
        daemon.device_health.on_gripper_health(done)  # the servo answers again
        assert grip.calls == (1 if release else 2)
        assert daemon.reaction.stop_owed  # the arm stays owed its stop


def test_frames_while_the_sensor_zeroes_itself_at_start_up_are_not_decided_on(base_cfg) -> None:
    """With ``tare: bias_command`` the daemon waits ``bias_timeout_s`` at start-up while the sensor zeroes itself. The
    frames of that time are neither zeroed nor its steady output: no decision (no alarm, no reaction) may come from
    them, and going live needs a decision after the bias (as after a reconnect)."""
    cfg = override(base_cfg, {"sensor.tare": "bias_command", "sensor.bias_timeout_s": 0.5, "arm.enabled": False,
                              "reaction.actions": ["tighten_gripper"], "reaction.on_failsafe": "log_only"})
    sensor, servo = EmulatedPapillArray(), EmulatedMX28()
    cfg = override(cfg, {"sensor.port": sensor.port, "gripper.port": servo.port})
    writer = Writer(sensor)
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics())
    seen: dict[str, object] = {}

    async def main() -> None:
        task = asyncio.create_task(daemon.run())
        writer.start()  # streaming from the first moment, through the bias
        await daemon.ready.wait()
        seen["at_ready"] = (daemon.stats.decisions, daemon.live)
        # Device outcomes are handled on this loop's thread while the daemon runs (``Reaction.post``).
        seen["post"] = daemon.reaction.post == asyncio.get_running_loop().call_soon_threadsafe
        await until(lambda: daemon.live, what="live on frames after the bias")
        seen["live_after"] = daemon.stats.decisions
        daemon.stop()
        await task

    try:
        asyncio.run(main())
    finally:
        writer.stop()
        daemon.close()
        sensor.close()
        servo.close()
    assert seen["at_ready"] == (0, False)
    assert seen["live_after"] >= 1
    assert seen["post"] and daemon.reaction.post is None


def test_a_restart_that_finds_the_jaw_gripping_keeps_the_sensors_zero(base_cfg) -> None:
    """slipd restarted mid-grasp (``Gripper.take_over`` found the jaw gripping): the start-up bias is not sent, so
    the held object's load is not taken for the zero and the contact stays visible to the detector. A start that found
    the jaw open zeroes the sensor as before (here under the same load, which then reads as no contact)."""

    class Grip:
        def __init__(self, gripping: bool) -> None:
            self.gripping_found = gripping

        def close(self) -> None:
            pass

    cfg = override(base_cfg, {"sensor.tare": "bias_command", "sensor.bias_timeout_s": 0.5, "arm.enabled": False,
                              "reaction.actions": ["tighten_gripper"], "reaction.on_failsafe": "log_only"})
    from slipd.recording import Recording

    force = np.random.default_rng(0).normal(0.0, 0.01, (5000, 9, 3)).astype(np.float32)
    force[:, :, 2] += 1.5  # a still grasp from the first frame, 1.5 N on every pillar
    held = Recording(t_us=np.arange(5000) * 1000, force=force, disp=np.zeros_like(force))
    for gripping in (True, False):
        sensor = EmulatedPapillArray(held, loop=True)  # streams on its own thread, which also obeys the commands
        daemon = Daemon(override(cfg, {"sensor.port": sensor.port}), Ensemble.load(cfg.model.manifest),
                        metrics=Metrics(), gripper=Grip(gripping))  # type: ignore[arg-type]

        async def main(daemon: Daemon, sensor: EmulatedPapillArray) -> None:
            sensor.start()
            # Streaming before the daemon opens the port: a bias that comes before the controller's first sample
            # has nothing to zero (the emulator, like the controller, takes the sample at hand).
            await until(lambda: sensor.frames_written > 10, what="the sensor streaming")
            task = asyncio.create_task(daemon.run())
            await until(lambda: daemon.live and daemon.stats.decisions > 20, what="live")
            daemon.stop()
            await task

        try:
            asyncio.run(main(daemon, sensor))
        finally:
            daemon.close()
            sensor.close()
        assert (("bias", None) in sensor.commands) is not gripping, sensor.commands
        assert daemon._grasp_held is gripping


def test_a_stop_during_the_start_up_bias_wait_ends_it(base_cfg) -> None:
    """SIGTERM while the daemon waits for the sensor to zero itself (``sensor.bias_timeout_s``, up to 30 s): run ends
    at once, where it once slept the wait out past systemd's 10 s TimeoutStopSec (killed before the devices closed)."""
    cfg = override(base_cfg, {"sensor.tare": "bias_command", "sensor.bias_timeout_s": 20.0, "arm.enabled": False,
                              "reaction.actions": ["tighten_gripper"], "reaction.on_failsafe": "log_only"})
    sensor = EmulatedPapillArray()
    daemon = Daemon(override(cfg, {"sensor.port": sensor.port}), Ensemble.load(cfg.model.manifest), metrics=Metrics())
    took: list[float] = []

    async def main() -> None:
        task = asyncio.create_task(daemon.run())
        await until(lambda: daemon._bias_until is not None, what="the bias wait")
        t0 = time.monotonic()
        daemon.stop()
        await asyncio.wait_for(task, 10.0)
        took.append(time.monotonic() - t0)

    try:
        asyncio.run(main())
    finally:
        daemon.close()
        sensor.close()
    assert took[0] < 2.0 and daemon.stats.decisions == 0


def test_the_daemons_start_up_keeps_a_grip_it_secured_before_a_restart(base_cfg) -> None:
    """The devices as ``slipd run`` builds them (real dynamixel-sdk, the emulated MX-28 keeping its registers across
    the two processes' connections): after a secure and a restart the servo still has the secure goal and effort, the
    gripper says it found the jaw gripping, and the new daemon's reaction starts the grasp at level 1."""
    cfg = override(base_cfg, {"arm.enabled": False, "reaction.actions": ["tighten_gripper"],
                              "reaction.on_failsafe": "log_only", "reaction.graded": True})
    with EmulatedMX28() as servo:
        cfg = override(cfg, {"gripper.port": servo.port})
        _, gripper = build_devices(cfg, Metrics())
        assert gripper is not None and not gripper.gripping_found  # a fresh servo: torque was off
        assert servo.register("goal_position") == cfg.gripper.hold_position
        gripper.tighten()
        time.sleep(0.5)  # the jaw closes on the object (the emulated servo runs on the real clock)
        gripper.close()  # slipd ends (torque_off_on_close is off): the servo holds on
        _, gripper = build_devices(cfg, Metrics())
        assert gripper is not None
        try:
            assert gripper.gripping_found and gripper.level_found == 1.0
            assert servo.register("goal_position") == cfg.gripper.secure_position
            assert servo.register("goal_pwm") == cfg.gripper.secure_pwm
            daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics(), gripper=gripper)
            assert daemon.reaction._grasp_level == 1.0
        finally:
            gripper.close()


def test_a_gripper_call_that_hangs_is_a_gripper_fault(base_cfg, monkeypatch) -> None:
    """A call stuck in the vendor library (the status poll, or a grip command it queues behind) never returned, so
    the gripper stayed 'ok' for good with the grip frozen; past GRIPPER_HANG_S it is a gripper fault (one fail-safe),
    and healthy again once the call returns."""
    from slipd.daemon import health

    monkeypatch.setattr(health, "GRIPPER_HANG_S", 0.3)
    release = threading.Event()

    class Grip:
        def read_status(self) -> object:
            release.wait(10)
            return SimpleNamespace(healthy=True, hardware_error=0, hardware_errors=())

        def close(self) -> None:
            pass

    cfg = override(base_cfg, {"arm.enabled": False, "reaction.on_failsafe": "log_only",
                              "reaction.actions": ["tighten_gripper"]})
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics(), gripper=Grip(),  # type: ignore[arg-type]
                    health_period_s=0.05, gripper_health_period_s=0.05)
    seen: dict[str, object] = {}

    async def main() -> None:
        task = asyncio.create_task(daemon.device_health.run())
        await asyncio.sleep(0.8)
        seen["hung"] = (daemon.health.get("gripper"), daemon.stats.failsafes)
        release.set()
        await until(lambda: daemon.health.get("gripper") == "ok", what="healthy once the call returned")
        seen["failsafes"] = daemon.stats.failsafes
        daemon.stop()
        await task

    try:
        asyncio.run(main())
    finally:
        release.set()
        daemon.close()
    health, failsafes = seen["hung"]
    assert isinstance(health, str) and health.startswith("not answering: a call has not returned") and failsafes == 1
    assert seen["failsafes"] == 1


def test_a_fail_safe_recording_carries_the_tare_offset_the_daemon_used(base_cfg, tmp_path) -> None:
    """An alarm's recording carried the daemon's tare offset, a fail-safe's did not: replay then re-tared from frames
    taken under load and every decision differed from the daemon's."""
    from slipd.daemon.recorder import Recorder
    from slipd.recording import Recording

    daemon = Daemon(base_cfg, Ensemble.load(base_cfg.model.manifest), metrics=Metrics())
    daemon.recorder = Recorder(tmp_path, 1000, seconds_before=0.1, seconds_after=0.0)
    rng = np.random.default_rng(0)
    force = (rng.normal(0, 0.01, (300, 9, 3)) + np.array([0.2, -0.1, 1.0])).astype(np.float32)
    daemon.detector.push_many(force, np.arange(300) * 1000)  # the start-up tare: an offset of about (0.2, -0.1, 1.0)
    daemon.recorder.push_frames(np.arange(300) * 1000, force, np.zeros_like(force))
    daemon._last_t_us = 299_000
    daemon.liveness.go_blind("sensor_stall", "no frame for 60 ms")
    (path,) = daemon.recorder.wait(5)
    rec = Recording.load(path)
    assert rec.meta["trigger"]["reason"] == "failsafe"
    offset = np.asarray(rec.meta["tare_offset"])
    assert np.allclose(offset, daemon.detector.offset) and abs(offset[0, 2] - 1.0) < 0.05
    daemon.recorder.close()
    daemon.close()


def test_an_unplugged_gripper_adapter_is_reopened_and_the_owed_tighten_sent(base_cfg, tmp_path) -> None:
    """The USB adapter of the servo is unplugged and plugged back under the same path. The driver kept its dead file
    handle (a bare termios.error, not even counted) and the daemon never reopened it: the gripper stayed 'not
    answering' and the tighten a slip alarm owed was never sent. Now the health task reopens the port with back-off
    and, the servo holding again, the owed tighten goes out."""
    from dynamixel_sdk import PacketHandler

    from slipd.io.gripper import _TimedPortHandler
    from slipd.sim.devices.mx28 import JawParams

    link = tmp_path / "ttyDXL"

    def plug() -> EmulatedMX28:
        dev = EmulatedMX28(protocol=2.0, jaw=JawParams(initial_position=2000.0))
        if link.is_symlink():
            link.unlink()
        link.symlink_to(dev.port)
        return dev

    first = plug()
    servos = [first]
    cfg = override(base_cfg, {"arm.enabled": False, "reaction.on_failsafe": "log_only",
                              "reaction.actions": ["tighten_gripper"], "gripper.port": str(link)})
    metrics = Metrics()
    _, gripper = build_devices(cfg, metrics)
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=metrics, gripper=gripper,
                    health_period_s=0.05, gripper_health_period_s=0.05)
    seen: dict[str, object] = {}

    async def main() -> None:
        task = asyncio.create_task(daemon.device_health.run())
        await until(lambda: daemon.health.get("gripper") == "ok", what="healthy at first")
        first.close()  # unplugged
        daemon.reaction.on_alarm(1.0)
        await until(lambda: daemon.reaction.tighten_owed is None and daemon.reaction._owed, what="the tighten owed")
        await until(lambda: daemon.health.get("gripper", "").startswith("not answering"), what="not answering")
        second = plug()  # back under the same path; the servo kept its power: torque on, holding
        servos.append(second)
        port = _TimedPortHandler(second.port, 100.0)
        port.baudrate = 1_000_000
        port.openPort()
        try:
            PacketHandler(2.0).write1ByteTxRx(port, 1, 64, 1)
        finally:
            port.closePort()
        secure = cfg.gripper.secure_position
        await until(lambda: second.register("goal_position") == secure, what="the owed tighten at the servo")
        seen["health"] = daemon.health.get("gripper")
        seen["reconnects"] = metrics.registry.get_sample_value("slipd_reconnects_total", {"device": "gripper"})
        daemon.stop()
        await task

    try:
        asyncio.run(main())
    finally:
        daemon.close()
        for s in servos:
            s.close()
    assert seen["reconnects"] == 1 and seen["health"] == "ok"
    assert metrics.registry.get_sample_value("slipd_device_errors_total", {"device": "gripper", "kind": "io"})


def test_a_crash_of_the_health_task_fails_safe_and_stops_the_daemon(base_cfg) -> None:
    """The supervision and health tasks had no watcher: one that raised died unseen (no device health, no arm
    reconnect for the rest of the run) while the systemd watchdog was still pinged. Now its end fails safe, stops the
    daemon and makes ``run`` fail (exit 1: systemd restarts it)."""

    class Grip:
        def read_status(self) -> object:
            return object()  # no ``healthy``: the health task's bookkeeping raises

        def close(self) -> None:
            pass

    cfg = override(base_cfg, {"arm.enabled": False, "reaction.on_failsafe": "log_only",
                              "reaction.actions": ["tighten_gripper"]})
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics(), gripper=Grip(),  # type: ignore[arg-type]
                    health_period_s=0.05, gripper_health_period_s=0.05)

    async def main() -> None:
        task = asyncio.create_task(daemon.device_health.run(), name="device health")
        task.add_done_callback(daemon._on_task_end)
        await until(lambda: daemon._stop.is_set(), what="the daemon asked to stop")
        with contextlib.suppress(AttributeError):
            await task

    try:
        asyncio.run(main())
    finally:
        daemon.close()
    assert daemon.stats.failsafes == 1 and isinstance(daemon._crashed, AttributeError)


def test_close_ends_the_arm_first_and_waits_once_for_a_hung_gripper(base_cfg, monkeypatch) -> None:
    """Shutdown closed the gripper, then the arm, each with its own 10 s timeout: a hung gripper thread delayed the end
    of the arm's control script past systemd's TimeoutStopSec (10 s), where SIGKILL raced it. Now the arm goes first
    and both share one deadline."""
    from slipd.daemon import loop as loop_mod

    monkeypatch.setattr(loop_mod, "DEVICE_CLOSE_TIMEOUT_S", 0.5)
    release = threading.Event()
    closed: dict[str, float] = {}

    class Grip:
        def read_status(self) -> object:
            return SimpleNamespace(healthy=True, hardware_error=0, hardware_errors=())

        def close(self) -> None:
            release.wait(10)  # hung in the vendor library

    class Arm:
        def read_state(self) -> object:
            return SimpleNamespace(connected=True, protective_stop=False)

        def close(self) -> None:
            closed["arm"] = time.monotonic()

    cfg = override(base_cfg, {"reaction.on_failsafe": "log_only"})
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics(), gripper=Grip(),  # type: ignore[arg-type]
                    arm=Arm())  # type: ignore[arg-type]
    t0 = time.monotonic()
    try:
        daemon.close()
        took = time.monotonic() - t0
    finally:
        release.set()
    assert closed["arm"] - t0 < 0.3 and took < 1.0
