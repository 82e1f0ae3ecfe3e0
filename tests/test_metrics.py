"""The decision path's own collectors serve what prometheus_client's Histogram and Counter serve."""

from __future__ import annotations

import pytest
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest

from slipd.metrics import FAST_BUCKETS, DecisionCounter, DecisionHistogram, Metrics


def _series(registry: CollectorRegistry) -> list[str]:
    """The exposition's sample lines, without ``_created`` (the library's own collectors add it; ours do not)."""
    text = generate_latest(registry).decode()
    return [line for line in text.splitlines() if line and not line.startswith("#") and "_created" not in line]


def test_a_decision_histogram_serves_what_a_histogram_serves() -> None:
    ours, theirs = CollectorRegistry(), CollectorRegistry()
    h = DecisionHistogram("x_seconds", "doc", FAST_BUCKETS, ours)
    ref = Histogram("x_seconds", "doc", buckets=FAST_BUCKETS, registry=theirs)
    # Below the first bound, on bounds (le: counted in that bucket), between them, beyond the last, zero.
    values = [1e-6, 25e-6, 26e-6, 1e-4, 1.2e-3, 0.1, 0.5, 0.0, 3e-3, 3e-3]
    for v in values:
        h.observe(v)
        ref.observe(v)
    assert _series(ours) == _series(theirs)
    assert 'x_seconds_bucket{le="2.5e-05"} 3.0' in _series(ours) and "x_seconds_count 10.0" in _series(ours)


def test_a_decision_counter_serves_what_a_counter_serves() -> None:
    ours, theirs = CollectorRegistry(), CollectorRegistry()
    c = DecisionCounter("n", "doc", "sensor", ours)
    ref = Counter("n", "doc", ["sensor"], registry=theirs)
    children = [(c.labels(sensor="0"), ref.labels(sensor="0")), (c.labels(sensor="1"), ref.labels(sensor="1"))]
    assert _series(ours) == _series(theirs) == ['n_total{sensor="0"} 0.0', 'n_total{sensor="1"} 0.0']
    for k in range(5):
        a, b = children[k % 2]
        a.inc()
        b.inc()
    assert c.labels(sensor="0") is children[0][0]  # one child per value, kept
    assert _series(ours) == _series(theirs) == ['n_total{sensor="0"} 3.0', 'n_total{sensor="1"} 2.0']
    with pytest.raises(ValueError, match="one label, sensor"):
        c.labels(finger="0")


def test_the_registry_still_refuses_a_second_metric_of_the_same_name() -> None:
    m = Metrics()
    for name in ("slipd_decisions", "slipd_loop_duration_seconds", "slipd_inference_duration_seconds"):
        with pytest.raises(ValueError, match="Duplicated timeseries"):
            Counter(name, "doc", registry=m.registry)
