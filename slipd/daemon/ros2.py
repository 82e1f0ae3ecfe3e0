"""Slip events on ROS 2 over Zenoh, as rmw_zenoh publishes them: a ROS 2 node subscribes with no bridge.

Topics (relative to ``ros2.namespace``), CDR payloads (``rosbags`` serialises them):

    slip/alarm        std_msgs/msg/Bool                  the alarm of any finger, at every decision
    slip/p_slip       std_msgs/msg/Float32               the highest fused P(slip) of the fingers' latest decisions
    slip/map          std_msgs/msg/Float32MultiArray     the slip map: [sensors, 9] P(slip) per pillar (NaN: none yet)
    slip/wrench/s<S>  geometry_msgs/msg/WrenchStamped    finger S's total force (N) and torque (N m) about the sensor
                                                          centre, on the frame it decided on
    /diagnostics      diagnostic_msgs/msg/DiagnosticArray  liveness, decisions, messages published and dropped

Key expressions and liveliness tokens follow rmw_zenoh_cpp 0.2 (the ROS 2 Jazzy releases; its docs/design.md):

    data:      <domain_id>/<topic without its leading />/<pkg>::msg::dds_::<Type>_/<RIHS01_ type hash>
    node:      @ros2_lv/<domain_id>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    publisher: @ros2_lv/<domain_id>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node name>/<topic>/<type>/
               <type hash>/<qos>

with every ``/`` inside a chunk written as ``%`` (an empty namespace or enclave is ``%``), the QoS as rmw_zenoh writes
it (each field left empty when it is rmw_zenoh's default; here reliable, volatile, keep-last 10: ``::,10:,:,:,,``),
and each sample's attachment: sequence number and source time in ns (int64 little-endian each), then the 16-byte
publisher GID behind its length (one byte, 16).

Threads: the loop's ``on_decision`` puts a small tuple into a bounded queue (``ros2.queue``; the oldest is dropped
and counted when it is full), and the end of its block (``on_block``) wakes the ``slipd-ros2`` thread, which
serialises and publishes. Nothing here blocks the loop: a network that stalls fills the queue, and the loop goes on.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from slipd.geometry import PILLAR_XY_MM

if TYPE_CHECKING:
    from slipd.config import Ros2Config
    from slipd.detect.decision import Detection
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.ros2")

QOS_KEY = "::,10:,:,:,,"
"""Reliable, volatile, keep last 10: rmw_zenoh's defaults but for the depth (its default is 42)."""
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
TYPES = {
    "alarm": "std_msgs/msg/Bool",
    "p_slip": "std_msgs/msg/Float32",
    "map": "std_msgs/msg/Float32MultiArray",
    "wrench": "geometry_msgs/msg/WrenchStamped",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
LEVEL_OK, LEVEL_WARN, LEVEL_ERROR = 0, 1, 2


@dataclass
class Health:
    """The daemon's state for the diagnostics message (read on the ``slipd-ros2`` thread)."""

    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)


def mangle(name: str) -> str:
    """A name as one chunk of a liveliness key expression: ``/`` becomes ``%``; empty becomes ``%``."""
    return name.replace("/", "%") or "%"


def dds_type(ros_type: str) -> str:
    """``std_msgs/msg/Bool`` -> ``std_msgs::msg::dds_::Bool_`` (the type name rmw_zenoh puts in key expressions)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_name(namespace: str, name: str) -> str:
    """The fully qualified topic name of ``name`` in ``namespace`` (an absolute ``name`` stays as it is)."""
    return name if name.startswith("/") else f"{namespace}/{name}"


def topic_key(domain_id: int, fqn: str, ros_type: str, type_hash: str) -> str:
    """The key expression of a topic's samples."""
    return f"{domain_id}/{fqn.lstrip('/')}/{dds_type(ros_type)}/{type_hash}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness token of a node."""
    return f"@ros2_lv/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{node}"


def publisher_token(domain_id: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str, fqn: str,
                    ros_type: str, type_hash: str, qos: str = QOS_KEY) -> str:
    """The liveliness token of a publisher."""
    return (f"@ros2_lv/{domain_id}/{zid}/{node_id}/{entity_id}/MP/%/{mangle(namespace)}/{node}/{mangle(fqn)}/"
            f"{dds_type(ros_type)}/{type_hash}/{qos}")


def attachment(sequence: int, t_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment: sequence, source time (ns), the publisher's GID (length-prefixed)."""
    return struct.pack("<qqB", sequence, t_ns, len(gid)) + gid


def finger_wrench(force: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Total force (N) and torque (N m) about the sensor centre of one finger's pillars ([9, 3], N)."""
    f = force.astype(np.float64)
    x, y = PILLAR_XY_MM[:, 0] / 1e3, PILLAR_XY_MM[:, 1] / 1e3
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    torque = ((y * fz).sum(), (-x * fz).sum(), (x * fy - y * fx).sum())
    return (float(fx.sum()), float(fy.sum()), float(fz.sum())), (float(torque[0]), float(torque[1]),
                                                                  float(torque[2]))


class Messages:
    """Builds and serialises the ROS 2 messages (``rosbags``' type store of ROS 2 Jazzy)."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.t = self.store.types

    def type_hash(self, ros_type: str) -> str:
        return str(self.store.hash_rihs01(ros_type))

    def cdr(self, msg: Any, ros_type: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, ros_type))

    def decode(self, data: bytes, ros_type: str) -> Any:
        return self.store.deserialize_cdr(data, ros_type)

    def header(self, t_ns: int, frame_id: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def bool_(self, v: bool) -> bytes:
        return self.cdr(self.t["std_msgs/msg/Bool"](data=bool(v)), TYPES["alarm"])

    def float32(self, v: float) -> bytes:
        return self.cdr(self.t["std_msgs/msg/Float32"](data=float(v)), TYPES["p_slip"])

    def slip_map(self, values: np.ndarray) -> bytes:
        s, n = values.shape
        dim = self.t["std_msgs/msg/MultiArrayDimension"]
        layout = self.t["std_msgs/msg/MultiArrayLayout"](
            dim=[dim(label="sensor", size=s, stride=s * n), dim(label="pillar", size=n, stride=n)], data_offset=0)
        msg = self.t["std_msgs/msg/Float32MultiArray"](layout=layout, data=values.astype(np.float32).ravel())
        return self.cdr(msg, TYPES["map"])

    def wrench(self, t_ns: int, frame_id: str, force: np.ndarray) -> bytes:
        (fx, fy, fz), (tx, ty, tz) = finger_wrench(force)
        v3 = self.t["geometry_msgs/msg/Vector3"]
        w = self.t["geometry_msgs/msg/Wrench"](force=v3(x=fx, y=fy, z=fz), torque=v3(x=tx, y=ty, z=tz))
        msg = self.t["geometry_msgs/msg/WrenchStamped"](header=self.header(t_ns, frame_id), wrench=w)
        return self.cdr(msg, TYPES["wrench"])

    def diagnostics(self, t_ns: int, health: Health) -> bytes:
        kv = self.t["diagnostic_msgs/msg/KeyValue"]
        status = self.t["diagnostic_msgs/msg/DiagnosticStatus"](
            level=health.level, name="slipd: incipient slip detection", message=health.message,
            hardware_id="papillarray", values=[kv(key=k, value=v) for k, v in health.values.items()])
        msg = self.t["diagnostic_msgs/msg/DiagnosticArray"](header=self.header(t_ns, ""), status=[status])
        return self.cdr(msg, TYPES["diagnostics"])


def session_config(mode: str, connect: list[str], listen: list[str]) -> Any:
    """A zenoh session configuration: multicast scouting off (as rmw_zenoh's default: the router tells peers about
    each other), the given endpoints."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    return conf


class Ros2Publisher:
    """A tap (``slipd.daemon.taps``) that publishes the loop's decisions as ROS 2 messages on its own thread."""

    def __init__(self, cfg: Ros2Config, sensors: int = 1, health: Callable[[], Health] | None = None,
                 metrics: Metrics | None = None) -> None:
        self.cfg = cfg
        self.sensors = sensors
        self.health = health
        self.queue: deque[tuple[Any, ...]] = deque(maxlen=cfg.queue)
        self.dropped = 0
        """Decisions dropped from a full queue (the ``slipd-ros2`` thread fell behind; ``slipd_tap_dropped_total``)."""
        self._m_dropped = metrics.tap_dropped.labels(tap="ros2") if metrics is not None else None
        self.published = 0
        self.errors = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._map = np.full((sensors, 9), np.nan, np.float32)
        self._p = np.zeros(sensors)
        self._alarm = np.zeros(sensors, bool)
        self._seq = 0
        self.msgs = Messages()
        self._session: Any = None
        self._pubs: dict[str, tuple[Any, bytes]] = {}
        self._tokens: list[Any] = []
        self.keys: dict[str, str] = {}
        """Topic -> key expression of its samples."""
        self.tokens: list[str] = []
        """The liveliness tokens declared (node first)."""
        self._thread = threading.Thread(target=self._run, name="slipd-ros2", daemon=True)

    # ------------------------------------------------------------------ set-up
    def start(self) -> Ros2Publisher:
        """Open the zenoh session, declare the node, its publishers and their liveliness tokens, start the thread."""
        import zenoh

        cfg = self.cfg
        self._session = zenoh.open(session_config(cfg.mode, cfg.connect, cfg.listen))
        zid = str(self._session.zid())
        ns, node = cfg.namespace, cfg.node_name
        names = {"alarm": "slip/alarm", "p_slip": "slip/p_slip", "map": "slip/map", "diagnostics": "/diagnostics"}
        names.update({f"wrench{s}": f"slip/wrench/s{s}" for s in range(self.sensors)})
        node_tok = node_token(cfg.domain_id, zid, 0, ns, node)
        self.tokens.append(node_tok)
        self._tokens.append(self._session.liveliness().declare_token(node_tok))
        for eid, (what, name) in enumerate(names.items(), start=1):
            ros_type = TYPES["wrench" if what.startswith("wrench") else what]
            h = self.msgs.type_hash(ros_type) if cfg.type_hashes else HASH_NOT_SUPPORTED
            fqn = topic_name(ns, name)
            key = topic_key(cfg.domain_id, fqn, ros_type, h)
            self.keys[fqn] = key
            self._pubs[what] = (self._session.declare_publisher(key), os.urandom(16))
            tok = publisher_token(cfg.domain_id, zid, 0, eid, ns, node, fqn, ros_type, h)
            self.tokens.append(tok)
            self._tokens.append(self._session.liveliness().declare_token(tok))
        self._thread.start()
        log.info("ros2: publishing %s on domain %d as node %s/%s (zenoh %s, connect %s)", ", ".join(self.keys),
                 cfg.domain_id, ns, node, cfg.mode, cfg.connect)
        return self

    # ------------------------------------------------------------------ the loop's side
    def on_block(self, t_us: np.ndarray, force: np.ndarray, disp: np.ndarray) -> None:
        """Wake the ``slipd-ros2`` thread for the block's decisions (frames are not published on ROS 2: the decisions
        carry what a ROS node acts on)."""
        if self.queue:
            self._wake.set()

    def on_decision(self, det: Detection, force: np.ndarray) -> None:
        """Queue one decision (a copy of its frame's forces); ``on_block`` wakes the ``slipd-ros2`` thread."""
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1  # the deque drops its oldest on append
            if self._m_dropped is not None:
                self._m_dropped.inc()
        pill = det.contact.pillar_slip if det.contact is not None else None
        self.queue.append((time.time_ns(), det.sensor, det.p_slip, det.alarm, pill, force.copy()))

    def close(self) -> None:
        """Stop the thread (it publishes what is queued first), withdraw the tokens, close the session."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for tok in self._tokens:
            try:
                tok.undeclare()
            except Exception:  # a session already gone: the tokens went with it
                log.debug("ros2: token undeclare failed", exc_info=True)
        self._tokens.clear()
        if self._session is not None:
            try:
                self._session.close()
            except Exception:
                log.debug("ros2: session close failed", exc_info=True)
            self._session = None

    # ------------------------------------------------------------------ the ros2 thread
    def _put(self, what: str, payload: bytes, t_ns: int) -> None:
        pub, gid = self._pubs[what]
        self._seq += 1
        pub.put(payload, attachment=attachment(self._seq, t_ns, gid))
        self.published += 1

    def _run(self) -> None:
        period = self.cfg.diagnostics_period_s
        next_diag = time.monotonic()
        while True:
            self._wake.wait(timeout=max(0.0, next_diag - time.monotonic()))
            self._wake.clear()
            try:
                while self.queue:
                    self._publish(*self.queue.popleft())
                if time.monotonic() >= next_diag:
                    next_diag = time.monotonic() + period
                    self._put("diagnostics", self.msgs.diagnostics(time.time_ns(), self._health()), time.time_ns())
            except Exception:
                self.errors += 1
                if self.errors == 1 or self.errors % 1000 == 0:
                    log.exception("ros2: publishing failed (%d failures)", self.errors)
            if self._stop.is_set() and not self.queue:
                return

    def _publish(self, t_ns: int, sensor: int, p: float, alarm: bool, pill: tuple[float, ...] | None,
                 force: np.ndarray) -> None:
        self._p[sensor], self._alarm[sensor] = p, alarm
        # The alarm first: it is what a subscriber acts on.
        self._put("alarm", self.msgs.bool_(bool(self._alarm.any())), t_ns)
        self._put("p_slip", self.msgs.float32(float(self._p.max())), t_ns)
        if pill is not None:
            self._map[sensor] = pill
            self._put("map", self.msgs.slip_map(self._map), t_ns)
        self._put(f"wrench{sensor}", self.msgs.wrench(t_ns, f"{self.cfg.frame_id}{sensor}", force), t_ns)

    def _health(self) -> Health:
        h = self.health() if self.health is not None else Health(LEVEL_OK, "running")
        values = dict(h.values)
        values.update(published=str(self.published), dropped=str(self.dropped), errors=str(self.errors))
        level = h.level if not self.dropped else max(h.level, LEVEL_WARN)
        return Health(level, h.message, values)


def daemon_health(daemon: Any) -> Health:
    """The daemon's liveness for the diagnostics (attributes the loop writes; read here without a lock: each read is
    one attribute, and a stale value is one diagnostics period old)."""
    stats = daemon.stats
    values = {"decisions": str(stats.decisions), "alarms": str(stats.alarm_count), "failsafes": str(stats.failsafes),
              "frames": str(stats.frames)}
    if daemon.live:
        return Health(LEVEL_OK, "live", values)
    if daemon.blind is not None:
        return Health(LEVEL_ERROR, f"blind: {daemon.blind}", values)
    return Health(LEVEL_WARN, "starting", values)
