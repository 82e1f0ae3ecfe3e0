"""An optional section enabled without its extra installed (``ros2`` needs ``slipd[ros2]``, ``viz`` ``slipd[viz]``):
``slipd check-config`` and the daemon's start-up checks refuse it in one line with exit 3, before any device is
opened. The extra is made unimportable here by a ``None`` in ``sys.modules`` (the import then fails as it does where
the package is not installed)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml
from conftest import ROOT

from slipd.cli import EXIT_CONFIG, EXIT_OK, main
from slipd.config import ConfigError, load_config
from slipd.daemon.preflight import EXTRAS, preflight
from slipd.metrics import Metrics


def _config(tmp_path: Path, section: str | None) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["model"]["manifest"] = "slip_ensemble"
    cfg["sensor"]["port"] = str(tmp_path / "ttyACM9")  # not there: the device check would refuse it (exit 5)
    cfg["gripper"]["port"] = str(tmp_path / "ttyUSB9")
    cfg["arm"]["enabled"] = False
    cfg["reaction"].update(actions=["tighten_gripper"], on_failsafe="log_only")
    cfg["recorder"]["directory"] = str(tmp_path / "recordings")
    if section is not None:
        cfg[section] = {"enabled": True}
    path = tmp_path / f"{section}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize("section", sorted(EXTRAS))
def test_check_config_refuses_a_section_whose_extra_is_missing_in_one_line(section, tmp_path, monkeypatch,
                                                                           capsys) -> None:
    path = _config(tmp_path, section)
    for package in EXTRAS[section]:
        pytest.importorskip(package)  # (the others of the section are there: the message names this one)
    for package in EXTRAS[section]:
        monkeypatch.setitem(sys.modules, package, None)
        assert main(["check-config", str(path)]) == EXIT_CONFIG
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert err.startswith(f"{path}: {section}.enabled: needs the {section} extra: pip install 'slipd[{section}]'")
        assert package in err  # the import that failed
        monkeypatch.delitem(sys.modules, package)


def test_check_config_accepts_the_sections_off_without_their_extras(tmp_path, monkeypatch, capsys) -> None:
    for packages in EXTRAS.values():
        for package in packages:
            monkeypatch.setitem(sys.modules, package, None)
    assert main(["check-config", str(_config(tmp_path, None))]) == EXIT_OK, capsys.readouterr().err


@pytest.mark.parametrize("section", sorted(EXTRAS))
def test_start_up_refuses_a_missing_extra_before_the_recorder_and_the_devices(section, tmp_path, monkeypatch) -> None:
    path = _config(tmp_path, section)
    cfg = load_config(path)
    monkeypatch.setitem(sys.modules, EXTRAS[section][0], None)
    with pytest.raises(ConfigError, match=rf"{section}\.enabled: needs the {section} extra"):
        preflight(cfg, Metrics(), str(path), {})
    assert not (tmp_path / "recordings").exists()  # the recorder's directory was never made
    # With the extra there, the next check runs: the missing sensor port (the devices come after the extras).
    monkeypatch.delitem(sys.modules, EXTRAS[section][0])
    monkeypatch.setattr("slipd.daemon.preflight.extra_problems", lambda cfg, source: [])
    with pytest.raises(Exception, match=r"sensor\.port"):
        preflight(cfg, Metrics(), str(path), {})
