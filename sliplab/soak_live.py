"""Soak the live daemon: 1 kHz frames for N seconds against the emulated devices; nothing may be lost.

    python tools/soak_live.py                          # 600 s, slipd/models/slip_ensemble.json
    python tools/soak_live.py --seconds 30 --model M.json
    python tools/soak_live.py --random-model           # no trained model yet: random weights, full size
    python tools/soak_live.py --seconds 5400 --slip-every 3 --failsafe-every 60 --record --warmup 1800 --json
                                                       # months, compressed: an hour after the histories are full

``--slip-every S`` puts the packaged sample slip (``slipd/models/sample_slip.npz``, on the hold's load) into the
looped stream every S seconds, so alarms, arm stops, gripper tightens and recordings keep coming; ``--failsafe-every
S`` stalls the sensor for ``STALL_MS`` every S seconds (a ``sensor_stall`` fail-safe: the arm stopped, its control
script ended and uploaded again once live). Every ``SAMPLE_S`` the process's resident memory, open file descriptors
and threads are read from /proc; after the first ``WARMUP_SHARE`` of the run (at least ``WARMUP_MIN_S``) a least-squares
line through the memory samples gives its slope in kB per hour. This process is the daemon alone: the emulated
sensor and servo run in a process of their own, the emulated UR controller in another, so the samples, and the CPU
figures, are the daemon's.

The real ``Daemon`` (pyserial reader, ONNX ensemble, dynamixel-sdk, ur_rtde, device health poll) runs
in this process against the emulated PapillArray (pty, quiet hold looped) and MX-28 (pty), both in one
child process (``slipd.sim.harness.EmulatorProcess``), and the UR controller (own process on ``--host``).
At the end the sensor emulator stops, the daemon drains the pty, and the counts are compared: frames
sent (written to the pty, plus any the emulator had to discard because the reader fell behind) against
frames the daemon processed.

Prints frames sent, processed, lost (must be 0), loop overruns, frames dropped by the packet counter,
reconnects, fail-safes, alarms, health polls, and CPU: the loop thread's own CPU seconds per wall
second (reader, decoder, features, model), the whole daemon process's, and the emulator process's.
Exit status 1 when a frame was lost or a decode error occurred.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slipd.recording import Recording
from sliplab.paths import ROOT

DEFAULT_HOST = "127.0.0.60"  # no test binds it: a long soak and the test suite can run side by side
TARE = 300
STALL_MS = 600.0
"""A fail-safe stall: well past the sim config's 250 ms stall timeout."""
SAMPLE_S = 10.0
WARMUP_SHARE = 0.1
WARMUP_MIN_S = 60.0
LAG_TICK_S = 0.05
LAG_REPORT_S = 0.1
"""A wake-up of the soak's own 50 ms timer this much late is reported as a stall of the daemon's event loop."""
EVENTS_KEPT = 64


def default_warmup(seconds: float) -> float:
    """Seconds before the memory samples start when ``--warmup`` is not given: a share of the run, at least a minute."""
    return max(WARMUP_MIN_S, WARMUP_SHARE * seconds)


@dataclass
class SoakReport:
    """Counts of one soak run."""

    seconds: float
    model: str
    frames_sent: int = 0
    frames_processed: int = 0
    frames_lost: int = 0
    emulator_discarded: int = 0
    overruns: int = 0
    dropped: int = 0
    decode_errors: int = 0
    reconnects: int = 0
    failsafes: int = 0
    alarms: int = 0
    decisions: int = 0
    step_errors: int = 0
    health_polls: int = 0
    slip_every_s: float = 0.0
    failsafe_every_s: float = 0.0
    recordings: int = 0
    recordings_failed: int = 0
    warmup_s: float = 0.0
    rss_first_kb: int = 0
    rss_last_kb: int = 0
    rss_max_kb: int = 0
    rss_slope_kb_per_h: float = 0.0
    fds: tuple[int, int] = (0, 0)
    threads: tuple[int, int] = (0, 0)
    """(min, max) after warm-up."""
    samples: int = 0
    loop_cpu_share: float = 0.0
    process_cpu_share: float = 0.0
    emulator_cpu_share: float = 0.0
    """CPU seconds per wall second of the emulated sensor and servo's own process."""
    emulators_own_process: bool = False
    """The emulated sensor and servo ran in a process of their own, so the samples and ``process_cpu_share`` are the
    daemon's alone (False in the JSON of a soak that held them in its process: the figures include theirs)."""
    wall_s: float = 0.0
    loop_lag_max_s: float = 0.0
    """The latest a 50 ms timer on the daemon's event loop woke (how long the loop was kept from its frames)."""
    loop_stalls: list[tuple[float, float]] = field(default_factory=list)
    """(seconds into the run, lag s) of wake-ups more than ``LAG_REPORT_S`` late, the first ``EVENTS_KEPT``."""
    discard_runs: list[tuple[float, int]] = field(default_factory=list)
    """(seconds into the run, frames) of each run of frames the emulator discarded, the last ``EVENTS_KEPT``."""

    @property
    def ok(self) -> bool:
        """No frame lost, no corrupt frame, no model step error."""
        return self.frames_lost == 0 and self.decode_errors == 0 and self.step_errors == 0

    def lines(self) -> list[str]:
        """Human-readable summary."""
        return [
            f"soak            {self.wall_s:.1f} s at 1 kHz, model {self.model}",
            f"frames sent     {self.frames_sent} (emulator discarded {self.emulator_discarded})",
            f"frames processed {self.frames_processed}",
            f"frames lost     {self.frames_lost}",
            f"overruns        {self.overruns}",
            f"dropped         {self.dropped} (packet counter gaps)   decode errors {self.decode_errors}",
            f"reconnects      {self.reconnects}",
            f"fail-safes      {self.failsafes}   alarms {self.alarms}   decisions {self.decisions}"
            f"   step errors {self.step_errors}   health polls {self.health_polls}",
            f"loop lag max    {self.loop_lag_max_s * 1e3:.0f} ms; {len(self.loop_stalls)} wake-ups over "
            f"{LAG_REPORT_S * 1e3:.0f} ms late"
            + "".join(f"; {t:.1f} s: {lag * 1e3:.0f} ms" for t, lag in self.loop_stalls[:5]),
            "emulator discards " + (", ".join(f"{n} at {t:.1f} s" for t, n in self.discard_runs[:10]) or "none"),
            f"events          a slip every {self.slip_every_s:g} s, a fail-safe stall every "
            f"{self.failsafe_every_s:g} s (0: none); recordings written {self.recordings}, "
            f"failed {self.recordings_failed}",
            f"memory          RSS {self.rss_first_kb} kB after {self.warmup_s:.0f} s of warm-up -> "
            f"{self.rss_last_kb} kB at the end "
            f"(max {self.rss_max_kb}); slope {self.rss_slope_kb_per_h:+.0f} kB/hour over {self.samples} samples",
            f"fds, threads    {self.fds[0]}..{self.fds[1]} open descriptors, {self.threads[0]}..{self.threads[1]} "
            "threads after warm-up",
            f"CPU share       loop thread {self.loop_cpu_share * 100:.1f} %   "
            + (f"daemon process {self.process_cpu_share * 100:.1f} %   "
               f"emulated sensor and servo (own process) {self.emulator_cpu_share * 100:.1f} %"
               if self.emulators_own_process else
               f"whole process (with the sensor and servo emulators) {self.process_cpu_share * 100:.1f} %"),
        ]


def quiet_hold(seconds: float = 10.0, seed: int = 0) -> Recording:
    """A still grasp with sensor noise; looped by the emulator for as long as the soak runs."""
    n = int(seconds * 1000)
    rng = np.random.default_rng(seed)
    force = rng.normal(0.0, 0.01, (n, 9, 3)).astype(np.float32)
    force[:, :, 2] += 1.5
    return Recording(t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=np.zeros((n, 9, 3), np.float32))


def with_slips(every_s: float, hold: Recording) -> Recording:
    """The hold followed by the packaged sample slip on the hold's load, ``every_s`` seconds in all (looped)."""
    slip = Recording.load(ROOT / "slipd" / "models" / "sample_slip.npz")
    n_hold = max(int(every_s * 1000) - len(slip), 1000)
    reps = -(-n_hold // len(hold))
    hf = np.concatenate([hold.force] * reps)[:n_hold]
    sf = slip.force.astype(np.float32).copy()
    sf[:, :, 2] += float(np.median(hold.force[:, :, 2]))
    force = np.concatenate([hf, sf])
    disp = np.zeros_like(force)
    return Recording(t_us=np.arange(len(force), dtype=np.int64) * 1000, force=force, disp=disp)


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far, from /proc."""
    import os

    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _proc_sample() -> tuple[int, int, int]:
    """(resident kB, open fds, threads) of this process, from /proc."""
    import os

    status = Path("/proc/self/status").read_text().splitlines()
    fields = {line.split(":", 1)[0]: line.split(":", 1)[1].split() for line in status if ":" in line}
    return int(fields["VmRSS"][0]), len(os.listdir("/proc/self/fd")), int(fields["Threads"][0])


def slope_per_hour(t_s: list[float], values: list[int]) -> float:
    """Least-squares slope of ``values`` against ``t_s``, per hour (0 with fewer than two samples)."""
    if len(t_s) < 2:
        return 0.0
    return float(np.polyfit(np.asarray(t_s), np.asarray(values, float), 1)[0] * 3600.0)


def random_model(out_dir: Path, members: int = 5, seed: int = 0) -> Path:
    """A full-size ensemble with random weights (the default SlipNet layout), exported to ONNX.

    For soaking before a trained model exists: the compute per step equals a trained model's of the same
    size; its probabilities mean nothing (the soak then sets the threshold out of reach)."""
    import torch

    from slipd.detect.features import FeatureSpec
    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet

    spec = FeatureSpec()
    folded = []
    for k in range(members):
        torch.manual_seed(seed + k)
        net = SlipNet(input_size=spec.input_size).eval()
        folded.append(fold_member(net.state_dict()))
    out = out_dir / "random_ensemble.onnx"
    export(folded, spec, out, "trained", {"note": "random weights for tools/soak_live.py"})
    return out.with_suffix(".json")


def soak(seconds: float, model: Path, *, host: str = DEFAULT_HOST, controller=None,
         threshold: float | None = None, slip_every: float = 0.0, failsafe_every: float = 0.0,
         record_dir: Path | None = None, warmup_s: float | None = None) -> SoakReport:
    """Run the daemon live for ``seconds`` and count; ``controller`` reuses a running URControllerProcess.
    ``slip_every``, ``failsafe_every``: seconds between slips and fail-safe stalls (0: none); ``record_dir``: the
    recorder's directory (None: no recorder); ``warmup_s``: seconds before the memory samples start (None: the first
    ``WARMUP_SHARE`` of the run, at least ``WARMUP_MIN_S``)."""
    from slipd.config import load_config, override
    from slipd.daemon.devices import build_devices
    from slipd.daemon.loop import Daemon
    from slipd.detect.ensemble import Ensemble
    from slipd.metrics import Metrics
    from slipd.sim.devices.ur_controller import URControllerProcess
    from slipd.sim.harness import EmulatorProcess

    own_ur = controller is None
    if own_ur:
        controller = URControllerProcess(host).start()
    host = controller.host
    rep = SoakReport(seconds=seconds, model=str(model), slip_every_s=slip_every, failsafe_every_s=failsafe_every,
                     emulators_own_process=True)
    source = with_slips(slip_every, quiet_hold()) if slip_every > 0 else quiet_hold()
    emu = EmulatorProcess(source, sensor={"loop": True})
    daemon = None
    try:
        emu.start()
        emu_pid = emu.pid
        assert emu_pid is not None
        updates = {**emu.overrides(), "arm.enabled": True, "arm.host": host, "model.manifest": str(model),
                   "model.detector": "onnx",
                   "sensor.tare": "startup", "sensor.tare_samples": TARE, "recorder.enabled": record_dir is not None}
        if record_dir is not None:
            updates.update({"recorder.directory": str(record_dir), "recorder.max_total_mb": 50.0})
        if threshold is not None:
            updates["decision.threshold"] = threshold
        cfg = override(load_config(ROOT / "config" / "sim.yaml"), updates)
        metrics = Metrics()
        ens = Ensemble.load(cfg.model.manifest, threads=cfg.model.threads)
        arm, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ens, metrics=metrics, arm=arm, gripper=gripper)
        if record_dir is not None:
            from slipd.daemon.preflight import open_recorder

            daemon.recorder = open_recorder(cfg, "soak", {"model_sha256": ens.manifest.sha256}, metrics)
        d = daemon
        warm_s = default_warmup(seconds) if warmup_s is None else warmup_s
        rep.warmup_s = warm_s
        ts: list[float] = []
        rss: list[int] = []
        fds: list[int] = []
        threads: list[int] = []

        async def watch_lag(t0: float) -> None:
            # The daemon's loop is this loop: a late wake-up here is time it could not read the sensor either.
            while True:
                due = time.monotonic() + LAG_TICK_S
                await asyncio.sleep(LAG_TICK_S)
                lag = time.monotonic() - due
                rep.loop_lag_max_s = max(rep.loop_lag_max_s, lag)
                if lag > LAG_REPORT_S and len(rep.loop_stalls) < EVENTS_KEPT:
                    rep.loop_stalls.append((round(due - t0, 3), round(lag, 4)))

        async def main() -> None:
            task = asyncio.create_task(d.run())
            await d.ready.wait()
            emu.call("sensor", "start")
            t0, c0, p0 = time.monotonic(), time.thread_time(), time.process_time()
            e0 = _cpu_seconds(emu_pid)
            watcher = asyncio.create_task(watch_lag(t0))
            try:
                next_sample = t0 + warm_s
                next_stall = t0 + failsafe_every if failsafe_every > 0 else float("inf")
                while time.monotonic() - t0 < seconds and not task.done():
                    await asyncio.sleep(0.2)
                    now = time.monotonic()
                    if now >= next_stall:
                        emu.call("sensor", "stall", STALL_MS)
                        next_stall += failsafe_every
                    if now >= next_sample:
                        r, f, th = _proc_sample()
                        ts.append(now - t0)
                        rss.append(r)
                        fds.append(f)
                        threads.append(th)
                        next_sample += SAMPLE_S
                emu.call("sensor", "stop")  # stop sending, then let the reader drain what is in flight
                await asyncio.to_thread(emu.call, "sensor", "write_frames", [], 5.0)  # push out bytes still queued
                # Read once streaming has stopped: the emulator's own counts, in its process.
                written = emu.get("sensor", "frames_written")
                rep.emulator_discarded = emu.get("sensor", "frames_discarded")
                rep.frames_sent = written + rep.emulator_discarded
                # time.monotonic() is one clock for every process on the machine: the emulator's times line up.
                rep.discard_runs = [(round(t - t0, 3), n) for t, n in emu.get("sensor", "discard_log")]
                deadline = time.monotonic() + 5.0
                while d.sensor.decoder.frames < written and time.monotonic() < deadline:
                    await asyncio.sleep(0.01)
                await asyncio.sleep(0.05)
                t1, c1, p1 = time.monotonic(), time.thread_time(), time.process_time()
                e1 = _cpu_seconds(emu_pid)
                rep.wall_s = t1 - t0
                rep.loop_cpu_share = (c1 - c0) / rep.wall_s
                rep.process_cpu_share = (p1 - p0) / rep.wall_s
                rep.emulator_cpu_share = (e1 - e0) / rep.wall_s
            finally:
                watcher.cancel()
                d.stop()
                await task

        asyncio.run(main())
    finally:
        if daemon is not None:
            daemon.close()
        emu.close()
        if own_ur:
            controller.stop()
    m, st = daemon.metrics, daemon.stats

    def val(name: str, **labels: str) -> float:
        v = m.registry.get_sample_value(name, labels or None)
        return 0.0 if v is None else v

    rep.frames_processed = st.frames
    rep.frames_lost = rep.frames_sent - st.frames
    rep.overruns = st.overruns
    rep.dropped = int(val("slipd_dropped_frames_total"))
    rep.decode_errors = int(sum(val("slipd_frame_errors_total", kind=k)
                                for k in ("bad_checksum", "bad_length", "bad_structure", "discontinuity")))
    rep.reconnects = int(val("slipd_reconnects_total", device="sensor") + val("slipd_reconnects_total", device="arm"))
    rep.failsafes = st.failsafes
    rep.alarms = st.alarm_count
    rep.decisions = st.decisions
    rep.step_errors = st.step_errors
    rep.health_polls = st.health_polls
    if rss:
        rep.rss_first_kb, rep.rss_last_kb, rep.rss_max_kb = rss[0], rss[-1], max(rss)
        rep.rss_slope_kb_per_h = slope_per_hour(ts, rss)
        rep.fds, rep.threads, rep.samples = (min(fds), max(fds)), (min(threads), max(threads)), len(rss)
    rep.recordings_failed = int(sum(val("slipd_recordings_failed_total", reason=r)
                                    for r in ("no_space", "read_only", "permission", "io", "backlog")))
    if daemon.recorder is not None:
        rep.recordings = daemon.recorder.files_written
    return rep


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=600.0, help="soak duration (default 600)")
    p.add_argument("--model", type=Path, default=ROOT / "slipd" / "models" / "slip_ensemble.json",
                   help="model manifest")
    p.add_argument("--random-model", action="store_true", help="soak a random-weight full-size ensemble instead")
    p.add_argument("--host", default=DEFAULT_HOST, help=f"loopback address of the emulated UR ({DEFAULT_HOST})")
    p.add_argument("--slip-every", type=float, default=0.0, help="seconds between slips (default 0: none)")
    p.add_argument("--failsafe-every", type=float, default=0.0,
                   help="seconds between fail-safe sensor stalls (default 0: none)")
    p.add_argument("--record", action="store_true", help="run the recorder (a temporary directory, 50 MB bound)")
    p.add_argument("--warmup", type=float, default=None,
                   help="seconds before the memory samples start (default: a tenth of the run, at least 60); "
                        "past the time the daemon's bounded histories fill, the slope shows what still grows (with "
                        "--record the recorder's list of deleted files is the last to fill: only once 50 MB of "
                        "recordings are on disk and 256 more have been written)")
    p.add_argument("--json", action="store_true", help="also print the counts as one JSON line")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    with tempfile.TemporaryDirectory(prefix="slipd-soak-") as tmp:
        threshold = None
        model = args.model
        if args.random_model:
            model, threshold = random_model(Path(tmp)), 0.999
        elif not model.exists():
            print(f"{model}: no such model manifest (pass --model, or --random-model before one is trained)",
                  file=sys.stderr)
            return 2
        rep = soak(args.seconds, model, host=args.host, threshold=threshold, slip_every=args.slip_every,
                   failsafe_every=args.failsafe_every, record_dir=Path(tmp) / "recordings" if args.record else None,
                   warmup_s=args.warmup)
    if args.random_model:
        rep.model = "random weights, full-size SlipNet x5 (threshold 0.999)"
    print("\n".join(rep.lines()))
    if args.json:
        import json

        print(json.dumps({**asdict(rep), "ok": rep.ok}))
    print("OK: no frame lost" if rep.ok else "FAIL: frames lost or corrupted", file=sys.stderr)
    return 0 if rep.ok else 1


if __name__ == "__main__":
    sys.exit(main())
