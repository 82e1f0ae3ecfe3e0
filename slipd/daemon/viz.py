"""The live view: a Foxglove WebSocket server (``foxglove-sdk``) with the channels of an MCAP recording, live.

The same channels and schemas as a recording (``slipd.recording_mcap``): ``/slipd/frames/s<S>`` decimated to
``viz.frame_rate_hz`` per sensor, the pillar arrows ``/slipd/pillars/s<S>`` at most ``SCENE_HZ`` a second, every
decision on ``/slipd/decisions``, alarms on ``/slipd/events``; so the layout ``deploy/foxglove/slipd.json`` shows a
live daemon as it shows a recording. Message times are the computer's clock.

Threads: the loop's ``on_block`` and ``on_decision`` copy what is due into a bounded queue (``viz.queue``; the
oldest is dropped and counted when it is full); the ``slipd-viz`` thread takes it every ``POLL_S``, builds the JSON
messages for the channels a viewer subscribed to (none while nobody watches) and hands them to the SDK. The SDK's
server runs on its own threads and keeps a bounded backlog per client, dropping what a client does not read: a
client that is slow or never reads costs the loop nothing (``tools/bench_daemon.py --viz``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from slipd.recording_mcap import (
    SCHEMAS,
    TOPIC_DECISIONS,
    TOPIC_EVENTS,
    TOPIC_FRAMES,
    TOPIC_PILLARS,
    decision_message,
    frame_message,
    pillar_scene,
    schema_of,
)

if TYPE_CHECKING:
    from slipd.config import VizConfig
    from slipd.detect.decision import Detection
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.viz")

POLL_S = 0.05
"""The ``viz`` thread sends what the loop queued this often."""
SCENE_HZ = 10.0
"""Pillar-arrow messages a second and sensor, at most."""
STOP_TIMEOUT_S = 1.0
"""How long closing waits for the server to stop."""
BACKLOG = 256
"""Messages the server keeps per client that has not read them; beyond it the client loses the oldest."""


class LiveView:
    """A tap (``slipd.daemon.taps``) that serves frames and decisions to Foxglove from its own thread."""

    def __init__(self, cfg: VizConfig, sensors: int = 1, rate_hz: float = 1000.0,
                 threshold: float | None = None, metrics: Metrics | None = None) -> None:
        self.cfg = cfg
        self.sensors = sensors
        self.threshold = threshold
        self.every = max(1, round(rate_hz / cfg.frame_rate_hz))
        """One frame in this many samples goes to the view."""
        self.scene_every = max(self.every, round(rate_hz / SCENE_HZ))
        """One pillar-arrows message in this many samples (at most ``SCENE_HZ`` a second: the 3D panel's arrows cost
        more to build and draw than a plot's points)."""
        self.queue: deque[tuple[Any, ...]] = deque(maxlen=cfg.queue)
        self.dropped = 0
        """Items dropped from a full queue (the ``slipd-viz`` thread fell behind; ``slipd_tap_dropped_total``)."""
        self._m_dropped = metrics.tap_dropped.labels(tap="viz") if metrics is not None else None
        self.sent = 0
        self.errors = 0
        self._samples = 0
        self._stop = threading.Event()
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run, name="slipd-viz", daemon=True)
        self.port: int | None = None

    def start(self) -> LiveView:
        """Start the WebSocket server (``viz.host``:``viz.port``), its channels and the ``slipd-viz`` thread."""
        import foxglove

        ctx = self._context = foxglove.Context()  # kept: the channels and the server live in it
        topics = [TOPIC_FRAMES.format(s) for s in range(self.sensors)] + [TOPIC_DECISIONS, TOPIC_EVENTS]
        topics += [TOPIC_PILLARS.format(s) for s in range(self.sensors)]
        for topic in topics:
            name = schema_of(topic)
            schema = foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode())
            self._channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="json", context=ctx)
        self._server = foxglove.start_server(name="slipd", host=self.cfg.host, port=self.cfg.port, context=ctx,
                                             message_backlog_size=BACKLOG)
        self.port = int(self._server.port)
        self._thread.start()
        log.info("viz: Foxglove live view on ws://%s:%d", self.cfg.host, self.port)
        return self

    # ------------------------------------------------------------------ the loop's side
    def _put(self, item: tuple[Any, ...]) -> None:
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1  # the deque drops its oldest on append
            if self._m_dropped is not None:
                self._m_dropped.inc()
        self.queue.append(item)

    def on_block(self, t_us: np.ndarray, force: np.ndarray, disp: np.ndarray) -> None:
        """Queue the block's frames that are due (one in ``every`` samples), copied."""
        k = len(t_us)
        base = self._samples
        first = (-base) % self.every
        self._samples += k
        if first < k:
            now = time.time_ns()
            for j in range(first, k, self.every):
                self._put(("frame", now, base + j, int(t_us[j]), force[j].copy(), disp[j].copy()))

    def on_decision(self, det: Detection, force: np.ndarray) -> None:
        """Queue one decision."""
        c = det.contact
        self._put(("decision", time.time_ns(), {
            "t_us": det.t_us, "sensor": det.sensor, "p_slip": det.p_slip, "alarm": det.alarm, "risk": det.risk,
            "pillar_slip": None if c is None else c.pillar_slip, "contact_risk": None if c is None else c.risk,
            "friction": None if c is None else c.friction}, det.rising_edge))

    def close(self) -> None:
        """Stop the thread and the server."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if self._server is not None:
            # The SDK's stop waits for each viewer's connection to close, which a viewer that stopped reading never
            # lets happen: it runs on a thread of its own, given STOP_TIMEOUT_S, and the daemon exits without it.
            stopper = threading.Thread(target=self._stop_server, args=(self._server,), name="slipd-viz-stop",
                                       daemon=True)
            stopper.start()
            stopper.join(STOP_TIMEOUT_S)
            if stopper.is_alive():
                log.warning("viz: the Foxglove server did not stop within %.0f s (a viewer that does not read); "
                            "exiting without it", STOP_TIMEOUT_S)
            self._server = None

    @staticmethod
    def _stop_server(server: Any) -> None:
        try:
            server.stop()
        except Exception:
            log.debug("viz: server stop failed", exc_info=True)

    # ------------------------------------------------------------------ the viz thread
    def _log(self, topic: str, msg: dict[str, Any], t_ns: int) -> None:
        self._channels[topic].log(json.dumps(msg, separators=(",", ":")).encode(), log_time=t_ns)
        self.sent += 1

    def _watched(self, topic: str) -> bool:
        """Whether a viewer subscribed to ``topic`` (no message is built for a channel nobody watches)."""
        return bool(self._channels[topic].has_sinks())

    def _run(self) -> None:
        while True:
            # Every POLL_S, not at each block: a person watches at this rate, and the loop pays no wake-up per block.
            self._stop.wait(POLL_S)
            try:
                while self.queue:
                    item = self.queue.popleft()
                    if item[0] == "frame":
                        _, t_ns, sample, t_us, force, disp = item
                        for s in range(self.sensors):
                            topic = TOPIC_FRAMES.format(s)
                            if self._watched(topic):
                                self._log(topic, frame_message(t_us, sample, s, force[s], disp[s]), t_ns)
                            if sample % self.scene_every < self.every and self._watched(TOPIC_PILLARS.format(s)):
                                self._log(TOPIC_PILLARS.format(s), pillar_scene(t_us, s, force[s]), t_ns)
                    else:
                        _, t_ns, row, rising = item
                        if self._watched(TOPIC_DECISIONS):
                            self._log(TOPIC_DECISIONS, decision_message(row, self.threshold), t_ns)
                        if rising and self._watched(TOPIC_EVENTS):
                            self._log(TOPIC_EVENTS, {"timestamp": {"sec": t_ns // 10**9, "nsec": t_ns % 10**9},
                                                     "level": 3, "name": "slipd", "file": "", "line": 0,
                                                     "message": f"alarm: sensor {row['sensor']} p_slip "
                                                                f"{row['p_slip']:.3f}"}, t_ns)
            except Exception:
                self.errors += 1
                if self.errors == 1 or self.errors % 1000 == 0:
                    log.exception("viz: sending failed (%d failures)", self.errors)
            if self._stop.is_set() and not self.queue:
                return
