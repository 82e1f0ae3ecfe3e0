"""onnxruntime writes a device id and an events database under ~/.cache unless its telemetry is off before it loads
(slipd.detect.ort): a replay and a check-config leave a fresh home folder empty."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import ROOT


def test_replay_and_check_config_write_nothing_under_home(tmp_path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("ORT_DISABLE_TELEMETRY", "XDG_CACHE_HOME")}
    env["HOME"] = str(home)
    for argv in (["replay", "--sample"], ["check-config", str(ROOT / "config" / "slipd.yaml")]):
        done = subprocess.run([sys.executable, "-m", "slipd", *argv], env=env, cwd=tmp_path, capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0, done.stderr
    assert sorted(p.relative_to(home).as_posix() for p in home.rglob("*")) == []
