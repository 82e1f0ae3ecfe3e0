"""SIGHUP: read the configuration file again, check it, and apply what can change while the daemon runs.

Run on the loop's thread between two blocks of frames (``slipd.daemon.signals.while_running``), so a change never
lands inside a decision. The new file is checked as ``slipd run`` checks it (the schema, then against the loaded
model); a file that fails is refused with one log line and the daemon runs on with the config in force. Of a valid
file, the keys in ``LIVE_KEYS`` are applied (the decision rule, the log level, the recorder, the rate tolerance);
every other changed key is named in one line as needing a restart and left as it is (the devices, the model, the
stream's rate and layout are opened or built once).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slipd.config import ConfigError, load_config
from slipd.detect.build import config_problems

if TYPE_CHECKING:
    from slipd.config import SlipdConfig
    from slipd.daemon.loop import Daemon

log = logging.getLogger("slipd.reload")

LIVE_KEYS = ("decision.", "control.log_level", "recorder.", "sensor.rate_tolerance")
"""Keys (a trailing dot: the whole section) applied by a reload."""
RESTART_KEYS = ("decision.confirm_rule", "decision.confirm_within_ms")
"""Keys of a live section that still take a restart: the rule beside the model is built with the detector."""


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def changed_keys(old: SlipdConfig, new: SlipdConfig) -> list[str]:
    """The dotted keys whose values differ, in the schema's order."""
    a, b = _flat(old.model_dump()), _flat(new.model_dump())
    return [k for k in b if a.get(k) != b[k]] + [k for k in a if k not in b]


def is_live(key: str) -> bool:
    return key not in RESTART_KEYS and any(key == k or (k.endswith(".") and key.startswith(k)) for k in LIVE_KEYS)


def _one_line(exc: Exception) -> str:
    return "; ".join(" ".join(str(exc).split("\n")).split("; "))


class Reloader:
    """Reloads ``path`` into ``daemon`` (``reload``); counts what it did for tests and the log."""

    def __init__(self, path: str | Path, daemon: Daemon) -> None:
        self.path = Path(path)
        self.daemon = daemon
        self.applied = 0
        self.refused = 0

    def reload(self) -> bool:
        """One reload; True when the file was valid (whether or not anything changed)."""
        d = self.daemon
        try:
            new = load_config(self.path)
            problems = config_problems(new, d.ensemble.manifest, str(self.path))
            if problems:
                raise ConfigError(problems)
        except ConfigError as exc:
            self.refused += 1
            log.error("reload refused, running on with the configuration in force: %s",
                      " | ".join(str(exc).splitlines()))
            return False
        keys = changed_keys(d.cfg, new)
        live = [k for k in keys if is_live(k)]
        later = [k for k in keys if not is_live(k)]
        if later:
            log.warning("reload: %s changed: needs a restart (left as it is until then)", ", ".join(later))
        if not live:
            if not later:
                log.info("reload: %s unchanged", self.path)
            return True
        try:
            self._apply(new, live)
        except (ConfigError, OSError, ValueError) as exc:
            self.refused += 1
            log.error("reload refused, running on with the configuration in force: %s", _one_line(exc))
            return False
        self.applied += 1
        log.info("reload: applied %s", ", ".join(f"{k}={_flat(new.model_dump()).get(k)!r}" for k in live))
        return True

    def _apply(self, new: SlipdConfig, live: list[str]) -> None:
        """Everything that can fail first (the recorder's directory), then the changes, none of which can."""
        from slipd.daemon.preflight import open_recorder, recording_meta

        d = self.daemon
        old = d.cfg
        recorder_changed = any(k.startswith("recorder.") for k in live)
        recorder = d.recorder
        # What every recording carries (the config and the threshold in force) follows the reloaded file.
        meta = recording_meta(new, d.ensemble.manifest)
        if recorder_changed:
            recorder = open_recorder(new, str(self.path), meta, d.metrics)
        elif recorder is not None:
            recorder.meta = meta
        d.set_decision_rule(new.decision)
        if new.control.log_level != old.control.log_level:
            logging.getLogger().setLevel(new.control.log_level)
        d.rate.tolerance = new.sensor.rate_tolerance
        if recorder_changed:
            before, d.recorder = d.recorder, recorder
            if before is not None:
                # Its writes may take a while: on a thread of its own, not the loop's.
                threading.Thread(target=before.close, name="slipd-recorder-close", daemon=True).start()
        d.cfg = old.model_copy(update={
            "decision": new.decision.model_copy(update={  # (the keys that wait for a restart keep what is in force)
                k.removeprefix("decision."): getattr(old.decision, k.removeprefix("decision.")) for k in RESTART_KEYS}),
            "recorder": new.recorder,
            "control": old.control.model_copy(update={"log_level": new.control.log_level}),
            "sensor": old.sensor.model_copy(update={"rate_tolerance": new.sensor.rate_tolerance}),
        })
