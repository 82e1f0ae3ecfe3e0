"""The systemd unit's start path with a bad config or model: refused once, not restarted.

systemd applies ``RestartPreventExitStatus=`` to the exit of ``ExecStart=`` only; a failing ``ExecStartPre=`` is
restarted like any other failure, up to the start limit. So the unit runs no pre-check: ``slipd run`` (its
``ExecStart=``) checks the config and the model before it opens a device and exits 3 or 4, which the unit lists in
``RestartPreventExitStatus=`` under ``Restart=on-failure``. systemd is not PID 1 here, so the unit cannot be
started: these tests read the unit file, let ``systemd-analyze verify`` parse it where installed, and run its
``ExecStart=`` command line against the installed slipd.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT

UNIT = ROOT / "systemd" / "slipd.service"


def _service_section() -> dict[str, list[str]]:
    """The [Service] section's settings (a key may repeat: each value in order)."""
    section, out = None, {}
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line
            continue
        if section == "[Service]":
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


def _exec_start_with(config: Path) -> list[str]:
    """The unit's ExecStart= command line, run with this interpreter's slipd and the given config."""
    argv = shlex.split(_service_section()["ExecStart"][0])
    assert argv[0] == "/opt/slipd/bin/slipd" and argv[1:3] == ["run", "--config"], argv
    return [sys.executable, "-m", "slipd", *argv[1:3], str(config)]


def test_the_unit_leaves_the_config_and_model_checks_to_exec_start() -> None:
    service = _service_section()
    assert "ExecStartPre" not in service, "a failed ExecStartPre= is restarted: RestartPreventExitStatus= ignores it"
    assert service["Restart"] == ["on-failure"]
    assert {"2", "3", "4"} <= set(service["RestartPreventExitStatus"][0].split())
    assert "dialout" in service["SupplementaryGroups"][0].split()


def test_the_unit_parses_with_systemd(tmp_path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    # verify wants ExecStart='s program to exist: the installed slipd stands in for /opt/slipd/bin/slipd.
    slipd = Path(sys.executable).with_name("slipd")
    unit = tmp_path / "slipd.service"
    unit.write_text(UNIT.read_text().replace("/opt/slipd/bin/slipd", str(slipd)))
    done = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(("change", "code"), [
    (("rate_hz: 1000", "rate_hz: 7"), 3),
    (("manifest: slip_ensemble_int8", "manifest: broken.json"), 4),
])
def test_exec_start_refuses_a_bad_config_or_model_with_an_exit_code_the_unit_does_not_restart(
        tmp_path, change, code) -> None:
    """config/slipd.yaml names /dev/ttyACM0, absent here: a daemon that opened its devices first would exit 5
    (device failure, which the unit does restart) instead."""
    text = (ROOT / "config" / "slipd.yaml").read_text()
    assert change[0] in text
    bad = tmp_path / "slipd.yaml"
    bad.write_text(text.replace(change[0], change[1], 1))
    (tmp_path / "broken.json").write_text('{"name": "broken"}')  # a manifest without its model
    done = subprocess.run(_exec_start_with(bad), capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == code, (done.returncode, done.stderr)
    assert str(code) in _service_section()["RestartPreventExitStatus"][0].split()
    assert "Traceback" not in done.stderr, done.stderr
