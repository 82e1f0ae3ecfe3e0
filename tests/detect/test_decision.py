"""Decision: threshold rule, hysteresis against chattering, rising edges, risk level."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slipd.detect.decision import Decision


def _alarms(d: Decision, ps: list[float]) -> list[bool]:
    return [d.update(p).alarm for p in ps]


def test_threshold_rule_without_hysteresis_is_per_window() -> None:
    d = Decision()
    assert _alarms(d, [0.1, 0.49999, 0.5, 0.7, 0.49, 0.5]) == [False, False, True, True, False, True]


def test_hysteresis_holds_the_alarm_and_prevents_chattering() -> None:
    near = [0.45, 0.52, 0.48, 0.51, 0.47, 0.53, 0.46]  # wanders around the threshold
    assert sum(r for r in _edges(Decision(0.5, 0.0), near)) == 3
    d = Decision(0.5, hysteresis=0.1)
    assert _alarms(d, near) == [False, True, True, True, True, True, True]
    assert sum(_edges(Decision(0.5, 0.1), near)) == 1
    assert d.update(0.41).alarm  # still >= 0.4
    assert not d.update(0.39).alarm  # clears only below threshold - hysteresis
    assert not d.update(0.45).alarm  # and re-arms only at the threshold again
    assert d.update(0.5).rising_edge


def _edges(d: Decision, ps: list[float]) -> list[bool]:
    return [d.update(p).rising_edge for p in ps]


def test_rising_edge_once_per_alarm_and_reset() -> None:
    d = Decision()
    assert _edges(d, [0.2, 0.6, 0.8, 0.9, 0.1, 0.7]) == [False, True, False, False, False, True]
    d.reset()
    assert d.update(0.9).rising_edge


def test_risk_and_member_agreement() -> None:
    d = Decision(threshold=0.5)
    r = d.update(0.25, np.array([0.1, 0.2, 0.3, 0.6, 0.05]))
    assert r.risk == pytest.approx(0.5) and r.members_alarming == pytest.approx(0.2) and not r.alarm
    r = d.update(0.5, np.array([0.5, 0.5, 0.5, 0.5, 0.5]))
    assert r.risk == 1.0 and r.alarm and r.members_alarming == 1.0
    assert d.update(0.9).risk == 1.0 and d.update(0.9).members_alarming is None
    # Risk keeps its meaning when the threshold is re-tuned: 1 means "at the alarm point".
    assert Decision(threshold=0.8).update(0.4).risk == pytest.approx(0.5)


@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=60), st.floats(0.0, 0.3))
def test_properties(ps: list[float], hyst: float) -> None:
    d = Decision(0.5, hyst)
    prev = False
    for p in ps:
        r = d.update(p)
        assert 0.0 <= r.risk <= 1.0
        assert r.rising_edge == (r.alarm and not prev)
        if p >= 0.5:
            assert r.alarm
        if p < 0.5 - hyst:
            assert not r.alarm
        prev = r.alarm


def test_bad_values_are_refused_without_changing_state() -> None:
    d = Decision()
    d.update(0.9)
    for bad in (float("nan"), float("inf"), -0.1, 1.5):
        with pytest.raises(ValueError, match="p_slip"):
            d.update(bad)
    assert d.alarm
    for kw in ({"threshold": 0.0}, {"threshold": 1.0}, {"hysteresis": -0.1}, {"hysteresis": 0.5}):
        with pytest.raises(ValueError):
            Decision(**kw)


def test_min_consecutive_needs_a_run_above_threshold() -> None:
    from slipd.detect.decision import Decision

    d = Decision(threshold=0.5, min_consecutive=3)
    got = [d.update(p).alarm for p in (0.6, 0.7, 0.4, 0.6, 0.6, 0.6, 0.7)]
    assert got == [False, False, False, False, False, True, True]


def test_a_held_update_does_not_raise_but_keeps_a_raised_alarm() -> None:
    d = Decision(threshold=0.5)
    r = d.update(0.9, may_raise=False)
    assert not r.alarm and not r.rising_edge
    r = d.update(0.9)
    assert r.alarm and r.rising_edge
    assert d.update(0.9, may_raise=False).alarm  # raised stays raised
    assert not d.update(0.1, may_raise=False).alarm  # and clears as usual


def test_the_limit_guard_raises_on_a_run_of_contact_risk_whatever_p_slip_says() -> None:
    d = Decision(threshold=0.5, limit_guard=0.9, limit_guard_decisions=3)
    # A dip below the guard starts the run again; no contact state (None) does too.
    risks = [0.95, 0.95, 0.8, 0.95, None, 0.95, 0.92, 0.99, 0.97, 0.5, 0.2]
    got = [d.advance(0.1, True, r) for r in risks]
    assert [a for a, _ in got] == [False] * 7 + [True, True, False, False]
    assert [e for _, e in got].count(True) == 1
    d.reset()
    for _ in range(3):
        d.advance(0.1, True, 1.0)
    assert d.guarded and d.risk(0.1) == 1.0  # the full reaction while it holds
    d.reset()
    assert not d.guarded and d.risk(0.1) == pytest.approx(0.2)


def test_the_limit_guard_keeps_the_press_hold_and_a_model_alarm() -> None:
    d = Decision(threshold=0.5, limit_guard=0.9, limit_guard_decisions=2)
    assert [d.advance(0.1, False, 1.0)[0] for _ in range(3)] == [False, False, False]  # a press raises nothing
    assert d.advance(0.1, True, 1.0) == (True, True)
    assert d.advance(0.7, True, 0.0)[0]  # the guard let go, the model's own alarm holds it
    off = Decision(threshold=0.5)  # no guard: the contact risk is read by nothing
    assert [off.advance(0.1, True, 1.0)[0] for _ in range(10)] == [False] * 10
    with pytest.raises(ValueError, match="limit_guard"):
        Decision(limit_guard=1.5)


def test_a_guard_switched_off_while_it_holds_lets_go() -> None:
    d = Decision(threshold=0.5, limit_guard=0.9, limit_guard_decisions=1)
    assert d.advance(0.1, True, 1.0) == (True, True) and d.guarded
    d.limit_guard = None  # (a reload's decision section with limit_guard: null)
    assert d.advance(0.1, True, 1.0) == (False, False)
    assert not d.guarded and d.risk(0.1) == pytest.approx(0.2)
