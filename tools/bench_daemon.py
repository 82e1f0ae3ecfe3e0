"""Daemon benchmarks: reaction latency and CPU share at 1 kHz, against the emulated devices.

    python tools/bench_daemon.py [--model slipd/models/slip_ensemble_int8.json] [--seconds 20]

1. **Reaction latency**: the last sample of the deciding window written to the sensor pty -> the tighten
   command's bytes read from the servo pty. The daemon (`slipd.daemon.loop.Daemon`, real pyserial reader,
   real ONNX session, real dynamixel-sdk driver) runs in this process; the emulated PapillArray and
   MX-28 run in a child process, as real devices would (``--shared-process`` puts them in the daemon's
   interpreter instead: their GIL contention then inflates the figures). To get many samples, the
   benchmark sets the threshold to 0 and clears the alarm after each decision, so *every* window raises
   an alarm and a tighten (the arm is left out: it has its own thread).
2. **CPU share**: ``slipd run`` as its own process, fed 1 kHz frames of a quiet hold, the model stepping
   every window; CPU seconds per wall second from /proc, side by side with the same daemon reading every
   frame as it arrives (``sensor.coalesce_margin_ms: null``) and with a baseline process that only reads
   and decodes the same frames (``--decode-only`` mode of this script), so each part's share shows.
Prints median, p99 and max latency against the 5 ms target, and the CPU shares with their ratio.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from slipd.recording import Recording

ROOT = Path(__file__).resolve().parents[1]

TARGET_P99_MS = 5.0
TARGET_CPU = 0.15


def quiet_hold(n: int, seed: int = 0) -> Recording:
    """A steady grasp with sensor noise: the daemon's everyday input."""
    rng = np.random.default_rng(seed)
    force = rng.normal(0, 0.01, (n, 9, 3)).astype(np.float32)
    force[:, :, 2] += 1.5
    force[:300] = rng.normal(0, 0.01, (300, 9, 3))  # unloaded start for the tare
    return Recording(t_us=np.arange(n) * 1000, force=force, disp=np.zeros((n, 9, 3)))


def _config(tmp: Path, model: Path, sensor_port: str, servo_port: str, coalesce: bool = True) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["model"]["manifest"] = str(model.resolve())
    cfg["model"]["detector"] = "onnx"
    cfg["sensor"].update(port=sensor_port, tare="startup", tare_samples=300, stall_timeout_ms=1000)
    if not coalesce:
        cfg["sensor"]["coalesce_margin_ms"] = None
    cfg["gripper"]["port"] = servo_port
    cfg["arm"]["enabled"] = False
    cfg["reaction"].update(actions=["tighten_gripper"], on_failsafe="log_only", rearm_after_s=0.0)
    cfg["recorder"]["enabled"] = False
    path = tmp / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _emulator_process(conn, n: int) -> None:
    """Child process: the emulated PapillArray (1 kHz quiet hold) and MX-28, driven over ``conn``.

    Sends the two port paths, streams on "start", and on "stop" sends back the monotonic time each
    frame was written and the servo's accepted writes. ``time.monotonic`` is one system-wide clock, so
    the parent can subtract the two.
    """
    from slipd.sim.devices.mx28 import EmulatedMX28
    from slipd.sim.devices.papillarray import EmulatedPapillArray

    rec = quiet_hold(n)
    written = np.zeros(n)

    def source(i: int):
        if i >= n:
            return None
        written[i] = time.monotonic()  # the frame is encoded and written right after this returns
        return rec.force[i], rec.disp[i]

    with EmulatedMX28() as servo, EmulatedPapillArray(source) as sensor:
        conn.send((sensor.port, servo.port))
        assert conn.recv() == "clear"
        servo.clear_writes()
        conn.send("cleared")
        assert conn.recv() == "start"
        sensor.start()
        assert conn.recv() == "stop"
        conn.send((written, [(w.t, w.address, bytes(w.data)) for w in servo.writes()]))


def reaction_latency(model: Path, seconds: float, separate: bool = True, coalesce: bool = True) -> np.ndarray:
    """Latencies (s) from the window's last sample written to the tighten bytes parsed by the servo.

    With ``separate`` (default) the emulators run in their own process, as real devices would: the
    figures are the daemon's own. Without it they share this interpreter (and its GIL) with the daemon.
    """
    import multiprocessing

    from slipd.config import load_config
    from slipd.daemon.devices import build_devices
    from slipd.daemon.loop import Daemon
    from slipd.detect.ensemble import Ensemble
    from slipd.metrics import Metrics

    n = int(seconds * 1000) + 1000
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = None
    if separate:
        proc = ctx.Process(target=_emulator_process, args=(child, n), daemon=True)
        proc.start()
    else:
        import threading

        threading.Thread(target=_emulator_process, args=(child, n), daemon=True).start()
    with tempfile.TemporaryDirectory() as tmp:
        sensor_port, servo_port = parent.recv()
        cfg = load_config(_config(Path(tmp), model, sensor_port, servo_port, coalesce))
        metrics = Metrics()
        ens = Ensemble.load(cfg.model.manifest)
        _, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ens, metrics=metrics, gripper=gripper)
        daemon.decision.threshold = 1e-9  # every window alarms ...
        update = daemon.decision.update

        def always_rising(p, pm=None):
            daemon.decision.reset()  # ... and rises again
            return update(p, pm)

        daemon.decision.update = always_rising  # type: ignore[method-assign]
        parent.send("clear")
        parent.recv()

        async def main():
            task = asyncio.create_task(daemon.run(duration_s=seconds + 1.0))
            await daemon.ready.wait()
            parent.send("start")
            return await task

        stats = asyncio.run(main())
        time.sleep(0.3)
        daemon.close()
        parent.send("stop")
        written, writes = parent.recv()
        if proc is not None:
            proc.join(10)
        secure = cfg.gripper.secure_position
        tightens = [t for t, address, data in writes if address == 116 and int.from_bytes(data[:4], "little") == secure]
    lat, split = [], []
    for (end, _, t_dec), t_write in zip(stats.alarms, tightens):
        lat.append(t_write - written[end])
        split.append((t_dec - written[end], t_write - t_dec))
    split_ms = np.array(split[1:]) * 1e3
    print(f"  split (median / p99 ms): sample written -> decision {np.median(split_ms[:, 0]):.2f} / "
          f"{np.percentile(split_ms[:, 0], 99):.2f}; decision -> tighten at the servo "
          f"{np.median(split_ms[:, 1]):.2f} / {np.percentile(split_ms[:, 1], 99):.2f}")
    return np.array(lat[1:])  # the first includes the tare replay


def cpu_share(model: Path, seconds: float, baseline: bool, coalesce: bool = True) -> float:
    """CPU seconds per wall second of one process reading the 1 kHz stream (daemon or decode-only)."""
    from slipd.sim.devices.mx28 import EmulatedMX28
    from slipd.sim.devices.papillarray import EmulatedPapillArray

    rec = quiet_hold(int((seconds + 30) * 1000))
    with tempfile.TemporaryDirectory() as tmp, EmulatedMX28() as servo, EmulatedPapillArray(rec) as sensor:
        cfg = _config(Path(tmp), model, sensor.port, servo.port, coalesce)
        cmd = ([sys.executable, __file__, "--decode-only", sensor.port] if baseline else
               [sys.executable, "-m", "slipd", "run", "--config", str(cfg)])
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(4.0)  # start-up (imports, warm-up) is not the steady state
            sensor.start()
            time.sleep(2.0)
            t0, c0 = time.monotonic(), _cpu_seconds(proc.pid)
            time.sleep(seconds)
            t1, c1 = time.monotonic(), _cpu_seconds(proc.pid)
        finally:
            proc.terminate()
            proc.wait(20)
    return (c1 - c0) / (t1 - t0)


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def decode_only(port: str) -> None:
    """Baseline process: the same serial reader and decoder, no model."""
    from slipd.io.sensor import SerialSensor

    async def main():
        s = SerialSensor(port, lambda frames: None)
        await s.start()
        await asyncio.Event().wait()

    asyncio.run(main())


def main(argv: list[str] | None = None) -> int:
    """Run both benchmarks and print the figures."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=ROOT / "slipd" / "models" / "slip_ensemble_int8.json",
                   help="model manifest (default: the one config/slipd.yaml runs)")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--shared-process", action="store_true",
                   help="latency: run the emulators in the daemon's own process (GIL shared: an upper bound)")
    p.add_argument("--no-coalesce", action="store_true",
                   help="latency: read every frame as it arrives (sensor.coalesce_margin_ms: null)")
    p.add_argument("--decode-only", metavar="PORT", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.decode_only:
        decode_only(args.decode_only)
        return 0
    logging.getLogger("slipd").setLevel(logging.ERROR)  # one alarm per window here: keep the log quiet
    lat = reaction_latency(args.model, args.seconds, separate=not args.shared_process,
                           coalesce=not args.no_coalesce) * 1e3
    print(f"reaction latency (window's last sample written -> tighten bytes at the servo), {len(lat)} alarms:")
    print(f"  median {np.median(lat):.2f} ms   p99 {np.percentile(lat, 99):.2f} ms   max {lat.max():.2f} ms"
          f"   p99 / target {np.percentile(lat, 99) / TARGET_P99_MS:.2f} (target {TARGET_P99_MS} ms)")
    daemon = cpu_share(args.model, args.seconds, baseline=False)
    per_frame = cpu_share(args.model, args.seconds, baseline=False, coalesce=False)
    base = cpu_share(args.model, args.seconds, baseline=True)
    print("CPU share of one core at 1 kHz (steady state):")
    print(f"  slipd run {daemon * 100:.1f} %   same, reading every frame {per_frame * 100:.1f} %"
          f" (ratio {daemon / per_frame:.2f})   decode-only baseline {base * 100:.1f} % (ratio {daemon / base:.2f})"
          f"   daemon / target {daemon / TARGET_CPU:.2f} (target {TARGET_CPU * 100:.0f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
