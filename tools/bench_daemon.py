"""Daemon benchmarks: reaction latency and CPU share at 1 kHz against the emulated devices, one and two sensors,
decision strides 40 / 20 / 10, the decode-only baseline and the machine's floor for this work, side by side.

    python tools/bench_daemon.py [--seconds 30] [--model slipd/models/slip_ensemble_int8.json] [--json FILE]
    python tools/bench_daemon.py --baseline-tree /tmp/base --strides 10 [--reps 4] [--seconds 15]
    python tools/bench_daemon.py --viz --sensors 1 --strides 10 [--seconds 30] [--cpu-runs 4]
    python tools/bench_daemon.py --instructions [--sensors 1 2] [--instr-decisions 2000] [--json FILE]

Per configuration (sensors x stride):

1. **Reaction latency**: the last sample of the deciding window written to the sensor pty -> the tighten
   command's bytes read from the servo pty. The daemon (`slipd.daemon.loop.Daemon`, real pyserial reader,
   real ONNX session, real dynamixel-sdk driver) runs in this process; the emulated PapillArray and MX-28
   run in a child process, as real devices would. To get many samples every window of one sensor raises an
   alarm and a tighten (the threshold is set to 0 and the alarm cleared after each decision; with two
   sensors on sensor 1, the second finger, while sensor 0 decides normally). ``frames_sent`` /
   ``frames_lost`` count this run's stream: frames the emulator wrote, and those the daemon never decided on.
2. **CPU share**: ``slipd run`` as its own process, fed 1 kHz frames of a quiet hold (in contact, so the model
   steps on every window of every sensor), CPU seconds per wall second from /proc (process CPU time: valid on
   a loaded machine; the load average is printed beside it).

``--baseline-tree DIR`` measures what a change saves: the CPU share of this tree and of another checkout's
``slipd`` (e.g. ``git worktree add /tmp/base <commit>``), runs alternating on the same stream; with ``--paired``
both run at once, each on its own stream, and the difference per pair is reported (see ``_paired_shares``).

3. **Hot path per decision** (``hot_path_cost``): the daemon's code on one read of ``stride`` frames (decode,
   freshness, detector, decision, metrics) without the event loop, back to back (a run of consecutive reads) and after
   10 ms asleep, against the model step alone, and where it goes per stage (``STAGES``: decode, freshness check,
   features, step, decision, contact state, reaction check, recorder, metrics; beside them the same reads untimed).
   ``--json`` writes them in each entry of ``runs``: ``hot_path_us`` and ``step_us`` (``{"back_to_back": ..,
   "after_sleep": .., "back_to_back_p10": ..}``: medians, and the back-to-back 10th percentile), ``python_us`` (the
   same path back to back with onnxruntime's call skipped: the Python around the model) and ``stages_us``; the
   idle event loop's share is ``idle_loop_percent`` at the top level, the loop with the model's step ``step_loop``.

``--instructions`` (opt-in; needs valgrind): the same hot path counted in instructions, which a loaded machine does not
change: per decision at stride 10, the hot path back to back, the same path with onnxruntime's call skipped (the
Python around the model) and the model step alone, each from a child process under ``valgrind --tool=callgrind``
(``instruction_counts``: the count of a run of ``--instr-decisions`` decisions less that of the same set-up with
none). For comparing trees or changes on a busy machine. Not a measure of time: valgrind runs the model's kernels
without the wider vector instructions the machine has, and an instruction of the model's does more work than one of
the interpreter's, so the ratio of the counts is not the ratio of the times.

Beside them: a process that only reads and decodes the same frames (``--decode-only``, one and two sensors,
reading every frame as it arrives), an event loop that only wakes 100 times a second (``idle_loop``: what this
machine charges for the decision rate's wake-ups alone), the same loop stepping the model once per wake-up
(``step_loop``: the decision's floor with none of the daemon's Python around the model), and the floor of the work
on this machine: the bytes (frames read once, decoded once) over the measured memory bandwidth plus the FLOPs (model
steps, median filter) over the measured float32 matrix rate.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import json
import logging
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from slipd.recording import Recording
from slipd.sim.harness import EmulatorProcess

ROOT = Path(__file__).resolve().parents[1]

TARGET_P99_MS = 3.0
TARGET_CPU = {1: 0.08, 2: 0.12}  # stride 10, of one core: the daemon's CPU budget
STRIDES = (40, 20, 10)
IDLE_HZ = 100.0
"""The ``idle_loop`` baseline's wake-up rate: the daemon's decisions per second at stride 10."""


def write_json(path: Path, text: str) -> None:
    """Write a ``--json`` report, making its folder first (``out/`` does not exist in a fresh clone)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def quiet_hold(n: int, sensors: int = 1, seed: int = 0) -> Recording:
    """A steady grasp with sensor noise on every finger: the daemon's everyday input."""
    rng = np.random.default_rng(seed)
    force = rng.normal(0, 0.01, (n, sensors, 9, 3)).astype(np.float32)
    force[:, :, :, 2] += 1.5
    force[:300] = rng.normal(0, 0.01, (300, sensors, 9, 3))  # unloaded start for the tare
    if sensors == 1:
        force = force[:, 0]
    return Recording(t_us=np.arange(n) * 1000, force=force, disp=np.zeros_like(force))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(tmp: Path, model: Path, sensor_port: str, servo_port: str, sensors: int, stride: int,
            policy: str = "stop_and_secure", viz_port: int | None = None, confirm_rule: float | None = None) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["model"].update(manifest=str(model.resolve()), detector="onnx", stride=stride)
    cfg["sensor"].update(port=sensor_port, tare="startup", tare_samples=300, stall_timeout_ms=1000, sensors=sensors)
    if confirm_rule:
        cfg["decision"]["confirm_rule"] = confirm_rule
    cfg["gripper"]["port"] = servo_port
    cfg["arm"]["enabled"] = False
    cfg["reaction"].update(actions=["tighten_gripper"], on_failsafe="log_only", rearm_after_s=0.0, policy=policy)
    cfg["recorder"]["enabled"] = False
    if viz_port is not None:
        cfg["viz"] = {"enabled": True, "host": "127.0.0.1", "port": viz_port}
    path = tmp / f"bench-{sensors}-{stride}-{policy}{'-viz' if viz_port else ''}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


# ---------------------------------------------------------------------------------------------- latency
class _StampedHold:
    """The quiet hold as a sample source that notes when each frame was taken (``time.monotonic``, one clock for
    every process), so the parent can subtract the write time of a window's last sample from its reaction's.

    Runs in the emulator process (``EmulatorProcess``); the parent reads ``written`` from there at the end."""

    def __init__(self, n: int, sensors: int) -> None:
        self.rec = quiet_hold(n, sensors)
        self.written = np.zeros(n)

    def __call__(self, i: int) -> tuple[np.ndarray, np.ndarray] | None:
        if i >= len(self.written):
            return None
        self.written[i] = time.monotonic()  # the frame is encoded and written right after this returns
        return self.rec.force[i], self.rec.disp[i]


def _stuck_viewer(port: int, sensors: int) -> Any:
    """A Foxglove client on the live view that subscribes to every channel and then never reads."""
    from slipd.sim.devices.foxglove_client import FoxgloveClient

    client = FoxgloveClient("127.0.0.1", port, recv_buffer=4096)
    client.wait_for_channels({f"/slipd/frames/s{s}" for s in range(sensors)} | {"/slipd/decisions"})
    client.subscribe_all()
    return client


def reaction_latency(model: Path, seconds: float, sensors: int, stride: int, viz: bool = False) -> dict[str, float]:
    """Latency figures (ms) from the window's last sample written to the tighten bytes parsed by the servo,
    and the stream's frames sent and lost. ``viz``: with the live view on and a viewer that never reads."""
    from slipd.config import load_config
    from slipd.daemon.devices import build_devices
    from slipd.daemon.loop import Daemon
    from slipd.daemon.service import start_taps
    from slipd.detect.ensemble import Ensemble
    from slipd.metrics import Metrics

    n = int(seconds * 1000) + 1000
    # The emulated sensor and servo in a process of their own: their threads must not share this one's GIL.
    with tempfile.TemporaryDirectory() as tmp, \
            EmulatorProcess(_StampedHold(n, sensors), sensor={"sensors": sensors}) as emu:
        cfg_path = _config(Path(tmp), model, emu.sensor_port, emu.servo_port, sensors, stride,
                           viz_port=_free_port() if viz else None)
        cfg = load_config(cfg_path)
        metrics = Metrics()
        ens = Ensemble.load(cfg.model.manifest)
        _, gripper = build_devices(cfg, metrics)
        daemon = Daemon(cfg, ens, metrics=metrics, gripper=gripper)
        start_taps(cfg, daemon, str(cfg_path))
        viewer = _stuck_viewer(cfg.viz.port, sensors) if viz else None
        subs = getattr(daemon.detector, "detectors", [daemon.detector])
        decision = subs[-1].decision  # one sensor's decisions: the second finger's when there are two
        decision.threshold = 1e-9  # every window alarms ...
        decision.min_consecutive = 1  # (the alarm is cleared after each decision: no run of two could form)
        advance = decision.advance

        def always_rising(p: float, may_raise: bool = True, contact_risk: float | None = None) -> tuple[bool, bool]:
            decision.reset()  # ... and rises again
            return advance(p, may_raise, contact_risk)

        decision.advance = always_rising  # type: ignore[method-assign]
        emu.call("servo", "clear_writes")

        async def main() -> Any:
            task = asyncio.create_task(daemon.run(duration_s=n / 1000 + 0.5))
            await daemon.ready.wait()
            emu.call("sensor", "start")
            return await task

        stats = asyncio.run(main())
        time.sleep(0.3)
        view = daemon.taps[0] if daemon.taps else None
        daemon.close()
        if viewer is not None:
            viewer.close()
        emu.call("sensor", "stop")
        written, sent = emu.get("source", "written"), emu.get("sensor", "frames_written")
        writes = [(w.t, w.address, w.data) for w in emu.call("servo", "writes")]
        secure = cfg.gripper.secure_position
        tightens = np.array(
            [t for t, address, data in writes if address == 116 and int.from_bytes(data[:4], "little") == secure]
        )
    # Each alarm's tighten is the first to reach the servo after its decision (the loop keeps the latest
    # alarms only, so they are matched by time, not by position).
    alarms = list(stats.alarms)[1:]  # the first includes the tare replay
    t_dec = np.array([a[2] for a in alarms])
    at = np.searchsorted(tightens, t_dec)
    ok = at < len(tightens)
    ends = np.array([a[0] for a in alarms])[ok]
    ms = (tightens[at[ok]] - written[ends]) * 1e3
    to_decision = (t_dec[ok] - written[ends]) * 1e3  # sample written -> decision made (read, decode, model)
    return {"latency_p50_ms": float(np.median(ms)), "latency_p99_ms": float(np.percentile(ms, 99)),
            "latency_max_ms": float(ms.max()), "decision_p50_ms": float(np.median(to_decision)),
            "decision_p99_ms": float(np.percentile(to_decision, 99)), "alarms": len(ms), "frames_sent": int(sent),
            "frames_lost": int(sent - stats.frames), "view_sent": getattr(view, "sent", 0),
            "view_dropped": getattr(view, "dropped", 0)}


# ---------------------------------------------------------------------------------------------- CPU
def cpu_share(model: Path, seconds: float, sensors: int, stride: int | None, tree: Path | None = None,
              policy: str = "stop_and_secure", idle_hz: float | None = None, viz: bool = False,
              idle_step: bool = False) -> float:
    """CPU seconds per wall second of one process reading the 1 kHz stream (``slipd run``; decode-only when
    ``stride`` is None). ``tree``: run the ``slipd`` of that source tree instead of this one (``--baseline-tree``).
    ``policy`` grip_control: the grip controller takes the quiet grasp over and runs on every decision.
    ``idle_hz``: instead, an event loop that only wakes this often (``idle_loop``), beside the same stream; with
    ``idle_step`` it steps ``model`` on ``sensors`` windows at each wake-up (``step_loop``)."""
    from slipd.sim.devices.mx28 import EmulatedMX28
    from slipd.sim.devices.papillarray import EmulatedPapillArray

    rec = quiet_hold(int((seconds + 30) * 1000), sensors)
    with tempfile.TemporaryDirectory() as tmp, EmulatedMX28() as servo, EmulatedPapillArray(rec) as sensor:
        if idle_hz is not None:
            cmd = [sys.executable, __file__, "--idle-loop", str(idle_hz)]
            if idle_step:
                cmd += ["--idle-step", "--model", str(model), "--sensors", str(sensors)]
        elif stride is None:
            cmd = [sys.executable, __file__, "--decode-only", sensor.port, "--sensors", str(sensors)]
        else:
            viz_port = _free_port() if viz else None
            cfg = _config(Path(tmp), model, sensor.port, servo.port, sensors, stride, policy, viz_port)
            cmd = [sys.executable, "-m", "slipd", "run", "--config", str(cfg)]
        env = None
        if tree is not None:  # the other tree's package first on the path (an editable install points here)
            env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")])}
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                                cwd=tree if tree is not None else None)
        viewer = None
        try:
            time.sleep(4.0)  # start-up (imports, warm-up) is not the steady state
            if viz:
                viewer = _stuck_viewer(viz_port, sensors)  # type: ignore[arg-type]
            sensor.start()
            time.sleep(2.0)
            t0, c0 = time.monotonic(), _cpu_seconds(proc.pid)
            time.sleep(seconds)
            t1, c1 = time.monotonic(), _cpu_seconds(proc.pid)
        finally:
            proc.terminate()
            proc.wait(20)
            if viewer is not None:
                viewer.close()
    return (c1 - c0) / (t1 - t0)


def times(share: float, base: float) -> str:
    """``share`` as a multiple of ``base`` for the printed ratios. A short run of a near-idle loop can read 0 % (the
    process's CPU time counts in clock ticks of 10 ms): then there is no ratio to print."""
    return f"{share / base:.1f}x" if base > 0 else "n/a (the baseline read 0 % CPU: under one clock tick) against"


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def decode_only(port: str, sensors: int) -> None:
    """Baseline process: the same serial reader and decoder, no model, every frame read as it arrives."""
    from slipd.io.sensor import SerialSensor

    async def main() -> None:
        s = SerialSensor(port, on_block=lambda block: None, sensors=sensors)
        await s.start()
        await asyncio.Event().wait()

    asyncio.run(main())


def idle_loop(hz: float, model: Path | None = None, sensors: int = 1) -> None:
    """Baseline process: an asyncio event loop (the daemon's) that wakes ``hz`` times a second on an absolute
    schedule and does nothing else. On a machine whose cores go cold while idle (this virtual machine: see
    ``hot_path_cost``) a wake-up alone costs far more than its instructions; this line shows how much of the
    daemon's share the machine charges for waking at the decision rate at all (this module holds numpy, as the
    daemon's process does).

    ``model``: each wake-up also steps that ensemble once on a batch of ``sensors`` windows (``step_loop``), the
    daemon's decision with none of its Python around the model: what the machine charges for the model's step
    after the sleep between decisions (its weights walked again from a cold cache)."""
    step: Any = None
    if model is not None:
        from slipd.detect.ensemble import Ensemble

        ens = Ensemble.load(model)
        window = np.full((sensors, ens.feature_spec.input_size), 0.1, np.float32)

        def step() -> None:
            ens.step(window)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        start = loop.time()

        def tick(k: int) -> None:
            loop.call_at(start + k / hz, tick, k + 1)
            if step is not None:
                step()

        tick(1)
        await asyncio.Event().wait()

    asyncio.run(main())


# ---------------------------------------------------------------------------------------------- hot path
HOT_SLEEP_S = 0.01
HOT_DECISIONS = 300


def _encoded(counter: int, t_us: int, force: np.ndarray) -> bytes:
    """One PTSCOM frame of ``force`` [S, 9, 3] (sensor 0 first, displacements zero, the optional blocks neutral)."""
    from slipd.io.pts import Frame, encode_frame

    z = np.zeros((9, 3), np.float32)
    return encode_frame(Frame(counter, t_us, force[0], z, wrench=np.zeros(6, np.float32),
                              slip_state=np.zeros(9, np.int8), friction=np.zeros(9, np.float32), sensor_state=0,
                              others=tuple((f, z) for f in force[1:])))


def _hot_path_setup(model: Path, sensors: int, stride: int, decisions: int, tmp: Path,
                    recorder: bool = False, confirm_rule: float | None = None) -> tuple[Any, Any, list[bytes]]:
    """A daemon (the bench's config at ``stride``, not running: no event loop, no devices) past its tare and first
    windows, its decoder, and ``2 * decisions`` reads of ``stride`` encoded frames each, the first read ending on a
    deciding frame. ``recorder``: with the recorder the default config runs (``recorder.enabled``); ``confirm_rule``:
    ``decision.confirm_rule`` at that level."""
    from slipd.config import load_config
    from slipd.daemon.loop import Daemon
    from slipd.daemon.recorder import Recorder
    from slipd.detect.ensemble import Ensemble
    from slipd.io.pts import FrameDecoder
    from slipd.metrics import Metrics

    n = 400 + stride * (2 * decisions + 20) + 40
    force = quiet_hold(n, sensors).force.reshape(n, sensors, 9, 3)
    data = [_encoded(i + 1, i * 1000, force[i]) for i in range(n)]
    cfg = load_config(_config(tmp, model, "/dev/null", "/dev/null", sensors, stride, confirm_rule=confirm_rule))
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics())
    members = getattr(daemon.detector, "model", daemon.detector)  # (the confirmed rule decides on any sample)
    if recorder:
        daemon.recorder = Recorder(tmp / "recordings", cfg.sensor.rate_hz, sensors=sensors)
    dec = FrameDecoder(sensors)
    daemon._on_frames(dec.feed_block(b"".join(data[:400])))  # the tare and the first windows
    i = 400
    while members.samples_to_decision() != stride:
        daemon._on_frames(dec.feed_block(data[i]))
        i += 1
    chunks = [b"".join(data[i + stride * k : i + stride * k + stride]) for k in range(2 * decisions)]
    return daemon, dec, chunks


def hot_path_cost(model: Path, sensors: int, decisions: int = HOT_DECISIONS, sleep_s: float = HOT_SLEEP_S,
                  stride: int = 10, confirm_rule: float | None = None) -> dict[str, Any]:
    """The daemon's work per decision without the event loop: ``stride`` encoded frames decoded
    (``FrameDecoder.feed_block``) and handed to ``Daemon._on_frames`` (freshness, detector, decision, metrics),
    in this process. Timed back to back and after ``sleep_s`` asleep, as the daemon is between decisions: what
    the code costs, and what the same code costs once the machine has let its caches go cold. Beside it the model
    step alone (one onnxruntime call on the daemon's batch, a stream of its own) and ``stages_us``, the hot path
    per stage (``stage_breakdown``). ``confirm_rule``: with ``decision.confirm_rule`` at that level (a level the hold's
    P(slip) reaches keeps the rule running throughout)."""
    with tempfile.TemporaryDirectory() as tmp:
        daemon, dec, chunks = _hot_path_setup(model, sensors, stride, decisions, Path(tmp), confirm_rule=confirm_rule)
        hot = _warm_and_cold(lambda k: daemon._on_frames(dec.feed_block(chunks[k])), decisions, sleep_s)
        ens = daemon.ensemble
        window = np.zeros((sensors, ens.feature_spec.input_size), np.float32)
        step = _warm_and_cold(lambda k: ens.step(window, stream=1_000), decisions, sleep_s)
        daemon.close()
    with tempfile.TemporaryDirectory() as tmp:
        daemon, dec, chunks = _hot_path_setup(model, sensors, stride, decisions, Path(tmp), recorder=True,
                                              confirm_rule=confirm_rule)
        stages = stage_breakdown(daemon, dec, chunks)
        daemon.close()
    with tempfile.TemporaryDirectory() as tmp:
        daemon, dec, chunks = _hot_path_setup(model, sensors, stride, decisions // 2, Path(tmp),
                                              confirm_rule=confirm_rule)
        python = _python_alone(daemon, dec, chunks)
        daemon.close()
    return {"back_to_back_us": hot[0], "after_sleep_us": hot[1], "back_to_back_p10_us": hot[2],
            "model_back_to_back_us": step[0], "model_after_sleep_us": step[1], "model_back_to_back_p10_us": step[2],
            "python_back_to_back_us": python[0], "python_back_to_back_p10_us": python[1], "stages_us": stages}


def _python_alone(daemon: Any, dec: Any, chunks: list[bytes]) -> tuple[float, float]:
    """The hot path back to back with onnxruntime's call skipped (median and 10th percentile, microseconds): the
    Python around the model, ``Ensemble.step``'s own included, with none of the model's arithmetic. The session's
    outputs keep the last real call's values (finite), so every decision takes the path it takes on a quiet hold.
    Beside ``hot_path_us - step_us``: the model's call costs more inside the path than alone (the Python between two
    calls lets the model's working set go from the caches), so that difference understates the Python."""
    session = daemon.ensemble._session
    session.run_with_iobinding = lambda *a, **k: None  # the instance's: the class's call is left as it was
    try:
        got = []
        for k in range(len(chunks)):
            t0 = time.perf_counter()
            daemon._on_frames(dec.feed_block(chunks[k]))
            got.append(time.perf_counter() - t0)
    finally:
        del session.run_with_iobinding
    us = np.array(got[5:]) * 1e6
    return float(np.median(us)), float(np.percentile(us, 10))


STAGES: tuple[tuple[str, tuple[tuple[str, str, str], ...]], ...] = (
    ("decode", (("slipd.io.pts", "FrameDecoder", "feed_block"),)),
    ("freshness check", (("slipd.daemon.loop", "Daemon", "_check_samples"),)),
    ("features", (("slipd.detect.detector", "Detector", "feature_windows"),
                  ("slipd.detect.features", "FeatureStream", "push_views"),
                  ("slipd.detect.features", "StreamGroup", "push_views"),
                  ("slipd.detect.multisensor", "MultiDetector", "_stacked_rows"))),
    ("step", (("slipd.detect.ensemble", "Ensemble", "step"), ("slipd.detect.ensemble", "Ensemble", "step_one"),
              ("slipd.detect.ensemble", "Ensemble", "step_rows"))),
    ("decision", (("slipd.detect.detector", "Detector", "push_many"), ("slipd.detect.multisensor", "MultiDetector",
                  "push_many"), ("slipd.detect.detector", "Detector", "_decide"),
                  ("slipd.detect.detector", "Detector", "_gate"), ("slipd.detect.detector", "Detector", "_finish"))),
    ("confirmed rule", tuple(("slipd.detect.confirmed", "ConfirmedDetector", f) for f in
                             ("push_many", "_keep", "_start_rule")) + tuple(
        ("slipd.detect.baselines", "_HeuristicDetector", f) for f in ("push_many", "_rule_on_block"))),
    ("contact state", (("slipd.detect.detector", "Detector", "contact_state"),
                       ("slipd.detect.contact", "ContactStream", "state"))),
    ("reaction check", (("slipd.daemon.loop", "Daemon", "_on_frames"), ("slipd.daemon.loop", "Daemon", "_on_block"),
                        ("slipd.daemon.loop", "Daemon", "_coalesce"))),
    ("recorder", tuple(("slipd.daemon.recorder", "Recorder", f) for f in
                       ("push_frames", "push_decision", "settle", "trigger"))),
    ("metrics", (("prometheus_client.metrics", "Counter", "inc"), ("prometheus_client.metrics", "Histogram", "observe"),
                 ("prometheus_client.metrics", "Gauge", "set"), ("slipd.metrics", "DecisionHistogram", "observe"),
                 ("slipd.metrics", "DecisionCount", "inc"))),
)
"""The hot path's stages and the functions each one's time is spent in. Time is exclusive: a function's nested calls
of another stage count there: "decision" is the detector's own work around the features, the step and the contact
state (contact gate, press hold, alarm rule, the detections); "reaction check" what the loop does around the detector
(per-decision bookkeeping, the rising-edge check that hands an alarm to the reaction, the read coalescing);
"confirmed rule" the fusion and the rule's speeds and flags (``decision.confirm_rule``; its median filter counts in
"features"; 0 without the key)."""


def stage_breakdown(daemon: Any, dec: Any, chunks: list[bytes]) -> dict[str, float]:
    """Mean microseconds per decision of each hot-path stage (``STAGES``), the reads of ``chunks`` handed to the
    daemon back to back with a timer around each stage's functions (the timers add a little to every stage),
    ``total``, the instrumented read and decision whole, and ``untimed``, the same code on as many reads before the
    timers were put in: the stages cover the whole path (their sum is ``total``), and ``total - untimed`` is what the
    timers themselves cost. Each mean leaves out the slowest tenth of its reads (a read the machine interrupted: on a
    loaded machine one preemption moved a stage's mean by tens of microseconds)."""
    import importlib

    acc = dict.fromkeys([name for name, _ in STAGES], 0.0)
    stack: list[float] = []  # per active timed call: the time its nested timed calls took

    def timed(f: Any, stage: str) -> Any:
        def call(*a: Any, **k: Any) -> Any:
            stack.append(0.0)
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                acc[stage] += dt - stack.pop()
                if stack:
                    stack[-1] += dt

        return call

    def reads(ks: range, per_stage: bool) -> tuple[np.ndarray, np.ndarray]:
        """Each read's time and, with the timers in, its stages' times: [n], [n, stages]."""
        totals, parts = [], []
        for k in ks:
            for v in acc:
                acc[v] = 0.0
            t0 = time.perf_counter()
            daemon._on_frames(dec.feed_block(chunks[k]))
            totals.append(time.perf_counter() - t0)
            if per_stage:
                parts.append(list(acc.values()))
        return np.array(totals) * 1e6, np.array(parts) * 1e6

    q = len(chunks) // 4  # untimed: warm-up, measured; timed: warm-up (the timers' own first calls), measured
    reads(range(q), False)
    untimed, _ = reads(range(q, 2 * q), False)
    patched = []
    for stage, targets in STAGES:
        for module, cls_name, attr in targets:
            cls = getattr(importlib.import_module(module), cls_name)
            f = cls.__dict__.get(attr)
            if f is None:  # another tree's slipd (``--baseline-tree``, PYTHONPATH) may not have it
                continue
            patched.append((cls, attr, f))
            setattr(cls, attr, timed(f, stage))
    try:
        reads(range(2 * q, 3 * q), True)
        total, parts = reads(range(3 * q, 4 * q), True)
    finally:
        for cls, attr, f in patched:
            setattr(cls, attr, f)
    keep = total <= np.percentile(total, 90)
    means = parts[keep].mean(axis=0)
    unused = () if hasattr(daemon.detector, "rules") else ("confirmed rule",)  # (no rule confirmed: not a stage)
    return {**{k: float(v) for k, v in zip(acc, means) if k not in unused}, "total": float(total[keep].mean()),
            "untimed": float(untimed[untimed <= np.percentile(untimed, 90)].mean())}


def _stages_line(stages: dict[str, float]) -> str:
    """The per-stage breakdown as one line: each stage's microseconds, the instrumented total, and the same reads
    without the timers."""
    parts = [f"{k} {v:.1f}" for k, v in stages.items() if k not in ("total", "untimed")]
    line = f"stages (us): {', '.join(parts)}; instrumented total {stages['total']:.0f}"
    if "untimed" in stages:
        line += f", untimed {stages['untimed']:.0f} (the timers' own cost {stages['total'] - stages['untimed']:.0f})"
    return line


def _warm_and_cold(call: Any, decisions: int, sleep_s: float) -> tuple[float, float, float]:
    """Median microseconds of ``call(k)``, k = 0 .. 2 * decisions - 1: the first ``decisions`` one straight after the
    other (back to back), then each after ``sleep_s`` asleep: (back to back, after the sleep).

    Back to back means a run of calls with nothing in between. A call straight after one that followed a sleep is
    neither figure: it still pays part of the cold penalty (here 1.5 to 3.5 times the consecutive cost, varying from run
    to run and more for the model step than for the Python around it), so a ratio of two such figures said more about
    the machine's state than about the code. Third: the back-to-back calls' 10th percentile, the code with the least
    interference from the rest of the machine (on a loaded machine the median grows with the load, more for the Python
    path than for the model's call)."""
    got: tuple[list[float], list[float]] = ([], [])
    for k in range(2 * decisions):
        cold = k >= decisions
        if cold:
            time.sleep(sleep_s)
        t0 = time.perf_counter()
        call(k)
        got[cold].append(time.perf_counter() - t0)
    return (float(np.median(got[0][5:])) * 1e6, float(np.median(got[1][5:])) * 1e6,
            float(np.percentile(got[0][5:], 10)) * 1e6)


# ---------------------------------------------------------------------------------------------- instructions
INSTR_KINDS = ("hot_path", "python", "step")
"""What ``--instructions`` counts per decision: the hot path, the hot path with onnxruntime's call skipped, the step."""


def instructions_child(model: Path, sensors: int, kind: str, decisions: int) -> None:
    """The run ``instruction_counts`` counts: the hot path's set-up (``_hot_path_setup``, stride 10) and 20 reads and
    model steps to warm up, then ``decisions`` of ``kind`` (``INSTR_KINDS``; "none": nothing more, the set-up's own
    count). The same set-up whatever ``kind`` and ``decisions``, so the difference of two counts is their work."""
    with tempfile.TemporaryDirectory() as tmp:
        daemon, dec, chunks = _hot_path_setup(model, sensors, 10, 1020, Path(tmp))
        ens = daemon.ensemble
        window = np.zeros((sensors, ens.feature_spec.input_size), np.float32)
        for k in range(20):
            daemon._on_frames(dec.feed_block(chunks[k]))
            ens.step(window, stream=1_000)
        if kind == "python":
            ens._session.run_with_iobinding = lambda *a, **k: None  # as ``_python_alone``
        if kind in ("hot_path", "python"):
            for k in range(20, 20 + decisions):
                daemon._on_frames(dec.feed_block(chunks[k]))
        elif kind == "step":
            for _ in range(decisions):
                ens.step(window, stream=1_000)
        daemon.close()


def callgrind_total(text: str) -> int:
    """The instruction count of a callgrind output file (its ``summary:`` or ``totals:`` line)."""
    for line in text.splitlines():
        if line.startswith(("summary:", "totals:")):
            return int(line.split()[1])
    raise ValueError("no summary or totals line in the callgrind output")


def instruction_counts(model: Path, sensors: int, decisions: int) -> dict[str, float]:
    """Instructions per decision of each of ``INSTR_KINDS`` (``instructions_child`` under callgrind, the set-up's own
    count subtracted), and ``decisions``."""
    totals = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("none", *INSTR_KINDS):
            out = Path(tmp) / f"callgrind.{kind}"
            n = 0 if kind == "none" else decisions
            cmd = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable, __file__,
                   "--instructions-child", kind, str(n), "--sensors", str(sensors), "--model", str(model)]
            env = {**os.environ, "PYTHONHASHSEED": "0"}  # (the same dict layouts in every run)
            subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            totals[kind] = callgrind_total(out.read_text())
    return {**{kind: (totals[kind] - totals["none"]) / decisions for kind in INSTR_KINDS}, "decisions": decisions}


def print_instructions(args: argparse.Namespace) -> int:
    """``--instructions``: the counts per decision for each of ``--sensors``; ``--json`` writes them."""
    rows = []
    for sensors in args.sensors:
        c = instruction_counts(args.model, sensors, args.instr_decisions)
        rows.append({"sensors": sensors, **c})
        print(f"{sensors} sensor(s), stride 10, instructions per decision (callgrind, {args.instr_decisions} "
              f"decisions): hot path {c['hot_path'] / 1e3:.1f} k, with onnxruntime's call skipped (the Python around "
              f"the model) {c['python'] / 1e3:.1f} k, the model step alone {c['step'] / 1e3:.1f} k; hot path / step "
              f"{c['hot_path'] / c['step']:.2f}x (counts, not times: see --help)", flush=True)
    if args.json:
        write_json(args.json, json.dumps({"instruction_counts": rows, "model": str(args.model)}, indent=1))
    return 0


# ---------------------------------------------------------------------------------------------- floor
_RATES = """
import time, numpy as np
a = np.ones(16 << 20, np.float32); b = np.empty_like(a); best = 9.0
for _ in range(5):
    t0 = time.perf_counter(); np.copyto(b, a); best = min(best, time.perf_counter() - t0)
bw = 2 * a.nbytes / best
n = 512; x = np.ones((n, n), np.float32); best = 9.0
for _ in range(10):
    t0 = time.perf_counter(); x @ x; best = min(best, time.perf_counter() - t0)
print(bw, 2 * n**3 / best)
"""


def machine_rates() -> tuple[float, float]:
    """(bytes/s of a copy, float32 FLOP/s of a 512^3 matrix product), best of a few, one thread (a child
    process with the BLAS limited to one thread: the daemon's model runs on one)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _RATES], env=env, capture_output=True, text=True, check=True)
    bw, flops = (float(v) for v in out.stdout.split())
    return bw, flops


def floor_share(model: Path, sensors: int, stride: int, bw: float, flops_rate: float) -> tuple[float, float, float]:
    """(bytes/s, FLOP/s, share of one core) of the work itself: every frame's bytes read from the port and
    decoded into arrays once, the 5-sample median of each sensor's 27 channels per sample, a model step per
    sensor every ``stride`` samples."""
    from slipd.detect.manifest import load_manifest, onnx_path_of
    from sliplab.timing import model_cost

    manifest = load_manifest(model, check_graph=False)
    _, step_flops = model_cost(onnx_path_of(manifest, model))
    frame = _encoded(0, 0, np.zeros((sensors, 9, 3), np.float32))
    rate = 1000.0
    byte_rate = len(frame) * rate * 2  # read from the port, written into the arrays
    median_flops = sensors * 27 * 7 * rate  # a 5-wide min/max network: 7 comparisons per channel and sample
    flop_rate = median_flops + sensors * step_flops * rate / stride
    return byte_rate, flop_rate, byte_rate / bw + flop_rate / flops_rate


# ---------------------------------------------------------------------------------------------- main
def _paired_shares(args: argparse.Namespace, sensors: int, stride: int, trees: list[Path]) -> list[float]:
    """``--paired``: the CPU share of each tree's daemon, all running at once, each on its own emulated stream.

    This machine's idle periods cost more than its busy ones (after a few ms asleep the next decision finds its
    caches cold: the same hot path takes ~0.2 ms back to back and ~1 ms after a 10 ms sleep), and how often the
    host lets that happen drifts by several points within minutes. Runs side by side meet the same drift, so
    their difference is measured far more tightly than that of runs one after another. Their absolute shares
    read lower than a lone run's (the other pair keeps the cores busier): compare them with each other only."""
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(len(trees), mp_context=ctx) as pool:
        futures = [pool.submit(cpu_share, args.model, args.seconds, sensors, stride, tree) for tree in trees]
        return [f.result() for f in futures]


def compare_trees(args: argparse.Namespace) -> int:
    """``--baseline-tree``: CPU share of this tree and of the baseline, alternating (A B B A ...) so that a drift
    in the machine's state hits both alike; mean and each run per configuration."""
    trees = {"baseline": args.baseline_tree.resolve(), "this tree": ROOT}
    print(f"A/B CPU share, {args.seconds:g} s per run, {args.reps} runs each, baseline {trees['baseline']}, "
          f"load average {os.getloadavg()[0]:.2f}")
    out = []
    for sensors in args.sensors:
        for stride in args.strides:
            got: dict[str, list[float]] = {k: [] for k in trees}
            for r in range(args.reps):
                if args.paired:
                    for name, share in zip(trees, _paired_shares(args, sensors, stride, list(trees.values()))):
                        got[name].append(100 * share)
                    continue
                for name in (trees if r % 2 == 0 else reversed(list(trees))):
                    got[name].append(100 * cpu_share(args.model, args.seconds, sensors, stride, trees[name]))
            diff = np.subtract(got["this tree"], got["baseline"])
            row = {"sensors": sensors, "stride": stride, **got, "paired": bool(args.paired)}
            out.append(row)
            a, b = (float(np.mean(got[k])) for k in trees)
            spread = f", difference per pair {diff.mean():+.2f} +- {diff.std(ddof=1):.2f}" if args.paired and \
                len(diff) > 1 else ""
            print(f"  {sensors} sensor(s) stride {stride}: baseline {a:.2f} % -> this tree {b:.2f} % "
                  f"({100 * (b - a) / a:+.0f} %{spread}); runs {[round(x, 1) for x in got['baseline']]} / "
                  f"{[round(x, 1) for x in got['this tree']]}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.2f}")
    if args.json:
        write_json(args.json, json.dumps({"ab": out, "baseline": str(trees["baseline"]), "seconds": args.seconds},
                                        indent=1))
    return 0


def compare_viz(args: argparse.Namespace) -> int:
    """``--viz``: each configuration with the live view off and on (a viewer subscribed to every channel that never
    reads), alternating, ``--cpu-runs`` rounds; the medians of p99 latency and CPU, and every frame lost."""
    load0 = os.getloadavg()[0]
    per = args.seconds / args.cpu_runs
    rows = []
    for sensors in args.sensors:
        for stride in args.strides:
            got: dict[bool, dict[str, list[float]]] = {False: {}, True: {}}
            for rnd in range(args.cpu_runs):
                for viz in ((False, True) if rnd % 2 == 0 else (True, False)):
                    r = reaction_latency(args.model, per, sensors, stride, viz=viz)
                    r["cpu_percent"] = 100 * cpu_share(args.model, per, sensors, stride, viz=viz)
                    for k, v in r.items():
                        got[viz].setdefault(k, []).append(float(v))
                print(f"  {sensors} sensor(s) stride {stride}: round {rnd + 1} of {args.cpu_runs} done", flush=True)
            rows.append((sensors, stride, got))
    load1 = os.getloadavg()[0]
    print(f"\nlive view off / on, {args.cpu_runs} alternating rounds of {per:g} s, model {args.model.name}, load "
          f"average {load0:.2f} -> {load1:.2f} on {os.cpu_count()} cores; medians (each round in brackets)")
    print(f"{'sensors':>7} {'stride':>6} {'view':>4} {'p99 ms':>7} {'p50 ms':>7} {'lost':>5} {'CPU %':>6}  "
          "messages sent / dropped by the view")
    out = []
    for sensors, stride, got in rows:
        for viz in (False, True):
            g = got[viz]
            lost = int(sum(g["frames_lost"]))
            print(f"{sensors:>7} {stride:>6} {'on' if viz else 'off':>4} {np.median(g['latency_p99_ms']):>7.2f} "
                  f"{np.median(g['latency_p50_ms']):>7.2f} {lost:>5} {np.median(g['cpu_percent']):>6.1f}  "
                  f"{int(sum(g['view_sent']))} / {int(sum(g['view_dropped']))}   "
                  f"[p99 {', '.join(f'{x:.2f}' for x in g['latency_p99_ms'])}; "
                  f"CPU {', '.join(f'{x:.1f}' for x in g['cpu_percent'])}]")
            out.append({"sensors": sensors, "stride": stride, "viz": viz, **g})
    if args.json:
        write_json(args.json, json.dumps({"viz": out, "load_average": [load0, load1], "seconds": args.seconds}))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run every configuration and print them side by side."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=ROOT / "slipd" / "models" / "slip_ensemble_int8.json",
                   help="model manifest (default: the one config/slipd.yaml runs)")
    p.add_argument("--seconds", type=float, default=20.0, help="measured seconds per run and figure")
    p.add_argument("--sensors", type=int, nargs="*", default=[1, 2], help="sensor counts to run")
    p.add_argument("--strides", type=int, nargs="*", default=list(STRIDES), help="decision strides to run")
    p.add_argument("--json", type=Path, help="also write the figures as JSON: {runs: [...]}")
    p.add_argument("--baseline-tree", type=Path, metavar="DIR",
                   help="A/B the CPU share instead: this tree against the slipd of another checkout (e.g. `git "
                        "worktree add /tmp/base <commit>`), alternating runs on the same stream, at --strides")
    p.add_argument("--reps", type=int, default=4, help="with --baseline-tree: runs of each tree per configuration")
    p.add_argument("--paired", action="store_true",
                   help="with --baseline-tree: run the two trees at the same time, each on its own stream, and report "
                        "the difference per pair (robust to the machine's drift; the shares themselves read lower)")
    p.add_argument("--grip-control", action="store_true",
                   help="also the CPU share with reaction.policy grip_control (the controller holding the "
                        "quiet grasp, updated on every decision), beside stop-and-secure's in the same run")
    p.add_argument("--cpu-runs", type=int, default=3,
                   help="CPU share: interleaved rounds of --seconds / cpu-runs each; the median is the figure")
    p.add_argument("--hot-path", type=float, nargs="+", metavar="SLEEP_MS",
                   help="only the hot-path line, after each of these sleeps (ms): its cost against the idle time")
    p.add_argument("--confirm-rule", type=float, metavar="LEVEL",
                   help="with --hot-path: the daemon with decision.confirm_rule at LEVEL (0.3: the rule at rest on the "
                   "bench's still hold; 1e-6: the hold's P(slip) reaches it, the rule runs throughout)")
    p.add_argument("--viz", action="store_true",
                   help="the live view off and on (a Foxglove viewer that never reads): p99, frames lost, CPU")
    p.add_argument("--instructions", action="store_true",
                   help="only the hot path's instruction counts per decision (valgrind's callgrind; load does not "
                        "change them): hot path, the Python around the model, the step alone; counts, not times")
    p.add_argument("--instr-decisions", type=int, default=2000,
                   help="with --instructions: decisions counted per run (valgrind runs Python about 50 times slower)")
    p.add_argument("--instructions-child", nargs=2, metavar=("KIND", "N"), help=argparse.SUPPRESS)
    p.add_argument("--decode-only", metavar="PORT", help=argparse.SUPPRESS)
    p.add_argument("--idle-loop", type=float, metavar="HZ", help=argparse.SUPPRESS)
    p.add_argument("--idle-step", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.decode_only:
        decode_only(args.decode_only, args.sensors[0])
        return 0
    if args.instructions_child:
        instructions_child(args.model, args.sensors[0], args.instructions_child[0], int(args.instructions_child[1]))
        return 0
    if args.instructions:
        return print_instructions(args)
    if args.idle_loop:
        idle_loop(args.idle_loop, args.model if args.idle_step else None, args.sensors[0])
        return 0
    if args.baseline_tree:
        return compare_trees(args)
    if args.hot_path:
        for s in args.sensors:
            for ms in args.hot_path:
                h = hot_path_cost(args.model, s, sleep_s=ms / 1e3, confirm_rule=args.confirm_rule)
                print(f"{s} sensor(s): hot path per decision {h['back_to_back_us']:.0f} us back to back, "
                      f"{h['after_sleep_us']:.0f} us after {ms:g} ms asleep; the model step alone "
                      f"{h['model_back_to_back_us']:.0f} / {h['model_after_sleep_us']:.0f} us (medians of "
                      f"{HOT_DECISIONS}); 10th percentiles back to back {h['back_to_back_p10_us']:.0f} / "
                      f"{h['model_back_to_back_p10_us']:.0f} us; with onnxruntime's call skipped "
                      f"{h['python_back_to_back_us']:.0f} us back to back", flush=True)
                print(f"  {_stages_line(h['stages_us'])}", flush=True)
        return 0
    logging.getLogger("slipd").setLevel(logging.ERROR)  # one alarm per window here: keep the log quiet
    if args.viz:
        return compare_viz(args)
    load0 = os.getloadavg()[0]
    runs: list[dict[str, Any]] = []
    for sensors in args.sensors:
        for stride in args.strides:
            run: dict[str, Any] = {"sensors": sensors, "stride": stride}
            run.update(reaction_latency(args.model, args.seconds, sensors, stride))
            runs.append(run)
            print(f"  {sensors} sensor(s) stride {stride}: p99 {run['latency_p99_ms']:.2f} ms", flush=True)
    # The CPU share in --cpu-runs rounds of seconds / cpu_runs each, every configuration once per round in a rotated
    # order: this machine's drift (several points within minutes, see _paired_shares) then spreads over all of them
    # alike, and the median of the rounds is the figure (every round is kept in the JSON).
    per = args.seconds / args.cpu_runs
    keys: list[tuple[str, int, int | None]] = [("stop_and_secure", r["sensors"], r["stride"]) for r in runs]
    if args.grip_control:
        keys += [("grip_control", r["sensors"], r["stride"]) for r in runs]
    keys += [("decode_only", s, None) for s in args.sensors]
    keys += [("idle_loop", 1, None)]  # the decision rate at stride 10: 100 wake-ups a second
    keys += [("step_loop", s, None) for s in args.sensors]  # ... each with the model's step alone
    shares: dict[tuple[str, int, int | None], list[float]] = {k: [] for k in keys}
    for rnd in range(args.cpu_runs):
        shift = rnd * len(keys) // args.cpu_runs
        for policy, sensors, stride in keys[shift:] + keys[:shift]:
            pol = "stop_and_secure" if policy in ("decode_only", "idle_loop", "step_loop") else policy
            idle = IDLE_HZ if policy in ("idle_loop", "step_loop") else None
            shares[(policy, sensors, stride)].append(100 * cpu_share(args.model, per, sensors, stride, policy=pol,
                                                                     idle_hz=idle, idle_step=policy == "step_loop"))
        print(f"  CPU round {rnd + 1} of {args.cpu_runs} done", flush=True)
    for r in runs:
        got = shares[("stop_and_secure", r["sensors"], r["stride"])]
        r.update(cpu_percent=float(np.median(got)), cpu_percent_runs=got)
        if args.grip_control:
            got = shares[("grip_control", r["sensors"], r["stride"])]
            r.update(cpu_percent_grip_control=float(np.median(got)), cpu_percent_grip_control_runs=got)
    base = {s: float(np.median(shares[("decode_only", s, None)])) for s in args.sensors}
    idle_runs = shares[("idle_loop", 1, None)]
    step_loop = {s: float(np.median(shares[("step_loop", s, None)])) for s in args.sensors}
    hot = {(r["sensors"], r["stride"]): hot_path_cost(args.model, r["sensors"], stride=r["stride"]) for r in runs}
    for r in runs:
        h = hot[(r["sensors"], r["stride"])]
        r.update(hot_path_us={"back_to_back": h["back_to_back_us"], "after_sleep": h["after_sleep_us"],
                              "back_to_back_p10": h["back_to_back_p10_us"]},
                 step_us={"back_to_back": h["model_back_to_back_us"], "after_sleep": h["model_after_sleep_us"],
                          "back_to_back_p10": h["model_back_to_back_p10_us"]},
                 python_us={"back_to_back": h["python_back_to_back_us"],
                            "back_to_back_p10": h["python_back_to_back_p10_us"]},
                 stages_us=h["stages_us"])
    bw, flops_rate = machine_rates()
    load1 = os.getloadavg()[0]

    print(f"\nslipd daemon at 1 kHz, {args.seconds:g} s per figure, model {args.model.name}, load average "
          f"{load0:.2f} -> {load1:.2f} on {os.cpu_count()} cores (CPU is the process's own time)")
    print("latency: deciding sample written -> tighten bytes at the servo; 'to decision': written -> decision made")
    print(f"CPU: the median of {args.cpu_runs} interleaved runs of {per:g} s (each run in brackets)")
    print(f"{'sensors':>7} {'stride':>6} {'CPU %':>7} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} "
          f"{'to decision p50/p99':>20} {'alarms':>7} {'sent':>7} {'lost':>5} {'floor %':>8}  target")
    for r in runs:
        byte_rate, flop_rate, floor = floor_share(args.model, r["sensors"], r["stride"], bw, flops_rate)
        r.update(floor_percent=100 * floor, floor_bytes_per_s=byte_rate, floor_flops_per_s=flop_rate)
        target = ""
        if r["stride"] == 10:
            cpu_t = TARGET_CPU.get(r["sensors"], 0.12) * 100
            ok = r["cpu_percent"] <= cpu_t and r["latency_p99_ms"] <= TARGET_P99_MS and r["frames_lost"] == 0
            target = f"CPU <= {cpu_t:.0f} %, p99 <= {TARGET_P99_MS:g} ms, 0 lost: {'met' if ok else 'NOT met'}"
        print(f"{r['sensors']:>7} {r['stride']:>6} {r['cpu_percent']:>7.1f} {r['latency_p50_ms']:>7.2f} "
              f"{r['latency_p99_ms']:>7.2f} {r['latency_max_ms']:>7.2f} "
              f"{r['decision_p50_ms']:>10.2f} / {r['decision_p99_ms']:<7.2f} {r['alarms']:>7} {r['frames_sent']:>7} "
              f"{r['frames_lost']:>5} {r['floor_percent']:>8.3f}  {target}  "
              f"[{', '.join(f'{x:.1f}' for x in r['cpu_percent_runs'])}]")
    for r in runs:
        if "cpu_percent_grip_control" in r:
            print(f"{r['sensors']:>7} {r['stride']:>6} {r['cpu_percent_grip_control']:>7.1f}  with reaction.policy "
                  f"grip_control (stop_and_secure above: {r['cpu_percent']:.1f})")
    for s, cpu in base.items():
        print(f"{s:>7} {'decode-only (every frame as it arrives)':<40} {cpu:>5.1f} % CPU")
    print(f"{'-':>7} {f'event loop waking {IDLE_HZ:g} times a second, nothing else':<40} "
          f"{float(np.median(idle_runs)):>5.1f} % CPU  [{', '.join(f'{x:.1f}' for x in idle_runs)}]")
    for s, cpu in step_loop.items():
        runs_s = shares[("step_loop", s, None)]
        print(f"{s:>7} {'the same, each wake-up one model step':<40} {cpu:>5.1f} % CPU  "
              f"[{', '.join(f'{x:.1f}' for x in runs_s)}]")
    for r in runs:
        if r["stride"] == 10:
            idle = float(np.median(idle_runs))
            print(f"{r['sensors']:>7} sensor(s) stride 10: CPU {times(r['cpu_percent'], idle)} the idle event loop, "
                  f"{times(r['cpu_percent'], step_loop[r['sensors']])} the loop with the model's step alone")
    print(f"hot path per decision (decode `stride` frames, freshness, detector, decision, metrics; no event loop), "
          f"medians of {HOT_DECISIONS}, back to back / after {HOT_SLEEP_S * 1e3:g} ms asleep, against the model step "
          "alone (one onnxruntime call on the same batch); per stage: means, instrumented, with the recorder on")
    for r in runs:
        hp, st = r["hot_path_us"], r["step_us"]
        print(f"{r['sensors']:>7} {r['stride']:>6}  hot path {hp['back_to_back']:.0f} / {hp['after_sleep']:.0f} us, "
              f"step {st['back_to_back']:.0f} / {st['after_sleep']:.0f} us: "
              f"{hp['back_to_back'] / st['back_to_back']:.2f}x / {hp['after_sleep'] / st['after_sleep']:.2f}x; "
              f"10th percentiles back to back {hp['back_to_back_p10']:.0f} / {st['back_to_back_p10']:.0f} us: "
              f"{hp['back_to_back_p10'] / st['back_to_back_p10']:.2f}x")
        py = r["python_us"]
        print(f"{'':>16}the same path with onnxruntime's call skipped (the Python around the model) "
              f"{py['back_to_back']:.0f} us back to back: {py['back_to_back'] / st['back_to_back']:.2f}x the step "
              "alone")
        print(f"{'':>16}{_stages_line(r['stages_us'])}")
    print(f"floor: bytes over {bw / 1e9:.1f} GB/s (copy) + FLOPs over {flops_rate / 1e9:.1f} GFLOP/s (float32 "
          "matrix product), one thread")
    if args.json:
        out = {"runs": runs, "decode_only": [{"sensors": s, "cpu_percent": c,
                                              "cpu_percent_runs": shares[("decode_only", s, None)]}
                                             for s, c in base.items()],
               "idle_loop": {"hz": IDLE_HZ, "cpu_percent": float(np.median(idle_runs)), "cpu_percent_runs": idle_runs},
               "idle_loop_percent": float(np.median(idle_runs)), "cpu_runs": args.cpu_runs,
               "step_loop": [{"sensors": s, "cpu_percent": c, "cpu_percent_runs": shares[("step_loop", s, None)]}
                             for s, c in step_loop.items()],
               "machine": {"copy_bytes_per_s": bw, "flops_per_s": flops_rate, "load_average": [load0, load1],
                           "cores": os.cpu_count()},
               "seconds": args.seconds, "model": str(args.model)}
        write_json(args.json, json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
