"""Recorder: ring buffer, dump around an alarm, size bound, file modes, crash mid-write."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from slipd.daemon.recorder import DIR_MODE, FILE_MODE, Recorder
from slipd.recording import Recording, list_recordings

ROOT = Path(__file__).resolve().parents[2]
RATE = 1000


def frame(i: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Frame i carries its own index in every value, so a dump shows exactly which frames it holds."""
    force = np.full((9, 3), i, dtype=np.float32)
    force[0, 0] = -i
    disp = np.full((9, 3), i / 1000.0, dtype=np.float32)
    return 1000 * i, force, disp


def feed(rec: Recorder, start: int, stop: int, alarm_at: set[int] = frozenset(), every: int = 40) -> None:
    for i in range(start, stop):
        rec.push_frame(*frame(i))
        if i % every == every - 1 or i in alarm_at:
            rec.push_decision(1000 * i, 0.9 if i in alarm_at else 0.1, i in alarm_at)


def test_a_recording_holds_the_decision_on_its_last_frame(tmp_path):
    """The daemon pushes a deciding frame, then its decisions: a recording that ends on a deciding frame is written
    once they are in (the next block's frames, or ``settle`` at the end of a block), not without them. Replay
    decides on that frame, so a recording without its decision disagreed with replay at the end."""
    rec = Recorder(tmp_path, RATE, seconds_before=0.1, seconds_after=0.05)
    feed(rec, 0, 1050, alarm_at={999}, every=10)  # the alarm frame decides; its stretch ends on frame 1049
    rec.settle()
    rec.close()
    (f,) = list_recordings(tmp_path)
    r = Recording.load(f)
    assert r.t_us[-1] == 1_049_000
    d = r.meta["decisions"]
    assert d["t_us"][-1] == 1_049_000 and d["t_us"] == list(range(909_000, 1_050_000, 10_000))
    # Without ``settle``, the next block's frames write it first, and those frames are not in it.
    rec = Recorder(tmp_path / "b", RATE, seconds_before=0.1, seconds_after=0.05)
    feed(rec, 0, 1060, alarm_at={999}, every=10)
    assert rec.wait() and len(rec.written) == 1
    again = Recording.load(rec.written[0])
    assert again.t_us[-1] == 1_049_000 and again.meta["decisions"]["t_us"][-1] == 1_049_000
    rec.close()


def test_ring_wraps_and_dump_holds_the_stretch_around_the_alarm(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.1, seconds_after=0.05)
    assert rec.capacity == 150
    # Several wraps of the ring before the alarm at frame 1000.
    feed(rec, 0, 1000)
    assert not rec.recording
    feed(rec, 1000, 1001, alarm_at={1000})
    assert rec.recording
    feed(rec, 1001, 1200)
    rec.close()
    files = list_recordings(tmp_path)
    assert len(files) == 1
    r = Recording.load(files[0])
    # 100 frames before the alarm frame ... 49 after it: [alarm - before, alarm + after).
    idx = np.arange(901, 1051)
    np.testing.assert_array_equal(r.t_us, 1000 * idx)
    np.testing.assert_array_equal(r.force[:, 1, 2], idx.astype(np.float32))
    np.testing.assert_array_equal(r.force[:, 0, 0], -idx.astype(np.float32))
    np.testing.assert_allclose(r.disp[:, 8, 1], idx / 1000.0, rtol=1e-6)
    d = r.meta["decisions"]
    assert all(901_000 <= t <= 1_050_000 for t in d["t_us"])
    assert d["t_us"] == sorted(d["t_us"])
    assert 1_000_000 in d["t_us"] and d["alarm"][d["t_us"].index(1_000_000)] is True
    assert r.meta["trigger"]["reason"] == "alarm" and r.meta["trigger"]["t_us"] == 1_000_000
    assert r.events["alarm"] == pytest.approx(0.099)


def test_alarm_early_in_the_stream_and_close_while_recording(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.5, seconds_after=0.5, formats=["npz", "csv"])
    feed(rec, 0, 20, alarm_at={10})
    rec.close()  # stream ended 9 frames after the alarm: a shorter recording, not none
    files = list_recordings(tmp_path)
    assert [f.suffix for f in files] == [".csv", ".npz"]
    for f in files:
        r = Recording.load(f)
        np.testing.assert_array_equal(r.t_us, 1000 * np.arange(20))
        assert r.meta["trigger"]["t_us"] == 10_000


def test_second_alarm_during_recording_is_part_of_it_and_later_one_starts_another(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.05, seconds_after=0.05)
    feed(rec, 0, 300, alarm_at={100, 120, 250})
    rec.close()
    files = list_recordings(tmp_path)
    assert len(files) == 2
    first, second = (Recording.load(f) for f in files)
    assert first.meta["trigger"]["t_us"] == 100_000 and 120_000 in first.meta["decisions"]["t_us"]
    assert second.meta["trigger"]["t_us"] == 250_000


def test_alarm_that_stays_high_extends_one_recording_beyond_the_ring(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.05, seconds_after=0.05, max_episode_s=10.0)
    high = set(range(100, 1000, 10))  # the alarm holds for 0.9 s: six ring lengths
    feed(rec, 0, 1200, alarm_at=high)
    rec.close()
    (f,) = list_recordings(tmp_path)
    r = Recording.load(f)
    # [onset - before, last alarm + after), as for a single alarm: every frame once, in order.
    idx = np.arange(51, 1041)
    np.testing.assert_array_equal(r.t_us, 1000 * idx)
    np.testing.assert_array_equal(r.force[:, 1, 2], idx.astype(np.float32))
    d = r.meta["decisions"]
    assert d["t_us"] == sorted(d["t_us"]) and len(set(d["t_us"])) == len(d["t_us"])
    assert {t // 1000 for t, a in zip(d["t_us"], d["alarm"]) if a} == high
    assert r.meta["trigger"]["t_us"] == 100_000


def test_latched_alarm_for_10_minutes_writes_one_bounded_recording_and_keeps_it(tmp_path):
    rate = 100  # 10 minutes of a 100 Hz stream keep the test fast; the logic counts frames
    rec = Recorder(tmp_path, rate, seconds_before=2.0, seconds_after=1.0, max_total_mb=0.5)
    n = 10 * 60 * rate
    for i in range(n):
        rec.push_frame(*frame(i))
        if i % 4 == 3:
            rec.push_decision(1000 * i, 0.95, i >= 1000)  # rises at frame 1003 and never falls
    rec.wait()
    (f,) = list_recordings(tmp_path)
    r = Recording.load(f)
    assert r.meta["trigger"]["t_us"] == 1_003_000  # the onset is in the recording kept
    assert len(r) == 200 + 30 * rate  # seconds_before + MAX_EPISODE_S: bounded, not 10 minutes
    assert not rec.deleted and len(rec.written) == 1
    # The alarm falls, then rises again: a new episode, a new recording.
    for i in range(n, n + 1000):
        rec.push_frame(*frame(i))
        if i % 4 == 3:
            rec.push_decision(1000 * i, 0.9, i >= n + 500)
    rec.close()
    assert len(rec.written) == 2


def test_trigger_for_failsafe_and_meta(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.01, seconds_after=0.0, meta={"model": "m1"})
    feed(rec, 0, 30)
    assert rec.trigger(29_000, "sensor_stall", stalled_ms=55.0)
    rec.close()
    (f,) = list_recordings(tmp_path)
    r = Recording.load(f)
    assert len(r) == 10 and r.t_us[-1] == 29_000
    assert r.meta["model"] == "m1"
    assert r.meta["trigger"]["reason"] == "sensor_stall" and r.meta["trigger"]["stalled_ms"] == 55.0


def test_modes(tmp_path):
    d = tmp_path / "rec" / "dir"
    rec = Recorder(d, RATE, seconds_before=0.01, seconds_after=0.01, formats=["npz", "csv"])
    feed(rec, 0, 50, alarm_at={20})
    rec.close()
    assert stat.S_IMODE(d.stat().st_mode) == DIR_MODE
    files = list_recordings(d)
    assert len(files) == 2
    for f in files:
        assert stat.S_IMODE(f.stat().st_mode) == FILE_MODE


def test_size_bound_deletes_oldest(tmp_path):
    one = Recorder(tmp_path / "probe", RATE, seconds_before=0.2, seconds_after=0.1)
    feed(one, 0, 400, alarm_at={250})
    one.close()
    size = one.total_bytes()
    assert size > 0
    # Room for about 2.5 recordings: after 6 alarms only the newest 2 remain.
    rec = Recorder(tmp_path / "bounded", RATE, seconds_before=0.2, seconds_after=0.1,
                   max_total_mb=2.5 * size / 2**20, max_pending=16)
    alarms = {400 + 400 * k for k in range(6)}
    feed(rec, 0, 2900, alarm_at=alarms)
    rec.close()
    left = [Recording.load(f) for f in list_recordings(tmp_path / "bounded")]
    assert [r.meta["trigger"]["t_us"] for r in left] == [2000 * 1000, 2400 * 1000]
    assert rec.total_bytes() <= rec.max_total_bytes
    assert len(rec.deleted) == 4 and len(rec.written) == 6


def test_no_allocation_per_sample(tmp_path):
    rec = Recorder(tmp_path, RATE, seconds_before=0.1, seconds_after=0.1)
    buffers = (rec._t, rec._force, rec._disp, rec._dt, rec._dp, rec._da)
    ids = [id(b) for b in buffers]
    feed(rec, 0, 500)
    assert [id(b) for b in (rec._t, rec._force, rec._disp, rec._dt, rec._dp, rec._da)] == ids
    rec.close()


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="formats"):
        Recorder(tmp_path, RATE, formats=["h5"])
    with pytest.raises(ValueError, match="rate_hz"):
        Recorder(tmp_path, 0)


def test_from_config(tmp_path):
    from slipd.config import RecorderConfig

    cfg = RecorderConfig(directory=tmp_path / "r", seconds_before=0.02, seconds_after=0.01, formats=["csv"])
    rec = Recorder.from_config(cfg, RATE)
    feed(rec, 0, 60, alarm_at={30})
    rec.close()
    assert [f.suffix for f in list_recordings(tmp_path / "r")] == [".csv"]


# The child records around an alarm; the write is frozen half-way (the format's writer is patched to
# stop after some bytes and announce it) and the parent kills it with SIGKILL at that moment.
CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    import slipd.recording as recording
    from slipd.daemon.recorder import Recorder

    fmt = {fmt!r}

    def freeze():
        print("MIDWRITE", flush=True)
        time.sleep(60)

    if fmt == "npz":
        def savez(fh, **arrays):
            fh.write(b"PK\\x03\\x04" + b"\\0" * 5000)  # the start of a zip, never finished
            fh.flush()
            freeze()
        recording.np.savez_compressed = savez
    else:
        real_writer = recording.csv.writer
        def writer(fh):
            w = real_writer(fh)
            class Half:
                n = 0
                def writerow(self, row):
                    w.writerow(row)
                    Half.n += 1
                    if Half.n == 50:
                        fh.flush()
                        freeze()
            return Half()
        recording.csv.writer = writer

    rec = Recorder({directory!r}, 1000, seconds_before=0.1, seconds_after=0.1, formats=[fmt])
    for i in range(400):
        rec.push_frame(1000 * i, np.full((9, 3), i, np.float32), np.zeros((9, 3), np.float32))
        if i == 200:
            rec.push_decision(1000 * i, 0.9, True)
    rec.wait(timeout=120)
    """
)


@pytest.mark.parametrize("fmt", ["npz", "csv"])
def test_crash_mid_write_leaves_no_valid_looking_file(tmp_path, fmt):
    d = tmp_path / "rec"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(root=str(ROOT), directory=str(d), fmt=fmt)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "MIDWRITE"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    leftovers = sorted(p.name for p in d.iterdir())
    assert leftovers, "the child should have left its partial file behind"
    assert all(n.endswith((".part", ".tmp")) for n in leftovers), leftovers
    assert list_recordings(d) == []  # replay sees nothing
    # The next recorder on that directory removes the debris.
    Recorder(d, 1000).close()
    assert list(d.iterdir()) == []


def test_slow_disk_drops_recordings_instead_of_queueing_without_bound(tmp_path):
    import threading

    from slipd.daemon.worker import DeviceWorker

    worker = DeviceWorker("recorder-test")
    gate = threading.Event()
    worker.submit(gate.wait, 30)  # the disk "hangs": the worker is busy until the gate opens
    rec = Recorder(tmp_path, RATE, seconds_before=0.01, seconds_after=0.01, worker=worker, max_pending=2)
    feed(rec, 0, 200, alarm_at={20, 60, 100, 140})
    assert rec.dropped == 2
    gate.set()
    rec.close()
    worker.close()
    assert len(list_recordings(tmp_path)) == 2 and rec.failures == 0


def test_each_decision_keeps_its_contact_state_through_a_long_episode(tmp_path):
    """The slip map, contact risk and friction of every decision are in the recording, aligned with the
    decision's time across the ring's spills; None where a decision had no contact state or no friction yet."""
    from slipd.detect.contact import ContactState

    def state(i: int) -> ContactState:
        return ContactState(pillar_slip=tuple((i % 100) / 100 + p / 1000 for p in range(9)),
                            friction=None if i % 3 == 0 else i / 10_000, friction_sd=None, risk=(i % 7) / 7,
                            grip_n=5.0, load_n=1.0)

    rec = Recorder(tmp_path, RATE, seconds_before=0.05, seconds_after=0.05, max_episode_s=10.0)
    for i in range(600):
        rec.push_frame(*frame(i))
        if i % 10 == 9:
            alarm = 100 <= i < 400  # 0.3 s of alarm: the episode outlives the 0.1 s ring
            rec.push_decision(1000 * i, 0.9 if alarm else 0.1, alarm, 0, None if i % 50 == 49 else state(i))
    rec.close()
    (f,) = list_recordings(tmp_path)
    d = Recording.load(f).meta["decisions"]
    assert len(d["t_us"]) > 30 and len(d["pillar_slip"]) == len(d["contact_risk"]) == len(d["t_us"])
    for t, pillars, risk, mu in zip(d["t_us"], d["pillar_slip"], d["contact_risk"], d["friction"]):
        i = t // 1000
        if i % 50 == 49:
            assert pillars is None and risk is None and mu is None
            continue
        s = state(i)
        assert pillars == pytest.approx(list(s.pillar_slip), abs=1e-4) and risk == pytest.approx(s.risk, abs=1e-4)
        assert mu == (None if s.friction is None else pytest.approx(s.friction, abs=1e-4))


def _daemon(recorder: Recorder):
    """The daemon of the simulated rig's config with the shipped model, fed by hand, recording into ``recorder``."""
    from conftest import ROOT

    from slipd.config import load_config, override
    from slipd.daemon.loop import Daemon
    from slipd.detect.ensemble import Ensemble
    from slipd.metrics import Metrics
    from slipd.models import packaged

    cfg = override(load_config(ROOT / "config" / "sim.yaml"), {
        "model.manifest": str(packaged("slip_ensemble_int8")), "model.detector": "onnx", "sensor.tare": "startup",
        "arm.enabled": False, "reaction.actions": ["tighten_gripper"], "reaction.on_failsafe": "log_only"})
    daemon = Daemon(cfg, Ensemble.load(cfg.model.manifest), metrics=Metrics())
    daemon.recorder = recorder
    return daemon


def test_a_fail_safe_writes_what_led_to_it_at_once(tmp_path):
    """Going blind (a stalled or lost sensor, a non-finite burst, an overdue decision) records the seconds before
    the fault straight away: no frame may follow it to complete a stretch after it."""
    daemon = _daemon(Recorder(tmp_path, RATE, seconds_before=0.5, seconds_after=1.0))
    n = 800
    rng = np.random.default_rng(0)
    force = rng.normal(0, 0.01, (n, 1, 9, 3)).astype(np.float32)
    t_us = np.arange(n, dtype=np.int64) * 1000
    for k in range(0, n, 10):
        daemon._on_block(t_us[k : k + 10], force[k : k + 10], np.zeros_like(force[k : k + 10]))
    daemon.liveness.go_blind("sensor_stalled", "no frame for 250 ms")
    daemon.liveness.go_blind("sensor_stalled", "still none")  # the same episode: no second recording
    daemon.recorder.close()
    (f,) = list_recordings(tmp_path)
    r = Recording.load(f)
    assert r.meta["trigger"]["reason"] == "failsafe" and r.meta["trigger"]["cause"] == "sensor_stalled"
    np.testing.assert_array_equal(r.t_us, t_us[n - 500 :])  # the last 0.5 s, up to the last frame handled
    np.testing.assert_array_equal(r.force, force[n - 500 :, 0])


def test_a_fail_safe_during_an_alarm_recording_writes_it_at_once_and_names_it(tmp_path):
    """The recording of an alarm waits for its frames after; a fail-safe on a stalled sensor meanwhile (no frame may
    follow) was refused, so the recording was lost at a kill, or written seconds later with a gap and no word of the
    fail-safe. Now the stretch so far is written at once, and the recording names the fail-safe."""
    rec = Recorder(tmp_path, RATE, seconds_before=0.05, seconds_after=0.5)
    feed(rec, 0, 100, alarm_at={79})
    assert rec.recording
    assert rec.trigger(99_000, "sensor_stall", wait_after=False, stalled_ms=55.0)
    assert not rec.recording
    (f,) = rec.wait(5)
    r = Recording.load(f)
    assert r.meta["trigger"]["reason"] == "alarm" and r.t_us[-1] == 99_000
    (event,) = r.meta["trigger"]["events"]
    assert event["reason"] == "sensor_stall" and event["stalled_ms"] == 55.0
    rec.close()


def test_a_failed_write_leaves_no_staging_file_and_the_size_bound_still_holds(tmp_path, monkeypatch):
    """A full disk failing the CSV of every episode left each one's half-written staging file, outside the size bound,
    and skipped the bound, so the directory grew until a restart."""
    from slipd.daemon import recorder as recorder_mod

    def full_disk(rec, path):
        Path(path).write_bytes(b"x" * 200_000)  # what a write gets out before the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(recorder_mod, "write_sdk_csv", full_disk)
    rec = Recorder(tmp_path, RATE, seconds_before=0.5, seconds_after=0.1, formats=["npz", "csv"], max_total_mb=0.2)
    for ep in range(6):
        feed(rec, ep * 1000, ep * 1000 + 1000, alarm_at={ep * 1000 + 700})
        rec.wait(5)
    rec.close()
    assert rec.failures == 6
    names = [p.name for p in tmp_path.iterdir()]
    assert not [n for n in names if n.endswith((".part", ".tmp"))], names
    assert rec.total_bytes() <= rec.max_total_bytes
    assert sum(p.stat().st_size for p in tmp_path.iterdir()) <= rec.max_total_bytes


def test_a_latched_alarm_on_one_finger_is_one_recording_whatever_the_other_says(tmp_path):
    """With two sensors the latch was one flag: the quiet finger's decisions cleared it, and a finger alarming for
    5 s started a recording every max_episode_s (10 against 1 with one sensor), pushing the onset's out of the quota."""
    rec = Recorder(tmp_path, RATE, seconds_before=0.05, seconds_after=0.05, max_episode_s=0.5, sensors=2)
    force = np.zeros((1, 2, 9, 3), np.float32)
    for i in range(5000):
        rec.push_frames(np.array([1000 * i]), force, force)
        if i % 10 == 9:
            rec.push_decision(1000 * i, 0.1, False, sensor=0)
            rec.push_decision(1000 * i, 0.9, i >= 1000, sensor=1)  # finger 1 alarms from 1 s on, without a break
    rec.close()
    assert len(list_recordings(tmp_path)) == 1


def test_an_alarm_still_up_when_a_short_recording_ends_starts_no_new_one(tmp_path):
    """``seconds_after`` 0 (allowed), or shorter than the decisions' spacing: the recording ends before the next alarm
    decision, and each one started a recording of its own (200 files for a 2 s alarm; the size bound then deleted
    the onset's). The alarm still up at the end latches: one recording until it falls."""
    for after in (0.0, 0.005):
        rec = Recorder(tmp_path / str(after), RATE, seconds_before=0.1, seconds_after=after, max_pending=64)
        feed(rec, 0, 3000, alarm_at=set(range(509, 2500, 10)), every=10)  # one alarm episode of 2 s
        feed(rec, 3000, 3300, alarm_at={3209}, every=10)  # after it fell, a new alarm records again
        rec.close()
        trig = [Recording.load(f).meta["trigger"]["t_us"] for f in list_recordings(tmp_path / str(after))]
        assert trig == [509_000, 3_209_000], (after, trig)


def test_a_break_in_the_stream_ends_the_recording_and_the_next_starts_after_it(tmp_path):
    """A sensor controller that restarts (its clock back at 0; the daemon restarts the detector and tells the recorder)
    must not give a recording that glues both streams: t_us ran backwards (unreadable) and every decision was lost. A
    recording running at the break ends with its frames; one triggered after it starts at the break."""
    rec = Recorder(tmp_path, RATE, seconds_before=2.0, seconds_after=1.0)
    t0 = 3_600_000_000  # an hour of sensor uptime
    f = np.ones((9, 3), np.float32)
    for i in range(3000):
        rec.push_frame(t0 + 1000 * i, f, f)
        if i % 10 == 9:
            rec.push_decision(t0 + 1000 * i, 0.9 if i == 2899 else 0.1, i == 2899)
    rec.restart()  # 100 ms into the first recording's second after
    for i in range(2000):
        rec.push_frame(1000 * i, f, f)
        if i % 10 == 9:
            rec.push_decision(1000 * i, 0.9 if i == 499 else 0.1, i == 499)
        rec.settle()
    rec.close()
    first, second = (Recording.load(p) for p in rec.written)
    assert first.t_us[-1] == t0 + 2_999_000 and first.meta["decisions"]["alarm"].count(True) == 1
    assert second.t_us[0] == 0 and second.t_us[-1] == 1_499_000  # from the break to the alarm's second after
    assert second.meta["decisions"]["alarm"].count(True) == 1 and second.meta["events"]["alarm"] == 0.499


def test_close_keeps_to_its_timeout_whatever_is_pending(tmp_path):
    """A hung disk: close(timeout) returns within its timeout (it waited that long per pending write, then joined the
    worker without a bound), so Daemon.close is not held past systemd's stop timeout."""
    import threading
    import time

    from slipd.daemon import recorder as recorder_mod

    gate = threading.Event()
    real = recorder_mod.Recorder._write

    def slow(self, snap, paths):
        gate.wait(10)
        real(self, snap, paths)

    rec = Recorder(tmp_path, RATE, seconds_before=0.01, seconds_after=0.01, max_pending=8)
    rec._write = slow.__get__(rec)  # type: ignore[method-assign]
    feed(rec, 0, 200, alarm_at={20, 60, 100})
    t = time.monotonic()
    rec.close(timeout=0.5)
    assert time.monotonic() - t < 2.0
    gate.set()


def test_a_state_directory_removed_while_running_comes_back_with_its_mode(tmp_path):
    import shutil

    rec = Recorder(tmp_path / "rec", RATE, seconds_before=0.05, seconds_after=0.05)
    shutil.rmtree(tmp_path / "rec")
    feed(rec, 0, 200, alarm_at={100})
    rec.close()
    assert len(list_recordings(tmp_path / "rec")) == 1 and rec.failures == 0
    assert stat.S_IMODE((tmp_path / "rec").stat().st_mode) == DIR_MODE


def test_the_size_bound_deletes_an_earlier_runs_recordings_before_this_ones(tmp_path):
    """After a reboot with the clock behind (no RTC, NTP not yet synced), this run's recordings are named earlier than
    the last run's: ordered by name, the bound deleted the new ones and kept the stale ones."""
    import time

    one = Recorder(tmp_path / "probe", RATE, seconds_before=0.2, seconds_after=0.1)
    feed(one, 0, 400, alarm_at={250})
    one.close()
    size = one.total_bytes()
    before = Recorder(tmp_path / "rec", RATE, seconds_before=0.2, seconds_after=0.1, max_pending=16)
    feed(before, 0, 1300, alarm_at={400, 800, 1200})
    before.close()
    stale = {p.stem for p in before.written}
    real = time.time
    try:
        time.time = lambda: real() - 86400.0  # type: ignore[assignment]  # the clock a day behind
        after = Recorder(tmp_path / "rec", RATE, seconds_before=0.2, seconds_after=0.1,
                         max_total_mb=3.5 * size / 2**20, max_pending=16)
        feed(after, 0, 1300, alarm_at={400, 800, 1200})
        after.close()
    finally:
        time.time = real  # type: ignore[assignment]
    left = {Path(p).stem for p in list_recordings(tmp_path / "rec")}
    assert {p.stem for p in after.written} <= left and len(left & stale) <= 1, (left, stale)


def test_a_lost_sensor_records_what_led_to_it_and_a_later_alarm_starts_after_the_break(tmp_path):
    """The daemon tells the recorder of every break (``Daemon._restart``): the fail-safe of a lost sensor still writes
    the seconds before the loss (the break cuts only what comes after it), and once frames flow again a recording
    starts at the break."""
    daemon = _daemon(Recorder(tmp_path, RATE, seconds_before=0.5, seconds_after=0.1))
    n = 800
    force = np.random.default_rng(0).normal(0, 0.01, (n, 1, 9, 3)).astype(np.float32)
    t_us = np.arange(n, dtype=np.int64) * 1000 + 3_600_000_000
    for k in range(0, n, 10):
        daemon._on_block(t_us[k : k + 10], force[k : k + 10], np.zeros_like(force[k : k + 10]))
    daemon._on_disconnect("unplugged")
    daemon.recorder.wait()
    (lost,) = (Recording.load(f) for f in list_recordings(tmp_path))
    np.testing.assert_array_equal(lost.t_us, t_us[n - 500 :])
    back = np.arange(300, dtype=np.int64) * 1000  # the controller's clock starts again at 0
    for k in range(0, 300, 10):
        daemon._on_block(back[k : k + 10], force[k : k + 10], np.zeros_like(force[k : k + 10]))
    daemon.recorder.trigger(int(back[-1]), "alarm", sensor=0)
    daemon._on_block(back[:100] + 300_000, force[:100], np.zeros_like(force[:100]))
    daemon.recorder.close()
    newest = Recording.load(sorted(list_recordings(tmp_path))[-1])
    assert newest.t_us[0] == 0 and (np.diff(newest.t_us) > 0).all()


def test_months_of_recordings_keep_the_recorders_lists_and_the_worker_bounded(tmp_path):
    """A soak writes and deletes recordings for hours: the lists of written and deleted files keep the latest
    MAX_KEPT_PATHS, the directory stays within its bound, and the writer thread keeps no recording's frames once it
    is written (one 30-s episode is megabytes)."""
    import gc
    import weakref

    from slipd.daemon.recorder import MAX_KEPT_PATHS

    rec = Recorder(tmp_path, RATE, seconds_before=0.02, seconds_after=0.01, max_total_mb=0.05)
    n = MAX_KEPT_PATHS + 60
    snaps: list[weakref.ref] = []
    submit = rec.worker.submit

    def watched(fn, snap, *a, **k):  # what the writer thread is handed, watched without keeping it alive
        snaps.append(weakref.ref(snap.force))
        return submit(fn, snap, *a, **k)

    rec.worker.submit = watched  # type: ignore[method-assign]
    for k in range(n):
        feed(rec, 40 * k, 40 * k + 40, alarm_at={40 * k + 25})
        rec.settle()
        assert rec.wait() is not None
    assert rec.files_written == n
    assert len(rec.written) == MAX_KEPT_PATHS and len(rec.deleted) == MAX_KEPT_PATHS
    assert rec.written[-1].exists() and not rec.deleted[-1].exists()
    assert rec.total_bytes() <= rec.max_total_bytes
    gc.collect()
    assert len(snaps) == n and all(r() is None for r in snaps)  # the last one's frames released too
    rec.close()
