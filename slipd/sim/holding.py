"""What grip holds an object through the rig's lift: the physics' own answer, with no detector and no reaction.

A reaction policy can only be as good as the grip the object needs allows. ``least_holding_grip`` runs a rig
scene's object through the rig's lift open loop (the rig's physics, ``GripperStepper``, with the table under the
object, the scene's UR speed and acceleration and ``LIFT_MM`` of travel, then a still hold) at a range of constant
grips at once (one batch), and returns the least grip from which on every grip keeps the object within the
tolerances. An off-centre object's weight twists the grasp; the pillars' and the rigid pad's lever arms are a few
millimetres, so its torque can need far more grip than its weight: where the least holding grip is above the
policy's force limit, no policy completes that lift without stopping the arm, and the object turns until the arm
stops (the table takes it back).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slipd.sim.physics import DT_S
from slipd.sim.rig import LIFT_MM, scene_physics
from slipd.sim.scene import GROSS_DEG, GROSS_MM, GripperScene

SETTLE_S = 0.3
"""Still grasp on the table before the lift (the grip's contact settles)."""


@dataclass(frozen=True)
class HoldingResult:
    """Open-loop lifts of one object at constant grips."""

    grips_n: np.ndarray
    translation_mm: np.ndarray
    """Object motion relative to the finger at the end of the hold, per grip."""
    rotation_deg: np.ndarray
    least_n: float | None
    """The least grip from which on every tried grip holds (None: none up to the largest tried)."""


def lift_velocity(speed_mm_s: float, accel_mm_s2: float, travel_mm: float = LIFT_MM) -> np.ndarray:
    """Finger speed per 1 ms sample of a trapezoidal ``movel`` (a triangle where the travel is short)."""
    t_acc = speed_mm_s / accel_mm_s2
    if accel_mm_s2 * t_acc**2 > travel_mm:  # never reaches the speed
        t_acc = float(np.sqrt(travel_mm / accel_mm_s2))
        speed_mm_s = accel_mm_s2 * t_acc
    t_cruise = (travel_mm - accel_mm_s2 * t_acc**2) / speed_mm_s
    t = np.arange(0.0, 2 * t_acc + t_cruise, DT_S)
    return np.minimum.reduce([accel_mm_s2 * t, np.full_like(t, speed_mm_s),
                              np.maximum(accel_mm_s2 * (2 * t_acc + t_cruise - t), 0.0)])


def holding_trial(scene: GripperScene, grips_n: np.ndarray, *, hold_s: float = 1.0, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(translation mm, rotation deg) at the end of an open-loop lift and hold, one per grip (one batch)."""
    grips = np.asarray(grips_n, np.float64)
    b = len(grips)
    _, ctx, st = scene_physics(scene, seed, b)
    load = np.broadcast_to(np.asarray(ctx.gravity[0], np.float64), (b, 2))
    com = np.broadcast_to(np.asarray(ctx.com_offset, np.float64), (b, 2))
    v, a = scene.motion.speed_accel()
    speed = np.concatenate([np.zeros(round(SETTLE_S / DT_S)), lift_velocity(v, a), np.zeros(round(hold_s / DT_S))])
    accel = np.zeros((b, 2))
    out = None
    prev = 0.0
    for vi in speed:
        accel[:, 1] = (vi - prev) / DT_S
        prev = vi
        out = st.step(grips, accel, load, com)
    assert out is not None
    motion = out.object_motion
    return np.hypot(motion[:, 0], motion[:, 1]), np.abs(motion[:, 2])


def least_holding_grip(scene: GripperScene, *, max_n: float = 60.0, step_n: float = 0.5, tol_mm: float = GROSS_MM,
                       tol_deg: float = GROSS_DEG, hold_s: float = 1.0, seed: int = 0) -> HoldingResult:
    """The least constant grip (to ``step_n``, up to ``max_n``) that lifts the scene's object and holds it within
    ``tol_mm`` and ``tol_deg`` (default: the labels' gross motion, 2 mm and 2 deg; a stuck contact's elastic
    twist alone can exceed half a degree); see the module docstring."""
    grips = np.arange(step_n, max_n + step_n / 2, step_n)
    tr, rot = holding_trial(scene, grips, hold_s=hold_s, seed=seed)
    held = (tr <= tol_mm) & (rot <= tol_deg)
    # The least grip from which on all hold (a grip that holds just by luck below a failing one does not count).
    failing = np.flatnonzero(~held)
    first = 0 if not len(failing) else failing[-1] + 1
    least = float(grips[first]) if first < len(grips) else None
    return HoldingResult(grips, tr, rot, least)
