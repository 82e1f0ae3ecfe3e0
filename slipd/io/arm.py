"""The robot arm: a small :class:`Arm` interface and :class:`URArm` for Universal Robots through ur_rtde.

slipd's only business with the arm is to *halt it fast* when the grasp starts to slip, and to know
whether it can: connected, program running, not protective-stopped. Every call here blocks (socket
round-trips inside ur_rtde), so the control loop runs them on the arm's own
:class:`slipd.daemon.worker.DeviceWorker` thread; an ``Arm`` is not thread-safe and expects that one thread.

How to stop a motion the *user's* program commands -- the trade-off
-------------------------------------------------------------------
``rtde_control.RTDEControlInterface`` works by uploading ur_rtde's own URScript control program to the
controller. A UR controller runs one program at a time, so connecting it **replaces** whatever program
the user was running. Two deployments follow:

* ``stop_method="stopl"`` (default, needs ``use_control=True``): the arm's motion is commanded through
  ur_rtde (e.g. ``moveL(..., asynchronous=True)`` from the application, or the rig). ``stopL(a)`` is the
  call that halts such a move: the control script first kills its asynchronous move thread and then
  decelerates linearly in tool space at ``a`` m/s^2. (``speedStop`` only ends speed mode -- it does not
  kill an asynchronous ``moveL`` thread on a real controller -- so it is offered as ``"speed_stop"`` for
  speedL/speedJ applications only.) Fastest path: one RTDE input package and the 2 ms script cycle.
* ``stop_method="dashboard_pause"`` / ``"dashboard_stop"`` (works with ``use_control=False``): the user's
  own PolyScope program keeps running untouched and slipd sends ``pause`` (program can be resumed) or
  ``stop`` to the dashboard server (port 29999). No script is replaced and no protective stop is
  provoked, but the dashboard is a slower text round-trip and the deceleration is the controller's
  program-stop ramp, not ours.

Neither path triggers a protective stop (``triggerProtectiveStop`` would, and needs a manual unlock).
``fallback_to_dashboard`` makes a failed RTDE stop fall back to the dashboard ``stop``.

When slipd dies
---------------
With the control interface, :meth:`URArm.kick_watchdog` arms ur_rtde's controller-side watchdog
(``setWatchdog(1 / watchdog_s)``: the control script calls ``rtde_set_watchdog("input_int_register_0",
f, "stop")``) on its first call and kicks it (``kickWatchdog``) on every call. The daemon kicks only while
its decisions are live, so when slipd is killed (SIGKILL, OOM, systemd's watchdog abort), frozen
(SIGSTOP, a wedged loop) or blind, the controller stops the program and the arm within ``watchdog_s``.
The watchdog is armed at the first kick, not at connect: the sensor's tare and the first decision take
longer than the period. The dashboard modes upload nothing, so there is no watchdog: a dead slipd leaves
the user's program running, unwatched.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from slipd.config import ArmConfig
from slipd.metrics import Metrics

STOP_METHODS = ("stopl", "speed_stop", "dashboard_pause", "dashboard_stop")
DASHBOARD_METHODS = ("dashboard_pause", "dashboard_stop")
WATCHDOG_REARM_KICKS = 20
"""Kicks between two ``setWatchdog`` on a script already watched (2.5 s at the daemon's 0.5 s watchdog, four kicks a
period): ur_rtde reconnects by itself on a dropped link and uploads a script without a watchdog, unseen here."""
"""Stop methods that pause or stop the user's own program through the dashboard server (no control script)."""
_NAN6 = (math.nan,) * 6

# RTDE robot_status_bits / safety_status_bits (UR RTDE guide).
_STATUS_PROGRAM_RUNNING = 1 << 1


class ArmError(RuntimeError):
    """A failure talking to the arm (connection, refused command); the message names the host and call."""


@dataclass(frozen=True)
class ArmState:
    """The arm as last read. With ``connected`` False the other values are not trusted (NaN / False)."""

    connected: bool
    pose: tuple[float, ...]  # TCP x, y, z (m), rx, ry, rz (rad, rotation vector), base frame
    speed: tuple[float, ...]  # TCP velocity (m/s, rad/s)
    protective_stop: bool
    emergency_stop: bool
    program_running: bool
    safety_mode: int
    robot_mode: int
    runtime_state: int
    t_read: float  # time.monotonic() when read

    @property
    def linear_speed(self) -> float:
        """Norm of the translational TCP speed (m/s)."""
        return math.sqrt(sum(v * v for v in self.speed[:3]))


@dataclass(frozen=True)
class StopResult:
    """What one :meth:`Arm.stop` did. ``ok`` means a stop command was accepted by the controller."""

    ok: bool
    method: str
    reason: str
    t_issued: float  # time.monotonic() just before the vendor call
    t_returned: float  # time.monotonic() when it returned
    protective_stop: bool = False  # the controller had already halted the arm with a protective stop
    error: str = ""  # why the configured method failed (also set when a fallback then succeeded)

    @property
    def duration(self) -> float:
        """Seconds the stop call blocked."""
        return self.t_returned - self.t_issued


class Arm(ABC):
    """A robot arm slipd can halt."""

    last_stop: StopResult | None = None

    @abstractmethod
    def connect(self) -> None:
        """Open the connections; raises :class:`ArmError` when the arm cannot be reached."""

    @abstractmethod
    def is_connected(self) -> bool:
        """True while the state stream (and the control channel, where used) is up."""

    @abstractmethod
    def read_state(self) -> ArmState:
        """The arm's current state; ``connected`` False instead of raising when the link is down."""

    @abstractmethod
    def stop(self, reason: str) -> StopResult:
        """Decelerate and halt any motion now; never raises for a refused stop (see ``StopResult.ok``)."""

    def kick_watchdog(self) -> None:  # noqa: B027 -- optional: an arm without a watchdog has nothing to kick
        """Tell the controller-side watchdog that slipd is alive (no-op for arms without one)."""

    def control_script_running(self) -> bool:
        """False when slipd's control program on the controller has ended (watchdog, pendant)."""
        return True

    @abstractmethod
    def reconnect(self) -> bool:
        """Re-open lost connections; True on success."""

    @abstractmethod
    def close(self) -> None:
        """Close every connection (idempotent)."""


@dataclass(frozen=True)
class URSettings:
    """How to reach and stop a UR arm.

    ``frequency`` -1 lets ur_rtde pick (500 Hz on e-Series, 125 Hz on CB3). ``stop_deceleration`` is the
    tool deceleration of ``stopl`` / ``speed_stop`` in m/s^2 (UR's own default is 10). A synchronous
    ``stopl`` blocks the arm's worker thread for the whole deceleration (v/a: 25 ms for 0.25 m/s at 10
    m/s^2); ``stop_asynchronous`` returns once the controller has taken the stop.
    """

    host: str
    frequency: float = -1.0
    stop_method: str = "stopl"
    stop_deceleration: float = 10.0
    stop_asynchronous: bool = False  # stopl only: return once the controller took the stop, not at standstill
    use_control: bool = True
    fallback_to_dashboard: bool = True
    dashboard_port: int = 29999
    script_start_timeout: float = 2.0  # seconds to wait for the control script after a re-upload
    watchdog_s: float = 0.5  # controller-side watchdog period (control interface only)

    @classmethod
    def from_config(cls, cfg: ArmConfig) -> URSettings:
        """The settings of the config's ``arm`` section (the other fields keep their defaults)."""
        if cfg.host is None:
            raise ValueError("arm.host: required when the arm is enabled")
        # The dashboard modes leave the user's program running: no control interface, so nothing is uploaded.
        return cls(host=cfg.host, frequency=cfg.rtde_frequency, stop_method=cfg.stop_method,
                   stop_deceleration=cfg.stop_deceleration, watchdog_s=cfg.watchdog_s,
                   use_control=cfg.stop_method not in DASHBOARD_METHODS)

    def __post_init__(self) -> None:
        if not self.host:
            raise ValueError("URSettings.host: empty")
        if self.stop_method not in STOP_METHODS:
            raise ValueError(f"URSettings.stop_method={self.stop_method!r}: expected one of {STOP_METHODS}")
        if self.stop_method in ("stopl", "speed_stop") and not self.use_control:
            raise ValueError(f"URSettings.stop_method={self.stop_method!r} needs use_control=True "
                             "(use 'dashboard_pause' or 'dashboard_stop' to leave the user's program in place)")
        if not (0.0 < self.stop_deceleration <= 40.0):
            raise ValueError(f"URSettings.stop_deceleration={self.stop_deceleration}: expected 0 < a <= 40 m/s^2")
        if not self.watchdog_s > 0:
            raise ValueError(f"URSettings.watchdog_s={self.watchdog_s}: expected > 0 s")
        if self.frequency != -1.0 and not (0 < self.frequency <= 500):
            raise ValueError(f"URSettings.frequency={self.frequency}: expected -1 (automatic) or 0 < f <= 500 Hz")


def _default_factory(module: str, cls: str) -> Callable[..., Any]:
    def make(*args: Any) -> Any:
        return getattr(importlib.import_module(module), cls)(*args)  # imported late: `slipd check-config` stays light
    return make


class URArm(Arm):
    """A Universal Robots arm through ur_rtde: state from RTDEReceiveInterface, stops through
    RTDEControlInterface (``stopL``/``speedStop``) or the dashboard server (``pause``/``stop``).

    The ``*_factory`` arguments build the ur_rtde objects (``factory(host, ...)``); they exist so unit
    tests can substitute our own fakes at this boundary. ``metrics`` counts failures in
    ``slipd_device_errors{device="arm", kind=...}`` with kinds ``connect``, ``disconnected``,
    ``reconnect``, ``stop_failed``, ``protective_stop`` and ``read``.
    """

    def __init__(self, settings: URSettings | ArmConfig, metrics: Metrics | None = None, *,
                 receive_factory: Callable[..., Any] | None = None,
                 control_factory: Callable[..., Any] | None = None,
                 dashboard_factory: Callable[..., Any] | None = None) -> None:
        self.settings = settings if isinstance(settings, URSettings) else URSettings.from_config(settings)
        self.metrics = metrics
        self._watchdog_armed = False  # setWatchdog sent to the control script now running
        self._kicks = 0  # kicks since the last setWatchdog
        self._receive_factory = receive_factory or _default_factory("rtde_receive", "RTDEReceiveInterface")
        self._control_factory = control_factory or _default_factory("rtde_control", "RTDEControlInterface")
        self._dashboard_factory = dashboard_factory or _default_factory("dashboard_client", "DashboardClient")
        self._receive: Any = None
        self._control: Any = None
        self._dashboard: Any = None
        self._was_protective = False
        self._was_down = False
        self.last_stop = None

    # -- helpers ---------------------------------------------------------------------------------------------
    def _count(self, kind: str) -> None:
        if self.metrics is not None:
            self.metrics.device_errors.labels(device="arm", kind=kind).inc()

    @property
    def _uses_dashboard(self) -> bool:
        return self.settings.stop_method.startswith("dashboard") or self.settings.fallback_to_dashboard

    def _dashboard_connected(self) -> Any:
        if self._dashboard is None:
            self._dashboard = self._dashboard_factory(self.settings.host, self.settings.dashboard_port)
        if not self._dashboard.isConnected():
            self._dashboard.connect()
        return self._dashboard

    # -- Arm -------------------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Connect the receive interface, then the control interface (uploads ur_rtde's control script,
        replacing the running program) when ``use_control``, then the dashboard where a stop path needs it."""
        s = self.settings
        try:
            self._receive = self._receive_factory(s.host, s.frequency)
            if s.use_control:
                self._control = self._control_factory(s.host, s.frequency)
            if self._uses_dashboard:
                self._dashboard_connected()
        except RuntimeError as e:
            self._count("connect")
            self.close()
            raise ArmError(f"UR arm at {s.host}: cannot connect: {e}") from e
        if not self.is_connected():
            self._count("connect")
            self.close()
            raise ArmError(f"UR arm at {s.host}: connected but the RTDE link reports it is down")

    def is_connected(self) -> bool:
        """True when the RTDE state stream, and the control interface where used, are connected."""
        if self._receive is None or not self._receive.isConnected():
            return False
        return self._control is None or bool(self._control.isConnected())

    def read_state(self) -> ArmState:
        """Read pose, speed and safety state; a link that is down yields ``connected=False`` and NaNs."""
        now = time.monotonic()
        if self._receive is None or not self._receive.isConnected():
            if not self._was_down:
                self._count("disconnected")  # once per loss of the link, not once per health read
            self._was_down = True
            return ArmState(False, _NAN6, _NAN6, False, False, False, 0, 0, 0, now)
        self._was_down = False
        r = self._receive
        try:
            protective = bool(r.isProtectiveStopped())
            state = ArmState(
                connected=True,
                pose=tuple(r.getActualTCPPose()),
                speed=tuple(r.getActualTCPSpeed()),
                protective_stop=protective,
                emergency_stop=bool(r.isEmergencyStopped()),
                program_running=bool(int(r.getRobotStatus()) & _STATUS_PROGRAM_RUNNING),
                safety_mode=int(r.getSafetyMode()),
                robot_mode=int(r.getRobotMode()),
                runtime_state=int(r.getRuntimeState()),
                t_read=now,
            )
        except RuntimeError:
            self._count("read")
            return ArmState(False, _NAN6, _NAN6, False, False, False, 0, 0, 0, now)
        if protective and not self._was_protective:
            self._count("protective_stop")  # counted once per occurrence, not per read
        self._was_protective = protective
        return state

    def stop(self, reason: str) -> StopResult:
        """Halt the arm with the configured method; falls back to the dashboard ``stop`` when that fails
        and ``fallback_to_dashboard`` is set. Records the issue/return times in ``last_stop``."""
        s = self.settings
        t_issued = time.monotonic()
        ok, error = self._stop_with(s.stop_method)
        method = s.stop_method
        if not ok and s.fallback_to_dashboard and not s.stop_method.startswith("dashboard"):
            ok2, error2 = self._stop_with("dashboard_stop")
            if ok2:
                ok, method = True, f"{s.stop_method}->dashboard_stop"
            error = f"{error}; fallback dashboard stop: {error2 or 'ok'}"
        t_returned = time.monotonic()
        protective = self._protective_now()
        if not ok:
            self._count("stop_failed")
        # ``error`` also survives a successful fallback: it says why the configured method was not enough.
        result = StopResult(ok, method, reason, t_issued, t_returned, protective, error)
        self.last_stop = result
        return result

    def _protective_now(self) -> bool:
        try:
            r = self._receive
            return r is not None and r.isConnected() and bool(r.isProtectiveStopped())
        except RuntimeError:
            return False

    def _stop_with(self, method: str) -> tuple[bool, str]:
        """Issue one stop; returns (accepted, error text)."""
        a = self.settings.stop_deceleration
        try:
            if method in ("stopl", "speed_stop"):
                c = self._control
                if c is None or not c.isConnected():
                    return False, "RTDE control interface not connected"
                if not c.isProgramRunning():
                    return False, "ur_rtde control script not running (protective stop, or stopped from the pendant)"
                if method == "stopl":
                    # Returns nothing. Synchronous: returns when the arm is at rest (the script's "done"
                    # handshake); asynchronous: as soon as the script has started its stop thread.
                    c.stopL(a, self.settings.stop_asynchronous)
                    # A refused stop leaves the script dead: check it survived the command.
                    if not c.isProgramRunning():
                        return False, "stopL: control script stopped while executing it"
                    return True, ""
                return (True, "") if c.speedStop(a) else (False, "speedStop refused by the controller")
            return self._dashboard_command("pause" if method == "dashboard_pause" else "stop"), ""
        except RuntimeError as e:  # ur_rtde raises RuntimeError for socket and dashboard failures
            return False, f"{method}: {e}"

    def _dashboard_command(self, name: str) -> bool:
        """Send ``pause``/``stop`` to the dashboard; one reconnect-and-retry, because a dropped dashboard
        socket is only noticed when written to. Raises RuntimeError when the retry fails too."""
        try:
            getattr(self._dashboard_connected(), name)()
        except RuntimeError as first:
            if "Failed to execute" in str(first):
                raise  # the controller refused (e.g. nothing to pause): a reconnect would not change that
            if self._dashboard is not None:
                with contextlib.suppress(RuntimeError):
                    self._dashboard.disconnect()
            self._dashboard = None
            getattr(self._dashboard_connected(), name)()
        return True

    def kick_watchdog(self) -> None:
        """Arm the controller-side watchdog on the running control script (first call after each upload, and
        every ``WATCHDOG_REARM_KICKS`` kicks: ur_rtde may reconnect and upload a script of its own, without one,
        unseen by this class), then kick it. Never raises: a failed kick is counted (``kind="watchdog"``); the
        controller halting the arm is then the intended outcome."""
        c = self._control
        if c is None:
            return
        try:
            self._kicks += 1
            if (not self._watchdog_armed or self._kicks >= WATCHDOG_REARM_KICKS) and not self._arm_watchdog():
                self._count("watchdog")
                return
            c.kickWatchdog()
        except RuntimeError:
            self._count("watchdog")

    def _arm_watchdog(self) -> bool:
        """Set the watchdog on the running control script; False when there is none or it refused."""
        c = self._control
        self._watchdog_armed = c is not None and c.isProgramRunning() and bool(
            c.setWatchdog(1.0 / self.settings.watchdog_s))
        self._kicks = 0
        return self._watchdog_armed

    def control_script_running(self) -> bool:
        """True when there is no control interface, or its script runs (the watchdog ends it when unkicked)."""
        try:
            return self._control is None or bool(self._control.isProgramRunning())
        except RuntimeError:
            return False

    def reconnect(self) -> bool:
        """Reconnect whatever is down; re-upload the control script when it is no longer running."""
        s = self.settings
        try:
            if self._receive is None:
                self._receive = self._receive_factory(s.host, s.frequency)
            elif not self._receive.isConnected():
                self._receive.reconnect()
            if s.use_control:
                uploaded = False
                if self._control is None:
                    self._control = self._control_factory(s.host, s.frequency)
                    uploaded = True
                elif not self._control.isConnected():
                    self._control.reconnect()  # uploads a fresh script of ur_rtde's
                    uploaded = True
                if not self._control.isProgramRunning() and not self._protective_now():
                    self._control.reuploadScript()
                    uploaded = True
                    deadline = time.monotonic() + s.script_start_timeout
                    while not self._control.isProgramRunning() and time.monotonic() < deadline:
                        time.sleep(0.01)
                if uploaded:
                    # A new script starts without a watchdog: arm it now rather than at the next kick. A blind
                    # daemon does not kick, so the controller then halts the arm by itself (the script slipd left
                    # running is always a watched one); a live one kicks within the period.
                    self._arm_watchdog()
            if self._uses_dashboard:
                self._dashboard_connected()
        except RuntimeError:
            self._count("reconnect")
            return False
        ok = self.is_connected()
        if not ok:
            self._count("reconnect")
        return ok

    def unlock_protective_stop(self) -> bool:
        """Release a protective stop from the dashboard and resume the paused program (``play``).

        Only for supervised set-ups: the cause of a protective stop should be inspected first.
        """
        try:
            d = self._dashboard_connected()
            d.unlockProtectiveStop()
            d.play()
            return True
        except RuntimeError:
            self._count("reconnect")
            return False

    def close(self) -> None:
        """Disconnect every interface (the control script is told to end first)."""
        if self._control is not None:
            with contextlib.suppress(RuntimeError):
                if self._control.isConnected() and self._control.isProgramRunning():
                    self._control.stopScript()
                self._control.disconnect()
        for obj in (self._receive, self._dashboard):
            if obj is not None:
                with contextlib.suppress(RuntimeError):
                    obj.disconnect()
        self._receive = self._control = self._dashboard = None
        self._watchdog_armed = False
