"""The engine family's MuJoCo model, written as an MJCF string (no mujoco import here).

Frames and units: MuJoCo works in SI (m, kg, N, s); the model is built in the sensor frame, in which the
pillar bases lie in the plane z = 0 at ``slipd.geometry.PILLAR_XY_MM`` and the grasped object sits at +z. The
finger and the jaw do not move in this frame: the arm's motion enters as a pseudo-force on the object (a
translating frame adds a uniform acceleration), which ``stepping`` sets through the model's gravity.

* Nine pillar tips: bodies of ``TIP_MASS_KG`` on slide joints along x, y and z. The tangential joints are
  springs of the sensor's tangential stiffness (``SensorParams.kt_n_mm``); the normal joint has no spring here:
  ``stepping`` applies the sensor's non-linear normal law (``physics.normal_force``) as a joint force every
  step. Each tip is a sphere whose top lies ``HEIGHT_OFFSET_MM`` below the centre tip (corners 0.5 mm, edges
  0.2 mm), with the scene's friction (the tips' geom priority makes their friction the contact's).
* The jaw: a rigid plate on a slide joint along z above the object, pushed towards the sensor by a motor
  (the grip force).
* The object: a free body (box, cylinder across or along the finger, sphere, or a box whose edge lies over
  the array), starting just clear of the tips.
Solver settings that make friction stick (elliptic cones, a high impratio, noslip iterations, a stiff contact
time constant, a 0.25 ms step) come from ``EngineParams``; they were measured on this model
(``docs/engine.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from slipd.geometry import HEIGHT_OFFSET_MM, N_PILLARS, PILLAR_XY_MM
from slipd.sim.physics import SensorParams

TIP_MASS_KG = 0.001
TIP_RADIUS_MM = 1.0
TIP_DAMPING_N_S_M = 2.0
JAW_MASS_KG = 0.05
JAW_DAMPING_N_S_M = 30.0
PAD_MASS_KG = 0.005
PAD_DAMPING_N_S_M = 5.0
START_GAP_MM = 0.2
"""Clearance between the object and the centre tip before the grip closes."""

Shape = Literal["box", "cylinder_across", "cylinder_along", "sphere", "edge"]
SHAPES: tuple[str, ...] = ("box", "cylinder_across", "cylinder_along", "sphere", "edge")


class EngineParams(BaseModel):
    """Solver settings of the engine (a scene's ``physics: {name: mujoco, ...}``)."""

    model_config = ConfigDict(extra="forbid")

    timestep_ms: float = Field(0.25, gt=0.0, le=1.0)
    impratio: float = Field(100.0, ge=1.0)
    noslip_iterations: int = Field(20, ge=0, le=200)
    solref_s: float = Field(0.002, gt=0.0)
    """Contact time constant (about 8 steps: stiff enough for gram-scale tips, soft enough not to chatter)."""
    solimp: tuple[float, float, float] = (0.99, 0.999, 0.0001)
    cone: Literal["elliptic", "pyramidal"] = "elliptic"
    integrator: Literal["implicitfast", "Euler", "implicit", "RK4"] = "implicitfast"
    slip_speed_mm_s: float = Field(0.2, gt=0.0)
    """A tip slides when its contact's tangential relative speed exceeds this ..."""
    cone_fraction: float = Field(0.95, gt=0.0, le=1.0)
    """... while its friction force is at least this fraction of mu x normal (below it the motion is the contact's
    elastic give)."""
    min_slide_mm: float = Field(0.02, ge=0.0)
    """... and only an episode in which the tip slides at least this far counts. When the weight passes from the
    table to the grasp, the solver lets a loaded tip on its cone move a few micrometres and stick again; such a
    blip is far below what the sensor (0.005 N of tangential force per micrometre at most) or a camera on the tips
    resolves, and it ends by itself."""
    slide_gap_samples: int = Field(5, ge=0)
    """Sliding interrupted for at most this many samples is one episode (a tip on the cone's edge flickers)."""


class BulletParams(BaseModel):
    """Solver settings of the second engine, Bullet (a scene's ``physics: {name: bullet, ...}``; ``bullet``)."""

    model_config = ConfigDict(extra="forbid")

    timestep_ms: float = Field(0.2, gt=0.0, le=1.0)
    solver_iterations: int = Field(100, ge=1, le=1000)
    erp: float = Field(0.2, gt=0.0, le=1.0)
    slip_speed_mm_s: float = Field(0.2, gt=0.0)
    """A tip slides when its contact's tangential relative speed exceeds this ..."""
    cone_fraction: float = Field(0.95, gt=0.0, le=1.0)
    """... while its friction force is at least this fraction of mu x normal ..."""
    min_slide_mm: float = Field(0.02, ge=0.0)
    """... in an episode that carries it at least this far."""
    slide_gap_samples: int = Field(5, ge=0)


@dataclass(frozen=True)
class ObjectGeometry:
    """What the object is: its shape, size and mass, and the friction of its contacts."""

    shape: str
    mass_kg: float
    mu: float
    """Friction of the tips on the object."""
    size_mm: float
    """Box / edge: the side of its face against the sensor; cylinder: its length."""
    radius_mm: float
    """Cylinder / sphere radius; box / edge: half its depth away from the sensor."""
    edge_mm: float = 0.0
    """Edge: where the box's edge lies across the array (x, mm; the box covers x > edge_mm)."""
    jaw_mu: float = 1.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    jaw_kt_n_mm: float = 20.0
    """Tangential stiffness of the jaw's pad (a rubber pad on a rigid jaw): the grasp's load splits between the
    pad and the pillars by their stiffness, as it does on a real two-finger grasp."""


def _f(*v: float) -> str:
    return " ".join(f"{x:.9g}" for x in v)


def object_half_height_mm(obj: ObjectGeometry) -> float:
    """Distance from the object's centre to its face towards the sensor (along z)."""
    return obj.radius_mm


def object_geom(obj: ObjectGeometry) -> tuple[str, tuple[float, float, float]]:
    """The object's geom element (without the body) and its centre (mm) in the sensor frame at the start."""
    m = 1e-3
    h = object_half_height_mm(obj)
    z = h + START_GAP_MM
    common = f'mass="{obj.mass_kg:.9g}" contype="2" conaffinity="5" condim="3"'
    if obj.shape == "box":
        s = obj.size_mm / 2
        return f'<geom name="object" type="box" size="{_f(s * m, s * m, h * m)}" {common}/>', (0.0, 0.0, z)
    if obj.shape == "edge":
        s = obj.size_mm / 2
        return (f'<geom name="object" type="box" size="{_f(s * m, s * m, h * m)}" {common}/>',
                (obj.edge_mm + s, 0.0, z))
    if obj.shape == "sphere":
        return f'<geom name="object" type="sphere" size="{_f(h * m)}" {common}/>', (0.0, 0.0, z)
    # Cylinders: the geom's axis is its local z; turn it onto the sensor's x (across) or y (along).
    quat = "0.70710678 0 0.70710678 0" if obj.shape == "cylinder_across" else "0.70710678 0.70710678 0 0"
    return (f'<geom name="object" type="cylinder" size="{_f(h * m, obj.size_mm / 2 * m)}" quat="{quat}" {common}/>',
            (0.0, 0.0, z))


def build_mjcf(sensor: SensorParams, obj: ObjectGeometry, params: EngineParams) -> str:
    """The model of one scene as an MJCF string."""
    m = 1e-3
    ref = f'solref="{_f(params.solref_s, 1.0)}" solimp="{_f(*params.solimp)}"'
    kt = sensor.kt_n_mm * 1e3  # N/m
    tips = []
    for i in range(N_PILLARS):
        x, y = PILLAR_XY_MM[i]
        zc = -HEIGHT_OFFSET_MM[i] - TIP_RADIUS_MM
        tips.append(
            f'<body name="tip{i}" pos="{_f(x * m, y * m, zc * m)}" gravcomp="1">'
            f'<joint name="p{i}x" type="slide" axis="1 0 0" stiffness="{kt:.9g}" damping="{TIP_DAMPING_N_S_M}"/>'
            f'<joint name="p{i}y" type="slide" axis="0 1 0" stiffness="{kt:.9g}" damping="{TIP_DAMPING_N_S_M}"/>'
            f'<joint name="p{i}z" type="slide" axis="0 0 1" damping="{TIP_DAMPING_N_S_M}"/>'
            f'<geom name="tip{i}" type="sphere" size="{TIP_RADIUS_MM * m:.9g}" mass="{TIP_MASS_KG}" '
            f'friction="{obj.mu:.9g} 0 0" priority="1" contype="1" conaffinity="2" condim="3" {ref}/>'
            f'</body>')
    geom, (ox, oy, oz) = object_geom(obj)
    ox, oy = ox + obj.offset_mm[0], oy + obj.offset_mm[1]
    top = oz + object_half_height_mm(obj)
    jaw_h = 2.0
    kp = obj.jaw_kt_n_mm * 1e3
    return f"""<mujoco model="papillarray_engine">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{params.timestep_ms * 1e-3:.9g}" cone="{params.cone}" impratio="{params.impratio:.9g}"
          noslip_iterations="{params.noslip_iterations}" integrator="{params.integrator}" solver="Newton"
          gravity="0 0 0"/>
  <default><geom {ref}/></default>
  <worldbody>
    {''.join(tips)}
    <body name="object" pos="{_f(ox * m, oy * m, oz * m)}">
      <freejoint name="object"/>
      {geom}
    </body>
    <body name="jaw" pos="{_f(0.0, 0.0, (top + 2 * jaw_h + 1.0) * m)}" gravcomp="1">
      <joint name="jaw" type="slide" axis="0 0 1" damping="{JAW_DAMPING_N_S_M}"/>
      <geom type="box" size="{_f(0.03, 0.03, jaw_h * m)}" mass="{JAW_MASS_KG}" contype="0" conaffinity="0"/>
      <body name="pad" gravcomp="1">
        <joint name="padx" type="slide" axis="1 0 0" stiffness="{kp:.9g}" damping="{PAD_DAMPING_N_S_M}"/>
        <joint name="pady" type="slide" axis="0 1 0" stiffness="{kp:.9g}" damping="{PAD_DAMPING_N_S_M}"/>
        <geom name="jaw" type="box" size="{_f(0.03, 0.03, 0.5 * m)}" pos="{_f(0, 0, -(jaw_h + 0.5) * m)}"
              mass="{PAD_MASS_KG}" friction="{obj.jaw_mu:.9g} 0 0" priority="1" contype="4" conaffinity="2"
              condim="3"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="grip" joint="jaw" gear="1"/></actuator>
</mujoco>
"""


def tip_centres_mm() -> np.ndarray:
    """[9, 3] rest position of each tip sphere's centre (mm)."""
    return np.column_stack([PILLAR_XY_MM, -HEIGHT_OFFSET_MM - TIP_RADIUS_MM])
