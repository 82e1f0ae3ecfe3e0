"""The emulated devices of the rig, started together: PapillArray (pty), MX-28 (pty), UR controller (process).

Used by the closed-loop rig (``slipd.sim.rig``), the end-to-end tests, the latency benchmark and the live soak,
so the daemon always meets the same emulators. Each speaks its real wire protocol: the daemon's own drivers
(pyserial + PTSCOM, dynamixel-sdk, ur_rtde) run unchanged against them.

``EmulatedDevices`` keeps the sensor and servo emulators in the caller's process (threads): cheap, and what
tests that reach into them need. ``EmulatorProcess`` runs the two in a process of their own, for measurements of
the daemon's process (memory, threads, descriptors, CPU, frames lost) that the emulators' threads, and their
share of one interpreter lock, must not blur.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import threading
from multiprocessing.connection import Connection
from typing import Any, Literal

from slipd.sim.devices.child_process import end_child
from slipd.sim.devices.mx28 import EmulatedMX28, JawParams
from slipd.sim.devices.papillarray import EmulatedPapillArray
from slipd.sim.devices.ur_controller import URControllerProcess


class EmulatedDevices:
    """Starts the three emulators; ``overrides()`` gives the config keys that point the daemon at them.

    The sensor emulator is created at once (its pty must exist before the daemon opens it) but only
    streams after ``start_sensor()``: pyserial flushes its input when it opens a port, so frames written
    before the daemon is ready would be lost.
    """

    def __init__(
        self,
        source: Any,
        *,
        host: str = "127.0.0.2",
        protocol: float = 2.0,
        dxl_id: int = 1,
        jaw: JawParams | None = None,
        ur: bool = True,
        ur_kwargs: dict | None = None,
    ) -> None:
        self.ur = URControllerProcess(host, **(ur_kwargs or {})) if ur else None
        self.servo = EmulatedMX28(protocol=protocol, dxl_id=dxl_id, jaw=jaw)
        self.sensor = EmulatedPapillArray(source)
        self.host = host

    def __enter__(self) -> EmulatedDevices:
        try:
            if self.ur is not None:
                self.ur.start()
        except Exception:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def overrides(self) -> dict[str, Any]:
        """Dotted config keys for ``slipd.config.override``."""
        out: dict[str, Any] = {"sensor.port": self.sensor.port, "gripper.port": self.servo.port}
        if self.sensor.sensors > 1:
            out["sensor.sensors"] = self.sensor.sensors
        if self.ur is not None:
            out["arm.host"] = self.host
        else:
            out["arm.enabled"] = False
        return out

    def start_sensor(self) -> None:
        """Begin streaming frames in real time."""
        self.sensor.start()

    def close(self) -> None:
        """Stop every emulator (safe to call twice)."""
        for dev in (self.sensor, self.servo):
            with contextlib.suppress(Exception):
                dev.close()
        if self.ur is not None:
            with contextlib.suppress(Exception):
                self.ur.stop()


EmulatorPart = Literal["sensor", "servo", "source"]


def _serve_emulators(conn: Connection, source: Any, sensor_kwargs: dict[str, Any],
                     servo_kwargs: dict[str, Any]) -> None:
    """Child process of ``EmulatorProcess``: build both emulators, send their ports, then serve calls until told
    to close (or the parent is gone)."""
    with EmulatedMX28(**servo_kwargs) as servo, EmulatedPapillArray(source, **sensor_kwargs) as sensor:
        parts: dict[str, Any] = {"sensor": sensor, "servo": servo, "source": source}
        conn.send((sensor.port, servo.port))
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            if msg is None:
                conn.send(("ok", None))
                return
            op, part, name, args = msg
            try:
                obj = parts[part]
                result = getattr(obj, name)(*args) if op == "call" else getattr(obj, name)
                conn.send(("ok", result))
            except Exception as exc:  # handed to the caller, which raises it
                try:
                    conn.send(("error", exc))
                except Exception:  # an exception that does not pickle
                    conn.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))


class EmulatorProcess:
    """The emulated PapillArray and MX-28 in a spawned process of their own, driven over a pipe.

    ``source`` (a Recording, or a picklable callable sample source) and the keyword dicts are handed to
    ``EmulatedPapillArray`` and ``EmulatedMX28`` in the child. ``call("sensor", "stall", 600.0)`` runs a method
    there and returns its result; ``get("sensor", "frames_written")`` reads an attribute; ``"source"`` names the
    source object as the child holds it (a callable source can keep what it saw). An exception in the child is
    raised here. Use as a context manager, or ``start()`` / ``close()``.
    """

    def __init__(self, source: Any, *, sensor: dict[str, Any] | None = None, servo: dict[str, Any] | None = None,
                 start_timeout: float = 60.0) -> None:
        self._args = (source, dict(sensor or {}), dict(servo or {}))
        self.start_timeout = start_timeout
        self.sensor_port = ""
        self.servo_port = ""
        self._conn: Connection | None = None
        self._proc: Any = None
        self._lock = threading.Lock()

    def start(self) -> EmulatorProcess:
        """Spawn the child and return once both ports exist; raises ``RuntimeError`` when it does not come up."""
        if self._proc is not None:
            raise RuntimeError("emulator process already started")
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: nothing of this process's state
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve_emulators, args=(child, *self._args), name="slipd-emulators",
                                 daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            ready = parent.poll(self.start_timeout)
            if ready:
                self.sensor_port, self.servo_port = parent.recv()
        except (EOFError, OSError):
            ready = False
        if not ready:
            code = self._proc.exitcode
            self.close()
            raise RuntimeError(f"emulator process did not start within {self.start_timeout} s (exit code {code})")
        return self

    @property
    def pid(self) -> int | None:
        """The child's process id (None before start and after close)."""
        return None if self._proc is None else int(self._proc.pid)

    @property
    def alive(self) -> bool:
        """True while the child process runs."""
        return self._proc is not None and self._proc.is_alive()

    def _request(self, msg: object) -> Any:
        if self._conn is None:
            raise RuntimeError("emulator process not started")
        with self._lock:  # one request and its answer at a time, whichever thread asks
            try:
                self._conn.send(msg)
                status, result = self._conn.recv()
            except (EOFError, OSError) as exc:
                raise RuntimeError(f"emulator process gone (exit code {self._proc.exitcode})") from exc
        if status == "error":
            raise result
        return result

    def call(self, part: EmulatorPart, method: str, *args: Any) -> Any:
        """Run ``part.method(*args)`` in the child and return its result."""
        return self._request(("call", part, method, args))

    def get(self, part: EmulatorPart, attribute: str) -> Any:
        """The value of ``part.attribute`` in the child."""
        return self._request(("get", part, attribute, ()))

    def overrides(self) -> dict[str, Any]:
        """Dotted config keys that point the daemon at the two ports (``slipd.config.override``)."""
        return {"sensor.port": self.sensor_port, "gripper.port": self.servo_port}

    def close(self) -> None:
        """Close both emulators (their ptys and links go with them) and wait for the child (safe to call twice)."""
        if self._proc is None:
            return
        end_child(self._proc, self._conn, lambda: self._request(None), (Exception,), join_s=10.0, terminate_s=5.0)
        self._proc, self._conn = None, None

    def __enter__(self) -> EmulatorProcess:
        return self if self._proc is not None else self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
