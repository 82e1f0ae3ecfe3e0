"""An emulated PapillArray controller on a pseudo-terminal: PTSCOM 2.0 frames in real time.

The emulator owns the master side of a pty; the daemon opens ``.port`` (a stable symlink in a
temporary folder that points at the current pty slave) with pyserial exactly as it opens
``/dev/ttyACM0``. Frames are paced on absolute deadlines from ``time.monotonic()``: a late wake-up
writes every frame that fell due (catch-up), so the long-run rate is exact and the device clock
(``t_us``) advances by exactly one period per frame.

Samples come from a :class:`~slipd.recording.Recording` (the sample nearest the device time, so a
lower rate decimates; ``loop=True`` replays it forever) or from a callable ``source(i)`` returning
``(force[9, 3], disp[9, 3])`` or None when done. A controller with two arrays (one per finger) is a
two-sensor recording ([N, 2, 9, 3]) or a source returning [2, 9, 3] arrays with ``sensors=2``: every
frame then carries both (``slipd.io.pts``); ``i`` counts the frames produced since ``start``
(the closed-loop rig supplies its physics that way).

Commands read from the pty: ``z`` zeroes the sensor: the mean of the next ``BIAS_S`` of raw samples is subtracted
from every frame after them (the controller needs the finger unloaded meanwhile, as the real one does),
``f100|f250|f500|f1000`` change the rate, ``S``/``s`` turn the controller's slip detection state on
and off (reported in the type 6 block; the per-pillar slip state is INELIGIBLE / CONTACT_AT_START by
the 0.5 N contact threshold while it is on, 0 while off; the controller's own slip algorithm is not
emulated).

Faults for tests: :meth:`inject_garbage`, :meth:`inject_truncated_frame`,
:meth:`inject_bad_checksum`, :meth:`inject_wrong_length`, :meth:`jump_counter`, :meth:`stall`,
:meth:`unplug` and :meth:`replug`. One-shot faults apply to the next frame produced.

Output that the reader does not drain waits in a bounded queue (``max_pending_bytes``); frames beyond
it are discarded and counted in ``frames_discarded``, as a real device's host buffer would overflow; the last
``DISCARD_LOG`` runs of discarded frames are kept in ``discard_log`` (when each began, how many) to say when the reader
fell behind.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import shutil
import tempfile
import threading
import time
import tty
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from slipd.geometry import CONTACT_THRESHOLD_N, N_PILLARS
from slipd.io.pts import (
    END,
    RATES_HZ,
    SLIP_CONTACT_AT_START,
    SLIP_INELIGIBLE,
    Frame,
    encode_frame,
    parse_command,
)
from slipd.recording import Recording, global_wrench

BIAS_S = 0.2
"""How long a bias averages the raw samples. The real controller needs the finger unloaded for a second and takes up to
two to zero itself: it averages, so its zero is off by far less than one sample's noise. A zero from one sample would
leave each pillar off by that sample's noise (up to 0.05 N), enough to move a light grasp's pillars across the 0.5 N
contact flag and the detector's decisions with them from run to run on the rig; 200 samples leave about 0.002 N."""

log = logging.getLogger(__name__)

SampleSource = Callable[[int], "tuple[np.ndarray, np.ndarray] | None"]


MAX_BURST = 5
"""Frames generated in one go before they are flushed to the pty (5 ms at 1 kHz)."""
DISCARD_LOG = 64
"""Runs of discarded frames kept in ``discard_log``: a bound, so a reader that never drains cannot grow it."""


class EmulatedPapillArray:
    """A PapillArray controller streaming PTSCOM 2.0 frames on a pty (see the module docstring)."""

    def __init__(
        self,
        source: Recording | SampleSource | None = None,
        rate_hz: int = 1000,
        *,
        loop: bool = False,
        link_dir: str | Path | None = None,
        max_pending_bytes: int = 256 * 1024,
        reset_counter_on_replug: bool = True,
        seed: int = 0,
        sensors: int | None = None,
        fixed_rate_hz: int | None = None,
    ) -> None:
        self.fixed_rate_hz = fixed_rate_hz
        """A controller that streams at this rate whatever it is told (another firmware, a faulty controller): any
        rate, rate commands recorded and ignored (``force_rate``). None: rate_hz, and rate commands obeyed."""
        if fixed_rate_hz is not None:
            rate_hz = fixed_rate_hz
        elif rate_hz not in RATES_HZ:
            raise ValueError(f"rate_hz {rate_hz} not supported by the PapillArray; choose one of {RATES_HZ}")
        self._source = source
        self.sensors = sensors or (source.sensors if isinstance(source, Recording) else 1)
        """Sensor arrays in each frame."""
        # Recording.rate_hz takes a median over the whole recording: compute it once, not per frame.
        self._source_rate = source.rate_hz if isinstance(source, Recording) else 0.0
        self.loop = loop
        self.rate_hz = rate_hz
        self.max_pending_bytes = max_pending_bytes
        self.reset_counter_on_replug = reset_counter_on_replug
        self._rng = np.random.default_rng(seed)
        self._own_dir = link_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="slipd-papillarray-")) if link_dir is None else Path(link_dir)
        self._dir.mkdir(parents=True, exist_ok=True)
        self.port = str(self._dir / "ttyPAPILLARRAY")
        """Path the reader opens: a symlink re-pointed to the current pty slave on replug."""

        self._lock = threading.RLock()
        self._master = -1
        self._slave = -1
        self._pending = bytearray()
        self._cmd_buf = bytearray()
        self._faults: collections.deque[tuple[str, object]] = collections.deque()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stall_until = 0.0
        self._counter = 0
        self._clock_offset_s = 0.0  # added to the device clock from a ``jump_clock`` on
        self._bias_force = np.zeros((self.sensors, N_PILLARS, 3), np.float32)
        self._bias_disp = np.zeros((self.sensors, N_PILLARS, 3), np.float32)
        self._bias_sum: tuple[np.ndarray, np.ndarray, int, int] | None = None
        """A bias under way: the sums of the raw (force, disp) so far, their count and how many it averages."""
        self.slip_detection = False
        self.finished = threading.Event()
        """Set when the source has no more samples (never with loop=True) or failed (see ``error``)."""
        self.error: Exception | None = None
        """What stopped the streaming thread, if it was not the end of the source."""
        self.frames_written = 0
        """Frames queued to the pty (streamed and via write_frames); discarded ones are not included."""
        self.frames_discarded = 0
        self.discard_log: collections.deque[tuple[float, int]] = collections.deque(maxlen=DISCARD_LOG)
        """Runs of consecutive discarded frames: (``time.monotonic()`` of the first, frames), the latest last."""
        self._discarding = False
        self.commands: list[tuple[str, object]] = []
        """Commands received, as (kind, value), in order."""
        self._plug()

    # ------------------------------------------------------------ pty
    @property
    def plugged(self) -> bool:
        """True while the pty exists (between unplug and replug it does not)."""
        return self._master >= 0

    @property
    def slave_path(self) -> str:
        """The current pty slave device (``.port`` points here)."""
        return os.ttyname(self._slave)

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: the pty carries bytes like a CDC device
        os.set_blocking(master, False)
        tmp = self.port + ".new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.port)  # atomic: a reader never sees a dangling half-made link
        with self._lock:
            self._master, self._slave = master, slave
            self._cmd_buf.clear()

    def unplug(self) -> None:
        """Pull the cable: close the pty (the reader sees EIO/hangup) and remove ``.port`` until replug."""
        with self._lock:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.port)
            for fd in (self._master, self._slave):
                if fd >= 0:
                    os.close(fd)
            self._master = self._slave = -1
            self._pending.clear()

    def replug(self) -> None:
        """Plug the cable back: a new pty behind the same ``.port`` path; the counter restarts and the bias is
        gone (a power cycle)."""
        with self._lock:
            if self._master >= 0:
                raise RuntimeError("replug() without unplug()")
            if self.reset_counter_on_replug:
                self._counter = 0
                self._bias_force[:] = 0.0
                self._bias_disp[:] = 0.0
                self._bias_sum = None
            self._plug()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start streaming from the source in a background thread."""
        if self._source is None:
            raise RuntimeError("no source: construct with a Recording or a callable to stream")
        if self._thread is not None:
            raise RuntimeError("already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="emulated-papillarray", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop streaming (the pty stays open)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def close(self) -> None:
        """Stop and remove the pty and the port link."""
        self.stop()
        self.unplug()
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> EmulatedPapillArray:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def counter(self) -> int:
        """Packet counter the next streamed frame will carry."""
        return self._counter

    # ------------------------------------------------------------ faults
    def inject_garbage(self, data: int | bytes = 64) -> None:
        """Write garbage before the next frame: ``data`` bytes, or that many random bytes."""
        if isinstance(data, int):
            data = self._rng.integers(0, 256, size=data, dtype=np.uint8).tobytes()
        self._faults.append(("garbage", bytes(data)))

    def inject_truncated_frame(self) -> None:
        """Send only the first half of the next frame (its counter is consumed, as if bytes were lost)."""
        self._faults.append(("truncate", None))

    def inject_bad_checksum(self) -> None:
        """Corrupt the checksum of the next frame."""
        self._faults.append(("checksum", None))

    def inject_wrong_length(self) -> None:
        """Insert a stray byte before the next frame's checksum, so its end marker is not where it belongs."""
        self._faults.append(("length", None))

    def force_rate(self, rate_hz: int | None) -> None:
        """Stream at ``rate_hz`` from now on whatever the host commands (None: obey rate commands again)."""
        self.fixed_rate_hz = rate_hz
        if rate_hz is not None:
            self.rate_hz = rate_hz

    def jump_counter(self, delta: int) -> None:
        """Add ``delta`` to the next frame's counter (delta > 0: frames look lost; < 0: counter goes back)."""
        self._faults.append(("jump", int(delta)))

    def jump_clock(self, seconds: float) -> None:
        """From the next frame on, the device clock reads ``seconds`` later (< 0: it went back); the counter and the
        samples go on as before."""
        self._faults.append(("clock", float(seconds)))

    def stall(self, ms: float) -> None:
        """Send nothing for ``ms`` milliseconds, then resume on fresh deadlines (no burst, counter continuous)."""
        self._stall_until = time.monotonic() + ms / 1000.0

    # ------------------------------------------------------------ bursts
    def write_frames(self, frames: Iterable[Frame | bytes], timeout: float = 30.0) -> int:
        """Queue frames (or raw bytes) at once and wait until the pty has taken them; returns frames queued.

        For burst tests. Bytes are passed through unchanged (use them for hand-made faults). Raises
        TimeoutError when the reader does not drain them within ``timeout`` seconds.
        """
        chunks = []
        n = 0
        for f in frames:
            if isinstance(f, Frame):
                chunks.append(encode_frame(f))
                n += 1
            else:
                chunks.append(bytes(f))
        with self._lock:
            if self._master < 0:
                raise RuntimeError("write_frames() while unplugged")
            self._pending += b"".join(chunks)
            self.frames_written += n
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                if self._thread is None:
                    self._flush()
                left = len(self._pending)
                master = self._master
            if not left:
                return n
            if time.monotonic() > deadline:
                raise TimeoutError(f"{left} bytes still queued after {timeout} s: is the reader running?")
            if master < 0:
                raise RuntimeError("unplugged during write_frames()")
            if self._thread is None:
                with contextlib.suppress(OSError, ValueError):
                    select.select([], [master], [], 0.01)
            else:
                time.sleep(0.001)

    # ------------------------------------------------------------ streaming
    def _sample(self, i: int, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        src = self._source
        if isinstance(src, Recording):
            n = len(src)
            if n == 0:
                return None
            k = round(t_s * self._source_rate)
            if k >= n:
                if not self.loop:
                    return None
                k %= n
            return src.force[k], src.disp[k]
        assert src is not None
        return src(i)

    @property
    def bias(self) -> tuple[np.ndarray, np.ndarray]:
        """The first sensor's (force, disp) offsets set by the last bias command, subtracted from every frame since."""
        with self._lock:
            return self._bias_force[0].copy(), self._bias_disp[0].copy()

    def _bias_step(self, raw_f: np.ndarray, raw_d: np.ndarray) -> None:
        """One raw sample into the bias under way; the zero changes once it has all its samples."""
        assert self._bias_sum is not None
        sum_f, sum_d, n, count = self._bias_sum
        sum_f += raw_f
        sum_d += raw_d
        n += 1
        if n < count:
            self._bias_sum = (sum_f, sum_d, n, count)
            return
        with self._lock:
            self._bias_force = (sum_f / n).astype(np.float32)
            self._bias_disp = (sum_d / n).astype(np.float32)
            self._bias_sum = None

    def _make_frame(self, i: int, t_s: float) -> bytes | None:
        sample = self._sample(i, t_s)
        if sample is None:
            return None
        shape = (self.sensors, N_PILLARS, 3)
        raw_f = np.asarray(sample[0], dtype=np.float32)
        raw_d = np.asarray(sample[1], dtype=np.float32)
        if raw_f.size != raw_d.size or raw_f.size != self.sensors * N_PILLARS * 3:
            want = "[9, 3]" if self.sensors == 1 else f"[{self.sensors}, 9, 3]"
            raise ValueError(f"source sample {i}: force/disp must be {want}; got {raw_f.shape}, {raw_d.shape}")
        raw_f, raw_d = raw_f.reshape(shape), raw_d.reshape(shape)
        if self._bias_sum is not None:
            self._bias_step(raw_f, raw_d)
        forces = raw_f - self._bias_force
        disps = raw_d - self._bias_disp
        force, disp = forces[0], disps[0]
        if self.slip_detection:
            state = np.where(force[:, 2] > CONTACT_THRESHOLD_N, SLIP_CONTACT_AT_START, SLIP_INELIGIBLE)
        else:
            state = np.zeros(N_PILLARS)
        counter = self._counter
        prefix = b""
        mode = None
        while self._faults:
            kind, value = self._faults.popleft()
            if kind == "garbage":
                prefix += value  # type: ignore[operator]
            elif kind == "jump":
                counter += value  # type: ignore[operator]
            elif kind == "clock":
                self._clock_offset_s += value  # type: ignore[operator]
            else:
                mode = kind
                break  # one corruption per frame; the rest wait for later frames
        frame = Frame(
            counter=counter % 2**32,
            t_us=max(0, round((t_s + self._clock_offset_s) * 1e6)),
            force=force,
            disp=disp,
            wrench=global_wrench(force[None])[0].astype(np.float32),
            slip_state=state.astype(np.int8),
            friction=np.full(N_PILLARS, -1.0, np.float32),
            sensor_state=1 if self.slip_detection else 0,
            others=tuple(zip(forces[1:], disps[1:])),
        )
        self._counter = (counter + 1) % 2**32
        data = encode_frame(frame)
        if mode == "truncate":
            data = data[: len(data) // 2]
        elif mode == "checksum":
            b = bytearray(data)
            b[-len(END) - 2] ^= 0xFF
            data = bytes(b)
        elif mode == "length":
            data = data[: -len(END) - 2] + b"\x00" + data[-len(END) - 2 :]
        return prefix + data

    def _run(self) -> None:
        try:
            self._stream()
        except Exception as exc:
            # A broken source must not die silently in a thread: keep the error for the caller.
            log.exception("emulated PapillArray: streaming stopped")
            self.error = exc
            self.finished.set()

    def _stream(self) -> None:
        period = 1.0 / self.rate_hz
        t0 = time.monotonic()
        next_t = t0
        t_dev = 0.0  # device clock (s) of the next frame
        i = 0
        while not self._stop.is_set():
            self._read_commands()
            if self.rate_hz != round(1.0 / period):
                period = 1.0 / self.rate_hz
                next_t = time.monotonic()  # re-anchor at the new rate
            now = time.monotonic()
            if now < self._stall_until:
                time.sleep(min(self._stall_until - now, 0.005))
                next_t = time.monotonic()
                continue
            burst = 0
            # Catch up on due frames, but flush at least every MAX_BURST frames: a source slower than real
            # time (a busy machine) must give a slower stream, not a long silence followed by a burst.
            while next_t <= now and not self.finished.is_set() and burst < MAX_BURST:
                burst += 1
                if self.plugged:
                    data = self._make_frame(i, t_dev)
                    if data is None:
                        self.finished.set()
                        break
                    with self._lock:
                        if len(self._pending) + len(data) > self.max_pending_bytes:
                            self._note_discard()
                        else:
                            self._pending += data
                            self.frames_written += 1
                            self._discarding = False
                    i += 1
                t_dev += period
                next_t += period
            with self._lock:
                self._flush()
                pending = bool(self._pending)
                master = self._master
            wait = max(0.0, next_t - time.monotonic())
            if master < 0 or self.finished.is_set():
                time.sleep(min(max(wait, 0.001), 0.005))
                continue
            # Wake for the next deadline, a command, or room in the pty when output is waiting.
            with contextlib.suppress(OSError, ValueError):
                select.select([master], [master] if pending else [], [], wait)

    def _note_discard(self) -> None:
        """Count one discarded frame, in the run it continues or a new one (caller holds the lock)."""
        self.frames_discarded += 1
        if self._discarding and self.discard_log:
            start, n = self.discard_log[-1]
            self.discard_log[-1] = (start, n + 1)
        else:
            self.discard_log.append((time.monotonic(), 1))
        self._discarding = True

    def _flush(self) -> None:
        """Write as much pending output as the pty takes now (caller holds the lock)."""
        while self._pending and self._master >= 0:
            try:
                n = os.write(self._master, self._pending)
            except BlockingIOError:
                return
            except OSError as exc:
                log.debug("emulated PapillArray: write failed (%s)", exc)
                return
            del self._pending[:n]

    def _read_commands(self) -> None:
        with self._lock:
            master = self._master
            if master < 0:
                return
            try:
                data = os.read(master, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # EIO while no reader has the slave open: nothing to read
            self._cmd_buf += data
            lines = self._cmd_buf.split(b"\n")
            self._cmd_buf[:] = lines.pop()
        for line in lines:
            if not line.strip():
                continue
            try:
                cmd = parse_command(line)
            except ValueError:
                log.warning("emulated PapillArray: ignoring unknown command %r", bytes(line))
                continue
            self.commands.append((cmd.kind, cmd.value))
            if cmd.kind == "bias":
                shape = (self.sensors, N_PILLARS, 3)
                count = max(1, round(BIAS_S * self.rate_hz))
                self._bias_sum = (np.zeros(shape), np.zeros(shape), 0, count)
            elif cmd.kind == "rate":
                self.rate_hz = self.fixed_rate_hz or int(cmd.value)  # type: ignore[arg-type]
            elif cmd.kind == "slip":
                self.slip_detection = bool(cmd.value)
