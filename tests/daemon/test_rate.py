"""The rate monitor on its own: counters and clocks as the reader hands them over (unit level; the daemon's use is
proved against the real process in test_run_signals.py)."""

from __future__ import annotations

import numpy as np

from slipd.daemon.rate import WINDOW_S, RateMonitor
from slipd.metrics import Metrics


def _feed(mon: RateMonitor, counter: np.ndarray, t_us: np.ndarray, block: int = 37) -> None:
    for i in range(0, len(counter), block):
        c, t = counter[i:i + block], t_us[i:i + block]
        mon.push(c, t.astype(np.uint64), np.zeros(len(c), bool))


def test_the_rate_is_counted_by_the_controllers_clock_through_a_counter_wrap_and_lost_frames() -> None:
    mon = RateMonitor(1000, 0.1)
    n = 2000
    counter = (np.arange(n, dtype=np.int64) + 2**32 - 500) & 0xFFFFFFFF  # wraps a quarter of the way in
    t_us = np.arange(n, dtype=np.int64) * 2000  # 500 Hz by the controller's clock
    keep = np.ones(n, bool)
    keep[::7] = False  # frames lost on the link: the counter still says how many were sent
    _feed(mon, counter[keep], t_us[keep])
    assert mon.measured is not None and abs(mon.measured - 500) < 1 and mon.outside
    assert mon.jumps == 0


def test_within_tolerance_is_not_outside_and_nothing_is_known_before_a_window() -> None:
    mon = RateMonitor(1000, 0.1)
    n = int(WINDOW_S * 1000) // 2
    _feed(mon, np.arange(n), np.arange(n) * 1000)
    assert not mon.known and not mon.outside
    _feed(mon, np.arange(n, 4 * n), np.arange(n, 4 * n) * 1050)  # 952 Hz: 5 % slow
    assert mon.known and not mon.outside


def test_a_clock_that_runs_back_is_counted_once_per_frame_and_the_window_starts_again() -> None:
    m = Metrics()
    mon = RateMonitor(1000, 0.1, m)
    t_us = 20_000_000 + np.arange(1000) * 1000
    t_us[600:] -= 5_000_000  # back 5 s from frame 600 on
    _feed(mon, np.arange(1000), t_us)
    assert mon.jumps == 1
    assert m.registry.get_sample_value("slipd_timestamp_jumps_total", {"kind": "backwards"}) == 1
    assert mon.measured is not None and abs(mon.measured - 1000) < 1  # measured again after the jump


def test_jumps_are_counted_wherever_they_fall_in_a_block_and_at_a_blocks_edge() -> None:
    # A decision's block of ten frames is checked in plain Python, a long one vectorised: a step that stands still or
    # jumps ahead is counted alike inside either, and between two blocks.
    for block in (10, 100):
        m = Metrics()
        mon = RateMonitor(1000, 0.1, m)
        t_us = np.arange(1000, dtype=np.int64) * 1000
        t_us[305:] += 60_000  # 60 ms ahead within a block: 61 ms for one packet
        t_us[499] = t_us[498]  # stands still at one frame, then runs on
        t_us[600:] += 60_000  # ahead at a block's first frame, against the block before's last
        _feed(mon, np.arange(1000), t_us, block=block)
        assert mon.jumps == 3, block
        assert m.registry.get_sample_value("slipd_timestamp_jumps_total", {"kind": "forward"}) == 2
        assert m.registry.get_sample_value("slipd_timestamp_jumps_total", {"kind": "backwards"}) == 1
        assert mon.measured is not None and abs(mon.measured - 1000) < 1  # measured again after the last


def test_a_step_of_just_jump_s_is_regular_and_one_beyond_it_per_packet_is_a_jump() -> None:
    mon = RateMonitor(1000, 0.1)
    t_us = np.arange(400, dtype=np.int64) * 1000
    t_us[200:] += 49_000  # 50 ms for one packet: within JUMP_S of the counter's 1 ms
    _feed(mon, np.arange(400), t_us, block=10)
    assert mon.jumps == 0
    mon = RateMonitor(1000, 0.1)
    t_us = np.arange(400, dtype=np.int64) * 1000
    t_us[200:] += 50_001  # 51.001 ms: 50.001 ms beyond the counter
    _feed(mon, np.arange(400), t_us, block=10)
    assert mon.jumps == 1


def test_a_reload_of_the_tolerance_judges_the_latest_measurement_again() -> None:
    mon = RateMonitor(1000, 0.1)
    _feed(mon, np.arange(600), np.arange(600) * 1150)  # 870 Hz: 13 % slow
    assert mon.outside
    mon.tolerance = 0.2
    assert not mon.outside
