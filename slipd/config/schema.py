"""The daemon's configuration schema: one pydantic model per section, one section per device.

Every section rejects unknown keys (a misspelt key is an error, never a silently ignored setting) and
every field carries a description and bounds; ``docs/configuration.md`` is generated from these
descriptions (``python tools/config_reference.py``). Relative paths (``model.manifest``,
``recorder.directory``) resolve against the config file's folder; ``model.manifest`` may also name a
packaged model (``slip_ensemble_int8``). ``recorder.directory`` left out means
``$STATE_DIRECTORY/recordings`` under systemd (``StateDirectory=slipd``), else ``/var/lib/slipd/recordings``.

The models are frozen. A caller that must change a loaded config (the simulated rig fills in the
ports of its emulated devices) uses ``slipd.config.override``, which validates the result again.
"""

from __future__ import annotations

import ipaddress
import os
import re
import reprlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from slipd import models

DEFAULT_STATE_DIR = Path("/var/lib/slipd")
DYNAMIXEL_BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000,
                       2000000, 2500000, 3000000, 3500000, 4000000)
"""Baud rates dynamixel-sdk's PortHandler accepts (the same list as ``slipd.io.gripper.BAUDRATES``, which is not
imported here so that ``check-config`` does not load the vendor SDK; a test keeps the two equal)."""
MAX_CONFIG_BYTES = 1 << 20
"""A config larger than this is refused before parsing."""

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
# Values in error messages are shown through reprlib: bounded in depth and items, so a YAML alias
# bomb (aliases are shared references, cheap to load, exponential to print) cannot hang check-config.

_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*$")


class ConfigError(ValueError):
    """An invalid configuration. ``problems`` holds one line per problem (file, key path, reason)."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class FieldProblem(ValueError):
    """A cross-field check failing on one named field of a section (so the error names that key)."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(reason)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, validate_default=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_numbers(cls, v: Any, info: ValidationInfo) -> Any:
        # pydantic takes true as 1 wherever a number is due: ``max_force_n: true`` would be a 1 N jaw,
        # ``protocol: true`` protocol 1.0.
        if isinstance(v, bool) and info.field_name is not None and not _admits_bool(
                cls.model_fields[info.field_name].annotation):
            raise ValueError(f"must be a number, not {str(v).lower()}")
        return v

    def changed(self, keys: Iterable[str]) -> tuple[str, Any, Any] | None:
        """The first of ``keys`` set to something other than its default, as (key, value, default); None when all
        keep theirs. Keys a mode never reads are refused when set: unread options, like unknown keys."""
        fields = type(self).model_fields
        for key in keys:
            value, default = getattr(self, key), fields[key].default
            if value != default:
                return key, value, default
        return None


def _admits_bool(annotation: Any) -> bool:
    """Whether a field's type takes a boolean (bool itself, or a union with it)."""
    return annotation is bool or any(_admits_bool(a) for a in get_args(annotation))


def _host(value: str, key: str) -> str:
    """Accept an IPv4/IPv6 address or a DNS host name."""
    try:
        ipaddress.ip_address(value)
        return value
    except ValueError:
        pass
    if not _HOSTNAME.match(value):
        raise ValueError(f"{key} must be an IP address or a host name")
    return value


def _path_text(value: Any) -> Any:
    """Paths must be written as non-empty strings (YAML ``123`` or ``[]`` is not a path)."""
    if isinstance(value, Path):
        return value
    if not isinstance(value, str) or not value.strip():
        raise ValueError("must be a non-empty path string")
    if "\0" in value:
        raise ValueError("must not contain a NUL character")
    return value


def _resolve(path: Path, info: ValidationInfo) -> Path:
    """Expand ``~`` and ``$VARS``; resolve a relative path against the config file's folder."""
    expanded = os.path.expandvars(os.path.expanduser(str(path)))
    if "$" in expanded:
        raise ValueError(f"contains an unset environment variable: {expanded!r}")
    p = Path(expanded)
    base = (info.context or {}).get("base_dir")
    if not p.is_absolute() and base is not None:
        p = Path(base) / p
    return Path(os.path.normpath(p))


# ---------------------------------------------------------------------------------------------- sections
class SensorConfig(_Section):
    """The PapillArray on its USB CDC serial port."""

    port: str = Field(min_length=1, description="serial device of the sensor, e.g. /dev/ttyACM0 or a udev symlink")
    baudrate: int = Field(
        115200, ge=1200, le=4_000_000, description="nominal baud rate; USB CDC ignores it, kept for USB-UART bridges"
    )
    rate_hz: Literal[100, 250, 500, 1000] = Field(
        1000, description="sample rate commanded at start-up (f100/f250/f500/f1000); must equal the model's rate"
    )
    sensors: int = Field(
        1, ge=1, le=2, description="sensor arrays the controller streams in each frame, one per sensorised finger "
        "(2: both fingers of a parallel gripper); each gets its own features, tare, model state and decision, an "
        "alarm on either reacts, and being blind on either fails safe"
    )
    tare: Literal["bias_command", "startup", "none"] = Field(
        "bias_command",
        description="bias_command: send 'z' (sensor zeroes itself, offset 0); startup: average the first "
        "tare_samples frames while unloaded; none: use the forces as reported",
    )
    tare_samples: int = Field(
        500, ge=1, le=60_000, description="frames averaged for tare=startup (the finger must be unloaded meanwhile)"
    )
    bias_timeout_s: float = Field(
        3.0, ge=0.5, le=30.0, description="how long the daemon waits after the bias command, before it decides "
        "(the sensor needs >= 1 s unloaded, <= 2 s; the wait is not shortened or checked)"
    )
    reconnect_initial_s: float = Field(0.1, ge=0.01, le=60.0, description="first reconnection delay after a loss")
    reconnect_max_s: float = Field(5.0, ge=0.01, le=600.0, description="reconnection delay cap (doubling backoff)")
    stall_timeout_ms: float = Field(
        50.0, ge=2.0, le=10_000.0, description="no frame for this long -> fail-safe (reaction.on_failsafe)"
    )
    rate_tolerance: float = Field(
        0.1, ge=0.01, le=0.5, description="how far the stream's rate, measured from the controller's own clock and "
        "packet counter over 0.2 s, may stray from rate_hz (a share: 0.1 is 10 %); beyond it the daemon fails safe "
        "with cause rate and is not live (nor READY at start-up) until the rate is back within it; applied by a reload"
    )
    low_latency: bool = Field(True, description="set the serial port's ASYNC_LOW_LATENCY flag (ftdi/cdc latency)")
    coalesce_margin_ms: float | None = Field(
        1.0, ge=0.0, le=100.0, description="coalesce frame reads: between decisions the loop stops watching the "
        "port, reads the buffered frames in one go and holds them undecoded until the deciding frame is in, "
        "resuming this many ms before that frame is due (by the reader's arrival clock; 1 ms covers the event "
        "loop's 1 ms timer granularity, so the deciding frame is still read at once). null: read and handle "
        "every frame as it arrives",
    )

    @model_validator(mode="after")
    def _consistent(self) -> SensorConfig:
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise FieldProblem(
                "reconnect_max_s",
                f"must be >= reconnect_initial_s ({self.reconnect_initial_s}), got {self.reconnect_max_s}",
            )
        period_ms = 1000.0 / self.rate_hz
        if self.stall_timeout_ms < 2 * period_ms:
            raise FieldProblem(
                "stall_timeout_ms",
                f"must be at least two frame periods at {self.rate_hz} Hz ({2 * period_ms:g} ms), "
                f"got {self.stall_timeout_ms:g}",
            )
        return self


class ModelConfig(_Section):
    """The ONNX ensemble, named by its manifest."""

    manifest: Path = Field(
        description="the model: a packaged model's name (slip_ensemble_int8; `slipd models` lists them) or a "
        "manifest path (.json beside the .onnx); a relative path resolves against this file's folder"
    )
    threads: int = Field(1, ge=1, le=64, description="onnxruntime intra-op threads (1: lowest jitter)")
    detector: Literal["onnx", "deceleration", "reference_pillar"] = Field(
        "onnx", description="onnx: the ensemble of the manifest; deceleration / reference_pillar: a published "
        "heuristic (slipd.detect.baselines) with the tuned parameters of baseline_params, for comparison on the rig; a "
        "heuristic decides on every sample by its own rule, so model.stride and the decision section keep their "
        "defaults"
    )
    baseline_params: Path | None = Field(
        None, description="tuned heuristic parameters (JSON); null: those tuned on gripper lifts beside the manifest "
        "(baselines_transfer.json, as the packaged models have), else baselines.json there"
    )
    stride: int = Field(
        0, ge=0, le=10_000,
        description="decision every N samples; 0 = the manifest's stride (the model's window when the manifest "
        "has none); otherwise it must divide the window"
    )

    @field_validator("manifest", "baseline_params", mode="before")
    @classmethod
    def _manifest_text(cls, v: Any, info: ValidationInfo) -> Any:
        if v is None:
            return v
        v = _path_text(v)
        if info.field_name == "manifest" and isinstance(v, str) and models.is_name(v):
            try:
                return models.packaged(v)
            except FileNotFoundError as exc:
                raise ValueError(str(exc)) from None
        return v

    @field_validator("manifest", "baseline_params")
    @classmethod
    def _resolve_manifest(cls, v: Path | None, info: ValidationInfo) -> Path | None:
        return v if v is None else _resolve(v, info)


class DecisionConfig(_Section):
    """Turning the ensemble's probability into an alarm."""

    threshold: float | None = Field(
        None, gt=0.0, lt=1.0, description="alarm when p_slip >= threshold; null: the manifest's threshold"
    )
    hysteresis: float = Field(
        0.0, ge=0.0, lt=0.5, description="alarm clears only when p_slip < threshold - hysteresis (0: off)"
    )
    min_consecutive: int = Field(
        2, ge=1, le=100,
        description="decisions in a row at or above the threshold before the alarm is raised (2 at stride 10: two "
        "phase-shifted GRU streams agree, 10 ms; 1: the method's per-window rule)",
    )
    press_rise: float | None = Field(
        0.1, gt=0.0, le=10.0,
        description="press hold: no alarm is raised while the contact's summed normal force rose by more than "
        "this share within the last window (40 ms), since a press loads the pillars without slipping them; "
        "null: off",
    )
    limit_guard: float | None = Field(
        0.9, gt=0.0, le=1.0,
        description="also raise the alarm when the contact risk (the load-weighted share of the contact sliding or "
        "at its friction limit) stays at or above this for limit_guard_decisions decisions in a row, whatever "
        "p_slip says: a slow slip under a growing load (a cup being filled), which the model does not call; "
        "null: off",
    )
    limit_guard_decisions: int = Field(
        3, ge=1, le=100, description="decisions in a row at or above limit_guard before it raises the alarm (3 at "
        "stride 10: 30 ms; a sliding contact's risk dips below 0.9 for a decision now and then)",
    )
    confirm_rule: float | None = Field(
        None, gt=0.0, le=1.0,
        description="also raise the alarm on the reference-pillar heuristic's alarm (model.baseline_params) while "
        "the model's p_slip reached this level at one of its decisions in the last confirm_within_ms: the rule's "
        "speed where the model leans towards a slip, the model's quiet elsewhere (0.3: docs/engine.md); null: off, "
        "the model alone. The heuristic reads the tip displacements",
    )
    confirm_within_ms: float = Field(
        100.0, gt=0.0, le=1000.0, description="how far back a decision at confirm_rule's level confirms the rule",
    )

    @model_validator(mode="after")
    def _consistent(self) -> DecisionConfig:
        if self.threshold is not None and self.threshold - self.hysteresis <= 0.0:
            raise FieldProblem(
                "hysteresis", f"must be smaller than threshold ({self.threshold}), got {self.hysteresis}"
            )
        return self

    def effective_threshold(self, manifest_threshold: float) -> float:
        """The threshold in force: this section's, else the model manifest's."""
        return self.threshold if self.threshold is not None else manifest_threshold


Action = Literal["stop_arm", "tighten_gripper"]


class ReactionConfig(_Section):
    """What happens on an alarm and on a fail-safe event."""

    actions: list[Action] = Field(
        default_factory=lambda: list[Action](["stop_arm", "tighten_gripper"]),
        description="in this order of submission; []: no reaction to an alarm (detects and records; a fail-safe "
        "still acts as reaction.on_failsafe says)",
    )
    graded: bool = Field(False, description="tighten in proportion to the risk (hold..secure) rather than to secure "
                         "(the ensemble's alarm rises at risk 1, so only the heuristics' alarms tighten partly)")
    on_failsafe: Literal["stop_arm", "stop_arm_and_tighten", "log_only"] = Field(
        "stop_arm",
        description="on sensor stall or model failure: stop_arm (keep the grip as it is), stop_arm_and_tighten "
        "(to the secure setting; under grip_control to grip_max_force_n, the object's limit), or log_only (not for "
        "production)",
    )
    rearm_after_s: float = Field(
        1.0, ge=0.0, le=3600.0, description="after a reaction, further alarms this soon do not re-issue it"
    )
    policy: Literal["stop_and_secure", "grip_control"] = Field(
        "stop_and_secure",
        description="stop_and_secure: an alarm runs the actions; grip_control: the grip follows the contact's "
        "friction use and risk (reaction.grip_*), the arm stops only at grip_stop_risk or at the force limit "
        "(actions: tighten_gripper lets it command the grip, stop_arm lets it stop the arm)",
    )
    grip_margin: float = Field(
        0.7, gt=0.0, le=1.0, description="grip_control: keep the friction use, shear / (friction x grip), at this "
        "share (the friction is the sliding pillars' estimate, i.e. the kinetic coefficient)"
    )
    grip_max_force_n: float = Field(
        30.0, gt=0.0, le=200.0, description="grip_control: the object's force limit; the grip never exceeds it: "
        "every gripper command's effort is capped at the one that gives it, the start-up hold's included "
        "(N; at most gripper.max_force_n, the jaw's full force, and the policy needs gripper.enabled)"
    )
    grip_catch: float = Field(
        2.0, ge=1.0, le=10.0, description="grip_control: at the start of a slip the grip jumps to this multiple of "
        "itself (a sliding contact's shear is its kinetic friction, not the load, so the need is unknown)"
    )
    grip_takeover_after_s: float = Field(
        0.1, ge=0.0, le=60.0, description="grip_control: take the grip over (force control at the force the hold "
        "setting produced) once it stayed steady this long, so that a catch is one effort change"
    )
    grip_twist: float | None = Field(
        None, ge=1.0, le=100.0, description="grip_control: a slip whose pillar shear is this multiple of the net load "
        "is a twist (an off-centre object turning) and stops the arm at once; null (the default): a twist is a slip "
        "like any other, which the grip catches, and the force limit stops the arm for a torque it cannot hold. "
        "Set it for objects held far from their centre of mass, where millimetre lever arms hold little torque"
    )
    grip_rise_n_s: float = Field(
        800.0, gt=0.0, le=10_000.0, description="grip_control: fastest grip increase (N/s), within the jaw's own rate "
        "when it closes by position; slower lets a slip run further before the catch holds (300: 0.59 mm on the rig "
        "against 0.45), faster splays the pillars of an off-centre grasp into a whole-contact slip (1500: three arm "
        "stops at the force limit in 12 lifts, against one)"
    )
    grip_relax_n_s: float = Field(
        2.0, ge=0.0, le=1000.0, description="grip_control: relaxation towards the required (at least the holding) "
        "force (N/s)"
    )
    grip_relax_after_s: float = Field(
        1.0, ge=0.0, le=3600.0, description="grip_control: relax only after the contact stayed quiet (no alarm, "
        "risk below grip_raise_risk) this long; a slip that resumes sooner is the same slip (no new catch)"
    )
    grip_raise_risk: float = Field(
        0.5, ge=0.0, le=1.0, description="grip_control: contact risk from which the contact counts as slipping "
        "(as does the detector's alarm): a new slip is caught at once, then the grip follows the requirement"
    )
    grip_stop_risk: float = Field(
        0.9, ge=0.0, le=1.0, description="grip_control: contact risk at which the arm is stopped as well (once it "
        "lasted grip_stop_after_s)"
    )
    grip_stop_after_s: float = Field(
        0.15, ge=0.0, le=60.0, description="grip_control: how long the risk must stay at grip_stop_risk before the "
        "arm stops (the grip had its chance to catch the slip)"
    )
    grip_update_hz: float = Field(
        62.0, gt=0.0, le=1000.0, description="grip_control: most grip commands per second (the servo's update rate)"
    )

    @field_validator("actions")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("an action is listed twice")
        return v


class GripperConfig(_Section):
    """Dynamixel MX-28 gripper servo (dynamixel-sdk)."""

    enabled: bool = Field(True, description="false: no gripper (reaction.actions must not tighten)")
    port: str | None = Field(None, min_length=1, description="servo bus serial device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(57600, description="servo bus baud rate (MX-28 factory: 57600); one dynamixel-sdk accepts")
    id: int = Field(1, ge=0, le=252, description="servo ID on the bus")
    # Float literals are what YAML gives (1.0, 2.0); typing's Literal takes them at run time (pydantic checks
    # the value), though the type checkers' Literal does not.
    protocol: Literal[1.0, 2.0] = Field(2.0, description="Dynamixel protocol of the servo firmware")  # type: ignore[valid-type]
    hold_position: int | None = Field(
        None, ge=0, le=4095, description="goal position while holding (ticks, 0.088 deg)"
    )
    secure_position: int | None = Field(
        None, ge=0, le=4095, description="goal position when securing the grasp (ticks; closes further)"
    )
    max_force_n: float = Field(
        40.0, gt=0.0, le=500.0,
        description="grip force at full effort (PWM 885 / torque limit 1023), the calibration of grip_control",
    )
    hold_pwm: int | None = Field(None, ge=0, le=885, description="protocol 2.0: goal PWM while holding (0..885)")
    secure_pwm: int | None = Field(None, ge=0, le=885, description="protocol 2.0: goal PWM when securing")
    hold_torque_limit: int | None = Field(
        None, ge=0, le=1023, description="protocol 1.0: torque limit while holding (0..1023)"
    )
    secure_torque_limit: int | None = Field(
        None, ge=0, le=1023, description="protocol 1.0: torque limit when securing"
    )
    retries: int = Field(3, ge=0, le=20, description="retries of a failed packet before a device error")
    packet_timeout_ms: float = Field(20.0, ge=1.0, le=1000.0, description="timeout of one status packet")

    @field_validator("baudrate")
    @classmethod
    def _known_baudrate(cls, v: int) -> int:
        if v not in DYNAMIXEL_BAUDRATES:
            raise ValueError(f"must be one of {', '.join(map(str, DYNAMIXEL_BAUDRATES))}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> GripperConfig:
        if not self.enabled:
            return self
        for key in ("port", "hold_position", "secure_position"):
            if getattr(self, key) is None:
                raise FieldProblem(key, "required when the gripper is enabled")
        if self.protocol == 2.0:
            need, other, hint = ("hold_pwm", "secure_pwm"), ("hold_torque_limit", "secure_torque_limit"), "pwm"
        else:
            need, other, hint = ("hold_torque_limit", "secure_torque_limit"), ("hold_pwm", "secure_pwm"), "torque_limit"
        for key in other:
            if getattr(self, key) is not None:
                raise FieldProblem(key, f"does not apply to protocol {self.protocol}; use the *_{hint} keys")
        for key in need:
            if getattr(self, key) is None:
                raise FieldProblem(key, f"required with protocol {self.protocol}")
        if getattr(self, need[1]) < getattr(self, need[0]):
            raise FieldProblem(need[1], f"must be >= {need[0]} ({getattr(self, need[0])}): securing never loosens")
        if self.secure_position == self.hold_position:
            raise FieldProblem("secure_position", "must differ from hold_position (tightening must move the fingers)")
        return self

    @property
    def hold_effort(self) -> int:
        """Holding PWM (2.0) or torque limit (1.0)."""
        return int(self.hold_pwm if self.protocol == 2.0 else self.hold_torque_limit)  # type: ignore[arg-type]

    @property
    def secure_effort(self) -> int:
        """Securing PWM (2.0) or torque limit (1.0)."""
        return int(self.secure_pwm if self.protocol == 2.0 else self.secure_torque_limit)  # type: ignore[arg-type]


class ArmConfig(_Section):
    """Universal Robots arm over RTDE (ur_rtde)."""

    enabled: bool = Field(True, description="false: no arm (reaction.actions must not stop it)")
    host: str | None = Field(None, min_length=1, description="controller IP address or host name")
    rtde_frequency: float = Field(
        -1.0, description="RTDE frequency (Hz), 0 < f <= 500; -1: automatic (500 on e-Series, 125 on CB3)"
    )
    stop_deceleration: float = Field(
        10.0, gt=0.0, le=40.0, description="tool deceleration of stopl / speed_stop (m/s^2; UR's default 10)"
    )
    stop_method: Literal["stopl", "speed_stop", "dashboard_pause", "dashboard_stop"] = Field(
        "stopl",
        description="stopl / speed_stop: decelerate over RTDE control (replaces the running program); "
        "dashboard_pause / dashboard_stop: pause or stop the user's program through the dashboard server",
    )
    watchdog_s: float = Field(
        0.5, ge=0.02, le=10.0,
        description="controller-side watchdog (ur_rtde setWatchdog, stopl / speed_stop only): the controller "
        "halts the arm and ends the control script when slipd has not kicked it for this long (slipd dead, "
        "frozen or blind); kicked only while decisions are live. Dashboard modes have none: a dead slipd "
        "leaves the user's program running",
    )

    @field_validator("rtde_frequency")
    @classmethod
    def _frequency(cls, v: float) -> float:
        if v != -1.0 and not 0.0 < v <= 500.0:
            raise ValueError("must be -1 (automatic) or 0 < f <= 500 Hz")
        return v

    @field_validator("host")
    @classmethod
    def _valid_host(cls, v: str | None) -> str | None:
        return None if v is None else _host(v, "host")

    @model_validator(mode="after")
    def _consistent(self) -> ArmConfig:
        if self.enabled and self.host is None:
            raise FieldProblem("host", "required when the arm is enabled")
        if self.stop_method.startswith("dashboard"):
            # No RTDE control interface: no watchdog and no deceleration. An engineer who sets them expects a
            # watchdog to halt the arm when slipd dies, and none would.
            unread = self.changed(("watchdog_s", "stop_deceleration"))
            if unread is not None:
                key, value, default = unread
                raise FieldProblem(key, f"{value:g} has no effect with stop_method {self.stop_method}, which "
                                   "has no RTDE control interface (no watchdog: a dead slipd leaves the program "
                                   f"running); leave it at its default ({default:g}) or use stopl / speed_stop")
        return self


class MetricsConfig(_Section):
    """Prometheus exporter."""

    enabled: bool = Field(True, description="serve /metrics over HTTP")
    host: str = Field("127.0.0.1", min_length=1, description="listen address (loopback unless scraped remotely)")
    port: int = Field(9477, ge=1, le=65535, description="listen port")

    @field_validator("host")
    @classmethod
    def _valid_host(cls, v: str) -> str:
        return _host(v, "host")


def _default_recording_dir() -> Path:
    state = os.environ.get("STATE_DIRECTORY", "")
    # systemd joins several StateDirectory= entries with ':'; the first is slipd's own.
    first = state.split(":")[0] if state else ""
    return (Path(first) if first else DEFAULT_STATE_DIR) / "recordings"


class RecorderConfig(_Section):
    """Recordings of raw frames and decisions around alarms."""

    enabled: bool = Field(True, description="record around alarms")
    directory: Path = Field(
        default_factory=_default_recording_dir,
        description="where recordings go; default $STATE_DIRECTORY/recordings, else /var/lib/slipd/recordings",
    )
    seconds_before: float = Field(2.0, ge=0.0, le=60.0, description="raw history kept before an alarm")
    seconds_after: float = Field(1.0, ge=0.0, le=60.0, description="recording continues this long after it")
    max_total_mb: float = Field(
        500.0, gt=0.0, le=1_000_000.0, description="MiB for all recordings; the oldest are deleted beyond it"
    )
    formats: list[Literal["mcap", "npz", "csv"]] = Field(
        default_factory=lambda: list[Literal["mcap", "npz", "csv"]](["mcap"]), min_length=1,
        description="mcap (opens in Foxglove; slipd replay reads it), npz and/or Contactile SDK CSV; one file per "
        "format and episode",
    )

    @field_validator("directory", mode="before")
    @classmethod
    def _directory_text(cls, v: Any) -> Any:
        return _path_text(v)

    @field_validator("directory")
    @classmethod
    def _resolve_dir(cls, v: Path, info: ValidationInfo) -> Path:
        return _resolve(v, info)

    @field_validator("formats")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("a format is listed twice")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> RecorderConfig:
        if self.enabled and self.seconds_before + self.seconds_after <= 0:
            raise FieldProblem("seconds_after", "seconds_before + seconds_after must be > 0 when recording")
        return self


_ROS_NAME = re.compile(r"^(/[A-Za-z][A-Za-z0-9_]*)*$")
_ROS_NODE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ZENOH_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|unixsock-stream|ws)/\S+$")


def _endpoints(v: list[str], key: str) -> list[str]:
    bad = [e for e in v if not _ZENOH_ENDPOINT.match(e)]
    if bad:
        raise ValueError(f"{key}: {bad[0]!r} is not a zenoh endpoint (like tcp/localhost:7447)")
    return v


class Ros2Config(_Section):
    """Slip events on ROS 2 over Zenoh (rmw_zenoh); needs the ros2 extra (pip install 'slipd[ros2]')."""

    enabled: bool = Field(False, description="publish the alarm, p_slip, the slip map, each finger's wrench and "
                          "diagnostics as ROS 2 messages (docs/ros2.md)")
    domain_id: int = Field(0, ge=0, le=232, description="the ROS_DOMAIN_ID of the ROS 2 graph")
    namespace: str = Field("", description="ROS namespace of the node and its topics ('' none, or like /robot1)")
    node_name: str = Field("slipd", min_length=1, description="ROS node name the topics belong to")
    mode: Literal["peer", "client"] = Field(
        "peer", description="zenoh session mode: peer (as rmw_zenoh's nodes: through the router, and directly to "
        "peers it tells about) or client (through the router only)")
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/localhost:7447"],
        description="zenoh endpoints to connect to; rmw_zenoh's router (ros2 run rmw_zenoh_cpp rmw_zenohd) "
        "listens on tcp/localhost:7447")
    listen: list[str] = Field(default_factory=list, description="zenoh endpoints to listen on (empty: none)")
    type_hashes: bool = Field(
        True, description="put the REP-2016 type hash (RIHS01) in the key expressions, as rmw_zenoh on Jazzy and "
        "later does; false for Humble's rmw_zenoh (TypeHashNotSupported)")
    frame_id: str = Field("slipd_sensor", min_length=1,
                          description="header frame_id of each finger's wrench, followed by the sensor index")
    queue: int = Field(256, ge=8, le=65536, description="messages waiting for the publishing thread; beyond it the "
                       "oldest are dropped and counted (the diagnostics report the count)")
    diagnostics_period_s: float = Field(1.0, gt=0.0, le=60.0, description="seconds between diagnostics messages")

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, v: str) -> str:
        if not _ROS_NAME.match(v):
            raise ValueError("must be empty or a ROS namespace like /robot1 (letters, digits, _; no trailing /)")
        return v

    @field_validator("node_name")
    @classmethod
    def _node(cls, v: str) -> str:
        if not _ROS_NODE.match(v):
            raise ValueError("must be a ROS node name (a letter, then letters, digits or _)")
        return v

    @field_validator("connect", "listen")
    @classmethod
    def _valid_endpoints(cls, v: list[str], info: ValidationInfo) -> list[str]:
        return _endpoints(v, str(info.field_name))


class VizConfig(_Section):
    """Live view in Foxglove (a WebSocket server); needs the viz extra (pip install 'slipd[viz]')."""

    enabled: bool = Field(False, description="serve the frames and decisions live to Foxglove (docs/recordings.md)")
    host: str = Field("127.0.0.1", min_length=1, description="listen address (loopback unless viewed remotely)")
    port: int = Field(8765, ge=1, le=65535, description="listen port (Foxglove: open connection, ws://host:port)")
    frame_rate_hz: float = Field(50.0, gt=0.0, le=1000.0,
                                 description="pillar frames sent per second and sensor (decimated from 1 kHz)")
    queue: int = Field(256, ge=8, le=65536, description="messages waiting for the view's thread; beyond it the "
                       "oldest are dropped and counted")

    @field_validator("host")
    @classmethod
    def _valid_host(cls, v: str) -> str:
        return _host(v, "host")


class ControlConfig(_Section):
    """The control loop and its supervision."""

    watchdog: bool = Field(True, description="ping the systemd watchdog (WatchdogSec= in the unit) from the loop")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="logging threshold")
    max_overrun_ms: float = Field(
        5.0, gt=0.0, le=1000.0, description="a supervision tick (the liveness check, on absolute deadlines) that "
        "runs later than this past its deadline counts as an overrun (slipd_loop_overruns_total): the event loop was "
        "blocked or starved; decisions are timed by slipd_loop_duration_seconds"
    )

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper(cls, v: Any) -> Any:
        return v.upper() if isinstance(v, str) else v


class SlipdConfig(_Section):
    """The whole configuration file."""

    sensor: SensorConfig = Field(description="the PapillArray")
    model: ModelConfig = Field(description="the ONNX ensemble")
    decision: DecisionConfig = Field(default_factory=DecisionConfig, description="alarm rule")
    reaction: ReactionConfig = Field(default_factory=ReactionConfig, description="what an alarm does")
    gripper: GripperConfig = Field(description="the Dynamixel gripper servo")
    arm: ArmConfig = Field(description="the UR arm")
    metrics: MetricsConfig = Field(default_factory=MetricsConfig, description="Prometheus exporter")
    recorder: RecorderConfig = Field(default_factory=RecorderConfig, description="alarm recordings")
    control: ControlConfig = Field(default_factory=ControlConfig, description="the loop and supervision")
    ros2: Ros2Config = Field(default_factory=Ros2Config, description="slip events on ROS 2 over Zenoh")
    viz: VizConfig = Field(default_factory=VizConfig, description="live view in Foxglove")

    @model_validator(mode="after")
    def _devices_for_actions(self) -> SlipdConfig:
        needs = {"stop_arm": ("arm", self.arm.enabled), "tighten_gripper": ("gripper", self.gripper.enabled)}
        for action in self.reaction.actions:
            device, enabled = needs[action]
            if not enabled:
                raise _SectionProblem(("reaction", "actions"), f"{action} needs {device}.enabled: true")
        if self.reaction.on_failsafe != "log_only" and not self.arm.enabled:
            raise _SectionProblem(("reaction", "on_failsafe"), f"{self.reaction.on_failsafe} needs arm.enabled: true")
        if self.reaction.on_failsafe == "stop_arm_and_tighten" and not self.gripper.enabled:
            raise _SectionProblem(("reaction", "on_failsafe"), "stop_arm_and_tighten needs gripper.enabled: true")
        if self.reaction.policy == "grip_control":
            if not self.gripper.enabled:
                raise _SectionProblem(("reaction", "policy"), "grip_control needs gripper.enabled: true")
            if "tighten_gripper" not in self.reaction.actions:
                # Otherwise the policy would command the grip while the actions say the gripper is left alone.
                raise _SectionProblem(("reaction", "actions"), "grip_control commands the grip: list tighten_gripper "
                                      "(and stop_arm to let it stop the arm)")
            if self.reaction.grip_max_force_n > self.gripper.max_force_n:
                # The jaw never reaches such a target, so "at the force limit" (which stops the arm) would never hold.
                raise _SectionProblem(("reaction", "grip_max_force_n"),
                                      f"{self.reaction.grip_max_force_n:g} N is above the gripper's full force "
                                      f"(gripper.max_force_n: {self.gripper.max_force_n:g} N)")
        if self.reaction.policy != "grip_control":
            # The grip_* keys are the grip controller's: under stop_and_secure nothing reads them, and a force limit
            # set there would be believed to bind (a tighten still goes to the secure setting).
            unread = self.reaction.changed(k for k in type(self.reaction).model_fields if k.startswith("grip_"))
            if unread is not None:
                key, value, default = unread
                raise _SectionProblem(("reaction", key), f"{value} has no effect with reaction.policy "
                                      f"{self.reaction.policy} (the grip_* keys are grip_control's); leave it at "
                                      f"its default ({default}), or set reaction.policy: grip_control")
        if self.model.detector != "onnx" and self.sensor.tare == "startup":
            # The heuristics have no start-up tare of their own: they would read the sensor's raw offsets.
            raise _SectionProblem(("sensor", "tare"), f"startup: model.detector {self.model.detector} has no "
                                  "start-up tare; use bias_command (or none for a sensor that is zeroed)")
        if self.sensor.sensors > 1 and self.model.detector != "onnx":
            raise _SectionProblem(("model", "detector"), f"{self.model.detector} reads one sensor; sensor.sensors "
                                  f"is {self.sensor.sensors} (the onnx detector decides per finger)")
        if self.decision.confirm_rule is not None:
            if self.model.detector != "onnx":
                raise _SectionProblem(("decision", "confirm_rule"), f"confirms the onnx detector's decisions; "
                                      f"model.detector is {self.model.detector}")
        elif self.decision.changed(("confirm_within_ms",)) is not None:
            raise _SectionProblem(("decision", "confirm_within_ms"), "has no effect without decision.confirm_rule")
        if self.model.detector != "onnx":
            # A heuristic decides on every sample with its own tuned rule: these keys would be read by nothing, and an
            # engineer who sets them expects an effect (unread options are refused, as unknown keys are).
            for section, keys in (("model", ("stride",)),
                                  ("decision", ("threshold", "hysteresis", "min_consecutive", "press_rise",
                                                "limit_guard", "limit_guard_decisions", "confirm_rule",
                                                "confirm_within_ms"))):
                unread = getattr(self, section).changed(keys)
                if unread is not None:
                    key, value, default = unread
                    raise _SectionProblem((section, key), f"{value} has no effect with model.detector "
                                          f"{self.model.detector}, which decides on every sample with its tuned "
                                          f"parameters (model.baseline_params); leave it at its default ({default})")
        return self


class _SectionProblem(FieldProblem):
    """A cross-section check naming a full key path."""

    def __init__(self, loc: tuple[str, ...], reason: str) -> None:
        super().__init__(".".join(loc), reason)
        self.loc = loc
