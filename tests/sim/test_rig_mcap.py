"""``out/sim.mcap``: a rig run as MCAP. Its channels list with the mcap reader, every message decodes against its
channel's schema, ``slipd replay`` on it gives the alarms of its decision channel and the daemon's live alarm, and
the shipped Foxglove layout plots fields that the file has."""

from __future__ import annotations

import json

import jsonschema
import pytest
from conftest import ROOT
from mcap.reader import make_reader

from slipd.cli import main
from slipd.recording_mcap import SCHEMAS
from slipd.sim.rig import DEFAULT_SCENE, run_rig
from slipd.sim.rig_mcap import write_run_mcap

SCENE = DEFAULT_SCENE
CONFIG = ROOT / "config" / "sim.yaml"
LAYOUT = ROOT / "deploy" / "foxglove" / "slipd.json"

pytestmark = pytest.mark.skipif(not (ROOT / "slipd" / "models" / "slip_ensemble.json").exists(),
                                reason="no shipped model")


@pytest.fixture(scope="module")
def sim_mcap(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    result, physics = run_rig(SCENE, CONFIG, duration_s=3.0, react=True, host="127.0.0.10", log=lambda *a: None)
    path, alarms = write_run_mcap(physics, result, CONFIG, out / "sim.mcap")
    return result, path, alarms


def _messages(path):
    with open(path, "rb") as fh:
        yield from make_reader(fh).iter_messages()


def test_channels_list_and_every_message_decodes_against_its_schema(sim_mcap) -> None:
    result, path, _ = sim_mcap
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert topics == {"/slipd/frames/s0": "slipd.PillarFrame", "/slipd/truth": "slipd.Truth",
                      "/slipd/decisions": "slipd.Decision", "/slipd/events": "foxglove.Log",
                      "/slipd/reactions": "slipd.Reaction", "/slipd/state": "slipd.GripArmState",
                      "/slipd/pillars/s0": "foxglove.SceneUpdate"}
    validators = {name: jsonschema.Draft202012Validator(SCHEMAS[name]) for name in set(topics.values())}
    counts: dict[str, int] = {}
    for schema, channel, message in _messages(path):
        assert json.loads(schema.data) == SCHEMAS[schema.name]
        validators[schema.name].validate(json.loads(message.data))
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts["/slipd/frames/s0"] == counts["/slipd/truth"] == counts["/slipd/state"] == result.frames
    assert counts["/slipd/decisions"] > 100 and counts["/slipd/reactions"] >= 2  # the stop and the tighten


def test_replay_of_sim_mcap_gives_the_runs_alarm(sim_mcap, tmp_path, capsys) -> None:
    result, path, alarms = sim_mcap
    out = tmp_path / "replay.json"
    assert main(["replay", str(path), "--json", str(out)]) == 0
    replayed = json.loads(out.read_text())
    assert replayed["alarms"] == alarms and alarms  # the recording's own decisions, from the same command
    recorded = [json.loads(m.data) for _, c, m in _messages(path) if c.topic == "/slipd/decisions"]
    assert [d["t_us"] for d in recorded] == [d["t_us"] for d in replayed["decisions"]]
    assert [d["p_slip"] for d in recorded] == [d["p_slip"] for d in replayed["decisions"]]
    # The daemon's live alarm (from its log; seconds from the timeline's start, as the recording's samples): the
    # same decision, give or take one stride (the live detector started on the unloaded frames before the timeline).
    assert result.alarm_s is not None
    assert abs(alarms[0] / 1000 - result.alarm_s) <= 0.011, (alarms, result.alarm_s)


def test_the_foxglove_layout_plots_fields_the_recording_has(sim_mcap) -> None:
    _, path, _ = sim_mcap
    layout = json.loads(LAYOUT.read_text())
    paths = [p["value"] for cfg in layout["configById"].values() for p in cfg.get("paths", [])]
    paths += [cfg["topicToRender"] for cfg in layout["configById"].values() if "topicToRender" in cfg]
    paths += [t for cfg in layout["configById"].values() for t in cfg.get("topics", {})]  # the 3D panel's
    assert sum("/slipd/frames/s0.tangential[" in p for p in paths) == 9
    first = {}
    for _, channel, message in _messages(path):
        first.setdefault(channel.topic, json.loads(message.data))
    for p in paths:
        topic, _, field = p.partition(".")
        assert topic in first, p
        if field:
            name, _, index = field.partition("[")
            value = first[topic][name]
            if index:
                value = value[int(index.rstrip("]"))]
            assert isinstance(value, (int, float, bool)), p
