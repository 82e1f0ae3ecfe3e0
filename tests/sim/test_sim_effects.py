"""Effects: each does what it claims; one that is not listed leaves no trace."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slipd.geometry import CENTRE, FT_RANGE_N, FZ_RANGE_N
from slipd.sim import generate, load_scene, parse_scene
from slipd.sim.effects import REGISTRY, SERIAL_FAULT_KINDS

SCENES = Path(__file__).resolve().parents[2] / "config" / "scenes"


def hexrec(effects=(), seed=7, **motion):
    m = {"kind": "translation", "speed_mm_s": 3.0, "direction_deg": 30.0, **motion}
    return generate(parse_scene({"family": "hexapod", "contact": {"depth_mm": 0.8}, "motion": m,
                                 "effects": list(effects)}), seed=seed)


@pytest.fixture(scope="module")
def clean():
    return hexrec()


def pre(rec):
    a, b = rec.meta["tare_samples"]
    return rec.force[a:b]


def test_registry_has_the_required_effects():
    required = {"noise", "glitches", "drift", "speed_variation", "partial_contact", "curvature", "tilt", "gravity",
                "offcenter_torque", "servo_lag", "serial_faults", "quantisation", "lowpass"}
    assert required <= set(REGISTRY)


def test_noise_has_the_published_sigma(clean):
    rec = hexrec([{"name": "noise"}])
    resid = (rec.force - clean.force)[: int(rec.events["motion_start"] * 1000)]
    assert resid[..., 0].std() == pytest.approx(0.01, rel=0.1)
    assert resid[..., 2].std() == pytest.approx(0.02, rel=0.1)
    assert not np.array_equal(rec.force, hexrec([{"name": "noise"}], seed=8).force)  # seeded
    assert np.array_equal(rec.force, hexrec([{"name": "noise"}]).force)


def test_quantisation_puts_values_on_the_16_bit_grid(clean):
    rec = hexrec([{"name": "noise"}, {"name": "quantisation"}])
    step = 2 * FT_RANGE_N / 2**16
    q = rec.force[..., 0] / step
    np.testing.assert_allclose(q, np.round(q), atol=1e-3)
    qz = rec.force[..., 2] / (FZ_RANGE_N / 2**16)
    np.testing.assert_allclose(qz, np.round(qz), atol=1e-2)


def test_lowpass_smooths_without_changing_levels(clean):
    rec = hexrec([{"name": "lowpass", "cutoff_hz": 50.0}])
    d_clean = np.abs(np.diff(clean.force[..., 2], axis=0)).max()
    d_lp = np.abs(np.diff(rec.force[..., 2], axis=0)).max()
    assert d_lp < d_clean
    start = int(rec.events["motion_start"] * 1000)
    np.testing.assert_allclose(rec.force[start - 1], clean.force[start - 1], atol=1e-4)  # settled level kept


def test_glitches_are_isolated_spikes_at_marked_samples(clean):
    rec = hexrec([{"name": "glitches", "rate_hz": 5.0, "amplitude_n": 1.0}])
    marked = set(rec.meta["glitch_samples"])
    assert marked
    changed = set(np.nonzero(np.any(rec.force != clean.force, axis=(1, 2)))[0].tolist())
    assert changed <= marked


def test_drift_moves_the_unloaded_offset(clean):
    rec = hexrec([{"name": "drift", "rate_n_s": 0.05, "walk_n": 0.0}])
    d = rec.force - clean.force
    assert np.abs(d[-1]).max() > np.abs(d[0]).max() + 0.05


def test_speed_variation_changes_the_motion_not_the_press(clean):
    rec = hexrec([{"name": "speed_variation", "amplitude": 0.5, "period_s": 0.3}])
    start = int(clean.events["motion_start"] * 1000)
    assert np.array_equal(rec.force[:start], clean.force[:start])
    assert not np.allclose(rec.object_motion[start + 200:], clean.object_motion[start + 200:])
    assert rec.events["onset"] != clean.events["onset"]


def test_partial_contact_tilt_and_curvature_change_the_normal_forces(clean):
    start = int(clean.events["motion_start"] * 1000) - 1
    pc = hexrec([{"name": "partial_contact", "pillars": [0, 8]}])
    assert np.all(pc.force[:, [0, 8], 2] == 0.0) and pc.force[start, CENTRE, 2] > 0
    tilt = hexrec([{"name": "tilt", "angle_deg": 2.0, "axis_deg": 0.0}])  # rises towards +x
    fz = tilt.force[start, :, 2]
    assert fz[0] < clean.force[start, 0, 2] and fz[2] > clean.force[start, 2, 2]  # P0 at +x, P2 at -x
    curv = hexrec([{"name": "curvature", "radius_mm": 50.0, "axis_deg": None}])
    assert np.all(curv.force[start, [0, 2, 6, 8], 2] < clean.force[start, [0, 2, 6, 8], 2])
    assert curv.force[start, CENTRE, 2] == clean.force[start, CENTRE, 2]


def test_serial_faults_mark_meta_only(clean):
    rec = hexrec([{"name": "serial_faults", "rate_hz": 20.0}])
    faults = rec.meta["serial_faults"]
    assert faults and all(f["kind"] in SERIAL_FAULT_KINDS and 0 <= f["index"] < len(rec) for f in faults)
    for name in ("force", "disp", "slip", "label", "object_motion"):
        assert np.array_equal(getattr(rec, name), getattr(clean, name))


def test_an_unlisted_effect_leaves_no_trace():
    base = [{"name": "noise"}, {"name": "glitches"}]
    a = hexrec(base)
    b = hexrec([*base, {"name": "serial_faults"}])
    assert np.array_equal(a.force, b.force)  # adding one effect does not change what the others draw
    assert "serial_faults" not in a.meta and "glitch_samples" not in hexrec().meta


def _grip(effects, grip_n=None):
    d = load_scene(SCENES / "wooden_box_undergrip.yaml").model_dump()
    d["effects"] = effects
    d["duration_s"] = 1.6
    if grip_n is not None:
        d["grip"]["force_n"] = grip_n
    return generate(parse_scene(d))


def test_gripper_effects_gravity_torque_and_servo_lag():
    none = _grip([])
    grav = _grip([{"name": "gravity"}])
    assert np.abs(none.object_motion).max() < 0.05  # without gravity the lift only meets inertia
    assert grav.object_motion[:, 1].min() < -1.0  # under-gripped: slides down relative to the finger
    # Gripped firmly enough to lift off the table, an off-centre weight twists the grasp.
    held = _grip([{"name": "gravity"}], grip_n=24.0)
    torque = _grip([{"name": "gravity"}, {"name": "offcenter_torque", "offset_mm": [20.0, 0.0]}], grip_n=24.0)
    assert np.abs(held.object_motion[:, 2]).max() < 0.01
    assert np.abs(torque.object_motion[:, 2]).max() > 2.0
    lag = _grip([{"name": "servo_lag", "tau_s": 0.2, "max_rate_n_s": 10.0}])
    k = int(0.55 * 1000)  # grip ramp ends at 0.6 s
    assert lag.force[k, :, 2].sum() < none.force[k, :, 2].sum() - 0.5


def test_reported_displacement_carries_the_force_measurement_error(clean):
    # The sensor computes forces from the displacements it measures, so one error shows in both: the
    # tangential force error over k_t is in dx, dy; the compression dz stays the true one.
    from slipd.sim.physics import sensor_params

    noisy = hexrec([{"name": "noise"}, {"name": "glitches"}, {"name": "quantisation"}])
    kt = sensor_params("v1").kt_n_mm
    err_f = noisy.force[..., :2].astype(np.float64) - clean.force[..., :2]
    err_d = noisy.disp[..., :2].astype(np.float64) - clean.disp[..., :2]
    unsaturated = np.abs(noisy.force[..., :2]) < FT_RANGE_N  # saturation clips the force, not the deflection
    assert np.allclose(err_d[unsaturated], err_f[unsaturated] / kt, atol=1e-6)
    assert err_d.std() > 0.001  # noise of 0.01 N over 3.5 N/mm: about 0.003 mm
    assert np.array_equal(noisy.disp[..., 2], clean.disp[..., 2])
