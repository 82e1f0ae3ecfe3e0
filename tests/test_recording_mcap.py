"""MCAP recordings: exact round trip, every message valid against its schema, the recorder's .mcap replays as its
.npz twin, a killed write leaves no unreadable file, ``slipd convert`` between the formats."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from slipd.cli import main
from slipd.daemon.recorder import Recorder
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.recording import Recording, RecordingError, list_recordings, read_mcap
from slipd.recording_mcap import SCHEMAS, TOPIC_DECISIONS, TOPIC_EVENTS, channels, write_mcap

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "slipd" / "models" / "sample_slip.npz"


def _rec(n: int = 300, sensors: int = 1, seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    shape = (n, 9, 3) if sensors == 1 else (n, sensors, 9, 3)
    force = rng.normal(0, 1, shape).astype(np.float32)
    force[5, ..., 0] = np.nan  # a glitch: written as null, read back as NaN
    fric = rng.uniform(0.2, 1.0, shape[:-2]).astype(np.float32)
    fric[:10] = np.nan  # the controller had no estimate yet
    return Recording(t_us=np.arange(n, dtype=np.int64) * 1000 + 123, force=force,
                     disp=rng.normal(0, 0.1, shape).astype(np.float32), slip=rng.random((n, 9)) > 0.5,
                     label=(np.arange(n) > n // 2).astype(np.uint8), object_motion=rng.normal(0, 1, (n, 3)),
                     friction_est=fric, meta={"scene": "x", "events": {"onset": 0.15}, "nested": [1, {"a": None}]})


def _same(a: Recording, b: Recording) -> None:
    for name in ("t_us", "force", "disp", "slip", "label", "object_motion", "friction_est"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), name
    assert a.meta == b.meta


@pytest.mark.parametrize("sensors", [1, 2])
def test_mcap_roundtrip_is_exact(tmp_path, sensors) -> None:
    rec = _rec(sensors=sensors)
    path = write_mcap(rec, tmp_path / "a.mcap")
    back = Recording.load(path)
    _same(rec, back)
    assert back.sensors == sensors
    assert not (tmp_path / "a.mcap.tmp").exists()
    topics = channels(path)
    assert {f"/slipd/frames/s{s}" for s in range(sensors)} <= set(topics)
    assert topics["/slipd/frames/s0"] == ("slipd.PillarFrame", len(rec))


def _validate_all(path: Path) -> dict[str, int]:
    """Decode every message of ``path`` and check it against its channel's schema; returns counts per topic."""
    counts: dict[str, int] = {}
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            assert schema is not None and schema.encoding == "jsonschema" and channel.message_encoding == "json"
            if schema.id not in validators:
                doc = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(doc)
                assert doc == SCHEMAS[schema.name]
                validators[schema.id] = jsonschema.Draft202012Validator(doc)
            validators[schema.id].validate(json.loads(message.data))
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_every_message_decodes_against_its_schema(tmp_path) -> None:
    rec = _rec(200)
    rec.meta["trigger"] = {"t_us": 50_123, "reason": "alarm", "sensor": 0,
                           "events": [{"t_us": 90_123, "reason": "failsafe", "cause": "sensor_stall"}]}
    decisions = [{"t_us": 123 + 1000 * i, "sensor": 0, "p_slip": i / 20, "alarm": i > 15, "risk": 0.5,
                  "pillar_slip": [0.1] * 8 + [None], "contact_risk": 0.2, "friction": None} for i in range(20)]
    reactions = [{"t_us": 60_123, "action": "stop_arm", "state": "sent"},
                 {"t_us": 61_123, "action": "stop_arm", "state": "acked", "detail": "stopl"}]
    state = {"grip_n": np.linspace(10, 20, 200), "arm_speed_mm_s": np.zeros(200)}
    path = write_mcap(rec, tmp_path / "all.mcap", decisions=decisions, reactions=reactions, state=state,
                      threshold=0.5)
    counts = _validate_all(path)
    assert counts == {"/slipd/frames/s0": 200, "/slipd/truth": 200, TOPIC_DECISIONS: 20, TOPIC_EVENTS: 2,
                      "/slipd/reactions": 2, "/slipd/state": 200, "/slipd/pillars/s0": 10}
    with open(path, "rb") as fh:
        events = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=[TOPIC_EVENTS])]
        fh.seek(0)
        meta = {m.name for m in make_reader(fh).iter_metadata()}
    assert events[0]["message"].startswith("alarm:") and "sensor_stall" in events[1]["message"]
    assert events[1]["level"] == 4
    assert {"slipd.recording", "slipd.meta"} <= meta


def test_config_and_model_become_metadata(tmp_path) -> None:
    rec = _rec(20)
    rec.meta.update(config={"decision": {"threshold": 0.5}}, model={"sha256": "ab", "members": 5})
    path = write_mcap(rec, tmp_path / "m.mcap")
    with open(path, "rb") as fh:
        meta = {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    assert json.loads(meta["slipd.config"]["decision"]) == {"threshold": 0.5}
    assert json.loads(meta["slipd.model"]["members"]) == 5


def _error(path: Path) -> str:
    with pytest.raises(RecordingError) as info:
        Recording.load(path)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{path}: ")
    return text[len(str(path)) + 2:]


def test_bad_mcap_files_name_the_file(tmp_path) -> None:
    (tmp_path / "empty.mcap").write_bytes(b"")
    assert _error(tmp_path / "empty.mcap") == "not an MCAP recording (empty file)"
    (tmp_path / "npz.mcap").write_bytes(SAMPLE.read_bytes())
    assert _error(tmp_path / "npz.mcap").startswith("not an MCAP recording (starts with b'PK")
    assert _error(tmp_path / "missing.mcap").startswith("cannot read")
    good = write_mcap(_rec(100), tmp_path / "good.mcap").read_bytes()
    for cut in (20, len(good) // 2, len(good) - 30):
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(good[:cut])
        _error(path)  # one line naming the file, whatever the reader met


def test_a_flipped_bit_is_refused_or_harmless(tmp_path) -> None:
    """The chunks' CRCs are checked: a corrupted byte is a one-line error, never a silently different force."""
    rec = _rec(300)
    good = write_mcap(rec, tmp_path / "good.mcap").read_bytes()
    rng = np.random.default_rng(3)
    refused = 0
    for k in range(60):
        bad = bytearray(good)
        bad[int(rng.integers(8, len(bad)))] ^= 0xFF
        path = tmp_path / f"flip{k}.mcap"
        path.write_bytes(bytes(bad))
        try:
            back = Recording.load(path)
        except RecordingError as exc:
            assert "\n" not in str(exc) and str(exc).startswith(str(path))
            refused += 1
            continue
        _same(rec, back)  # the flip hit bytes the reader does not need (an index, padding)
    assert refused > 30


def _fed_recorder(directory: Path, model: Path) -> tuple[Recorder, list]:
    """A recorder fed as the daemon's loop feeds it: frames up to each decision, then the decision."""
    rec = Recording.load(SAMPLE)
    ens = Ensemble.load(model)
    dets = replay(rec, ens)
    assert any(d.alarm for d in dets)
    r = Recorder(directory, 1000, seconds_before=2.0, seconds_after=1.0, formats=["npz", "mcap", "csv"],
                 meta={"tare_samples": rec.meta.get("tare_samples", [0, 200]), "threshold": 0.5})
    pushed = 0
    for d in dets:
        r.push_frames(rec.t_us[pushed : d.index + 1], rec.force[pushed : d.index + 1], rec.disp[pushed : d.index + 1])
        pushed = d.index + 1
        r.push_decision(d.t_us, d.p_slip, d.alarm, d.sensor, d.contact)
    r.push_frames(rec.t_us[pushed:], rec.force[pushed:], rec.disp[pushed:])
    r.settle()
    r.close()
    return r, dets


def test_recorder_mcap_replays_as_its_npz_and_csv_twins(tmp_path, detect_model_json) -> None:
    _, _ = _fed_recorder(tmp_path, detect_model_json)
    files = list_recordings(tmp_path)
    assert sorted(f.suffix for f in files) == [".csv", ".mcap", ".npz"]
    by = {f.suffix: f for f in files}
    twins = {k: Recording.load(v) for k, v in by.items()}
    _same(twins[".npz"], twins[".mcap"])
    ens = Ensemble.load(detect_model_json)
    runs = {k: [(d.index, d.t_us, d.p_slip, d.alarm, d.rising_edge) for d in replay(r, ens)]
            for k, r in twins.items()}
    assert runs[".mcap"] == runs[".npz"] == runs[".csv"]
    assert any(a for *_, a, _ in runs[".mcap"])
    counts = _validate_all(by[".mcap"])
    assert counts[TOPIC_DECISIONS] == len(twins[".npz"].meta["decisions"]["t_us"]) > 0
    assert counts[TOPIC_EVENTS] == 1  # the alarm that started the recording


CHILD = textwrap.dedent(
    """
    import sys
    import numpy as np
    from slipd.daemon.recorder import Recorder

    # One long two-finger episode (30 s): its .mcap takes long enough to write that the kill lands inside it.
    rec = Recorder({directory!r}, 1000, seconds_before=2.0, seconds_after=1.0, formats=["mcap"], sensors=2,
                   max_episode_s=30.0)
    rng = np.random.default_rng(0)
    block = rng.normal(0, 1, (100, 2, 9, 3)).astype(np.float32)
    for b in range(340):
        t = (np.arange(100) + 100 * b) * 1000
        rec.push_frames(t, block, block)
        rec.push_decision(int(t[-1]), 0.9, 2000 <= t[-1] < 31_000_000, 0)
    print("QUEUED", flush=True)
    rec.wait(timeout=600)
    print("DONE", flush=True)
    """
)


def test_killed_mcap_write_leaves_no_unreadable_file(tmp_path) -> None:
    d = tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, "-c", CHILD.format(directory=str(d))], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "QUEUED"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not any(p.name.endswith(".tmp") for p in d.iterdir()):
            time.sleep(0.01)
        time.sleep(0.2)  # well inside the write (seconds long)
        assert proc.poll() is None, "the write finished before the kill: the episode is too short"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    leftovers = sorted(p.name for p in d.iterdir())
    assert leftovers and all(n.endswith((".part", ".tmp")) for n in leftovers), leftovers
    assert list_recordings(d) == []  # replay sees nothing half-written
    Recorder(d, 1000).close()  # the next recorder removes the debris
    assert list(d.iterdir()) == []


def test_convert_between_formats_and_replay_each(tmp_path, capsys) -> None:
    mc, csv, npz = tmp_path / "a.mcap", tmp_path / "a.csv", tmp_path / "b.npz"
    assert main(["convert", str(SAMPLE), str(mc)]) == 0
    assert main(["convert", str(mc), str(csv)]) == 0
    assert main(["convert", str(csv), str(npz)]) == 0
    _same(Recording.load(SAMPLE), read_mcap(mc))
    _same(Recording.load(SAMPLE), Recording.load(npz))
    outs = {}
    for p in (SAMPLE, mc, csv, npz):
        j = tmp_path / f"{p.name}.json"
        assert main(["replay", str(p), "--json", str(j)]) == 0
        outs[p.suffix + p.stem] = json.loads(j.read_text())["decisions"]
    first = next(iter(outs.values()))
    assert first and all(v == first for v in outs.values())
    capsys.readouterr()
    assert main(["convert", str(SAMPLE), str(tmp_path / "a.h5")]) == 2
    assert "unknown format" in capsys.readouterr().err
    (tmp_path / "junk.mcap").write_bytes(b"junk")
    assert main(["convert", str(tmp_path / "junk.mcap"), str(tmp_path / "c.npz")]) == 1
    assert "not an MCAP recording" in capsys.readouterr().err
