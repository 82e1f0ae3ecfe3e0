"""Contact physics: stiffness laws, the stick-slip law, slip order, edge cases, stepper agreement."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.geometry import CENTRE, CORNERS, EDGES, FT_RANGE_N, FZ_RANGE_N, OUTER
from slipd.sim.physics import (
    GripperStepper,
    HexapodStepper,
    ObjectParams,
    compression,
    compression_for_force,
    depth_for_total_force,
    normal_force,
    run_hexapod,
    sensor_params,
    stick_slip_step,
)
from slipd.sim.scene import generate, generate_batch, parse_scene

V1, V2 = sensor_params("v1"), sensor_params("v2")


def hexapod(kind="translation", depth=0.8, speed=3.0, stop=None, effects=(), **motion):
    m = {"kind": kind, "speed_mm_s": speed, "accel_mm_s2": 30.0, "rot_speed_deg_s": 8.0, **motion}
    if stop is not None:
        m["stop_fraction"] = stop
    return parse_scene({"family": "hexapod", "contact": {"depth_mm": depth}, "motion": m,
                        "friction": {"mu_s": 0.7, "mu_k": 0.6}, "effects": list(effects)})


def first_slip(rec):
    return [int(np.argmax(rec.slip[:, p])) if rec.slip[:, p].any() else None for p in range(9)]


def test_normal_stiffness_matches_published_secants():
    # v2: secant ~9.1 N/mm near 0.2 mm, ~5 N/mm near 2 mm (papillarray.md).
    assert normal_force(0.2, V2) / 0.2 == pytest.approx(9.1, abs=0.3)
    assert normal_force(2.0, V2) / 2.0 == pytest.approx(5.0, abs=0.3)
    assert normal_force(0.5, V1) > normal_force(0.5, V2)  # v1 is harder
    assert V1.kt_n_mm > V2.kt_n_mm
    f = np.linspace(0, 12, 7)
    np.testing.assert_allclose(normal_force(compression_for_force(f, V2), V2), f, atol=1e-9)


def test_compression_respects_height_offsets_and_mask():
    c = compression(0.3)
    assert c[CENTRE] == pytest.approx(0.3)
    assert all(c[i] == pytest.approx(0.1) for i in EDGES)
    assert all(c[i] == 0.0 for i in CORNERS)
    mask = np.zeros(9, bool)
    mask[CENTRE] = True
    assert compression(1.0, contact_mask=mask).sum() == pytest.approx(1.0)
    depth = depth_for_total_force(np.array([6.0]), V2)
    assert normal_force(compression(depth), V2).sum() == pytest.approx(6.0, abs=1e-6)


def test_stuck_tip_follows_surface_until_static_limit_then_slides_at_kinetic():
    u = np.zeros((1, 2))
    sliding = np.zeros(1, bool)
    lim_s, lim_k = np.array([0.3]), np.array([0.25])
    step = np.array([[0.01, 0.0]])
    for _ in range(29):  # 0.29 mm < static limit: stuck, exact follow
        u, sliding = stick_slip_step(u, step, lim_s, lim_k, sliding)
        assert not sliding[0]
    assert u[0, 0] == pytest.approx(0.29)
    u, sliding = stick_slip_step(u, step, lim_s, lim_k, sliding)  # reaches 0.30: slides
    assert sliding[0]
    assert np.hypot(*u[0]) == pytest.approx(0.25)  # force drops to the kinetic level
    u, sliding = stick_slip_step(u, step, lim_s, lim_k, sliding)
    assert sliding[0] and np.hypot(*u[0]) == pytest.approx(0.25)
    u, sliding = stick_slip_step(u, np.zeros((1, 2)), lim_s, lim_k, sliding)  # surface stops
    assert not sliding[0]
    u2, s2 = stick_slip_step(u, -step, lim_s, lim_k, sliding)  # reversal: stuck, unloads elastically
    assert not s2[0] and u2[0, 0] == pytest.approx(0.24)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2)), min_size=1, max_size=40),
    st.floats(0.0, 2.0),
    st.floats(0.1, 1.0),
)
def test_no_tip_ever_beyond_its_static_limit(steps, lim_s, ratio):
    u = np.zeros((1, 2))
    sliding = np.zeros(1, bool)
    ls, lk = np.array([lim_s]), np.array([lim_s * ratio])
    for dx, dy in steps:
        u, sliding = stick_slip_step(u, np.array([[dx, dy]]), ls, lk, sliding)
        assert np.all(np.isfinite(u))
        assert np.hypot(*u[0]) <= lim_s * (1 + 1e-9) + 1e-12


def test_translation_slips_corners_then_edges_then_centre():
    rec = generate(hexapod("translation", depth=0.8, direction_deg=20.0))
    first = first_slip(rec)
    assert all(first[i] is not None for i in range(9))
    assert max(first[i] for i in CORNERS) < min(first[i] for i in EDGES)
    assert max(first[i] for i in EDGES) < first[CENTRE]
    ev = rec.events
    assert ev["onset"] < ev["gross_slip"]
    assert rec.label[int(ev["onset"] * 1000)] == 1 and rec.label[int(ev["gross_slip"] * 1000)] == 0


def test_rotation_about_centre_slips_outer_never_centre():
    rec = generate(hexapod("rotation", depth=0.8))
    first = first_slip(rec)
    assert first[CENTRE] is None
    assert all(first[i] is not None for i in OUTER)
    assert max(first[i] for i in CORNERS) <= min(first[i] for i in EDGES)  # farther out: slips first
    assert "gross_slip" in rec.events  # label ends when all outer pillars slide


def test_onset_earlier_with_lower_depth_and_higher_speed():
    recs = generate_batch([hexapod(depth=0.7), hexapod(depth=1.2), hexapod(speed=2.0), hexapod(speed=8.0)])
    onset = [r.events["onset"] for r in recs]
    assert onset[0] < onset[1]
    assert onset[3] < onset[2]


def test_stop_scene_plate_halts_before_any_pillar_slips():
    for kind in ("translation", "rotation", "both"):
        rec = generate(hexapod(kind, stop=0.8, centre_mm=(2.0, 1.0)))
        assert rec.meta["kind"] == "stop"
        assert not rec.slip.any(), kind
        assert not rec.label.any()
        assert "motion_stop" in rec.events and "onset" not in rec.events


def test_every_slip_scene_has_gross_after_onset():
    scenes = [hexapod(k, depth=d, speed=v) for k in ("translation", "rotation", "both")
              for d in (0.6, 1.0) for v in (2.0, 6.0)]  # v/omega keeps the pivot off the array
    for rec in generate_batch(scenes):
        ev = rec.events
        assert ev["motion_start"] <= ev["onset"] < ev["gross_slip"]


def test_forces_saturate_like_the_sensor():
    rec = generate(hexapod(depth=3.0, speed=10.0))  # deep press: true forces exceed the ranges
    assert np.abs(rec.force[..., :2]).max() <= FT_RANGE_N
    assert rec.force[..., 2].max() == pytest.approx(FZ_RANGE_N)
    assert rec.force[..., 2].min() >= 0.0


@pytest.mark.parametrize("depth,speed", [(0.8, 0.0), (0.8, 60.0), (0.0, 5.0), (3.0, 5.0)])
def test_edge_cases_are_finite_and_within_friction(depth, speed):
    rec = generate(hexapod(depth=depth, speed=speed, accel_mm_s2=500.0))
    assert np.all(np.isfinite(rec.force)) and np.all(np.isfinite(rec.disp))
    assert rec.force[..., 2].min() >= 0.0
    ft = V1.kt_n_mm * np.hypot(rec.disp[..., 0], rec.disp[..., 1])
    fz = normal_force(rec.disp[..., 2], V1)
    assert np.all(ft <= 0.7 * fz * (1 + 1e-5) + 1e-6)
    if speed == 0.0 or depth == 0.0:
        assert not rec.slip.any() and not rec.label.any()


def test_single_pillar_in_contact():
    off = [p for p in range(9) if p != CENTRE]
    rec = generate(hexapod(depth=1.0, effects=[{"name": "partial_contact", "pillars": off}]))
    assert np.all(rec.force[:, off, :] == 0.0)
    assert rec.slip[:, CENTRE].any() and not rec.slip[:, off].any()
    assert rec.events["onset"] == rec.events["gross_slip"]  # one considered pillar: no incipient phase


def test_hexapod_stepper_agrees_with_batch_path():
    rng = np.random.default_rng(3)
    n = 600
    t = np.cumsum(rng.normal(0.004, 0.002, size=(n, 2)), axis=0)
    th = np.cumsum(rng.normal(0.0, 0.0005, size=n))
    depth = np.minimum(np.arange(n) / 100.0, 0.9)
    batch = run_hexapod(V1, t[:, None], th[:, None], depth[:, None], np.array([0.6]), np.array([0.5]))
    stepper = HexapodStepper(V1, batch=1, mu_s=0.6, mu_k=0.5)
    for k in range(n):
        out = stepper.step(t[k][None], np.rad2deg(th[k])[None], depth[k][None])
        np.testing.assert_allclose(out.force[0, :, :2], V1.kt_n_mm * batch["u"][k, 0], atol=1e-9)
        np.testing.assert_allclose(out.force[0, :, 2], batch["fz"][k, 0], atol=1e-9)
        assert np.array_equal(out.slip[0], batch["slip"][k, 0])
    assert batch["slip"].any() and not batch["slip"].all()


def test_gripper_stepper_step_equals_advance_and_holds_or_slips():
    obj = ObjectParams(mass_kg=0.5, mu_s=0.4, mu_k=0.3)
    a = GripperStepper(V2, obj, batch=2, table=True)
    b = GripperStepper(V2, obj, batch=2, table=True)
    grip = np.array([3.0, 20.0])  # under-gripped vs secure
    depth = depth_for_total_force(grip, V2)
    load = np.array([[0.0, -9810.0]] * 2)
    acc = np.array([[0.0, 50.0]] * 2)
    for k in range(1500):
        accel = acc if k < 200 else np.zeros((2, 2))
        o1 = a.step(grip, accel, load, np.zeros((2, 2)))
        o2 = b.advance(grip, depth, accel, load, np.zeros((2, 2)))
        np.testing.assert_array_equal(o1.force, o2.force)
    assert o1.object_motion[0, 1] < -2.0  # under-gripped: the object stays down as the finger rises
    assert abs(o1.object_motion[1, 1]) < 0.5 and not o1.slip[1].any()
    assert np.all(np.isfinite(o1.force)) and o1.force[..., 2].min() >= 0.0


def test_gripper_at_the_friction_limit_is_finite():
    obj = ObjectParams(mass_kg=0.5, mu_s=0.4, mu_k=0.4)
    g = GripperStepper(V2, obj, batch=1, table=True)
    grip = np.array([0.5 * 9.81 / (2 * 0.4)])  # exactly the holding force
    for _ in range(800):
        o = g.step(grip, np.zeros((1, 2)), np.array([[0.0, -9810.0]]), np.zeros((1, 2)))
    assert np.all(np.isfinite(o.force)) and o.force[..., 2].min() >= 0.0
    ft = np.hypot(o.force[0, :, 0], o.force[0, :, 1])
    assert np.all(ft <= 0.4 * o.force[0, :, 2] * (1 + 1e-6) + 1e-9)


def test_fast_forward_of_stuck_stretches_is_bit_identical_to_stepping():
    from slipd.sim.physics import friction_limits, splay_delta, surface_delta

    n = 900
    k = np.arange(n)
    depth = np.clip((k - 100) / 200.0, 0.0, 1.0)[:, None] * np.array([0.8, 0.0])  # one scene never touches
    t = np.zeros((n, 2, 2))
    t[:, :, 0] = (np.clip(k - 400, 0, None) * 0.003)[:, None]
    th = np.zeros((n, 2))
    mu_s, mu_k = np.array([0.6, 0.6]), np.array([0.5, 0.5])
    fast = run_hexapod(V1, t, th, depth, mu_s, mu_k)
    c = compression(depth)
    c_prev = np.concatenate([np.zeros((1, 2, 9)), c[:-1]])
    t_prev = np.concatenate([np.zeros((1, 2, 2)), t[:-1]])
    delta = surface_delta(t_prev, np.zeros((n, 2)), t, th) + splay_delta(c - c_prev, V1)
    fz = normal_force(c, V1)
    ls, lk = friction_limits(fz, mu_s, mu_k, V1)
    u = np.zeros((2, 9, 2))
    sliding = np.zeros((2, 9), bool)
    for i in range(n):
        u, slide = stick_slip_step(u, delta[i], ls[i], lk[i], sliding)
        sliding = slide & (fz[i] > 0)
        assert np.array_equal(fast["u"][i], u) and np.array_equal(fast["slip"][i], sliding), i
    assert fast["slip"].any()
