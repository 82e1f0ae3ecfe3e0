"""Scenes: YAML -> validated ``Scene`` -> simulated ``Recording`` with slip truth and labels.

Two families (see ``config/scenes/``):

* ``hexapod``: a plate pressed onto the sensor to ``contact.depth_mm`` and then translated, rotated
  (about ``motion.centre_mm``) or both, ramping at ``accel`` up to ``speed``. A *stop* scene
  (``motion.stop_fraction``) halts the plate at that fraction of the travel at which the first pillar
  would slip, then holds for ``hold_s``.
* ``gripper``: an object held between the sensor finger and a rigid finger at ``grip.force_n``,
  lifted or pushed by the arm at a UR ``movel`` level (low / medium / high) or an explicit
  speed and acceleration. ``kind: stop`` trials hold a secure grip.

Timeline of every recording: ``pre_s`` unloaded (the tare stretch, ``meta["tare_samples"]``), the
press / grip closing, a settle, then the motion (``events.motion_start``).

Labels (the method's rule): incipient slip (1) from the first sample after motion start at which any
considered pillar slides until all considered pillars slide at once (gross slip, 0 again). Considered:
pillars in contact at motion start (``slipd.sim.labels``: a light grasp counts its lightly touching pillars); for
hexapod rotations only the outer eight. Gripper scenes also
end the label at gross object motion (> 2 mm or > 2 deg relative to the finger). Stop scenes are all 0.
In a combined motion whose instantaneous centre of rotation lies on a pillar, that pillar never
slides: the label then runs to the end and there is no ``gross_slip`` event (physically right).

API: ``load_scene(path) -> Scene``, ``parse_scene(dict, source) -> Scene``,
``generate(scene, seed=None) -> Recording``, ``generate_batch(scenes, seeds) -> list[Recording]``
(many scenes in one vectorised time loop: the fast path for data sets).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from slipd.geometry import N_PILLARS
from slipd.recording import Recording
from slipd.sim import contact_models as cm
from slipd.sim import effects as fx
from slipd.sim import timeline as tl
from slipd.sim.engine.spec import EngineScene
from slipd.sim.labels import considered_pillars, incipient_labels
from slipd.sim.physics import (
    DT_S,
    GripperStepper,
    ObjectParams,
    compression,
    depth_for_total_force,
    measured_disp,
    normal_force,
    pillar_outputs,
    run_hexapod,
    saturate,
    sensor_params,
)

GENERATOR_VERSION = "slipd.sim/3"
"""2: the reported tip displacements carry the force measurement error (``physics.measured_disp``). 3: off-centre
lifts put the centre of mass 4 mm beside the grasp instead of 15 mm (``datasets.OFFCENTRE_MM``), so that a stop trial's
secure grip holds the object."""
GROSS_MM, GROSS_DEG = 2.0, 2.0
UR_LEVELS = {"low": (4.0, 10.0), "medium": (10.0, 50.0), "high": (40.0, 100.0)}
"""UR ``movel`` speed (mm/s) and acceleration (mm/s^2) levels of the method's online trials."""


class SceneError(ValueError):
    """A scene file or dict is invalid; the message names the file, the key path and the reason."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Friction(_Model):
    mu_s: float = Field(0.6, gt=0.0, le=3.0)
    mu_k: float = Field(0.5, gt=0.0, le=3.0)

    @model_validator(mode="after")
    def _kinetic_below_static(self) -> Friction:
        if self.mu_k > self.mu_s:
            raise ValueError("mu_k must be <= mu_s")
        return self


class HexContact(_Model):
    depth_mm: float = Field(..., ge=0.0, le=3.0)
    press_s: float = Field(0.3, gt=0.0)


class HexMotion(_Model):
    kind: Literal["translation", "rotation", "both"]
    speed_mm_s: float = Field(5.0, ge=0.0, le=100.0)
    accel_mm_s2: float = Field(50.0, gt=0.0)
    direction_deg: float = 0.0
    rot_speed_deg_s: float = Field(10.0, ge=-360.0, le=360.0)
    """Signed: positive turns counter-clockwise."""
    centre_mm: tuple[float, float] = (0.0, 0.0)
    stop_fraction: float | None = Field(None, gt=0.0, lt=1.0)
    """Stop scene: halt at this fraction of the travel at which the first pillar would slip."""
    hold_s: float = Field(0.8, gt=0.0)


class _SceneBase(_Model):
    name: str = "scene"
    duration_s: float = Field(4.0, gt=0.0, le=600.0)
    pre_s: float = Field(0.3, ge=0.05)
    settle_s: float = Field(0.2, ge=0.0)
    effects: list[dict[str, Any]] = Field(default_factory=list)
    seed: int | None = None

    @field_validator("effects")
    @classmethod
    def _effects_valid(cls, value: list[dict[str, Any]]) -> list[dict[str, Any]]:
        for i, spec in enumerate(value):
            fx.build_effect(spec, where=str(i))  # raises ValueError naming the index and key
        return value

    def build_effects(self) -> list[fx.Effect]:
        """The listed effects as objects, in list order."""
        return [fx.build_effect(s, f"effects.{i}") for i, s in enumerate(self.effects)]


class HexapodScene(_SceneBase):
    family: Literal["hexapod"] = "hexapod"
    sensor: Literal["v1", "v2"] = "v1"
    contact: HexContact | None = None
    motion: HexMotion | None = None
    timeline: list[tl.Segment] | None = None
    """A sequence of events instead of ``contact`` + ``motion`` (``slipd.sim.timeline``)."""
    physics: dict[str, Any] | None = None
    """The contact model (``slipd.sim.contact_models``): ``{name: stick_slip | viscoelastic | stribeck, ...}``."""
    friction: Friction = Friction()
    pre_s: float = Field(0.3, ge=0.05)
    settle_s: float = Field(0.2, ge=0.0)

    @field_validator("physics")
    @classmethod
    def _physics_valid(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        if cm.build_model(value).engine:  # build_model raises ValueError naming the key and reason
            raise ValueError(f"name: {value['name']} runs engine scenes (family: engine)")
        return value

    @model_validator(mode="after")
    def _contact_motion_or_timeline(self) -> HexapodScene:
        if self.timeline is None and (self.contact is None or self.motion is None):
            raise ValueError("needs contact and motion, or a timeline")
        if self.timeline is not None and (self.contact is not None or self.motion is not None):
            raise ValueError("a timeline replaces contact and motion: give one or the other")
        return self

    def build_model(self) -> cm.ContactModel:
        """The scene's contact model (the default when none is named)."""
        return cm.build_model(self.physics)

    @property
    def kind(self) -> str:
        if self.timeline is not None:
            moves = [s for s in self.timeline if s.op == "move"]
            if any(m.stop_fraction is None for m in moves):
                return "slip"
            return "stop" if moves else "hold"
        return "stop" if self.motion.stop_fraction is not None else "slip"


class ObjectModel(_Model):
    name: str
    mass_kg: float = Field(..., gt=0.0, le=10.0)
    mu_s: float = Field(..., gt=0.0, le=3.0)
    mu_k: float = Field(..., gt=0.0, le=3.0)
    size_mm: float = Field(60.0, gt=0.0)
    curvature_1_mm: float = Field(0.0, ge=0.0, le=0.2)
    """1 / radius of the contact surface (0 = flat); applied by the ``curvature`` effect."""
    com_offset_mm: tuple[float, float] = (0.0, 0.0)
    """Centre of mass relative to the grasp centre; its torque is applied by ``offcenter_torque``."""

    @model_validator(mode="after")
    def _kinetic_below_static(self) -> ObjectModel:
        if self.mu_k > self.mu_s:
            raise ValueError("mu_k must be <= mu_s")
        return self


class Grip(_Model):
    force_n: float = Field(..., ge=0.0, le=100.0)
    close_s: float = Field(0.3, gt=0.0)


class GripMotion(_Model):
    kind: Literal["lift", "push", "hold"] = "lift"
    level: Literal["low", "medium", "high"] | None = "medium"
    speed_mm_s: float | None = Field(None, ge=0.0, le=500.0)
    accel_mm_s2: float | None = Field(None, gt=0.0, le=5000.0)
    direction_deg: float | None = None
    """Direction of the arm's motion in the sensor plane; default up (+90) to lift, +0 to push."""
    push_resist_n: float = Field(2.0, ge=0.0)
    """Push: drag of the table on the object, opposing the motion."""

    def speed_accel(self) -> tuple[float, float]:
        """(speed mm/s, acceleration mm/s^2): explicit values win over the level."""
        v, a = UR_LEVELS[self.level] if self.level else (10.0, 50.0)
        return (self.speed_mm_s if self.speed_mm_s is not None else v,
                self.accel_mm_s2 if self.accel_mm_s2 is not None else a)


class GripperScene(_SceneBase):
    family: Literal["gripper"] = "gripper"
    sensor: Literal["v1", "v2"] = "v2"
    object: ObjectModel
    grip: Grip
    motion: GripMotion = GripMotion()
    trial: Literal["slip", "stop"] = "slip"
    """``stop``: a secure-grip trial, labelled 0 throughout (the method's stop trials)."""
    rigid_kt_n_mm: float = Field(30.0, gt=0.0)

    @property
    def kind(self) -> str:
        return self.trial


Scene = Annotated[HexapodScene | GripperScene | EngineScene, Field(discriminator="family")]


class _SceneDoc(_Model):
    scene: Scene


def _format_error(source: str, exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        keys = [str(x) for x in err["loc"][1:]]
        loc = ".".join(x for x in keys if x not in ("hexapod", "gripper", "engine"))
        msg = err["msg"].removeprefix("Value error, ")
        for long, short in (("Input should be greater than or equal to", "must be >="),
                            ("Input should be less than or equal to", "must be <="),
                            ("Input should be greater than", "must be >"), ("Input should be less than", "must be <")):
            msg = msg.replace(long, short)
        parts.append(f"{source}: {loc or '(top)'}: {msg}")
    return "; ".join(parts)


def parse_scene(data: Any, source: str = "scene") -> HexapodScene | GripperScene:
    """Validate a scene dict. Raises SceneError("<source>: <key.path>: <reason>")."""
    if not isinstance(data, dict):
        raise SceneError(f"{source}: a scene must be a mapping, got {type(data).__name__}")
    if "family" not in data:
        raise SceneError(f"{source}: family: required (hexapod, gripper or engine)")
    try:
        return _SceneDoc(scene=data).scene
    except ValidationError as exc:
        raise SceneError(_format_error(source, exc)) from None


def load_scene(path: str | Path) -> HexapodScene | GripperScene:
    """Read and validate a scene YAML file."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise SceneError(f"{path.name}: cannot read ({exc})") from exc
    except yaml.YAMLError as exc:
        raise SceneError(f"{path.name}: not valid YAML ({exc})") from exc
    return parse_scene(data, path.name)


# ---------------------------------------------------------------------------- kinematics
def ramp_progress(n: int, start: int, ramp_s: float, stop_index: int | None = None) -> np.ndarray:
    """Normalised progress q (seconds at cruise speed) of a trapezoidal move; [n].

    The speed ramps linearly from 0 to 1 over ``ramp_s`` from sample ``start``; from ``stop_index``
    it ramps down at the same rate to rest.
    """
    k = np.arange(n)
    tau = np.maximum(k - start, 0) * DT_S
    speed = np.minimum(tau / ramp_s, 1.0) if ramp_s > 0 else (tau > 0).astype(float)
    if stop_index is not None and stop_index < n:
        v0 = speed[stop_index]
        down = np.maximum(v0 - np.maximum(k - stop_index, 0) * DT_S / max(ramp_s, DT_S), 0.0)
        speed = np.where(k >= stop_index, down, speed)
    return np.cumsum(speed) * DT_S


def _stop_index_for(q: np.ndarray, ramp_s: float, target_q: float, start: int) -> int:
    """Last sample from which ramping down still ends at or before progress ``target_q``."""
    speed = np.gradient(q) / DT_S
    final = q + speed**2 * max(ramp_s, DT_S) / 2.0
    ok = np.nonzero(final[start:] <= target_q)[0]
    return start + (int(ok[-1]) if len(ok) else 0)


def _hex_layout(sc: HexapodScene) -> tuple[int, int, int]:
    pre = round(sc.pre_s / DT_S)
    press = round(sc.contact.press_s / DT_S)
    start = pre + press + round(sc.settle_s / DT_S)
    return pre, press, start


def _hex_ramp_s(m: HexMotion) -> float:
    # Rotations ramp so that a tip 7 mm from the centre sees the scene's acceleration.
    if m.kind == "rotation":
        return float(np.deg2rad(abs(m.rot_speed_deg_s))) * 7.0 / m.accel_mm_s2
    return m.speed_mm_s / m.accel_mm_s2


def _hex_context(sc: HexapodScene, n: int, stop_index: int | None) -> fx.SimContext:
    pre, press, start = _hex_layout(sc)
    m = sc.motion
    k = np.arange(n)
    ramp = np.clip((k - pre) / max(press, 1), 0.0, 1.0)
    depth = sc.contact.depth_mm * ramp * ramp * (3 - 2 * ramp)  # smooth press, no jerk at the ends
    q = ramp_progress(n, start, _hex_ramp_s(m), stop_index)
    v = m.speed_mm_s if m.kind != "rotation" else 0.0
    w = np.deg2rad(m.rot_speed_deg_s) if m.kind != "translation" else 0.0
    d = np.deg2rad(m.direction_deg)
    trans = (v * q)[:, None] * np.array([np.cos(d), np.sin(d)])
    th = w * q
    c = np.asarray(m.centre_mm, np.float64)
    # Rotation about point c: T = c + trans - R(th) c.
    rc = np.stack([np.cos(th) * c[0] - np.sin(th) * c[1], np.sin(th) * c[0] + np.cos(th) * c[1]], 1)
    ctx = fx.SimContext(family="hexapod", n=n, t_s=k * DT_S, motion_start=start)
    ctx.pose_t, ctx.pose_th, ctx.depth = c + trans - rc, th, depth
    return ctx


def _considered(kind: str, fz_at_start: np.ndarray) -> np.ndarray:
    return considered_pillars(fz_at_start, rotation=kind == "rotation")


# ---------------------------------------------------------------------------- generation
def _seed_of(scene: HexapodScene | GripperScene, seed: int | None) -> int:
    return int(seed if seed is not None else scene.seed if scene.seed is not None else 0)


def generate(scene: HexapodScene | GripperScene, seed: int | None = None) -> Recording:
    """Simulate one scene. Deterministic for (scene, seed); seed defaults to ``scene.seed`` or 0."""
    return generate_batch([scene], [seed])[0]


def generate_batch(scenes: list[HexapodScene | GripperScene], seeds: list[int | None] | None = None) -> list[Recording]:
    """Simulate many scenes at once (one vectorised time loop per family and sensor)."""
    seeds = [None] * len(scenes) if seeds is None else list(seeds)
    if len(seeds) != len(scenes):
        raise ValueError(f"{len(scenes)} scenes but {len(seeds)} seeds")
    out: list[Recording | None] = [None] * len(scenes)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, sc in enumerate(scenes):
        family = "timeline" if isinstance(sc, HexapodScene) and sc.timeline is not None else sc.family
        groups.setdefault((family, sc.sensor), []).append(i)
    for (family, _), idx in groups.items():
        if family == "engine":
            from functools import partial

            from slipd.sim.engine.generate import Rules, generate_engine  # imports MuJoCo (the sim extra)

            run = partial(generate_engine, rules=Rules(_finish, incipient_labels, GROSS_MM, GROSS_DEG))
        else:
            run = {"hexapod": _generate_hexapod, "gripper": _generate_gripper, "timeline": _generate_timeline}[family]
        for i, rec in zip(idx, run([scenes[i] for i in idx], [_seed_of(scenes[i], seeds[i]) for i in idx])):
            out[i] = rec
    return out  # type: ignore[return-value]


def _pad(a: np.ndarray, n: int) -> np.ndarray:
    """Hold the last value up to length n (physics is causal, so trimming afterwards is exact)."""
    if len(a) >= n:
        return a[:n]
    return np.concatenate([a, np.repeat(a[-1:], n - len(a), axis=0)])


def _run_hex_contexts(sensor_name: str, scenes: list[HexapodScene], ctxs: list[fx.SimContext],
                      seeds: list[int]) -> list[dict]:
    """Physics of hexapod contexts: the default model through ``run_hexapod`` (bit-identical to before the
    registry), every other family through ``contact_models.run_general``."""
    models = [sc.build_model() for sc in scenes]
    default = [i for i, m in enumerate(models) if m.default_path]
    other = [i for i, m in enumerate(models) if not m.default_path]
    out: list[dict | None] = [None] * len(scenes)
    if default:
        res = _run_hex_default(sensor_name, [scenes[i] for i in default], [ctxs[i] for i in default])
        for i, r in zip(default, res):
            out[i] = r
    if other:
        res = _run_hex_general(sensor_name, [scenes[i] for i in other], [ctxs[i] for i in other],
                               [models[i] for i in other], [seeds[i] for i in other])
        for i, r in zip(other, res):
            out[i] = r
    return out  # type: ignore[return-value]


def _run_hex_general(sensor_name: str, scenes: list[HexapodScene], ctxs: list[fx.SimContext],
                     models: list[cm.ContactModel], seeds: list[int]) -> list[dict]:
    sensor = sensor_params(sensor_name)
    n = max(c.n for c in ctxs)
    spread = [cm.pillar_spread(m, s) for m, s in zip(models, seeds)]
    coefs = [m.coefficients() for m in models]
    res = cm.run_general(
        sensor,
        np.stack([_pad(c.pose_t, n) for c in ctxs], 1),
        np.stack([_pad(c.pose_th, n) for c in ctxs], 1),
        np.stack([_pad(c.depth, n) for c in ctxs], 1),
        np.stack([s.friction.mu_s * p["mu"] for s, p in zip(scenes, spread)]),
        np.stack([s.friction.mu_k * p["mu"] for s, p in zip(scenes, spread)]),
        np.stack([c.contact_offset + p["height_mm"] for c, p in zip(ctxs, spread)]),
        np.stack([c.contact_mask for c in ctxs]),
        np.stack([p["kt"] for p in spread]),
        {k: np.array([c[k] for c in coefs], np.float64) for k in coefs[0]},
    )
    out = []
    for b, c in enumerate(ctxs):
        fz = res["fz"][: c.n, b]
        force = np.concatenate([res["ft"][: c.n, b], fz[..., None]], -1)
        disp = np.concatenate([res["u"][: c.n, b], res["c"][: c.n, b, :, None]], -1)
        out.append({"force": force, "disp": disp, "slip": res["slip"][: c.n, b]})
    return out


def _run_hex_default(sensor_name: str, scenes: list[HexapodScene], ctxs: list[fx.SimContext]) -> list[dict]:
    sensor = sensor_params(sensor_name)
    n = max(c.n for c in ctxs)
    res = run_hexapod(
        sensor,
        np.stack([_pad(c.pose_t, n) for c in ctxs], 1),
        np.stack([_pad(c.pose_th, n) for c in ctxs], 1),
        np.stack([_pad(c.depth, n) for c in ctxs], 1),
        np.array([s.friction.mu_s for s in scenes]),
        np.array([s.friction.mu_k for s in scenes]),
        np.stack([c.contact_offset for c in ctxs]),
        np.stack([c.contact_mask for c in ctxs]),
    )
    out = []
    for b, c in enumerate(ctxs):
        force, disp = pillar_outputs(res["u"][: c.n, b], res["c"][: c.n, b], res["fz"][: c.n, b], sensor)
        out.append({"force": force, "disp": disp, "slip": res["slip"][: c.n, b]})
    return out


def _generate_hexapod(scenes: list[HexapodScene], seeds: list[int]) -> list[Recording]:
    sensor_name = scenes[0].sensor
    effects = [sc.build_effects() for sc in scenes]

    def contexts(ids: list[int], stops: list[int | None], lengths: list[int]) -> list[fx.SimContext]:
        ctxs = []
        for i in ids:
            ctx = _hex_context(scenes[i], lengths[i], stops[i])
            fx.run_stage("contact", effects[i], ctx, seeds[i])
            fx.run_stage("motion", effects[i], ctx, seeds[i])
            ctxs.append(ctx)
        return ctxs

    full = [round(sc.duration_s / DT_S) for sc in scenes]
    ctxs = contexts(list(range(len(scenes))), [None] * len(scenes), full)
    phys = _run_hex_contexts(sensor_name, scenes, ctxs, seeds)
    # Stop scenes: find where the first considered pillar would slip, then re-run halting before it.
    stop_ids = [i for i, sc in enumerate(scenes) if sc.kind == "stop"]
    if stop_ids:
        stops: list[int | None] = [None] * len(scenes)
        lengths = list(full)
        for i in stop_ids:
            sc, ctx = scenes[i], ctxs[i]
            cons = _considered(sc.motion.kind, phys[i]["force"][ctx.motion_start, :, 2])
            _, onset, _ = incipient_labels(phys[i]["slip"], cons, ctx.motion_start)
            ramp = _hex_ramp_s(sc.motion)
            q = ramp_progress(full[i], ctx.motion_start, ramp)
            target = sc.motion.stop_fraction * (q[onset] if onset is not None else q[-1])
            stops[i] = _stop_index_for(q, ramp, target, ctx.motion_start)
            settle = round(ramp / DT_S) + 1
            lengths[i] = min(full[i], stops[i] + settle + round(sc.motion.hold_s / DT_S))
        sub = [scenes[i] for i in stop_ids]
        sub_ctx = contexts(stop_ids, stops, lengths)
        sub_res = _run_hex_contexts(sensor_name, sub, sub_ctx, [seeds[i] for i in stop_ids])
        for i, ctx, res in zip(stop_ids, sub_ctx, sub_res):
            ctxs[i], phys[i] = ctx, res
            ctx.meta["motion_stop_index"] = stops[i]
    recs = []
    sensor = sensor_params(sensor_name)
    for sc, eff, seed, ctx, res in zip(scenes, effects, seeds, ctxs, phys):
        motion = np.concatenate([ctx.pose_t, np.rad2deg(ctx.pose_th)[:, None]], 1)
        recs.append(_finish(sc, eff, seed, ctx, res, motion, sensor.to_dict(), sc.motion.kind))
    return recs


def _finish(sc: HexapodScene | GripperScene, eff: list[fx.Effect], seed: int, ctx: fx.SimContext, res: dict,
            motion: np.ndarray, sensor: dict, motion_type: str, gross_motion: int | None = None,
            labels: tuple[np.ndarray, int | None, int | None] | None = None) -> Recording:
    """Labels, signal effects, saturation, meta: physics output -> Recording."""
    n, start = ctx.n, ctx.motion_start
    slip = res["slip"]
    fz0 = res["force"][start, :, 2] if start is not None and start < n else np.zeros(N_PILLARS)
    if labels is not None:
        label, onset, gross = labels
    elif sc.kind == "stop":
        label, onset, gross = np.zeros(n, np.uint8), None, None
    else:
        label, onset, gross = incipient_labels(slip, _considered(motion_type, fz0), start, gross_motion)
    ctx.force = np.array(res["force"], np.float64)
    model = sc.build_model() if isinstance(sc, HexapodScene) else None
    if model is not None:
        ctx.force = cm.apply_calibration(model, seed, ctx.force)  # the sensor's error, not the truth's
    fx.run_stage("signal", eff, ctx, seed)
    disp = measured_disp(res["disp"], res["force"], ctx.force, sensor_params(sc.sensor))
    force = saturate(ctx.force, sensor_params(sc.sensor))
    fx.run_stage("meta", eff, ctx, seed)
    events: dict[str, float] = {"motion_start": start * DT_S} if start is not None else {}
    stop_index = ctx.meta.pop("motion_stop_index", None)
    if stop_index is not None:
        events["motion_stop"] = stop_index * DT_S
    if onset is not None:
        events["onset"] = onset * DT_S
    if gross is not None:
        events["gross_slip"] = gross * DT_S
    if gross_motion is not None:
        events["gross_motion"] = gross_motion * DT_S
    pre = round(sc.pre_s / DT_S)
    meta = dict(ctx.meta)
    dump = sc.model_dump(mode="json")
    for key in ("timeline", "physics"):  # scenes without them keep the meta they always had
        if dump.get(key, 0) is None:
            dump.pop(key)
    meta.update({
        "generator": GENERATOR_VERSION,
        "scene": dump,
        "seed": int(seed),
        "sensor": sensor,
        "effects": [e.name for e in eff],
        "kind": sc.kind,
        "family": sc.family,
        "motion": motion_type,
        "events": events,
        "tare_samples": [min(20, pre - 1), pre],
    })
    if model is not None and sc.physics is not None:
        meta["physics"] = {"name": model.name, **model.p.model_dump(mode="json")}
    return Recording(
        t_us=np.arange(n, dtype=np.int64) * 1000,
        force=force.astype(np.float32),
        disp=disp.astype(np.float32),
        slip=slip,
        label=label,
        object_motion=motion.astype(np.float32),
        meta=meta,
    )


# ---------------------------------------------------------------------------- timelines
def _timeline_context(sc: HexapodScene, stops: dict[int, int]) -> tuple[fx.SimContext, tl.Built]:
    built = tl.build(sc.timeline, round(sc.pre_s / DT_S), stops)
    depth, pose_t, pose_th = tl.arrays(built)
    n = len(depth)
    start = built.moves[0]["start"] if built.moves else None
    ctx = fx.SimContext(family="hexapod", n=n, t_s=np.arange(n) * DT_S, motion_start=start)
    ctx.pose_t, ctx.pose_th, ctx.depth = pose_t, pose_th, depth
    return ctx, built


def _generate_timeline(scenes: list[HexapodScene], seeds: list[int]) -> list[Recording]:
    """Timeline scenes: probe runs resolve the stop moves one by one, then the final run and its labels."""
    sensor_name = scenes[0].sensor
    effects = [sc.build_effects() for sc in scenes]
    stops: list[dict[int, int]] = [{} for _ in scenes]

    def contexts(ids: list[int]) -> tuple[list[fx.SimContext], list[tl.Built]]:
        ctxs, builts = [], []
        for i in ids:
            ctx, built = _timeline_context(scenes[i], stops[i])
            fx.run_stage("contact", effects[i], ctx, seeds[i])
            fx.run_stage("motion", effects[i], ctx, seeds[i])
            ctxs.append(ctx)
            builts.append(built)
        return ctxs, builts

    onset_q: list[dict[int, tuple[float | None, float]]] = [{} for _ in scenes]
    todo = list(range(len(scenes)))
    while True:
        ctxs, builts = contexts(todo)
        probing = [j for j, b in enumerate(builts) if b.probe is not None]
        if not probing:
            break
        sub = [todo[j] for j in probing]
        res = _run_hex_contexts(sensor_name, [scenes[i] for i in sub], [ctxs[j] for j in probing],
                                [seeds[i] for i in sub])
        for i, j, r in zip(sub, probing, res):
            b = builts[j]
            mv = b.moves[-1]
            seg = scenes[i].timeline[b.probe]
            cons = _considered(seg.kind, r["force"][mv["start"], :, 2])
            _, onset, _ = incipient_labels(r["slip"], cons, mv["start"])
            q = tl.probe_progress(seg)
            onset_q[i][b.probe] = (q[onset - mv["start"]] if onset is not None else None, q[-1])
            stops[i][b.probe] = tl.stop_samples(seg, *onset_q[i][b.probe])
    ctxs, builts = contexts(list(range(len(scenes))))
    phys = _run_hex_contexts(sensor_name, scenes, ctxs, seeds)
    # A stop must not slip: where a pillar still slid during a stop move (a family whose neighbouring tips
    # or decelerating plate push it over), halt that move earlier (80 % of its travel) and run again.
    for attempt in range(4):
        redo = []
        for i, b in enumerate(builts):
            for mv in b.moves:
                if mv["stop"] and phys[i]["slip"][mv["start"]: mv["end"]].any():
                    seg = scenes[i].timeline[mv["segment"]]
                    oq, qe = onset_q[i][mv["segment"]]
                    scale = 0.8 ** (attempt + 1)
                    stops[i][mv["segment"]] = tl.stop_samples(seg, oq * scale if oq is not None else None, qe * scale)
                    redo.append(i)
        redo = sorted(set(redo))
        if not redo:
            break
        sub_ctx, sub_built = contexts(redo)
        sub_res = _run_hex_contexts(sensor_name, [scenes[i] for i in redo], sub_ctx, [seeds[i] for i in redo])
        for i, c, b, r in zip(redo, sub_ctx, sub_built, sub_res):
            ctxs[i], builts[i], phys[i] = c, b, r
    sensor = sensor_params(sensor_name)
    recs = []
    for sc, eff, seed, ctx, b, res in zip(scenes, effects, seeds, ctxs, builts, phys):
        labels, extra = _timeline_labels(b, res)
        motion = np.concatenate([ctx.pose_t, np.rad2deg(ctx.pose_th)[:, None]], 1)
        if b.moves and b.moves[0]["stop_index"] is not None:
            ctx.meta["motion_stop_index"] = b.moves[0]["stop_index"]
        kinds = sorted({m["kind"] for m in b.moves})
        mtype = "+".join(kinds) if kinds else "none"
        rec = _finish(sc, eff, seed, ctx, res, motion, sensor.to_dict(), mtype, labels=labels)
        rec.meta["timeline"] = {
            "starts_in_contact": b.starts_in_contact,
            "segments": [{"op": s["op"], "start_s": s["start"] * DT_S, "end_s": s["end"] * DT_S} for s in b.segments],
            "moves": extra,
        }
        if b.starts_in_contact:
            # Started mid-grasp: the stretch before the first event is loaded. The sensor zeroed itself while
            # unloaded, before the recording (its bias command), so the offset is 0, which [0, 0] says.
            rec.meta["tare_samples"] = [0, 0]
        recs.append(rec)
    return recs


def _timeline_labels(b: tl.Built, res: dict) -> tuple[tuple[np.ndarray, int | None, int | None], list[dict]]:
    """Union of the incipient-slip labels of every non-stop move, each within its own window."""
    slip = res["slip"]
    label = np.zeros(len(slip), np.uint8)
    first: tuple[int | None, int | None] = (None, None)
    extra = []
    for mv in b.moves:
        end = mv["end"]  # each move is labelled from its start until the plate is at rest again
        item = {"kind": mv["kind"], "stop": mv["stop"], "start_s": mv["start"] * DT_S, "end_s": mv["end"] * DT_S}
        if mv["stop"]:
            item["stop_s"] = mv["stop_index"] * DT_S if mv["stop_index"] is not None else None
            # From its start until at rest: pillars the labels consider (in contact at the start), and any other
            # (a barely touching tip below the contact threshold may slide under a stop).
            cons = _considered(mv["kind"], res["force"][mv["start"], :, 2])
            item["truth_slip"] = bool(slip[mv["start"]: mv["end"], cons].any())
            item["light_contact_slip"] = bool(slip[mv["start"]: mv["end"], ~cons].any())
        else:
            cons = _considered(mv["kind"], res["force"][mv["start"], :, 2])
            lab, onset, gross = incipient_labels(slip[:end], cons, mv["start"])
            label[: end] |= lab
            item["onset_s"] = onset * DT_S if onset is not None else None
            item["gross_slip_s"] = gross * DT_S if gross is not None else None
            if first == (None, None) and onset is not None:
                first = (onset, gross)
        extra.append(item)
    return (label, *first), extra


# ---------------------------------------------------------------------------- gripper
def _grip_context(sc: GripperScene) -> fx.SimContext:
    n = round(sc.duration_s / DT_S)
    pre = round(sc.pre_s / DT_S)
    close = round(sc.grip.close_s / DT_S)
    start = pre + close + round(sc.settle_s / DT_S)
    k = np.arange(n)
    ctx = fx.SimContext(family="gripper", n=n, t_s=k * DT_S, motion_start=min(start, n - 1))
    ramp = np.clip((k - pre) / max(close, 1), 0.0, 1.0)
    ctx.grip = sc.grip.force_n * ramp
    m = sc.motion
    v, a = m.speed_accel()
    direction = m.direction_deg if m.direction_deg is not None else (90.0 if m.kind == "lift" else 0.0)
    unit = np.array([np.cos(np.deg2rad(direction)), np.sin(np.deg2rad(direction))])
    accel = np.zeros(n)
    if m.kind != "hold" and v > 0:
        ramp_n = round(v / a / DT_S)
        accel[start: start + ramp_n] = a
    ctx.accel = accel[:, None] * unit
    ctx.gravity = np.zeros((n, 2))
    if m.kind == "push":
        # Table drag opposes the push; it builds up over the first millimetre of arm travel (the
        # compliant contacts load first), expressed as a load per unit mass.
        travel = np.cumsum(np.cumsum(accel) * DT_S) * DT_S
        share = np.clip(travel / 1.0, 0.0, 1.0)
        ctx.gravity = ctx.gravity - (m.push_resist_n / sc.object.mass_kg * 1e3) * share[:, None] * unit
    ctx.com_offset = np.zeros(2)
    ctx.object_com_offset = tuple(sc.object.com_offset_mm)
    ctx.curvature_1_mm = sc.object.curvature_1_mm
    return ctx


gripper_context = _grip_context
"""Public name of the gripper scene's input profiles (grip, arm acceleration, loads) before physics;
the closed-loop rig builds its stepper from it."""


def _generate_gripper(scenes: list[GripperScene], seeds: list[int]) -> list[Recording]:
    sensor = sensor_params(scenes[0].sensor)
    effects = [sc.build_effects() for sc in scenes]
    ctxs = []
    for sc, eff, seed in zip(scenes, effects, seeds):
        ctx = _grip_context(sc)
        for stage in ("contact", "motion", "load"):
            fx.run_stage(stage, eff, ctx, seed)
        ctxs.append(ctx)
    n = max(c.n for c in ctxs)
    b = len(scenes)
    objs = [ObjectParams(sc.object.mass_kg, sc.object.mu_s, sc.object.mu_k, sc.object.size_mm, sc.rigid_kt_n_mm)
            for sc in scenes]
    offs = np.stack([c.contact_offset for c in ctxs])
    masks = np.stack([c.contact_mask for c in ctxs])
    stepper = GripperStepper(sensor, objs, b, offs, masks, np.array([c.table for c in ctxs]))
    grip = np.stack([_pad(c.grip, n) for c in ctxs], 1)  # [N, B]
    # Depth for every sample's grip force: the grip takes few distinct values (a ramp, then a hold),
    # so solve only those, per scene, with the same bisection the stepper uses.
    depth = np.empty_like(grip)
    for i in range(b):
        values, inverse = np.unique(grip[:, i], return_inverse=True)
        depth[:, i] = depth_for_total_force(values[:, None], sensor, offs[i], masks[i])[:, 0][inverse]
    accel = np.stack([_pad(c.accel, n) for c in ctxs], 1)
    load = np.stack([_pad(c.gravity, n) for c in ctxs], 1)
    com = np.stack([c.com_offset for c in ctxs])
    force = np.empty((n, b, N_PILLARS, 3))
    disp = np.empty((n, b, N_PILLARS, 3))
    slip = np.empty((n, b, N_PILLARS), bool)
    motion = np.empty((n, b, 3))
    for k in range(n):
        o = stepper.advance(grip[k], depth[k], accel[k], load[k], com)
        force[k], disp[k], slip[k], motion[k] = o.force, o.disp, o.slip, o.object_motion
    recs = []
    for i, (sc, eff, seed, ctx) in enumerate(zip(scenes, effects, seeds, ctxs)):
        res = {"force": force[: ctx.n, i], "disp": disp[: ctx.n, i], "slip": slip[: ctx.n, i]}
        mot = motion[: ctx.n, i] - motion[ctx.motion_start, i]  # relative to the grasp at lift-off
        gross_motion = None
        if sc.kind == "slip":
            big = (np.hypot(mot[:, 0], mot[:, 1]) > GROSS_MM) | (np.abs(mot[:, 2]) > GROSS_DEG)
            big[: ctx.motion_start] = False
            gross_motion = int(np.argmax(big)) if big.any() else None
        mtype = sc.motion.kind + ("_offcentre" if any(e.name == "offcenter_torque" for e in eff) else "")
        recs.append(_finish(sc, eff, seed, ctx, res, mot, sensor.to_dict(), mtype, gross_motion))
    return recs


def secure_grip_n(obj: ObjectModel, accel_mm_s2: float, safety: float = 1.5) -> float:
    """Grip force (N) that holds ``obj`` against gravity plus ``accel_mm_s2`` with a safety factor.

    Both contact sides carry friction (sensor pillars and rigid pad), each up to mu_s * grip.
    """
    load = obj.mass_kg * (9810.0 + accel_mm_s2) * 1e-3
    torque_arm = float(np.hypot(*obj.com_offset_mm))
    # The torsional capacity is weaker than the linear one: give off-centre objects more grip.
    return safety * load / (2 * obj.mu_s) * (1.0 + torque_arm / 20.0)


def contact_forces(depth_mm: float, sensor_name: str) -> np.ndarray:
    """Normal force per pillar (N) at a depth: a quick look-up for choosing scene parameters."""
    return normal_force(compression(np.asarray(depth_mm)), sensor_params(sensor_name))
