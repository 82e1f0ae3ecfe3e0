"""The engine family (``slipd.sim.engine``, MuJoCo) against analytic cases, and its scenes end to end."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from slipd.sim import SceneError, generate, parse_scene
from slipd.sim.engine.generate import profiles, simulate
from slipd.sim.engine.stepping import EngineSim, sustained_slides

CORNERS, EDGES, CENTRE = [0, 2, 6, 8], [1, 3, 5, 7], 4


def _scene(obj: dict, timeline: list[dict], g: float = 0.0, **kw) -> dict:
    return {"family": "engine", "name": "t", "sensor": "v2", "gravity": {"g_m_s2": g},
            "object": {"shape": "box", "mass_kg": 0.1, "mu": 0.5, "radius_mm": 10.0, **obj}, "timeline": timeline, **kw}


def _run(d: dict):
    sc = parse_scene(d)
    return sc, profiles(sc), simulate(sc, profiles(sc))


def _onsets(slip: np.ndarray) -> list[int | None]:
    return [int(np.argmax(slip[:, i])) if slip[:, i].any() else None for i in range(slip.shape[1])]


@pytest.mark.parametrize("engine", ["mujoco", "bullet"])
def test_one_pillar_slips_at_its_stick_limit(engine):
    # A small sphere at a light grip touches the centre tip alone; a push grows until the tip slides. Both engines
    # (``slipd.sim.engine.bullet`` is the second) must get this right.
    if engine == "bullet":
        pytest.importorskip("pybullet")
    mu = 0.6
    _, prof, out = _run(_scene({"shape": "sphere", "radius_mm": 5.0, "mu": mu},
                               [{"op": "grip", "force_n": 2.0, "duration_s": 0.2}, {"op": "hold", "duration_s": 0.1},
                                {"op": "push", "rate": 2.0, "duration_s": 1.5}], physics={"name": engine}))
    start = prof.moves[0]["start"]
    assert out.contact_fn[start, CENTRE] == pytest.approx(2.0, rel=0.02)
    assert out.contact_fn[start, [*CORNERS, *EDGES]].max() == 0.0  # nothing else touches
    onset = _onsets(out.slip)[CENTRE]
    assert onset is not None and onset > start + 100
    # The friction force peaks at mu x normal on the way to the slide (as the tip breaks away the solver's force dips
    # below the cone for a few samples, so the peak rather than the sample before the onset); the sensor's forces
    # (kt u over the normal law, in the sensor's axes) differ by the tilt of the sphere-on-tip contact normal.
    solver = out.contact_ft[:, CENTRE] / np.maximum(out.contact_fn[:, CENTRE], 1e-9)
    before = start + int(np.argmax(solver[start:onset]))
    assert onset - before < 30
    assert solver[before] == pytest.approx(mu, rel=0.02)
    ratio = np.hypot(*out.force[before, CENTRE, :2]) / out.force[before, CENTRE, 2]
    assert ratio == pytest.approx(mu, rel=0.08)
    # Well before the onset the tip sticks with the ratio below the limit.
    early = start + (onset - start) // 2
    assert not out.slip[start:early, CENTRE].any()
    assert np.hypot(*out.force[early, CENTRE, :2]) / out.force[early, CENTRE, 2] < 0.7 * mu


@pytest.mark.parametrize("engine", ["mujoco", "bullet"])
def test_a_held_object_balances_grip_and_weight(engine):
    mass, grip = 0.3, 12.0
    sc = parse_scene(_scene({"mass_kg": mass, "mu": 0.8}, [
        {"op": "grip", "force_n": grip, "duration_s": 0.3}, {"op": "hold", "duration_s": 0.1},
        {"op": "lift", "speed_mm_s": 10.0, "accel_mm_s2": 50.0, "distance_mm": 5.0}, {"op": "hold", "duration_s": 0.4}],
        g=9.81, physics={"name": engine}))
    prof = profiles(sc)
    from slipd.sim.engine.generate import object_geometry
    from slipd.sim.physics import sensor_params

    if engine == "mujoco":
        sim = EngineSim(sensor_params("v2"), object_geometry(sc), sc.engine_params())  # type: ignore[arg-type]
        out = sim.run(prof.grip, prof.accel, prof.force, prof.torque)
        pad_mm = sim.data.joint("pady").qpos[0] * 1e3
    else:
        pb = pytest.importorskip("pybullet")
        from slipd.sim.engine.bullet import BulletSim

        bullet = BulletSim(sensor_params("v2"), object_geometry(sc), sc.engine_params())  # type: ignore[arg-type]
        try:
            out = bullet.run(prof.grip, prof.accel, prof.force, prof.torque)
            pad_mm = pb.getJointState(bullet.jaw, 2, physicsClientId=bullet.client)[0]  # its world is in mm
        finally:
            bullet.close()
    assert not out.slip[prof.moves[0]["start"]:].any()  # a secure grasp: nothing slides
    # Normal: the pillars push back with the grip (the sensor's forces and the solver's agree).
    assert out.force[-1, :, 2].sum() == pytest.approx(grip, rel=0.02)
    assert out.contact_fn[-1].sum() == pytest.approx(grip, rel=0.02)
    # Tangential: the pillars and the jaw's pad together carry the weight, each by its stiffness.
    # (The sensor reports the force on its tips, which the object drags down: the support is its negative.)
    pillars = -out.force[-1, :, 1].sum()
    pad = -object_geometry(sc).jaw_kt_n_mm * pad_mm
    assert pillars + pad == pytest.approx(mass * 9.81, rel=0.03)
    assert 0.2 * mass * 9.81 < pillars < 0.8 * mass * 9.81
    assert abs(out.force[-1, :, 0].sum()) < 0.02 * mass * 9.81
    assert abs(out.pose[-1, 1]) < 0.5


def test_partial_slip_spreads_from_the_outer_pillars_inward():
    _, _, out = _run(_scene({"mu": 0.5}, [{"op": "grip", "force_n": 15.0, "duration_s": 0.3},
                                             {"op": "hold", "duration_s": 0.2},
                                             {"op": "push", "rate": 8.0, "duration_s": 2.0}]))
    on = _onsets(out.slip)
    assert all(on[i] is not None for i in range(9))
    assert max(on[i] for i in CORNERS) < min(on[i] for i in EDGES) <= max(on[i] for i in EDGES) <= on[CENTRE]
    # The slipping ring grows with the load: corners alone first, for a long stretch.
    assert min(on[i] for i in EDGES) - max(on[i] for i in CORNERS) > 500
    # Each outer pillar starts to slide at its own stick limit, in the solver's forces and in the sensor's (a flat
    # face: the contact normal is the sensor's).
    for i in [*CORNERS, *EDGES]:
        k = on[i] - 1
        assert out.contact_ft[k, i] / out.contact_fn[k, i] == pytest.approx(0.5, rel=0.03)
        assert np.hypot(*out.force[k, i, :2]) / out.force[k, i, 2] == pytest.approx(0.5, rel=0.03)


def test_creep_below_the_stick_limit_is_small():
    # The same grasp as above, whose corners slide once the push reaches about 2 N: the push stops at 1.2 N (60 % of
    # that) and stays for a second.
    _, prof, out = _run(_scene({"mu": 0.5}, [{"op": "grip", "force_n": 15.0, "duration_s": 0.3},
                                             {"op": "hold", "duration_s": 0.2},
                                             {"op": "push", "rate": 8.0, "duration_s": 0.15},
                                             {"op": "hold", "duration_s": 1.0}]))
    assert not out.slip.any()
    k0, k1 = prof.moves[0]["end"] + 50, len(out.slip) - 1
    drift_um_s = abs(out.pose[k1, 0] - out.pose[k0, 0]) * 1e3 / ((k1 - k0) * 1e-3)
    assert drift_um_s < 1.0
    # No force lost to creep: the held force (which wobbles by ~1 % as the grasp rings) is the same a second later.
    held = out.force[k0: k0 + 300, :, 0].sum(1).mean()
    assert held > 0.4
    assert out.force[k1 - 300: k1, :, 0].sum(1).mean() == pytest.approx(held, rel=0.02)


def test_an_engine_scene_goes_through_the_sensor_model_and_the_label_rule():
    d = _scene({"mass_kg": 0.3, "mu": 0.5, "radius_mm": 20.0},
               [{"op": "grip", "force_n": 2.5, "duration_s": 0.3}, {"op": "hold", "duration_s": 0.2},
                {"op": "lift", "speed_mm_s": 10.0, "accel_mm_s2": 50.0, "distance_mm": 10.0},
                {"op": "hold", "duration_s": 0.2}], g=9.81,
               effects=[{"name": "lowpass"}, {"name": "noise"}, {"name": "quantisation"}])
    rec = generate(parse_scene(d), seed=1)
    again = generate(parse_scene(d), seed=1)
    assert np.array_equal(rec.force, again.force)  # reproducible
    assert rec.meta["family"] == "engine" and rec.meta["physics"]["name"] == "mujoco"
    assert rec.meta["kind"] == "slip"  # 2.5 N cannot hold 2.9 N of weight
    ev = rec.meta["events"]
    assert ev["motion_start"] < ev["onset"] <= ev["gross_slip"]
    assert "gross_motion" in ev
    # The noise effect acted on the measurement only: the unloaded stretch is noisy, the truth is not.
    assert 0.005 < rec.force[:200, :, 0].std() < 0.02
    assert not rec.slip[: round(ev["motion_start"] * 1000)].any()


def test_engine_scenes_are_validated():
    with pytest.raises(SceneError, match="runs engine scenes"):
        parse_scene({"family": "hexapod", "physics": {"name": "mujoco"}, "contact": {"depth_mm": 1.0},
                     "motion": {"kind": "translation"}})
    with pytest.raises(SceneError, match="only signal and meta effects"):
        parse_scene(_scene({}, [{"op": "hold", "duration_s": 0.1}], effects=[{"name": "tilt"}]))
    with pytest.raises(SceneError, match=r"engine scenes run on one of \('mujoco', 'bullet'\)"):
        parse_scene(_scene({}, [{"op": "hold", "duration_s": 0.1}], physics={"name": "stribeck"}))
    with pytest.raises(SceneError, match="shape"):
        parse_scene(_scene({"shape": "torus"}, [{"op": "hold", "duration_s": 0.1}]))


def test_a_slide_counts_only_when_it_carries_the_tip_its_minimum_distance():
    # 1 kHz samples of sliding speed (mm/s; 0 where the tip sticks): pillar 0 blips for 10 ms at 1 mm/s (10 um);
    # pillar 1 slides 30 ms at 1 mm/s with a 3-sample flicker inside; pillar 2 two 10 ms blips 40 samples apart.
    speed = np.zeros((200, 9))
    speed[20:30, 0] = 1.0
    speed[50:65, 1] = 1.0
    speed[68:83, 1] = 1.0
    speed[100:110, 2] = 1.0
    speed[150:160, 2] = 1.0
    slip = sustained_slides(speed, min_slide_mm=0.02, gap=5)
    assert not slip[:, 0].any() and not slip[:, 2].any()
    assert slip[50:83, 1].all() and slip[:, 1].sum() == 33  # one episode, the flicker inside it
    assert sustained_slides(speed, min_slide_mm=0.0, gap=0)[:, [0, 2]].sum() == 30


def test_a_recording_is_a_slip_a_partial_slip_a_stop_or_a_hold():
    from slipd.sim.engine.generate import kind

    lift = {"op": "lift", "stop": False}
    assert kind(1200, [lift, {**lift, "partial": True}], True) == "slip"  # one move slipped to gross slip
    assert kind(None, [lift, {**lift, "partial": True}], True) == "partial"  # one slipped part way, then stuck
    assert kind(None, [lift], True) == "stop"
    assert kind(None, [], False) == "hold"
