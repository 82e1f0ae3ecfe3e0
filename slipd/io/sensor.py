"""Serial reader of the PapillArray: PTSCOM 2.0 frames into the asyncio loop, with reconnects.

The port is read on the loop's own thread: ``loop.add_reader`` wakes us when bytes are waiting, one
non-blocking ``readv`` fills a preallocated buffer, the decoder turns it into frames and the consumer
gets them at once: ``on_block(block)`` with a ``FrameBlock`` (arrays in the decoder's preallocated
storage: the daemon's path, no object per frame), or ``on_frames(frames)`` with ``Frame`` objects. No
thread hop per sample.

Opening: pyserial with ``exclusive=True`` (an flock, so a second daemon cannot interleave reads),
then the kernel's low-latency flag (TIOCSSERIAL ASYNC_LOW_LATENCY) where the driver supports it, and a
warning when an FTDI adapter's latency timer would batch frames (the PapillArray itself is USB CDC ACM,
which has none).

Packet counter accounting, per frame (vectorised over a read; the loop below runs only when a read holds
something other than consecutive counters):
    counter + 1                  normal
    counter + 2 .. + max_gap     ``dropped_before`` = missing frames, counted in ``dropped_frames``
    equal                        a repeated sample, not a new one: dropped before ``on_frames`` and
                                 counted in ``repeated_frames`` (``frame_errors{kind="repeated_counter"}``);
                                 a counter that never advances therefore starves the daemon's liveness
                                 check instead of restarting the detector on every frame
    backwards, or a jump larger than ``max_gap``
                                 ``discontinuity`` = True (the consumer resets its state), counted in
                                 ``discontinuities``; nothing counted as dropped
The first frame after a reconnect is flagged as a discontinuity too (the link was down; how many frames
that cost is unknowable when the controller restarts its counter). The counter wraps at 2**32.

Holding frames back: between decisions the consumer needs no frame the moment it lands, only the one that
completes its next window. ``hold_for(n, ...)`` makes the reader keep the bytes it reads in the decoder's
buffer, undecoded (``FrameDecoder.stash``), until about ``n`` frames' worth have gathered, pausing itself
between reads, and then decode them and hand them over as one block: one decode and one pass of the
consumer's per-block work per decision instead of one per read (a read is capped by the kernel's tty
buffer, see ``pause``). More than ``max_s`` since the first held byte, ``HOLD_MAX_FRAMES``, or a buffer
without room deliver at once; counters and metrics are updated when the frames are decoded.

Arrival clock: the reader keeps an estimate of when the latest frame reached the host (a periodic model
of the packet counter, tightened by every read: a frame arrived no later than the read that found it),
so a consumer that pauses the reader (``pause``) can resume just before the frame it waits for
(``expected_arrival``) instead of waking for every frame on the way.

On EOF, EIO or hangup the reader closes the port, calls ``on_disconnect(reason)`` and retries the open
with exponential backoff (``reconnect_initial_s`` doubling up to ``reconnect_max_s``); each success
after a loss counts in ``reconnects``.
"""

from __future__ import annotations

import array
import asyncio
import contextlib
import errno
import fcntl
import logging
import os
import struct
import termios
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import serial

from slipd.io.pts import Frame, FrameBlock, FrameDecoder
from slipd.metrics import Metrics

log = logging.getLogger(__name__)

# linux/serial.h and asm-generic/ioctls.h
_TIOCGSERIAL = 0x541E
_TIOCSSERIAL = 0x541F
_ASYNC_LOW_LATENCY = 1 << 13
_SERIAL_FLAGS_OFFSET = 16  # struct serial_struct: int type, int line, unsigned port, int irq, int flags
_SERIAL_STRUCT_BYTES = 128  # larger than the kernel's struct on every ABI; the kernel copies its own size

FTDI_SYSFS = "/sys/bus/usb-serial/devices"
TTY_BUFFER_BYTES = 4096
"""The kernel's n_tty read buffer: one read() returns at most this less one byte, and a buffer this full throttles
the port."""
PAUSE_SPILL_BYTES = 1024
"""What a pause may let pile up beyond ``TTY_BUFFER_BYTES``. Throttling loses nothing by itself: the bytes already
on their way wait in the tty's flip buffer (a pty's writer does not block before 64 KiB; USB CDC ACM keeps its 16
read URBs in flight, 2 KiB at full speed and 16 KiB at high speed, before the device sees a NAK), and a read that
empties the line discipline's buffer pulls them through at once (``_on_readable`` reads on). 1 KiB (2.4 ms of
one-sensor frames at 1 kHz) lets one pause cover a 10 ms decision (4.3 KiB; it covered 7 frames when pauses stopped
at 75 % of the kernel buffer, so most decisions took three reads instead of two) and keeps at least as much again
for a late timer. Should the device ever be held back, the packet counter says so (``dropped_frames``)."""
HOLD_MAX_FRAMES = 256
"""Most frames held back at once (a bound on the decoder storage a hold may use)."""
ARRIVAL_REANCHOR_S = 0.003
"""A read this much later than the arrival clock predicts re-anchors it (a stall, a restarted stream)."""
ARRIVAL_LEAK = 0.01
"""The arrival clock may run this fraction slower than the nominal period between reads (sensor and host
clocks differ by ~1e-4); a read that finds a frame earlier than predicted pulls it back at once."""


class SensorError(RuntimeError):
    """The sensor port cannot be opened or written; the message names the port and the reason."""


def set_low_latency(fd: int, port: str = "") -> bool:
    """Set ASYNC_LOW_LATENCY on a serial fd. Returns False (logged at debug) where the driver lacks it."""
    buf = array.array("b", bytes(_SERIAL_STRUCT_BYTES))
    try:
        fcntl.ioctl(fd, _TIOCGSERIAL, buf, True)
        flags = int.from_bytes(buf[_SERIAL_FLAGS_OFFSET : _SERIAL_FLAGS_OFFSET + 4].tobytes(), "little", signed=True)
        if flags & _ASYNC_LOW_LATENCY:
            return True
        flags |= _ASYNC_LOW_LATENCY
        buf[_SERIAL_FLAGS_OFFSET : _SERIAL_FLAGS_OFFSET + 4] = array.array(
            "b", flags.to_bytes(4, "little", signed=True)
        )
        fcntl.ioctl(fd, _TIOCSSERIAL, buf, True)
    except OSError as exc:
        # A pty or a CDC ACM device without TIOCSSERIAL: nothing to set, reads are already immediate.
        log.debug("%s: low-latency mode not supported (%s)", port or fd, exc)
        return False
    log.debug("%s: low-latency mode set", port or fd)
    return True


def check_latency_timer(port: str, sysfs_root: str | Path = FTDI_SYSFS) -> int | None:
    """Warn when a USB-serial adapter's latency timer (ms) would batch 1 kHz frames; returns it or None."""
    tty = os.path.basename(os.path.realpath(port))
    path = Path(sysfs_root) / tty / "latency_timer"
    try:
        value = int(path.read_text().strip())
    except (OSError, ValueError):
        return None
    if value > 1:
        log.warning(
            "%s: USB latency timer is %d ms (%s); frames arrive in batches. Set it to 1: echo 1 > %s",
            port, value, path, path,
        )
    return value


class SerialSensor:
    """Reads PTSCOM 2.0 frames from a serial port inside the running asyncio loop.

    ``on_block(block)`` (or ``on_frames(frames)``) and ``on_disconnect(reason)`` are called on the loop's
    thread; an exception they raise is logged and does not stop the reader. ``baudrate`` is nominal (CDC
    ignores it). ``sensors``: the arrays read from each frame (``slipd.io.pts``); ``rate_hz`` the nominal
    frame rate (the arrival clock's period).
    """

    def __init__(
        self,
        port: str,
        on_frames: Callable[[list[Frame]], None] | None = None,
        *,
        on_block: Callable[[FrameBlock], None] | None = None,
        sensors: int = 1,
        rate_hz: float = 1000.0,
        baudrate: int = 115200,
        on_disconnect: Callable[[str], None] | None = None,
        on_reconnect: Callable[[], None] | None = None,
        reconnect_initial_s: float = 0.05,
        reconnect_max_s: float = 2.0,
        metrics: Metrics | None = None,
        max_gap: int = 60_000,
        read_bytes: int = 1 << 16,
        sysfs_root: str | Path = FTDI_SYSFS,
        low_latency: bool = True,
    ) -> None:
        if (on_frames is None) == (on_block is None):
            raise ValueError("give exactly one of on_frames (Frame objects) and on_block (FrameBlock arrays)")
        if reconnect_initial_s <= 0 or reconnect_max_s < reconnect_initial_s:
            raise ValueError(
                f"reconnect backoff needs 0 < initial ({reconnect_initial_s}) <= max ({reconnect_max_s})"
            )
        self.port = port
        self.baudrate = baudrate
        self.on_frames = on_frames
        self.on_block = on_block
        self.period_s = 1.0 / rate_hz
        self.on_disconnect = on_disconnect
        self.on_reconnect = on_reconnect
        """Called once the port is open again after a loss (the controller may have been power-cycled: its rate and
        bias are its defaults again)."""
        self.reconnect_initial_s = reconnect_initial_s
        self.reconnect_max_s = reconnect_max_s
        self.max_gap = max_gap
        self.sysfs_root = sysfs_root
        self.decoder = FrameDecoder(sensors)
        self._rbuf = bytearray(read_bytes)
        self._rview = memoryview(self._rbuf)
        self._serial: serial.Serial | None = None
        self._fd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reconnect_task: asyncio.Task[None] | None = None
        self._stopping = False
        self._connected = asyncio.Event()
        self._last_counter: int | None = None
        self._after_reconnect = False
        # Counters (cumulative over reconnects).
        self.frames = 0
        self.dropped_frames = 0
        self.starting = False
        """Set by a consumer that is not live yet (the daemon before its first live decision): counter gaps meanwhile
        are frames the controller streamed before the port was read, counted in ``discarded_at_start``
        (``slipd_frames_discarded_at_start_total``), not as losses."""
        self.discarded_at_start = 0
        self.discontinuities = 0
        self.repeated_frames = 0
        self.last_repeat_time: float | None = None
        """time.monotonic() of the read that delivered the latest repeated-counter frame."""
        self.reconnects = 0
        self.disconnects = 0
        self.want_low_latency = low_latency
        self.low_latency = False
        self.frame_bytes = 0
        """Bytes per frame seen on the latest read (sizes the coalescing pauses)."""
        self.pauses = 0
        """Times the reader was paused by ``pause`` (frames coalesced into one later read)."""
        self._resume_handle: asyncio.TimerHandle | None = None
        self._watching = False  # the fd is registered with the loop (add_reader)
        self.last_frame_time: float | None = None
        """time.monotonic() of the read that delivered the latest frame (None before the first)."""
        self._arrival: float | None = None  # estimated time.monotonic() at which the latest frame arrived
        self._held = 0  # bytes stashed in the decoder, not decoded yet
        self._held_frames = 0  # frames those bytes complete (end markers)
        self._hold_frames = 0  # deliver once this many are held (0: at once)
        self._hold_max_s = 0.0
        self._held_read_t = 0.0  # when the last held bytes were read
        self._read_t = 0.0  # when the latest read returned
        self._read_drained = False  # it returned less than it asked for: it emptied the port
        self._hold_margin_s = 0.0
        self._hold_since = 0.0
        self._flush_handle: asyncio.TimerHandle | None = None
        self._metrics = metrics
        self._seen_errors = dict.fromkeys(FrameDecoder.ERROR_KINDS, 0)
        self._seen_garbage = 0
        if metrics is not None:
            kinds = (*FrameDecoder.ERROR_KINDS, "discontinuity", "repeated_counter")
            self._m_errors = {k: metrics.frame_errors.labels(kind=k) for k in kinds}
            self._m_reconnects = metrics.reconnects.labels(device="sensor")

    # ------------------------------------------------------------ lifecycle
    @property
    def connected(self) -> bool:
        """True while the port is open and being read."""
        return self._fd >= 0

    @property
    def last_counter(self) -> int | None:
        """Packet counter of the latest frame."""
        return self._last_counter

    async def start(self) -> None:
        """Open the port and start reading. Raises SensorError when the first open fails."""
        self._loop = asyncio.get_running_loop()
        self._stopping = False
        try:
            self._open()
        except (serial.SerialException, OSError) as exc:
            raise SensorError(f"{self.port}: cannot open sensor port ({exc})") from exc

    async def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until the port is open (after a reconnect); False on timeout."""
        try:
            await asyncio.wait_for(self._connected.wait(), timeout)
        except asyncio.TimeoutError:
            return False
        return True

    async def stop(self) -> None:
        """Stop reading, cancel reconnecting and close the port."""
        self._stopping = True
        task, self._reconnect_task = self._reconnect_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._drain()
        self._close()

    def _drain(self) -> None:
        """At a stop, hand over what is held back or waits in the port (a pause or a hold leaves up to a
        decision's worth of frames there), so that the consumer and the recorder see every frame that came."""
        self._cancel_pause()
        self._hold_frames = 0  # no further holds: every read below is delivered
        for _ in range(64):  # bounded: a device that keeps streaming cannot keep the stop waiting
            if self._fd < 0 or self.pending_bytes() <= 0:
                break
            self._on_readable(prompt=False)
        if self._held and self._fd >= 0:
            self._flush_held(force=True)

    def send_command(self, data: bytes) -> None:
        """Write a controller command (see slipd.io.pts: CMD_BIAS, rate_command(...)). SensorError if not open."""
        if self._fd < 0:
            raise SensorError(f"{self.port}: cannot send {data!r}: sensor not connected")
        view = memoryview(data)
        deadline = time.monotonic() + 0.1
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                # Commands are a few bytes; a full output queue for 100 ms means the device is not reading.
                if time.monotonic() > deadline:
                    raise SensorError(f"{self.port}: output queue full, command {data!r} not sent") from None
                time.sleep(0.001)
                continue
            except OSError as exc:
                self._lost(f"write error: {exc}")
                raise SensorError(f"{self.port}: cannot send {data!r} ({exc})") from exc
            view = view[n:]

    # ------------------------------------------------------------ port
    def _open(self) -> None:
        ser = serial.Serial(self.port, self.baudrate, timeout=0, write_timeout=0, exclusive=True)
        try:
            fd = ser.fileno()
            flags = fcntl.fcntl(fd, fcntl.F_GETFL)
            fcntl.fcntl(fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            self.low_latency = set_low_latency(fd, self.port) if self.want_low_latency else False
            check_latency_timer(self.port, self.sysfs_root)
            assert self._loop is not None
            self._loop.add_reader(fd, self._on_readable)
            self._watching = True
        except BaseException:
            ser.close()
            raise
        self._serial, self._fd = ser, fd
        self.decoder.reset()
        self._connected.set()
        log.info("%s: sensor port open", self.port)

    def pause(self, seconds: float, rate_hz: float) -> bool:
        """Stop watching the port for up to ``seconds``; the frames that arrive meanwhile are read in one go.

        The control loop calls this when it knows no decision is due before then: frames wait in the
        kernel's tty buffer, nothing is lost, and the loop wakes a few times per window instead of once per
        1 ms frame. The pause is refused while the loop is behind (the latest read did not empty the port, or there
        was none: the kernel is asked, and bytes waiting mean read first) and capped so that the bytes due from that
        read until the resume fill the kernel's 4 KiB line-discipline buffer and spill at most ``PAUSE_SPILL_BYTES``
        beyond it, which waits in the tty's flip buffer and is read in the same wake-up (a device held back further
        would queue frames, or lose them, on its side). A frame that came after a read that emptied the port, while
        the consumer handled what it brought, does not mean the loop is behind: the cap counts from the read, so it
        waits with the rest. Asking the kernel (FIONREAD) once per decision instead refused the pause whenever a
        frame had landed during the decision; dropping that saved 0.35 points of a core per pair at one sensor and
        stride 10 (docs/results.md, ``tools/bench_daemon.py --baseline-tree ... --paired``).
        Returns True when the reader was paused.
        """
        if self._fd < 0 or self._loop is None or self._resume_handle is not None or seconds <= 0:
            return False
        drained = self._read_drained
        if self.frame_bytes > 0 and rate_hz > 0:
            cap = (TTY_BUFFER_BYTES + PAUSE_SPILL_BYTES) / (self.frame_bytes * rate_hz)
            if drained:
                cap -= time.monotonic() - self._read_t  # what arrived since the read is in the buffer already
            seconds = min(seconds, cap)
        if seconds < 1e-3 or (not drained and self.pending_bytes() > 0):
            return False
        if self._watching:
            self._loop.remove_reader(self._fd)
            self._watching = False
        self._resume_handle = self._loop.call_later(seconds, self._resume)
        self.pauses += 1
        return True

    def hold_for(self, frames: int, max_s: float, margin_s: float) -> None:
        """Hold the next frames back until ``frames`` have gathered (or ``max_s`` passed since the first), then
        deliver them as one block; meanwhile pause between reads, resuming ``margin_s`` before the frame
        that completes the hold is due (module docstring). ``frames`` <= 1: deliver every read."""
        self._hold_frames = min(int(frames), HOLD_MAX_FRAMES)
        self._hold_max_s = max_s
        self._hold_margin_s = margin_s

    def pending_bytes(self) -> int:
        """Bytes received by the kernel and not read yet (FIONREAD); 0 when closed or unknown."""
        if self._fd < 0:
            return 0
        try:
            return int(struct.unpack("i", fcntl.ioctl(self._fd, termios.FIONREAD, b"\0\0\0\0"))[0])
        except OSError:
            return 0

    def expected_arrival(self, frames_ahead: int) -> float | None:
        """Estimated ``time.monotonic()`` at which the frame ``frames_ahead`` after the latest one arrives
        (None before the first frame): the arrival clock of the module docstring."""
        if self._arrival is None:
            return None
        return self._arrival + frames_ahead * self.period_s

    def _tick_arrival(self, now: float, new: int, prompt: bool = True) -> None:
        """Advance the arrival clock by ``new`` frames read at ``now`` (an upper bound on their arrival).

        ``prompt``: the read came from the port's readiness (the frames had just arrived), not at the end of
        a pause (they may have waited): only a prompt read that is far later than predicted re-anchors the
        clock (a stall, a restarted stream); a late read after a pause says nothing about arrival."""
        est = self._arrival
        if est is None:
            self._arrival = now
            return
        pred = est + new * self.period_s
        if now < pred or (prompt and now - pred > ARRIVAL_REANCHOR_S):
            self._arrival = now
        else:
            self._arrival = min(now, pred + ARRIVAL_LEAK * new * self.period_s)

    def _resume(self) -> None:
        """End of a pause: read what piled up at once (no wait for the loop to report the fd readable);
        watch the port again unless that read's consumer paused once more (then it stays unwatched,
        which saves two epoll_ctl calls and a loop pass per coalesced read)."""
        self._resume_handle = None
        if self._fd < 0 or self._loop is None:
            return
        # Read straight away (the deciding frame is due: bytes almost always wait, and asking the kernel first
        # costs an ioctl per pause). With VMIN = VTIME = 0 a read of an empty tty returns 0, as EOF does, so
        # here 0 means "nothing yet": an empty (or hung-up) port is left to the loop's readiness report.
        self._on_readable(prompt=False, empty_ok=True)
        if self._fd >= 0 and self._resume_handle is None and not self._watching:
            self._loop.add_reader(self._fd, self._on_readable)
            self._watching = True

    def _cancel_pause(self) -> None:
        if self._resume_handle is not None:
            self._resume_handle.cancel()
            self._resume_handle = None

    def _close(self) -> None:
        self._cancel_pause()
        if self._fd >= 0 and self._loop is not None and self._watching:
            self._loop.remove_reader(self._fd)
        self._watching = False
        if self._serial is not None:
            with contextlib.suppress(Exception):
                self._serial.close()
        self._serial, self._fd = None, -1
        self._connected.clear()
        self._held = self._hold_frames = 0
        self._read_drained = False
        if self._flush_handle is not None:
            self._flush_handle.cancel()
            self._flush_handle = None

    def _lost(self, reason: str) -> None:
        """The link died: close, tell the consumer, and start reconnecting."""
        if self._fd < 0:
            return
        self._close()
        self.disconnects += 1
        self._after_reconnect = True
        # A consumer that is told (the daemon's blind line names the reason) makes this a detail.
        log.log(logging.INFO if self.on_disconnect is not None else logging.WARNING, "%s: sensor disconnected (%s)",
                self.port, reason)
        if self.on_disconnect is not None:
            try:
                self.on_disconnect(reason)
            except Exception:
                log.exception("on_disconnect callback failed")
        if not self._stopping and self._loop is not None:
            self._reconnect_task = self._loop.create_task(self._reconnect())

    async def _reconnect(self) -> None:
        delay = self.reconnect_initial_s
        while not self._stopping:
            await asyncio.sleep(delay)
            try:
                self._open()
            except (serial.SerialException, OSError) as exc:
                log.debug("%s: reconnect failed (%s); next try in %.3f s", self.port, exc, delay)
                delay = min(delay * 2, self.reconnect_max_s)
                continue
            self.reconnects += 1
            if self._metrics is not None:
                self._m_reconnects.inc()
            log.info("%s: sensor reconnected (reconnect #%d)", self.port, self.reconnects)
            if self.on_reconnect is not None:
                try:
                    self.on_reconnect()
                except Exception:
                    log.exception("on_reconnect callback failed")
            return

    # ------------------------------------------------------------ reading
    def _on_readable(self, prompt: bool = True, empty_ok: bool = False) -> None:
        try:
            n = os.readv(self._fd, [self._rbuf])
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            reason = "hangup (EIO)" if exc.errno == errno.EIO else f"read error: {exc}"
            self._lost(reason)
            return
        last = n
        while last >= TTY_BUFFER_BYTES - 1 and n < len(self._rbuf):
            # The line discipline's buffer was full: what came after waits in the flip buffer, and the next read
            # pushes it through (the kernel flushes it synchronously), so a pause that spilled
            # (``PAUSE_SPILL_BYTES``) costs one wake-up, not two.
            try:
                last = os.readv(self._fd, [self._rview[n:]])
            except OSError:
                break  # drained (EAGAIN); an error on the port shows on the next read, after these bytes
            n += last
        now = self._read_t = time.monotonic()
        self._read_drained = n < len(self._rbuf)
        if n == 0:
            if not empty_ok:
                self._lost("EOF")
            return
        if self.on_block is not None and self._hold(n, now, prompt):
            return
        self._deliver(n, now, prompt)

    def _flush_held(self, force: bool = False) -> None:
        """The hold's time may be up: hand over what is held when no read ended the hold in time (the stream
        stopped, or slowed); a later hold that is still young re-arms the timer for its own deadline.
        ``force``: hand it over now (a stop)."""
        if self._flush_handle is not None:
            self._flush_handle.cancel()  # a no-op when this is the timer's own call
            self._flush_handle = None
        if not self._held or self._fd < 0:
            return
        deadline = self._hold_since + self._hold_max_s
        if not force and self._loop is not None and time.monotonic() < deadline:
            self._flush_handle = self._loop.call_at(deadline, self._flush_held)
        else:
            self._hold_frames = 0
            # Stamped with the last read's time, not the flush's: these frames are that old, and liveness
            # (a stall, a missing decision) counts from when data last arrived.
            self._deliver(0, self._held_read_t)

    def _deliver(self, n: int, now: float, prompt: bool = False) -> None:
        """Decode the held bytes and the ``n`` just read, account for them and hand them to the consumer."""
        held, self._held = self._held, 0
        frames: list[Frame] | None = None
        if self.on_block is not None:
            block = self.decoder.feed_block(self._rview[:n])
        else:
            frames = self.decoder.feed(self._rview[:n])
            block = self.decoder.block()
        if self._metrics is not None:
            self._update_error_metrics()
        k = len(block)
        if not k:
            return
        self.last_frame_time = now
        ticked = self._held_frames if held else 0  # the arrival clock followed these while they were stashed
        self._held_frames = 0
        self.frame_bytes = (held + n) // k
        if self._after_reconnect or self._last_counter is None:
            self._arrival = None
        if k > ticked:
            self._tick_arrival(now, k - ticked, prompt)
        keep = self._account(block)
        if frames is not None:
            for f, d, b in zip(frames, block.dropped_before.tolist(), block.discontinuity.tolist()):
                f.dropped_before, f.discontinuity = d, b
            if keep is not None:
                frames = [f for f, ok in zip(frames, keep.tolist()) if ok]
            if not frames:
                return
        elif keep is not None:
            block = block.select(keep)
            if not len(block):
                return
        try:
            if frames is not None:
                assert self.on_frames is not None
                self.on_frames(frames)
            else:
                assert self.on_block is not None
                self.on_block(block)
        except Exception:
            log.exception("on_frames callback failed")

    def _hold(self, n: int, now: float, prompt: bool) -> bool:
        """Whether to stash the ``n`` bytes just read instead of decoding them (``hold_for``); when so, pause
        until shortly before the frame that completes the hold is due."""
        want = self._hold_frames
        if want <= 1 or self._arrival is None:
            return False
        if self._held == 0:
            # Counted from the last hand-over, not from this read: the pause before it already kept frames from the
            # stall check, and pause plus hold reached the stall timeout itself (a false stall after a restart, when
            # a decision needs a whole window, with stall timeouts of about 23 ms and less).
            last = self.last_frame_time
            self._hold_since = now if last is None else min(now, last)
            self._held_frames = 0
        if now - self._hold_since >= self._hold_max_s:
            self._hold_frames = 0
            return False
        done = self.decoder.stash(self._rview[:n])
        if done is None:
            self._hold_frames = 0
            return False
        self._held_read_t = now
        if self._held == 0 and self._flush_handle is None and self._loop is not None:
            # However the stream goes on (or stops), what is held reaches the consumer within max_s. One timer
            # serves every hold: a delivery leaves it armed (it then finds nothing held, or re-arms for the
            # newer hold's deadline), so a hold per decision adds no timer to the loop's heap.
            self._flush_handle = self._loop.call_at(now + self._hold_max_s, self._flush_held)
        self._held += n
        self._held_frames += done
        if done:
            self._tick_arrival(now, done, prompt)
        if self._held_frames >= want:
            self._hold_frames = 0
            self._deliver(0, now)  # the deciding frame is in: decode the lot at once
            return True
        due = self.expected_arrival(want - self._held_frames)
        if due is not None:
            self.pause(due - self._hold_margin_s - now, 1.0 / self.period_s)
        return True

    def _account(self, block: FrameBlock) -> np.ndarray | None:
        """Gap and discontinuity detection from the packet counter: fills ``block.dropped_before`` and
        ``block.discontinuity``; returns the mask of frames to keep (None: all; repeats are dropped)."""
        c = block.counter
        k = len(c)
        last = self._last_counter
        ok = last is not None and not self._after_reconnect
        if ok:
            # Consecutive counters, the common read: a loop over plain ints costs less than numpy's calls on the few
            # frames of a read.
            before = last
            for ci in c.tolist():
                if (ci - before) & 0xFFFFFFFF != 1:
                    ok = False
                    break
                before = ci
        keep = None
        dropped = breaks = repeats = 0
        if ok:
            last = int(c[-1])
        else:
            # Something other than consecutive counters (start, reconnect, gap, repeat): frame by frame.
            keep = np.ones(k, bool)
            for i, ci in enumerate(c.tolist()):
                if last is None:
                    pass
                elif self._after_reconnect:
                    block.discontinuity[i] = True
                    breaks += 1
                else:
                    diff = (ci - last) & 0xFFFFFFFF
                    if diff == 0:
                        keep[i] = False
                        repeats += 1
                        continue
                    if diff != 1:
                        if 1 < diff <= self.max_gap:
                            block.dropped_before[i] = diff - 1
                            dropped += diff - 1
                        else:
                            block.discontinuity[i] = True
                            breaks += 1
                self._after_reconnect = False
                last = ci
            if not repeats:
                keep = None
        self._last_counter = last
        self.frames += k
        if self.starting:
            self.discarded_at_start += dropped
        else:
            self.dropped_frames += dropped
        self.discontinuities += breaks
        m = self._metrics
        if m is not None:
            m.frames.inc(k)
            if dropped:
                (m.frames_discarded_at_start if self.starting else m.dropped_frames).inc(dropped)
            if breaks:
                self._m_errors["discontinuity"].inc(breaks)
            if repeats:
                self._m_errors["repeated_counter"].inc(repeats)
        if repeats:
            self.repeated_frames += repeats
            self.last_repeat_time = self.last_frame_time
        return keep

    def _update_error_metrics(self) -> None:
        d = self.decoder
        if d.garbage_bytes != self._seen_garbage:
            assert self._metrics is not None
            self._metrics.garbage_bytes.inc(d.garbage_bytes - self._seen_garbage)
            self._seen_garbage = d.garbage_bytes
        for kind, seen in self._seen_errors.items():
            now = getattr(d, kind)
            if now != seen:
                self._m_errors[kind].inc(now - seen)
                self._seen_errors[kind] = now
