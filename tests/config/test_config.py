"""Configuration: errors name file, line, key path and reason; check-config exit codes; shipped configs."""

from __future__ import annotations

import os
import subprocess
import textwrap
from pathlib import Path

import pytest
import yaml

from slipd.config import ConfigError, config_from_dict, load_config, override, parse_config

ROOT = Path(__file__).resolve().parents[2]
SLIPD = ROOT / ".venv" / "bin" / "slipd"

VALID = textwrap.dedent(
    """\
    sensor:
      port: /dev/ttyACM0
    model:
      manifest: models/m.json
    gripper:
      port: /dev/ttyUSB0
      hold_position: 2048
      secure_position: 2600
      hold_pwm: 300
      secure_pwm: 700
    arm:
      host: 192.168.1.10
    """
)


def write(tmp_path: Path, text: str, name: str = "slipd.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def errors_of(tmp_path: Path, text: str) -> list[str]:
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert all(line.startswith(str(p)) for line in exc.value.problems), exc.value.problems
    return exc.value.problems


def with_(base: str, **sections: dict) -> str:
    """VALID with some keys replaced (section -> {key: value}; value None deletes the key)."""
    data = yaml.safe_load(base)
    for section, keys in sections.items():
        data.setdefault(section, {})
        for k, v in keys.items():
            if v is None:
                data[section].pop(k, None)
            else:
                data[section][k] = v
    return yaml.safe_dump(data, sort_keys=False)


def test_minimal_valid_config_and_defaults(tmp_path, monkeypatch):
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    cfg = load_config(write(tmp_path, VALID))
    assert cfg.sensor.rate_hz == 1000 and cfg.sensor.tare == "bias_command"
    assert cfg.model.manifest == tmp_path / "models" / "m.json"  # relative to the config's folder
    assert cfg.decision.threshold is None and cfg.decision.effective_threshold(0.42) == 0.42
    assert cfg.reaction.actions == ["stop_arm", "tighten_gripper"]
    assert cfg.gripper.protocol == 2.0 and cfg.gripper.hold_effort == 300 and cfg.gripper.secure_effort == 700
    assert cfg.metrics.host == "127.0.0.1" and cfg.metrics.port == 9477
    assert cfg.recorder.directory == Path("/var/lib/slipd/recordings")


def test_state_directory_and_env_vars(tmp_path, monkeypatch):
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/slipd:/var/lib/other")
    assert load_config(write(tmp_path, VALID)).recorder.directory == Path("/var/lib/slipd/recordings")
    monkeypatch.setenv("SLIPD_TEST_DIR", "/srv/x")
    cfg = load_config(write(tmp_path, with_(VALID, recorder={"directory": "${SLIPD_TEST_DIR}/rec"})))
    assert cfg.recorder.directory == Path("/srv/x/rec")
    problems = errors_of(tmp_path, with_(VALID, recorder={"directory": "$SLIPD_UNSET_XYZ/rec"}))
    assert "recorder.directory" in problems[0] and "unset environment variable" in problems[0]


def test_broken_yaml_names_line_and_column(tmp_path):
    (line,) = errors_of(tmp_path, "sensor:\n  port: /dev/ttyACM0\n  rate_hz: [1000\nmodel: {}\n")
    assert "YAML syntax error" in line
    assert "slipd.yaml:4:6: YAML syntax error: while parsing a flow sequence" in line
    # An escape beyond U+10FFFF: PyYAML raises chr()'s ValueError, not a YAML error (found by the config fuzzer).
    (line,) = errors_of(tmp_path, VALID + 'metrics:\n  host: "\\U00110000"\n')
    assert "slipd.yaml:" in line and "YAML syntax error" in line and "chr()" in line


def test_tab_indentation_and_duplicate_keys(tmp_path):
    (line,) = errors_of(tmp_path, "sensor:\n\tport: x\n")
    assert "slipd.yaml:2:1: YAML syntax error" in line
    (line,) = errors_of(tmp_path, VALID + "sensor:\n  port: /dev/ttyACM1\n")
    assert "duplicate key 'sensor'" in line and "slipd.yaml:13:1:" in line


def test_empty_and_non_mapping(tmp_path):
    assert "empty" in errors_of(tmp_path, "# nothing\n")[0]
    assert "top level must be a mapping" in errors_of(tmp_path, "- a\n- b\n")[0]


def test_unknown_keys_rejected_with_suggestion(tmp_path):
    problems = errors_of(tmp_path, VALID.replace("  hold_pwm: 300", "  hold_pmw: 300") + "extra: 1\n")
    joined = "\n".join(problems)
    assert "slipd.yaml:9: gripper.hold_pmw: unknown key (did you mean 'hold_pwm'?)" in joined
    assert "slipd.yaml:13: extra: unknown key" in joined


def test_wrong_types(tmp_path):
    problems = errors_of(tmp_path, with_(VALID, sensor={"rate_hz": "fast", "low_latency": "maybe"},
                                         gripper={"id": 1.5, "baudrate": 12345}, arm={"host": 10}))
    joined = "\n".join(problems)
    assert "sensor.rate_hz: Input should be 100, 250, 500 or 1000 (got 'fast')" in joined
    assert "sensor.low_latency: Input should be a valid boolean" in joined
    assert "gripper.id:" in joined and "(got 1.5)" in joined
    assert "gripper.baudrate: must be one of 9600, 19200" in joined and "(got 12345)" in joined
    assert "arm.host: Input should be a valid string (got 10)" in joined


def test_out_of_range_values(tmp_path):
    problems = errors_of(tmp_path, with_(VALID, gripper={"secure_pwm": 900}, metrics={"port": 70000},
                                         decision={"threshold": 1.0}, sensor={"stall_timeout_ms": float("nan")}))
    joined = "\n".join(problems)
    assert ": gripper.secure_pwm: Input should be less than or equal to 885 (got 900)" in joined
    assert "metrics.port: Input should be less than or equal to 65535 (got 70000)" in joined
    assert "decision.threshold: Input should be less than 1 (got 1.0)" in joined
    assert "sensor.stall_timeout_ms: Input should be a finite number" in joined


def test_missing_required_device_fields(tmp_path):
    problems = errors_of(tmp_path, "model:\n  manifest: m.json\ngripper: {}\narm: {}\n")
    joined = "\n".join(problems)
    assert "sensor: required key is missing" in joined
    assert "slipd.yaml:3: gripper.port: required when the gripper is enabled" in joined
    assert "slipd.yaml:4: arm.host: required when the arm is enabled" in joined
    (line,) = errors_of(tmp_path, with_(VALID, sensor={"port": None}))
    assert "sensor.port: required key is missing" in line


def test_protocol_specific_effort_keys(tmp_path):
    (line,) = errors_of(tmp_path, with_(VALID, gripper={"protocol": 1.0}))
    assert "gripper.hold_pwm: does not apply to protocol 1.0" in line
    cfg = load_config(write(tmp_path, with_(VALID, gripper={
        "protocol": 1, "hold_pwm": None, "secure_pwm": None, "hold_torque_limit": 200, "secure_torque_limit": 900})))
    assert cfg.gripper.protocol == 1.0 and cfg.gripper.secure_effort == 900
    (line,) = errors_of(tmp_path, with_(VALID, gripper={"secure_pwm": 100}))
    assert "gripper.secure_pwm: must be >= hold_pwm (300)" in line


def test_grip_control_needs_a_gripper_that_can_reach_its_force_limit(tmp_path):
    # A limit above the jaw's full force is never reached, so the arm stop at the limit would never come.
    (line,) = errors_of(tmp_path, with_(VALID, reaction={"policy": "grip_control", "grip_max_force_n": 60.0}))
    assert "reaction.grip_max_force_n: 60 N is above the gripper's full force (gripper.max_force_n: 40 N)" in line
    (line,) = errors_of(tmp_path, with_(VALID, gripper={"enabled": False},
                                        reaction={"policy": "grip_control", "actions": ["stop_arm"]}))
    assert "reaction.policy: grip_control needs gripper.enabled: true" in line
    (line,) = errors_of(tmp_path, with_(VALID, reaction={"policy": "grip_control", "actions": ["stop_arm"]}))
    assert "reaction.actions: grip_control commands the grip: list tighten_gripper" in line
    cfg = load_config(write(tmp_path, with_(VALID, reaction={"policy": "grip_control", "grip_max_force_n": 40.0})))
    assert cfg.reaction.grip_max_force_n == cfg.gripper.max_force_n == 40.0


def test_numbers_are_read_as_yaml_1_2_and_a_boolean_is_no_number(tmp_path):
    """YAML 1.1 (PyYAML's default) reads 0100 as octal 64, 1:30 as sexagesimal 90, and yes / on as true, which
    pydantic then takes for 1 wherever a number is due: a hold position, a stall timeout, a 1 N jaw, protocol 1.0."""
    cfg = load_config(write(tmp_path, VALID.replace("hold_position: 2048", "hold_position: 02048")))
    assert cfg.gripper.hold_position == 2048
    cfg = load_config(write(tmp_path, VALID.replace("secure_position: 2600", "secure_position: 0100")))
    assert cfg.gripper.secure_position == 100
    (line,) = errors_of(tmp_path, VALID.replace("sensor:\n", "sensor:\n  stall_timeout_ms: 1:30\n"))
    assert "sensor.stall_timeout_ms" in line
    for key, value in (("max_force_n", "yes"), ("max_force_n", "true"), ("protocol", "on"), ("retries", "true")):
        (line,) = errors_of(tmp_path, VALID.replace("gripper:\n", f"gripper:\n  {key}: {value}\n"))
        assert f"gripper.{key}" in line, (key, value, line)
    cfg = load_config(write(tmp_path, VALID.replace("gripper:\n", "gripper:\n  enabled: yes\n")))
    assert cfg.gripper.enabled is True  # a boolean key still reads yes
    cfg = load_config(write(tmp_path, VALID.replace("gripper:\n", "gripper:\n  max_force_n: 4e1\n")))
    assert cfg.gripper.max_force_n == 40.0


def test_keys_that_the_chosen_mode_never_reads_are_refused(tmp_path):
    """Unread options are refused, as unknown keys are: a grip_control key under stop_and_secure (a force limit there
    would be believed to bind; a tighten still goes to the secure setting), a watchdog or deceleration with a dashboard
    stop (no RTDE control interface: a dead slipd leaves the program running)."""
    (line,) = errors_of(tmp_path, with_(VALID, reaction={"grip_max_force_n": 5.0}))
    assert "reaction.grip_max_force_n: 5.0 has no effect with reaction.policy stop_and_secure" in line
    cfg = load_config(write(tmp_path, with_(VALID, reaction={"policy": "grip_control", "grip_max_force_n": 5.0})))
    assert cfg.reaction.grip_max_force_n == 5.0
    for key, value in (("watchdog_s", 0.1), ("stop_deceleration", 5.0)):
        (line,) = errors_of(tmp_path, with_(VALID, arm={"stop_method": "dashboard_stop", key: value}))
        assert f"arm.{key}" in line and "no effect with stop_method dashboard_stop" in line
    assert load_config(write(tmp_path, with_(VALID, arm={"stop_method": "speed_stop", "watchdog_s": 0.1})))


def test_a_heuristic_detector_needs_a_zeroed_sensor(tmp_path):
    # The heuristics have no start-up tare of their own: with tare startup they read the raw offsets.
    (line,) = errors_of(tmp_path, with_(VALID, model={"detector": "reference_pillar"}, sensor={"tare": "startup"}))
    assert "sensor.tare: startup: model.detector reference_pillar has no start-up tare" in line
    zeroed = with_(VALID, model={"detector": "deceleration"}, sensor={"tare": "bias_command"})
    cfg = load_config(write(tmp_path, zeroed))
    assert cfg.model.detector == "deceleration"


def test_a_heuristic_detector_refuses_the_ensembles_decision_keys(tmp_path):
    # The heuristics decide on every sample with their own tuned rule: the ensemble's threshold, hysteresis, run
    # length, press hold and stride would be read by nothing, so a value other than the default is refused.
    zeroed = with_(VALID, model={"detector": "reference_pillar"}, sensor={"tare": "bias_command"})
    (line,) = errors_of(tmp_path, with_(zeroed, decision={"threshold": 0.7}))
    assert "decision.threshold: 0.7 has no effect with model.detector reference_pillar" in line
    (line,) = errors_of(tmp_path, with_(zeroed, decision={"min_consecutive": 3}))
    assert "decision.min_consecutive: 3 has no effect" in line and "default (2)" in line
    (line,) = errors_of(tmp_path, with_(zeroed, decision={"press_rise": 0.2}))
    assert "decision.press_rise: 0.2 has no effect" in line
    (line,) = errors_of(tmp_path, with_(zeroed, model={"detector": "reference_pillar", "stride": 20}))
    assert "model.stride: 20 has no effect" in line
    # The defaults, written out as config/slipd.yaml does, are fine; the ensemble takes every value.
    cfg = load_config(write(tmp_path, with_(zeroed, decision={"min_consecutive": 2, "press_rise": 0.1})))
    assert cfg.model.detector == "reference_pillar"
    assert load_config(write(tmp_path, with_(VALID, decision={"threshold": 0.7}))).decision.threshold == 0.7


def test_cross_field_checks(tmp_path):
    (line,) = errors_of(tmp_path, with_(VALID, arm={"enabled": False}))
    assert "reaction.actions: stop_arm needs arm.enabled: true" in line
    (line,) = errors_of(tmp_path, with_(VALID, sensor={"reconnect_initial_s": 10, "reconnect_max_s": 1}))
    assert "sensor.reconnect_max_s: must be >= reconnect_initial_s" in line
    (line,) = errors_of(tmp_path, with_(VALID, sensor={"rate_hz": 100, "stall_timeout_ms": 10}))
    assert "sensor.stall_timeout_ms: must be at least two frame periods at 100 Hz (20 ms)" in line
    (line,) = errors_of(tmp_path, with_(VALID, reaction={"actions": ["stop_arm", "stop_arm"]}))
    assert "reaction.actions: an action is listed twice" in line
    (line,) = errors_of(tmp_path, with_(VALID, reaction={"actions": ["stop_arm", "open_gripper"]}))
    assert "reaction.actions[1]: Input should be 'stop_arm' or 'tighten_gripper'" in line
    # Both devices off: detect-and-record only is a valid setup when nothing is asked of them.
    cfg = load_config(write(tmp_path, with_(VALID, arm={"enabled": False}, gripper={"enabled": False},
                                            reaction={"actions": [], "on_failsafe": "log_only"})))
    assert cfg.reaction.actions == [] and not cfg.arm.enabled


def test_unreadable_and_not_utf8(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.yaml")
    p = tmp_path / "latin1.yaml"
    p.write_bytes(b"sensor:\n  port: /dev/tty\xe9\n")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(p)


def test_override_revalidates_and_model_copy(tmp_path):
    cfg = load_config(write(tmp_path, VALID))
    rig = override(cfg, {"sensor.port": "/dev/pts/7", "gripper.port": "/dev/pts/8", "arm.host": "127.0.0.2"})
    assert rig.sensor.port == "/dev/pts/7" and rig.arm.host == "127.0.0.2"
    assert rig.model.manifest == cfg.model.manifest
    with pytest.raises(ConfigError, match=r"gripper\.secure_pwm"):
        override(cfg, {"gripper.secure_pwm": 10_000})
    with pytest.raises(ConfigError, match="no such section"):
        override(cfg, {"nosuch.key": 1})
    copy = cfg.model_copy(update={"sensor": cfg.sensor.model_copy(update={"port": "/dev/pts/9"})})
    assert copy.sensor.port == "/dev/pts/9" and cfg.sensor.port == "/dev/ttyACM0"
    with pytest.raises(Exception, match="frozen"):
        cfg.sensor.port = "x"  # type: ignore[misc]


def test_parse_config_text_without_base_dir():
    cfg = parse_config(VALID, source="<text>")
    assert cfg.model.manifest == Path("models/m.json")  # no folder to anchor it: left relative
    with pytest.raises(ConfigError, match=r"^<text>:2: sensor\.port: Input should be a valid string"):
        parse_config(VALID.replace("/dev/ttyACM0", "[a, b]"), source="<text>")


def test_config_from_dict_names_source():
    with pytest.raises(ConfigError, match=r"^<rig>: sensor: required key is missing"):
        config_from_dict({"model": {"manifest": "/m.json"}, "gripper": {"enabled": False},
                          "arm": {"enabled": False}, "reaction": {"actions": [], "on_failsafe": "log_only"}},
                         source="<rig>")


def test_shipped_configs_are_valid():
    real = load_config(ROOT / "config" / "slipd.yaml")
    assert real.sensor.port == "/dev/ttyACM0" and real.gripper.enabled and real.arm.enabled
    sim = load_config(ROOT / "config" / "sim.yaml")
    assert sim.model.manifest == ROOT / "slipd" / "models" / "slip_ensemble.json"
    assert sim.recorder.directory == Path("/tmp/slipd-sim-recordings")  # any folder: the package may be read-only


def test_every_key_of_the_real_config_is_documented():
    """Each key line in config/slipd.yaml carries a comment; every field of every section is present."""
    from slipd.config import SlipdConfig

    text = (ROOT / "config" / "slipd.yaml").read_text()
    for line in text.splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith("#") and not stripped.endswith(":"):
            assert "#" in line, f"undocumented key line: {line!r}"
    for name, field in SlipdConfig.model_fields.items():
        assert f"\n{name}:" in "\n" + text, name
        for key in field.annotation.model_fields:
            assert f" {key}:" in text, f"{name}.{key} not in config/slipd.yaml"


def test_device_vocabularies_match_the_drivers():
    """config.py spells out the drivers' accepted values (so check-config does not load vendor SDKs)."""
    from typing import get_args

    from slipd.config import DYNAMIXEL_BAUDRATES, ArmConfig

    arm = pytest.importorskip("slipd.io.arm")
    assert get_args(ArmConfig.model_fields["stop_method"].annotation) == arm.STOP_METHODS
    gripper = pytest.importorskip("slipd.io.gripper")
    assert gripper.BAUDRATES == DYNAMIXEL_BAUDRATES


def test_fuzz_short():
    from sliplab.fuzz_config import run

    counts = run(150, seed=1)
    assert counts["total"] >= 135  # hypothesis may discard a few over-sized draws
    assert counts["escaped"] == 0
    assert counts["valid"] > 0 and counts["config_error"] > 0


# ------------------------------------------------------------------------------------------ check-config
def tiny_model(folder: Path) -> Path:
    """A minimal ensemble-shaped ONNX graph with a manifest that slipd.detect.manifest accepts."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    from slipd.detect.features import FeatureSpec
    from slipd.detect.manifest import Manifest, io_infos, sha256_file, write_manifest

    spec = FeatureSpec()
    z, h = 2, 4
    graph = helper.make_graph(
        [
            helper.make_node("Identity", ["h"], ["h_next"]),
            helper.make_node("ReduceMean", ["h"], ["hm"], axes=[2], keepdims=0),
            helper.make_node("Sigmoid", ["hm"], ["p_members"]),
            helper.make_node("ReduceMean", ["p_members"], ["p_slip"], axes=[0], keepdims=0),
        ],
        "tiny",
        [helper.make_tensor_value_info("window", TensorProto.FLOAT, ["B", spec.input_size]),
         helper.make_tensor_value_info("h", TensorProto.FLOAT, [z, "B", h])],
        [helper.make_tensor_value_info("p_slip", TensorProto.FLOAT, ["B"]),
         helper.make_tensor_value_info("p_members", TensorProto.FLOAT, [z, "B"]),
         helper.make_tensor_value_info("h_next", TensorProto.FLOAT, [z, "B", h])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    folder.mkdir(parents=True, exist_ok=True)
    onnx.save(model, folder / "tiny.onnx")
    inputs, outputs = io_infos(spec.input_size, z, h)
    manifest = Manifest(
        onnx_file="tiny.onnx", sha256=sha256_file(folder / "tiny.onnx"), opset=17, ir_version=8,
        inputs=inputs, outputs=outputs, sample_rate_hz=spec.rate_hz, window=spec.window, median=spec.median,
        stride=spec.step, pillars=list(spec.pillars), channels=list(spec.channels), members=z, hidden=h,
        threshold=0.5, input_clip=100.0, feature_spec=spec.to_dict(), source="trained", pillar_mapping="sdk-raster",
    )
    write_manifest(manifest, folder / "tiny.json")
    return folder / "tiny.json"


def check_config(path: Path) -> subprocess.CompletedProcess:
    exe = [str(SLIPD)] if SLIPD.exists() else [str(ROOT / ".venv" / "bin" / "python"), "-m", "slipd"]
    env = {k: v for k, v in os.environ.items() if k != "STATE_DIRECTORY"}
    return subprocess.run([*exe, "check-config", str(path)], capture_output=True, text=True, timeout=120,
                          cwd=ROOT, env=env)


def test_check_config_exit_codes(tmp_path):
    """The installed ``slipd check-config`` command: 0 valid, 3 bad config, 4 bad model."""
    tiny_model(tmp_path / "models")
    good = write(tmp_path, VALID.replace("models/m.json", "models/tiny.json"))
    good.chmod(0o640)
    r = check_config(good)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"OK {good}: sensor /dev/ttyACM0 @ 1000 Hz") and "threshold 0.5" in r.stdout
    assert r.stderr == ""

    bad = write(tmp_path, VALID.replace("hold_pwm: 300", "hold_pwm: -1"), "bad.yaml")
    r = check_config(bad)
    assert r.returncode == 3 and "bad.yaml:9: gripper.hold_pwm" in r.stderr and r.stdout == ""

    missing_model = write(tmp_path, VALID, "nomodel.yaml")  # models/m.json does not exist
    r = check_config(missing_model)
    assert r.returncode == 4 and "model.manifest" in r.stderr and "file not found" in r.stderr


def main_check_in_process(path: Path, capsys) -> tuple[int, str, str]:
    from argparse import Namespace

    from slipd.cli import cmd_check_config as main_check

    code = main_check(Namespace(config=str(path)))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_check_config_warns_world_writable_and_catches_a_changed_model(tmp_path, capsys):
    tiny_model(tmp_path / "models")
    good = write(tmp_path, VALID.replace("models/m.json", "models/tiny.json"))
    good.chmod(0o666)
    code, out, err = main_check_in_process(good, capsys)
    assert code == 0 and out.startswith("OK") and "world-writable" in err
    (tmp_path / "models" / "tiny.onnx").write_bytes(b"not onnx")
    code, out, err = main_check_in_process(good, capsys)
    assert code == 4 and "sha256" in err and out == ""


def test_check_config_against_manifest(tmp_path, capsys):
    tiny_model(tmp_path / "models")
    text = VALID.replace("models/m.json", "models/tiny.json")
    code, _, err = main_check_in_process(
        write(tmp_path, with_(text, sensor={"rate_hz": 500}, model={"stride": 15}), "x.yaml"), capsys)
    assert code == 3
    assert "sensor.rate_hz: 500 Hz, but the model was trained at 1000 Hz" in err
    assert "model.stride: must divide the model's window (40), got 15" in err


def test_check_config_and_run_read_a_heuristics_parameters_before_any_device(tmp_path, capsys, monkeypatch):
    """A heuristic detector's tuned parameters are read when the daemon builds its detector, after the devices were
    opened and the gripper told to hold: a missing file must refuse the config first, naming the key."""
    tiny_model(tmp_path / "models")
    text = with_(VALID.replace("models/m.json", "models/tiny.json"), model={"detector": "deceleration",
                                                                           "baseline_params": "missing.json"},
                 sensor={"tare": "bias_command"})
    path = write(tmp_path, text, "h.yaml")
    code, _, err = main_check_in_process(path, capsys)
    assert code == 3 and "model.baseline_params" in err and "missing.json" in err

    from slipd.config import ConfigError
    from slipd.daemon import preflight, service

    opened: list[str] = []
    monkeypatch.setattr(preflight, "check_devices", lambda cfg: opened.append("checked"))
    monkeypatch.setattr(service, "build_devices", lambda cfg, m: opened.append("built") or (None, None))
    with pytest.raises(ConfigError, match=r"model\.baseline_params"):
        service.prepare(path)
    assert opened == []


# ---------------------------------------------------------------------------------------------- bounded input
def alias_bomb(levels: int = 10, width: int = 9) -> str:
    """The "billion laughs": each line is a list of ``width`` aliases to the line above (9**10 values)."""
    lines = [f"l0: &l0 [{', '.join(['lol'] * width)}]"]
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * width)}]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


def test_alias_bomb_refused_naming_file_and_line(tmp_path):
    problems = errors_of(tmp_path, alias_bomb())
    assert len(problems) == 1
    # 9**4 = 6561 values per *l3 alias: the fourth alias line (line 5) crosses the 20000-value bound.
    assert problems[0].startswith(f"{tmp_path / 'slipd.yaml'}:5:") and "alias *l3" in problems[0]
    assert "refused" in problems[0] and "alias bomb" in problems[0]


def test_alias_bomb_inside_a_section_and_as_merge_key(tmp_path):
    bomb = alias_bomb(8).replace("\n", "\n  ").rstrip()
    problems = errors_of(tmp_path, VALID.replace("arm:\n", f"bogus:\n  {bomb}\narm:\n"))
    assert "refused" in problems[0] and "alias *l" in problems[0]
    merges = ["base: &m0 {a: 1, b: 2, c: 3}"]
    merges += [f"m{i}: &m{i} {{x: [{', '.join([f'*m{i - 1}'] * 9)}]}}" for i in range(1, 8)]
    problems = errors_of(tmp_path, "\n".join(merges) + "\nsensor:\n  <<: *m7\n")
    assert "refused" in problems[0]


def test_small_aliases_still_work(tmp_path):
    """Anchors have honest uses (one port named once); the bound is on the expanded size, not on aliases."""
    text = VALID.replace("port: /dev/ttyACM0", "port: &sensor_port /dev/ttyACM0")
    text = text.replace("  port: /dev/ttyUSB0", "  port: *sensor_port")
    cfg = load_config(write(tmp_path, text))
    assert cfg.gripper.port == cfg.sensor.port == "/dev/ttyACM0"


def test_recursive_alias_refused(tmp_path):
    problems = errors_of(tmp_path, "sensor: &a [*a]\n")
    expected = f"{tmp_path / 'slipd.yaml'}:1:13: refused: alias *a refers to its own anchor (a recursive value)"
    assert problems == [expected]


@pytest.mark.parametrize(
    "text",
    [
        "sensor: " + "[" * 5000 + "]" * 5000 + "\n",  # flow lists
        "sensor: " + "{a: " * 2000 + "1" + "}" * 2000 + "\n",  # flow mappings
        "sensor:\n" + "".join("  " * i + f"k{i}:\n" for i in range(1, 300)),  # block mappings
        "sensor: " + "[" * 200000 + "\n",  # unterminated: refused at the bound, before the syntax error
    ],
    ids=["flow-lists", "flow-maps", "block", "unterminated"],
)
def test_deep_nesting_refused_with_line(tmp_path, text):
    problems = errors_of(tmp_path, text)
    assert len(problems) == 1 and "refused: nested deeper than 32 levels" in problems[0]
    assert problems[0].split(":")[1].isdigit()  # file:LINE:column


def test_check_config_refuses_alias_bomb_quickly(tmp_path):
    """The installed command: exit 3, one line. Run under a memory cap and a timeout so a regression
    (the unbounded loader grew to 4.9 GB over 60 s) fails this test instead of the CI machine."""
    import resource

    bomb = write(tmp_path, alias_bomb(), "bomb.yaml")

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    exe = [str(SLIPD)] if SLIPD.exists() else [str(ROOT / ".venv" / "bin" / "python"), "-m", "slipd"]
    r = subprocess.run([*exe, "check-config", str(bomb)], capture_output=True, text=True, timeout=60,
                       preexec_fn=cap)
    assert r.returncode == 3, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(f"{bomb}:5:") and "refused" in r.stderr
    # In-process, the refusal itself is well under a second (the bound) even on a busy machine.
    import time

    t0 = time.perf_counter()
    with pytest.raises(ConfigError):
        parse_config(alias_bomb(), "bomb")
    assert time.perf_counter() - t0 < 1.0


def _expanded_size(levels: int, width: int) -> int:
    """Values in ``alias_bomb(levels, width)`` with every alias expanded: the top mapping, and per line
    a key and a list (the first of ``width`` scalars, each later one of ``width`` copies of the last)."""
    total, size = 1, 1 + width
    for i in range(levels):
        total += 1 + size
        size = 1 + width * size if i + 1 < levels else size
    return total


@pytest.mark.parametrize("levels,width", [(1, 3), (3, 9), (4, 9), (5, 7), (6, 5), (8, 3), (9, 3), (14, 2)])
def test_alias_bound_is_the_expanded_size(levels, width):
    """Refused exactly when the document, aliases expanded, is larger than the bound: the counting is
    of values, not of lines or of alias uses."""
    from slipd.config.load import MAX_YAML_NODES

    size = _expanded_size(levels, width)
    try:
        parse_config(alias_bomb(levels, width), "bomb")
        refused = False
    except ConfigError as exc:
        refused = "refused" in str(exc)
    assert refused == (size > MAX_YAML_NODES), (size, MAX_YAML_NODES)


def test_depth_bound_is_exact():
    """The top mapping is level 1, so ``sensor:`` holds at most 30 nested lists below the bound of 32."""
    from slipd.config.load import MAX_YAML_DEPTH

    def doc(depth: int) -> str:
        return "sensor: " + "[" * depth + "]" * depth + "\n"

    with pytest.raises(ConfigError) as exc:
        parse_config(doc(MAX_YAML_DEPTH - 1), "ok")
    assert "refused" not in str(exc.value)  # within the bound: an ordinary validation error
    with pytest.raises(ConfigError, match="refused: nested deeper than 32 levels"):
        parse_config(doc(MAX_YAML_DEPTH), "deep")


def test_two_sensors_need_the_onnx_detector() -> None:
    from slipd.config import ConfigError, load_config, override

    cfg = load_config(ROOT / "config" / "slipd.yaml")
    assert cfg.sensor.sensors == 1 and cfg.model.stride == 0  # the model's own stride by default
    assert override(cfg, {"sensor.sensors": 2}).sensor.sensors == 2
    with pytest.raises(ConfigError, match=r"model\.detector: deceleration reads one sensor"):
        override(cfg, {"sensor.sensors": 2, "model.detector": "deceleration", "sensor.tare": "bias_command"})


def test_an_unusable_recorder_directory_is_refused_before_any_device(tmp_path, monkeypatch):
    """A recorder directory that cannot be made (here under a regular file) raised a traceback after the gripper
    was told to hold; it is a config problem naming the key, found before the devices are opened."""
    from slipd.config import ConfigError
    from slipd.daemon import preflight, service

    tiny_model(tmp_path / "models")
    (tmp_path / "afile").write_text("")
    text = with_(VALID.replace("models/m.json", "models/tiny.json"),
                 recorder={"enabled": True, "directory": str(tmp_path / "afile" / "rec")})
    path = write(tmp_path, text, "r.yaml")
    opened: list[str] = []
    monkeypatch.setattr(preflight, "check_devices", lambda cfg: None)
    monkeypatch.setattr(service, "build_devices", lambda cfg, m: opened.append("built") or (None, None))
    with pytest.raises(ConfigError, match=r"recorder\.directory"):
        service.prepare(path)
    assert opened == []
