"""The live view: a Foxglove client gets the recording's channels live (every message valid against its schema), and a
client that never reads costs the daemon's loop no frame and no decision."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
from conftest import ROOT, run_streamed

from slipd.config import VizConfig, load_config, override
from slipd.daemon.devices import build_devices
from slipd.daemon.loop import Daemon
from slipd.daemon.service import start_taps
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.metrics import Metrics
from slipd.models import SAMPLE_RECORDING, packaged
from slipd.recording import Recording
from slipd.recording_mcap import SCHEMAS, schema_of
from slipd.sim.devices.foxglove_client import FoxgloveClient
from slipd.sim.harness import EmulatedDevices

pytest.importorskip("foxglove")
jsonschema = pytest.importorskip("jsonschema")
from slipd.daemon.viz import LiveView  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_client_gets_frames_and_decisions_valid_against_their_schemas(detect_model_json) -> None:
    rec = Recording.load(SAMPLE_RECORDING)
    dets = [d for d in replay(rec, Ensemble.load(detect_model_json)) if d.valid]
    view = LiveView(VizConfig(enabled=True, port=_free_port(), frame_rate_hz=100), threshold=0.5).start()
    client = FoxgloveClient("127.0.0.1", view.port)
    got: list = []
    try:
        client.wait_for_channels({"/slipd/frames/s0", "/slipd/decisions", "/slipd/events"})
        client.subscribe_all()
        time.sleep(0.3)  # the subscription reaches the server
        frames = (dets[-1].index + 1 + 9) // 10
        scenes = (dets[-1].index + 1 + 99) // 100  # the pillar arrows: 10 a second
        want = len(dets) + frames + scenes + sum(d.rising_edge for d in dets)
        reader = threading.Thread(target=lambda: got.extend(client.messages(want, timeout=20)))
        reader.start()  # a client that reads as the messages come (the server keeps a bounded backlog per client)
        pushed = 0
        for d in dets:
            view.on_decision(d, rec.force[d.index])
            view.on_block(rec.t_us[pushed : d.index + 1], rec.force[pushed : d.index + 1, None],
                          rec.disp[pushed : d.index + 1, None])
            pushed = d.index + 1
            time.sleep(0.001)
        reader.join(30)
    finally:
        client.close()
        view.close()
    assert view.dropped == 0 and view.errors == 0
    by: dict[str, list[dict]] = {}
    for topic, _, payload in got:
        msg = json.loads(payload)
        jsonschema.validate(msg, SCHEMAS[schema_of(topic)])
        by.setdefault(topic, []).append(msg)
    assert [m["p_slip"] for m in by["/slipd/decisions"]] == [d.p_slip for d in dets]
    assert all(m["threshold"] == 0.5 for m in by["/slipd/decisions"])
    frames = by["/slipd/frames/s0"]
    assert len(frames) == pushed // 10 and [f["sample"] for f in frames] == list(range(0, pushed, 10))  # 100 Hz
    i = frames[7]["sample"]
    assert np.array_equal(np.float32(frames[7]["force"]), rec.force[i].ravel())
    assert len(by["/slipd/events"]) == sum(d.rising_edge for d in dets) > 0
    assert len(by["/slipd/pillars/s0"]) == scenes


def test_a_client_that_never_reads_costs_the_loop_nothing(tmp_path) -> None:
    """The daemon end to end (pyserial reader, the int8 ensemble) with the live view on and a viewer subscribed to
    every channel that never reads: every frame is decided on, and the alarms are replay's."""
    port = _free_port()
    cfg = load_config(ROOT / "config" / "sim.yaml")
    cfg = override(cfg, {"model.manifest": str(packaged("slip_ensemble_int8")), "model.detector": "onnx",
                         "sensor.tare": "startup", "sensor.tare_samples": 300, "sensor.stall_timeout_ms": 1000,
                         "arm.enabled": False, "reaction.actions": ["tighten_gripper"],
                         "reaction.on_failsafe": "log_only", "viz.enabled": True, "viz.port": port,
                         "viz.frame_rate_hz": 1000})
    rec = Recording.load(SAMPLE_RECORDING)
    ens = Ensemble.load(cfg.model.manifest)
    metrics = Metrics()
    with EmulatedDevices(rec, ur=False) as dev:
        live_cfg = override(cfg, dev.overrides())
        offline = [d.index for d in replay(rec, ens, live_cfg) if d.rising_edge]
        _, gripper = build_devices(live_cfg, metrics)
        daemon = Daemon(live_cfg, Ensemble.load(live_cfg.model.manifest), metrics=metrics, gripper=gripper)
        start_taps(live_cfg, daemon, "test.yaml")
        view = daemon.taps[0]
        stuck = FoxgloveClient("127.0.0.1", port, recv_buffer=4096)
        stuck.wait_for_channels({"/slipd/frames/s0", "/slipd/decisions"})
        stuck.subscribe_all()
        try:
            stats, _ = run_streamed(daemon, dev, len(rec) / 1000 + 0.5, settle_s=0.3)
        finally:
            daemon.close()
            stuck.close()
    assert stats.frames == len(rec) and stats.failsafes == 0  # nothing lost, never blind
    assert [a[0] for a in stats.alarms] == offline
    assert view.sent >= len(rec)  # every frame went to the server (which dropped what the viewer did not read)


def test_a_full_queue_drops_its_oldest_and_counts_them_in_the_metric() -> None:
    m = Metrics()
    view = LiveView(VizConfig(enabled=True, frame_rate_hz=1000, queue=8), metrics=m)  # never started: nothing drains
    force = np.zeros((20, 1, 9, 3), np.float32)
    force[:, 0, 0, 2] = np.arange(20)
    view.on_block(np.arange(20) * 1000, force, np.zeros_like(force))
    assert len(view.queue) == 8 and view.dropped == 12
    assert [q[4][0, 0, 2] for q in view.queue] == list(range(12, 20))  # the newest eight kept
    assert m.registry.get_sample_value("slipd_tap_dropped_total", {"tap": "viz"}) == 12
    assert m.registry.get_sample_value("slipd_tap_dropped_total", {"tap": "ros2"}) == 0
