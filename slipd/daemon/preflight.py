"""What ``slipd run`` checks on this machine before it touches a device.

A resource that is not there is found before the gripper is torqued and set to hold, and before ur_rtde's
control script replaces the user's program: otherwise each start that fails on it re-grips the object, and
systemd's restarts do so again each time. The checks, in order: the packages of the optional sections the
configuration enables can be imported (``ros2.enabled`` needs the ``ros2`` extra, ``viz.enabled`` the ``viz`` one,
``extra_problems``; a config problem, exit 3, which ``slipd check-config`` reports too), the recording directory can
be made and written (``recorder.directory``; exit 3), each device path exists and may be opened
(``slipd.daemon.devices.check_devices``; exit 5), and the metrics port can be bound (``metrics.host`` and
``metrics.port``; exit 6). The port is bound here and kept: the server that answers scrapes is this one, so
nothing can take the port between the check and the run.
"""

from __future__ import annotations

import errno
import importlib
import os
from typing import TYPE_CHECKING, Any

from slipd.config import ConfigError
from slipd.daemon.devices import check_devices

if TYPE_CHECKING:
    from wsgiref.simple_server import WSGIServer

    from slipd.config import SlipdConfig
    from slipd.daemon.recorder import Recorder
    from slipd.metrics import Metrics


EXTRAS: dict[str, tuple[str, ...]] = {"ros2": ("zenoh", "rosbags"), "viz": ("foxglove",)}
"""The packages each optional section needs, by its name, which is also its extra's (``slipd[ros2]``,
``slipd[viz]``)."""


def extra_problems(cfg: SlipdConfig, source: str) -> list[str]:
    """One line per section the configuration enables whose extra cannot be imported (``EXTRAS``): the file, the key,
    what to install and why the import failed. Imports the packages of the enabled sections only."""
    problems = []
    for section, packages in EXTRAS.items():
        if not getattr(cfg, section).enabled:
            continue
        for name in packages:
            try:
                importlib.import_module(name)
            except ImportError as exc:
                problems.append(f"{source}: {section}.enabled: needs the {section} extra: pip install "
                                f"'slipd[{section}]' ({' '.join(str(exc).split())})")
                break
    return problems


class ResourceError(RuntimeError):
    """A resource of this machine that slipd needs is unavailable (a port in use); the message is one line naming the
    key and the reason."""


def recording_meta(cfg: SlipdConfig, manifest: Any) -> dict[str, Any]:
    """What every recording carries about the daemon that made it: the model (sha256 and manifest), the configuration
    and the alarm threshold in force (the MCAP recordings show them as metadata, and the threshold with p_slip)."""
    threshold = cfg.decision.threshold if cfg.decision.threshold is not None else manifest.threshold
    return {"model_sha256": manifest.sha256, "threshold": float(threshold),
            "config": cfg.model_dump(mode="json"), "model": manifest.model_dump(mode="json")}


def open_recorder(cfg: SlipdConfig, source: str, meta: dict[str, Any],
                  metrics: Metrics | None = None) -> Recorder | None:
    """The recorder, its directory made and checked writable (None when ``recorder.enabled`` is false); a directory
    that cannot be used is a ``ConfigError`` naming ``recorder.directory``."""
    if not cfg.recorder.enabled:
        return None
    from slipd.daemon.recorder import Recorder

    try:
        recorder = Recorder.from_config(cfg.recorder, rate_hz=cfg.sensor.rate_hz, sensors=cfg.sensor.sensors,
                                        meta=meta, metrics=metrics)
    except OSError as exc:
        raise ConfigError([f"{source}: recorder.directory: {cfg.recorder.directory} cannot be used: "
                           f"{exc.strerror or exc}"]) from exc
    try:
        # A directory that exists with the right mode can still refuse files (a read-only mount, a full disk): write
        # one and remove it.
        probe = recorder.directory / f".slipd-write-check-{os.getpid()}"
        with open(probe, "wb") as f:
            f.write(b"slipd")
        probe.unlink()
    except OSError as exc:
        recorder.close()
        raise ConfigError([f"{source}: recorder.directory: {cfg.recorder.directory} is not writable: "
                           f"{exc.strerror or exc}"]) from exc
    return recorder


def serve_metrics(cfg: SlipdConfig, metrics: Metrics) -> WSGIServer | None:
    """Bind and serve ``/metrics`` (None when ``metrics.enabled`` is false); ``ResourceError`` when the address
    cannot be bound."""
    m = cfg.metrics
    if not m.enabled:
        return None
    try:
        return metrics.serve(m.host, m.port)
    except OSError as exc:
        why = "in use by another process" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        raise ResourceError(f"metrics.port: {m.host}:{m.port} cannot be bound: {why}") from exc


def preflight(cfg: SlipdConfig, metrics: Metrics, source: str,
              meta: dict[str, Any]) -> tuple[Recorder | None, WSGIServer | None]:
    """Every check of the module docstring, in its order; returns the recorder and the metrics server, both ready.
    Raises ``ConfigError``, ``DeviceError`` or ``ResourceError``; what was opened before a failure is released."""
    problems = extra_problems(cfg, source)
    if problems:
        raise ConfigError(problems)
    recorder = open_recorder(cfg, source, meta, metrics)
    try:
        check_devices(cfg)
        server = serve_metrics(cfg, metrics)
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise
    return recorder, server
