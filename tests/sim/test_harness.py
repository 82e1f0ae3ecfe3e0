"""slipd.sim.harness.EmulatorProcess: the emulated PapillArray and MX-28 in a process of their own, driven from the
test's process; a real pyserial port and the real decoder read what it streams."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from slipd.io.pts import FrameDecoder
from slipd.recording import Recording
from slipd.sim.harness import EmulatorProcess

N = 500


def _hold(n: int) -> Recording:
    force = np.zeros((n, 9, 3), np.float32)
    force[:, :, 2] = 1.5 + np.arange(n, dtype=np.float32)[:, None] * 1e-3  # each frame its own load
    return Recording(t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=np.zeros_like(force))


def test_streams_from_its_own_process_counts_there_and_raises_its_errors_here() -> None:
    rec = _hold(N)
    with EmulatorProcess(rec) as emu:
        assert emu.alive and emu.pid is not None and emu.pid != os.getpid()
        assert Path(emu.sensor_port).exists() and Path(emu.servo_port).exists()
        assert emu.overrides() == {"sensor.port": emu.sensor_port, "gripper.port": emu.servo_port}
        with serial.Serial(emu.sensor_port, timeout=0.2) as port:
            emu.call("sensor", "start")
            # The streaming thread is the child's: none of this process's threads is an emulator.
            assert not [t.name for t in threading.enumerate() if t.name.startswith("emulated")]
            dec, frames = FrameDecoder(), []
            deadline = time.monotonic() + 20.0
            while len(frames) < N and time.monotonic() < deadline:
                frames += dec.feed(port.read(4096))
        assert [f.counter for f in frames] == list(range(N))
        np.testing.assert_allclose([f.force[0, 2] for f in frames], rec.force[:, 0, 2], atol=1e-3)
        assert emu.get("sensor", "frames_written") == N and emu.get("sensor", "frames_discarded") == 0
        assert emu.call("servo", "writes") == []  # nothing talked to the servo
        with pytest.raises(RuntimeError, match="already started"):  # the child's exception, raised here
            emu.call("sensor", "start")
        with pytest.raises(AttributeError):
            emu.get("sensor", "no_such_attribute")
        assert emu.alive  # an error in a call leaves the emulators running
        port_path = emu.sensor_port
    assert not emu.alive and emu.pid is None
    assert not Path(port_path).exists()  # the child closed its emulators: pty link removed


def test_a_dead_emulator_process_is_one_clear_error() -> None:
    emu = EmulatorProcess(_hold(10)).start()
    try:
        pid = emu.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 10.0
        while emu.alive and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(RuntimeError, match="emulator process gone"):
            emu.get("sensor", "frames_written")
    finally:
        emu.close()
    assert emu.pid is None
