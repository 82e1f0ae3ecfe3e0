"""`slipd run` as a real process against the emulated sensor, servo and UR controller: what it checks before any
device, the signals it is sent, a sensor at the wrong rate, timestamps that jump and recordings it cannot write."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, still_hold

from slipd.sim.devices.mx28 import EmulatedMX28
from slipd.sim.devices.papillarray import EmulatedPapillArray

pytestmark = pytest.mark.timeout(240)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _config(tmp: Path, model: Path, sensor_port: str, servo_port: str, **sections: dict) -> dict:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["model"].update(manifest=str(model), detector="onnx", stride=10)
    cfg["decision"]["threshold"] = 0.999  # the tiny random model: no alarm
    cfg["sensor"].update(port=sensor_port, tare="startup", tare_samples=100, stall_timeout_ms=250)
    cfg["gripper"].update(port=servo_port, packet_timeout_ms=200)  # a busy test process answers the servo late
    cfg["arm"]["enabled"] = False
    cfg["reaction"].update(actions=["tighten_gripper"], on_failsafe="log_only")
    cfg["recorder"]["enabled"] = False
    cfg["metrics"].update(enabled=True, host="127.0.0.1", port=_free_port())
    for name, values in sections.items():
        cfg[name].update(values)
    return cfg


def _write(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg))
    return path


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        return r.read().decode()


def _value(text: str, name: str) -> float:
    m = re.search(rf"^{re.escape(name)} (\S+)$", text, re.M)
    return float(m.group(1)) if m else float("nan")


class _Daemon:
    """One ``slipd run``: its output collected on a thread-free pipe read at the end."""

    def __init__(self, path: Path, port: int) -> None:
        self.port = port
        self.log = path.with_suffix(".log")
        self._out = open(self.log, "w")  # noqa: SIM115 -- closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-m", "slipd", "run", "--config", str(path)],
                                     stdout=self._out, stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})

    def output(self) -> str:
        return self.log.read_text()

    def metric(self, name: str) -> float:
        try:
            return _value(_scrape(self.port), name)
        except OSError:
            return float("nan")

    def wait_for(self, what: str, cond, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert self.proc.poll() is None, f"slipd exited {self.proc.returncode} waiting for {what}:\n" \
                                             f"{self.output()[-3000:]}"
            assert time.monotonic() < deadline, f"timed out waiting for {what}:\n{self.output()[-3000:]}"
            time.sleep(0.05)

    def wait_live(self, timeout: float = 60.0) -> None:
        self.wait_for("slipd_live 1", lambda: self.metric("slipd_live") == 1.0, timeout)

    def wait_line(self, text: str, timeout: float = 30.0) -> None:
        self.wait_for(repr(text), lambda: text in self.output(), timeout)

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self._out.close()
        return rc


@contextmanager
def _running(path: Path, port: int) -> Iterator[_Daemon]:
    d = _Daemon(path, port)
    try:
        yield d
    finally:
        d.stop(signal.SIGKILL if d.proc.poll() is None else signal.SIGTERM)


# ------------------------------------------------------------------------------------------ resources first
def test_a_busy_metrics_port_exits_6_in_one_line_before_any_servo_packet_or_arm_script(tiny_model_json: Path,
                                                                                      tmp_path: Path) -> None:
    """The port was found taken only after the gripper was torqued and set to hold, then exit 1 with a traceback:
    systemd's restarts re-gripped each time. Now it is bound before any device is opened."""
    from slipd.sim.devices.ur_controller import URControllerProcess

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor, \
                URControllerProcess("127.0.0.11") as ur:
            cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
            cfg["metrics"]["port"] = taken.getsockname()[1]
            cfg["arm"].update(enabled=True, host=ur.host)
            cfg["reaction"].update(actions=["stop_arm", "tighten_gripper"], on_failsafe="stop_arm")
            path = _write(tmp_path / "busy.yaml", cfg)
            r = subprocess.run([sys.executable, "-m", "slipd", "run", "--config", str(path)],
                               capture_output=True, text=True, timeout=120)
            state = ur.state()
            packets = servo.packets_received
    finally:
        taken.close()
    assert r.returncode == 6, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "metrics.port" in lines[0] and str(cfg["metrics"]["port"]) in lines[0] and "in use" in lines[0]
    assert packets == 0  # the gripper was never opened
    assert state.scripts_received == 0 and not state.control_script_running  # nor the arm's control


# ------------------------------------------------------------------------------------------ signals
def test_sighup_applies_a_valid_config_names_what_needs_a_restart_and_refuses_an_invalid_one(
        tiny_model_json: Path, tmp_path: Path) -> None:
    """SIGHUP (``systemctl reload``, a closed terminal) killed the daemon at once, devices not closed."""
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
        path = _write(tmp_path / "slipd.yaml", cfg)
        with _running(path, cfg["metrics"]["port"]) as d:
            sensor.start()
            d.wait_live()
            cfg["decision"]["threshold"] = 0.97
            cfg["control"]["log_level"] = "DEBUG"
            cfg["sensor"]["stall_timeout_ms"] = 300  # read once at start-up
            _write(path, cfg)
            d.proc.send_signal(signal.SIGHUP)
            d.wait_line("reload: applied")
            time.sleep(0.5)
            assert d.proc.poll() is None and d.metric("slipd_live") == 1.0
            _write(path, {**cfg, "decision": {**cfg["decision"], "threshold": 1.5}})  # fails validation
            d.proc.send_signal(signal.SIGHUP)
            d.wait_line("reload refused")
            (tmp_path / "slipd.yaml").write_text("sensor: [unclosed\n")  # not even YAML
            d.proc.send_signal(signal.SIGHUP)
            d.wait_for("the second refusal", lambda: d.output().count("reload refused") == 2)
            time.sleep(0.5)
            assert d.proc.poll() is None and d.metric("slipd_live") == 1.0  # ran on
            rc = d.stop()
        out = d.output()
    assert rc == 0, out[-3000:]
    applied = [line for line in out.splitlines() if "reload: applied" in line]
    assert len(applied) == 1 and "decision.threshold=0.97" in applied[0] and "control.log_level='DEBUG'" in applied[0]
    restart = [line for line in out.splitlines() if "needs a restart" in line]
    assert len(restart) == 1 and "sensor.stall_timeout_ms" in restart[0] and "decision" not in restart[0]
    refused = [line for line in out.splitlines() if "reload refused" in line]
    assert len(refused) == 2 and "decision.threshold" in refused[0] and "ERROR" in refused[0]
    assert "Traceback" not in out


def test_other_stop_signals_take_the_sigterm_path_and_end_the_arms_control_script(tiny_model_json: Path,
                                                                                  tmp_path: Path) -> None:
    """SIGQUIT, SIGUSR1 and the like ended the process at once: no log line, the devices not closed, the arm's
    control script left to the controller's watchdog (and with a dashboard stop mode nothing stopped it)."""
    from slipd.sim.devices.ur_controller import URControllerProcess

    results, outs = [], []
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor, \
            URControllerProcess("127.0.0.12") as ur:
        sensor.start()
        for sig in (signal.SIGQUIT, signal.SIGUSR1):
            cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
            cfg["arm"].update(enabled=True, host=ur.host, watchdog_s=5.0)  # slipd's close, not the watchdog
            cfg["reaction"].update(actions=["stop_arm", "tighten_gripper"], on_failsafe="stop_arm")
            path = _write(tmp_path / f"{sig.name}.yaml", cfg)
            with _running(path, cfg["metrics"]["port"]) as d:
                d.wait_live()
                assert ur.state().control_script_running
                rc = d.stop(sig)
                time.sleep(0.3)
                out = d.output()
                results.append((sig.name, rc, ur.state().control_script_running,
                                sum(f"{sig.name}: stopping" in line for line in out.splitlines())))
                outs.append(out[-1500:])
            ur.drop_connections(0.0)
            time.sleep(0.5)
    assert results == [("SIGQUIT", 0, False, 1), ("SIGUSR1", 0, False, 1)], "\n".join(outs)


# ------------------------------------------------------------------------------------------ rate
@pytest.mark.parametrize("rate", [500, 2000])
def test_a_sensor_at_the_wrong_rate_fails_safe_with_cause_rate_and_is_never_ready(
        tiny_model_json: Path, tmp_path: Path, rate: int) -> None:
    """At 500 Hz the daemon went live and decided on windows twice as long in time as the model learnt; at 2 kHz it
    dropped frames, still live. The controller here ignores the rate command."""
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True, fixed_rate_hz=rate) as sensor:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
        path = _write(tmp_path / "slipd.yaml", cfg)
        with _running(path, cfg["metrics"]["port"]) as d:
            sensor.start()
            d.wait_for("the rate fail-safe", lambda: d.metric('slipd_failsafe_stops_total{reason="rate"}') == 1.0)
            time.sleep(1.0)
            assert d.metric("slipd_live") == 0.0
            assert d.metric("slipd_sensor_rate_hz") == pytest.approx(rate, rel=0.02)
            sensor.force_rate(1000)  # the controller streams at the model's rate again: recovered
            d.wait_live(timeout=30)
            assert d.metric('slipd_failsafe_stops_total{reason="rate"}') == 1.0
            rc = d.stop()
        out = d.output()
    assert rc == 0, out[-3000:]
    blind = [line for line in out.splitlines() if "blind:" in line]
    assert len(blind) == 1 and f"at {rate} Hz" in blind[0] and "model's rate is 1000 Hz" in blind[0], out[-3000:]
    assert sum("live again after rate" in line for line in out.splitlines()) == 1


# ------------------------------------------------------------------------------------------ timestamps
def test_timestamps_that_jump_are_counted_and_logged_once_per_episode(tiny_model_json: Path, tmp_path: Path) -> None:
    """A device clock running back 5 s passed unflagged."""
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
        path = _write(tmp_path / "slipd.yaml", cfg)
        with _running(path, cfg["metrics"]["port"]) as d:
            sensor.start()
            d.wait_live()
            d.wait_for("6 s of device time", lambda: sensor.frames_written > 6000)
            sensor.jump_clock(-5.0)
            sensor.jump_clock(0.001)  # the next frame: still in the same episode
            d.wait_for("the jump counted",
                       lambda: d.metric('slipd_timestamp_jumps_total{kind="backwards"}') == 1.0)
            time.sleep(1.0)  # regular timestamps again: the episode ends
            sensor.jump_clock(2.0)
            d.wait_for("the second jump counted",
                       lambda: d.metric('slipd_timestamp_jumps_total{kind="forward"}') == 1.0)
            time.sleep(0.5)
            assert d.metric("slipd_live") == 1.0
            rc = d.stop()
        out = d.output()
    assert rc == 0, out[-3000:]
    logged = [line for line in out.splitlines() if "sensor: its timestamps" in line]
    assert len(logged) == 2 and "ran backwards" in logged[0] and "jumped ahead" in logged[1], out[-3000:]


# ------------------------------------------------------------------------------------------ recordings lost
def _mount_namespaces() -> bool:
    """A private mount namespace can be made and entered here (root, util-linux): the read-only directory tests."""
    import shutil

    if os.geteuid() != 0 or not shutil.which("unshare") or not shutil.which("nsenter"):
        return False
    return subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0


needs_mounts = pytest.mark.skipif(not _mount_namespaces(), reason="needs root and mount namespaces (unshare, nsenter)")


def _in_namespace(directory: Path, cmd: list[str], read_only: bool = False) -> list[str]:
    """``cmd`` in a mount namespace of its own where ``directory`` is a bind mount (read-only from the start when
    asked); ``set_read_only`` remounts it read-only there later."""
    ro = f" && mount -o remount,bind,ro {directory} {directory}" if read_only else ""
    return ["unshare", "-m", "--propagation", "private", "sh", "-c",
            f"mount --bind {directory} {directory}{ro} && exec \"$0\" \"$@\"", *cmd]


def _set_read_only(pid: int, directory: Path, read_only: bool) -> None:
    mode = "ro" if read_only else "rw"
    subprocess.run(["nsenter", "-t", str(pid), "-m", "mount", "-o", f"remount,bind,{mode}", str(directory)],
                   check=True, capture_output=True)


@needs_mounts
def test_a_read_only_recording_directory_at_start_up_exits_3_before_any_device(tiny_model_json: Path,
                                                                              tmp_path: Path) -> None:
    rec = tmp_path / "recordings"
    rec.mkdir(mode=0o750)
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port, recorder={"enabled": True,
                                                                                    "directory": str(rec)})
        path = _write(tmp_path / "ro.yaml", cfg)
        r = subprocess.run(_in_namespace(rec, [sys.executable, "-m", "slipd", "run", "--config", str(path)],
                                         read_only=True), capture_output=True, text=True, timeout=120)
        packets = servo.packets_received
    assert r.returncode == 3, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "recorder.directory" in lines[0] and "Read-only file system" in lines[0], r.stderr
    assert packets == 0


@needs_mounts
def test_a_recording_directory_gone_read_only_counts_each_lost_recording_in_one_line_and_recovers(
        tiny_model_json: Path, tmp_path: Path) -> None:
    """Each lost recording was an ERROR with two tracebacks (about 25 lines) and no metric counted it."""
    rec = tmp_path / "recordings"
    rec.mkdir(mode=0o750)
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port, recorder={"enabled": True,
                                                                                    "directory": str(rec)})
        path = _write(tmp_path / "slipd.yaml", cfg)
        port = cfg["metrics"]["port"]
        d = _Daemon.__new__(_Daemon)
        d.port, d.log = port, path.with_suffix(".log")
        d._out = open(d.log, "w")  # noqa: SIM115 -- closed by stop()
        d.proc = subprocess.Popen(_in_namespace(rec, [sys.executable, "-m", "slipd", "run", "--config", str(path)]),
                                  stdout=d._out, stderr=subprocess.STDOUT, text=True,
                                  env={**os.environ, "PYTHONUNBUFFERED": "1"})
        lost = 'slipd_recordings_failed_total{reason="read_only"}'
        try:
            sensor.start()
            d.wait_live()
            _set_read_only(d.proc.pid, rec, True)
            for k in (1, 2):  # a fail-safe's recording is written at once: two stalls, two lost recordings
                sensor.stall(600)
                d.wait_for(f"lost recording {k}", lambda k=k: d.metric(lost) == k)
                d.wait_live()
            _set_read_only(d.proc.pid, rec, False)
            sensor.stall(600)  # room again: the next one is written
            d.wait_for("a recording written", lambda: any(p.suffix == ".npz" for p in rec.iterdir()))
            assert d.metric(lost) == 2
            rc = d.stop()
        finally:
            if d.proc.poll() is None:
                d.stop(signal.SIGKILL)
        out = d.output()
    assert rc == 0, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    lines = [line for line in out.splitlines() if "recorder:" in line and "lost" in line]
    assert len(lines) == 2 and all("(read_only)" in line and "Read-only file system" in line for line in lines), out


# ------------------------------------------------------------------------------------------ logs that tell the truth
def test_a_fail_safe_episode_is_two_lines_and_slipds_own_stop_of_the_arm_is_no_error(tiny_model_json: Path,
                                                                                    tmp_path: Path) -> None:
    """Each fail-safe logged an ERROR "control script ended (watchdog expired or stopped from the pendant)" that
    slipd's own stop had caused, beside two lines of its own: an unplug storm of 55 episodes gave 98 ERROR lines."""
    from slipd.sim.devices.ur_controller import URControllerProcess

    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True) as sensor, \
            URControllerProcess("127.0.0.13") as ur:
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
        cfg["arm"].update(enabled=True, host=ur.host, watchdog_s=0.3)
        cfg["reaction"].update(actions=["stop_arm", "tighten_gripper"], on_failsafe="stop_arm")
        path = _write(tmp_path / "slipd.yaml", cfg)
        with _running(path, cfg["metrics"]["port"]) as d:
            sensor.start()
            d.wait_live()
            ur.wait_for(lambda s: s.control_script_running and s.watchdog_hz > 0, timeout=30.0, what="kicked")
            mark = len(d.output().splitlines())
            for k in (1, 2, 3):
                sensor.unplug()
                time.sleep(0.5)
                sensor.replug()
                d.wait_for(f"episode {k} over",
                           lambda k=k: d.output().count("live again after") == k and d.metric("slipd_live") == 1.0)
                ur.wait_for(lambda s: s.control_script_running, timeout=30.0, what="the script back")
            time.sleep(1.0)
            rc = d.stop()
        out = d.output()
    assert rc == 0, out[-3000:]
    episode = out.splitlines()[mark:]
    loud = [line for line in episode if " WARNING " in line or " ERROR " in line]
    assert len(loud) == 6, "\n".join(loud)  # per episode: "blind: ...; fail-safe" and "live again after ..."
    assert sum(" ERROR " in line for line in loud) == 3 and all("blind:" in line for line in loud if " ERROR " in line)
    assert any("control script ended after slipd's stop" in line and " INFO " in line for line in episode), \
        "\n".join(episode)


def test_frames_missing_before_the_daemon_is_live_are_counted_apart_from_drops(tiny_model_json: Path,
                                                                              tmp_path: Path) -> None:
    """The controller streams before slipd reads the port: the frames it could not hold showed as ~1000 dropped
    frames after every start, which tripped the dropped-frames alert on each restart."""
    with EmulatedMX28() as servo, EmulatedPapillArray(still_hold(), loop=True, max_pending_bytes=16 * 1024) as sensor:
        sensor.start()  # before the daemon: its output piles up and overflows
        time.sleep(1.0)
        cfg = _config(tmp_path, tiny_model_json, sensor.port, servo.port)
        path = _write(tmp_path / "slipd.yaml", cfg)
        with _running(path, cfg["metrics"]["port"]) as d:
            d.wait_live()
            time.sleep(1.0)
            text = _scrape(d.port)
            rc = d.stop()
    assert rc == 0
    assert sensor.frames_discarded > 0  # the emulator did lose frames before the port was read
    assert _value(text, "slipd_frames_discarded_at_start_total") > 0, text
    assert _value(text, "slipd_dropped_frames_total") == 0, text
