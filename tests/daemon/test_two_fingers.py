"""Two sensorised fingers end to end (issue 15): the emulated controller streams two arrays in every PTSCOM
frame on a pty; the daemon (pyserial reader, shipped int8 ensemble, one model call for both fingers,
dynamixel-sdk) decides per finger. Only finger 1 slips: the alarm fires, names sensor 1 and tightens the
gripper; the recorder's recording holds both arrays and `slipd replay` reproduces the alarm from it."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from conftest import ROOT

from slipd.config import load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.daemon.recorder import Recorder
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.metrics import Metrics
from slipd.models import SAMPLE_RECORDING, packaged
from slipd.recording import Recording
from slipd.sim.harness import EmulatedDevices

TARE = 300


def two_fingers() -> Recording:
    """Finger 1: the packaged slip sample (press, hold, then the surface moves: incipient slip at 1.038 s).
    Finger 0: the same press and hold, but it stays put (held values plus sensor noise) and never slips."""
    one = Recording.load(SAMPLE_RECORDING)
    rng = np.random.default_rng(5)
    f0, d0 = one.force.copy(), one.disp.copy()
    f0[800:], d0[800:] = f0[799], d0[799]
    f0[800:] += rng.normal(0, 0.01, f0[800:].shape).astype(np.float32)
    return Recording(one.t_us, np.stack([f0, one.force], 1), np.stack([d0, one.disp], 1), meta={"events": one.events})


@pytest.fixture(scope="module")
def cfg():
    cfg = load_config(ROOT / "config" / "sim.yaml")
    return override(cfg, {"model.manifest": str(packaged("slip_ensemble_int8")), "model.detector": "onnx",
                          "sensor.tare": "startup", "sensor.tare_samples": TARE, "sensor.stall_timeout_ms": 1000,
                          "arm.enabled": False, "reaction.actions": ["tighten_gripper"],
                          "reaction.on_failsafe": "log_only"})


def test_only_finger_1_slips_alarm_names_sensor_1_recorder_and_replay_reproduce_it(cfg, tmp_path) -> None:
    rec = two_fingers()
    ens = Ensemble.load(cfg.model.manifest)
    offline = [(d.index, d.sensor) for d in replay(rec, ens, override(cfg, {"sensor.sensors": 2})) if d.rising_edge]
    assert offline and {s for _, s in offline} == {1}

    metrics = Metrics()
    with EmulatedDevices(rec, ur=False) as dev:
        assert dev.sensor.sensors == 2
        live_cfg = override(cfg, dev.overrides())
        assert live_cfg.sensor.sensors == 2
        ens = Ensemble.load(live_cfg.model.manifest)
        _, gripper = build_devices(live_cfg, metrics)
        daemon = Daemon(live_cfg, ens, metrics=metrics, gripper=gripper)
        # The ring holds the whole stream, so the recording starts at the daemon's first frame.
        daemon.recorder = Recorder(tmp_path, 1000, seconds_before=3.0, seconds_after=0.2, sensors=2)

        async def main():
            task = asyncio.create_task(daemon.run(duration_s=len(rec) / 1000 + 0.5))
            await daemon.ready.wait()
            dev.start_sensor()
            return await task

        try:
            stats = asyncio.run(main())
            time.sleep(0.3)  # the gripper thread finishes the tighten
            writes = dev.servo.writes()
        finally:
            daemon.close()  # also waits for the recording to be written
    assert stats.frames == len(rec) and stats.failsafes == 0  # both arrays decoded, nothing lost, never blind
    assert [(a[0], a[3]) for a in stats.alarms] == offline  # the live loop decides as replay does: sensor 1
    secure = live_cfg.gripper.secure_position
    assert any(w.address == 116 and int.from_bytes(w.data[:4], "little") == secure for w in writes)
    value = metrics.registry.get_sample_value("slipd_alarms_total", {"sensor": "1"})
    assert value == len(offline) and not metrics.registry.get_sample_value("slipd_alarms_total", {"sensor": "0"})

    files = sorted(tmp_path.glob("slip-*.npz"))
    assert len(files) == 1
    dump = Recording.load(files[0])
    assert dump.sensors == 2 and dump.force.shape[1:] == (2, 9, 3)
    assert dump.meta["trigger"]["sensor"] == 1 and set(dump.meta["decisions"]["sensor"]) == {0, 1}
    np.testing.assert_array_equal(dump.force, rec.force[: len(dump)])  # both arrays, bit for bit
    again = [d for d in replay(dump, ens) if d.rising_edge]
    assert [(d.index, d.sensor) for d in again] == offline


def test_freshness_is_per_finger_on_every_path(cfg) -> None:
    """A block is fresh for a finger when any of its samples differs from the one before (the first block always
    is); a bit-identical finger is not, whether the other one moves or holds a non-finite sample."""
    daemon = Daemon(override(cfg, {"sensor.sensors": 2}), Ensemble.load(cfg.model.manifest), metrics=Metrics())
    rng = np.random.default_rng(0)
    block = rng.normal(0, 0.01, (10, 2, 9, 3)).astype(np.float32)
    disp = np.zeros_like(block)

    def fresh_after(force: np.ndarray) -> np.ndarray:
        daemon._fresh_ts[:] = 0.0
        daemon._check_samples(force, disp)
        return daemon._fresh_ts > 0.0

    assert fresh_after(block).tolist() == [True, True]  # the first block
    frozen = block.copy()
    frozen[:, 1] = block[-1, 1]  # finger 1 repeats its last sample, finger 0 moves
    assert fresh_after(frozen).tolist() == [True, False]
    assert fresh_after(np.repeat(frozen[-1:], 10, axis=0)).tolist() == [False, False]
    one = frozen[-1:].copy()
    one[0, 0, 4, 2] += 0.5  # one sample, finger 0 only
    assert fresh_after(one).tolist() == [True, False]
    bad = np.repeat(one, 10, axis=0)
    bad[3:, 0, 0, 0] = np.nan  # finger 0 non-finite from the fourth sample on, finger 1 still frozen
    bad[1, 1, 2, 2] += 0.1
    assert fresh_after(bad).tolist() == [False, True]
    assert daemon._nonfinite_run.tolist() == [7, 0]
