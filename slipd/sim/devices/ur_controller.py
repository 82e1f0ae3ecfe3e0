"""An emulated Universal Robots controller in its own process, spoken to by the real ur_rtde client library.

Why a process: ur_rtde's constructors hold the GIL while they wait for the controller to answer, so a
server in the same interpreter would never get to answer. The controller therefore runs in a child
started with the ``spawn`` method (no inherited threads or locks) and binds a loopback address such as
127.0.0.2 (only 127.0.0.0/8 is accepted). It serves:

* **RTDE** (port 30004, protocol 2): version negotiation, controller version (5.11.1, an e-Series, so
  ur_rtde asks for 500 Hz), output and input recipe set-up for any variable of the RTDE guide,
  start/pause, data packages at ``min(requested, rate_hz)`` and input packages written by clients.
* **Dashboard** (29999): the text commands ur_rtde's DashboardClient sends (``PolyscopeVersion``,
  ``robotmode``, ``safetymode``, ``safetystatus``, ``programState``, ``running``, ``play``, ``pause``,
  ``stop``, ``unlock protective stop``, ``close safety popup``, ``is in remote control``, ...).
* **Script ports** (30001/30002/30003): receive URScript programs. A program containing ur_rtde's control
  loop (``rtde_control`` with its ``signal_ready``) starts the *control script emulation*: every tick the
  emulator does what the uploaded script's main loop would do with the RTDE registers --
  ``input_int_register_0`` (+ the injected offset, 0 or 24) is the command, ``input_double_register_*``
  and ``input_int_register_1`` its arguments, ``output_int_register_0`` the handshake (1 ready, 2 done),
  ``output_int_register_2`` the async progress word. Implemented commands: movel (3) and movej_ik (2,
  moved linearly here), stopl (33), stopj (34), speed_stop (15), servo_stop (16), set_watchdog (35),
  protective_stop (31), is_steady (47), stop script (255); set_payload/set_tcp and other non-motion
  commands are acknowledged without effect and counted as ``unsupported``.

Motion model: the TCP pose (x, y, z, rx, ry, rz) moves along a straight line in pose space (the rotation
vector is interpolated linearly, adequate for the small moves of the rig) with a trapezoidal speed profile;
a stop decelerates at the commanded rate. No joint kinematics: ``actual_q`` is a fixed home posture.

Parent side: :class:`URControllerProcess` starts the child, reads its state from shared memory without
RTDE (:meth:`URControllerProcess.state`) and sends commands over a pipe: a scripted moveL "as if the user's
program moved the arm", protective stop injection and release, dropping every connection, making the
control script fail on its next command. The ``spawn`` start method re-imports the parent's main module
in the child, so a script that starts a controller needs the usual ``if __name__ == "__main__":`` guard.

Simplifications, on purpose: a scripted (user) move and ur_rtde's control script share one motion, so
slipd's ``stopL`` halts the user's lift (on a real controller uploading the control script would first
have ended the user's program; see ``slipd/arm.py``); ``speed_stop`` halts any motion; the primary and
secondary ports take programs but send no robot-state stream; input registers are never reported
``IN_USE``; speedL/speedJ/servo/force modes and joint moves (movej) are acknowledged, not executed.
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import multiprocessing as mp
import multiprocessing.connection as mpc
import re
import selectors
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from slipd.sim.devices import rtde_protocol as rp
from slipd.sim.devices.child_process import end_child
from slipd.sim.devices.ur_motion import LinearMotion

# RTDE enumerations (RTDE guide / ur_rtde).
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP = 1, 3
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
STATUS_POWER_ON, STATUS_PROGRAM_RUNNING = 1 << 0, 1 << 1
SAFETY_BIT_NORMAL, SAFETY_BIT_PROTECTIVE, SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 1 << 0, 1 << 2, 1 << 10

# ur_rtde control script command ids (ur_rtde 1.6.x).
CMD_NONE, CMD_MOVEJ_IK, CMD_MOVEL = 0, 2, 3
CMD_SPEED_STOP, CMD_SERVO_STOP, CMD_PROTECTIVE_STOP = 15, 16, 31
CMD_STOPL, CMD_STOPJ, CMD_SET_WATCHDOG, CMD_IS_STEADY, CMD_STOP_SCRIPT = 33, 34, 35, 47, 255
# Commands the script treats as real-time: processed and answered "ready" at once (never "done").
REALTIME_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
SCRIPT_READY, SCRIPT_DONE = 1, 2

HOME_Q = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
STOP_KINDS = {"stopl": 1, "stopj": 2, "speed_stop": 3, "servo_stop": 4, "dashboard_stop": 5, "dashboard_pause": 6,
              "script_end": 7, "watchdog": 8}


@dataclass(frozen=True)
class URPorts:
    """TCP ports the controller listens on (a real controller's numbers by default)."""

    rtde: int = 30004
    dashboard: int = 29999
    script: tuple[int, ...] = (30001, 30002, 30003)


@dataclass(frozen=True)
class URControllerConfig:
    """Settings of the emulated controller (all plain data: it crosses into the child process)."""

    host: str = "127.0.0.2"
    ports: URPorts = field(default_factory=URPorts)
    rate_hz: float = 500.0  # control tick: motion, script emulation and the highest data-package rate
    controller_version: tuple[int, int, int, int] = (5, 11, 1, 108318)
    initial_pose: tuple[float, ...] = (0.30, -0.20, 0.40, 0.0, 3.1416, 0.0)
    protective_stop_decel: float = 10.0  # m/s^2 for the stop a protective stop makes
    dashboard_stop_decel: float = 3.0  # m/s^2 when the program is stopped or paused from the dashboard
    serial_number: str = "20235500001"
    robot_model: str = "UR5"

    def __post_init__(self) -> None:
        if not ipaddress.ip_address(self.host).is_loopback:
            raise ValueError(f"URControllerConfig.host={self.host!r}: the emulator binds loopback addresses only")
        if not self.rate_hz > 0:
            raise ValueError(f"URControllerConfig.rate_hz={self.rate_hz}: must be > 0")


# Layout of the shared state array (doubles).
_POSE, _SPEED = slice(0, 6), slice(6, 12)
(_PROGRAM_RUNNING, _STOP_COUNT, _LAST_STOP_T, _PROTECTIVE, _CONTROL_SCRIPT, _MOVING, _CLIENTS, _TICKS,
 _SAFETY_MODE, _ROBOT_MODE, _RUNTIME_STATE, _LAST_STOP_KIND, _LAST_STOP_DECEL, _MOVES, _UNSUPPORTED,
 _SCRIPTS, _LAST_STOP_RX_T, _WATCHDOG_HZ, _WATCHDOG_INPUT_T) = range(12, 31)
_SHARED_SIZE = 31


@dataclass(frozen=True)
class URControllerState:
    """One consistent snapshot of the emulated controller, read from shared memory."""

    tcp_pose: tuple[float, ...]
    tcp_speed: tuple[float, ...]
    program_running: bool
    control_script_running: bool
    moving: bool
    protective_stop: bool
    safety_mode: int
    robot_mode: int
    runtime_state: int
    stop_count: int
    last_stop_t: float  # time.monotonic() (system-wide clock) when the last stop started decelerating
    last_stop_received_t: float  # time.monotonic() when the input package carrying it arrived
    last_stop_kind: str
    last_stop_decel: float
    moves_started: int
    unsupported_commands: int
    scripts_received: int
    clients: int
    ticks: int
    watchdog_hz: float  # the control script's RTDE watchdog (0: none set)
    watchdog_input_t: float  # time.monotonic() of the latest update of the watched register (a kick)

    @property
    def linear_speed(self) -> float:
        """Norm of the TCP's translational speed (m/s)."""
        return math.sqrt(sum(v * v for v in self.tcp_speed[:3]))


def _snapshot(arr: Any) -> URControllerState:
    with arr.get_lock():
        v = list(arr[:])
    kinds = {code: name for name, code in STOP_KINDS.items()}
    return URControllerState(
        tcp_pose=tuple(v[_POSE]), tcp_speed=tuple(v[_SPEED]), program_running=bool(v[_PROGRAM_RUNNING]),
        control_script_running=bool(v[_CONTROL_SCRIPT]), moving=bool(v[_MOVING]), protective_stop=bool(v[_PROTECTIVE]),
        safety_mode=int(v[_SAFETY_MODE]), robot_mode=int(v[_ROBOT_MODE]), runtime_state=int(v[_RUNTIME_STATE]),
        stop_count=int(v[_STOP_COUNT]), last_stop_t=v[_LAST_STOP_T], last_stop_received_t=v[_LAST_STOP_RX_T],
        last_stop_kind=kinds.get(int(v[_LAST_STOP_KIND]), ""), last_stop_decel=v[_LAST_STOP_DECEL],
        moves_started=int(v[_MOVES]), unsupported_commands=int(v[_UNSUPPORTED]), scripts_received=int(v[_SCRIPTS]),
        clients=int(v[_CLIENTS]), ticks=int(v[_TICKS]), watchdog_hz=v[_WATCHDOG_HZ],
        watchdog_input_t=v[_WATCHDOG_INPUT_T],
    )


# --------------------------------------------------------------------------------------------------------------
# The controller (runs in the child process)
# --------------------------------------------------------------------------------------------------------------
@dataclass
class _Client:
    sock: socket.socket
    kind: str  # "rtde", "dashboard", "script"
    out: bytearray = field(default_factory=bytearray)
    reader: rp.PacketReader = field(default_factory=rp.PacketReader)
    text: bytearray = field(default_factory=bytearray)
    outputs: rp.Recipe | None = None
    getters: list[Callable[[], object]] = field(default_factory=list)
    inputs: dict[int, rp.Recipe] = field(default_factory=dict)
    started: bool = False
    next_send: float = 0.0
    last_rx: float = 0.0


_DEF_RE = re.compile(rb"^\s*def\s+(\w+)\s*\(\s*\)\s*:", re.MULTILINE)
# ur_rtde 1.6 injects the register offset (0 or 24) right after the comment that ends this line.
_OFFSET_RE = re.compile(rb"global\s+reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")


class _Controller:
    """Single-threaded controller: one selector for every socket, a fixed-rate tick for everything else."""

    def __init__(self, cfg: URControllerConfig, shared: Any, conn: mpc.Connection) -> None:
        self.cfg, self.shared, self.conn = cfg, shared, conn
        self.sel = selectors.DefaultSelector()
        self.listeners: dict[socket.socket, str] = {}
        self.clients: dict[socket.socket, _Client] = {}
        self.dt = 1.0 / cfg.rate_hz
        self.t0 = self.now = time.monotonic()
        self.motion = LinearMotion(cfg.initial_pose)
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.in_bits = 0
        self.out_bits = 0
        # Program state.
        self.control_script = False
        self.user_program = False
        self.paused = False
        self.protective = False
        self.powered = True
        self.reg_offset = 0
        self.executing_cmd = False
        self.blocked_on_motion = False
        self.refuse_next = 0
        self.watchdog_hz = 0.0
        self.last_input_t = 0.0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.async_move = False
        self.cmd_rx_t = 0.0  # when the package that set the current command arrived
        # Counters mirrored into shared memory.
        self.stop_count = 0
        self.last_stop_t = 0.0
        self.last_stop_rx_t = 0.0
        self.last_stop_kind = 0
        self.last_stop_decel = 0.0
        self.moves = 0
        self.unsupported = 0
        self.scripts = 0
        self.ticks = 0
        self.reopen_at = 0.0
        self.running = True

    # -- sockets ---------------------------------------------------------------------------------------------
    def open_listeners(self) -> None:
        p = self.cfg.ports
        for port, kind in [(p.rtde, "rtde"), (p.dashboard, "dashboard"), *[(s, "script") for s in p.script]]:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.cfg.host, port))
            except OSError as e:
                s.close()
                self.close_listeners()
                raise OSError(f"emulated UR controller cannot bind {self.cfg.host}:{port} ({kind}): {e}") from e
            s.listen(8)
            s.setblocking(False)
            self.sel.register(s, selectors.EVENT_READ, "listen")
            self.listeners[s] = kind

    def close_listeners(self) -> None:
        for s in list(self.listeners):
            with contextlib.suppress(KeyError, ValueError):
                self.sel.unregister(s)
            s.close()
        self.listeners.clear()

    def _accept(self, lsock: socket.socket) -> None:
        try:
            sock, _ = lsock.accept()
        except OSError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, self.listeners[lsock], last_rx=time.monotonic())
        self.clients[sock] = client
        self.sel.register(sock, selectors.EVENT_READ, "client")
        if client.kind == "dashboard":
            self._send(client, b"Connected: Universal Robots Dashboard Server\n")

    def _drop(self, client: _Client) -> None:
        if client.sock not in self.clients:
            return
        if client.kind == "script" and client.text:
            self._program_received(client)
        del self.clients[client.sock]
        with contextlib.suppress(KeyError, ValueError):
            self.sel.unregister(client.sock)
        with contextlib.suppress(OSError):
            client.sock.shutdown(socket.SHUT_RDWR)
        client.sock.close()

    def drop_all(self, down_s: float) -> None:
        """Fault injection: close every connection; with ``down_s`` > 0 also refuse new ones for that long."""
        for c in list(self.clients.values()):
            self._drop(c)
        if down_s > 0:
            self.close_listeners()
            self.reopen_at = time.monotonic() + down_s

    def _send(self, client: _Client, data: bytes) -> None:
        client.out += data
        self._flush(client)

    def _flush(self, client: _Client) -> None:
        if not client.out:
            return
        try:
            n = client.sock.send(client.out)
            del client.out[:n]
        except BlockingIOError:
            pass
        except OSError:
            self._drop(client)
            return
        if len(client.out) > 4_000_000:  # a client that stopped reading: drop it as a controller would
            self._drop(client)

    def _readable(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        now = time.monotonic()
        client.last_rx = now
        if client.kind == "rtde":
            try:
                for ptype, payload in client.reader.feed(data):
                    self._rtde_packet(client, ptype, payload, now)
            except (ValueError, struct.error, KeyError) as e:
                self._send(client, rp.encode_text_message(f"protocol error: {e}", level=0))
                self._drop(client)
        elif client.kind == "dashboard":
            client.text += data
            while b"\n" in client.text:
                line, _, rest = client.text.partition(b"\n")
                client.text = bytearray(rest)
                reply = self._dashboard(line.decode(errors="replace").strip())
                if client.sock not in self.clients:
                    return
                self._send(client, reply.encode() + b"\n")
                if reply == "Disconnected":
                    self._drop(client)
                    return
        else:
            client.text += data

    # -- RTDE ------------------------------------------------------------------------------------------------
    def _rtde_packet(self, client: _Client, ptype: int, payload: bytes, now: float) -> None:
        if ptype == rp.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0]
            self._send(client, rp.encode(ptype, bytes([1 if version in (1, 2) else 0])))
        elif ptype == rp.GET_URCONTROL_VERSION:
            self._send(client, rp.encode(ptype, struct.pack(">IIII", *self.cfg.controller_version)))
        elif ptype == rp.CONTROL_PACKAGE_SETUP_OUTPUTS:
            frequency = struct.unpack(">d", payload[:8])[0]
            names = payload[8:].decode().split(",")
            recipe = rp.make_recipe(1, names, frequency)
            client.outputs = recipe
            client.getters = [self._getter(n) for n in recipe.names]
            self._send(client, rp.encode(ptype, bytes([recipe.recipe_id if recipe.valid else 0])
                                         + ",".join(recipe.types).encode()))
        elif ptype == rp.CONTROL_PACKAGE_SETUP_INPUTS:
            recipe = rp.make_recipe(len(client.inputs) + 1, payload.decode().split(","))
            if recipe.valid:
                client.inputs[recipe.recipe_id] = recipe
            self._send(client, rp.encode(ptype, bytes([recipe.recipe_id if recipe.valid else 0])
                                         + ",".join(recipe.types).encode()))
        elif ptype == rp.CONTROL_PACKAGE_START:
            ok = client.outputs is None or client.outputs.valid
            client.started = ok
            client.next_send = now
            self._send(client, rp.encode(ptype, bytes([1 if ok else 0])))
        elif ptype == rp.CONTROL_PACKAGE_PAUSE:
            client.started = False
            self._send(client, rp.encode(ptype, bytes([1])))
        elif ptype == rp.DATA_PACKAGE:
            recipe = client.inputs.get(payload[0])
            if recipe is None:
                raise ValueError(f"data package for unknown input recipe {payload[0]}")
            self._write_inputs(recipe.unpack(payload[1:]), now)
        elif ptype == rp.TEXT_MESSAGE:
            pass  # clients may log into the controller; nothing to do
        else:
            raise ValueError(f"unknown RTDE packet type {ptype!r}")

    def _write_inputs(self, values: dict[str, object], now: float) -> None:
        if f"input_int_register_{self.reg_offset}" in values:
            # rtde_set_watchdog watches one input variable, the command register: any package that writes
            # it (every ur_rtde command, and kickWatchdog) is an update; other inputs are not.
            self.last_input_t = now
        for name, value in values.items():
            m = re.match(r"input_(int|double|bit)_register_(\d+)$", name)
            if not m:
                continue  # digital outputs, speed slider...: accepted, not modelled
            kind, idx = m.group(1), int(m.group(2))
            if kind == "int":
                if idx == self.reg_offset and value != self.in_int[idx]:
                    self.cmd_rx_t = now
                self.in_int[idx] = int(value)  # type: ignore[call-overload]
            elif kind == "double":
                self.in_double[idx] = float(value)  # type: ignore[arg-type]
            elif value:
                self.in_bits |= 1 << idx
            else:
                self.in_bits &= ~(1 << idx)

    def _safety_bits(self) -> int:
        if self.protective:
            return SAFETY_BIT_PROTECTIVE | SAFETY_BIT_STOPPED_DUE_TO_SAFETY
        return SAFETY_BIT_NORMAL

    def _program_running(self) -> bool:
        return (self.control_script or self.user_program) and not self.paused and not self.protective

    def _runtime_state(self) -> int:
        if self._program_running():
            return RUNTIME_PLAYING
        if (self.control_script or self.user_program) and (self.paused or self.protective):
            return RUNTIME_PAUSED
        return RUNTIME_STOPPED

    def _getter(self, name: str) -> Callable[[], object]:
        """A callable producing the current value of output variable ``name`` (built once per recipe)."""
        m = re.match(r"(output|input)_(int|double|bit)_register_(\d+)$", name)
        if m:
            idx, kind, out = int(m.group(3)), m.group(2), m.group(1) == "output"
            if kind == "bit":
                return (lambda: bool(self.out_bits >> idx & 1)) if out else (lambda: bool(self.in_bits >> idx & 1))
            if kind == "int":
                return (lambda: self.out_int[idx]) if out else (lambda: self.in_int[idx])
            return (lambda: self.out_double[idx]) if out else (lambda: self.in_double[idx])
        simple: dict[str, Callable[[], object]] = {
            "timestamp": lambda: self.now - self.t0,
            "actual_TCP_pose": lambda: self.motion.pose,
            "target_TCP_pose": lambda: self.motion.pose,
            "actual_TCP_speed": lambda: self.motion.velocity,
            "target_TCP_speed": lambda: self.motion.velocity,
            "actual_q": lambda: HOME_Q,
            "target_q": lambda: HOME_Q,
            "robot_mode": lambda: ROBOT_MODE_RUNNING if self.powered else ROBOT_MODE_POWER_OFF,
            "joint_mode": lambda: (253,) * 6,  # JOINT_RUNNING_MODE
            "safety_mode": lambda: SAFETY_MODE_PROTECTIVE_STOP if self.protective else SAFETY_MODE_NORMAL,
            "safety_status": lambda: SAFETY_MODE_PROTECTIVE_STOP if self.protective else SAFETY_MODE_NORMAL,
            "robot_status_bits": lambda: (STATUS_POWER_ON if self.powered else 0)
            | (STATUS_PROGRAM_RUNNING if self._program_running() else 0),
            "safety_status_bits": self._safety_bits,
            "runtime_state": self._runtime_state,
            "speed_scaling": lambda: 1.0,
            "target_speed_fraction": lambda: 1.0,
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 48.0,
            "actual_robot_current": lambda: 0.6,
            "actual_joint_voltage": lambda: (48.0,) * 6,
            "joint_temperatures": lambda: (31.0,) * 6,
            "actual_execution_time": lambda: 0.3,
            "output_bit_registers0_to_31": lambda: self.out_bits & 0xFFFFFFFF,
            "output_bit_registers32_to_63": lambda: (self.out_bits >> 32) & 0xFFFFFFFF,
            "actual_tool_accelerometer": lambda: (0.0, 0.0, -9.81),
        }
        if name in simple:
            return simple[name]
        # Everything else (currents, analog I/O, payload, ...) is not modelled and reads as zero.
        t = rp.variable_type(name)
        if t.startswith("VECTOR"):
            zero_vec = (0.0,) * (3 if t == "VECTOR3D" else 6) if t.endswith("D") else (0,) * 6
            return lambda: zero_vec
        zero: object = 0.0 if t == "DOUBLE" else False if t == "BOOL" else 0
        return lambda: zero

    def _send_data(self, now: float) -> None:
        self.now = now
        for client in list(self.clients.values()):
            if client.kind != "rtde" or not client.started or client.outputs is None:
                continue
            if now + 1e-4 < client.next_send:
                continue
            rate = min(client.outputs.frequency or self.cfg.rate_hz, self.cfg.rate_hz)
            client.next_send = max(client.next_send + 1.0 / rate, now - 1.0 / rate)
            self._send(client, client.outputs.pack([g() for g in client.getters]))

    # -- dashboard -------------------------------------------------------------------------------------------
    def _program_name(self) -> str:
        return "rtde_control" if self.control_script else "slipd_user_program.urp" if self.user_program else "<unnamed>"

    def _dashboard(self, line: str) -> str:
        cmd = line.lower()
        state_name = {RUNTIME_PLAYING: "PLAYING", RUNTIME_PAUSED: "PAUSED"}.get(self._runtime_state(), "STOPPED")
        if cmd == "polyscopeversion":
            v = self.cfg.controller_version
            return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Nov 22 2026)"
        if cmd == "robotmode":
            return "Robotmode: " + ("RUNNING" if self.powered else "POWER_OFF")
        if cmd in ("safetymode", "safetystatus"):
            label = "Safetymode" if cmd == "safetymode" else "Safetystatus"
            return f"{label}: " + ("PROTECTIVE_STOP" if self.protective else "NORMAL")
        if cmd == "programstate":
            return f"{state_name} {self._program_name()}"
        if cmd == "running":
            return "Program running: " + ("true" if self._program_running() else "false")
        if cmd == "is in remote control":
            return "true"
        if cmd == "play":
            if self.protective or not (self.control_script or self.user_program):
                return "Failed to execute: play"
            self.paused = False
            return "Starting program"
        if cmd == "pause":
            if not self._program_running():
                return "Failed to execute: pause"
            self.paused = True
            self._start_stop("dashboard_pause", self.cfg.dashboard_stop_decel, time.monotonic())
            return "Pausing program"
        if cmd == "stop":
            self._end_programs()  # a real controller answers "Stopped" whether or not a program ran
            self._start_stop("dashboard_stop", self.cfg.dashboard_stop_decel, time.monotonic())
            return "Stopped"
        if cmd == "unlock protective stop":
            self.protective = False
            return "Protective stop releasing"
        if cmd == "close safety popup":
            return "closing safety popup"
        if cmd == "close popup":
            return "closing popup"
        if cmd.startswith("popup"):
            return "showing popup"
        if cmd == "power on":
            self.powered = True
            return "Powering on"
        if cmd == "power off":
            self.powered = False
            self._end_programs()
            self.motion.stop(self.cfg.protective_stop_decel)
            return "Powering off"
        if cmd == "brake release":
            return "Brake releasing"
        if cmd == "restart safety":
            self.protective = False
            return "Restarting safety"
        if cmd == "get serial number":
            return self.cfg.serial_number
        if cmd == "get robot model":
            return self.cfg.robot_model
        if cmd == "get loaded program":
            return f"Loaded program: {self._program_name()}"
        if cmd.startswith("load "):
            return f"Loading program: {line[5:].strip()}"
        if cmd == "quit":
            return "Disconnected"
        return f"could not understand: '{line}'"

    # -- script ----------------------------------------------------------------------------------------------
    def _program_received(self, client: _Client) -> None:
        text = bytes(client.text)
        client.text.clear()
        self.scripts += 1
        m = _DEF_RE.search(text)
        if m is None:
            return  # a single script line (e.g. ``stopl(1)`` outside a program): not modelled
        # A new program replaces whatever ran before, as on a real controller.
        self._end_programs()
        if b"signal_ready" in text and b"read_input_integer_register" in text:
            off = _OFFSET_RE.search(text)
            self.reg_offset = int(off.group(1)) if off else 0
            self.control_script, self.paused = True, False
            self.executing_cmd = self.blocked_on_motion = False
            self._async_progress(-1)
        else:
            self.user_program, self.paused = True, False

    def _end_programs(self) -> None:
        self.control_script = self.user_program = self.paused = False
        self.executing_cmd = self.blocked_on_motion = False
        self.watchdog_hz = 0.0

    def _async_progress(self, value: int) -> None:
        # The progress word of ur_rtde's script: bits 24-30 operation id, 16-23 write count, 15 running.
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[self.reg_offset + 2] = reg

    def _start_stop(self, kind: str, decel: float, now: float) -> None:
        self.stop_count += 1
        self.last_stop_t = now
        self.last_stop_rx_t = self.cmd_rx_t if kind in ("stopl", "stopj", "speed_stop", "servo_stop") else now
        self.last_stop_kind = STOP_KINDS[kind]
        self.last_stop_decel = decel
        self.motion.stop(decel if decel > 0 else 10.0)

    def _script_tick(self, now: float) -> None:
        """One cycle of ur_rtde's control-script main loop, acting on the RTDE registers."""
        off = self.reg_offset
        if self.blocked_on_motion:  # a synchronous move/stop blocks the script until the arm is still
            if not self.motion.active:
                self.blocked_on_motion = False
                if self.async_move:
                    self._async_progress(-1)
                    self.async_move = False
                self.out_int[off] = SCRIPT_DONE
            return
        if self.async_move and not self.motion.active:
            self._async_progress(-1)
            self.async_move = False
        cmd = self.in_int[off]
        if cmd in REALTIME_CMDS:
            self.unsupported += 1  # servo/speed/force modes are not modelled
            self.out_int[off] = SCRIPT_READY
        elif cmd == CMD_NONE:
            self.executing_cmd = False
            self.out_int[off] = SCRIPT_READY
        elif not self.executing_cmd:
            self.executing_cmd = True
            self._process_cmd(cmd, now)

    def _process_cmd(self, cmd: int, now: float) -> None:
        off = self.reg_offset
        d = self.in_double[off : off + 24]
        arg_int = self.in_int[off + 1]
        if cmd == CMD_STOP_SCRIPT:
            self._end_programs()
            if self.motion.active:
                self._start_stop("script_end", self.cfg.dashboard_stop_decel, now)
            return
        if self.refuse_next > 0:
            # Fault injection: the script dies on this command as a URScript runtime error would stop it.
            self.refuse_next -= 1
            self._end_programs()
            self.motion.stop(self.cfg.protective_stop_decel)
            return
        done = True
        if cmd in (CMD_MOVEL, CMD_MOVEJ_IK):
            try:
                self.motion.move_to(d[0:6], speed=d[6], accel=d[7])
            except ValueError:
                self._end_programs()  # the real script stops with a runtime error on an invalid pose
                return
            self.moves += 1
            if arg_int == 1:  # asynchronous: acknowledged now, progress in output_int_register_2
                self._async_progress(0)
                self.async_move = True
            else:
                done = False
        elif cmd in (CMD_STOPL, CMD_STOPJ, CMD_SPEED_STOP, CMD_SERVO_STOP):
            kind = {CMD_STOPL: "stopl", CMD_STOPJ: "stopj", CMD_SPEED_STOP: "speed_stop",
                    CMD_SERVO_STOP: "servo_stop"}[cmd]
            decel = d[0] if d[0] > 0 else 10.0
            self._start_stop(kind, decel, now)
            asynchronous = cmd in (CMD_STOPL, CMD_STOPJ) and arg_int == 1
            if asynchronous:
                self._async_progress(0)
                self.async_move = True
            else:
                done = not self.motion.active
        elif cmd == CMD_SET_WATCHDOG:
            self.watchdog_hz = max(0.0, d[0])
            self.last_input_t = now  # the period runs from the set-up
        elif cmd == CMD_PROTECTIVE_STOP:
            self._protective_stop()
        elif cmd == CMD_IS_STEADY:
            self.out_int[off + 1] = 0 if self.motion.active else 1
        else:
            self.unsupported += 1
        if done:
            self.out_int[off] = SCRIPT_DONE
        else:
            self.blocked_on_motion = True

    def _protective_stop(self) -> None:
        # The running program pauses; after the unlock it stays paused until "play", as on a real controller.
        self.protective = True
        if self.control_script or self.user_program:
            self.paused = True
        self.motion.stop(self.cfg.protective_stop_decel)

    # -- parent commands -------------------------------------------------------------------------------------
    def _parent_command(self) -> None:
        try:
            name, args = self.conn.recv()
        except (EOFError, OSError):
            self.running = False
            return
        try:
            result = self._apply(name, args)
            self.conn.send(("ok", result))
        except Exception as e:  # reported to the parent, which raises it
            self.conn.send(("error", f"{type(e).__name__}: {e}"))

    def _apply(self, name: str, args: dict[str, Any]) -> object:
        if name == "movel":
            self.motion.move_to(args["target"], args["speed"], args["accel"])
            self.moves += 1
            if not self.control_script:
                self.user_program, self.paused = True, False
            return None
        if name == "protective_stop":
            self._protective_stop()
        elif name == "clear_protective_stop":
            self.protective = False
            if args.get("resume", False):
                self.paused = False
        elif name == "drop_connections":
            self.drop_all(float(args.get("down_s", 0.0)))
        elif name == "refuse":
            self.refuse_next += int(args.get("count", 1))
        elif name == "set_pose":
            if self.motion.active:
                raise RuntimeError("set_pose while the arm moves")
            self.motion = LinearMotion(args["pose"])
        elif name == "shutdown":
            self.running = False
        else:
            raise ValueError(f"unknown controller command {name!r}")
        return None

    # -- main loop -------------------------------------------------------------------------------------------
    def _tick(self, now: float) -> None:
        self.ticks += 1
        if self.reopen_at and now >= self.reopen_at:
            self.reopen_at = 0.0
            self.open_listeners()
        self.motion.step(self.dt)
        if self.user_program and not self.control_script and not self.motion.active and not self.paused:
            self.user_program = False  # the user's program ends with its move
        if self.control_script and self._program_running():
            self._script_tick(now)
            if self.watchdog_hz > 0 and now - self.last_input_t > 1.0 / self.watchdog_hz:
                # rtde_set_watchdog(..., "stop"): the program stops, and with it the arm, as on a real
                # controller when the RTDE client died, froze or stopped kicking.
                self._end_programs()
                self._start_stop("watchdog", self.cfg.dashboard_stop_decel, now)
        for client in list(self.clients.values()):
            if client.kind == "script" and client.text and now - client.last_rx > 0.05:
                self._program_received(client)  # a program is complete once its sender pauses
            self._flush(client)
        self._send_data(now)
        self._publish()

    def _publish(self) -> None:
        a = self.shared
        with a.get_lock():
            a[_POSE] = self.motion.pose
            a[_SPEED] = self.motion.velocity
            a[_PROGRAM_RUNNING] = float(self._program_running())
            a[_STOP_COUNT] = self.stop_count
            a[_LAST_STOP_T] = self.last_stop_t
            a[_LAST_STOP_RX_T] = self.last_stop_rx_t
            a[_PROTECTIVE] = float(self.protective)
            a[_CONTROL_SCRIPT] = float(self.control_script)
            a[_MOVING] = float(self.motion.active)
            a[_CLIENTS] = len(self.clients)
            a[_TICKS] = self.ticks
            a[_SAFETY_MODE] = SAFETY_MODE_PROTECTIVE_STOP if self.protective else SAFETY_MODE_NORMAL
            a[_ROBOT_MODE] = ROBOT_MODE_RUNNING if self.powered else ROBOT_MODE_POWER_OFF
            a[_RUNTIME_STATE] = self._runtime_state()
            a[_LAST_STOP_KIND] = self.last_stop_kind
            a[_LAST_STOP_DECEL] = self.last_stop_decel
            a[_MOVES] = self.moves
            a[_UNSUPPORTED] = self.unsupported
            a[_SCRIPTS] = self.scripts
            a[_WATCHDOG_HZ] = self.watchdog_hz
            a[_WATCHDOG_INPUT_T] = self.last_input_t

    def run(self) -> None:
        self.sel.register(self.conn.fileno(), selectors.EVENT_READ, "parent")
        next_tick = time.monotonic()
        while self.running:
            timeout = max(0.0, next_tick - time.monotonic())
            for key, _ in self.sel.select(timeout):
                if key.data == "listen":
                    self._accept(key.fileobj)  # type: ignore[arg-type]
                elif key.data == "parent":
                    self._parent_command()
                else:
                    client = self.clients.get(key.fileobj)  # type: ignore[call-overload]
                    if client is not None:
                        self._readable(client)
            now = time.monotonic()
            if now >= next_tick:
                self._tick(now)
                next_tick += self.dt
                if now - next_tick > 0.25:  # far behind (machine stalled): resynchronise, do not burst
                    next_tick = now + self.dt
        for c in list(self.clients.values()):
            self._drop(c)
        self.close_listeners()


def _child_main(cfg: URControllerConfig, shared: Any, conn: mpc.Connection) -> None:
    controller = _Controller(cfg, shared, conn)
    try:
        controller.open_listeners()
    except OSError as e:
        conn.send(("error", str(e)))
        return
    controller._publish()
    conn.send(("ready", None))
    controller.run()


# --------------------------------------------------------------------------------------------------------------
# Parent side
# --------------------------------------------------------------------------------------------------------------
class URControllerProcess:
    """Runs an emulated UR controller in a child process and controls it from the parent.

    Use as a context manager or call :meth:`start` / :meth:`stop`. State is read from shared memory
    (:meth:`state`), never through RTDE, so tests and the rig can observe the arm independently of
    the client under test.
    """

    def __init__(self, host: str = "127.0.0.2", *, config: URControllerConfig | None = None,
                 start_timeout: float = 10.0, **overrides: Any) -> None:
        if config is None:
            config = URControllerConfig(host=host, **overrides)
        elif overrides or (host != config.host and host != "127.0.0.2"):
            raise ValueError("pass either config= or host/keyword settings, not both")
        self.config = config
        self.host = config.host
        self.start_timeout = start_timeout
        self._ctx = mp.get_context("spawn")
        self._shared = self._ctx.Array("d", _SHARED_SIZE, lock=True)
        self._conn: mpc.Connection | None = None
        self._proc: Any = None

    def start(self) -> URControllerProcess:
        """Start the child and return once every port listens; raises ``RuntimeError`` on failure."""
        if self._proc is not None:
            raise RuntimeError("emulated UR controller already started")
        parent, child = self._ctx.Pipe(duplex=True)
        self._proc = self._ctx.Process(target=_child_main, args=(self.config, self._shared, child),
                                       name=f"ur-controller-{self.host}", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        if not parent.poll(self.start_timeout):
            self.stop()
            raise RuntimeError(f"emulated UR controller on {self.host} did not start within {self.start_timeout} s")
        status, detail = parent.recv()
        if status != "ready":
            self.stop()
            raise RuntimeError(f"emulated UR controller on {self.host} failed to start: {detail}")
        return self

    def stop(self) -> None:
        """Shut the child down (closing every connection) and wait for it."""
        if self._proc is None:
            return
        end_child(self._proc, self._conn, lambda: self._call("shutdown", timeout=2.0),
                  (OSError, EOFError, RuntimeError), join_s=3.0, terminate_s=2.0)
        self._proc, self._conn = None, None

    def __enter__(self) -> URControllerProcess:
        return self if self._proc is not None else self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        """True while the child process runs."""
        return self._proc is not None and self._proc.is_alive()

    def _call(self, name: str, timeout: float = 5.0, **args: Any) -> object:
        if self._conn is None:
            raise RuntimeError("emulated UR controller is not running")
        self._conn.send((name, args))
        if not self._conn.poll(timeout):
            raise RuntimeError(f"emulated UR controller did not answer {name!r} within {timeout} s")
        status, detail = self._conn.recv()
        if status != "ok":
            raise RuntimeError(f"emulated UR controller refused {name!r}: {detail}")
        return detail

    def state(self) -> URControllerState:
        """The controller's current state (shared memory; no RTDE involved)."""
        return _snapshot(self._shared)

    def wait_for(self, predicate: Callable[[URControllerState], bool], timeout: float = 5.0,
                 what: str = "condition") -> URControllerState:
        """Poll :meth:`state` until ``predicate`` holds; raises ``TimeoutError`` naming ``what``."""
        deadline = time.monotonic() + timeout
        while True:
            s = self.state()
            if predicate(s):
                return s
            if time.monotonic() > deadline:
                raise TimeoutError(f"emulated UR controller: {what} not reached within {timeout} s (state {s})")
            time.sleep(0.005)

    def move_l(self, target: Sequence[float], speed: float = 0.25, accel: float = 1.2) -> None:
        """Start a linear move as the user's own program would (the rig's lift); returns at once."""
        self._call("movel", target=[float(x) for x in target], speed=float(speed), accel=float(accel))

    def inject_protective_stop(self) -> None:
        """Put the robot into a protective stop: motion halts, the program pauses, commands fail."""
        self._call("protective_stop")

    def clear_protective_stop(self, resume: bool = False) -> None:
        """Release the protective stop (as the pendant's unlock); ``resume`` also continues the program."""
        self._call("clear_protective_stop", resume=resume)

    def drop_connections(self, down_s: float = 0.0) -> None:
        """Close every client connection; with ``down_s`` > 0 refuse new connections for that long."""
        self._call("drop_connections", down_s=down_s)

    def refuse_next_command(self, count: int = 1) -> None:
        """Make the control script fail (stop, as on a URScript runtime error) on its next ``count`` commands."""
        self._call("refuse", count=count)

    def set_pose(self, pose: Sequence[float]) -> None:
        """Teleport the idle TCP to ``pose`` (test set-up)."""
        self._call("set_pose", pose=[float(x) for x in pose])
