"""Faults at the daemon level, through the emulated devices and the real client libraries.

Each test runs the real ``Daemon`` (pyserial reader, ONNX ensemble, dynamixel-sdk, ur_rtde) in-process
against the emulated PapillArray (pty), MX-28 (pty) and UR controller (own process on 127.0.0.5),
injects one kind of fault, and checks what reaches the devices and the metrics. The model is the tiny
random fixture with the alarm threshold at 0.999, so every arm stop seen here comes from a fault path
(each test asserts that no alarm was raised unless it makes one on purpose).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import pytest
from conftest import ROOT

from slipd.config import load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.detect.ensemble import Ensemble
from slipd.io.pts import Frame
from slipd.metrics import Metrics
from slipd.recording import Recording
from slipd.sim.devices.ur_controller import URControllerProcess
from slipd.sim.harness import EmulatedDevices

HOST = "127.0.0.5"  # other tests use .2, .3, .4
TARE = 100
BURST = 10_000

pytestmark = pytest.mark.timeout(120)


def quiet_hold(seconds: float = 2.0, seed: int = 0) -> Recording:
    """A still grasp: every pillar pressed to about 1.5 N with sensor-like noise, no motion."""
    n = int(seconds * 1000)
    rng = np.random.default_rng(seed)
    force = np.zeros((n, 9, 3), np.float32)
    force[:, :, 2] = 1.5
    force += rng.normal(0.0, 0.01, force.shape).astype(np.float32)
    disp = np.zeros((n, 9, 3), np.float32)
    return Recording(t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=disp, meta={"kind": "quiet_hold"})


@pytest.fixture(scope="module")
def controller():
    """One emulated UR controller process for the whole file (starting one costs about a second)."""
    ur = URControllerProcess(HOST)
    ur.start()
    yield ur
    ur.stop()


@pytest.fixture(scope="module")
def base_cfg(tiny_model_json):
    cfg = load_config(ROOT / "config" / "sim.yaml")
    return override(cfg, {
        "model.manifest": str(tiny_model_json), "model.detector": "onnx", "decision.threshold": 0.999,
        "sensor.tare": "startup",
        "sensor.tare_samples": TARE, "recorder.enabled": False, "sensor.stall_timeout_ms": 150,
        "reaction.rearm_after_s": 0.0,
    })


def metric(m: Metrics, name: str, **labels: str) -> float:
    """Current value of a sample (0 when the labelled child does not exist yet)."""
    v = m.registry.get_sample_value(name, labels or None)
    return 0.0 if v is None else v


async def until(pred: Callable[[], bool], timeout: float = 5.0, what: str = "condition") -> None:
    """Poll ``pred`` on the loop (so the daemon keeps running) until it holds; fail naming ``what``."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for: {what}")
        await asyncio.sleep(0.01)


Scenario = Callable[[Daemon, EmulatedDevices, URControllerProcess], Awaitable[None]]


def run_live(controller: URControllerProcess, cfg, scenario: Scenario, *, stream: bool = True, source: Any = None,
             **overrides) -> tuple[Daemon, EmulatedDevices]:
    """Start fresh sensor and servo emulators, the devices and the daemon; run ``scenario``; shut down. ``source``:
    the sensor's samples (default: a quiet hold, looped)."""
    dev = EmulatedDevices(quiet_hold() if source is None else source, ur=False)
    dev.sensor.loop = True  # stream for as long as the scenario needs
    cfg = override(cfg, {**dev.overrides(), "arm.enabled": True, "arm.host": HOST, **overrides})
    metrics = Metrics()
    daemon = None
    try:
        ens = Ensemble.load(cfg.model.manifest)
        arm, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ens, metrics=metrics, arm=arm, gripper=gripper)

        async def main() -> None:
            task = asyncio.create_task(daemon.run())
            await daemon.ready.wait()
            if stream:
                dev.start_sensor()
            try:
                await scenario(daemon, dev, controller)
            finally:
                daemon.stop()
                await task

        asyncio.run(main())
    finally:
        if daemon is not None:
            daemon.close()
        dev.close()
    return daemon, dev


async def frames_after(daemon: Daemon, n: int, timeout: float = 5.0, what: str = "frames") -> None:
    """Wait until ``n`` more frames than now have reached the daemon."""
    target = daemon.stats.frames + n
    await until(lambda: daemon.stats.frames >= target, timeout, f"{n} more {what}")


# ---------------------------------------------------------------------------------------------- sensor
def test_sensor_stall_fails_safe_stops_the_arm_and_the_stream_resumes(controller, base_cfg) -> None:
    seen: dict[str, float] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 200)
        stops0 = ur.state().stop_count
        stall0 = metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_stall")
        dev.sensor.stall(250)  # 5x the 50 ms timeout
        await until(lambda: metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_stall") > stall0,
                    what="sensor_stall fail-safe counted")
        await until(lambda: ur.state().stop_count > stops0, what="fail-safe stop reached the UR controller")
        await frames_after(d, 300, what="frames after the stall")
        await until(lambda: d.live, what="live again after the stall")
        seen["stall"] = metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_stall") - stall0

    d, _ = run_live(controller, base_cfg, scenario, **{"sensor.stall_timeout_ms": 50})
    assert seen["stall"] >= 1
    assert not d.stats.alarms  # the stop came from the fail-safe, not a detection
    assert d.stats.failsafes >= 1


def test_a_power_cycled_sensor_is_zeroed_again_after_the_reconnect(controller, base_cfg) -> None:
    """``tare: bias_command``: the controller forgets its bias when power-cycled, so the daemon sends its rate and
    the bias again on the reconnect, and decides again only on frames after the bias."""
    seen: dict[str, Any] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await until(lambda: d.stats.decisions > 0, what="first decisions")
        seen["bias_before"] = [k for k, _ in dev.sensor.commands].count("bias")
        dev.sensor.unplug()
        await until(lambda: not d.live, what="blind after the loss")
        await asyncio.sleep(0.2)
        dev.sensor.replug()  # a power cycle: the emulated controller's bias is gone
        await until(lambda: metric(d.metrics, "slipd_reconnects_total", device="sensor") >= 1, what="reconnect")
        await until(lambda: [k for k, _ in dev.sensor.commands].count("bias") == 2, what="the bias again")
        t_bias = time.monotonic()
        decisions = d.stats.decisions
        await until(lambda: d.live, timeout=5.0, what="live again")
        seen["live_after_s"] = time.monotonic() - t_bias
        seen["decisions_after"] = d.stats.decisions - decisions
        seen["rates"] = [k for k, _ in dev.sensor.commands].count("rate")

    d, dev = run_live(controller, base_cfg, scenario, **{"sensor.tare": "bias_command", "sensor.bias_timeout_s": 0.5})
    assert seen["bias_before"] == 1 and seen["rates"] == 2
    assert seen["live_after_s"] >= 0.4  # nothing decided while the sensor zeroed itself
    assert seen["decisions_after"] > 0 and d.stats.failsafes == 1  # one episode, one fail-safe
    assert np.abs(dev.sensor._bias_force).max() > 1.0  # zeroed again (the quiet hold presses 1.5 N per pillar)


def test_a_sensor_zeroed_under_a_grasp_is_zeroed_again_in_software_once_the_jaw_lets_go(controller, base_cfg) -> None:
    """The bias after a power cycle mid-grasp takes the held load for the zero (the test above). Once the jaw lets go,
    the free air is the zero again, with no blind spell and no fail-safe; before, every later grasp read low by the
    old load until a restart."""
    load = {"fz": 1.5}
    rng = np.random.default_rng(5)

    def sample(i: int) -> tuple[np.ndarray, np.ndarray]:
        f = rng.normal(0.0, 0.01, (9, 3)).astype(np.float32)
        f[:, 2] += load["fz"]
        return f, np.zeros((9, 3), np.float32)

    seen: dict[str, Any] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await until(lambda: d.stats.decisions > 0, what="first decisions")
        dev.sensor.unplug()
        await until(lambda: not d.live, what="blind after the loss")
        await asyncio.sleep(0.2)
        dev.sensor.replug()  # a power cycle mid-grasp: the bias takes the held 1.5 N per pillar
        await until(lambda: [k for k, _ in dev.sensor.commands].count("bias") == 2, what="the bias again")
        await until(lambda: d.live, timeout=5.0, what="live again")
        seen["offset_held"] = float(np.abs(d.detector.offset[:, 2]).max())
        seen["bias_held"] = dev.sensor._bias_force[0, :, 2].copy()
        failsafes = d.stats.failsafes
        load["fz"] = 0.0  # the jaw lets go
        await until(lambda: d.detector.offset[:, 2].max() < -1.4, timeout=5.0, what="zeroed again in free air")
        load["fz"] = 2.0  # the next grasp
        await until(lambda: (c := d.detector.contact.latest) is not None and c.grip_n > 15.0, timeout=3.0,
                    what="the next grasp read at its force")
        await asyncio.sleep(0.2)
        seen["grip"] = d.detector.contact.latest.grip_n
        seen["failsafes"] = d.stats.failsafes - failsafes
        seen["live"] = d.live
        # Released, then a power cycle in free air: the sensor's own bias is the zero again, the software one goes.
        load["fz"] = 0.0
        await asyncio.sleep(0.3)
        dev.sensor.unplug()
        await until(lambda: not d.live, what="blind after the second loss")
        dev.sensor.replug()
        await until(lambda: [k for k, _ in dev.sensor.commands].count("bias") == 3, what="the third bias")
        await until(lambda: d.live, timeout=5.0, what="live after the third bias")
        await asyncio.sleep(0.2)
        seen["offset_after"] = float(np.abs(d.detector.offset).max())
        seen["free_air"] = d.detector.contact.latest.grip_n

    d, _ = run_live(controller, base_cfg, scenario, source=sample,
                      **{"sensor.tare": "bias_command", "sensor.bias_timeout_s": 0.5})
    assert np.abs(seen["bias_held"] - 1.5).max() < 0.1  # the bias took the grasp's load
    assert seen["offset_held"] == 0.0  # no software zero while the grasp went on
    assert abs(seen["grip"] - 18.0) < 0.5  # 9 pillars x 2 N, not 9 x 0.5 N
    assert seen["failsafes"] == 0 and seen["live"]
    assert seen["offset_after"] == 0.0 and seen["free_air"] == 0.0  # not 9 x 1.5 N of phantom grasp
    assert metric(d.metrics, "slipd_sensor_rezeros_total") == 1


def test_sensor_unplug_fails_safe_then_reconnects_and_restarts_the_detector(controller, base_cfg) -> None:
    seen: dict[str, float] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 200)
        await until(lambda: d.stats.decisions > 0, what="first decisions")
        stops0, resets0 = ur.state().stop_count, d.detector.resets
        dev.sensor.unplug()
        await until(lambda: metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_lost") >= 1,
                    what="sensor_lost fail-safe")
        await until(lambda: ur.state().stop_count > stops0, what="fail-safe stop reached the UR controller")
        await asyncio.sleep(0.3)  # cable out for a while: the reader keeps retrying
        assert not d.sensor.connected
        dev.sensor.replug()
        await until(lambda: metric(d.metrics, "slipd_reconnects_total", device="sensor") >= 1, what="reconnect")
        decisions = d.stats.decisions
        await frames_after(d, TARE + 300, what="frames after the replug")
        seen["decisions_after"] = d.stats.decisions - decisions
        seen["resets"] = d.detector.resets - resets0

    d, _ = run_live(controller, base_cfg, scenario)
    assert seen["resets"] >= 2  # on the disconnect and on the first frame after the reconnect
    assert seen["decisions_after"] > 0  # the restarted detector decides again
    # One fault, one stop: the stall that follows the loss belongs to the same episode.
    assert metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_lost") == 1
    assert metric(d.metrics, "slipd_failsafe_stops_total", reason="sensor_stall") == 0
    assert d.stats.failsafes == 1 and d.live
    assert not d.stats.alarms


def test_corrupt_frames_are_counted_and_later_frames_processed(controller, base_cfg) -> None:
    seen: dict[str, float] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 100)
        s = dev.sensor
        s.inject_garbage(64)
        await frames_after(d, 20)
        s.inject_truncated_frame()
        await frames_after(d, 20)
        s.inject_bad_checksum()
        await frames_after(d, 20)
        s.inject_wrong_length()
        await frames_after(d, 20)
        s.jump_counter(5)  # 5 frames look lost
        await frames_after(d, 20)
        s.jump_counter(-1000)  # counter goes back: a discontinuity, the detector restarts
        await frames_after(d, TARE + 200, what="frames after the faults")
        s.stop()  # end the stream so every frame written can be accounted for
        written = s.frames_written
        await until(lambda: d.sensor.decoder.frames + 3 >= written, what="reader drained the pty")
        await asyncio.sleep(0.1)
        seen["written"] = written

    d, _ = run_live(controller, base_cfg, scenario)
    m = d.metrics
    errors = {k: metric(m, "slipd_frame_errors_total", kind=k)
              for k in ("bad_checksum", "bad_length", "bad_structure", "discontinuity")}
    assert errors["bad_checksum"] >= 1
    assert errors["bad_length"] + errors["bad_structure"] >= 2  # the truncated and the wrong-length frame
    assert errors["discontinuity"] == 1
    assert metric(m, "slipd_garbage_bytes_total") >= 64
    # 5 from the jump, 3 for the destroyed frames (their counters were consumed).
    assert metric(m, "slipd_dropped_frames_total") == 8
    # Every intact frame written reached the daemon: only the three corrupted ones are missing.
    assert d.stats.frames == seen["written"] - 3
    assert d.stats.restarts >= 1 and d.stats.decisions > 0
    assert not d.stats.alarms


def test_burst_of_frames_is_processed_without_loss(controller, base_cfg) -> None:
    rec = quiet_hold(BURST / 1000, seed=1)
    frames = [Frame(counter=i, t_us=int(rec.t_us[i]), force=rec.force[i], disp=rec.disp[i]) for i in range(BURST)]
    seen: dict[str, float] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        t0 = time.perf_counter()
        writer = asyncio.create_task(asyncio.to_thread(dev.sensor.write_frames, frames, 60.0))
        await until(lambda: d.stats.frames >= BURST, timeout=60.0, what=f"all {BURST} burst frames")
        seen["catch_up_s"] = time.perf_counter() - t0
        assert await writer == BURST

    d, _ = run_live(controller, base_cfg, scenario, stream=False, **{"sensor.stall_timeout_ms": 1000})
    print(f"\nburst of {BURST} frames (10 s of data) processed in {seen['catch_up_s']:.2f} s "
          f"({BURST / seen['catch_up_s']:.0f} frames/s incl. {d.stats.decisions} model steps)")
    assert d.stats.frames == BURST
    assert metric(d.metrics, "slipd_dropped_frames_total") == 0
    assert metric(d.metrics, "slipd_frames_received_total") == BURST
    assert d.stats.decisions > 0 and d.stats.step_errors == 0


# --------------------------------------------------------------------------------------------- gripper
def test_servo_silent_while_tightening_falls_back_to_stopping_the_arm(controller, base_cfg) -> None:
    seen: dict[str, object] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 100)
        stops0 = ur.state().stop_count
        dev.servo.mute_for(3.0)
        # The path from a rising alarm edge on (what _on_frames calls): stop the arm, tighten the gripper.
        futures = d.reaction.on_alarm(1.0)
        await until(lambda: all(f.done() for f in futures), timeout=5.0, what="reaction calls finished")
        rec = d.reaction.records[0]
        seen["errors"] = dict(rec.errors)
        await until(lambda: metric(d.metrics, "slipd_failsafe_stops_total", reason="tighten_gripper failed") >= 1,
                    what="fail-safe after the failed tighten")
        # The alarm's own stop plus the fail-safe stop both reach the controller.
        await until(lambda: ur.state().stop_count >= stops0 + 2, what="fail-safe stop reached the UR controller")
        await frames_after(d, 100, what="frames after the gripper fault")

    d, _ = run_live(controller, base_cfg, scenario)
    assert "tighten_gripper" in seen["errors"]  # GripperError from dynamixel-sdk's timeout
    assert "stop_arm" not in seen["errors"]
    assert metric(d.metrics, "slipd_device_errors_total", device="gripper", kind="reaction") >= 1


def test_tighten_lost_while_the_servo_was_silent_is_retried_when_it_answers(controller, base_cfg) -> None:
    seen: dict[str, object] = {}

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 100)
        await until(lambda: d.health.get("gripper") == "ok", what="first gripper poll")
        dev.servo.mute_for(1.0)
        t_back = time.monotonic() + 1.0
        futures = d.reaction.on_alarm(1.0)
        await until(lambda: all(f.done() for f in futures), what="reaction calls finished")
        await until(lambda: d.reaction.tighten_owed is None and d.reaction._owed, what="the failed tighten owed")
        await until(lambda: d.health.get("gripper", "ok") != "ok", timeout=3.0, what="silence seen by the poll")
        await until(lambda: d.health.get("gripper") == "ok", timeout=5.0, what="the servo answers again")
        await until(lambda: not d.reaction._owed, what="the owed tighten sent again")
        await until(lambda: any(w.t >= t_back and w.values.get("goal_position") == 2600 for w in dev.servo.writes()),
                    what="the secure goal position written after the servo came back")
        seen["owed"] = d.reaction._owed

    d, _ = run_live(controller, base_cfg, scenario)
    assert seen["owed"] is False
    assert metric(d.metrics, "slipd_failsafe_stops_total", reason="tighten_gripper failed") == 1


def test_servo_hardware_error_seen_by_the_health_poll_fails_safe(controller, base_cfg) -> None:
    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await frames_after(d, TARE + 100)
        await until(lambda: d.health.get("gripper") == "ok", what="first gripper poll")
        stops0 = ur.state().stop_count
        dev.servo.inject_overload()
        await until(lambda: "overload" in d.health.get("gripper", ""), what="overload seen by the health poll")
        await until(lambda: ur.state().stop_count > stops0, what="fail-safe stop reached the UR controller")
        await asyncio.sleep(1.2)  # more polls of the same fault: no further fail-safe
        await frames_after(d, 100)

    d, _ = run_live(controller, base_cfg, scenario)
    assert metric(d.metrics, "slipd_failsafe_stops_total", reason="gripper_fault") == 1
    assert metric(d.metrics, "slipd_device_errors_total", device="gripper", kind="unhealthy") == 1
    assert not d.stats.alarms


# ------------------------------------------------------------------------------------------------- arm
def test_arm_protective_stop_and_link_loss_are_noticed_and_the_link_comes_back(controller, base_cfg,
                                                                              caplog) -> None:
    caplog.set_level(logging.WARNING, logger="slipd.daemon.loop")

    async def scenario(d: Daemon, dev: EmulatedDevices, ur: URControllerProcess) -> None:
        await until(lambda: d.health.get("arm") == "ok", what="first arm poll")
        try:
            ur.inject_protective_stop()
            await until(lambda: d.health.get("arm") == "protective_stop", what="protective stop noticed")
        finally:
            ur.clear_protective_stop(resume=True)
        await until(lambda: d.health.get("arm") == "ok", what="protective stop cleared")
        ur.drop_connections(down_s=0.5)
        await until(lambda: d.health.get("arm") == "disconnected", what="link loss noticed")
        await until(lambda: metric(d.metrics, "slipd_reconnects_total", device="arm") >= 1, timeout=8.0,
                    what="arm reconnected")
        await until(lambda: d.health.get("arm") == "ok", what="arm healthy after the reconnect")
        await frames_after(d, 100, what="frames during and after the arm faults")

    d, _ = run_live(controller, base_cfg, scenario)
    m = d.metrics
    assert metric(m, "slipd_device_errors_total", device="arm", kind="protective_stop") == 1
    assert metric(m, "slipd_device_errors_total", device="arm", kind="disconnected") >= 1
    text = caplog.text
    assert "protective stop" in text and "RTDE link lost" in text and "arm: reconnected" in text


# ------------------------------------------------------------------------------------------------ soak
@pytest.mark.slow
def test_soak_30_s_at_1_khz_loses_no_frame(controller, tiny_model_json) -> None:
    from sliplab.soak_live import soak

    # The emulated sensor and servo run in a process of their own; the stalls are sent there.
    rep = soak(30.0, tiny_model_json, controller=controller, threshold=0.999, failsafe_every=12.0, warmup_s=5.0)
    print("\n" + "\n".join(rep.lines()))
    assert rep.frames_sent >= 25_000  # the emulator really streamed for the whole run
    assert rep.frames_lost == 0 and rep.emulator_discarded == 0
    assert rep.frames_processed == rep.frames_sent
    assert rep.decode_errors == 0 and rep.step_errors == 0 and rep.dropped == 0
    assert rep.decisions > 0 and rep.health_polls > 0
    assert rep.failsafes >= 2  # a stall at 12 s and at 24 s, each a fail-safe
    assert rep.emulator_cpu_share > 0.0 and rep.process_cpu_share > 0.0  # two processes, each measured
    assert rep.samples >= 2 and rep.rss_first_kb > 0 and rep.threads[0] > 0


def test_reliability_report_cites_only_existing_tests() -> None:
    from sliplab.reliability import FAULTS, missing_tests, table

    assert missing_tests() == []
    assert len(table()) == len(FAULTS) + 2
    # Every daemon-level test of this file appears in the report's table.
    cited = {t.split("::")[1] for f in FAULTS for t in f.tests if t.startswith("tests/daemon/test_faults.py")}
    this = "test_reliability_report_cites_only_existing_tests"
    here = {name for name in globals() if name.startswith("test_") and name != this}
    assert here <= cited, here - cited
