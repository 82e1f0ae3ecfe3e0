"""Fuzz the PTSCOM 2.0 decoder: random streams of valid, corrupted and junk bytes, in random splits.

Each input is a short byte string made of intact frames (unique counters below 2**31), mutated frames
(bit flips, inserted or deleted bytes, truncation, swapped markers; counters from 2**31 up) and junk
(random bytes, lone start/end markers, marker fragments). Inputs are fed to one long-lived decoder in
random-sized reads, as a serial port would deliver them. Checked:

- the decoder never raises;
- every intact frame is found, with the counter and forces it was encoded with (recall);
- frames returned have the documented shapes and dtypes.

Prints inputs tried, bytes fed, frames found, intact frames missed, exceptions, time and peak memory.
Exit status 1 when an exception or a missed intact frame occurred.

    python tools/fuzz_pts.py                 # 100 000 inputs
    python tools/fuzz_pts.py -n 5000 --seed 3
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
import traceback
import tracemalloc
from dataclasses import dataclass, field

import numpy as np

from slipd.io.pts import END, START, Frame, FrameDecoder, encode_frame


@dataclass
class FuzzReport:
    """Outcome of a fuzz run."""

    inputs: int = 0
    bytes_fed: int = 0
    frames_found: int = 0
    intact_sent: int = 0
    intact_missed: int = 0
    wrong_values: int = 0
    exceptions: int = 0
    seconds: float = 0.0
    peak_rss_mib: float = 0.0
    peak_traced_mib: float | None = None
    errors: dict[str, int] = field(default_factory=dict)
    garbage_bytes: int = 0
    first_exception: str = ""

    @property
    def ok(self) -> bool:
        """No exception, every intact frame found with its values."""
        return self.exceptions == 0 and self.intact_missed == 0 and self.wrong_values == 0


def _random_frame(rng: np.random.Generator, counter: int) -> Frame:
    force = rng.normal(0.0, 3.0, size=(9, 3)).astype(np.float32)
    disp = rng.normal(0.0, 0.5, size=(9, 3)).astype(np.float32)
    if rng.random() < 0.02:
        force.flat[rng.integers(27)] = np.nan  # non-finite values are data, not framing errors
    frame = Frame(counter, int(rng.integers(0, 2**63)), force, disp)
    if rng.random() < 0.7:
        frame.wrench = rng.normal(size=6).astype(np.float32)
    if rng.random() < 0.6:
        frame.slip_state = rng.integers(-2, 4, size=9).astype(np.int8)
        frame.friction = rng.random(9).astype(np.float32)
    if rng.random() < 0.6:
        frame.sensor_state = int(rng.integers(0, 3))
        frame.friction_est = float(rng.random())
        frame.target_grip_force = float(rng.random() * 10)
    return frame


def _mutate(rng: np.random.Generator, data: bytes) -> bytes:
    b = bytearray(data)
    kind = rng.integers(6)
    if kind == 0:  # bit flips anywhere
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(len(b)))
            b[i] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # inserted bytes
        i = int(rng.integers(len(b)))
        b[i:i] = rng.integers(0, 256, size=int(rng.integers(1, 8)), dtype=np.uint8).tobytes()
    elif kind == 2:  # deleted bytes
        i = int(rng.integers(len(b) - 1))
        del b[i : i + int(rng.integers(1, 8))]
    elif kind == 3:  # truncated
        del b[int(rng.integers(1, len(b))) :]
    elif kind == 4:  # end marker inside the payload, as a float could contain it
        i = int(rng.integers(4, len(b) - 10))
        b[i : i + 4] = END
    else:  # header damage: index size or a table entry
        i = int(rng.integers(4, 30))
        b[i] = int(rng.integers(256))
    return bytes(b)


def _junk(rng: np.random.Generator) -> bytes:
    kind = rng.integers(4)
    if kind == 0:
        return rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes()
    if kind == 1:
        return START
    if kind == 2:
        return END + START[: int(rng.integers(1, 4))]
    return START + rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8).tobytes()


def fuzz(n_inputs: int = 100_000, seed: int = 0, trace_memory: bool = False) -> FuzzReport:
    """Run ``n_inputs`` random inputs through one FrameDecoder; return what happened."""
    rng = np.random.default_rng(seed)
    rep = FuzzReport()
    decoder = FrameDecoder()
    expected: dict[int, np.ndarray] = {}  # intact counter -> force it carries
    next_intact = 0
    next_mutant = 2**31
    if trace_memory:
        tracemalloc.start()
    t0 = time.perf_counter()

    def take(frames: list[Frame]) -> None:
        rep.frames_found += len(frames)
        for f in frames:
            if f.force.shape != (9, 3) or f.force.dtype != np.float32 or f.disp.shape != (9, 3):
                rep.wrong_values += 1
            want = expected.pop(f.counter, None)
            if want is not None and not np.array_equal(want, f.force, equal_nan=True):
                rep.wrong_values += 1

    for _ in range(n_inputs):
        parts: list[bytes] = []
        for _ in range(int(rng.integers(1, 7))):
            r = rng.random()
            if r < 0.45:
                frame = _random_frame(rng, next_intact)
                expected[next_intact] = frame.force.copy()
                next_intact += 1
                rep.intact_sent += 1
                parts.append(encode_frame(frame))
            elif r < 0.75:
                parts.append(_mutate(rng, encode_frame(_random_frame(rng, next_mutant))))
                next_mutant = min(next_mutant + 1, 2**32 - 1)
            else:
                parts.append(_junk(rng))
        data = b"".join(parts)
        rep.inputs += 1
        rep.bytes_fed += len(data)
        pos = 0
        while pos < len(data):
            step = int(rng.integers(1, 1200))
            try:
                take(decoder.feed(data[pos : pos + step]))
            except Exception:
                rep.exceptions += 1
                if not rep.first_exception:
                    rep.first_exception = traceback.format_exc()
                decoder = FrameDecoder()
            pos += step
    # Intact frames that were the last thing fed are complete and must already be out; anything still
    # expected was missed.
    rep.intact_missed = len(expected)
    rep.seconds = time.perf_counter() - t0
    if trace_memory:
        rep.peak_traced_mib = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    rep.peak_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rep.errors = decoder.errors()
    rep.garbage_bytes = decoder.garbage_bytes
    return rep


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", "--inputs", type=int, default=100_000, help="random inputs to try (default 100000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tracemalloc", action="store_true", help="also report peak Python allocations (slower)")
    args = ap.parse_args(argv)
    rep = fuzz(args.inputs, args.seed, args.tracemalloc)
    print(f"inputs tried      {rep.inputs}")
    print(f"bytes fed         {rep.bytes_fed}")
    print(f"frames found      {rep.frames_found}")
    print(f"intact frames     {rep.intact_sent} sent, {rep.intact_missed} missed, {rep.wrong_values} wrong values")
    print(f"decoder errors    {rep.errors}, garbage bytes {rep.garbage_bytes}")
    print(f"exceptions        {rep.exceptions}")
    print(f"time              {rep.seconds:.2f} s ({rep.bytes_fed / max(rep.seconds, 1e-9) / 1e6:.2f} MB/s)")
    print(f"peak RSS          {rep.peak_rss_mib:.1f} MiB")
    if rep.peak_traced_mib is not None:
        print(f"peak traced       {rep.peak_traced_mib:.2f} MiB")
    if rep.first_exception:
        print(rep.first_exception)
    return 0 if rep.ok else 1


if __name__ == "__main__":
    sys.exit(main())
