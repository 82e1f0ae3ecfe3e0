"""End to end with real parts: simulated scene -> PTSCOM frames on a pty -> `Daemon` (pyserial reader,
ONNX ensemble) -> ur_rtde stop to the emulated UR controller (own process) and dynamixel-sdk tighten
to the emulated MX-28 (pty); metrics scraped over HTTP. The live alarms must equal `slipd replay`'s."""

from __future__ import annotations

import urllib.request

import numpy as np
import pytest
from conftest import ROOT, run_streamed

from slipd.config import load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.metrics import Metrics
from slipd.sim.datasets import dataset_scenes
from slipd.sim.harness import EmulatedDevices
from slipd.sim.scene import generate, parse_scene

TARE = 300


def _scenes(kind: str, ens: Ensemble, cfg, want_alarm: bool, tries: int = 12):
    """First simulated test scene of ``kind`` on which offline replay alarms inside the method's window
    (``want_alarm``) or stays silent; the live run must then reproduce replay exactly."""
    for scene, seed in dataset_scenes("offline", "test", 40, seed=7):
        if tries == 0:
            break
        rec = generate(parse_scene(scene) if isinstance(scene, dict) else scene, seed)
        if rec.meta["kind"] != kind:
            continue
        tries -= 1
        alarms = [d.index for d in replay(rec, ens, cfg) if d.rising_edge]
        if want_alarm and alarms:
            onset, gross = rec.meta["events"]["onset"], rec.meta["events"].get("gross_slip", 1e9)
            if onset - 0.3 <= alarms[0] / 1000 <= gross:
                return rec, alarms
        if not want_alarm and not alarms:
            return rec, alarms
    pytest.skip(f"no {kind} scene found with the wanted offline outcome")


@pytest.fixture(scope="module")
def base_cfg(detect_model_json):
    cfg = load_config(ROOT / "config" / "sim.yaml")
    return override(cfg, {"model.manifest": str(detect_model_json), "model.detector": "onnx", "sensor.tare": "startup",
                          "sensor.tare_samples": TARE, "recorder.enabled": False, "sensor.stall_timeout_ms": 1000})


def _run_live(rec, cfg):
    metrics = Metrics()
    server = metrics.serve("127.0.0.1", 0)
    with EmulatedDevices(rec, host="127.0.0.3") as dev:
        cfg = override(cfg, dev.overrides())
        ens = Ensemble.load(cfg.model.manifest)
        arm, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ens, metrics=metrics, arm=arm, gripper=gripper)
        try:
            # Then let the device threads finish the reaction.
            stats, writes = run_streamed(daemon, dev, len(rec) / 1000 + 0.5, settle_s=0.3)
            ur_state = dev.ur.state()
            body = urllib.request.urlopen(f"http://127.0.0.1:{server.server_address[1]}/metrics").read().decode()
        finally:
            daemon.close()
            server.shutdown()
    return stats, ur_state, writes, body


def test_slip_scene_stops_arm_and_tightens_gripper(base_cfg) -> None:
    ens = Ensemble.load(base_cfg.model.manifest)
    rec, offline_alarms = _scenes("slip", ens, base_cfg, want_alarm=True)
    stats, ur_state, writes, metrics_text = _run_live(rec, base_cfg)
    assert stats.frames == len(rec)  # nothing lost on the pty
    live = [a[0] for a in stats.alarms]
    assert live == offline_alarms  # replay gives exactly the live loop's alarms
    onset, gross = rec.meta["events"]["onset"], rec.meta["events"]["gross_slip"]
    assert onset - 0.3 <= live[0] / 1000 <= gross
    assert ur_state.stop_count >= 1  # ur_rtde's stop reached the emulated controller
    secure = base_cfg.gripper.secure_position
    goal_writes = [w for w in writes if w.address == 116]  # Goal Position (protocol 2.0)
    assert any(int.from_bytes(w.data[:4], "little") == secure for w in goal_writes)
    assert "slipd_alarms_total 1.0" in metrics_text or "slipd_alarms_total" in metrics_text
    assert f"slipd_frames_received_total {float(len(rec))}" in metrics_text


def test_stop_scene_raises_no_alarm(base_cfg) -> None:
    ens = Ensemble.load(base_cfg.model.manifest)
    rec, _ = _scenes("stop", ens, base_cfg, want_alarm=False)
    stats, ur_state, writes, _ = _run_live(rec, base_cfg)
    assert stats.frames == len(rec)
    assert not stats.alarms and stats.failsafes == 0
    assert ur_state.stop_count == 0
    assert not [w for w in writes if w.address == 116 and
                int.from_bytes(w.data[:4], "little") == base_cfg.gripper.secure_position]
    assert np.isfinite(ens.hidden_state(0)).all()


def test_the_loop_feeds_a_heuristic_detector_the_tip_displacements(base_cfg) -> None:
    """``model.detector: reference_pillar`` in the daemon decides on the frames' displacements as replay and the
    evaluation do (the loop once passed forces alone, and the heuristic fell back to force over stiffness)."""
    from slipd.models import SAMPLE_RECORDING
    from slipd.recording import Recording

    rec = Recording.load(SAMPLE_RECORDING)
    cfg = override(base_cfg, {"model.detector": "reference_pillar", "sensor.tare": "bias_command"})
    ens = Ensemble.load(cfg.model.manifest)
    daemon = Daemon(cfg, ens, metrics=Metrics())
    decided: list[tuple[int, float]] = []
    push_many = daemon.detector.push_many

    def watched(*args):  # every decision the loop gets from the detector
        out = push_many(*args)
        decided.extend((d.index, d.p_slip) for _, d in out)
        return out

    daemon.detector.push_many = watched  # type: ignore[method-assign]
    for k in range(0, len(rec), 10):
        daemon._on_block(rec.t_us[k : k + 10], rec.force[k : k + 10, None], rec.disp[k : k + 10, None])
    offline = replay(rec, ens, cfg)
    assert decided == [(d.index, d.p_slip) for d in offline]
    assert [a[0] for a in daemon.stats.alarms] == [d.index for d in offline if d.rising_edge]


def test_the_rule_confirmed_by_the_model_alarms_in_the_loop_as_in_replay_and_sooner_than_the_model_alone() -> None:
    """``decision.confirm_rule`` in the daemon: the loop hands the confirmed detector the tip displacements, its
    decisions and alarms are replay's, and on a slip where the model leans early the alarm comes sooner."""
    from slipd.detect.confirmed import ConfirmedDetector

    scene, seed = list(dataset_scenes("transfer", "test", 2, seed=7))[1]
    rec = generate(parse_scene(scene) if isinstance(scene, dict) else scene, seed)
    cfg = override(load_config(ROOT / "config" / "sim.yaml"), {"recorder.enabled": False})
    ens = Ensemble.load(cfg.model.manifest)
    alone = [d.index for d in replay(rec, ens, cfg) if d.rising_edge]
    cfg = override(cfg, {"decision.confirm_rule": 0.3})
    offline = replay(rec, ens, cfg)
    daemon = Daemon(cfg, ens, metrics=Metrics())
    assert isinstance(daemon.detector, ConfirmedDetector)
    decided: list[tuple[int, float, bool]] = []
    push_many = daemon.detector.push_many

    def watched(force, t_us, disp):  # every decision the loop gets from the detector
        assert disp is not None and np.array_equal(disp, rec.disp[t_us[0] // 1000 :][: len(disp)])
        out = push_many(force, t_us, disp)
        decided.extend((d.index, d.p_slip, d.alarm) for _, d in out)
        return out

    daemon.detector.push_many = watched  # type: ignore[method-assign]
    for k in range(0, len(rec), 10):
        daemon._on_block(rec.t_us[k : k + 10], rec.force[k : k + 10, None], rec.disp[k : k + 10, None])
    assert decided == [(d.index, d.p_slip, d.alarm) for d in offline]
    live = [a[0] for a in daemon.stats.alarms]
    assert live == [d.index for d in offline if d.rising_edge]
    onset = rec.meta["events"]["onset"]
    assert onset - 0.3 <= live[0] / 1000 and live[0] < alone[0]
