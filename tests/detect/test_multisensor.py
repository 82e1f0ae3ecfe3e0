"""Two sensors (one per finger): own features, tare, gate, state and decision each; one model call per window."""

import numpy as np
import pytest

from slipd.detect.build import build_detector
from slipd.detect.detector import run_recording
from slipd.detect.ensemble import Ensemble
from slipd.models import SAMPLE_RECORDING
from slipd.recording import Recording

MODELS = ["slip_ensemble", "slip_ensemble_int8"]


@pytest.fixture(scope="module")
def sample() -> Recording:
    return Recording.load(SAMPLE_RECORDING)


@pytest.mark.parametrize("name", MODELS)
def test_finger_1_slips_finger_0_idle_alarm_names_sensor_1_with_the_one_sensor_values(name, sample) -> None:
    from slipd.models import packaged

    ens = Ensemble.load(packaged(name))
    one = run_recording(build_detector(None, ens, tare_samples=100), sample.force, sample.t_us)
    ens.reset()
    idle = np.repeat(sample.force[:1], len(sample), axis=0)  # finger 0 never touches anything
    both = run_recording(build_detector(None, ens, tare_samples=100, sensors=2),
                         np.stack([idle, sample.force], axis=1), sample.t_us)
    assert [d.sensor for d in both] == [0, 1] * len(one)
    s1 = [d for d in both if d.sensor == 1]
    assert [d.index for d in s1] == [d.index for d in one]
    # One finger stepping alone gets what the one-sensor daemon gets (int8 included: the idle row does not
    # move the batch's quantisation range; fp32 kernels for B = 2 may round differently, ~1e-7).
    np.testing.assert_allclose([d.p_slip for d in s1], [d.p_slip for d in one], atol=1e-6, rtol=0)
    assert [d.index for d in s1 if d.rising_edge] == [d.index for d in one if d.rising_edge] != []
    assert not any(d.alarm for d in both if d.sensor == 0)


def test_both_fingers_step_in_one_call_and_keep_their_own_states(sample) -> None:
    from slipd.models import packaged

    ens = Ensemble.load(packaged("slip_ensemble"))
    quiet = sample.force[:700]  # the sample before its motion starts: contact, no slip
    force = np.stack([quiet, sample.force[:700]], axis=1).copy()
    force[:, 0] *= np.float32(0.8)  # a lighter grip on finger 0: different values, its own state
    det = build_detector(None, ens, tare_samples=100, sensors=2)
    calls = []
    step_rows = ens.step_rows

    def counting(x, stream, active):
        calls.append(int(np.count_nonzero(active)))
        return step_rows(x, stream, active)

    ens.step_rows = counting  # type: ignore[method-assign]
    try:
        dets = run_recording(det, force, sample.t_us[:700])
    finally:
        del ens.step_rows
    p0 = [d.p_slip for d in dets if d.sensor == 0 and d.valid]
    p1 = [d.p_slip for d in dets if d.sensor == 1 and d.valid]
    assert max(calls) == 2 and len(calls) < len(dets)  # both rows in one call once both touch
    assert p0 != p1


def test_a_nonfinite_window_is_refused_for_its_row_only() -> None:
    from slipd.models import packaged

    ens = Ensemble.load(packaged("slip_ensemble"))
    d = ens.feature_spec.input_size
    x = np.random.default_rng(0).normal(size=(2, d)).astype(np.float32)
    ens.step_rows(x, 0, np.array([True, True]))
    h = ens.hidden_state(0).copy()
    x[0, 3] = np.nan
    p, _, ok = ens.step_rows(x, 0, np.array([True, True]))
    assert ok.tolist() == [False, True] and np.isnan(p[0]) and np.isfinite(p[1])
    h2 = ens.hidden_state(0)
    assert np.array_equal(h2[:, 0], h[:, 0]) and not np.array_equal(h2[:, 1], h[:, 1])
    assert ens.refused_inputs == 1
    ens.reset_row(1)
    assert not ens.hidden_state(0)[:, 1].any() and np.array_equal(ens.hidden_state(0)[:, 0], h[:, 0])


def test_every_row_stepping_gives_what_the_general_path_gives(monkeypatch) -> None:
    # Both fingers stepping on finite windows (every decision of a grasp) take a shorter path through step_rows; the
    # general one (rows kept aside, outputs checked row by row) must give the same outputs and states, bit for bit.
    import slipd.detect.ensemble as ensemble_mod
    from slipd.models import packaged

    ens = Ensemble.load(packaged("slip_ensemble_int8"))
    x = np.random.default_rng(1).normal(size=(6, 2, ens.feature_spec.input_size)).astype(np.float32)
    both = np.array([True, True])
    checks = []
    exact = ensemble_mod._all_finite

    def counted(a: np.ndarray) -> bool:
        checks.append(a.shape)
        return exact(a)

    monkeypatch.setattr(ensemble_mod, "_all_finite", counted)
    short = [ens.step_rows(w, 0, both) for w in x]
    h_short = ens.hidden_state(0)
    # Each call after the first (which makes the stream on the general path): its windows and outputs in one check.
    assert len(checks) == len(x) - 1
    ens.reset()
    monkeypatch.setattr(ensemble_mod, "_all_finite", lambda a: False)  # never sure: the general path every time
    general = [ens.step_rows(w, 0, both) for w in x]
    for a, b in zip(short, general, strict=True):
        assert all(np.array_equal(u, v) for u, v in zip(a, b, strict=True))
    assert all(ok.all() for _, _, ok in short)
    assert np.array_equal(h_short, ens.hidden_state(0)) and h_short.any()


def test_each_finger_takes_its_own_software_zero() -> None:
    """``set_offset`` ([S, 9, 3]): the daemon's free-air zero after a bias taken under a grasp (slipd.daemon.rezero)."""
    from slipd.models import packaged

    det = build_detector(None, Ensemble.load(packaged("slip_ensemble")), sensors=2)
    zero = np.zeros((2, 9, 3), np.float32)
    zero[0, :, 2], zero[1, :, 0] = -1.5, 0.3
    det.set_offset(zero)
    np.testing.assert_array_equal(det.offset, zero)
    for d, z in zip(det.detectors, zero, strict=True):  # the contact state's stream too, where it cuts its own windows
        np.testing.assert_array_equal(d.contact.features._offset.reshape(9, 3), z)


def test_the_fingers_feature_streams_in_one_pass_give_what_each_stream_gives(sample) -> None:
    # The daemon's blocks (a read of a few frames) go through both fingers' feature streams at once (StreamGroup); the
    # same blocks sensor by sensor must give the same detections, contact states and counters, bit for bit, across a
    # block to sanitise (NaN), one to clip (a glitch), blocks of every size, a restart and a software zero.
    from slipd.models import packaged

    force = np.stack([sample.force[:1500] * np.float32(0.8), sample.force[:1500]], axis=1).copy()
    force[700, 0, 4, 1] = np.nan
    force[900, 1, 2, 2] = 1e6
    t_us = sample.t_us[:1500]
    cuts = np.cumsum(np.random.default_rng(3).integers(1, 45, size=200))
    cuts = cuts[cuts < len(force)]
    runs = []
    for grouped in (True, False):
        ens = Ensemble.load(packaged("slip_ensemble_int8"))
        det = build_detector(None, ens, tare_samples=100, sensors=2)
        assert det._group is not None
        if not grouped:
            det._group = None
        got = []
        for n, (a, b) in enumerate(zip([0, *cuts], [*cuts, len(force)])):
            if n == 40:
                det.restart()
            if n == 60:
                det.set_offset(np.full((2, 9, 3), 0.01, np.float32))
            got += [(a + i, d) for i, d in det.push_many(force[a:b], t_us[a:b])]
        counts = [(f.nonfinite_count, f.clipped_count) for f in det.feature_streams]
        runs.append((got, counts, det.offset))
    (grouped_dets, grouped_counts, grouped_offset), (each_dets, each_counts, each_offset) = runs
    assert len(grouped_dets) > 200 and any(d.contact is not None for _, d in grouped_dets)
    assert grouped_dets == each_dets
    assert grouped_counts == each_counts and grouped_counts[0][0] == 1 and grouped_counts[1][1] >= 1
    np.testing.assert_array_equal(grouped_offset, each_offset)
