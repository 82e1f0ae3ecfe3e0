"""The daemon end to end with its MCAP recorder and the ROS 2 publisher: the emulated PapillArray streams the packaged
slip sample on a pty, the loop (pyserial reader, shipped int8 ensemble, dynamixel-sdk) decides; a zenoh subscriber
gets the alarm the loop raised and one p_slip per decision, and the recording in .mcap replays to the decisions of
its .npz twin."""

from __future__ import annotations

import json
import socket
import threading

import numpy as np
import pytest
from conftest import ROOT, run_streamed
from mcap.reader import make_reader

from slipd.config import load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.daemon.recorder import Recorder
from slipd.daemon.recording_context import attach
from slipd.daemon.service import start_taps
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.metrics import Metrics
from slipd.models import SAMPLE_RECORDING, packaged
from slipd.recording import Recording, list_recordings
from slipd.sim.harness import EmulatedDevices

zenoh = pytest.importorskip("zenoh")
ros2 = pytest.importorskip("slipd.daemon.ros2")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_live_daemon_publishes_its_alarm_and_records_mcap_like_npz(tmp_path) -> None:
    port = _free_port()
    cfg = load_config(ROOT / "config" / "sim.yaml")
    cfg = override(cfg, {"model.manifest": str(packaged("slip_ensemble_int8")), "model.detector": "onnx",
                         "sensor.tare": "startup", "sensor.tare_samples": 300, "sensor.stall_timeout_ms": 1000,
                         "arm.enabled": False, "reaction.actions": ["tighten_gripper"],
                         "reaction.on_failsafe": "log_only", "ros2.enabled": True,
                         "ros2.connect": [f"tcp/127.0.0.1:{port}"]})
    rec = Recording.load(SAMPLE_RECORDING)
    sub_session = zenoh.open(ros2.session_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    msgs = ros2.Messages()
    alarms: list[bool] = []
    p_count = [0]
    lock = threading.Lock()

    def on_sample(sample) -> None:
        key = str(sample.key_expr)
        with lock:
            if "/slip/alarm/" in key:
                alarms.append(bool(msgs.decode(sample.payload.to_bytes(), ros2.TYPES["alarm"]).data))
            elif "/slip/p_slip/" in key:
                p_count[0] += 1

    sub = sub_session.declare_subscriber("0/**", on_sample)
    metrics = Metrics()
    try:
        with EmulatedDevices(rec, ur=False) as dev:
            live_cfg = override(cfg, dev.overrides())
            _, gripper = build_devices(live_cfg, metrics)
            daemon = Daemon(live_cfg, Ensemble.load(live_cfg.model.manifest), metrics=metrics, gripper=gripper)
            daemon.recorder = Recorder(tmp_path, 1000, seconds_before=2.0, seconds_after=0.3,
                                       formats=["mcap", "npz"], meta={"threshold": 0.5})
            attach(daemon.recorder, daemon)  # as the service does: the recordings carry the reactions
            start_taps(live_cfg, daemon, "test.yaml")
            assert len(daemon.taps) == 1
            pub = daemon.taps[0]
            try:
                stats, _ = run_streamed(daemon, dev, len(rec) / 1000 + 0.5, settle_s=0.3)
            finally:
                daemon.close()  # closes the taps (the queue is published first) and writes the recording
    finally:
        sub.undeclare()
        sub_session.close()
    assert stats.alarms and stats.failsafes == 0
    assert pub.dropped == 0 and pub.errors == 0
    assert any(alarms) and p_count[0] == stats.decisions  # every decision reached the subscriber
    files = {p.suffix: p for p in list_recordings(tmp_path)}
    assert set(files) == {".mcap", ".npz"}
    twins = {k: Recording.load(v) for k, v in files.items()}
    assert np.array_equal(twins[".mcap"].force, twins[".npz"].force) and twins[".mcap"].meta == twins[".npz"].meta
    ens = Ensemble.load(live_cfg.model.manifest)
    runs = {k: [(d.index, d.p_slip, d.alarm) for d in replay(r, ens, live_cfg)] for k, r in twins.items()}
    assert runs[".mcap"] == runs[".npz"] and any(a for *_, a in runs[".mcap"])
    # The tighten the alarm sent, and the servo's answer, on the recording's clock after the alarm's sample.
    with open(files[".mcap"], "rb") as fh:
        reactions = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=["/slipd/reactions"])]
    alarm_t = stats.alarms[0][1]
    states = [(r["action"], r["state"]) for r in reactions]
    assert ("tighten_gripper", "sent") in states and ("tighten_gripper", "acked") in states, reactions
    assert all(alarm_t <= r["t_us"] < alarm_t + 200_000 for r in reactions), (alarm_t, reactions)
