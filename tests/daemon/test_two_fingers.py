"""Two sensorised fingers end to end: the emulated controller streams two arrays in every PTSCOM
frame on a pty; the daemon (pyserial reader, shipped int8 ensemble, one model call for both fingers,
dynamixel-sdk) decides per finger. Only finger 1 slips: the alarm fires, names sensor 1 and tightens the
gripper; the recorder's recording holds both arrays and `slipd replay` reproduces the alarm from it."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import ROOT, run_streamed

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
        try:
            # Then the gripper thread finishes the tighten.
            stats, writes = run_streamed(daemon, dev, len(rec) / 1000 + 0.5, settle_s=0.3)
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
    offline_again = replay(dump, ens)
    again = [d for d in offline_again if d.rising_edge]
    assert [(d.index, d.sensor) for d in again] == offline
    # Each decision's contact state is in the recording too, as replay computes it from the same frames.
    by_key = {(d.t_us, d.sensor): d.contact for d in offline_again}
    dec = dump.meta["decisions"]
    compared = 0
    for t, s, pillars, risk in zip(dec["t_us"], dec["sensor"], dec["pillar_slip"], dec["contact_risk"]):
        c = by_key.get((t, s))
        if c is not None and pillars is not None:
            assert pillars == pytest.approx(list(c.pillar_slip), abs=1e-3) and risk == pytest.approx(c.risk, abs=1e-3)
            compared += 1
    assert compared > 0.9 * len(dec["t_us"])
    # Every decision replay makes on the recording's frames is in it (replay, given the daemon's tare, also decides
    # inside the start-up tare, where the daemon reports only the last window).
    assert sorted(zip(dec["t_us"], dec["sensor"])) == sorted(k for k in by_key if k[0] >= dec["t_us"][0])


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


class _Jaw:
    """The gripper boundary of a unit test: records the grip commands."""

    def __init__(self) -> None:
        self.targets: list[float] = []

    def grip_force(self, newtons: float) -> None:
        self.targets.append(newtons)

    def close(self) -> None:
        pass


def test_grip_control_takes_one_grasp_state_per_decision_from_both_fingers(cfg) -> None:
    """Both fingers feel the jaw, each through its own sensor's calibration: finger 1 reads 10 % more normal force.
    The controller gets the grasp once per decision (not each finger's state in turn, which made the pressed force
    jump by 10 % between calls, so the grasp never counted as steady and grip control never took over)."""
    two = override(cfg, {"sensor.sensors": 2, "reaction.policy": "grip_control", "reaction.grip_max_force_n": 40.0})
    jaw = _Jaw()
    daemon = Daemon(two, Ensemble.load(two.model.manifest), metrics=Metrics(), gripper=jaw)  # type: ignore[arg-type]
    controller = daemon.reaction.grip_control
    assert controller is not None
    updates = []
    update = controller.update
    controller.update = lambda state, now, alarm=False, sampled=None: (
        updates.append(state), update(state, now, alarm=alarm, sampled=sampled))
    rng = np.random.default_rng(1)
    n = TARE + 1500
    force = rng.normal(0, 0.01, (n, 2, 9, 3)).astype(np.float32)
    force[TARE:, 0, :, 2] += 1.5  # a still grasp: 13.5 N on finger 0,
    force[TARE:, 1, :, 2] += 1.65  # 14.85 N on finger 1
    t_us = np.arange(n, dtype=np.int64) * 1000
    try:
        for k in range(0, n, 10):  # ten frames at a time, as the reader hands them over
            daemon._on_block(t_us[k : k + 10], force[k : k + 10], np.zeros_like(force[k : k + 10]))
            time.sleep(0.002)  # the controller's clock: its take-over waits for 0.1 s of a steady grasp
    finally:
        daemon.close()
    assert daemon.stats.decisions > 100 and len(updates) == daemon.stats.decisions // 2
    assert all(s is not None and s.pressed_n is not None and 14.0 < s.pressed_n < 14.4 for s in updates[-10:])
    assert controller.target is not None and 14.0 < controller.target < 14.4  # took over at the jaw's force
    assert jaw.targets and 14.0 < jaw.targets[0] < 14.4


def test_grip_control_on_two_fingers_end_to_end_catches_the_slip_of_finger_1(cfg) -> None:
    """The live chain with grip control: two arrays in every PTSCOM frame on a pty, the pyserial reader, one model
    call for both fingers, the grasp's state to the controller, dynamixel-sdk to the emulated MX-28. The controller
    takes the still grasp over at its force, and finger 1's slip (finger 0 stays put) raises the grip at the servo."""
    rec = two_fingers()
    with EmulatedDevices(rec, ur=False) as dev:
        live = override(cfg, {**dev.overrides(), "reaction.policy": "grip_control",
                              "reaction.grip_max_force_n": 150.0, "gripper.max_force_n": 150.0,
                              "recorder.enabled": False})  # the sample presses with 41 N
        metrics = Metrics()
        _, gripper = build_devices(live, metrics)
        daemon = Daemon(live, Ensemble.load(live.model.manifest), metrics=metrics, gripper=gripper)
        controller = daemon.reaction.grip_control
        assert controller is not None
        targets: list[tuple[float, float | None]] = []  # (time, target) after every update
        update = controller.update

        def watched(state, now, alarm=False, sampled=None):
            update(state, now, alarm=alarm, sampled=sampled)
            targets.append((now, controller.target))

        controller.update = watched  # type: ignore[method-assign]
        try:
            # Then the gripper thread sends the last command.
            stats, writes = run_streamed(daemon, dev, len(rec) / 1000 + 0.3, settle_s=0.2)
        finally:
            daemon.close()
    assert stats.failsafes == 0 and [a[3] for a in stats.alarms] == [1]  # finger 1's slip alone
    # One update per decision of the two fingers, not one per finger.
    assert len(targets) == pytest.approx(stats.decisions / 2, abs=2)
    taken = [t for _, t in targets if t is not None]
    assert taken, "grip control never took the grasp over"
    assert max(taken) > 1.5 * taken[0]  # the catch of finger 1's slip
    # The controller's commands reach the servo as goal PWM (the last ones written), the catch above the take-over.
    efforts = [int.from_bytes(w.data[:2], "little") for w in writes if w.address == 100][-controller.commands:]
    assert controller.commands >= 2 and max(efforts) > 1.5 * efforts[0]
