"""The second engine (``slipd.sim.engine.bullet``, Bullet) against the same analytic cases as MuJoCo, and its scenes
end to end: a detector held out from one engine is tested on the other, so both must get the basics right."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pybullet")

import pybullet as pb

from slipd.sim import SceneError, generate, parse_scene
from slipd.sim.datasets import dataset_scenes
from slipd.sim.engine.bullet import BulletSim
from slipd.sim.engine.generate import object_geometry, profiles, simulate
from slipd.sim.physics import sensor_params

CORNERS, EDGES, CENTRE = [0, 2, 6, 8], [1, 3, 5, 7], 4


def _scene(obj: dict, timeline: list[dict], g: float = 0.0, **kw) -> dict:
    return {"family": "engine", "name": "t", "sensor": "v2", "gravity": {"g_m_s2": g}, "physics": {"name": "bullet"},
            "object": {"shape": "box", "mass_kg": 0.1, "mu": 0.5, "radius_mm": 10.0, **obj}, "timeline": timeline, **kw}


def test_one_pillar_slips_at_its_stick_limit():
    # A small sphere at a light grip touches the centre tip alone; a push grows until the tip slides.
    mu = 0.6
    sc = parse_scene(_scene({"shape": "sphere", "radius_mm": 5.0, "mu": mu},
                            [{"op": "grip", "force_n": 2.0, "duration_s": 0.2}, {"op": "hold", "duration_s": 0.1},
                             {"op": "push", "rate": 2.0, "duration_s": 1.5}]))
    prof = profiles(sc)
    out = simulate(sc, prof)
    start = prof.moves[0]["start"]
    assert out.contact_fn[start, CENTRE] == pytest.approx(2.0, rel=0.02)
    assert out.contact_fn[start, [*CORNERS, *EDGES]].max() == 0.0  # nothing else touches
    assert out.slip[:, CENTRE].any()
    onset = int(np.argmax(out.slip[:, CENTRE]))
    assert onset > start + 100
    # The solver's friction force reaches mu x normal just before the tip slides, and the sensor's forces (kt u over
    # the normal law) say the same within the tilt of the sphere-on-tip contact normal.
    solver = out.contact_ft[:, CENTRE] / np.maximum(out.contact_fn[:, CENTRE], 1e-9)
    before = start + int(np.argmax(solver[start:onset]))
    assert onset - before < 30
    assert solver[before] == pytest.approx(mu, rel=0.02)
    ratio = np.hypot(*out.force[before, CENTRE, :2]) / out.force[before, CENTRE, 2]
    assert ratio == pytest.approx(mu, rel=0.08)
    early = start + (onset - start) // 2
    assert not out.slip[start:early, CENTRE].any()
    assert np.hypot(*out.force[early, CENTRE, :2]) / out.force[early, CENTRE, 2] < 0.7 * mu


def test_a_held_object_balances_grip_and_weight():
    mass, grip = 0.3, 12.0
    sc = parse_scene(_scene({"mass_kg": mass, "mu": 0.8}, [
        {"op": "grip", "force_n": grip, "duration_s": 0.3}, {"op": "hold", "duration_s": 0.1},
        {"op": "lift", "speed_mm_s": 10.0, "accel_mm_s2": 50.0, "distance_mm": 5.0}, {"op": "hold", "duration_s": 0.4}],
        g=9.81))
    prof = profiles(sc)
    sim = BulletSim(sensor_params("v2"), object_geometry(sc), sc.engine_params())  # type: ignore[arg-type]
    try:
        out = sim.run(prof.grip, prof.accel, prof.force, prof.torque)
        pad_y = pb.getJointState(sim.jaw, 2, physicsClientId=sim.client)[0]  # mm
    finally:
        sim.close()
    assert not out.slip[prof.moves[0]["start"]:].any()  # a secure grasp: nothing slides
    assert out.force[-1, :, 2].sum() == pytest.approx(grip, rel=0.02)
    assert out.contact_fn[-1].sum() == pytest.approx(grip, rel=0.02)
    # The pillars and the jaw's pad together carry the weight, each by its stiffness; the object stays put.
    pillars = -out.force[-1, :, 1].sum()
    pad = -object_geometry(sc).jaw_kt_n_mm * pad_y
    assert pillars + pad == pytest.approx(mass * 9.81, rel=0.03)
    assert 0.2 * mass * 9.81 < pillars < 0.8 * mass * 9.81
    assert abs(out.pose[-1, 1]) < 0.5


def test_an_under_gripped_lift_slips_to_a_labelled_onset_and_a_secure_one_does_not():
    def lift(grip: float):
        # A slippery jaw (0.2) leaves the pillars most of the load; 2.5 N loads five of them.
        d = _scene({"mass_kg": 0.2, "mu": 0.5, "jaw_mu": 0.2, "size_mm": 40.0}, [
            {"op": "grip", "force_n": grip, "duration_s": 0.2}, {"op": "hold", "duration_s": 0.1},
            {"op": "lift", "speed_mm_s": 40.0, "accel_mm_s2": 100.0, "distance_mm": 20.0},
            {"op": "hold", "duration_s": 0.3}], g=9.81, effects=[{"name": "noise"}])
        return generate(parse_scene(d), seed=1)

    slip, held = lift(2.5), lift(8.0)
    assert slip.meta["kind"] == "slip" and slip.label.any()
    assert slip.meta["physics"]["name"] == "bullet"
    ev = slip.meta["events"]
    assert ev["motion_start"] < ev["onset"] < ev["gross_slip"]  # incipient: some pillars slide before all do
    assert slip.label[round(ev["onset"] * 1000)] == 1
    assert held.meta["kind"] == "stop" and not held.label.any()


def test_the_bullet_set_runs_its_scenes_on_bullet_and_tags_them():
    scenes = dataset_scenes("bullet", "test", 8, 0)
    assert {d["physics"]["name"] for d, _ in scenes} == {"bullet"}
    assert {d["_tags"]["physics_family"] for d, _ in scenes} == {"bullet"}
    # Drawn afresh: not the MuJoCo set's scenes with another engine's name.
    mujoco = dataset_scenes("engine", "test", 8, 0)
    assert [d["object"] for d, _ in scenes] != [d["object"] for d, _ in mujoco]


def test_an_unknown_engine_setting_is_named():
    with pytest.raises(SceneError, match=r"physics.*impratio"):
        parse_scene(_scene({}, [{"op": "hold", "duration_s": 0.1}], physics={"name": "bullet", "impratio": 10}))
