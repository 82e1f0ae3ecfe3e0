"""Engine scenes (``family: engine``): what a scene file says, validated; no MuJoCo import here.

A scene names the engine with ``physics: {name: mujoco, <solver settings>}`` (``model.EngineParams``) or
``{name: bullet, ...}`` (``model.BulletParams``: the same scene on a second engine), the object
(shape, mass, friction, size), the grasp's gravity (magnitude, direction in the sensor plane, tilt out of it) and
a timeline of segments run after ``pre_s`` with the grip open:

``{op: grip, force_n, duration_s}``      the grip force goes (smoothstep) from its current value to ``force_n``
                                         (closing, a regrasp, a press).
``{op: hold, duration_s}``               nothing changes.
``{op: lift, speed_mm_s, accel_mm_s2, distance_mm, direction_deg}``
                                         the arm moves the gripper (trapezoid: accelerate, cruise, decelerate
                                         over ``distance_mm``) in a direction of the sensor plane (default: against
                                         gravity). Until the first lift a table carries the object's weight; it
                                         hands the weight over to the grasp over the first ``liftoff_mm``.
``{op: push | twist | fill, rate, duration_s, direction_deg, stop_fraction}``
                                         a load on the object that grows at ``rate`` for ``duration_s`` and then
                                         stays: a push (N/s, in ``direction_deg``), a twist about the sensor normal
                                         (N mm/s), or a filling container (g/s of added mass, along gravity). With
                                         ``stop_fraction`` the load stops growing at that fraction of the load at
                                         which the first pillar would slip (a probe run finds it): a stop near the
                                         stick limit, never labelled.

Truth and labels: per-pillar slip from the engine's contact sliding speeds; every lift and load segment is labelled
on its own by the method's rule (``scene.incipient_labels``: from the first slipping pillar among those in contact
at the segment's start until all of them slide or the object has moved 2 mm / 2 deg), from its start until the next
segment of that kind; the recording's label is their union and its kind ``slip`` when any segment slipped, else
``stop``. Only ``signal`` and ``meta`` effects apply (the measurement chain): the engine itself decides contact,
motion and loads.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from slipd.sim import contact_models as cm
from slipd.sim import effects as fx
from slipd.sim.engine.model import SHAPES, BulletParams, EngineParams

ENGINE_NAME = "mujoco"
ENGINE_NAMES = ("mujoco", "bullet")


class _P(BaseModel):
    model_config = ConfigDict(extra="forbid")


class EngineObject(_P):
    shape: Literal["box", "cylinder_across", "cylinder_along", "sphere", "edge"] = "box"
    mass_kg: float = Field(..., gt=0.0, le=10.0)
    mu: float = Field(..., gt=0.0, le=3.0)
    """Friction of the pillar tips on the object (the engine has one coefficient: static = kinetic)."""
    size_mm: float = Field(60.0, ge=10.0, le=300.0)
    """Box / edge: the side of the face against the sensor; cylinder: its length."""
    radius_mm: float = Field(20.0, ge=3.0, le=200.0)
    """Cylinder / sphere: radius; box / edge: half its depth between the fingers."""
    edge_mm: float = Field(0.0, ge=-9.0, le=9.0)
    """Edge: where the box's edge lies across the array (x, mm)."""
    offset_mm: tuple[float, float] = (0.0, 0.0)
    """Where the object's centre sits over the array (a sphere between two pillars loads both)."""
    jaw_mu: float | None = Field(None, gt=0.0, le=3.0)
    """Friction of the jaw's pad on the object (default: ``mu``)."""
    jaw_kt_n_mm: float = Field(20.0, gt=0.0, le=500.0)


class EngineGravity(_P):
    g_m_s2: float = Field(9.81, ge=0.0, le=30.0)
    direction_deg: float = -90.0
    """Direction of gravity in the sensor plane (-90: along -y)."""
    out_of_plane_deg: float = Field(0.0, ge=-89.0, le=89.0)
    """Tilt out of the sensor plane: positive pulls the object towards the jaw, negative onto the sensor."""


class GripSeg(_P):
    op: Literal["grip"]
    force_n: float = Field(..., ge=0.0, le=60.0)
    duration_s: float = Field(0.3, gt=0.0, le=60.0)


class HoldSeg(_P):
    op: Literal["hold"]
    duration_s: float = Field(..., gt=0.0, le=600.0)


class LiftSeg(_P):
    op: Literal["lift"]
    speed_mm_s: float = Field(10.0, gt=0.0, le=1000.0)
    accel_mm_s2: float = Field(50.0, gt=0.0, le=20000.0)
    distance_mm: float = Field(20.0, gt=0.0, le=1000.0)
    direction_deg: float | None = None
    """Direction of the arm's motion in the sensor plane; default: against gravity."""
    liftoff_mm: float = Field(0.5, gt=0.0, le=20.0)


class LoadSeg(_P):
    op: Literal["push", "twist", "fill"]
    rate: float = Field(..., gt=0.0, le=100000.0)
    """N/s (push), N mm/s (twist) or g/s (fill)."""
    duration_s: float = Field(..., gt=0.0, le=60.0)
    direction_deg: float = 0.0
    """Push: its direction in the sensor plane; twist: +1 counter-clockwise when >= 0 else clockwise."""
    stop_fraction: float | None = Field(None, gt=0.0, lt=1.0)


Segment = Annotated[GripSeg | HoldSeg | LiftSeg | LoadSeg, Field(discriminator="op")]
MOVE_OPS = ("lift", "push", "twist", "fill")


class EngineScene(_P):
    family: Literal["engine"] = "engine"
    name: str = "engine_scene"
    sensor: Literal["v1", "v2"] = "v2"
    physics: dict[str, Any] = Field(default_factory=lambda: {"name": ENGINE_NAME})
    """``{name: mujoco, <EngineParams>}`` or ``{name: bullet, <BulletParams>}``."""
    object: EngineObject
    gravity: EngineGravity = EngineGravity()
    pre_s: float = Field(0.3, ge=0.05)
    timeline: list[Segment] = Field(..., min_length=1)
    effects: list[dict[str, Any]] = Field(default_factory=list)
    seed: int | None = None

    @field_validator("physics")
    @classmethod
    def _physics_valid(cls, value: dict[str, Any]) -> dict[str, Any]:
        engine_params(value)
        return value

    @field_validator("effects")
    @classmethod
    def _effects_valid(cls, value: list[dict[str, Any]]) -> list[dict[str, Any]]:
        for i, spec in enumerate(value):
            e = fx.build_effect(spec, where=str(i))
            if e.stage not in ("signal", "meta"):
                raise ValueError(f"{i}.name: {e.name} acts on the {e.stage} stage; the engine decides contact, "
                                 "motion and loads itself (only signal and meta effects apply)")
        return value

    @model_validator(mode="after")
    def _one_stop(self) -> EngineScene:
        if sum(isinstance(s, LoadSeg) and s.stop_fraction is not None for s in self.timeline) > 1:
            raise ValueError("timeline: at most one load segment may have a stop_fraction")
        return self

    def build_effects(self) -> list[fx.Effect]:
        return [fx.build_effect(s, f"effects.{i}") for i, s in enumerate(self.effects)]

    def engine_params(self) -> EngineParams | BulletParams:
        return engine_params(self.physics)

    @property
    def kind(self) -> str:
        """The designed kind (the truth decides the recording's: ``generate`` sets ``slip`` if any segment slid)."""
        loads = [s for s in self.timeline if s.op in MOVE_OPS]
        return "stop" if loads else "hold"


def engine_params(spec: dict[str, Any]) -> EngineParams | BulletParams:
    """The solver settings of a ``physics`` entry naming an engine; ValueError naming the key otherwise."""
    model = cm.build_model(spec)
    if not model.engine:
        raise ValueError(f"physics.name: engine scenes run on one of {ENGINE_NAMES}, not {model.name!r}")
    assert isinstance(model.p, EngineParams | BulletParams)
    return model.p


__all__ = ["ENGINE_NAME", "ENGINE_NAMES", "MOVE_OPS", "SHAPES", "EngineObject", "EngineScene", "engine_params"]
