"""grip_control: take over at the hold force, catch a slip, hold the friction margin, rate-limited, bounded,
fail-safe."""

from __future__ import annotations

from typing import Any

from slipd.daemon.grip_control import GripController, GripControlSettings
from slipd.detect.contact import ContactState
from slipd.metrics import Metrics

DT = 0.01  # one decision every 10 ms (stride 10 at 1 kHz)


class Jaw:
    def __init__(self, fail: bool = False) -> None:
        self.sent: list[float] = []
        self.fail = fail

    def grip_force(self, n: float) -> float:
        if self.fail:
            raise RuntimeError("servo silent")
        self.sent.append(n)
        return 0.0


def _state(grip: float, load: float, mu: float | None, risk: float, shear: float | None = None) -> ContactState:
    return ContactState((0.0,) * 9, mu, 0.0 if mu else None, risk, grip, load, shear_n=shear)


def _ctl(jaw: Any, **kw: Any) -> tuple[GripController, list[str], list[str]]:
    stops: list[str] = []
    fails: list[str] = []
    c = GripController(GripControlSettings(**kw), gripper=jaw, gripper_worker=None, stop_arm=stops.append,
                       failsafe=fails.append)
    return c, stops, fails


def _run(c: GripController, t: float, n: int, *args: Any, alarm: bool = False, **kw: Any) -> float:
    for _ in range(n):
        t += DT
        c.update(_state(*args, **kw), t, alarm=alarm)
    return t


def test_takes_the_grip_over_at_its_force_once_it_is_steady() -> None:
    jaw = Jaw()
    c, _, _ = _ctl(jaw, takeover_after_s=0.1)
    t = 0.0
    for g in (2.0, 4.0, 6.0, 8.0, 10.0):  # the jaw is still closing: hands off
        t = _run(c, t, 1, g, 0.0, None, 0.0)
    assert jaw.sent == []
    t = _run(c, t, 15, 10.0, 0.0, None, 0.0)  # steady for 0.15 s
    assert jaw.sent == [10.0] and c.hold_n == 10.0


def test_what_the_closing_left_is_not_a_slip_nor_the_friction() -> None:
    """Pillars splay and slide while the jaw closes: the slip states (risk) and friction samples that leaves are
    not the object's. A risk still up at the take-over counts once it has been down; a friction estimate that has
    not moved since the take-over is not used."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.8, max_force_n=40.0)
    t = _run(c, 0.0, 20, 20.0, 0.05, 0.05, 0.7)  # closed: a stale risk of 0.7 and a friction of 0.05
    assert c.target == 20.0
    t = _run(c, t, 20, 20.0, 1.0, 0.05, 0.7)  # loaded: 1 / (0.05 * 0.8) = 25 N if that friction were believed
    assert c.target == 20.0 and stops == []
    t = _run(c, t, 5, 20.0, 1.0, 0.05, 0.2)  # the stale risk has gone
    t = _run(c, t, 1, 20.0, 2.0, 0.1, 0.7)  # a real slip now, with a friction estimate that moved
    assert c.target is not None and c.target > 20.0


def test_a_slip_is_caught_at_once_within_the_servo_rate_and_the_catch_holds_while_it_slips() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, rise_n_s=300.0, margin=0.85, max_force_n=40.0)
    t = _run(c, 0.0, 20, 10.0, 0.0, None, 0.0)
    t = _run(c, t, 1, 10.0, 1.0, None, 0.0, alarm=True)  # slips: its load is unknown while it slides
    assert c.target is not None and abs(c.target - (10.0 + 300.0 * DT)) < 1e-9  # the rate bounds the jump
    t = _run(c, t, 10, 10.0, 1.0, None, 0.0, alarm=True)
    assert c.target == 20.0  # 2 x the grip it slipped at, held while the alarm lasts
    assert all(b - a <= 300.0 * 2 * DT + 1e-9 for a, b in zip(jaw.sent, jaw.sent[1:], strict=False))
    assert stops == []


def test_holds_the_margin_with_the_highest_friction_seen_and_relaxes_slowly_to_it() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.8, relax_n_s=2.0, relax_after_s=0.5, max_force_n=40.0)
    t = _run(c, 0.0, 20, 10.0, 0.0, None, 0.0)
    t = _run(c, t, 10, 10.0, 1.5, 0.15, 1.0, alarm=True)  # slides: the sliding pillars give mu 0.15
    assert c.target == 20.0
    # Caught: the load is 2 N, so 2 / (0.15 * 0.8) = 16.7 N keeps the margin. The contact's own estimate
    # now reads lower (lagging slip states) but the grasp's highest one stands.
    t = _run(c, t, 30, 20.0, 2.0, 0.12, 0.0)
    assert c.target == 20.0  # quiet for 0.3 s: not relaxing yet
    t = _run(c, t, 100, 20.0, 2.0, 0.12, 0.0)
    want = 2.0 / (0.15 * 0.8)
    assert c.target is not None and want <= c.target < 20.0 - 2.0 * 0.4  # 2 N/s down, never below the need
    t = _run(c, t, 300, 20.0, 2.0, 0.12, 0.0)
    assert abs(c.target - want) < 1e-9
    assert stops == []


def test_the_requirement_counts_the_twist_and_a_twist_stops_the_arm_at_once() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.8, twist=1.15, max_force_n=40.0)
    t = _run(c, 0.0, 20, 20.0, 0.0, None, 0.0)
    t = _run(c, t, 1, 20.0, 1.0, 0.06, 0.6, alarm=True, shear=1.1)  # slides straight down
    assert stops == [] and c.target is not None and c.target > 20.0
    t = _run(c, t, 1, 20.0, 0.6, 0.06, 0.9, alarm=True, shear=2.0)  # and turns
    assert stops == ["grip control: twist"]
    # The catch is called off (the arm stop holds a twist; a grip jump makes the pillars slip all at once):
    # the grip follows the net load's requirement, 0.6 / (0.06 * 0.8) = 12.5 N, kept at the grip it has.
    assert c.target is not None and c.target <= 20.0 + 1e-9
    t = _run(c, t, 20, 20.0, 0.6, 0.06, 0.9, alarm=True, shear=2.0)
    assert c.target is not None and c.target <= 20.0 + 1e-9 and len(stops) == 1


def test_by_default_a_twist_is_a_slip_the_grip_catches() -> None:
    """Without ``twist`` (the default) a turning contact keeps the lift going: the catch raises the grip, and only
    the force limit stops the arm."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.8, max_force_n=40.0)
    t = _run(c, 0.0, 20, 20.0, 0.0, None, 0.0)
    t = _run(c, t, 20, 20.0, 0.6, 0.06, 0.8, alarm=True, shear=1.5)  # turns: shear 2.5 times the load
    assert stops == [] and c.target is not None and c.target > 30.0
    _run(c, t, 50, 39.5, 2.4, 0.06, 0.8, alarm=True, shear=4.0)  # still slips with the grip at the limit
    assert stops == ["grip control: grip at its limit"]


def test_an_alarm_with_the_risk_up_is_caught_whatever_the_friction_in_use() -> None:
    """A friction estimate from light edge pillars can exceed the contact's sliding ratio, so the computed use is
    low while the whole contact slides: the alarm and the risk agreeing is a slip all the same."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=40.0)
    t = _run(c, 0.0, 20, 17.7, 0.0, None, 0.0)
    t = _run(c, t, 5, 17.7, 2.1, 0.149, 0.0)
    _run(c, t, 2, 17.7, 2.14, 0.149, 0.56, alarm=True)  # use 2.14 / (0.149 * 17.7) = 0.81
    assert c.target is not None and abs(c.target - min(2.0 * 17.7, 17.7 + c.s.rise_n_s * 0.02)) < 1e-6


def test_no_catch_where_the_friction_in_use_rules_a_slide_out() -> None:
    """Every friction estimate errs low, so the use computed with it errs high: an alarm on a contact whose computed
    use is below halfway from the margin to the limit (a changing load, pillars splaying under a rising grip) keeps
    the requirement without a catch; one at the limit is caught."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, catch=2.0, margin=0.8, max_force_n=40.0)
    t = _run(c, 0.0, 20, 20.0, 0.0, None, 0.0)
    t = _run(c, t, 5, 20.0, 1.0, 0.1, 0.0)  # a friction estimate from slid pillars
    t = _run(c, t, 5, 20.0, 1.0, 0.1, 0.0, alarm=True)  # use 1 / (0.1 * 20) = 0.5
    assert c.target == 20.0
    t = _run(c, t, 120, 20.0, 1.0, 0.1, 0.0)  # quiet past relax_after_s: the next alarm is a new slip
    g = c.target
    assert g is not None
    _run(c, t, 10, g, 0.1 * g, 0.1, 0.0, alarm=True)  # at the limit
    assert c.target is not None and abs(c.target - 2.0 * g) < 1e-9


def test_never_beyond_the_force_limit_and_the_arm_stops_there() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, max_force_n=8.0)
    c.metrics = Metrics()
    t = _run(c, 0.0, 20, 5.0, 0.0, None, 0.0)
    _run(c, t, 200, 5.0, 5.0, 0.2, 0.5)  # 5 N of load at mu 0.2 needs 36 N
    assert max(jaw.sent) <= 8.0 and stops == ["grip control: grip at its limit"]
    assert c.metrics.registry.get_sample_value("slipd_grip_arm_stops_total", {"reason": "limit"}) == 1.0


def test_one_pillar_contact_friction_from_the_alarm_and_no_relaxing_below_the_catch() -> None:
    """A contact on one pillar never shows the pillars' asynchronous deceleration: the alarm is the only slip
    signal, and the contact's utilisation during it (before the catch raised the grip) is the friction."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, catch=1.6, margin=0.8, relax_after_s=0.2, relax_n_s=5.0, max_force_n=8.0)
    t = _run(c, 0.0, 20, 2.0, 0.0, None, 0.0)
    t = _run(c, t, 3, 2.0, 0.5, None, 0.0, alarm=True)  # sliding at 0.5 N on 2 N: mu 0.25
    assert c.alarm_friction.estimate() is not None
    assert abs(c.alarm_friction.estimate().mu - 0.25) < 1e-9  # type: ignore[union-attr]
    # Held: 0.74 N of load needs 0.74 / (0.25 * 0.8) = 3.7 N.
    t = _run(c, t, 200, 3.2, 0.74, None, 0.0)
    assert c.target is not None and abs(c.target - 0.74 / (0.25 * 0.8)) < 1e-6
    assert max(jaw.sent) <= 8.0


def test_update_rate_is_the_servo_rate() -> None:
    jaw = Jaw()
    c, _, _ = _ctl(jaw, rise_n_s=1000.0, update_hz=62.0, max_force_n=100.0)
    t = _run(c, 0.0, 20, 5.0, 0.0, None, 0.0)
    n0 = len(jaw.sent)
    for k in range(1000):  # 1 s of decisions at 1 kHz, load growing all the time
        c.update(_state(5.0, 0.01 * k, 0.3, 0.0), t + k / 1000.0)
    assert 45 <= len(jaw.sent) - n0 <= 62  # never more than the servo's 62 per second


def test_a_failed_grip_command_fails_safe_and_nan_never_reaches_the_servo() -> None:
    c, _, fails = _ctl(Jaw(fail=True))
    c.update(_state(5.0, 3.0, 0.2, 0.9), 0.0, alarm=True)
    assert fails == ["grip_control failed"]
    jaw = Jaw()
    c2, _, _ = _ctl(jaw)
    _run(c2, 0.0, 30, 5.0, float("nan"), 0.2, 0.0)
    assert all(x == x for x in jaw.sent)


def test_release_resets() -> None:
    jaw = Jaw()
    c, _, _ = _ctl(jaw)
    c.update(_state(5.0, 3.0, 0.2, 0.9), 0.0, alarm=True)
    assert c.target is not None
    c.update(_state(0.0, 0.0, None, 0.0), 0.1)
    assert c.target is None and c.alarm_friction.estimate() is None


def test_a_slip_that_reaches_the_limit_later_is_caught_from_the_grip_it_has_then() -> None:
    """A load growing slowly (a cup being filled): the slip starts with the friction in use below the catch's
    plausibility, so only the requirement raises the grip, at the servo's pace; once the whole contact slides at
    the limit the slip is caught, once, from the grip it has then (the rig's filling cup slid 30 mm off without)."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=30.0)
    t = _run(c, 0.0, 20, 3.3, 0.1, None, 0.0)
    t = _run(c, t, 5, 3.3, 0.78, 0.268, 0.61)  # use 0.78 / (0.268 * 3.3) = 0.88: no whole-contact slide yet
    assert c.target is not None and c.target < 2.0 * 3.3
    t = _run(c, t, 30, 4.5, 1.13, 0.25, 0.8)  # the same slip, now at the limit: 1.13 / (0.25 * 4.5) = 1.0
    assert c.target is not None and abs(c.target - 2.0 * 4.5) < 1e-9
    _run(c, t, 10, 9.0, 1.13, 0.25, 0.6)  # a flicker of the same slip at the raised grip: no second catch
    assert c.target is not None and c.target <= 2.0 * 4.5 + 1e-9 and stops == []


def test_takes_over_while_a_light_pillar_flickers_across_the_contact_threshold() -> None:
    """The rig's filling cup rests on a 2.2 N pillar and two at 0.5 N, the contact threshold: ``grip_n`` steps
    between 3.3 and 2.8 N as they flicker, the grasp never counted as settled, and the cup slid out unanswered.
    Steadiness is judged on the pressed pillars' whole normal force, which does not step; and the grip taken over is
    that force, whatever ``grip_n`` read at that moment: a take-over at 2.8 N loosened the jaw from 3.3 N, the light
    pillars fell below the threshold, and a cup on one pillar slid out without any sign (a rig run dropped it)."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, takeover_after_s=0.1)
    t = 0.0
    for k in range(30):
        t += DT
        grip = 2.8 if k % 3 == 0 else 3.3  # a pillar at the threshold in and out of the contact's grip
        c.update(ContactState((0.0,) * 9, None, None, 0.0, grip, 0.1, shear_n=0.1, pressed_n=3.31), t)
    assert c.target == 3.31 and jaw.sent == [3.31]
    assert c.hold_n == 3.31  # nor does it relax below the hold's force later


def _cup(grip: float, shear: float, *, top_util: float, pressed_n: float = 2.9) -> ContactState:
    """The rig's filling cup as its contact state shows it: no friction known, no risk, the shear on the grip."""
    return ContactState((0.0,) * 9, None, None, 0.0, grip, shear, shear_n=shear, pressed_n=pressed_n,
                        top_util=top_util)


def _held_cup(c: GripController) -> float:
    """The cup held still for 0.2 s (the controller takes the grip over); returns the time."""
    t = 0.0
    for _ in range(20):
        t += DT
        c.update(_cup(2.1, 0.02, top_util=0.2), t)
    return t


def test_an_alarm_on_a_contact_that_cannot_be_sliding_is_no_friction_sample() -> None:
    """The rig's filling cup: the lift's alarm comes while the cup sticks at shear / grip 0.04 on its one loaded pillar,
    its two light pillars at 0.2-0.3 of their cone. No friction is below a pillar's utilisation, so 0.04 is no sample:
    taken as the friction it made the requirement climb to the force limit as the cup was filled, and the arm
    stopped (11 of 30 rig runs). The catch still answers the alarm, and the grip holds at it."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=30.0)
    t = _held_cup(c)
    for _ in range(4):  # the lift's alarm at 0.1 N of shear on 2.1 N
        t += DT
        c.update(_cup(2.1, 0.1, top_util=0.2), t, alarm=True)
    assert c.alarm_friction.estimate() is None
    assert c.target is not None and abs(c.target - 2.0 * 2.1) < 1e-9  # the catch
    for k in range(300):  # the cup is filled: 1.2 N of shear, the grip at the catch, no slip
        t += DT
        c.update(_cup(4.2, 0.1 + 1.1 * k / 300, top_util=0.3, pressed_n=4.3), t)
    assert c.target is not None and c.target < 5.0 and max(jaw.sent) < 5.0 and stops == []


def test_an_alarm_on_one_pillar_sliding_at_its_cone_is_a_friction_sample() -> None:
    """The same contact really sliding: shear / grip at the light pillars' utilisation (within the static-to-kinetic
    slack) is a sample, and the grip follows the load with it."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=30.0)
    t = _held_cup(c)
    for _ in range(3):
        t += DT
        c.update(_cup(2.1, 0.52, top_util=0.3), t, alarm=True)
    est = c.alarm_friction.estimate()
    assert est is not None and abs(est.mu - 0.52 / 2.1) < 1e-9


def test_an_alarm_of_the_confirmed_heuristic_alone_is_caught_but_no_friction_sample() -> None:
    """The same sliding contact, its alarm raised by the heuristic the model confirms (``decision.confirm_rule``),
    which comes while some pillars still stick: the catch answers it, the contact's ratio is no sample."""
    jaw = Jaw()
    c, _, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=30.0)
    t = _held_cup(c)
    for _ in range(3):
        t += DT
        c.update(_cup(2.1, 0.52, top_util=0.3), t, alarm=True, sampled=False)
    assert c.alarm_friction.estimate() is None
    assert c.target is not None and abs(c.target - 2.0 * 2.1) < 1e-9  # the catch


def test_a_twist_never_sets_a_grip_beyond_the_force_limit() -> None:
    """At a twist the target becomes the net load's requirement: with little friction known that is far above the
    object's limit, and the limit still holds."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, twist=1.15, max_force_n=10.0, margin=0.8)
    t = _run(c, 0.0, 20, 9.0, 0.0, None, 0.0)
    _run(c, t, 5, 9.0, 2.0, 0.05, 0.9, alarm=True, shear=4.0)  # turns; 2 N / (0.05 * 0.8) = 50 N
    assert len(stops) == 1 and c._twist  # the arm stopped (the limit's rule speaks first), the twist is known
    assert c.target is not None and c.target <= 10.0 and max(jaw.sent) <= 10.0


def test_the_daemons_gripper_holds_within_the_objects_limit_from_start_up() -> None:
    """Built from the config (the real driver against the emulated MX-28 over a pty): under grip_control the start-up
    hold's effort is capped at the object's limit. The rig's hold setting is full effort (885: its force comes from
    the position), which would give a fragile 8 N cup up to 40 N wherever the cup sits farther in than expected."""
    from conftest import ROOT

    from slipd.config import load_config, override
    from slipd.daemon.devices import build_devices
    from slipd.sim.devices.mx28 import PWM_MAX, EmulatedMX28

    with EmulatedMX28() as servo:
        cfg = override(load_config(ROOT / "config" / "sim.yaml"), {
            "gripper.port": servo.port, "arm.enabled": False, "reaction.actions": ["tighten_gripper"],
            "reaction.on_failsafe": "log_only", "reaction.policy": "grip_control", "reaction.grip_max_force_n": 8.0})
        assert cfg.gripper.hold_pwm == PWM_MAX
        _, gripper = build_devices(cfg, Metrics())
        assert gripper is not None
        try:
            assert servo.register("goal_pwm") == int(8.0 / cfg.gripper.max_force_n * PWM_MAX)  # 177: 8.0 N
            assert gripper.settings.force_limit_n == 8.0
        finally:
            gripper.close()
        _, gripper = build_devices(override(cfg, {"reaction.policy": "stop_and_secure",
                                                  "reaction.grip_max_force_n": 30.0}), Metrics())
        assert gripper is not None
        try:
            assert servo.register("goal_pwm") == PWM_MAX  # stop_and_secure: the settings as they are
        finally:
            gripper.close()


def test_a_run_of_failed_grip_commands_fails_safe_once() -> None:
    """A silent servo fails every command at the servo rate: one fail-safe for the run, another once a command got
    through and a later one failed again."""
    jaw = Jaw(fail=True)
    c, _, fails = _ctl(jaw, max_force_n=200.0)  # far from the limit: every growing load is a new target
    t = 0.0
    for _ in range(100):  # one second of decisions, about 60 commands sent and failed
        t += DT
        c.update(_state(5.0, 3.0 + t, 0.2, 0.9), t, alarm=True)
    assert fails == ["grip_control failed"]
    jaw.fail = False
    t = _run(c, t, 20, 5.0, 3.0, 0.25, 0.9, alarm=True)  # the contact's own friction: a requirement to follow
    assert jaw.sent  # commands get through again
    jaw.fail, sent = True, len(jaw.sent)
    for k in range(20):  # the load grows: new targets to send, and they fail
        t += DT
        c.update(_state(5.0, 3.0 + 0.2 * k, 0.25, 0.9), t, alarm=True)
    assert len(jaw.sent) == sent and fails == ["grip_control failed"] * 2


def test_an_estimate_the_contact_refuted_is_dropped() -> None:
    """The contact forgets an estimate a sticking pillar refutes (``slipd.detect.contact.FRICTION_REFUTE``); the
    controller, which keeps the highest estimate of the grasp, must forget it too, or a misjudged 0.07 keeps asking
    for more than the limit and stops the arm on a still hold."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, max_force_n=40.0, margin=0.85)
    t = _run(c, 0.0, 20, 30.0, 2.5, None, 0.0)  # taken over at 30 N, no friction known
    t = _run(c, t, 1, 30.0, 2.5, 0.067, 0.0)  # one misjudged sample: 2.5 / (0.067 * 0.85) = 44 N asked for
    assert c._mu == 0.067
    _run(c, t, 100, 30.0, 2.5, None, 0.0)  # refuted: the contact has no estimate any more
    assert c._mu is None and stops == [] and max(jaw.sent) < 40.0


def test_a_slide_at_the_limit_stops_the_arm_even_where_the_friction_estimate_hides_it() -> None:
    """A slip flag at the force limit stops the arm, whatever the requirement says. The estimate can exceed the
    slide's own ratio (the highest of the grasp, taken near a static peak: 0.20 against a kinetic 0.16), and then
    a slide at 39.6 N computes 37.3 N required, within the limit. Stopping at the limit only on the
    requirement or a lasting alarm: this slide (risk 0.7, no alarm) then went on for good."""
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, catch=2.0, margin=0.85, max_force_n=40.0, stop_after_s=0.15)
    t = _run(c, 0.0, 20, 20.5, 0.0, None, 0.0)
    t = _run(c, t, 5, 20.5, 2.0, 0.20, 0.0)  # held, friction known
    t = _run(c, t, 5, 20.5, 3.0, 0.20, 0.8, alarm=True)  # a slip: caught at 2 x 20.5, capped at 40
    assert c.target == 40.0 and stops == []
    _run(c, t, 30, 39.6, 0.16 * 39.6, 0.20, 0.7)  # slides at the limit, risk up, no alarm
    assert stops == ["grip control: grip at its limit"]
