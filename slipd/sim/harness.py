"""The emulated devices of the rig, started together: PapillArray (pty), MX-28 (pty), UR controller (process).

Used by the closed-loop rig (``slipd.sim.rig``), the end-to-end tests and the latency benchmark, so
the daemon always meets the same emulators. Each speaks its real wire protocol: the daemon's own
drivers (pyserial + PTSCOM, dynamixel-sdk, ur_rtde) run unchanged against them.
"""

from __future__ import annotations

import contextlib
from typing import Any

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
