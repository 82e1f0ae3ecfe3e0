"""The closed-loop simulated rig: physics at 1 kHz wired to emulated devices, the unchanged daemon reacting.

    rig process                                               daemon process (``slipd run``)
    GripperStepper (physics) --force/disp--> EmulatedPapillArray --pty, PTSCOM--> SerialSensor -> Detector
          ^ grip force                                                                      | alarm
          |                         EmulatedMX28 <--pty, Dynamixel 2.0-- DynamixelGripper <--+ tighten
          ^ finger motion           URControllerProcess <--RTDE, 127.0.0.x-- URArm <---------+ stopL
          +------------------------ (own process; the rig lifts with move_l, reads the TCP speed)

The physics steps inside the sensor emulator's frame callback, once per frame, so the sensor stream
and the physics share one real-time clock. Each step reads the servo's grip force (with its lag and
62 Hz refresh) and the arm's TCP speed (the finger's motion), so the daemon's reaction changes the
physics: a stop halts the lift, a tighten raises the grip.

Timeline (seconds from the first frame): the object rests on a table, the sensor unloaded, while the
daemon tares (``GRASP_S``); the grasp closes on the object (the servo already holds the daemon's hold
setting; the object enters the jaw); after the scene's close and settle time the arm lifts it with the
scene's UR ``movel`` speed and acceleration (``LIFT_MM`` up).

Measurement per run (``RigResult``): truth onset of incipient slip and gross slip (the method's labels
from per-pillar slip), the daemon's first alarm (its log), when the stop reached the UR controller and
the tighten reached the servo, the object's translation and rotation relative to the finger when the
grasp became secure (object at rest after the reaction), and whether it was dropped.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, ParamSpec, TypeVar, cast

import numpy as np
import yaml

from slipd.detect.manifest import read_manifest
from slipd.sim import effects as fx
from slipd.sim.devices.mx28 import JawParams
from slipd.sim.harness import EmulatedDevices
from slipd.sim.labels import motion_labels
from slipd.sim.physics import DT_S, GripperStepper, ObjectParams, measured_disp, saturate, sensor_params
from slipd.sim.scene import GripperScene, gripper_context, load_scene

# Packaged with slipd (``slipd[sim]`` runs from any folder); a checkout's config/ links to the same files.
_PACKAGE = Path(str(resources.files("slipd.sim")))
SCENES = _PACKAGE / "scenes"
DEFAULT_SCENE = SCENES / "thermos_flask_undergrip.yaml"
"""The demo's scene: its incipient phase on the rig (32 ms without a reaction, ``slipd sim --no-reaction``) is long
enough for the alarm to come inside it; the wooden box's (19 ms) is not."""
DEFAULT_CONFIG = _PACKAGE / "sim.yaml"

GRASP_S = 0.8
"""The object enters the jaw here: the daemon has opened the sensor and tared on an unloaded stretch."""
LIFT_MM = 100.0
SECURE_REST_MM_S = 1.0
"""The grasp counts as secure once the object moves slower than this relative to the finger ..."""
SECURE_HOLD_S = 0.05
"""... for this long after the reaction reached the devices."""
DROP_MM = 20.0
GROSS_MM, GROSS_DEG = 2.0, 2.0
_ALARM_RE = re.compile(r"ALARM: .* at t=([0-9.]+) s")


@dataclass
class RigResult:
    """Summary of one closed-loop run (times in seconds from the first sensor frame; None: did not happen)."""

    scene: str
    reaction: bool
    lift_start_s: float
    onset_s: float | None
    gross_slip_s: float | None
    """All considered pillars slipping (the method's label end)."""
    gross_motion_s: float | None
    """The object moved more than 2 mm or 2 deg relative to the finger (the method's online T_g)."""
    alarm_s: float | None
    stop_reached_s: float | None
    tighten_reached_s: float | None
    secure_s: float | None
    translation_mm: float
    rotation_deg: float
    dropped: bool
    max_grip_n: float
    frames: int
    sensor_stalls: int = 0
    policy: str = "stop_and_secure"
    arm_stopped: bool = False
    """The UR controller received a stop (the lift did not go on as planned)."""
    final_translation_mm: float = 0.0
    final_rotation_deg: float = 0.0
    """Object motion relative to the finger at the end of the run (after the whole lift and hold)."""
    mean_grip_n: float = 0.0
    """Mean grip force from the lift to the end of the run."""
    """Fail-safe stops for a stalled sensor: the rig fell behind real time (a busy machine), so the run
    measured the fail-safe, not the detector."""

    def verdict(self) -> str:
        """In words: when the alarm came relative to incipient and gross slip."""
        if self.alarm_s is None:
            return "no alarm" + (" although the object slipped" if self.onset_s is not None else "")
        if self.onset_s is None:
            return "alarm without any slip in the physics: a false alarm"
        after = _ms(self.alarm_s - self.onset_s)
        if self.alarm_s < self.onset_s:
            return f"alarm {-after} ms before the labelled onset of incipient slip"
        if self.gross_slip_s is None:
            return f"alarm during incipient slip ({after} ms after it began); gross slip never came"
        if self.alarm_s < self.gross_slip_s:
            return (f"alarm during incipient slip ({after} ms after it began, "
                    f"{_ms(self.gross_slip_s - self.alarm_s)} ms before gross slip)")
        return (f"alarm after gross slip ({_ms(self.alarm_s - self.gross_slip_s)} ms after every pillar slipped): "
                "too late to count as incipient-slip detection")

    def lines(self) -> list[str]:
        """Human-readable summary: the events on one time line, in ms from the onset of incipient slip."""
        zero = self.onset_s if self.onset_s is not None else self.lift_start_s
        origin = "the onset of incipient slip" if self.onset_s is not None else "the start of the lift"

        def t(v: float | None, never: str = "never") -> str:
            return f"{never:>8}" if v is None else f"{_ms(v - zero):+6d} ms"

        events = [(self.lift_start_s, "never", "the arm starts lifting"),
                  (self.onset_s, "never", "incipient slip: some pillars in contact slip, others stick (truth)"),
                  (self.alarm_s, "no alarm", "the daemon's alarm"),
                  (self.stop_reached_s, "no stop", "the stop reaches the arm"),
                  (self.tighten_reached_s, "no grip", "the tighten reaches the gripper"),
                  (self.gross_slip_s, "never", "gross slip: every pillar in contact slips (truth)"),
                  (self.gross_motion_s, "never", "the object has moved 2 mm or 2 deg against the finger"),
                  (self.secure_s, "never", "the grasp is secure (object at rest against the finger)")]
        # In time order; what never happened goes last.
        events.sort(key=lambda e: (e[0] is None, e[0] or 0.0))
        return [
            f"scene {self.scene}  (reaction {'on' if self.reaction else 'off'}, {self.frames / 1000:.1f} s)",
            f"  times in ms from {origin} ({zero:.3f} s into the run)",
            *(f"  {t(v, never)}  {text}" for v, never, text in events),
            f"  => {self.verdict()}",
            f"  object moved {self.translation_mm:.2f} mm and turned {self.rotation_deg:.2f} deg against the finger "
            f"{'before it was secure' if self.secure_s is not None else 'by the end of the run'}; "
            f"{'DROPPED' if self.dropped else 'not dropped'} (max grip {self.max_grip_n:.1f} N)",
        ] + ([f"  WARNING: {self.sensor_stalls} sensor stall(s): the rig fell behind real time; run it on a quieter "
              "machine"] if self.sensor_stalls else [])


def _ms(seconds: float) -> int:
    return round(seconds * 1000)


def scene_physics(scene: GripperScene, seed: int, batch: int = 1
                  ) -> tuple[list[fx.Effect], fx.SimContext, GripperStepper]:
    """A gripper scene's physics as the rig runs it: its effects, its context after the contact, motion and load
    stages, and a ``GripperStepper`` holding ``batch`` copies of its object (``slipd.sim.holding`` runs a batch of
    grips through the same physics)."""
    effects = scene.build_effects()
    ctx = gripper_context(scene)
    for stage in ("contact", "motion", "load"):
        fx.run_stage(stage, effects, ctx, seed)
    o = scene.object
    stepper = GripperStepper(
        sensor_params(scene.sensor), ObjectParams(o.mass_kg, o.mu_s, o.mu_k, o.size_mm, scene.rigid_kt_n_mm), batch,
        ctx.contact_offset[None], ctx.contact_mask[None], np.full(batch, bool(ctx.table)),
    )
    return effects, ctx, stepper


class RigPhysics:
    """The physics side of the rig: one GripperStepper advanced per sensor frame from device state."""

    def __init__(self, scene: GripperScene, seed: int, duration_s: float, devices: EmulatedDevices | None = None):
        self.scene = scene
        self.seed = seed
        self.sensor = sensor_params(scene.sensor)
        self.effects, ctx, self.stepper = scene_physics(scene, seed)
        self.ctx = ctx
        self.load = np.asarray(ctx.gravity[0], np.float64)[None]
        self.com = np.asarray(ctx.com_offset, np.float64)[None]
        self.devices = devices
        n = round(duration_s / DT_S)
        self.n = n
        self.force = np.zeros((n, 9, 3), np.float32)
        self.disp = np.zeros((n, 9, 3), np.float32)
        self.slip = np.zeros((n, 9), bool)
        self.motion = np.zeros((n, 3), np.float32)
        self.grip = np.zeros(n, np.float32)
        self.arm_speed = np.zeros(n, np.float32)
        self.mono = np.zeros(n, np.float64)
        self.steps = 0
        self.done = threading.Event()
        self._begin = threading.Event()
        self._start: int | None = None  # the emulator's frame index at which the timeline began
        self.lift_index: int | None = None
        self.grasp_index = round(GRASP_S / DT_S)
        self.lift_at = self.grasp_index + round((scene.grip.close_s + scene.settle_s) / DT_S)
        self._prepare_measurement()
        self.fill_kg_s, self.fill_after_s, self.fill_to_kg = 0.0, 0.0, 0.0
        self.daemon_p: list[tuple[float, float]] = []
        """The daemon's P(slip) decisions (seconds from the timeline's start, p), filled in after the run."""
        self.threshold: float | None = None
        """The ensemble's alarm threshold (None: a heuristic detector ran)."""

    def grasp(self) -> None:
        """The object enters the jaw (hook for the rig's timeline)."""

    def lift(self) -> None:
        """Start the scene's lift on the UR controller (hook for the rig's timeline)."""

    def begin(self) -> None:
        """Start the scene's timeline at the next frame (until then the sensor streams unloaded noise)."""
        self._begin.set()

    @property
    def timeline_start_s(self) -> float:
        """Sensor-clock time at which the timeline began (0 before it did)."""
        return (self._start or 0) * DT_S

    def _idle(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """An unloaded sample with the scene's measurement noise: a real sensor streams before anything
        happens, and a daemon that sees no frames (or bit-identical ones) rightly fails safe."""
        zero = np.zeros((9, 3), np.float32)
        measured = self._measure(zero, i % self.n)
        return measured, measured_disp(zero, zero, measured, self.sensor).astype(np.float32)

    def source(self, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The sensor emulator's frame callback: advance the physics one sample, return (force, disp)."""
        if self._start is None:
            if not self._begin.is_set():
                return self._idle(k)
            self._start = k
        i = k - self._start
        if i >= self.n:
            self.done.set()
            return None
        if i == self.grasp_index:
            self.grasp()
        if i == self.lift_at:
            self.lift_index = i
            self.lift()
        grip, v_up = self.device_inputs()
        st = self.stepper
        if self.fill_kg_s and self.lift_index is not None and i >= self.lift_at + round(self.fill_after_s / DT_S):
            # A cup being filled during the hold: its mass (and weight) grows at fill_kg_s up to fill_to_kg.
            st.mass[:] = np.minimum(st.mass + self.fill_kg_s * DT_S, self.fill_to_kg)
        # Drive the finger at the arm's measured speed: the acceleration that brings the stepper's
        # finger velocity to the TCP's over one sample (+y in the sensor plane is up).
        accel = np.array([[0.0, (v_up - st.finger_vel[0, 1]) / DT_S]])
        out = st.step(np.array([grip]), accel, self.load, self.com)
        force = saturate(out.force, self.sensor)[0]
        measured = self._measure(force, i)
        disp = measured_disp(out.disp[0], force, measured, self.sensor)
        self.force[i], self.disp[i] = measured, disp
        self.slip[i], self.motion[i] = out.slip[0], out.object_motion[0]
        self.grip[i], self.arm_speed[i], self.mono[i] = grip, v_up, time.monotonic()
        self.steps = i + 1
        return measured, disp.astype(np.float32)

    def device_inputs(self) -> tuple[float, float]:
        """(grip force N, finger speed up mm/s) from the emulated servo and UR controller."""
        dev = self.devices
        grip = dev.servo.grip_force_n if dev is not None else 0.0
        v = dev.ur.state().tcp_speed[2] * 1e3 if dev is not None and dev.ur is not None else 0.0
        return grip, v

    def _measure(self, force: np.ndarray, i: int) -> np.ndarray:
        """The scene's signal-stage effects on one sample.

        Additive effects (noise, glitches, drift) are the same effect classes run once, at start-up,
        on a zero signal (``_additive``); quantisation is applied per sample. The anti-alias lowpass
        needs filter state across samples and is not applied in closed loop (at 338.8 Hz it barely
        changes a 1 kHz stream of slowly varying forces).
        """
        x = force.astype(np.float64) + self._additive[i]
        if self._quantise is not None:
            ctx = fx.SimContext(family="gripper", n=1, t_s=self._t1, motion_start=0)
            ctx.force = x[None]
            self._quantise.apply(ctx, None)  # type: ignore[arg-type]
            x = ctx.force[0]
        return x.astype(np.float32)

    def _prepare_measurement(self) -> None:
        additive = [e for e in self.effects if e.stage == "signal" and e.name in ("noise", "glitches", "drift")]
        ctx = fx.SimContext(family="gripper", n=self.n, t_s=np.arange(self.n) * DT_S, motion_start=0)
        ctx.force = np.zeros((self.n, 9, 3))
        fx.run_stage("signal", additive, ctx, self.seed)
        self._additive = ctx.force
        self._quantise = next((e for e in self.effects if e.name == "quantisation"), None)
        self._t1 = np.zeros(1)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2) as r:
        return r.read().decode()


def _daemon_config(base: Path, dev: EmulatedDevices, metrics_port: int, react: bool, out_dir: Path,
                   detector: str | None = None, extra: dict[str, Any] | None = None) -> Path:
    from slipd.config import load_config, override

    cfg = load_config(base)
    updates: dict[str, Any] = {**dev.overrides(), "metrics.enabled": True, "metrics.port": metrics_port,
                               "recorder.directory": str(out_dir / "recordings")}
    if not react:
        updates["reaction.actions"] = []
    if detector is not None:
        updates["model.detector"] = detector
        if detector != "onnx":
            updates["decision.confirm_rule"] = None  # (a heuristic alone: no model to confirm it)
    updates.update(extra or {})
    cfg = override(cfg, updates)
    path = out_dir / "daemon.yaml"
    path.write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    return path


START_ATTEMPTS = 3
"""Runs started afresh when the daemon cannot reach the emulated devices at start-up (exit code 5 before it is
ready): on a loaded machine the emulators' threads can miss the daemon's first status packets. A failure after the
daemon is ready is never retried: it belongs to the run."""


P = ParamSpec("P")
R = TypeVar("R")


class DeviceStartupError(RuntimeError):
    """The daemon exited with the device start-up code (5) before it was ready."""


def _afresh_on_device_startup_failure(run: Callable[P, R]) -> Callable[P, R]:
    """``run`` started afresh up to ``START_ATTEMPTS`` times when the daemon's device start-up fails; each new
    attempt is logged through the call's ``log``."""

    @functools.wraps(run)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        log = cast(Callable[[str], object], kwargs.get("log", print))
        for attempt in range(1, START_ATTEMPTS + 1):
            try:
                return run(*args, **kwargs)
            except DeviceStartupError as exc:
                if attempt == START_ATTEMPTS:
                    raise
                log(f"rig: the daemon's device start-up failed (attempt {attempt} of {START_ATTEMPTS}); "
                    f"starting again: {str(exc).strip().splitlines()[-1]}")
        raise AssertionError("unreachable")

    return wrapper


@_afresh_on_device_startup_failure
def run_rig(
    scene_path: str | Path = DEFAULT_SCENE,
    config_path: str | Path = DEFAULT_CONFIG,
    *,
    duration_s: float | None = None,
    react: bool = True,
    seed: int | None = None,
    host: str = "127.0.0.2",
    out_dir: str | Path | None = None,
    detector: str | None = None,
    log=print,
    overrides: dict[str, Any] | None = None,
    fill: tuple[float, float, float] | None = None,
) -> tuple[RigResult, RigPhysics]:
    """Run one closed-loop scene: start the emulators and ``slipd run`` as a separate process, stream the
    physics in real time, and measure what happened. Returns the summary and the recorded physics."""
    scene = load_scene(scene_path)
    if not isinstance(scene, GripperScene):
        raise ValueError(f"{scene_path}: the rig runs gripper scenes (family: gripper)")
    seed = scene.seed if seed is None and scene.seed is not None else (seed or 0)
    duration_s = duration_s or max(scene.duration_s, 3.0)
    tmp_ctx = tempfile.TemporaryDirectory(prefix="slipd-rig-") if out_dir is None else contextlib.nullcontext(out_dir)
    with tmp_ctx as tmp:
        out = Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        from slipd.config import load_config, override

        # The emulated servo and jaw follow the config the daemon runs (its overrides too): the servo answers at its
        # bus ID and the jaw meets the object where that config's hold setting puts it.
        base_cfg = override(load_config(config_path), overrides) if overrides else load_config(config_path)
        g = base_cfg.gripper
        stiffness = JawParams().stiffness_n_per_tick
        # The jaw meets the object where the hold setting produces the scene's grip force.
        sign = 1 if g.secure_position > g.hold_position else -1
        contact = g.hold_position - sign * scene.grip.force_n / stiffness
        jaw = JawParams(contact_position=None, closing_sign=sign, initial_position=float(g.hold_position))
        physics = RigPhysics(scene, seed, duration_s)
        if fill is not None:  # (kg/s, seconds after the lift starts, final kg): a cup being filled
            physics.fill_kg_s, physics.fill_after_s, physics.fill_to_kg = fill
        with EmulatedDevices(physics.source, host=host, protocol=float(g.protocol), dxl_id=g.id, jaw=jaw) as dev:
            physics.devices = dev
            physics.grasp = lambda: dev.servo.set_contact(contact)  # type: ignore[method-assign]
            v, a = scene.motion.speed_accel()

            def lift() -> None:
                pose = list(dev.ur.state().tcp_pose)
                pose[2] += LIFT_MM / 1e3
                dev.ur.move_l(pose, speed=v / 1e3, accel=a / 1e3)

            physics.lift = lift  # type: ignore[method-assign]
            port = _free_port()
            cfg_file = _daemon_config(Path(config_path), dev, port, react, out, detector, overrides)
            log_file = out / "daemon.log"
            env = {**os.environ, "PYTHONUNBUFFERED": "1"}
            env.pop("NOTIFY_SOCKET", None)
            with open(log_file, "w") as lf:
                proc = subprocess.Popen([sys.executable, "-m", "slipd", "run", "--config", str(cfg_file)],
                                        stdout=lf, stderr=subprocess.STDOUT, env=env)
            # The sensor streams unloaded noise from the start, as a real one does: the daemon's liveness
            # check fails safe on a sensor that stays silent after start-up.
            dev.start_sensor()
            try:
                _wait_ready(proc, port, log_file)
                log(f"rig: daemon ready (pid {proc.pid}, metrics http://127.0.0.1:{port}/metrics); streaming")
                physics.begin()
                physics.done.wait(duration_s + 30)
                # Snapshot at once: with the stream ended the daemon will soon see a stalled sensor
                # and (rightly) fail safe, which must not count as this run's reaction.
                ur_state = dev.ur.state()
                writes = dev.servo.writes()
                metrics_text = _scrape(port)
                # For out/sim.mcap (slipd.sim.rig_mcap): what the devices received, and the sensor's bias.
                physics.ur_state, physics.servo_writes = ur_state, writes
                physics.sensor_bias, physics.sensor_bias_disp = dev.sensor.bias
            finally:
                proc.terminate()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        text = log_file.read_text()
        (out / "metrics.txt").write_text(metrics_text)
        physics.daemon_p = _daemon_p_slip(out / "recordings", physics.timeline_start_s)
        if (detector or base_cfg.model.detector) == "onnx":
            physics.threshold = base_cfg.decision.threshold or read_manifest(base_cfg.model.manifest).threshold
        result = summarise(physics, scene_path, react, text, ur_state, writes, g.secure_position)
        result.policy = str((overrides or {}).get("reaction.policy", base_cfg.reaction.policy))
    return result, physics


def _daemon_p_slip(folder: Path, offset_s: float) -> list[tuple[float, float]]:
    """The daemon's own P(slip) decisions, (seconds from the timeline's start, p), from the recordings it wrote around
    its alarms; empty when it wrote none (no alarm)."""
    from slipd.recording import Recording

    out: dict[float, float] = {}
    for path in sorted(folder.glob("*.npz")):
        dec = Recording.load(path).meta.get("decisions") or {}
        for t_us, p in zip(dec.get("t_us", []), dec.get("p_slip", [])):
            out[t_us / 1e6 - offset_s] = float(p)
    return sorted(out.items())


def _wait_ready(proc: subprocess.Popen, port: int, log_file: Path, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            error = DeviceStartupError if proc.returncode == 5 else RuntimeError
            raise error(f"daemon exited with {proc.returncode}:\n{log_file.read_text()[-3000:]}")
        with contextlib.suppress(OSError):
            if "slipd_ready 1.0" in _scrape(port):
                return
        time.sleep(0.1)
    raise RuntimeError(f"daemon not ready after {timeout} s:\n{log_file.read_text()[-3000:]}")


def _index_of(mono: np.ndarray, t: float | None) -> int | None:
    if t is None or t <= 0 or not len(mono):
        return None
    return int(np.searchsorted(mono, t))


def summarise(physics: RigPhysics, scene_path: Any, react: bool, daemon_log: str, ur_state: Any, writes: list,
              secure_position: int) -> RigResult:
    """Turn the recorded run into a ``RigResult`` (see the module docstring)."""
    n = physics.steps
    mono = physics.mono[:n]
    lift = physics.lift_index or 0
    motion = physics.motion[:n].astype(np.float64) - physics.motion[lift]
    _, onset, gross = motion_labels(physics.slip[:n], physics.force[lift, :, 2], lift)
    # The daemon logs the sensor's own clock, which ran through the idle frames before the timeline began.
    offset = physics.timeline_start_s
    alarms = [float(m) - offset for m in _ALARM_RE.findall(daemon_log)]
    alarm_s = alarms[0] if alarms else None
    stop_i = _index_of(mono, ur_state.last_stop_received_t) if ur_state.stop_count else None
    # A reaction is a write from the lift on: a tighten (the secure goal position) or, under grip_control, a new
    # grip force (Goal PWM). grip_control's take-over at the hold force goes out before the lift: not a reaction.
    t_lift = mono[lift] if n else 0.0
    tighten = [w.t for w in writes if w.t >= t_lift and (w.address == 100 or (
        w.address in (116, 30) and int.from_bytes(bytes(w.data[:2]), "little") == secure_position))]
    tighten_i = _index_of(mono, tighten[0]) if tighten else None
    reached = max([i for i in (stop_i, tighten_i) if i is not None], default=None)
    speed = np.hypot(*np.gradient(motion[:, :2], DT_S, axis=0).T) if n > 2 else np.zeros(n)
    rot_speed = np.abs(np.gradient(motion[:, 2], DT_S)) if n > 2 else np.zeros(n)
    secure_i = None
    start = reached if reached is not None else lift
    hold = int(SECURE_HOLD_S / DT_S)
    rest = (speed < SECURE_REST_MM_S) & (rot_speed < SECURE_REST_MM_S)
    if react and reached is not None:
        for k in range(start, n - hold):
            if rest[k: k + hold].all():
                secure_i = k
                break
    at = secure_i if secure_i is not None else n - 1
    translation = float(np.hypot(motion[at, 0], motion[at, 1]))
    rotation = float(abs(motion[at, 2]))
    final = float(np.hypot(motion[n - 1, 0], motion[n - 1, 1]))
    dropped = final > DROP_MM or (speed[n - hold:].mean() > 5.0 if n > hold else False)
    big = (np.hypot(motion[:, 0], motion[:, 1]) > GROSS_MM) | (np.abs(motion[:, 2]) > GROSS_DEG)
    gross_motion = np.flatnonzero(big)
    gross_motion = gross_motion[gross_motion >= lift]
    gross_motion_i = int(gross_motion[0]) if len(gross_motion) else None

    def s(i: int | None) -> float | None:
        return None if i is None else i * DT_S

    return RigResult(
        scene=str(Path(str(scene_path)).stem),
        reaction=react,
        lift_start_s=lift * DT_S,
        onset_s=s(onset),
        gross_slip_s=s(gross),
        gross_motion_s=s(gross_motion_i),
        alarm_s=alarm_s,
        stop_reached_s=s(stop_i),
        tighten_reached_s=s(tighten_i),
        secure_s=s(secure_i),
        translation_mm=translation,
        rotation_deg=rotation,
        dropped=bool(dropped),
        max_grip_n=float(physics.grip[:n].max()) if n else 0.0,
        frames=n,
        sensor_stalls=daemon_log.count("fail-safe: sensor_stall"),
        arm_stopped=bool(ur_state.stop_count),
        final_translation_mm=final,
        final_rotation_deg=float(abs(motion[n - 1, 2])),
        mean_grip_n=float(physics.grip[lift:n].mean()) if n > lift else 0.0,
    )


def plot_run(physics: RigPhysics, result: RigResult, path: str | Path) -> Path:
    """One run on one figure (PNG): the whole run on the left, the lift zoomed on the right (ms from the onset);
    per-pillar shear force, grip, slipping pillars with the daemon's P(slip) and its threshold, object motion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    n = physics.steps
    t = np.arange(n) * DT_S
    lift = physics.lift_index or 0
    mot = physics.motion[:n] - physics.motion[lift]
    zero = result.onset_s if result.onset_s is not None else result.lift_start_s
    events = [(result.lift_start_s, "k", ":", "arm starts lifting"),
              (result.onset_s, "g", "--", "incipient slip begins (truth: the method's label)"),
              (result.alarm_s, "r", "-", "daemon alarm"),
              (result.gross_slip_s, "m", "-.", "gross slip: every pillar slips (truth)"),
              (result.secure_s, "b", ":", "grasp secure")]
    fig, ax = plt.subplots(4, 2, figsize=(15, 11), gridspec_kw={"width_ratios": [3, 2]})
    end = max(v for v, *_ in events if v is not None)
    lo, hi = zero - 0.12, max(end + 0.08, zero + 0.15)
    for col, (scale, origin, xlabel) in enumerate(((1.0, 0.0, "time into the run (s)"),
                                                   (1000.0, zero, "time from the onset of incipient slip (ms)"))):
        x = (t - origin) * scale
        a = ax[:, col]
        for p in range(9):
            a[0].plot(x, physics.force[:n, p, 1], lw=0.8, label=f"pillar {p}")
        a[0].set_ylabel("shear force fy (N)")
        a[1].plot(x, physics.force[:n, :, 2].sum(1), label="total normal force fz")
        a[1].plot(x, physics.grip[:n], label="servo grip force")
        a[1].set_ylabel("force (N)")
        a[2].plot(x, physics.slip[:n].sum(1), drawstyle="steps-post", color="tab:orange",
                  label="pillars slipping (truth, any pillar)")
        a[2].set_ylabel("slipping pillars (of 9)")
        a[2].set_ylim(-0.3, 9.3)
        pa = a[2].twinx()
        if physics.daemon_p:
            tp, pp = (np.asarray(v) for v in zip(*physics.daemon_p))
            pa.plot((tp - origin) * scale, pp, "k.-", ms=3, lw=0.8, label="daemon's P(slip)")
        if physics.threshold is not None:
            pa.axhline(physics.threshold, color="k", ls=":", lw=0.8, label=f"alarm threshold {physics.threshold:g}")
        pa.set_ylim(-0.03, 1.03)
        pa.set_ylabel("P(slip)")
        a[3].plot(x, np.hypot(mot[:, 0], mot[:, 1]), color="tab:blue", label="translation (mm)")
        a[3].set_ylabel("object translation\nagainst the finger (mm)", color="tab:blue")
        ra = a[3].twinx()
        ra.plot(x, np.abs(mot[:, 2]), color="tab:red", label="rotation (deg)")
        ra.set_ylabel("object rotation (deg)", color="tab:red")
        a[3].set_xlabel(xlabel)
        for k in range(4):
            for val, color, style, _ in events:
                if val is not None:
                    a[k].axvline((val - origin) * scale, color=color, ls=style, lw=1.2)
            if col == 1:
                a[k].set_xlim((lo - zero) * 1000, (hi - zero) * 1000)
            else:
                a[k].set_xlim(0, t[-1] if n else 1)
        if col == 1:
            handles = a[2].get_legend_handles_labels()[0] + pa.get_legend_handles_labels()[0]
            a[2].legend(handles=handles, fontsize=7, loc="upper left")
            a[1].legend(fontsize=7, loc="upper left")
        else:
            a[0].legend(ncol=9, fontsize=6, loc="lower left", bbox_to_anchor=(0.0, 1.0), frameon=False,
                        handlelength=1.2, columnspacing=0.8)
    ax[0, 0].set_title("the whole run", loc="right", fontsize=9)
    ax[0, 1].set_title("the lift, zoomed", loc="right", fontsize=9)
    proxies = [Line2D([], [], color=c, ls=s_, lw=1.2) for _, c, s_, _ in events]
    fig.legend(proxies, [lab for *_, lab in events], loc="upper center", ncol=3, fontsize=8,
               bbox_to_anchor=(0.5, 0.955), frameon=False)
    fig.suptitle(f"slipd sim: {result.scene} (reaction {'on' if result.reaction else 'off'}): {result.verdict()}",
                 fontsize=11, y=0.985)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main_sim(args: Any) -> int:
    """``slipd sim``: the README's main command."""
    scene = Path(args.scene) if args.scene else DEFAULT_SCENE
    config = Path(args.config) if args.config else DEFAULT_CONFIG
    result, physics = run_rig(scene, config, duration_s=args.duration, react=not args.no_reaction,
                              detector=args.detector)
    print("\n".join(result.lines()))
    if args.plot:
        print(f"plot: {plot_run(physics, result, args.plot)}")
    Path("out").mkdir(exist_ok=True)
    Path("out/sim_result.json").write_text(json.dumps(asdict(result), indent=1))
    from slipd.sim.rig_mcap import write_run_mcap

    detector = {"model.detector": args.detector} if args.detector else None
    path, alarms = write_run_mcap(physics, result, config, "out/sim.mcap", detector)
    print(f"recording: {path} (open it in Foxglove with deploy/foxglove/slipd.json; slipd replay {path} "
          f"replays it: {len(alarms)} alarm(s))")
    return 0
