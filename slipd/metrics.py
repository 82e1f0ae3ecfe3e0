"""Prometheus metrics: one registry, every metric object of slipd, base units, ``slipd_`` prefix.

Modules import the objects they update from here; nothing else creates metrics. The registry is
private (not prometheus_client's global one) so tests can create several daemons in one process.

Per-finger metrics carry a ``sensor`` label, "0" or "1" (``sensor.sensors`` arrays; bounded by the
config: never a value from the wire).
"""

from __future__ import annotations

from bisect import bisect_left
from collections.abc import Callable, Iterable, Sequence
from itertools import accumulate
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info, start_http_server
from prometheus_client.core import CounterMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.utils import floatToGoString

if TYPE_CHECKING:
    from wsgiref.simple_server import WSGIServer

_go_float: Callable[[float], str] = floatToGoString
"""A bucket bound as prometheus_client's ``Histogram`` writes it in ``le``."""

# Sub-millisecond buckets: a 1 kHz loop and a 25 Hz model step are judged in tens of microseconds.
FAST_BUCKETS = (
    25e-6, 50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6,
    1e-3, 1.5e-3, 2e-3, 3e-3, 5e-3, 7.5e-3, 10e-3, 25e-3, 50e-3, 0.1,
)

TAPS = ("ros2", "viz")
"""The live taps (``slipd_tap_dropped_total{tap}``): the ROS 2 publisher and the live view in Foxglove."""
RECORDING_FAILURES = ("no_space", "read_only", "permission", "io", "backlog")
"""Why a recording was lost (``slipd_recordings_failed_total{reason}``): the disk full, the file system read-only,
no permission, another I/O error, or more writes pending than ``Recorder.max_pending``."""


class DecisionHistogram:
    """A histogram observed on every decision: ``observe`` costs a bisection and two additions, and the registry reads
    the numbers when it is scraped (a collector; the same series as a ``Histogram``'s, without ``_created``).

    prometheus_client's ``Histogram`` takes one lock for the sum and one for the bucket, and checks its state, on every
    observation: about a microsecond, twice per decision, against a scrape every few seconds. Only the loop's thread
    observes; a scrape reads plain numbers, each whole, so it sees every observation made before it (the one under way
    in its bucket perhaps, not yet in the sum)."""

    def __init__(self, name: str, documentation: str, buckets: Sequence[float], registry: CollectorRegistry) -> None:
        self._name, self._doc = name, documentation
        self._bounds = tuple(float(b) for b in buckets)
        self._le = [_go_float(b) for b in self._bounds] + ["+Inf"]
        self._counts = [0] * (len(self._bounds) + 1)  # per bucket, not cumulative: [-inf, b0], (b0, b1], ..., (bn, inf)
        self._sum = 0.0
        registry.register(self)

    def observe(self, amount: float) -> None:
        """One observation (seconds)."""
        self._counts[bisect_left(self._bounds, amount)] += 1  # the first bound at or above it: le semantics
        self._sum += amount

    def collect(self) -> Iterable[Metric]:
        """The series for a scrape: cumulative buckets, the count and the sum."""
        total = self._sum
        buckets = list(zip(self._le, accumulate(list(self._counts)), strict=True))
        return [HistogramMetricFamily(self._name, self._doc, buckets=buckets, sum_value=total)]

    def describe(self) -> Iterable[Metric]:
        """The series' names, for the registry's check against duplicates."""
        return [HistogramMetricFamily(self._name, self._doc)]


class DecisionCount:
    """One label value's count of a ``DecisionCounter``."""

    def __init__(self) -> None:
        self.value = 0.0

    def inc(self, amount: float = 1.0) -> None:
        """Count ``amount`` (>= 0) more."""
        self.value += amount


class DecisionCounter:
    """A counter with one label, incremented on every decision: ``labels(value)`` once (the daemon keeps the child),
    then ``inc`` adds to a plain number; the registry reads the numbers when it is scraped (a collector; the series of a
    ``Counter``, ``_total``, without ``_created``). prometheus_client's ``Counter`` takes a lock and checks its state on
    every ``inc``; only the loop's thread counts, and a scrape reads each number whole."""

    def __init__(self, name: str, documentation: str, label: str, registry: CollectorRegistry) -> None:
        self._name, self._doc, self._label = name, documentation, label
        self._children: dict[str, DecisionCount] = {}
        registry.register(self)

    def labels(self, **values: str) -> DecisionCount:
        """The child of one label value (made on first use, served from then on, at 0 until counted)."""
        if list(values) != [self._label]:
            raise ValueError(f"{self._name} has one label, {self._label}; got {sorted(values)}")
        return self._children.setdefault(str(values[self._label]), DecisionCount())

    def collect(self) -> Iterable[Metric]:
        """The series for a scrape, one per label value."""
        family = CounterMetricFamily(self._name, self._doc, labels=[self._label])
        for value, child in list(self._children.items()):
            family.add_metric([value], child.value)
        return [family]

    def describe(self) -> Iterable[Metric]:
        """The series' names, for the registry's check against duplicates."""
        return [CounterMetricFamily(self._name, self._doc, labels=[self._label])]


class Metrics:
    """All metric objects of one daemon, on one registry."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        r = self.registry = registry or CollectorRegistry()
        self.frames = Counter("slipd_frames_received", "Sensor frames decoded", registry=r)
        self.frame_errors = Counter(
            "slipd_frame_errors", "Corrupt sensor input by kind", ["kind"], registry=r
        )
        self.garbage_bytes = Counter("slipd_garbage_bytes", "Serial bytes skipped while resynchronising", registry=r)
        self.dropped_frames = Counter(
            "slipd_dropped_frames", "Frames missing according to the packet counter", registry=r
        )
        self.frames_discarded_at_start = Counter(
            "slipd_frames_discarded_at_start",
            "Frames missing by the packet counter before the first live decision (the controller streamed before the "
            "port was open, or while the daemon started): not losses of a running daemon",
            registry=r,
        )
        self.sensor_rate = Gauge(
            "slipd_sensor_rate_hz", "Stream rate measured from the controller's clock and packet counter (0: not yet)",
            registry=r,
        )
        self.timestamp_jumps = Counter(
            "slipd_timestamp_jumps", "Controller timestamps that ran backwards or jumped ahead of the packet counter",
            ["kind"], registry=r,
        )
        for kind in ("backwards", "forward"):
            self.timestamp_jumps.labels(kind=kind)
        self.recordings_failed = Counter(
            "slipd_recordings_failed", "Recordings lost, by reason (no_space, read_only, permission, io, backlog)",
            ["reason"], registry=r,
        )
        for reason in RECORDING_FAILURES:
            self.recordings_failed.labels(reason=reason)
        self.tap_dropped = Counter(
            "slipd_tap_dropped", "Messages a live tap (ros2, viz) dropped from its full queue: its thread fell behind "
            "the loop (the loop itself loses nothing)", ["tap"], registry=r,
        )
        for tap in TAPS:
            self.tap_dropped.labels(tap=tap)
        self.reconnects = Counter("slipd_reconnects", "Sensor reconnections", ["device"], registry=r)
        self.rezeros = Counter(
            "slipd_sensor_rezeros", "Software zeros in free air after a bias the sensor took under a grasp", registry=r
        )
        self.nonfinite = Counter(
            "slipd_nonfinite_values",
            "Non-finite or impossible (beyond twice the range) sensor values replaced or clipped",
            registry=r,
        )
        self.step_errors = Counter(
            "slipd_model_step_errors", "Windows that produced no decision (refused or non-finite output)", ["sensor"],
            registry=r,
        )
        # Observed or counted on every decision: the decision path's own collectors (see ``DecisionHistogram``).
        self.loop_seconds = DecisionHistogram(
            "slipd_loop_duration_seconds", "Work per control-loop iteration", FAST_BUCKETS, r
        )
        self.inference_seconds = DecisionHistogram(
            "slipd_inference_duration_seconds", "Ensemble step time", FAST_BUCKETS, r
        )
        self.reaction_seconds = Histogram(
            "slipd_reaction_latency_seconds",
            "Alarm decision to reaction command sent",
            buckets=FAST_BUCKETS,
            registry=r,
        )
        self.overruns = Counter(
            "slipd_loop_overruns", "Supervision ticks later than control.max_overrun_ms past their deadline", registry=r
        )
        self.p_slip = Gauge("slipd_slip_probability", "Latest ensemble slip probability", ["sensor"], registry=r)
        self.risk = Gauge("slipd_slip_risk", "Continuous slip risk level (0..1)", ["sensor"], registry=r)
        self.alarms = Counter("slipd_alarms", "Incipient-slip alarms raised", ["sensor"], registry=r)
        self.contact_risk = Gauge(
            "slipd_contact_risk", "Load-weighted share of the contact slipping or near its friction limit (0..1)",
            ["sensor"], registry=r,
        )
        self.friction = Gauge(
            "slipd_friction_estimate", "Friction coefficient estimated from the sliding pillars (0: none seen yet)",
            ["sensor"], registry=r,
        )
        self.pillar_slip = Gauge(
            "slipd_pillar_slip_probability", "Per-pillar slip probability (pillar 0..8, SDK order)",
            ["sensor", "pillar"], registry=r,
        )
        self.grip_target = Gauge(
            "slipd_grip_target_newtons", "Grip force commanded by reaction.policy grip_control (0: not commanding)",
            registry=r,
        )
        self.grip_stops = Counter(
            "slipd_grip_arm_stops", "Arm stops by reaction.policy grip_control, by reason (risk, limit, twist)",
            ["reason"], registry=r,
        )
        for reason in ("risk", "limit", "twist"):  # the bounded reasons, served at 0 from the start
            self.grip_stops.labels(reason=reason)
        self.decisions = DecisionCounter("slipd_decisions", "Model decisions made", "sensor", r)
        self.failsafe = Counter("slipd_failsafe_stops", "Fail-safe arm stops by reason", ["reason"], registry=r)
        self.device_errors = Counter(
            "slipd_device_errors", "Errors talking to a device", ["device", "kind"], registry=r
        )
        self.ready = Gauge("slipd_ready", "1 once warm-up is done and the loop runs", registry=r)
        self.live = Gauge(
            "slipd_live", "1 while decisions are live (a valid decision on fresh sensor data within the stall "
            "timeout); 0 before the first one and while blind", registry=r,
        )
        self.model = Info("slipd_model", "Loaded model (name, sha256)", registry=r)

    def serve(self, host: str = "127.0.0.1", port: int = 9477) -> WSGIServer:
        """Start the HTTP endpoint in a daemon thread; returns the server (``.shutdown()`` to stop)."""
        server, _thread = start_http_server(port, addr=host, registry=self.registry)
        return server
