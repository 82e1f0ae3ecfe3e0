"""The contact state: per-pillar slip, friction estimate and contact risk."""

from __future__ import annotations

import numpy as np

from slipd.detect.contact import ContactState, ContactStream, grasp_state
from slipd.detect.features import FeatureSpec
from slipd.detect.friction import FrictionEstimator
from slipd.detect.pillar_slip import PillarSlip
from slipd.detect.risk import contact_risk

FZ = np.array([1.0, 2.0, 1.0, 2.0, 4.0, 2.0, 1.0, 2.0, 1.0])


def _loading(n: int, slide: set[int], mu: float = 0.5, rate_n_s: float = 2.0) -> np.ndarray:
    """[n, 9, 3] samples: the contact loaded in +x; pillars in ``slide`` sit on their friction limit."""
    t = np.arange(n)[:, None] / 1000.0
    f = np.zeros((n, 9, 3))
    f[:, :, 2] = FZ
    f[:, :, 0] = rate_n_s * t
    for p in slide:
        f[:, p, 0] = np.minimum(f[:, p, 0], mu * FZ[p])
    return f


def test_pillars_that_stop_following_the_load_slide_and_give_the_friction() -> None:
    mu = 0.5
    f = _loading(600, {0, 2, 6, 8}, mu=mu)  # corners (least normal force) reach the limit first
    stream = ContactStream(FeatureSpec(window=40, stride=10))
    states = [s for _, s in stream.push_many(f)]
    last = states[-1]
    p = np.array(last.pillar_slip)
    assert (p[[0, 2, 6, 8]] > 0.9).all() and (p[[1, 3, 4, 5, 7]] < 0.1).all()
    assert last.friction is not None and abs(last.friction - mu) < 0.02
    assert 0.0 < last.risk < 1.0
    assert last.friction_use is not None and last.friction_use < 1.0


def test_pillars_that_stop_at_their_own_lower_limit_slide_and_the_friction_is_the_contacts() -> None:
    """Per-pillar friction spread: the edge pillars stop at 0.35, the corners at 0.5. The edges never reach the top
    utilisation, yet they stopped following the load: they slide too, and the estimate is the contact's
    (the normal-force-weighted mean of the sliding pillars' coefficients), not the grippiest pillars' alone."""
    t = np.arange(600)[:, None] / 1000.0
    f = np.zeros((600, 9, 3))
    f[:, :, 2] = FZ
    f[:, :, 0] = 2.0 * t
    mu = np.array([0.5, 0.35, 0.5, 0.35, 0.5, 0.35, 0.5, 0.35, 0.5])
    sliding = [0, 1, 2, 3, 5, 6, 7, 8]  # the centre (4 N) sticks
    f[:, sliding, 0] = np.minimum(f[:, sliding, 0], mu[sliding] * FZ[sliding])
    last = [s for _, s in ContactStream(FeatureSpec(window=40, stride=10)).push_many(f)][-1]
    p = np.array(last.pillar_slip)
    assert (p[sliding] > 0.9).all() and p[4] < 0.1
    contact_mu = float(np.dot(FZ[sliding], mu[sliding]) / FZ[sliding].sum())  # 0.40
    assert last.friction is not None and abs(last.friction - contact_mu) < 0.03


def test_sensor_noise_alone_does_not_clear_a_slide_on_a_slippery_object() -> None:
    """A slippery object (mu 0.08: 0.08-0.32 N of shear per pillar) slides on steadily: the filtered noise moves a
    pillar's ratio by several % and its normal force by a few mN, which is no tightening grip; the pillars seen
    sliding stay sliding for the whole second that follows. (The centre, the last to reach its limit, had no pillar
    still following the load to lag behind: it is never marked.)"""
    n_load, n_hold = 300, 1000
    f = _loading(n_load, set(range(9)), mu=0.08)
    hold = np.repeat(f[-1:], n_hold, axis=0)
    rng = np.random.default_rng(1)
    data = np.concatenate([f, hold]) + rng.normal(0.0, 0.01, (n_load + n_hold, 9, 3))
    states = [s for _, s in ContactStream(FeatureSpec(window=40, stride=10)).push_many(data)]
    late = np.array([s.pillar_slip for s in states[-(n_hold // 10) :]])
    assert (late[:, [0, 1, 2, 3, 5, 6, 7, 8]] > 0.5).all()


def test_a_sliding_pillar_read_just_under_the_contact_flag_keeps_its_state_and_one_off_the_surface_sticks() -> None:
    """A corner on its limit is marked sliding; then it reads 0.45 N (under the 0.5 N flag, still on the surface) and
    keeps its state, while another that reads 0.1 N has left the surface and sticks."""
    ps = PillarSlip()
    f = _loading(600, {0, 2, 6, 8}, mu=0.5)  # the corners (1 N each) on their limit
    for k in range(40, 601, 10):
        ps.update(f[k - 40:k])
    assert ps.probability()[[0, 2]].min() > 0.9
    w = f[560:600].copy()
    w[:, 0, 2], w[:, 2, 2] = 0.45, 0.1
    for _ in range(3):
        p = ps.update(w)
    assert p[0] > 0.9 and p[2] < 0.5


def test_no_slip_while_the_contact_sticks() -> None:
    f = _loading(600, set())
    states = [s for _, s in ContactStream(FeatureSpec(window=40, stride=10)).push_many(f)]
    assert max(max(s.pillar_slip) for s in states) < 0.5
    assert all(s.friction is None for s in states)


def test_release_resets_the_friction_estimate() -> None:
    f = _loading(600, {0, 2, 6, 8})
    free = np.zeros((200, 9, 3))
    stream = ContactStream(FeatureSpec(window=40, stride=10))
    stream.push_many(f)
    assert stream.latest is not None and stream.latest.friction is not None
    stream.push_many(free)
    assert stream.latest is not None and stream.latest.friction is None and stream.latest.grip_n == 0.0


def test_friction_estimator_weights_and_spread() -> None:
    est = FrictionEstimator(forget=1.0)
    assert est.update(np.full(9, 0.4), np.full(9, 3.0), np.zeros(9)) is None  # nothing sliding: no estimate
    util = np.array([0.4, 0.6, 0, 0, 0, 0, 0, 0, 0])
    fz = np.array([3.0, 3.0, 0, 0, 0, 0, 0, 0, 0])
    r = est.update(util, fz, np.array([1, 1, 0, 0, 0, 0, 0, 0, 0.0]))
    assert r is not None and abs(r.mu - 0.5) < 1e-6 and abs(r.sd - 0.1) < 1e-6
    # A ratio no real friction has (a glitch) is not a sample.
    r2 = est.update(np.array([50.0, 0, 0, 0, 0, 0, 0, 0, 0]), np.full(9, 3.0), np.eye(9)[0])
    assert r2 is not None and abs(r2.mu - 0.5) < 1e-6
    # A pillar whose normal force rose 10 % since the last decision is gripped harder, not sliding: no sample; the
    # same ratio at a steady normal force is one.
    r3 = est.update(np.full(9, 0.2), np.full(9, 3.3), np.eye(9)[0])
    assert r3 is not None and abs(r3.mu - 0.5) < 1e-6
    r4 = est.update(np.full(9, 0.2), np.full(9, 3.3), np.eye(9)[0])
    assert r4 is not None and r4.mu < 0.5


def test_friction_ignores_the_light_edge_pillars_of_a_curved_contact() -> None:
    """The rig's shampoo bottle: the middle column carries 5-6 N, its neighbours 0.7 N at a higher, noisier ratio."""
    fz = np.array([0, 5.1, 0, 0.7, 6.1, 0.7, 0, 5.1, 0])
    util = np.array([0, 0.12, 0, 0.145, 0.12, 0.14, 0, 0.12, 0])
    edge = FrictionEstimator(min_fz_n=0.5, edge_share=0.2)
    r = edge.update(util, fz, np.array([0, 0, 0, 1.0, 0, 0, 0, 0, 0]))
    assert r is None  # only the edge pillar was seen sliding: no sample
    r = edge.update(util, fz, (fz > 0).astype(float))
    assert r is not None and abs(r.mu - 0.12) < 1e-9
    # a push on light pillars alone (every one under 1 N) still gives samples
    light = FrictionEstimator(min_fz_n=0.5, edge_share=0.2)
    r = light.update(np.full(9, 0.3), np.full(9, 0.8), np.ones(9))
    assert r is not None and abs(r.mu - 0.3) < 1e-9


def test_contact_risk_is_the_load_weighted_share_at_risk() -> None:
    fz = np.array([1.0, 3.0, 0, 0, 0, 0, 0, 0, 0])
    p = np.array([1.0, 0, 0, 0, 0, 0, 0, 0, 0])
    assert contact_risk(fz, np.zeros(9), p, None, 0.3) == 0.25  # only the sliding pillar, a quarter of the load
    util = np.array([0.5, 0.5, 0, 0, 0, 0, 0, 0, 0])
    assert contact_risk(fz, util, p, 0.5, 0.3) == 1.0  # the other one at its limit too
    assert contact_risk(fz, util * 0.7, np.zeros(9), 0.5, 0.3) == 0.0  # at 70 % of the limit: no risk yet
    assert contact_risk(np.zeros(9), util, p, 0.5, 0.3) == 0.0  # no contact


def test_pillar_state_is_bounded_and_finite() -> None:
    ps = PillarSlip()
    rng = np.random.default_rng(0)
    for _ in range(2000):
        w = rng.normal(0, 5, (40, 9, 3))
        p = ps.update(w)
        assert np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all()


def test_a_detector_on_all_nine_pillars_shares_its_filtered_window_with_the_contact_state() -> None:
    """The shipped layout (util of P0..P8): one median per window feeds both the model and the contact state,
    and the states equal those of a ContactStream of its own, sample by sample and block by block."""
    from slipd.detect.decision import Decision
    from slipd.detect.detector import Detector
    from slipd.detect.ensemble import Ensemble
    from slipd.models import packaged

    ens = Ensemble.load(packaged("slip_ensemble_int8"))
    rng = np.random.default_rng(3)
    f = (_loading(900, {0, 2, 6, 8}) + rng.normal(0, 0.01, (900, 9, 3))).astype(np.float32)
    offset = np.zeros((9, 3), np.float32)
    expected = [s for _, s in ContactStream(ens.feature_spec, offset).push_many(f)]
    by_block = Detector(ens, Decision(), offset=offset)
    assert by_block._shared
    got = [d.contact for _, d in by_block.push_many(f, np.arange(900) * 1000)]
    ens.reset()
    one = Detector(ens, Decision(), offset=offset)
    singles = [d.contact for d in (one.push(x, i * 1000) for i, x in enumerate(f)) if d is not None]
    assert got == expected == singles and len(expected) == (900 - 40) // ens.feature_spec.step + 1


def test_a_grip_that_caught_the_slip_clears_the_slip_state_and_keeps_the_friction() -> None:
    """After the corners slid, the grip doubles with the load held: the corners' utilisation halves,
    so they stick (no lingering slip state), and their sticking ratios never pull the friction estimate down."""
    mu = 0.5
    f = _loading(600, {0, 2, 6, 8}, mu=mu)
    stream = ContactStream(FeatureSpec(window=40, stride=10))
    stream.push_many(f)
    before = stream.latest
    assert before is not None and before.friction is not None and max(before.pillar_slip) > 0.9
    hold = np.repeat(f[-1:], 400, axis=0)
    hold[:100, :, 2] *= np.linspace(1.0, 2.0, 100)[:, None]  # the grip rises over 0.1 s, tangential forces stay
    hold[100:, :, 2] *= 2.0
    stream.push_many(hold)
    after = stream.latest
    assert after is not None and max(after.pillar_slip) < 0.5
    assert after.friction is not None and abs(after.friction - before.friction) < 0.01
    assert after.risk < 0.5


def test_shear_counts_a_twist_that_cancels_in_the_net_load() -> None:
    f = np.zeros((100, 9, 3))
    f[:, :, 2] = FZ
    f[:, [0, 3, 6], 1] = 0.2  # one column pushed up, the other down: a torque, no net load
    f[:, [2, 5, 8], 1] = -0.2
    stream = ContactStream(FeatureSpec(window=40, stride=10))
    stream.push_many(f)
    s = stream.latest
    assert s is not None and s.load_n < 1e-6 and s.shear_n is not None and abs(s.shear_n - 1.2) < 1e-6


def test_top_util_is_a_lower_bound_of_the_friction_from_every_pressed_pillar() -> None:
    """The filling cup's contact: one loaded pillar sticking at 0.04 of its cone, two light ones below the contact
    threshold at 0.3 of theirs. ``top_util`` reads the light pillars too, over the threshold rather than their own
    force (understated, never overstated), so a friction below it is ruled out."""
    f = np.zeros((100, 9, 3))
    f[:, 4, 2], f[:, 4, 0] = 2.2, 0.088  # 0.04
    f[:, [1, 7], 2], f[:, [1, 7], 0] = 0.3, 0.09  # 0.3 of their own force, 0.18 over the 0.5 N threshold
    stream = ContactStream(FeatureSpec(window=40, stride=10))
    stream.push_many(f)
    s = stream.latest
    assert s is not None and abs(s.grip_n - 2.2) < 1e-6 and s.top_util is not None
    assert abs(s.top_util - 0.09 / 0.5) < 1e-6
    assert s.to_dict()["top_util"] == round(s.top_util, 4)


def _finger(grip: float, shear: float, *, risk: float = 0.1, friction: float | None = None,
            pressed: float | None = None) -> ContactState:
    return ContactState(pillar_slip=(0.0,) * 9, friction=friction, friction_sd=None if friction is None else 0.01,
                        risk=risk, grip_n=grip, load_n=shear, shear_n=shear,
                        pressed_n=grip if pressed is None else pressed, top_util=shear / grip)


def test_the_grasp_of_two_fingers_is_decided_by_the_finger_nearest_its_limit() -> None:
    calm = _finger(10.0, 1.0, risk=0.2, friction=0.6, pressed=10.2)
    loaded = _finger(11.0, 3.0, risk=0.1, friction=0.4, pressed=11.0)
    g = grasp_state([calm, loaded])
    assert g is not None
    # The loaded finger's grip, shear and utilisation, whole (their ratio is the controller's friction sample).
    assert (g.grip_n, g.load_n, g.shear_n, g.top_util) == (11.0, 3.0, 3.0, loaded.top_util)
    assert g.risk == 0.2  # a slip on either finger is a slip of the grasp
    assert (g.friction, g.friction_sd) == (0.6, 0.01)  # the highest estimate: every estimate errs low
    assert g.pressed_n == (10.2 + 11.0) / 2  # the jaw's force, whichever finger decides
    assert grasp_state([loaded, calm]) == g  # the order of the sensors does not matter


def test_one_sensor_is_its_own_grasp_and_a_finger_out_of_contact_does_not_count() -> None:
    lone = _finger(0.3, 0.0)  # below the contact threshold
    held = _finger(8.0, 2.0, friction=None)
    assert grasp_state([lone]) is lone
    assert grasp_state([lone, held]) is held and grasp_state([None, held]) is held
    assert grasp_state([lone, None]) is None  # released on both: the controller resets
    both = grasp_state([held, _finger(8.0, 1.0, friction=None)])
    assert both is not None and both.friction is None and both.shear_n == 2.0


def _hold(index: int, seed: int, seconds: float = 5.0):
    from slipd.sim.datasets import hold_scene
    from slipd.sim.scene import generate, parse_scene

    d = hold_scene(np.random.default_rng(seed), index, hold_s=seconds)
    rec = generate(parse_scene({k: v for k, v in d.items() if k != "_tags"}, d["name"]), seed)
    assert not rec.slip.any()  # the truth: nothing slips
    return rec


def test_a_still_press_and_a_shear_hold_give_no_friction_estimate_and_no_risk() -> None:
    """Holds where nothing slips (the simulator's, seed 7 of tests/detect/test_still_holds.py and its neighbours). A
    press splays the pillars (a few per cent of each normal force sideways) and the first windows of a shear load cross
    that splay: the pillar estimate judged one pillar sliding there, its utilisation (0.05-0.07) became the friction
    estimate on contacts of 0.5-0.8, and the risk then read 0.6-1.0 for the whole hold. Now a pressing window gives
    no sample (``FRICTION_PRESS_RISE``) and a pillar sticking at far more than the estimate refutes it
    (``FRICTION_REFUTE``)."""
    for index, seed in ((6, 7), (1, 8), (6, 9)):  # a slow press (0.95 s); two shear holds
        rec = _hold(index, seed)
        stream = ContactStream(FeatureSpec(pillars=tuple(range(9)), channels=("util",), window=40, median=5, stride=10))
        states = [s for _, s in stream.push_many(rec.force)]
        held = states[len(states) // 2 :]  # the hold, past the press and the shear load
        assert all(s.friction is None for s in held), (index, seed, held[-1].friction)
        assert max(s.risk for s in held) <= 0.05, (index, seed, max(s.risk for s in held))
