"""grip_control: the least grip that keeps the friction margin, rate-limited, bounded, fail-safe (issue 16)."""

from __future__ import annotations

from typing import Any

from slipd.daemon.grip_control import GripController, GripControlSettings
from slipd.detect.contact import ContactState


class Jaw:
    def __init__(self, fail: bool = False) -> None:
        self.sent: list[float] = []
        self.fail = fail

    def grip_force(self, n: float) -> float:
        if self.fail:
            raise RuntimeError("servo silent")
        self.sent.append(n)
        return 0.0


def _state(grip: float, load: float, mu: float | None, risk: float) -> ContactState:
    return ContactState((0.0,) * 9, mu, 0.0 if mu else None, risk, grip, load)


def _ctl(jaw: Any, **kw: Any) -> tuple[GripController, list[str], list[str]]:
    stops: list[str] = []
    fails: list[str] = []
    c = GripController(GripControlSettings(**kw), gripper=jaw, gripper_worker=None, stop_arm=stops.append,
                       failsafe=fails.append)
    return c, stops, fails


def test_raises_to_keep_the_margin_at_the_servo_rate_and_relaxes_slowly() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, margin=0.7, rise_n_s=100.0, relax_n_s=2.0, relax_after_s=0.5, max_force_n=30.0)
    c.update(_state(10.0, 2.0, None, 0.0), 0.0)  # held, no friction known: nothing to do
    assert jaw.sent == []
    t = 0.0
    for _ in range(100):  # friction 0.2 seen: 2 N of load needs 2 / (0.2 * 0.7) = 14.3 N
        t += 0.01
        c.update(_state(10.0, 2.0, 0.2, 0.0), t)
    assert abs(jaw.sent[-1] - 2.0 / (0.2 * 0.7)) < 0.06
    assert all(b - a <= 100.0 / 62.0 + 1.01 for a, b in zip([10.0, *jaw.sent], jaw.sent, strict=False))  # rate
    c.update(_state(14.3, 0.5, 0.2, 0.0), t + 0.1)  # load dropped: stays put until relax_after_s ...
    top = c.target
    c.update(_state(14.3, 0.5, 0.2, 0.0), t + 1.0)
    assert c.target is not None and top is not None and top - 2.0 * 0.9 - 0.01 <= c.target < top
    assert stops == []


def test_update_rate_is_the_servo_rate() -> None:
    jaw = Jaw()
    c, _, _ = _ctl(jaw, rise_n_s=1000.0, update_hz=62.0, max_force_n=100.0)
    for k in range(1000):  # 1 s of decisions at 1 kHz, load growing all the time
        c.update(_state(5.0, 0.01 * k, 0.3, 0.0), k / 1000.0)
    assert 45 <= len(jaw.sent) <= 62  # never more than the servo's 62 per second


def test_never_beyond_the_force_limit_and_the_arm_stops_there() -> None:
    jaw = Jaw()
    c, stops, _ = _ctl(jaw, max_force_n=8.0)
    for k in range(200):
        c.update(_state(5.0, 5.0, 0.2, 0.5), k / 100.0)
    assert max(jaw.sent) <= 8.0 and len(stops) == 1


def test_a_failed_grip_command_fails_safe_and_nan_never_reaches_the_servo() -> None:
    c, _, fails = _ctl(Jaw(fail=True))
    c.update(_state(5.0, 3.0, 0.2, 0.9), 0.0)
    assert fails == ["grip_control failed"]
    jaw = Jaw()
    c2, _, _ = _ctl(jaw)
    c2.update(_state(5.0, float("nan"), 0.2, 0.0), 0.0)
    assert all(x == x for x in jaw.sent)


def test_release_resets() -> None:
    jaw = Jaw()
    c, _, _ = _ctl(jaw)
    c.update(_state(5.0, 3.0, 0.2, 0.0), 0.0)
    assert c.target is not None
    c.update(_state(0.0, 0.0, None, 0.0), 0.1)
    assert c.target is None
