"""slipd.sim.holding: the least grip that holds a rig object through the lift, open loop (the physics' bound on any
reaction policy)."""

from __future__ import annotations

import numpy as np

from slipd.sim.holding import holding_trial, least_holding_grip, lift_velocity
from slipd.sim.physics import DT_S
from slipd.sim.rig import LIFT_MM, SCENES
from slipd.sim.scene import load_scene


def test_the_lift_profile_travels_the_rigs_lift_within_its_speed_and_acceleration() -> None:
    v = lift_velocity(50.0, 200.0)
    assert abs(v.sum() * DT_S - LIFT_MM) < 0.1
    assert v.max() <= 50.0 + 1e-9 and np.abs(np.diff(v)).max() <= 200.0 * DT_S + 1e-9
    short = lift_velocity(500.0, 100.0, travel_mm=10.0)  # never reaches its speed: a triangle
    assert abs(short.sum() * DT_S - 10.0) < 0.1 and short.max() < 500.0


def test_an_under_gripped_object_slips_below_its_holding_grip_and_is_held_above_it() -> None:
    scene = load_scene(SCENES / "pringles_can_undergrip.yaml")
    tr, rot = holding_trial(scene, np.array([5.0, 40.0]))
    assert tr[0] > 5.0  # 5 N lets it slide away
    assert tr[1] < 0.5 and rot[1] < 0.5


def test_an_off_centre_weight_needs_grip_times_lever_arms() -> None:
    """The rig's off-centre coffee jar (4 mm) is held within the servo's 40 N; 15 mm out (generator slipd.sim/2) it
    turns at any grip up to 60 N: the contacts' lever arms are a few millimetres."""
    scene = load_scene(SCENES / "coffee_jar_offcentre.yaml")
    res = least_holding_grip(scene, max_n=60.0, step_n=5.0)
    assert res.least_n is not None and res.least_n <= 40.0
    far = scene.model_copy(update={"object": scene.object.model_copy(update={"com_offset_mm": (15.0, 0.0)})})
    res = least_holding_grip(far, max_n=60.0, step_n=10.0)
    assert res.least_n is None and res.rotation_deg[-1] > 10.0
