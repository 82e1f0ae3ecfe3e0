"""Recordings around alarms: a ring buffer of raw frames and decisions, dumped off the control loop.

The control loop calls ``push_frames`` for every block of sensor frames (``push_frame`` for one) and
``push_decision`` for every model decision. Both copy into preallocated ring buffers, frames by slices
(no allocation, no Python work per sample). With ``sensors`` > 1 the rings hold every finger's array
([.., S, 9, 3]) and each decision its ``sensor``; the recording then carries all of them. The ring holds
``seconds_before + seconds_after`` of frames, so when an alarm (a decision with ``alarm=True``, or
``trigger()`` for a fail-safe event) has been followed by ``seconds_after`` of frames, the ring holds
exactly the stretch [alarm - before, alarm + after). That stretch is copied once and handed to the
recorder's own worker thread, which writes it as a ``slipd.recording.Recording`` (``.mcap``, ``.npz`` and/or the
Contactile SDK CSV) with the decisions of the stretch in ``meta["decisions"]``: time, P(slip), alarm and sensor of
each, and where the decision carried a contact state its nine pillars' P(slip), contact risk and friction
estimate (None before the contact showed one, and for a decision without a contact state).

Crash safety: each file is first written under a staging name (``*.part``, itself written through
``Recording.save``'s ``*.tmp`` + rename), flushed to disk, given mode 0640, and only then renamed to
its final ``.mcap`` / ``.npz`` / ``.csv`` name. A crash at any point leaves either the complete file or only
staging files, which ``slipd.recording.list_recordings`` (suffix ``.mcap``/``.npz``/``.csv``) never returns and
the next ``Recorder`` deletes. The directory is created with mode 0750.

Episodes: one recording per alarm episode. An alarm decision while a recording runs extends it to
``seconds_after`` past that decision, up to ``max_episode_s`` after the onset; frames that would fall out
of the ring meanwhile are copied out in blocks (one copy per ring length, not per sample). An alarm that
stays high past that bound (a latched alarm) starts no further recording until it falls: a 10-minute
latched alarm is one recording, holding its onset, not a new file every ``seconds_after``.

Size bound: after every write the oldest recordings are deleted until all of them together fit
``max_total_mb`` (MiB): an earlier run's first (by name), then this run's in the order it wrote them (names carry
the wall-clock time, which a reboot may set back). The newest recording is always kept, even alone above the bound.
As each episode is one recording, the one that holds an onset is never pushed out by later files of its own episode.

Breaks: the daemon calls ``restart`` when the stream breaks (counter discontinuity, reconnect, bias); a recording
then ends with the frames it has, and the next one starts after the break, so no file glues two streams.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slipd.daemon.worker import DeviceWorker
from slipd.geometry import N_PILLARS
from slipd.recording import SUFFIXES, Recording, write_sdk_csv
from slipd.recording_mcap import write_mcap

if TYPE_CHECKING:
    from slipd.detect.contact import ContactState
    from slipd.metrics import Metrics

log = logging.getLogger("slipd.daemon.recorder")

FILE_MODE = 0o640
DIR_MODE = 0o750
PREFIX = "slip-"
STAGING_SUFFIXES = (".part", ".tmp")
FORMATS = ("npz", "csv", "mcap")
MAX_TRIGGER_EVENTS = 100
"""Fail-safe events one recording names beside its trigger (bounded: one per blind episode, but an episode may last)."""
MAX_KEPT_PATHS = 256
MAX_EPISODE_S = 30.0
"""Longest recording of one alarm episode (after its onset); a latched alarm records no more than this."""


def _rounded(values: list[float]) -> list[float | None]:
    """JSON-ready: 4 decimals, None for NaN (no contact state, or no friction estimate yet)."""
    return [None if math.isnan(v) else round(v, 4) for v in values]


@dataclass
class _Snapshot:
    """One stretch to write, copied out of the rings. The decisions stay arrays here: their JSON form (lists, rounded,
    nine pillars each) is built on the worker thread, as it took up to a third of a second on the loop's for a long
    two-finger episode."""

    name: str
    t_us: np.ndarray
    force: np.ndarray
    disp: np.ndarray
    meta: dict[str, Any]
    decisions: tuple[np.ndarray, ...] = ()
    """t_us, p_slip, alarm, sensor, pillar_slip [n, 9], contact_risk, friction of each decision in the stretch."""


def _decisions_meta(dt: np.ndarray, dp: np.ndarray, da: np.ndarray, ds: np.ndarray, dpill: np.ndarray,
                    drisk: np.ndarray, dfric: np.ndarray) -> dict[str, list[Any]]:
    """``meta["decisions"]`` of a recording (JSON-ready)."""
    return {"t_us": dt.tolist(), "p_slip": [round(float(p), 6) for p in dp], "alarm": da.tolist(),
            "sensor": ds.tolist(),
            "pillar_slip": [None if math.isnan(row[0]) else _rounded(row) for row in dpill.tolist()],
            "contact_risk": _rounded(drisk.tolist()), "friction": _rounded(dfric.tolist())}


class Recorder:
    """Ring buffer of the last seconds of frames and decisions; writes a recording around each alarm.

    ``push_frame``/``push_decision``/``trigger`` are for the control loop thread only (not thread-safe
    among themselves); the files are written on the ``recorder`` worker thread.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        rate_hz: float,
        *,
        seconds_before: float = 2.0,
        seconds_after: float = 1.0,
        max_total_mb: float = 500.0,
        formats: tuple[str, ...] | list[str] = ("npz",),
        meta: Mapping[str, Any] | None = None,
        worker: DeviceWorker | None = None,
        max_pending: int = 4,
        max_episode_s: float = MAX_EPISODE_S,
        sensors: int = 1,
        metrics: Metrics | None = None,
    ) -> None:
        if rate_hz <= 0 or seconds_before < 0 or seconds_after < 0:
            raise ValueError(f"rate_hz > 0 and non-negative seconds required, got {rate_hz}, "
                             f"{seconds_before}, {seconds_after}")
        unknown = [f for f in formats if f not in FORMATS]
        if unknown or not formats:
            raise ValueError(f"formats must be among {FORMATS}, got {list(formats)}")
        self.directory = Path(directory)
        self.rate_hz = float(rate_hz)
        self.seconds_before = float(seconds_before)
        self.seconds_after = float(seconds_after)
        self.max_total_bytes = int(max_total_mb * 2**20)
        self.formats = tuple(formats)
        self.meta = dict(meta or {})
        self.before = math.ceil(seconds_before * rate_hz)
        self.after = math.ceil(seconds_after * rate_hz)
        self.capacity = max(1, self.before + self.after)
        self.sensors = int(sensors)
        n = self.capacity
        self._t = np.zeros(n, dtype=np.int64)
        self._force = np.zeros((n, self.sensors, N_PILLARS, 3), dtype=np.float32)
        self._disp = np.zeros((n, self.sensors, N_PILLARS, 3), dtype=np.float32)
        # At most one decision per frame and sensor, so this capacity covers the same stretch of time.
        nd = n * self.sensors
        self._dt = np.zeros(nd, dtype=np.int64)
        self._dp = np.zeros(nd, dtype=np.float32)
        self._da = np.zeros(nd, dtype=bool)
        self._ds = np.zeros(nd, dtype=np.int8)
        # The contact state of each decision (NaN: none; friction NaN also before one was estimated).
        self._dpill = np.full((nd, N_PILLARS), np.nan, dtype=np.float32)
        self._drisk = np.full(nd, np.nan, dtype=np.float32)
        self._dfric = np.full(nd, np.nan, dtype=np.float32)
        self.frames_seen = 0
        self.decisions_seen = 0
        self._pending_end: int | None = None  # frames_seen at which the current dump is complete
        self._limit = 0  # frames_seen at which the current episode's recording ends whatever the alarm does
        self.max_episode = max(self.after, math.ceil(max_episode_s * rate_hz))
        self._copied = 0  # frames (and decisions) of the recording copied out of the rings so far
        self._dcopied = 0
        self._chunks: list[list[np.ndarray]] = []  # [t, force, disp] blocks copied out of the ring
        self._dchunks: list[list[np.ndarray]] = []  # [t, p, alarm] blocks of decisions
        # Per sensor: its alarm is up now; its alarm outlived its episode's recording (no new one until it falls).
        # One flag for all let the other finger's quiet decisions clear a latched finger's latch, and the latched
        # alarm then started a recording every max_episode_s.
        self._alarm_up = np.zeros(self.sensors, bool)
        self._latched = np.zeros(self.sensors, bool)
        self._trigger: dict[str, Any] = {}
        self._break = self._dbreak = 0
        """Frames (decisions) seen when the stream last broke (``restart``): a recording started after frames came
        since then begins there, as the frames before it are another stream's (their t_us may even run backwards)."""
        self._seq = 0
        self.max_pending = max_pending
        self._futures: list[Future[list[Path]]] = []
        self._lock = threading.Lock()  # counters below are written on the worker thread
        # The latest paths only: a daemon that runs for months keeps bounded state (the files are the record).
        self.written: deque[Path] = deque(maxlen=MAX_KEPT_PATHS)
        self.deleted: deque[Path] = deque(maxlen=MAX_KEPT_PATHS)
        self.files_written = 0
        """Every file written (``written`` keeps only the latest)."""
        self.failures = 0
        self.dropped = 0
        self.extra_meta: Callable[[int, int], dict[str, Any]] | None = None
        """Called on the loop thread when a recording is cut, with its first and last t_us: what the daemon adds to its
        meta (``slipd.daemon.recording_context``: the reactions)."""
        self.metrics = metrics
        """Counts each lost recording by reason (``slipd_recordings_failed_total{reason}``)."""
        self._own_worker = worker is None
        self.worker = worker or DeviceWorker("recorder")
        self._prepare_directory()

    @classmethod
    def from_config(
        cls, cfg: Any, rate_hz: float, meta: Mapping[str, Any] | None = None, worker: DeviceWorker | None = None,
        sensors: int = 1, metrics: Metrics | None = None,
    ) -> Recorder:
        """Build from a ``slipd.config.RecorderConfig``."""
        return cls(
            cfg.directory,
            rate_hz,
            seconds_before=cfg.seconds_before,
            seconds_after=cfg.seconds_after,
            max_total_mb=cfg.max_total_mb,
            formats=tuple(cfg.formats),
            meta=meta,
            worker=worker,
            sensors=sensors,
            metrics=metrics,
        )

    # ------------------------------------------------------------------ control-loop side
    @property
    def recording(self) -> bool:
        """True between an alarm and the end of its ``seconds_after``."""
        return self._pending_end is not None

    def push_frame(self, t_us: int, force: np.ndarray, disp: np.ndarray) -> None:
        """Add one raw frame (``force``/``disp`` [9, 3], or [S, 9, 3]); completes a dump when one is due."""
        self.push_frames(np.array([t_us], np.int64), np.asarray(force)[None], np.asarray(disp)[None])

    def push_frames(self, t_us: np.ndarray, force: np.ndarray, disp: np.ndarray) -> None:
        """Add a block of raw frames (``t_us`` [k]; ``force``/``disp`` [k, 9, 3] or [k, S, 9, 3]) by slices of
        the ring. A recording whose last frame came in earlier is written first (``settle``); one that ends inside
        this block stops taking frames at its last one."""
        k = len(t_us)
        shape = (k, self.sensors, N_PILLARS, 3)
        force = np.asarray(force).reshape(shape)
        disp = np.asarray(disp).reshape(shape)
        cap = self.capacity
        done = 0
        while done < k:
            self.settle()
            m = k - done
            if self._pending_end is not None:
                if self.frames_seen - self._copied >= cap:
                    self._spill()  # a long episode: the frames about to be overwritten are still to be written
                m = min(m, cap - (self.frames_seen - self._copied), self._pending_end - self.frames_seen)
            i = self.frames_seen % cap
            m = min(m, cap - i)  # one contiguous slice of the ring
            self._t[i : i + m] = t_us[done : done + m]
            self._force[i : i + m] = force[done : done + m]
            self._disp[i : i + m] = disp[done : done + m]
            self.frames_seen += m
            done += m

    def settle(self) -> None:
        """Write the recording whose last frame is in, now that the decisions on that frame are in too: the daemon
        pushes a deciding frame before its decisions (``push_decision``), so writing at the frame itself left the
        decisions on a recording's last frame out of it (replay decides there). The daemon calls this at the end of
        every block; the next frames call it first."""
        if self._pending_end is not None and self.frames_seen >= self._pending_end:
            self._dump()

    def restart(self) -> None:
        """The stream broke (a counter discontinuity, a reconnect, the sensor's bias): a running recording ends with the
        frames it has (the next push writes it, or a fail-safe now names itself in it), and a later one starts after
        the break. Recordings that glued both streams had t_us running backwards (unreadable) and lost every
        decision."""
        if self._pending_end is not None:
            self._pending_end = min(self._pending_end, self.frames_seen)
        self._break, self._dbreak = self.frames_seen, self.decisions_seen

    def push_decision(self, t_us: int, p_slip: float, alarm: bool, sensor: int = 0,
                      contact: ContactState | None = None) -> None:
        """Add one model decision (of ``sensor``, with its contact state where it has one); an alarm starts a
        recording unless one is already running."""
        i = self.decisions_seen % len(self._dt)
        self._dt[i] = t_us
        self._dp[i] = p_slip
        self._da[i] = alarm
        self._ds[i] = sensor
        if contact is None:
            self._dpill[i] = np.nan
            self._drisk[i] = self._dfric[i] = np.nan
        else:
            self._dpill[i] = contact.pillar_slip
            self._drisk[i] = contact.risk
            self._dfric[i] = np.nan if contact.friction is None else contact.friction
        self.decisions_seen += 1
        self._alarm_up[sensor] = alarm
        if not alarm:
            self._latched[sensor] = False
        elif self._pending_end is not None:
            self._pending_end = min(max(self._pending_end, self.frames_seen + self.after), self._limit)
        elif not self._latched[sensor]:
            self.trigger(t_us, "alarm", p_slip=float(p_slip), sensor=int(sensor))

    def trigger(self, t_us: int, reason: str, *, wait_after: bool = True, **details: Any) -> bool:
        """Start a recording around now (an alarm, a fail-safe event); False if one is already running.

        The stretch ends ``seconds_after`` of frames from now; alarms meanwhile are part of it. ``wait_after``
        False: write the stretch up to now at once (a fail-safe on a stalled sensor: no frame may follow).
        """
        if self._pending_end is not None and reason != "alarm":
            # A fail-safe inside a running recording: it names the event, and when no frame may follow (a stalled
            # sensor) the stretch so far is written now; it was refused, and the recording waited for frames that
            # never came (lost at a kill, or written seconds later with a gap and no word of the fail-safe).
            events = self._trigger.setdefault("events", [])
            if len(events) < MAX_TRIGGER_EVENTS:
                events.append({"t_us": int(t_us), "reason": reason, "wall_time": time.time(), **details})
            if not wait_after:
                self._dump()
            return True
        if self._pending_end is not None or (reason == "alarm" and self._latched[int(details.get("sensor", 0))]):
            return False
        self._trigger = {"t_us": int(t_us), "reason": reason, "wall_time": time.time(), **details}
        self._pending_end = self.frames_seen + (self.after if wait_after else 0)
        self._limit = self.frames_seen + self.max_episode
        self._copied = max(0, self.frames_seen - self.before)
        self._dcopied = max(0, self.decisions_seen - len(self._dt))
        if self._break < self.frames_seen:  # frames came since the last break: the stretch starts after it
            self._copied = max(self._copied, self._break)
            self._dcopied = max(self._dcopied, self._dbreak)
        self._chunks, self._dchunks = [], []
        if self.after == 0 or not wait_after:
            self._dump()
        return True

    def close(self, timeout: float | None = 30.0) -> None:
        """Write a recording still in progress (shorter ``after``), wait for writes, stop the worker: within
        ``timeout`` in all (a hung disk must not keep the daemon past systemd's stop timeout)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        if self._pending_end is not None:
            self._dump()
        self.wait(timeout)
        if self._own_worker:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not self.worker.close(wait=True, timeout=left):
                log.warning("recorder: writes still pending at close: given up after %s s", timeout)

    def wait(self, timeout: float | None = 30.0) -> list[Path]:
        """Block until the queued writes are done (``timeout`` for all of them together); returns every file written
        so far."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for fut in list(self._futures):
            # A failed write is already logged and counted by the worker; a timeout leaves it queued.
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            with contextlib.suppress(Exception):
                fut.result(timeout=left)
        self._futures = [f for f in self._futures if not f.done()]
        with self._lock:
            return list(self.written)

    def _ordered(self, count: int, t: np.ndarray, *arrays: np.ndarray, since: int = 0) -> list[np.ndarray]:
        """Copies of the ring entries from ``since`` to ``count``, oldest first (one allocation per call)."""
        size = len(t)
        n = min(count - since, size)
        start = (count - n) % size
        idx = (np.arange(n) + start) % size
        return [a[idx] for a in (t, *arrays)]

    def _spill(self) -> None:
        """Copy the episode's frames and decisions still in the rings out before they are overwritten."""
        self._chunks.append(self._ordered(self.frames_seen, self._t, self._force, self._disp, since=self._copied))
        self._dchunks.append(
            self._ordered(self.decisions_seen, self._dt, self._dp, self._da, self._ds, self._dpill, self._drisk,
                          self._dfric, since=self._dcopied)
        )
        self._copied, self._dcopied = self.frames_seen, self.decisions_seen

    def _dump(self) -> None:
        trig, self._trigger = self._trigger, {}
        # An alarm still up when its recording ends (at max_episode_s, or a seconds_after shorter than the decisions'
        # spacing) starts no new recording until it falls: with seconds_after 0 every alarm decision of one episode
        # wrote a recording of its own, and the size bound then deleted the one that held the onset.
        self._latched |= self._alarm_up
        self._pending_end = None
        self._spill()
        chunks, dchunks, self._chunks, self._dchunks = self._chunks, self._dchunks, [], []
        self._futures = [f for f in self._futures if not f.done()]
        if len(self._futures) >= self.max_pending:
            # The disk cannot keep up; losing a recording is better than growing memory without bound.
            self.dropped += 1
            self._count_loss("backlog")
            log.warning("recorder: %d writes pending, recording of %s dropped", len(self._futures), trig)
            return
        t, force, disp = (np.concatenate(a) for a in zip(*chunks))
        dt, dp, da, ds, dpill, drisk, dfric = (np.concatenate(a) for a in zip(*dchunks))
        if len(t):
            keep = (dt >= t[0]) & (dt <= t[-1])
            dt, dp, da, ds, dpill, drisk, dfric = (a[keep] for a in (dt, dp, da, ds, dpill, drisk, dfric))
        if self.sensors == 1:
            force, disp = force[:, 0], disp[:, 0]  # the one-sensor layout: [N, 9, 3]
        meta = dict(self.meta)
        meta.update(
            source="slipd-recorder",
            rate_hz=self.rate_hz,
            seconds_before=self.seconds_before,
            seconds_after=self.seconds_after,
            trigger=trig,
            sensors=self.sensors,
        )
        if len(t):
            meta["events"] = {trig.get("reason", "alarm"): (trig.get("t_us", int(t[0])) - int(t[0])) / 1e6}
            if self.extra_meta is not None:
                meta.update(self.extra_meta(int(t[0]), int(t[-1])))
        self._seq += 1
        stamp = datetime.fromtimestamp(trig.get("wall_time", time.time()), tz=timezone.utc)
        name = f"{PREFIX}{stamp:%Y%m%dT%H%M%S.%fZ}-{os.getpid()}-{self._seq:04d}"
        snap = _Snapshot(name, t, force, disp, meta, (dt, dp, da, ds, dpill, drisk, dfric))
        self._futures.append(self.worker.submit(self._write_logged, snap))

    # ------------------------------------------------------------------ worker side
    def _prepare_directory(self) -> None:
        """Create the directory (0750) and remove staging files a crash left behind."""
        self.directory.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
        st = self.directory.stat()
        if st.st_uid == os.geteuid() and (st.st_mode & 0o777) != DIR_MODE:
            os.chmod(self.directory, DIR_MODE)
        for p in self.directory.iterdir():
            if p.name.startswith(PREFIX) and p.name.endswith(STAGING_SUFFIXES) and p.is_file():
                log.info("recorder: removing %s left by an interrupted write", p)
                p.unlink(missing_ok=True)

    def _write_logged(self, snap: _Snapshot) -> list[Path]:
        paths: list[Path] = []
        try:
            self._write(snap, paths)
        except Exception as exc:
            with self._lock:
                self.failures += 1
            reason = loss_reason(exc)
            self._count_loss(reason)
            if isinstance(exc, OSError):
                # The disk's state, not a bug: one line (a full disk logged ~25 lines of tracebacks per recording). The
                # next recording is tried as usual, and succeeds once there is room again.
                log.error("recorder: recording %s lost (%s): %s", snap.name, reason, exc.strerror or exc)
            else:
                log.exception("recorder: writing %s failed", snap.name)
            # What the failed format left half-written goes (a full disk kept every episode's staging file, outside
            # the size bound, until a restart); the formats written before it are complete recordings.
            for p in self.directory.glob(f"{snap.name}.*"):
                if p.name.endswith(STAGING_SUFFIXES):
                    p.unlink(missing_ok=True)
            raise
        finally:
            with self._lock:
                self.written.extend(paths)
                self.files_written += len(paths)
            try:
                self._enforce_bound(keep=snap.name)  # after a failure too: the disk is what fills
            except OSError as exc:
                log.error("recorder: enforcing max_total_mb failed: %s", exc.strerror or exc)
        log.info("recorder: wrote %s", ", ".join(str(p) for p in paths))
        return paths

    def _count_loss(self, reason: str) -> None:
        if self.metrics is not None:
            self.metrics.recordings_failed.labels(reason=reason).inc()

    def _write(self, snap: _Snapshot, paths: list[Path]) -> None:
        """Write ``snap`` in every format, appending each finished file to ``paths`` (a failure leaves the ones
        before it there)."""
        if snap.decisions:
            snap.meta["decisions"] = _decisions_meta(*snap.decisions)
        if not self.directory.is_dir():
            self._prepare_directory()  # removed while running: back with its mode (0750), not the default
        rec = Recording(t_us=snap.t_us, force=snap.force, disp=snap.disp, meta=snap.meta)
        for fmt in self.formats:
            final = self.directory / f"{snap.name}.{fmt}"
            staging = final.with_name(final.name + ".part")
            if fmt == "npz":
                rec.save(staging)
            elif fmt == "mcap":
                write_mcap(rec, staging)
            else:
                write_sdk_csv(rec, staging)
            _finalize(staging, final)
            paths.append(final)
        _fsync_dir(self.directory)

    def recordings(self) -> dict[str, list[Path]]:
        """Complete recordings in the directory: name stem -> its files, oldest first."""
        groups: dict[str, list[Path]] = {}
        for p in self.directory.iterdir():
            if p.name.startswith(PREFIX) and p.suffix in SUFFIXES and p.is_file():
                groups.setdefault(p.stem, []).append(p)
        return dict(sorted(groups.items()))

    def total_bytes(self) -> int:
        """Bytes used by the complete recordings in the directory."""
        return sum(_size(p) for files in self.recordings().values() for p in files)

    def _enforce_bound(self, keep: str) -> None:
        groups = self.recordings()
        total = sum(_size(p) for files in groups.values() for p in files)
        # Oldest first: another process's recordings (a run before a restart) by name, then this one's in the order
        # it wrote them. Names carry the wall-clock time, which after a reboot with the clock behind (no RTC, NTP not
        # synced yet) sorted every new recording before the stale ones, and the bound deleted the new ones.
        with self._lock:
            mine = list(dict.fromkeys(p.stem for p in self.written))
        own = set(mine)
        order = [stem for stem in groups if stem not in own] + [stem for stem in mine if stem in groups]
        for stem in order:
            files = groups[stem]
            if total <= self.max_total_bytes:
                break
            if stem == keep:
                continue
            for p in files:
                total -= _size(p)
                p.unlink(missing_ok=True)
                with self._lock:
                    self.deleted.append(p)
            log.info("recorder: deleted %s (max_total_mb)", stem)
        if total > self.max_total_bytes:
            log.warning("recorder: newest recording alone (%d bytes) exceeds max_total_mb", total)


_LOSS_REASONS = {errno.ENOSPC: "no_space", errno.EDQUOT: "no_space", errno.EROFS: "read_only",
                 errno.EACCES: "permission", errno.EPERM: "permission"}


def loss_reason(exc: BaseException) -> str:
    """The ``reason`` label of a lost recording (``slipd.metrics.RECORDING_FAILURES``)."""
    return _LOSS_REASONS.get(exc.errno or 0, "io") if isinstance(exc, OSError) else "io"


def _size(p: Path) -> int:
    try:
        return p.stat().st_size
    except FileNotFoundError:
        return 0


def _finalize(staging: Path, final: Path) -> None:
    """Flush the staged file to disk, set its mode, then give it its final name (atomic rename)."""
    fd = os.open(staging, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.fchmod(fd, FILE_MODE)
    finally:
        os.close(fd)
    os.replace(staging, final)


def _fsync_dir(directory: Path) -> None:
    """Make the renames durable (a power cut keeps the directory entries)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
