"""Simulator effects: one small class per effect, registered by name with the stage it acts on.

A scene lists the effects it wants (``effects: [{name: noise, fx_n: 0.01}, ...]``); the simulator
runs exactly those, stage by stage, and nothing else. Each effect draws from its own random
generator (seeded from the scene seed, its name and its position in the list), so an effect that is
not listed leaves no trace and adding one effect does not change what another one draws.

Stages, in the order the simulator runs them:
    contact   before physics: which pillars touch and how far the surface misses each one
              (``ctx.contact_offset`` [9] mm, ``ctx.contact_mask`` [9] bool)
    motion    before physics: the driving inputs (hexapod ``ctx.pose_t`` [N,2] / ``ctx.pose_th`` [N] /
              ``ctx.depth`` [N]; gripper ``ctx.grip`` [N] N, ``ctx.accel`` [N,2], ``ctx.speed_scale``)
    load      before physics, gripper only: ``ctx.gravity`` [N,2] mm/s^2, ``ctx.com_offset`` [2] mm
    signal    after physics on the measured forces ``ctx.force`` [N,9,3] (float64, N)
    meta      after everything: may only add entries to ``ctx.meta`` (serial faults for the emulator)
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from slipd.geometry import FT_RANGE_N, FZ_RANGE_N, N_PILLARS, OUTER, PILLAR_XY_MM

STAGES = ("contact", "motion", "load", "signal", "meta")

_PT = TypeVar("_PT", bound=BaseModel)


@dataclass
class SimContext:
    """Everything an effect may read or change; arrays are per sample at 1 kHz."""

    family: str
    n: int
    t_s: np.ndarray
    motion_start: int
    contact_offset: np.ndarray = field(default_factory=lambda: np.zeros(N_PILLARS))
    contact_mask: np.ndarray = field(default_factory=lambda: np.ones(N_PILLARS, bool))
    pose_t: np.ndarray | None = None
    pose_th: np.ndarray | None = None
    depth: np.ndarray | None = None
    grip: np.ndarray | None = None
    accel: np.ndarray | None = None
    gravity: np.ndarray | None = None
    com_offset: np.ndarray | None = None
    object_com_offset: tuple[float, float] = (0.0, 0.0)
    """The scene object's centre-of-mass offset, which ``offcenter_torque`` applies."""
    table: bool = False
    """Gripper: the object starts on a table that carries its weight until lift-off (set by ``gravity``)."""
    curvature_1_mm: float = 0.0
    """Object curvature (1/radius) a ``curvature`` effect may apply; set by gripper scenes."""
    force: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)


class EffectParams(BaseModel):
    """Base of every effect's parameters: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


class Effect:
    """An effect: ``name`` and ``stage`` class attributes, a ``Params`` model, and ``apply``."""

    name: ClassVar[str]
    stage: ClassVar[str]
    order: ClassVar[int] = 50
    """Position within the stage (signal chain: drift, lowpass, noise, glitches, quantisation)."""
    Params: ClassVar[type[EffectParams]] = EffectParams

    def __init__(self, params: EffectParams) -> None:
        self.p = params

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:  # pragma: no cover - abstract
        """Change ``ctx`` in place."""
        raise NotImplementedError


REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: make an effect available to scenes by its name."""
    if cls.stage not in STAGES:
        raise ValueError(f"effect {cls.name}: unknown stage {cls.stage!r}")
    REGISTRY[cls.name] = cls
    return cls


def build_effect(spec: dict[str, Any], where: str = "effects") -> Effect:
    """An effect from its scene entry ``{name: ..., <params>}``; errors name the key path and reason."""
    if not isinstance(spec, dict) or "name" not in spec:
        raise ValueError(f"{where}: each effect needs a 'name' (one of {sorted(REGISTRY)})")
    name = spec["name"]
    if name not in REGISTRY:
        raise ValueError(f"{where}.name: unknown effect {name!r}; known: {sorted(REGISTRY)}")
    cls = REGISTRY[name]
    return cls(scene_params(cls.Params, spec, where))


def scene_params(params_cls: type[_PT], spec: dict[str, Any], where: str) -> _PT:
    """The parameters of a registered class (an effect, a contact model) from its scene entry
    ``{name: ..., <params>}``; a bad value raises ValueError naming the key path and reason."""
    try:
        return params_cls(**{k: v for k, v in spec.items() if k != "name"})
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise ValueError(f"{where}.{loc}: {err['msg']}") from None


def effect_rng(seed: int, name: str, index: int) -> np.random.Generator:
    """Independent generator per (scene seed, effect name, position in the list)."""
    return np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(name.encode()), index])


def run_stage(stage: str, effects: list[Effect], ctx: SimContext, seed: int) -> None:
    """Apply the listed effects of one stage in their chain order."""
    chosen = [(e.order, i, e) for i, e in enumerate(effects) if e.stage == stage]
    for _, i, e in sorted(chosen, key=lambda x: (x[0], x[1])):
        e.apply(ctx, effect_rng(seed, e.name, i))


# ---------------------------------------------------------------------------- contact stage
@register
class PartialContact(Effect):
    """Some pillars miss the surface entirely (an object smaller than the array, an edge contact)."""

    name, stage = "partial_contact", "contact"

    class Params(EffectParams):
        pillars: list[int] | None = None
        """SDK indices not in contact; if omitted, ``count`` random outer pillars are chosen."""
        count: int = Field(1, ge=1, le=8)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        if self.p.pillars is not None:
            bad = [p for p in self.p.pillars if not 0 <= p < N_PILLARS]
            if bad:
                raise ValueError(f"partial_contact.pillars: {bad} are not SDK indices 0..8")
            off = list(self.p.pillars)
        else:
            off = list(rng.choice(OUTER, size=self.p.count, replace=False))
        ctx.contact_mask = ctx.contact_mask.copy()
        ctx.contact_mask[off] = False


@register
class Tilt(Effect):
    """The surface is tilted: pillars on one side are reached later (compression falls linearly)."""

    name, stage = "tilt", "contact"

    class Params(EffectParams):
        angle_deg: float = Field(1.0, ge=0.0, le=10.0)
        axis_deg: float | None = None
        """Direction (in the sensor plane) in which the surface rises; random if omitted."""

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        axis = np.deg2rad(self.p.axis_deg if self.p.axis_deg is not None else rng.uniform(0, 360))
        along = PILLAR_XY_MM @ np.array([np.cos(axis), np.sin(axis)])
        ctx.contact_offset = ctx.contact_offset + np.tan(np.deg2rad(self.p.angle_deg)) * along


@register
class Curvature(Effect):
    """A convex surface of radius R: a pillar at distance r from the contact line/point misses it by r^2 / 2R.

    ``axis_deg`` set: a cylinder whose axis runs along that direction (bottles, cans); omitted: a sphere.
    """

    name, stage = "curvature", "contact"

    class Params(EffectParams):
        radius_mm: float | None = Field(None, gt=0.0)
        """Radius of curvature; default: the scene object's curvature (gripper scenes)."""
        centre_mm: tuple[float, float] = (0.0, 0.0)
        axis_deg: float | None = 90.0

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        k = 1.0 / self.p.radius_mm if self.p.radius_mm is not None else ctx.curvature_1_mm
        rel = PILLAR_XY_MM - np.asarray(self.p.centre_mm)
        if self.p.axis_deg is None:
            r2 = (rel**2).sum(1)
        else:
            a = np.deg2rad(self.p.axis_deg)
            r2 = (rel @ np.array([-np.sin(a), np.cos(a)])) ** 2  # distance from the axis line
        ctx.contact_offset = ctx.contact_offset + 0.5 * k * r2


# ---------------------------------------------------------------------------- motion stage
@register
class SpeedVariation(Effect):
    """The drive's speed wanders smoothly around its set point (hexapod pose, or the arm's acceleration)."""

    name, stage = "speed_variation", "motion"

    class Params(EffectParams):
        amplitude: float = Field(0.2, ge=0.0, le=0.9)
        """Peak relative speed change."""
        period_s: float = Field(0.5, gt=0.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        t = ctx.t_s
        phase = rng.uniform(0, 2 * np.pi)
        factor = 1.0 + self.p.amplitude * np.sin(2 * np.pi * t / self.p.period_s + phase)
        if ctx.family == "hexapod":
            # Re-time the path: progress along it advances at the varied speed (a time warp of the pose).
            m0 = ctx.motion_start
            warp = np.concatenate([t[:m0], t[m0] + np.cumsum(factor[m0:]) * (t[1] - t[0]) - (t[1] - t[0])])
            ctx.pose_t = np.stack([np.interp(warp, t, ctx.pose_t[:, i]) for i in range(2)], 1)
            ctx.pose_th = np.interp(warp, t, ctx.pose_th)
        else:
            ctx.accel = ctx.accel * factor[:, None]


@register
class ServoLag(Effect):
    """The gripper servo follows its grip-force command through a first-order lag and a rate limit."""

    name, stage = "servo_lag", "motion"

    class Params(EffectParams):
        tau_s: float = Field(0.03, gt=0.0)
        max_rate_n_s: float = Field(200.0, gt=0.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        if ctx.grip is None:
            raise ValueError("servo_lag: only gripper scenes have a servo")
        dt = float(ctx.t_s[1] - ctx.t_s[0]) if ctx.n > 1 else 1e-3
        alpha = dt / (self.p.tau_s + dt)
        out = np.empty_like(ctx.grip)
        g = 0.0
        step_max = self.p.max_rate_n_s * dt
        for k, target in enumerate(ctx.grip.tolist()):  # once per scene, before physics: a plain loop
            g += min(max(alpha * (target - g), -step_max), step_max)
            out[k] = g
        ctx.grip = out


# ---------------------------------------------------------------------------- load stage
@register
class Gravity(Effect):
    """The object's weight acts in the sensor plane (-y); a table carries it until the grasp lifts it."""

    name, stage = "gravity", "load"

    class Params(EffectParams):
        g_mm_s2: float = Field(9810.0, ge=0.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        if ctx.gravity is None:
            raise ValueError("gravity: only gripper scenes carry an object")
        ctx.gravity = ctx.gravity + np.array([0.0, -self.p.g_mm_s2])
        ctx.table = True


@register
class OffcenterTorque(Effect):
    """The object's centre of mass sits off the grasp centre, so its load also twists the grasp."""

    name, stage = "offcenter_torque", "load"

    class Params(EffectParams):
        offset_mm: tuple[float, float] | None = None
        """Centre-of-mass offset; default: the scene object's com_offset_mm."""

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        if ctx.com_offset is None:
            raise ValueError("offcenter_torque: only gripper scenes carry an object")
        off = self.p.offset_mm if self.p.offset_mm is not None else ctx.object_com_offset
        ctx.com_offset = np.asarray(off, np.float64)


# ---------------------------------------------------------------------------- signal stage
@register
class Drift(Effect):
    """Slow offset drift of every channel (temperature): a linear trend plus a small random walk."""

    name, stage, order = "drift", "signal", 10

    class Params(EffectParams):
        rate_n_s: float = Field(0.01, ge=0.0)
        """Peak linear drift rate."""
        walk_n: float = Field(0.005, ge=0.0)
        """Random-walk size after one second."""

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        slope = rng.uniform(-1, 1, size=(N_PILLARS, 3)) * self.p.rate_n_s
        walk = np.cumsum(rng.normal(0, self.p.walk_n * np.sqrt(1e-3), size=ctx.force.shape), axis=0)
        ctx.force = ctx.force + ctx.t_s[:, None, None] * slope + walk


@register
class Lowpass(Effect):
    """The sensor's anti-alias filter: causal 2nd-order Butterworth (338.8 Hz at 1 kHz by default)."""

    name, stage, order = "lowpass", "signal", 20

    class Params(EffectParams):
        cutoff_hz: float = Field(338.8, gt=0.0, lt=500.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        from scipy.signal import butter, lfilter, lfilter_zi

        b, a = butter(2, self.p.cutoff_hz / 500.0)
        x = ctx.force.reshape(ctx.n, -1)
        zi = lfilter_zi(b, a)[:, None] * x[:1]  # start settled on the first sample: no start-up transient
        y, _ = lfilter(b, a, x, axis=0, zi=zi)
        ctx.force = y.reshape(ctx.force.shape)


@register
class Noise(Effect):
    """White Gaussian measurement noise (published sigma: ~0.01 N on fx, fy; ~0.02 N on fz)."""

    name, stage, order = "noise", "signal", 30

    class Params(EffectParams):
        fx_n: float = Field(0.01, ge=0.0)
        fy_n: float = Field(0.01, ge=0.0)
        fz_n: float = Field(0.02, ge=0.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        sigma = np.array([self.p.fx_n, self.p.fy_n, self.p.fz_n])
        ctx.force = ctx.force + rng.normal(size=ctx.force.shape) * sigma


@register
class Glitches(Effect):
    """Isolated single-sample spikes on random channels (optical glitches the median filter removes)."""

    name, stage, order = "glitches", "signal", 40

    class Params(EffectParams):
        rate_hz: float = Field(2.0, ge=0.0)
        amplitude_n: float = Field(2.0, ge=0.0)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        count = rng.poisson(self.p.rate_hz * ctx.n / 1000.0)
        idx = rng.integers(0, ctx.n, size=count)
        pil = rng.integers(0, N_PILLARS, size=count)
        ax = rng.integers(0, 3, size=count)
        ctx.force = ctx.force.copy()
        ctx.force[idx, pil, ax] += rng.choice([-1.0, 1.0], size=count) * self.p.amplitude_n
        ctx.meta.setdefault("glitch_samples", []).extend(sorted(int(i) for i in idx))


@register
class Quantisation(Effect):
    """16-bit quantisation over the sensor's ranges (+-4 N tangential, 0..15 N normal by default)."""

    name, stage, order = "quantisation", "signal", 90

    class Params(EffectParams):
        bits: int = Field(16, ge=4, le=24)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        step = np.array([2 * FT_RANGE_N, 2 * FT_RANGE_N, FZ_RANGE_N]) / 2**self.p.bits
        ctx.force = np.round(ctx.force / step) * step


# ---------------------------------------------------------------------------- meta stage
SERIAL_FAULT_KINDS = ("drop", "checksum", "truncate", "garbage", "duplicate")


@register
class SerialFaults(Effect):
    """Marks samples whose serial frame the PapillArray emulator should corrupt; physics arrays untouched.

    ``meta["serial_faults"]`` = list of ``{"index": sample, "kind": one of SERIAL_FAULT_KINDS}``.
    """

    name, stage = "serial_faults", "meta"

    class Params(EffectParams):
        rate_hz: float = Field(1.0, ge=0.0)
        kinds: list[str] = list(SERIAL_FAULT_KINDS)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        bad = [k for k in self.p.kinds if k not in SERIAL_FAULT_KINDS]
        if bad or not self.p.kinds:
            raise ValueError(f"serial_faults.kinds: {bad or 'empty'}; allowed: {list(SERIAL_FAULT_KINDS)}")
        count = rng.poisson(self.p.rate_hz * ctx.n / 1000.0)
        idx = np.sort(rng.choice(ctx.n, size=min(count, ctx.n), replace=False))
        kinds = rng.choice(self.p.kinds, size=len(idx))
        ctx.meta["serial_faults"] = [{"index": int(i), "kind": str(k)} for i, k in zip(idx, kinds)]

