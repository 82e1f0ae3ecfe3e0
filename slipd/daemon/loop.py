"""The daemon: one asyncio loop from sensor frames to arm and gripper commands.

Start-up order is fail-safe: the configuration and the model (manifest, hash, shapes, feature
layout) are checked, the session warmed up, and only then are devices opened. A broken config or
model therefore never touches hardware (exit codes in ``slipd.cli``).

The hot path is event-driven: the sensor reader (``slipd.io.sensor``) calls ``_on_frames`` on the loop
thread as soon as bytes arrive, with the frames of the read as arrays (``slipd.io.pts.FrameBlock``: no
object per frame); each block goes through the shared ``Detector`` (features -> ensemble -> decision) in
one call and, on a rising alarm edge, ``Reaction`` hands the arm stop and the gripper tighten to their
device threads at once. Nothing on this path blocks. With two sensors (``sensor.sensors: 2``, one array
per finger) each finger has its own decisions and a rising edge on either reacts.

A supervision task (``slipd.daemon.liveness``) runs on absolute deadlines and owns **liveness**, defined once
there (``Liveness.blind_cause``): a valid decision on a window of fresh samples within the stall timeout
(``sensor.stall_timeout_ms``). A sample is fresh when its packet counter advanced (repeats are dropped by
the reader), every value the detector reads is finite and it is not bit-identical to the one before (a real sensor is
never noise-free). Blind causes, each failing safe (stop the arm, keep the grip) once per episode with
one log line and ``slipd_failsafe_stops_total{reason=...}``: ``sensor_lost`` (port gone),
``sensor_silent`` (no frame since start-up), ``sensor_stall`` (frames stopped), ``sensor_counter_stuck``,
``sensor_frozen`` (frames arrive, none fresh), ``rate`` (the stream's rate by the controller's own clock and
counter is not the model's, ``slipd.daemon.rate``; at start-up the daemon is not live before it was measured),
``sensor_nonfinite`` (non-finite samples for longer than
``NONFINITE_BRIDGE_S``, what the feature stage may bridge by holding the last value) and
``no_decisions`` (fresh frames, but no valid decision when one was due; when the frames that decision needed
never all came, the stream stopped short of it: ``sensor_stall``). With two sensors every rule holds
per finger: fresh samples and valid decisions are needed on both, and a blind finger is a blind daemon
(the detail names the sensor). An episode ends with the first
valid decision on fresh data; a loss followed by a stall is one episode, one stop. Only while live is
the systemd watchdog pinged and the arm's controller-side watchdog (ur_rtde ``kickWatchdog``) kicked, so
a wedged or dead loop, or a blind one, halts the arm; ``READY=1`` goes out with the first live decision.

Beside the loop, in modules of their own: the device health task (``slipd.daemon.health``: polls, reconnects, a
gripper fault), the stream's rate and timestamps (``slipd.daemon.rate``: the ``rate`` cause above), the software zero
after a bias under a grasp (``slipd.daemon.rezero``); around it, the start-up checks (``slipd.daemon.preflight``),
signals (``slipd.daemon.signals``) and reloads (``slipd.daemon.reload``).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from slipd.daemon.devices import close_quietly
from slipd.daemon.grip_control import GripControlSettings
from slipd.daemon.health import GRIPPER_HEALTH_PERIOD_S, HEALTH_PERIOD_S, DeviceHealth
from slipd.daemon.liveness import Liveness
from slipd.daemon.rate import RateMonitor
from slipd.daemon.reaction import Reaction
from slipd.daemon.rezero import LoadedZero
from slipd.daemon.worker import DeviceWorker
from slipd.detect.build import build_detector
from slipd.detect.contact import grasp_state
from slipd.detect.detector import SlipDetector
from slipd.geometry import CONTACT_THRESHOLD_N
from slipd.metrics import Metrics

if TYPE_CHECKING:
    from slipd.config import SlipdConfig
    from slipd.config.schema import DecisionConfig
    from slipd.daemon.recorder import Recorder
    from slipd.daemon.sdnotify import Notifier
    from slipd.daemon.taps import Tap
    from slipd.detect.contact import ContactState
    from slipd.detect.decision import Detection
    from slipd.detect.ensemble import Ensemble
    from slipd.io.arm import Arm
    from slipd.io.gripper import DynamixelGripper
    from slipd.io.pts import FrameBlock

log = logging.getLogger("slipd.daemon.loop")

# How long ``Daemon.close`` waits for a device's thread to finish its queued calls and close the device.
DEVICE_CLOSE_TIMEOUT_S = 5.0
"""How long ``close`` waits for the device threads, all of them together: well under systemd's ``TimeoutStopSec``
(10 s), so that a hung device is left behind and the process still exits before it is killed."""


NONFINITE_BRIDGE_S = 0.005
"""Non-finite samples the feature stage may bridge (it holds the last finite value): a few ms. Longer
runs make every decision one on a frozen picture of the grasp, so liveness fails."""
MAX_KEPT = 256
"""Alarms kept in ``LoopStats.alarms`` (the oldest are dropped): the daemon's state stays bounded. A recording's
context needs only the alarms of its own few seconds; ``alarm_count`` and ``slipd_alarms_total`` count them all."""


@dataclass
class LoopStats:
    """Counters of one daemon run (also exported as metrics)."""

    frames: int = 0
    decisions: int = 0
    alarms: deque[tuple[int, int, float, int]] = field(default_factory=lambda: deque(maxlen=MAX_KEPT))
    """(sample index since start, sensor t_us, monotonic time of the decision, sensor) per rising edge; the
    latest ``MAX_KEPT`` (``alarm_count`` and ``slipd_alarms_total`` count them all)."""
    alarm_count: int = 0
    overruns: int = 0
    failsafes: int = 0
    restarts: int = 0
    step_errors: int = 0
    health_polls: int = 0


class Daemon:
    """Owns the detector, the devices and the loop. Build with ``Daemon.build(cfg)``; run with ``await run()``."""

    def __init__(
        self,
        cfg: SlipdConfig,
        ensemble: Ensemble,
        *,
        metrics: Metrics | None = None,
        arm: Arm | None = None,
        gripper: DynamixelGripper | None = None,
        notifier: Notifier | None = None,
        health_period_s: float = HEALTH_PERIOD_S,
        gripper_health_period_s: float = GRIPPER_HEALTH_PERIOD_S,
    ) -> None:
        self.cfg = cfg
        self.health_period_s = health_period_s
        self.gripper_health_period_s = gripper_health_period_s
        self.health: dict[str, str] = {}
        """Last known device condition: ``{"arm": "ok" | "disconnected" | "protective_stop",
        "gripper": "ok" | reason}``; filled by the health poll."""
        self.metrics = metrics or Metrics()
        self.ensemble = ensemble
        self.detector: SlipDetector = build_detector(cfg, ensemble)
        self.arm, self.gripper = arm, gripper
        self.arm_worker = DeviceWorker("arm") if arm is not None else None
        self.gripper_worker = DeviceWorker("gripper") if gripper is not None else None
        self.reaction = Reaction(
            actions=list(cfg.reaction.actions),
            arm=arm,
            gripper=gripper,
            arm_worker=self.arm_worker,
            gripper_worker=self.gripper_worker,
            metrics=self.metrics,
            graded=cfg.reaction.graded,
            rearm_after_s=cfg.reaction.rearm_after_s,
            on_failsafe=cfg.reaction.on_failsafe,
            policy=cfg.reaction.policy,
            grip=GripControlSettings.from_config(cfg.reaction),
        )
        self.notifier = notifier
        self.device_health = DeviceHealth(self)
        self.liveness = Liveness(self)
        self._crashed: BaseException | None = None  # a crash of supervision or the health task (``_on_task_end``)
        self.recorder: Recorder | None = None
        self.taps: list[Tap] = []
        """ROS 2 publisher, live view (``slipd.daemon.taps``): they copy frames and decisions off this thread."""
        self.stats = LoopStats()
        self.sensor: Any = None
        self._stop = asyncio.Event()
        self.ready = asyncio.Event()
        """Set once the sensor is open and supervision runs (tests start streaming then)."""
        self.started_live = False
        """True once the first valid decision was made (``READY=1`` sent)."""
        self.live = False
        """Liveness (module docstring): a valid decision on fresh data within the stall timeout."""
        self.blind: str | None = None
        """The cause of the current blind episode (one fail-safe each), None while live or starting."""
        self._stall_s = cfg.sensor.stall_timeout_ms / 1e3
        self._rate_hz = cfg.sensor.rate_hz  # (sensor.* other than its tolerance takes a restart to change)
        self.rate = RateMonitor(cfg.sensor.rate_hz, cfg.sensor.rate_tolerance, self.metrics)
        """The stream's rate by the controller's clock and counter: outside its tolerance the daemon is blind
        (``rate``); at start-up it is live only once the rate was measured."""
        self._nonfinite_bridge = max(1, round(NONFINITE_BRIDGE_S * cfg.sensor.rate_hz))
        self.sensors = cfg.sensor.sensors
        ns = self.sensors
        self._nonfinite_run = np.zeros(ns, np.int64)  # per sensor: consecutive non-finite samples up to now
        self._nonfinite_burst = False  # a run beyond the bridge since the supervisor last looked
        self._nonfinite_sensor = 0  # the sensor of the latest such run (the log line names it)
        self._nonfinite_open = False  # some sensor's run of non-finite samples is under way
        self._prev_bits: bytes | None = None  # the latest frame's values read, sensor by sensor (27 or 54 float32)
        # The ensemble reads forces only; the heuristics (alone, or the rule confirmed by the model) read the tip
        # displacements too.
        self._reads_disp = cfg.model.detector != "onnx" or cfg.decision.confirm_rule is not None
        # Fresh data is what decides: the forces, and the displacements where a heuristic alone decides (the rule the
        # model confirms counts only where the model's forces lean towards a slip).
        self._fresh_disp = cfg.model.detector != "onnx"
        now = time.monotonic()
        self._fresh_ts = np.full(ns, now)  # per sensor: when its latest fresh sample was handled
        self._fresh_t = now  # the oldest of them (re-based when the loop starts)
        self._decided_t: float | None = None  # latest valid decision on fresh data (None: none this episode)
        self._decision_due = now  # a valid decision is overdue after this (re-based on every restart)
        self._decision_frames = 0  # the reader's frame count by which that decision's frames are all in
        self._nonfinite_seen = 0
        self._last_t_us: int | None = None  # sensor time of the latest frame handled (a fail-safe recording's end)
        self._bias_until: float | None = None  # after a reconnect: frames until then are the sensor zeroing itself
        # A bias sent on a reconnect mid-grasp took the grasp's load for the zero: zeroed again in software once the
        # jaw lets go (slipd.daemon.rezero). The heuristic detectors' front ends keep the offset they were built with:
        # not for them (a warning at such a reconnect says so).
        self._loaded_zero = LoadedZero(ns, cfg.sensor.rate_hz) if hasattr(self.detector, "set_offset") else None
        streams = getattr(self.detector, "feature_streams", None)
        feats = getattr(self.detector, "features", None)  # the ensemble's pipeline; the heuristics have none
        self._feature_streams = list(streams) if streams is not None else [feats] if feats is not None else []
        m = self.metrics
        # Bounded label values: one child per configured sensor, made once (no label lookup per decision).
        self._m_sensor = [(m.decisions.labels(sensor=str(k)), m.alarms.labels(sensor=str(k)),
                           m.step_errors.labels(sensor=str(k))) for k in range(ns)]
        # The per-decision gauges are read when Prometheus scrapes (a scrape every few seconds against 100
        # decisions a second per sensor): the hot path keeps each sensor's latest valid decision and contact
        # state, and a gauge's function reads it; nothing is set per decision.
        self._latest: list[Detection | None] = [None] * ns
        self._latest_contact: list[ContactState | None] = [None] * ns
        self._grasp_held = False
        """Some finger was in contact at the latest decision with a contact state (``_track_grasp``)."""
        for k in range(ns):
            m.p_slip.labels(sensor=str(k)).set_function(partial(self._latest_value, k, "p_slip"))
            m.risk.labels(sensor=str(k)).set_function(partial(self._latest_value, k, "risk"))
            m.contact_risk.labels(sensor=str(k)).set_function(partial(self._contact_value, k, "risk"))
            m.friction.labels(sensor=str(k)).set_function(partial(self._contact_value, k, "friction"))
            for p in range(9):
                m.pillar_slip.labels(sensor=str(k), pillar=str(p)).set_function(partial(self._pillar_value, k, p))
        m.model.info({"name": str(cfg.model.manifest.name), "sha256": ensemble.manifest.sha256})

    # ----------------------------------------------------------------- hot path
    def _on_frames(self, block: FrameBlock) -> None:
        t0 = time.perf_counter()
        rate = self.rate
        disc = block.discontinuity
        broken = 1 in disc.tobytes()  # (some flag set: the cheapest test of a short bool array, a byte search)
        rate.push(block.counter, block.t_us, disc, broken)  # also while the sensor zeroes itself
        if rate.outside and self.blind is None:
            self.liveness.wake()
        if self._bias_until is not None:
            if time.monotonic() < self._bias_until:
                return  # the sensor zeroes itself after a reconnect: these frames are not decided on
            self._bias_until = None
            self._restart(retare=True)  # the history starts after the bias, on a sensor zeroed again
        if not broken:
            self._on_block(block.t_us, block.force, block.disp)
        else:
            n = len(block)
            start = 0
            for end in (*(int(b) for b in np.flatnonzero(disc) if b > 0), n):
                # A block runs to the next discontinuity (counter went backwards or the sensor reconnected):
                # the history is not continuous there, so the detector restarts before that frame.
                if disc[start]:
                    self._restart()
                self._on_block(block.t_us[start:end], block.force[start:end], block.disp[start:end])
                start = end
        self.metrics.loop_seconds.observe(time.perf_counter() - t0)
        self._coalesce()

    def _on_block(self, t_us: np.ndarray, force: np.ndarray, disp: np.ndarray) -> None:
        """Frames without a discontinuity (``t_us`` [k]; ``force``, ``disp`` [k, S, 9, 3]): through the detector
        in one call, then each decision in order.

        Per frame semantics are kept: the recorder gets the frames up to a decision before that decision,
        and an alarm carries the sample index and t_us of the frame that completed its window.
        """
        m = self.metrics
        rec = self.recorder
        det_ = self.detector
        k = len(t_us)
        one = self.sensors == 1
        stamps = t_us.astype(np.int64)
        self._last_t_us = int(stamps[-1])
        # The heuristics read the tip displacements too (as tuned); the ensemble reads forces only.
        moved = (disp[:, 0] if one else disp) if self._reads_disp else None
        dets = det_.push_many(force[:, 0] if one else force, stamps, moved)
        # After the detector (nothing there reads the freshness): a block its feature pipeline found all finite on the
        # way is not searched for a non-finite value again.
        clean = det_.clean_block
        self._check_samples(force, disp, clean)
        self.stats.frames += k
        valid = [False] * self.sensors
        recorded = 0
        grip = self.reaction.grip_control is not None
        grasp: list[Detection] = []  # grip control: this decision's detections with a contact state, one per sensor
        for (i, det), step_s in zip(dets, det_.step_seconds):
            s = det.sensor
            m_dec, m_alarms, m_err = self._m_sensor[s]
            if rec is not None and recorded <= i:
                rec.push_frames(stamps[recorded : i + 1], force[recorded : i + 1], disp[recorded : i + 1])
                recorded = i + 1
            if step_s is not None:
                m.inference_seconds.observe(step_s)
            if not det.valid:
                self.stats.step_errors += 1
                m_err.inc()
                continue
            self.stats.decisions += 1
            valid[s] = True
            m_dec.inc()
            self._latest[s] = det
            if rec is not None:
                if det.alarm and not rec.recording:
                    self._note_offset()
                rec.push_decision(det.t_us, det.p_slip, det.alarm, s, det.contact)
            if det.contact is not None:
                # Contact metrics and grip_control, apart from the hot path; the grip controller gets the
                # grasp once per decision, when every sensor's state for it is in.
                self._latest_contact[s] = det.contact
                if grip:  # (under stop_and_secure the state is for the metrics alone)
                    if grasp and grasp[0].index != det.index:
                        self._on_grasp(grasp)
                        grasp = []
                    grasp.append(det)
                    if len(grasp) == self.sensors:
                        self._on_grasp(grasp)
                        grasp = []
            if det.rising_edge:
                t_dec = time.monotonic()
                self.reaction.on_alarm(det.risk, t_dec)
                m_alarms.inc()
                self.stats.alarms.append((det.index, det.t_us, t_dec, s))
                self.stats.alarm_count += 1
                log.warning("ALARM: incipient slip on sensor %d (p=%.3f risk=%.2f) at t=%.3f s", s, det.p_slip,
                            det.risk, det.t_us / 1e6)
                if rec is not None:
                    rec.trigger(det.t_us, "alarm", p_slip=det.p_slip, sensor=s)
            for tap in self.taps:  # after the reaction went out; the taps' threads wake at the block's end
                tap.on_decision(det, force[i, s])
        if grasp:  # a sensor without a valid decision (or contact state) for the last one
            self._on_grasp(grasp)
        if dets:
            self._track_grasp()
        for tap in self.taps:
            tap.on_block(stamps, force, disp)
        if rec is not None:
            if recorded < k:
                rec.push_frames(stamps[recorded:], force[recorded:], disp[recorded:])
            rec.settle()  # a recording that ended in this block is written with its last frame's decisions
        if all(valid) and not self._nonfinite_burst:
            # A valid decision on every sensor (a blind finger is a blind daemon); one on held values beyond
            # the bridge is no sign of life.
            now = time.monotonic()
            self._decided_t = now
            self._expect_decision(now)
        if self._feature_streams and not clean:  # (a clean block counted nothing)
            bad = 0
            for f in self._feature_streams:
                bad += f.nonfinite_count + f.clipped_count
            if bad != self._nonfinite_seen:  # counted once per block, not per sample
                m.nonfinite.inc(bad - self._nonfinite_seen)
                self._nonfinite_seen = bad
        if self._loaded_zero is not None and self._loaded_zero.armed:
            self._rezero(force)  # last: the block's frames and decisions all belong to the old zero's stream

    def _track_grasp(self) -> None:
        """A grasp ends when no finger is in contact any more (every sensor's latest contact state at or below the
        SDK's contact threshold, the grip controller's release rule): the reaction then forgets what it owed that
        grasp. A tighten owed to an object that has gone was sent once the servo answered again, closing the jaw on
        nothing, on the next object at the old grasp's secure force, or on a hand in the way."""
        held = False
        for c in self._latest_contact:  # (a loop: any() over a generator costs more, once per decision)
            if c is not None and c.grip_n > CONTACT_THRESHOLD_N:
                held = True
                break
        if held != self._grasp_held:
            self._grasp_held = held
            if not held:
                self.reaction.released()

    def _rezero(self, force: np.ndarray) -> None:
        """After a bias taken under a grasp: the free air's mean becomes the zero once the jaw has let go."""
        assert self._loaded_zero is not None
        offset = self._loaded_zero.push(force, np.asarray(self.detector.offset), self._grasp_held)  # type: ignore[attr-defined]
        if offset is None:
            return
        self.detector.set_offset(offset if self.sensors > 1 else offset[0])  # type: ignore[attr-defined]
        self._restart(retare=True)  # the history cut with the old zero is another stream's
        self.metrics.rezeros.inc()
        log.warning("sensor: zeroed again in software after the release (the bias after the reconnect was taken under "
                    "a grasp; normal force offsets %s N)", np.round(offset[..., 2], 2).tolist())

    def _on_grasp(self, dets: list[Detection]) -> None:
        """One decision's contact states, one per sensor, to the grip controller (``policy: grip_control``): a gripper
        has one grip, so the fingers' states become the grasp's (``grasp_state``), and an alarm on either finger is an
        alarm of the grasp. One sensor: its state as it is."""
        alarm = sampled = False
        for d in dets:  # (an alarm of the confirmed heuristic alone is no friction sample: ``Detection.rule_only``)
            alarm = alarm or d.alarm
            sampled = sampled or (d.alarm and not d.rule_only)
        self.reaction.on_detection(grasp_state([d.contact for d in dets]), alarm, time.monotonic(), sampled)

    # Scrape-time readers of the per-decision gauges (called from the metrics server's thread: each reads
    # one reference the loop replaces whole, never a half-written value).
    def _latest_value(self, sensor: int, field: str) -> float:
        det = self._latest[sensor]
        return 0.0 if det is None else float(getattr(det, field))

    def _contact_value(self, sensor: int, field: str) -> float:
        c = self._latest_contact[sensor]
        value = None if c is None else getattr(c, field)
        return 0.0 if value is None else float(value)

    def _pillar_value(self, sensor: int, pillar: int) -> float:
        c = self._latest_contact[sensor]
        return 0.0 if c is None else float(c.pillar_slip[pillar])

    def _check_samples(self, force: np.ndarray, disp: np.ndarray, finite: bool = False) -> None:
        """Freshness of a block, per sensor (once per block): finite, and not bit-identical to the sample before, in
        what the detector reads (forces; displacements too for the heuristics). Updates each sensor's fresh time and
        its run of non-finite samples up to the block's end. ``finite``: the detector found every value finite already
        (``clean_block``), so the block is not searched again."""
        n = len(force)
        ns = self.sensors
        vals = force.reshape(n, ns, -1)
        if self._fresh_disp:
            vals = np.concatenate([vals, disp.reshape(n, ns, -1)], axis=2)
        prev = self._prev_bits
        tail = vals[-1].tobytes()  # every sensor's latest values, one after the other (one call, sliced per sensor)
        self._prev_bits = tail
        # Every value finite: no zero byte among the flags (a byte search; ndarray.all and a finite sum cost more).
        if not finite and 0 in np.isfinite(vals).tobytes():
            self._check_nonfinite(vals, prev)
            return
        # The common block, all finite: a sensor is fresh unless every sample is bit-identical to the one before (the
        # first block always is). Its last sample differing from the block before's answers at once; if it does not,
        # one comparison of the block's bytes does.
        if self._nonfinite_open:
            self._nonfinite_run[:] = 0
            self._nonfinite_open = False
        if prev is None or (ns == 1 and tail != prev):  # (one sensor, its latest sample changed: the common block)
            now = self._arrived()
            self._fresh_ts.fill(now)
            self._fresh_t = now
            return
        arrived: float | None = None
        stale = False
        width = len(tail) // ns
        for s in range(ns):
            last = tail[s * width : (s + 1) * width]
            if last == prev[s * width : (s + 1) * width] and vals[:, s].tobytes() == last * n:
                stale = True
                continue
            if arrived is None:
                arrived = self._arrived()
            self._fresh_ts[s] = arrived
        if arrived is not None:  # (every sensor fresh, the common block: the oldest fresh time is this one)
            self._fresh_t = float(self._fresh_ts.min()) if stale else arrived

    def _arrived(self) -> float:
        """When the data of the block at hand arrived (a held block can be handed over up to half a stall timeout
        later)."""
        arrived = self.sensor.last_frame_time if self.sensor is not None else None
        return time.monotonic() if arrived is None else float(arrived)

    def _check_nonfinite(self, vals: np.ndarray, prev: bytes | None) -> None:
        """``_check_samples`` on a block with a non-finite value (a fault: sample by sample). Follows each sensor's run
        of non-finite samples across blocks; a run longer than the bridge is remembered until the supervisor has seen
        it, even when it ended inside this block."""
        n, ns = len(vals), self.sensors
        bits = vals.view(np.uint32)  # bit-identical, as the common block's test
        finite = np.isfinite(vals).all(axis=2)  # [n, S]
        changed = np.empty((n, ns), bool)
        if prev is None:
            changed[0] = True
        else:
            changed[0] = (bits[0] != np.frombuffer(prev, np.uint32).reshape(ns, -1)).any(axis=1)
        changed[1:] = (bits[1:] != bits[:-1]).any(axis=2)
        fresh = (finite & changed).any(axis=0)
        if fresh.any():
            self._fresh_ts[fresh] = self._arrived()
            self._fresh_t = float(self._fresh_ts.min())
        for s in range(ns):
            run = int(self._nonfinite_run[s])
            for ok in finite[:, s].tolist():
                run = 0 if ok else run + 1
                if run > self._nonfinite_bridge:
                    self._nonfinite_burst = True
                    self.liveness.wake()
                    self._nonfinite_sensor = s
            self._nonfinite_run[s] = run
        self._nonfinite_open = bool(self._nonfinite_run.any())

    def _coalesce(self) -> None:
        """Pause the sensor reader until shortly before the next decision's last sample is due, and have it
        hold the frames back until then.

        Frames keep arriving into the kernel's buffer and are read in one go on resume (a pause is capped by
        that buffer, so a decision may take a few reads); the reader keeps what it decoded until the deciding
        frame is in and hands the frames over in one block, so the per-block work runs once per decision. No
        frame is lost or reordered; only the samples that end a window must be handled the moment they
        arrive. Frames are never kept from the stall check for more than half its timeout.
        """
        margin = self.cfg.sensor.coalesce_margin_ms
        sensor = self.sensor
        if margin is None or sensor is None:
            return
        due = self.detector.samples_to_decision()  # the next deciding sample is `due` frames away
        half_stall = self.cfg.sensor.stall_timeout_ms / 2e3
        if due > 1:
            sensor.hold_for(due, half_stall, margin / 1e3)
        arrival = sensor.expected_arrival(due)
        if arrival is None:
            wait_s = (due - 1) / self.cfg.sensor.rate_hz - margin / 1e3
        else:  # resume `margin` before the deciding frame is due (the reader's arrival clock)
            wait_s = arrival - margin / 1e3 - time.monotonic()
        wait_s = min(wait_s, half_stall)
        if wait_s >= 1e-3:  # shorter pauses save nothing over one wake-up per frame
            sensor.pause(wait_s, self.cfg.sensor.rate_hz)

    def _on_disconnect(self, reason: str) -> None:
        self._restart()
        self.rate.restart()
        self.liveness.go_blind("sensor_lost", f"sensor lost: {reason}")

    def _on_reconnect(self) -> None:
        """The sensor is back, perhaps power-cycled: set its rate again and, with ``tare: bias_command``, zero it
        again; its frames until the bias is done are not decided on (they are neither zeroed nor the sensor's
        steady output), so the daemon stays blind until a valid decision after it."""
        from slipd.io.sensor import SensorError

        try:
            if self._set_up_sensor():
                self._bias_until = time.monotonic() + self.cfg.sensor.bias_timeout_s
                if self._loaded_zero is not None:
                    # The sensor zeroed itself (offset 0, as built for bias_command): a software zero from an earlier
                    # bias would now count twice.
                    self.detector.set_offset(np.zeros_like(self.detector.offset))  # type: ignore[attr-defined]
                if self._grasp_held:
                    # In contact when the sensor went: the bias takes the grasp's load. (Not disarmed by a bias in
                    # free air: a zero already taken under the grasp reads that grasp as no contact, so a second
                    # power cycle before the release looks like one in free air and zeroes the same load again.)
                    if self._loaded_zero is None:
                        log.warning("sensor: zeroed under a grasp (power-cycled mid-grasp?); detector %s cannot zero "
                                    "again in software: later grasps read low by the held load until slipd restarts",
                                    self.cfg.model.detector)
                    else:
                        log.warning("sensor: zeroed under a grasp (power-cycled mid-grasp?): zeroing again in "
                                    "software once the jaw lets go")
                        self._loaded_zero.arm([0.0 if c is None else c.grip_n for c in self._latest_contact])
        except SensorError as exc:
            log.error("sensor: cannot set it up again after the reconnect: %s", exc)

    def _set_up_sensor(self, start_up: bool = False) -> bool:
        """Send the configured rate and, with ``tare: bias_command``, the bias (at start-up and after a reconnect);
        True when a bias was sent (the sensor zeroes itself for ``sensor.bias_timeout_s``).

        Not at a start-up that found the jaw gripping (``Gripper.gripping_found``: slipd restarted mid-grasp, its
        sensor's controller still powered and zeroed from before): a bias then would take the held object's load for
        the zero, and the detector would see no contact for as long as that grasp lasts."""
        from slipd.io.pts import CMD_BIAS, rate_command

        cfg = self.cfg.sensor
        self.sensor.send_command(rate_command(cfg.rate_hz))
        mid_grasp = start_up and getattr(self.gripper, "gripping_found", False)
        if cfg.tare == "startup" and mid_grasp:
            log.warning("sensor: the jaw grips already (slipd restarted mid-grasp?): tare: startup averages the held "
                        "load into its zero; tare: bias_command keeps the sensor's zero from before")
        if cfg.tare != "bias_command":
            return False
        if mid_grasp:
            log.warning("sensor: the jaw grips already (slipd restarted mid-grasp?): no bias sent, the sensor's zero "
                        "from before stands")
            return False
        self.sensor.send_command(CMD_BIAS)
        return True

    def _restart(self, retare: bool = False) -> None:
        """The history is broken (discontinuity, reconnect): restart the detector; the next valid decision
        is due once it has its samples again (tare, window) plus the stall timeout. ``retare``: the sensor zeroed
        itself (its bias)."""
        self.detector.restart(retare)
        if self.recorder is not None:
            self.recorder.restart()  # no recording glues the streams either side of the break
        self.stats.restarts += 1
        self._prev_bits = None
        self._expect_decision(time.monotonic())

    def _expect_decision(self, now: float) -> None:
        """The next valid decision: due once the detector has its samples, plus the stall timeout; the reader's frame
        count by which its frames are all in tells ``Liveness.blind_cause`` whether an overdue one is the stream's
        fault."""
        need = self.detector.samples_to_decision()
        self._decision_due = now + self._stall_s + need / self._rate_hz
        self._decision_frames = need + (self.sensor.frames if self.sensor is not None else 0)

    def set_decision_rule(self, rule: DecisionConfig) -> None:
        """A reload's decision section (``slipd.daemon.reload``), applied between two blocks: threshold, hysteresis,
        decisions in a row, the limit guard and the press hold of every sensor's decision rule (the heuristics have
        none)."""
        threshold = rule.effective_threshold(self.ensemble.threshold)
        for det in getattr(self.detector, "detectors", [self.detector]):
            decision = getattr(det, "decision", None)
            if decision is None:
                continue
            decision.threshold, decision.hysteresis = float(threshold), float(rule.hysteresis)
            decision.min_consecutive = int(rule.min_consecutive)
            decision.limit_guard, decision.limit_guard_decisions = rule.limit_guard, int(rule.limit_guard_decisions)
            det.press_rise = rule.press_rise

    def _fail_safe(self, reason: str, logged: bool = False) -> None:
        self.stats.failsafes += 1
        self.reaction.failsafe(reason, logged)

    def _note_offset(self) -> None:
        """The recording about to start replays with the tare offset the daemon used (``slipd replay``): an alarm's,
        and a fail-safe's (without it replay re-tared from frames taken under load, and every decision differed)."""
        offset = getattr(self.detector, "offset", None)
        if offset is not None and self.recorder is not None:
            self.recorder.meta["tare_offset"] = np.asarray(offset).tolist()

    # ---------------------------------------------------------------- lifecycle
    async def run(self, sensor_port: str | None = None, duration_s: float | None = None) -> LoopStats:
        """Open the sensor, run until ``stop()`` (or ``duration_s``), then close everything."""
        from slipd.io.sensor import SerialSensor

        cfg = self.cfg.sensor
        self.reaction.post = asyncio.get_running_loop().call_soon_threadsafe  # device outcomes on this thread
        self.sensor = SerialSensor(
            sensor_port or cfg.port,
            on_block=self._on_frames,
            sensors=cfg.sensors,
            rate_hz=cfg.rate_hz,
            baudrate=cfg.baudrate,
            on_disconnect=self._on_disconnect,
            on_reconnect=self._on_reconnect,
            reconnect_initial_s=cfg.reconnect_initial_s,
            reconnect_max_s=cfg.reconnect_max_s,
            metrics=self.metrics,
            low_latency=cfg.low_latency,
        )
        self.sensor.starting = not self.started_live
        await self.sensor.start()
        if self._set_up_sensor(start_up=True):
            # The frames while the sensor zeroes itself are neither zeroed nor its steady output: not decided on (no
            # alarm, no grip command from them), as after a reconnect; the first frame after it restarts the history.
            self._bias_until = time.monotonic() + cfg.bias_timeout_s
            # A stop meanwhile ends the wait (up to 30 s, beyond systemd's TimeoutStopSec, which then killed slipd
            # before it closed the devices).
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._stop.wait(), cfg.bias_timeout_s)
        # Everything built so far (modules, the model, the devices) lives as long as the daemon: out of the
        # collector's sight, so a full collection scans only what the loop allocates since (it stalled the
        # loop for ~20 ms at the worst, tools/bench_daemon.py).
        gc.collect()
        gc.freeze()
        supervisor = asyncio.create_task(self.liveness.run(), name="supervision")
        health = (asyncio.create_task(self.device_health.run(), name="device health") if self.health_period_s > 0
                  else None)
        for task in (supervisor, health):
            if task is not None:
                task.add_done_callback(self._on_task_end)
        self.metrics.ready.set(1)
        self.ready.set()
        try:
            if duration_s is None:
                await self._stop.wait()
            else:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), duration_s)
        finally:
            self._stop.set()
            for task in (supervisor, health):
                if task is None:
                    continue
                task.cancel()
                with contextlib.suppress(Exception, asyncio.CancelledError):  # a crash was logged by _on_task_end
                    await task
            await self.sensor.stop()
            self.reaction.post = None  # outcomes after the loop's end are handled where they happen
            self.metrics.ready.set(0)
            self.metrics.live.set(0)
            if self.notifier is not None:
                self.notifier.stopping()
        if self._crashed is not None:
            raise RuntimeError("the daemon's supervision or health task crashed") from self._crashed
        return self.stats

    def _on_task_end(self, task: asyncio.Task[None]) -> None:
        """Supervision or the health task ended before the daemon: a crash would leave it unsupervised (no stall check,
        no device health, no arm reconnect) while the systemd watchdog was still pinged. Fail safe and stop: systemd
        restarts it."""
        if task.cancelled() or self._stop.is_set():
            return
        exc = task.exception()
        if exc is None:
            return  # done with nothing to do (the health task without a device to poll)
        log.error("%s ended unexpectedly (%r): failing safe and stopping", task.get_name(), exc,
                  exc_info=exc)
        self._fail_safe("internal_error")
        self._crashed = exc
        self.stop()

    def stop(self) -> None:
        """Ask ``run`` to finish (safe from signal handlers on the loop)."""
        self._stop.set()

    def close(self) -> None:
        """Release device threads and the recorder (the devices keep their last state: grip held).

        Each device is closed on its own thread, after whatever was queued there (the libraries are not
        thread-safe); a thread still stuck in a vendor call after ``DEVICE_CLOSE_TIMEOUT_S`` (ur_rtde's
        reconnect timeouts after a dropped link) is left behind so that the daemon still exits."""
        # The arm first (ending its control script halts it), both at once under one deadline: one after the other, a
        # hung gripper thread delayed the arm's close by its whole timeout, past systemd's kill.
        devices = [("arm", self.arm_worker, self.arm), ("gripper", self.gripper_worker, self.gripper)]
        waiting = []
        for name, w, dev in devices:
            if dev is None:
                continue
            if w is None:
                close_quietly(dev)
                continue
            w.submit(close_quietly, dev)
            waiting.append((name, w))
        deadline = time.monotonic() + DEVICE_CLOSE_TIMEOUT_S
        for name, w in waiting:
            if not w.close(timeout=max(0.0, deadline - time.monotonic())):
                log.warning("%s: its thread is still in a vendor call after %.0f s; exiting without closing it",
                            name, DEVICE_CLOSE_TIMEOUT_S)
        if self.recorder is not None:
            self.recorder.close()
        for tap in self.taps:
            tap.close()
