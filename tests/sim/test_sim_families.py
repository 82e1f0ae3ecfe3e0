"""Physics families (``slipd.sim.contact_models``) and scenario timelines (``slipd.sim.timeline``)."""

from __future__ import annotations

import numpy as np
import pytest

from slipd.sim import SceneError, generate, parse_scene
from slipd.sim import contact_models as cm
from slipd.sim.datasets import FAMILIES, HOLD_TYPES, dataset_scenes, physics_spec, write_dataset
from slipd.sim.scene import generate_batch

FAMILY_SPECS = {
    "stick_slip": {"name": "stick_slip"},
    "viscoelastic": {"name": "viscoelastic", "ratio": 0.5, "tau_s": 0.2},
    "stribeck": {"name": "stribeck", "vs_mm_s": 1.0, "coupling": 0.3},
    "spread": {"name": "stick_slip", "spread": {}},
    "calibration": {"name": "stick_slip", "calibration": {}},
}
PRESS = {"op": "press", "depth_mm": 1.0, "duration_s": 0.3}


def _scene(timeline=None, physics=None, sensor="v1", **kw):
    d = {"family": "hexapod", "sensor": sensor, "friction": {"mu_s": 0.7, "mu_k": 0.6}, **kw}
    if timeline is None:
        d.update({"contact": {"depth_mm": 1.0}, "motion": {"kind": "translation", "speed_mm_s": 2.0}})
    else:
        d["timeline"] = timeline
    if physics is not None:
        d["physics"] = physics
    return parse_scene(d)


def _move(**kw):
    return {"op": "move", "kind": "translation", "speed_mm_s": 2.0, "accel_mm_s2": 20.0, "duration_s": 1.5, **kw}


def test_every_family_is_registered_and_selectable():
    assert {"stick_slip", "viscoelastic", "stribeck"} <= set(cm.REGISTRY)
    for fam in FAMILIES:
        sc = _scene([PRESS, {"op": "hold", "duration_s": 0.2}], physics_spec(fam, np.random.default_rng(0)))
        assert sc.build_model().name == physics_spec(fam, np.random.default_rng(0))["name"]
    with pytest.raises(SceneError, match="unknown contact model 'magic'"):
        _scene(physics={"name": "magic"})
    with pytest.raises(SceneError, match="ratio"):
        _scene(physics={"name": "viscoelastic", "ratio": 2.0})


def test_default_family_is_bit_identical_and_the_general_loop_agrees():
    plain = generate(_scene(), seed=3)
    named = generate(_scene(physics={"name": "stick_slip"}), seed=3)
    for a, b in ((plain.force, named.force), (plain.disp, named.disp), (plain.slip, named.slip),
                 (plain.label, named.label)):
        assert np.array_equal(a, b)
    assert "physics" not in plain.meta["scene"] and "physics" in named.meta
    # The general loop with a zero spread is the same law: equal up to rounding.
    zero = generate(_scene(physics={"name": "stick_slip", "spread": {"kt": 0, "height_mm": 0, "mu": 0}}), seed=3)
    assert np.allclose(zero.force, plain.force, atol=1e-4)
    assert np.mean(zero.slip != plain.slip) < 1e-3


@pytest.mark.parametrize("family", list(FAMILY_SPECS))
def test_still_press_held_for_minutes_never_slips(family):
    sc = _scene([PRESS, {"op": "hold", "duration_s": 180.0}], FAMILY_SPECS[family], effects=[])
    rec = generate(sc, seed=1)
    press_end = round((0.3 + 0.3) / 1e-3)
    assert not rec.slip[press_end:].any()
    assert rec.meta["kind"] == "hold" and not rec.label.any() and "motion_start" not in rec.meta["events"]
    assert rec.force[-1, :, 2].sum() > 1.0  # still pressed at the end


def test_viscoelastic_force_relaxes_after_a_halt_while_the_tip_stays():
    tl = [PRESS, {"op": "hold", "duration_s": 0.5}, _move(stop_fraction=0.8), {"op": "hold", "duration_s": 3.0}]
    rec = generate(_scene(tl, FAMILY_SPECS["viscoelastic"]), seed=0)
    stop = rec.meta["timeline"]["moves"][0]
    at_rest = round(stop["end_s"] / 1e-3)
    ft = np.hypot(rec.force[..., 0], rec.force[..., 1]).sum(1)
    assert ft[-1] < 0.8 * ft[at_rest]
    assert np.allclose(rec.disp[-1, :, :2], rec.disp[at_rest, :, :2], atol=1e-6)
    assert not rec.slip.any() and rec.meta["kind"] == "stop"
    # Rate dependence: the same stick travel loaded fast gives more force than slowly (before relaxing).
    elastic = generate(_scene(tl, FAMILY_SPECS["stick_slip"]), seed=0)
    assert ft[at_rest] < np.hypot(elastic.force[at_rest, :, 0], elastic.force[at_rest, :, 1]).sum() * 1.01


def test_stribeck_slides_in_bursts_and_couples_neighbours():
    tl = [PRESS, {"op": "hold", "duration_s": 0.3}, _move(duration_s=2.0)]
    strib = generate(_scene(tl, FAMILY_SPECS["stribeck"], effects=[]), seed=0)
    plain = generate(_scene(tl, FAMILY_SPECS["stick_slip"], effects=[]), seed=0)
    assert strib.label.any() and strib.meta["events"]["onset"] > strib.meta["events"]["motion_start"]
    # Velocity weakening: sliding tips re-stick and release again (more slip/stick transitions).
    def transitions(r):
        return int(np.abs(np.diff(r.slip.astype(int), axis=0)).sum())
    assert transitions(strib) > transitions(plain)


def test_several_events_in_one_recording_have_the_right_truth():
    tl = [{"op": "press", "depth_mm": 1.0, "duration_s": 0.0}, {"op": "hold", "duration_s": 1.0}, _move(),
          {"op": "hold", "duration_s": 1.0}, {"op": "release", "duration_s": 0.3}, {"op": "hold", "duration_s": 0.5},
          {"op": "press", "depth_mm": 0.9, "duration_s": 0.5}, {"op": "hold", "duration_s": 2.0},
          _move(stop_fraction=0.7), {"op": "hold", "duration_s": 2.0}, _move(direction_deg=90.0),
          {"op": "hold", "duration_s": 0.5}]
    rec = generate(_scene(tl, effects=[]), seed=0)
    meta = rec.meta["timeline"]
    assert meta["starts_in_contact"] and rec.force[0, :, 2].sum() > 1.0
    moves = meta["moves"]
    assert [m["stop"] for m in moves] == [False, True, False]
    assert not moves[1]["truth_slip"]
    t = np.arange(len(rec)) * 1e-3
    labelled = rec.label.astype(bool)
    for m in (moves[0], moves[2]):
        assert m["start_s"] < m["onset_s"] < m["gross_slip_s"] <= m["end_s"]
        inside = (t >= m["onset_s"]) & (t < m["gross_slip_s"])
        assert labelled[inside].all()
    in_any = np.zeros(len(rec), bool)
    for m in (moves[0], moves[2]):
        in_any |= (t >= m["onset_s"]) & (t < m["gross_slip_s"])
    assert not labelled[~in_any].any()
    assert rec.meta["kind"] == "slip" and rec.meta["events"]["onset"] == pytest.approx(moves[0]["onset_s"])
    # Nothing slides while everything is still (holds between the moves, the long hold after the stop).
    stop_rest = round(moves[1]["end_s"] / 1e-3)
    assert not rec.slip[stop_rest: round(moves[2]["start_s"] / 1e-3)].any()


def test_calibration_error_changes_the_measurement_not_the_truth():
    tl = [PRESS, {"op": "hold", "duration_s": 0.3}, _move()]
    a = generate(_scene(tl, FAMILY_SPECS["stick_slip"], effects=[]), seed=2)
    b = generate(_scene(tl, FAMILY_SPECS["calibration"], effects=[]), seed=2)
    assert np.array_equal(a.slip, b.slip) and np.array_equal(a.label, b.label)
    assert not np.allclose(a.force, b.force)


def test_robust_and_holds_sets_record_family_and_scenario(tmp_path):
    items = dataset_scenes("robust", "train", 10, 0)
    assert {d["_tags"]["physics_family"] for d, _ in items} == set(FAMILIES)
    test_seeds = {s for _, s in dataset_scenes("robust", "test", 10, 0)}
    assert not test_seeds & {s for _, s in items}
    index = write_dataset("holds", "test", tmp_path, count=10, hold_s=1.0)
    assert index["scenario"] == {h: 2 for h in HOLD_TYPES}
    from slipd.recording import Recording

    for e in index["recordings"]:
        rec = Recording.load(tmp_path / e["file"])
        assert rec.meta["scenario"] == e["scenario"] and rec.meta["physics_family"] == e["physics_family"]
        assert rec.meta["kind"] in ("hold", "stop") and not rec.label.any()
        assert not rec.slip[-500:].any()
    free = [e for e in index["recordings"] if e["scenario"] == "free_air"]
    assert all(Recording.load(tmp_path / e["file"]).force[:, :, 2].max() < 0.5 for e in free)


def test_batches_mixing_families_equal_single_runs():
    tls = [[PRESS, {"op": "hold", "duration_s": 0.2}, _move(duration_s=0.8)],
           [PRESS, {"op": "hold", "duration_s": 1.0}, _move(stop_fraction=0.5), {"op": "hold", "duration_s": 0.5}]]
    scenes = [_scene(tl, FAMILY_SPECS[f]) for tl in tls for f in ("viscoelastic", "stribeck", "stick_slip")]
    batch = generate_batch(scenes, list(range(len(scenes))))
    for i, sc in enumerate(scenes):
        single = generate(sc, seed=i)
        assert np.array_equal(single.slip, batch[i].slip)
        assert np.allclose(single.force, batch[i].force, atol=1e-5)


def test_grips_set_randomises_closing_rate_and_hold_before_the_move():
    items = dataset_scenes("grips", "test", 20, 0)
    scenes = [parse_scene({k: v for k, v in d.items() if k != "_tags"}, d["name"]) for d, _ in items]
    closes = [sc.grip.close_s for sc in scenes]
    settles = [sc.settle_s for sc in scenes]
    assert min(closes) >= 0.05 and max(closes) <= 2.0 and max(closes) > 4 * min(closes)
    assert min(settles) >= 0.2 and max(settles) > 2.0
    for sc in scenes:  # the motion still fits: 3.2 s after the arm starts, as in the transfer design
        assert sc.duration_s == pytest.approx(sc.pre_s + sc.grip.close_s + sc.settle_s + 3.2, abs=2e-3)
    assert {d["_tags"]["scenario"] for d, _ in items} == {"grip"}
