"""ROS 2 over Zenoh without ROS: the key expressions and tokens are rmw_zenoh's, and a zenoh subscriber decodes every
message type back into the values the loop decided; a full queue drops its oldest and counts."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from conftest import ROOT  # noqa: E402

from slipd.config import Ros2Config  # noqa: E402
from slipd.daemon.ros2 import (  # noqa: E402
    TYPES,
    Health,
    Messages,
    Ros2Publisher,
    finger_wrench,
    publisher_token,
    session_config,
    topic_key,
)
from slipd.detect.ensemble import Ensemble  # noqa: E402
from slipd.detect.replay import replay  # noqa: E402
from slipd.metrics import Metrics  # noqa: E402
from slipd.recording import Recording  # noqa: E402
from slipd.recording import global_wrench as sdk_wrench  # noqa: E402

SAMPLE = ROOT / "slipd" / "models" / "sample_slip.npz"


def test_key_expressions_and_tokens_follow_rmw_zenoh() -> None:
    """The examples of rmw_zenoh's docs/design.md (the demo talker on `chatter`, domain 2)."""
    h = Messages().type_hash("std_msgs/msg/String")
    assert h == "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    assert topic_key(0, "/chatter", "std_msgs/msg/String", h) == f"0/chatter/std_msgs::msg::dds_::String_/{h}"
    assert topic_key(0, "/robot1/chatter", "std_msgs/msg/String", h).startswith("0/robot1/chatter/std_msgs::")
    assert publisher_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "", "talker", "/chatter",
                           "std_msgs/msg/String", h, qos="::,7:,:,:,,") == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{h}/::,7:,:,:,,")


def test_the_wrench_is_the_sdk_global_wrench_in_si_units() -> None:
    force = np.random.default_rng(0).normal(0, 1, (9, 3)).astype(np.float32)
    f, t = finger_wrench(force)
    sdk = sdk_wrench(force[None])[0]  # N and N mm
    assert np.allclose(f, sdk[:3]) and np.allclose(t, sdk[3:] / 1e3)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def decided(detect_model_json):
    rec = Recording.load(SAMPLE)
    dets = [d for d in replay(rec, Ensemble.load(detect_model_json)) if d.valid]
    assert any(d.rising_edge for d in dets)
    return rec, dets


def test_a_zenoh_subscriber_decodes_every_message_and_gets_the_alarm(decided) -> None:
    rec, dets = decided
    port = _free_port()
    sub_session = zenoh.open(session_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    got: dict[str, list[tuple[float, bytes, bytes]]] = {}
    tokens: list[str] = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        t = time.perf_counter()
        with lock:
            got.setdefault(str(sample.key_expr), []).append((t, sample.payload.to_bytes(),
                                                             sample.attachment.to_bytes()))

    subs = [sub_session.declare_subscriber("0/**", on_sample),
            sub_session.liveliness().declare_subscriber("@ros2_lv/0/**", lambda s: tokens.append(str(s.key_expr)))]
    cfg = Ros2Config(enabled=True, connect=[f"tcp/127.0.0.1:{port}"], namespace="/lab", diagnostics_period_s=0.2)
    pub = Ros2Publisher(cfg, sensors=1, health=lambda: Health(0, "live", {"decisions": "n"})).start()
    try:
        deadline = time.monotonic() + 10
        while len(tokens) < 6 and time.monotonic() < deadline:  # the node and its five publishers
            time.sleep(0.02)
        assert sorted(tokens) == sorted(pub.tokens)
        sent_at = None
        for d in dets:
            if d.rising_edge and sent_at is None:
                sent_at = time.perf_counter()
            pub.on_decision(d, rec.force[d.index])
            pub.on_block(rec.t_us[d.index : d.index + 1], rec.force[d.index : d.index + 1, None],
                         rec.disp[d.index : d.index + 1, None])  # the loop's block ends: the thread wakes
            time.sleep(0.0005)  # about the loop's pace (a decision every 10 ms, here faster)
        deadline = time.monotonic() + 10
        key = pub.keys["/lab/slip/p_slip"]
        while time.monotonic() < deadline and len(got.get(key, [])) < len(dets):
            time.sleep(0.02)
        time.sleep(0.3)  # a diagnostics period
    finally:
        pub.close()
        for s in subs:
            s.undeclare()
        sub_session.close()
    assert pub.dropped == 0 and pub.errors == 0
    m = Messages()

    def decoded(topic: str, kind: str) -> list:
        return [m.decode(payload, TYPES[kind]) for _, payload, _ in got[pub.keys[topic]]]

    p = [msg.data for msg in decoded("/lab/slip/p_slip", "p_slip")]
    assert p == [np.float32(d.p_slip) for d in dets]
    alarms = [msg.data for msg in decoded("/lab/slip/alarm", "alarm")]
    assert alarms == [d.alarm for d in dets] and any(alarms)
    maps = decoded("/lab/slip/map", "map")
    with_contact = [d for d in dets if d.contact is not None]
    assert len(maps) == len(with_contact) > 0
    assert [list(mm.data) for mm in maps] == [list(np.float32(d.contact.pillar_slip)) for d in with_contact]
    assert [(dim.label, dim.size) for dim in maps[0].layout.dim] == [("sensor", 1), ("pillar", 9)]
    wrenches = decoded("/lab/slip/wrench/s0", "wrench")
    assert len(wrenches) == len(dets) and wrenches[0].header.frame_id == "slipd_sensor0"
    for w, d in zip(wrenches, dets):
        f, t = finger_wrench(rec.force[d.index])
        assert np.allclose([w.wrench.force.x, w.wrench.force.y, w.wrench.force.z], f)
        assert np.allclose([w.wrench.torque.x, w.wrench.torque.y, w.wrench.torque.z], t)
    diags = decoded("/diagnostics", "diagnostics")
    assert diags and diags[-1].status[0].message == "live"
    values = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert values["decisions"] == "n" and values["dropped"] == "0"
    # rmw_zenoh's attachment: sequence, source time, GID length 16 and the GID.
    seqs = []
    for _, _, att in got[pub.keys["/lab/slip/alarm"]]:
        seq, t_ns, n = struct.unpack_from("<qqB", att)
        assert n == 16 and len(att) == 33 and abs(t_ns - time.time_ns()) < 60e9
        seqs.append(seq)
    assert seqs == sorted(seqs)
    # The alarm reached the subscriber (the latency on loopback: tools/ros2_latency.py prints it).
    first = next(i for i, d in enumerate(dets) if d.rising_edge)
    t_rx = got[pub.keys["/lab/slip/alarm"]][first][0]
    assert sent_at is not None and t_rx >= sent_at


def test_a_full_queue_drops_its_oldest_and_counts(decided) -> None:
    rec, dets = decided
    m = Metrics()
    pub = Ros2Publisher(Ros2Config(enabled=True, queue=8), metrics=m)  # never started: nothing drains the queue
    for d in dets[:20]:
        pub.on_decision(d, rec.force[d.index])
    assert len(pub.queue) == 8 and pub.dropped == 12
    assert m.registry.get_sample_value("slipd_tap_dropped_total", {"tap": "ros2"}) == 12
    assert m.registry.get_sample_value("slipd_tap_dropped_total", {"tap": "viz"}) == 0  # served from the start
    assert [q[2] for q in pub.queue] == [d.p_slip for d in dets[12:20]]  # the newest eight kept
