"""The second engine (``slipd.sim.engine.bullet``, Bullet) against analytic cases, and its scenes end to end: a
detector held out from one engine is tested on the other, so both must get the basics right. One pillar's stick
limit and a held object's force balance are checked on both engines in ``test_engine.py``."""

from __future__ import annotations

import pytest

pytest.importorskip("pybullet")


from slipd.sim import SceneError, generate, parse_scene
from slipd.sim.datasets import dataset_scenes

CORNERS, EDGES, CENTRE = [0, 2, 6, 8], [1, 3, 5, 7], 4


def _scene(obj: dict, timeline: list[dict], g: float = 0.0, **kw) -> dict:
    return {"family": "engine", "name": "t", "sensor": "v2", "gravity": {"g_m_s2": g}, "physics": {"name": "bullet"},
            "object": {"shape": "box", "mass_kg": 0.1, "mu": 0.5, "radius_mm": 10.0, **obj}, "timeline": timeline, **kw}


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
