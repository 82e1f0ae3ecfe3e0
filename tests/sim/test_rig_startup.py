"""The rig starts a run afresh when the daemon cannot reach the emulated devices at start-up, and only then.

On a loaded machine the emulators' threads can miss the daemon's first status packets; the daemon then exits with
the device start-up code (5) before it is ready. That is the rig's problem, not the run's: a failure after the daemon
is ready, or with any other code, must reach the caller unchanged.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from slipd.sim import rig


def _exited(code: int, tmp_path):
    log = tmp_path / "daemon.log"
    log.write_text("slipd: device start-up failed: gripper ping failed after 4 attempt(s)\n")
    proc = subprocess.Popen([sys.executable, "-c", f"import sys; sys.exit({code})"])
    proc.wait()
    return proc, log


def test_exit_code_5_before_ready_is_a_device_startup_error(tmp_path):
    proc, log = _exited(5, tmp_path)
    with pytest.raises(rig.DeviceStartupError, match="ping failed"):
        rig._wait_ready(proc, port=1, log_file=log, timeout=5.0)
    proc, log = _exited(3, tmp_path)  # an invalid config is no start-up race
    with pytest.raises(RuntimeError) as err:
        rig._wait_ready(proc, port=1, log_file=log, timeout=5.0)
    assert not isinstance(err.value, rig.DeviceStartupError)


def test_a_run_starts_again_after_a_device_startup_failure():
    calls: list[dict] = []

    @rig._afresh_on_device_startup_failure
    def once(scene: str, *, seed: int = 0, log=print) -> tuple[str, str]:
        calls.append({"scene": scene, "seed": seed})
        if len(calls) < rig.START_ATTEMPTS:
            raise rig.DeviceStartupError("daemon exited with 5:\nslipd: device start-up failed")
        return "result", "physics"

    logged: list[str] = []
    assert once("scene.yaml", seed=7, log=logged.append) == ("result", "physics")
    assert calls == [{"scene": "scene.yaml", "seed": 7}] * rig.START_ATTEMPTS
    assert len(logged) == rig.START_ATTEMPTS - 1 and "starting again" in logged[0]
    assert "device start-up failed" in logged[0]


def test_it_gives_up_and_never_retries_other_failures():
    calls = []

    @rig._afresh_on_device_startup_failure
    def always(log=print) -> None:
        calls.append(1)
        raise rig.DeviceStartupError("daemon exited with 5")

    with pytest.raises(rig.DeviceStartupError):
        always(log=lambda *a: None)
    assert len(calls) == rig.START_ATTEMPTS

    @rig._afresh_on_device_startup_failure
    def broken(log=print) -> None:
        calls.append(1)
        raise RuntimeError("daemon not ready after 60 s")

    calls.clear()
    with pytest.raises(RuntimeError, match="not ready"):
        broken(log=lambda *a: None)
    assert len(calls) == 1


def test_run_rig_is_the_retried_run():
    assert rig.run_rig.__wrapped__.__name__ == "run_rig"  # functools.wraps: the decorated function, its signature


def test_a_heuristic_on_the_rig_runs_alone_whatever_the_config_confirms(tmp_path):
    """``slipd sim --detector reference_pillar`` on a config with ``decision.confirm_rule`` set: the heuristic decides
    alone (the key confirms the onnx detector, and the config would be refused with it)."""
    import yaml

    base = yaml.safe_load(rig.DEFAULT_CONFIG.read_text())
    base["decision"]["confirm_rule"] = 0.3
    path = tmp_path / "base.yaml"
    path.write_text(yaml.safe_dump(base))

    class Devices:
        def overrides(self) -> dict:
            return {}

    for detector, level in (("reference_pillar", None), ("onnx", 0.3), (None, 0.3)):
        out = tmp_path / str(detector)
        out.mkdir()
        written = yaml.safe_load(rig._daemon_config(path, Devices(), 9999, True, out, detector).read_text())
        assert written["decision"]["confirm_rule"] == level
        assert written["model"]["detector"] == (detector or "onnx")
