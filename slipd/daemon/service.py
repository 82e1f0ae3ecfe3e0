"""``slipd run``: the daemon's start-up order, its run and its shutdown.

Order (fail-safe): the config, then the model (manifest, hash, shapes, feature layout, warm-up), then what this
machine must provide (``slipd.daemon.preflight``: the recording directory writable, every device path there and
accessible, the arm's controller answering, the metrics port bound), and only then are the devices opened. A broken
config or model, a missing device or a busy port therefore never touches hardware. Each step raises its own typed
error (``ConfigError``, ``ModelError``, ``DeviceError``, ``ResourceError``); ``slipd.cli`` turns them into exit codes
(one line, no traceback). Signals: ``slipd.daemon.signals``; SIGHUP reloads the config (``slipd.daemon.reload``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import os
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from slipd.config import ConfigError, SlipdConfig, load_config
from slipd.daemon import signals
from slipd.daemon.devices import DeviceError, build_devices, close_quietly
from slipd.daemon.loop import Daemon
from slipd.daemon.preflight import ResourceError, extra_problems, preflight, recording_meta
from slipd.daemon.reload import Reloader
from slipd.daemon.sdnotify import Notifier
from slipd.daemon.signals import StopRequested
from slipd.detect.build import config_problems
from slipd.detect.ensemble import Ensemble
from slipd.metrics import Metrics

if TYPE_CHECKING:
    from wsgiref.simple_server import WSGIServer

log = logging.getLogger("slipd.service")


@dataclass
class Service:
    """A configured daemon with its model loaded and devices open, ready to ``run``."""

    cfg: SlipdConfig
    daemon: Daemon
    metrics: Metrics
    native: NativeOutput | None = None
    server: WSGIServer | None = None
    """The metrics endpoint, bound before any device was opened (``slipd.daemon.preflight``)."""
    config_path: Path | None = None
    """The file a SIGHUP reads again (None: reloads are refused)."""

    def run(self) -> None:
        """Run the loop until a stop signal; SIGHUP reloads the config; always releases the devices."""
        m = self.cfg.metrics
        if m.enabled:
            exposure = metrics_exposure(m.host)
            if exposure:
                log.warning("metrics.host %s: /metrics (model hash, alarm and fail-safe counts) is served %s; "
                            "keep it on 127.0.0.1 unless a firewall limits who can scrape it", m.host, exposure)
        reloader = Reloader(self.config_path, self.daemon) if self.config_path is not None else None

        def reload() -> None:
            if reloader is None:
                log.warning("SIGHUP: no configuration file to read again; ignored")
            else:
                reloader.reload()

        async def _main() -> None:
            signals.while_running(asyncio.get_running_loop(), self.daemon.stop, reload)
            if signals.reload_pending():  # a SIGHUP during start-up: the file may have changed since it was read
                reload()
            await self.daemon.run()

        try:
            asyncio.run(_main())
        finally:
            signals.while_closing()
            self.daemon.close()
            if self.server is not None:
                self.server.shutdown()
                self.server.server_close()
            if self.native is not None:
                self.native.close()


class NativeOutput:
    """Routes what native libraries write to the process's stdout and stderr through the log.

    ur_rtde (C++) prints its reconnect and exception messages with ``std::cout``/``std::cerr`` straight to
    file descriptors 1 and 2, outside the log format (no time, level or source). Both descriptors are
    pointed at pipes; a thread turns each line into a ``slipd.ur_rtde`` log record (stderr lines as
    warnings). Python's own ``sys.stdout``/``sys.stderr`` (logging, the CLI's messages) keep writing to
    the original destinations through duplicates of the original descriptors. ``close`` restores them.
    """

    def __init__(self) -> None:
        self._saved = [os.dup(1), os.dup(2)]
        self._py = (sys.stdout, sys.stderr)
        sys.stdout = open(self._saved[0], "w", buffering=1, closefd=False)  # noqa: SIM115 -- lives until close
        sys.stderr = open(self._saved[1], "w", buffering=1, closefd=False)  # noqa: SIM115
        self._threads = []
        for fd, level in ((1, logging.INFO), (2, logging.WARNING)):
            r, w = os.pipe()
            os.dup2(w, fd)
            os.close(w)
            t = threading.Thread(target=self._pump, args=(r, level), name=f"slipd-native-{fd}", daemon=True)
            t.start()
            self._threads.append(t)

    @staticmethod
    def _pump(fd: int, level: int) -> None:
        out = logging.getLogger("slipd.ur_rtde")
        with open(fd, "rb") as pipe:
            for raw in pipe:
                line = raw.decode(errors="replace").rstrip()
                if line:
                    out.log(level, "%s", line)

    def close(self) -> None:
        """Point descriptors 1 and 2 back at the originals; the pumps log what is left and end."""
        if not self._saved:
            return
        with contextlib.suppress(ValueError, OSError):
            sys.stdout.flush()
            sys.stderr.flush()
        for fd, saved in zip((1, 2), self._saved):
            os.dup2(saved, fd)  # closes the pipe's last write end: the pump sees EOF after the rest
        for t in self._threads:
            t.join(timeout=1.0)
        ours = (sys.stdout, sys.stderr)
        sys.stdout, sys.stderr = self._py
        for h in logging.getLogger().handlers:  # the log handler made meanwhile goes back to the real stream
            if isinstance(h, logging.StreamHandler) and h.stream in ours:
                h.setStream(self._py[ours.index(h.stream)])
        for saved in self._saved:
            os.close(saved)
        self._saved = []


def metrics_exposure(host: str) -> str:
    """Empty for a loopback listen address, else who can reach it (for the start-up warning)."""
    if host == "localhost":
        return ""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return f"on the interface of host name {host!r}, beyond this machine"
    if ip.is_loopback:
        return ""
    if ip.is_unspecified:
        return "on every network interface of this machine"
    return f"on the network interface {host}, beyond this machine"


def start_taps(cfg: SlipdConfig, daemon: Daemon, config_path: str) -> None:
    """The ROS 2 publisher and the live view where the configuration enables them (each needs its extra); a failure
    closes the ones already started."""
    problems = extra_problems(cfg, config_path)  # (preflight refused these already, before any device was opened)
    if problems:
        raise ConfigError(problems)
    try:
        if cfg.ros2.enabled:
            from slipd.daemon.ros2 import Ros2Publisher, daemon_health

            try:
                daemon.taps.append(Ros2Publisher(cfg.ros2, cfg.sensor.sensors, health=lambda: daemon_health(daemon),
                                                 metrics=daemon.metrics).start())
            except Exception as exc:  # zenoh's own errors (a client that reaches no router)
                raise DeviceError(f"ros2: cannot open the zenoh session: {' '.join(str(exc).split())}") from exc
        if cfg.viz.enabled:
            from slipd.daemon.viz import LiveView

            threshold = cfg.decision.threshold or daemon.ensemble.manifest.threshold
            try:
                daemon.taps.append(LiveView(cfg.viz, cfg.sensor.sensors, cfg.sensor.rate_hz, threshold,
                                            metrics=daemon.metrics).start())
            except Exception as exc:  # the SDK's own errors (the port is taken)
                raise DeviceError(f"viz: cannot start the Foxglove server on {cfg.viz.host}:{cfg.viz.port}: "
                                  f"{' '.join(str(exc).split())}") from exc
    except BaseException:
        for tap in daemon.taps:
            tap.close()
        daemon.taps.clear()
        raise


def prepare(config_path: str | os.PathLike[str]) -> Service:
    """Load and check everything, then open the devices (in that order). Raises ConfigError, ModelError,
    DeviceError or ResourceError; nothing is opened when the config or the model is refused, a device is missing or a
    resource unavailable."""
    signals.during_start_up()  # a stop during start-up unwinds it, closing what is open (StopRequested)
    native = NativeOutput()  # first: the log handler must take the original stderr, not the pipe
    arm = gripper = recorder = server = None
    try:
        cfg = load_config(config_path)
        logging.basicConfig(level=cfg.control.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        ensemble = Ensemble.load(cfg.model.manifest, threads=cfg.model.threads)
        problems = config_problems(cfg, ensemble.manifest, str(config_path))
        if problems:  # as check-config says, before any device is opened
            raise ConfigError(problems)
        metrics = Metrics()
        recorder, server = preflight(cfg, metrics, str(config_path), recording_meta(cfg, ensemble.manifest))
        with signals.held():
            arm, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ensemble, metrics=metrics, arm=arm, gripper=gripper, notifier=Notifier())
        daemon.recorder = recorder
        if recorder is not None:
            from slipd.daemon.recording_context import attach

            attach(recorder, daemon)  # the recordings carry the reactions
        start_taps(cfg, daemon, str(config_path))
    except BaseException:
        close_quietly(arm, gripper)  # opened, then a stop or a failure before the daemon took them over
        if recorder is not None:
            recorder.close()
        if server is not None:
            server.shutdown()
            server.server_close()
        native.close()
        raise
    return Service(cfg, daemon, metrics, native, server, Path(config_path))


__all__ = ["DeviceError", "ResourceError", "Service", "StopRequested", "prepare"]
