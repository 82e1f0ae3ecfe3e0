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


def test_run_rig_starts_again_after_a_device_startup_failure(monkeypatch):
    calls: list[dict] = []

    def once(*args, **kwargs):
        calls.append(kwargs)
        if len(calls) < rig.START_ATTEMPTS:
            raise rig.DeviceStartupError("daemon exited with 5")
        return "result", "physics"

    monkeypatch.setattr(rig, "_run_rig_once", once)
    logged: list[str] = []
    assert rig.run_rig("scene.yaml", seed=7, log=logged.append) == ("result", "physics")
    assert len(calls) == rig.START_ATTEMPTS and all(c["seed"] == 7 for c in calls)
    assert len(logged) == rig.START_ATTEMPTS - 1 and "starting again" in logged[0]


def test_run_rig_gives_up_and_never_retries_other_failures(monkeypatch):
    calls = []

    def always(*args, **kwargs):
        calls.append(1)
        raise rig.DeviceStartupError("daemon exited with 5")

    monkeypatch.setattr(rig, "_run_rig_once", always)
    with pytest.raises(rig.DeviceStartupError):
        rig.run_rig("scene.yaml", log=lambda *a: None)
    assert len(calls) == rig.START_ATTEMPTS

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("daemon not ready after 60 s")

    calls.clear()
    monkeypatch.setattr(rig, "_run_rig_once", broken)
    with pytest.raises(RuntimeError, match="not ready"):
        rig.run_rig("scene.yaml", log=lambda *a: None)
    assert len(calls) == 1
