"""Detector: raw samples in, decisions out. The one path shared by the live loop, replay and evaluation.

    sample [9, 3] -> tare (startup or given) -> FeatureStream -> Ensemble.step -> Decision.update

Tare: with ``tare_samples > 0`` the first ``tare_samples`` samples after a (re)start are averaged
(``slipd.detect.features.tare_offset``) while the sensor is unloaded; they are held back and then pushed
through the pipeline, so the windows are cut exactly as ``batch_windows`` cuts a recording whose
offset comes from the same stretch. With an explicit ``offset`` (or the sensor's own bias command,
offset 0) decisions start at once.

Decision stride: the model's window is fixed (40 samples). With ``stride = window / k`` the feature
stream emits a window every ``stride`` samples and the detector runs ``k`` phase-shifted GRU state
streams, window ``j`` stepping stream ``j mod k``; each stream sees exactly the non-overlapping
window sequence the model was trained on, shifted in phase, and a decision is made every ``stride``
samples.

Contact gate: no contact, no slip. While no pillar's (tared) normal force exceeds the SDK contact
threshold, the model is not stepped: the detector reports p_slip 0 and the GRU states stay at the trained
initial state (h0 = 0), so a daemon started with the gripper open, or an arm moving towards an object,
cannot alarm on sensor noise, and every new contact starts from h0. A change of contact (made or lost)
counts only once it persists beyond ``median // 2`` samples (a run the median filter would remove), so a
dropout frame or a short glitch neither wipes the state in the middle of a grasp nor wakes the model in
free air. ``ContactGate`` is that rule; training (``sliplab.train``) runs the same class over each
recording's windows, so the model learns exactly the sequences the gate lets through.

Press hold: a press loads the pillars, it does not slip them. While the contact's summed (tared) normal force
has risen by more than ``press_rise`` (a share; ``decision.press_rise``, 0.1 by default) over the last window's
span (40 ms), a lowered alarm is not raised; the model still steps, so its state is the same as without the
hold, and a raised alarm is kept.
Under a physics the model never saw (velocity-weakening friction with membrane coupling: the edge pillars
splay while the plate is pressed) the utilisation of a press can look like incipient slip; the normal force
says it is a press. A slip under a grip that is being tightened waits for the tightening to slow: 40 ms at
the 10 % rise a fast grip closes with. ``None`` (a bare ``Detector``'s default, the method's rule) turns the
hold off; ``slipd.detect.build`` sets it from the config.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from slipd.detect.contact import ContactState, ContactStream
from slipd.detect.decision import Detection
from slipd.detect.ensemble import StepError
from slipd.detect.features import FeatureSpec, FeatureStream, tare_offset
from slipd.geometry import CONTACT_THRESHOLD_N

if TYPE_CHECKING:
    from slipd.detect.decision import Decision
    from slipd.detect.ensemble import Ensemble


class SlipDetector(Protocol):
    """What the loop, replay and evaluation need of a detector: the ensemble and the heuristics alike."""

    last_step_s: float | None
    step_seconds: list[float | None]
    clean_block: bool
    """The latest ``push_many``'s samples were all finite, checked on their way through the feature pipeline (False
    where the detector does not know: the loop then checks them itself)."""

    @property
    def windows(self) -> int:
        """Windows the model stepped on since the last contact change."""
        ...

    @property
    def resets(self) -> int:
        """Contact losses and restarts."""
        ...

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """Feed one raw sample [9, 3]; a Detection when a decision is made."""
        ...

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """Feed a block [k, 9, 3]; ``(i, detection)`` for each sample that decided."""
        ...

    def samples_to_decision(self) -> int:
        """Samples still to push until the next decision (1: the very next one)."""
        ...

    def restart(self, retare: bool = False) -> None:
        """Forget history and state (reconnect, counter discontinuity)."""
        ...


class ContactGate:
    """Whether the model may run: contact made and held, with glitch tolerance (see the module docstring).

    ``check`` is called once per completed window with that window's last (tared) normal forces [9]; it
    returns (open, changed): the gate's state after this check, and whether it just flipped.

    Contact is measured against a free-air baseline: while the gate is closed and no pillar is pressed, the
    baseline follows each pillar's normal force with a time constant of ``BASELINE_TAU_S``. A tare drifts
    (temperature; about 0.01 N/s was seen in free air) and a drift past the SDK's 0.5 N must not look like a
    grasp and wake the model. A press loads the pillars within 0.05-2 s, far faster than the baseline moves,
    and the baseline stands still while anything is pressed or the gate is open.
    """

    BASELINE_TAU_S = 5.0

    def __init__(self, tolerance: int, period_s: float) -> None:
        self.tolerance = int(tolerance)
        self._alpha = float(min(1.0, period_s / self.BASELINE_TAU_S))
        self.open = False
        self._since: int | None = None  # sample index of the first check that disagreed with ``open``
        self._baseline = np.zeros(9, np.float64)  # written in place (``MultiDetector`` holds the gates' side by side)

    def touching(self, fz_tared: np.ndarray) -> bool | None:
        """Raw contact of one sample: some pillar above the baseline by the SDK threshold (None: no finite value)."""
        top = top_rise(fz_tared.tolist(), self._baseline.tolist())
        if not math.isfinite(top):  # rare: an infinite pillar (ignored, as a NaN one) or none finite
            rel = np.subtract(fz_tared, self._baseline)  # in float64 (the baseline's type)
            finite = np.isfinite(rel)
            if not finite.any():
                return None
            top = float(np.max(rel[finite]))
        return top > CONTACT_THRESHOLD_N

    def check(self, fz_tared: np.ndarray, index: int) -> tuple[bool, bool]:
        """One check at sample ``index``: update the baseline in free air, then the gate."""
        return self.follow(fz_tared, self.touching(fz_tared), index)

    def follow(self, fz_tared: np.ndarray, touching: bool | None, index: int) -> tuple[bool, bool]:
        """``check`` once the sample's raw contact is known (``touching(fz_tared)``; the fingers of a gripper have
        theirs computed together, ``slipd.detect.multisensor``)."""
        if touching is False and not self.open:
            rel = np.asarray(fz_tared, np.float64) - self._baseline
            ok = np.isfinite(rel)
            # Each step bounded by the contact threshold: free air moves a pillar by noise and drift, and one glitch
            # (a finite -1e6 N, which the features clip but this raw value is not) shifted the baseline by 2000 N and
            # held the gate open for good, the model running in free air.
            thr = CONTACT_THRESHOLD_N
            self._baseline[ok] += self._alpha * np.clip(rel[ok], -thr, thr)
        elif touching is None or touching == self.open:  # ``update``'s common case (a held grasp), without its call
            self._since = None
            return self.open, False
        return self.update(touching, index)

    def update(self, touching: bool | None, index: int) -> tuple[bool, bool]:
        """Feed one check's raw contact (None keeps the state) at sample ``index``."""
        if touching is None or touching == self.open:
            self._since = None
            return self.open, False
        if self._since is None:
            self._since = index
        if index - self._since > self.tolerance:
            self.open, self._since = touching, None
            return self.open, True
        return self.open, False

    def reset(self, retare: bool = True) -> None:
        """No contact known. ``retare``: the sensor was zeroed again (its bias, a start-up tare), so the baseline
        starts at zero again; otherwise (a gap in the stream, the same tare) the drift it followed still stands, and
        zeroing it opened the gate in free air once the drift had passed the threshold."""
        self.open, self._since = False, None
        if retare:
            self._baseline[:] = 0.0


def top_rise(fz_tared: list[float], baseline: list[float]) -> float:
    """The largest rise of a pillar's normal force over its free-air baseline, NaN pillars skipped: what ``np.fmax``
    reduces to over ``fz_tared - baseline`` (float32 values convert to float64 exactly, and each difference is the same
    float64 subtraction) wherever it is finite; -inf where no pillar is finite (NaN there), +-inf where an infinite
    pillar decides. Nine plain floats: a loop costs less than numpy's subtraction and reduction on nine values."""
    top = -math.inf
    for z, b in zip(fz_tared, baseline, strict=True):
        r = z - b
        if r > top:  # (NaN compares False: skipped)
            top = r
    return top


def gate_windows(force_tared: np.ndarray, spec: FeatureSpec) -> np.ndarray:
    """The gate's state at every window ``batch_windows`` cuts from a tared recording [N, 9, 3] (bool [K]).

    The batch twin of the streaming check: the same ``ContactGate`` fed the same window-end samples.
    """
    ends = np.arange(spec.window - 1, len(force_tared), spec.step)
    gate = ContactGate(spec.median // 2, spec.step / spec.rate_hz)
    return np.array([gate.check(force_tared[i, :, 2], int(i))[0] for i in ends], bool)


_ZEROS = np.zeros(9, np.float32)
_ZEROS.flags.writeable = False

PRESS_MIN_N = 0.1
"""A press hold needs a rise of at least 0.1 N as well, so the noise of a light contact does not hold alarms."""


class Detector:
    """Streams samples through the shared feature pipeline, the ensemble and the decision rule.

    ``row``/``rows``: this detector is sensor ``row`` of ``rows`` that share the ensemble
    (``slipd.detect.multisensor``): its GRU states are row ``row`` of the streams stepped with
    ``Ensemble.step_rows``, a stream per window phase (the phase follows from the sample count, the same
    for every sensor), and a contact change resets its row only. None: the one sensor, as before.
    """

    def __init__(
        self,
        ensemble: Ensemble,
        decision: Decision,
        spec: FeatureSpec | None = None,
        offset: np.ndarray | None = None,
        tare_samples: int = 0,
        contact_gate: bool = True,
        *,
        row: int | None = None,
        rows: int = 1,
        press_rise: float | None = None,
    ) -> None:
        self.ensemble = ensemble
        self.row = row
        self.rows = rows
        self.sensor = row or 0
        self.decision = decision
        self.spec = spec or ensemble.feature_spec
        if self.spec.window % self.spec.step:
            raise ValueError(f"stride {self.spec.step} must divide the window {self.spec.window}")
        self.n_streams = self.spec.window // self.spec.step
        self.contact = ContactStream(self.spec, offset)
        """Per-pillar slip, friction, contact risk: windows end with the detector's (``Detection.contact``)."""
        self._shared = self.contact.shares_window(self.spec)
        self.pillar_p: np.ndarray | None = None
        """The model's per-pillar P(slip) on the latest stepped window (SDK order), or None."""
        # Shared: the stream's filtered rows of a window serve the contact state as they are, so the 1 kHz path
        # sanitises, tares and median-filters each sample once, not twice.
        self.features = FeatureStream(self.spec, offset)
        self.tare_samples = 0 if offset is not None else int(tare_samples)
        self._tare_buf = np.zeros((max(self.tare_samples, 1), 9, 3), np.float32)
        self._tare_t = np.zeros(max(self.tare_samples, 1), np.int64)
        self.contact_gate = contact_gate
        self.gate = ContactGate(self.spec.median // 2, self.spec.step / self.spec.rate_hz)
        self.press_rise = press_rise
        # The summed normal force at the ends of the last window/step windows: the oldest is one window back.
        self._loads = [math.nan] * self.n_streams
        self._load_i = 0
        self.pressing = False
        """The press hold is on: the latest window's summed normal force rose by ``press_rise`` in a window."""
        # A window end's tared normal forces and their pressed part (``_gate``: written in place, read at once).
        # (np.nansum costs ten times more on the hot path; add.reduce is ndarray.sum without its Python wrapper; the
        # zeros an array: a scalar operand is the slow loop)
        self._fz = np.zeros(9, np.float32)
        self._fz_pressed = np.zeros(9, np.float32)
        self.index = -1
        self.windows = 0
        self.resets = 0
        self.step_errors = 0
        self.last_step_s: float | None = None
        self.step_seconds: list[float | None] = []
        """Model step time behind each detection the latest ``push_many`` returned (same order)."""
        self.clean_block = False
        """Every sample of the latest ``push_many`` went through the feature stream's common block (finite, within the
        clip: ``FeatureStream.clean``), none through the start-up tare."""
        self._tared = self.tare_samples == 0
        self._n_tare = 0

    @property
    def offset(self) -> np.ndarray:
        """The tare offset in use ([9, 3])."""
        return self.features._offset.reshape(9, 3).copy()

    def set_offset(self, offset: np.ndarray) -> None:
        """A tare offset ([9, 3]) from the next sample on, for the model's windows and the contact state alike: the
        start-up tare's, or the daemon's software zero after a bias taken under a grasp (``slipd.daemon.rezero``; the
        history cut with the old offset is another stream's: restart after it)."""
        self.features.set_offset(offset)
        self.contact.set_offset(self.features._offset.reshape(9, 3))

    def restart(self, retare: bool = False) -> None:
        """After a reconnect or a counter discontinuity: forget the feature history and GRU states. ``retare``: the
        sensor was zeroed again (a start-up tare is taken again; the contact gate's free-air baseline starts at 0)."""
        self.features.reset()
        self.contact.reset()
        self.ensemble.reset()
        self.decision.reset()
        self.windows = 0
        self.gate.reset(retare)
        self._loads = [math.nan] * self.n_streams
        self.pressing = False
        self.resets += 1
        if retare and self.tare_samples:
            self._tared = False
        if not self._tared:
            # A tare under way (or asked for) starts again: samples from before the gap are another stream's.
            self._n_tare = 0

    def samples_to_decision(self) -> int:
        """Samples still to push until the next one that completes a window (1: the very next one).

        During the startup tare every sample may matter (the replay decides at its end): 1.
        """
        if not self._tared:
            return max(1, self.tare_samples - self._n_tare)
        return self.features.samples_to_window()

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """Feed one raw sample; returns a Detection when a window completes, else None (``disp`` unused:
        the model reads forces only; the argument keeps the signature of the heuristic detectors)."""
        self.index += 1
        if not self._tared:
            self._tare_buf[self._n_tare] = force
            self._tare_t[self._n_tare] = t_us
            self._n_tare += 1
            if self._n_tare < self.tare_samples:
                return None
            # Offset known: replay the buffered samples through the pipeline so windows start at the first
            # sample, exactly as the batch path (training, evaluation) cuts them. Windows completed inside the
            # tare stretch step the model (state continuity) but only the last one is reported.
            self.set_offset(tare_offset(self._tare_buf, 0, self.tare_samples))
            self._tared = True
            last = None
            for k in range(self.tare_samples):
                det = self._process(self._tare_buf[k], int(self._tare_t[k]), self.index - self.tare_samples + 1 + k)
                last = det or last
            return last
        return self._process(force, t_us, self.index)

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """Feed a block of raw samples ([k, 9, 3], their ``t_us`` [k]); ``push`` for each, in one pass.

        Returns ``(i, detection)`` for each ``push(force[i], t_us[i])`` that would have returned one, in
        order: the same detections (index, t_us, model state, contact resets) as k calls of ``push``. The
        feature stages run once per block (``FeatureStream.push_many``); the model runs per window.
        ``step_seconds`` holds the model step time behind each returned detection (the inference metric).
        ``disp`` is unused, as in ``push``.
        """
        force = np.asarray(force, dtype=np.float32)
        out: list[tuple[int, Detection]] = []
        self.step_seconds = []
        self.clean_block = False
        i = 0
        while i < len(force) and not self._tared:
            # The start-up tare holds samples back and replays them: rare, sample by sample.
            det = self.push(force[i], int(t_us[i]))
            if det is not None:
                out.append((i, det))
                self.step_seconds.append(self.last_step_s)
            i += 1
        if i == len(force):
            return out
        base = self.index + 1 - i  # sample index of force[0]
        self.index += len(force) - i
        if self._shared:  # (the shipped model's layout: the windows straight from the stream)
            views = self.features.push_views(force[i:])
            self.clean_block = self.features.clean and i == 0
            for j, window, filtered, tared in views:
                k = i + j
                out.append((k, self._decide(window, force[k], int(t_us[k]), base + k, filtered, None, tared)))
                self.step_seconds.append(self.last_step_s)
            return out
        for j, window, _, state in self.feature_windows(force[i:]):
            k = i + j
            out.append((k, self._decide(window, force[k], int(t_us[k]), base + k, None, state)))
            self.step_seconds.append(self.last_step_s)
        return out

    def feature_windows(self, force: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray | None,
                                                                ContactState | None]]:
        """The feature stages on a block of tared-phase samples: ``(i, model window, filtered rows, contact state)``
        for each sample that ends a window (the model is not stepped here; window and rows are views of the feature
        stream's buffers, valid until its next push). A detector that shares its filtered rows with the contact state
        returns them (``contact_state`` turns them into the state once the model has stepped), the state None;
        otherwise the contact stream's own state, the rows None."""
        if self._shared:
            return [(j, w, f, None) for j, w, f, _ in self.features.push_views(force)]
        contact = dict(self.contact.push_many(force))
        return [(j, w, None, contact.get(j)) for j, w, _, _ in self.features.push_views(force)]

    def contact_state(self, filtered: np.ndarray | None, state: ContactState | None) -> ContactState | None:
        """The contact state of a decided window: from the shared ``filtered`` rows, with the model's own
        per-pillar P(slip) where its graph has a per-pillar head and it stepped on this window
        (``pillar_p``), else the feature pipeline's estimate; ``state`` as it is otherwise."""
        if filtered is None:
            return state
        return self.contact.state(filtered, self.pillar_p)

    def _process(self, force: np.ndarray, t_us: int, index: int) -> Detection | None:
        state = None if self._shared else self.contact.push(force)
        window = self.features.push(force)
        if window is None:
            return None
        return self._decide(window, force, t_us, index, self.features.filtered() if self._shared else None, state)

    def _decide(self, window: np.ndarray, force: np.ndarray, t_us: int, index: int, filtered: np.ndarray | None,
                state: ContactState | None, tared: np.ndarray | None = None) -> Detection:
        """A completed window (its last sample ``force``, ``index``): contact gate, model step, decision, and the
        window's contact state (``contact_state`` of ``filtered`` or ``state``). ``tared``: ``force`` tared as the
        feature stream prepared it, every column (``FeatureStream.push_views``), where it is at hand."""
        self.pillar_p = None
        det = self._gate(force, t_us, index, tared)
        if det is not None:
            return det.with_contact(self.contact_state(filtered, state))
        t0 = time.perf_counter()
        if self.row is None:
            try:
                p, pillars = self.ensemble.step_one(window, self.windows % self.n_streams)
                valid = p == p  # (NaN: no decision)
                if valid and pillars is not None:
                    self.set_pillars(pillars)
            except StepError:
                p, valid = float("nan"), False
        else:
            x = np.zeros((self.rows, len(window)), np.float32)
            x[self.row] = window
            active = np.arange(self.rows) == self.row
            ps, _, ok = self.ensemble.step_rows(x, self.phase(self.features.samples_seen), active)
            p, valid = ps[self.row], bool(ok[self.row])
            rows = self.ensemble.pillar_rows
            if valid and rows is not None:
                self.set_pillars(rows[self.row])
        self.last_step_s = time.perf_counter() - t0
        # (``contact_state``, without its call)
        return self._finish(float(p), valid, t_us, index,
                            state if filtered is None else self.contact.state(filtered, self.pillar_p))

    def set_pillars(self, p_pillars: np.ndarray | None) -> None:
        """The model's per-pillar P(slip) on the window just stepped, for the contact state; None where the graph
        has no per-pillar head. Only a shared window reads it (``contact_state``), and sharing means the model's
        pillars are P0..P8 in SDK order (``ContactStream.shares_window``)."""
        self.pillar_p = None if p_pillars is None else np.asarray(p_pillars, np.float64)

    def phase(self, samples: int) -> int:
        """The stream (window phase) of the window that ends at the ``samples``-th sample since the restart."""
        return ((samples - self.spec.window) // self.spec.step) % self.n_streams

    def _gate(self, force: np.ndarray, t_us: int, index: int, tared: np.ndarray | None = None) -> Detection | None:
        """The contact gate on a completed window: its Detection (p 0) while closed, None when the model
        must step. Also tracks the press hold (``pressing``) that ``_finish`` applies. ``tared``: ``force`` tared by
        the feature stream (its 27 values in SDK order), where it is at hand."""
        if self.press_rise is None and not self.contact_gate:
            return None
        # Checked once per window, on its last sample (tared, as the model sees it): the feature stream's prepared row
        # where it hands one over (a finite sample within the clip: the same float32 subtraction, the same values).
        if tared is None:
            fz = np.subtract(np.asarray(force, np.float32).reshape(9, 3)[:, 2], self.features.offset_z, out=self._fz)
        else:
            fz = tared[2::3]
        load = float(np.add.reduce(np.maximum(fz, _ZEROS, out=self._fz_pressed)))
        return self._gated(fz, load, self.gate.touching(fz) if self.contact_gate else None, t_us, index)

    def _gated(self, fz: np.ndarray, load: float, touching: bool | None, t_us: int, index: int) -> Detection | None:
        """``_gate`` on a window end's tared normal forces ``fz`` [9], their summed load (pressed pillars only, the
        press hold's) and raw contact (``ContactGate.touching``): computed here, or for every sensor at once."""
        if self.press_rise is not None:
            self._press(load, self.press_rise)
        if not self.contact_gate:
            return None
        was_open = self.gate.open
        is_open, changed = self.gate.follow(fz, touching, index)
        if changed:
            if not is_open:
                # Released: the next grasp may be another object (the contact state's own release test, no pillar
                # above 0.5 N tared, misses it once the tare has drifted by that much).
                self.contact.release()
            # Made or lost: either way the next contact's first window meets h0, as in training.
            if self.row is None:
                self.ensemble.reset()
            else:
                self.ensemble.reset_row(self.row)
            self.windows = 0
            if was_open:
                self.resets += 1
        if is_open:
            return None
        alarm, rising = self.decision.advance(0.0)
        self.last_step_s = None
        return Detection(index, t_us, 0.0, self.decision.risk(0.0), alarm, rising, True, self.sensor)

    def _press(self, load: float, press_rise: float) -> None:
        """One window end's summed load (the tared normal forces of the pressed pillars; ``_gate``) -> ``pressing``:
        that load against one window back."""
        if not math.isfinite(load):
            load = math.nan  # a non-finite sample: no rise can be measured against it, nor one window on
        before = self._loads[self._load_i]  # the slot written n_streams windows (one window) ago
        self._loads[self._load_i] = load
        self._load_i = (self._load_i + 1) % len(self._loads)
        # NaN (the first window after a restart, a non-finite sample) compares False: no hold.
        rise = load - before
        self.pressing = bool(rise > PRESS_MIN_N and rise > press_rise * before)

    def _finish(self, p_slip: float, valid: bool, t_us: int, index: int,
                contact: ContactState | None = None) -> Detection:
        """The decision on a model step's output (``valid`` False: refused input or non-finite output), with the
        window's ``contact`` state."""
        self.windows += 1
        if not valid:
            # Refused (non-finite window: state kept) or non-finite output (stream reset): no decision.
            self.step_errors += 1
            return Detection(index, t_us, float("nan"), 0.0, bool(self.decision.alarm), False, valid=False,
                             sensor=self.sensor, contact=contact)
        # The members' agreement (``DecisionResult.members_alarming``) is evaluation's: a Detection does not carry it.
        p = float(p_slip)
        decision = self.decision
        alarm, rising = decision.advance(p, not self.pressing, None if contact is None else contact.risk)
        return Detection(index, t_us, p, decision.risk(p), alarm, rising, True, self.sensor, contact)  # (positional)


class HeuristicDetector:
    """A published heuristic (``slipd.detect.baselines``) behind the Detector interface the loop uses."""

    def __init__(self, name: str, params_path: str | Path, offset: np.ndarray | None = None) -> None:
        from slipd.detect.baselines import load_params, make_baseline

        params, frontend = load_params(params_path, name)
        self.name = name
        self._det = make_baseline(name, params, frontend, offset)
        self.contact = ContactStream(FeatureSpec(window=40, stride=10), offset)
        """The contact state, on its own 40 / 10 windows; each detection carries the latest."""
        self.windows = 0
        self.resets = 0
        self.last_step_s: float | None = None
        self.step_seconds: list[float | None] = []
        self.features = None
        self.clean_block = False  # (no feature pipeline checks a heuristic's samples: the loop does)

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """Feed one raw sample (forces and tip displacements); a Detection when the heuristic decides."""
        out = self.push_many(np.asarray(force)[None], [t_us], None if disp is None else np.asarray(disp)[None])
        return out[0][1] if out else None

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """A block of raw samples: ``(i, detection)`` for each that decided (see Detector), the heuristic and the
        contact state each taking the block in one pass; a detection carries the contact state of the latest contact
        window at or before its sample, as a push per sample gives it."""
        force = np.asarray(force)
        latest = self.contact.latest
        states = self.contact.push_many(force)
        dets = self._det.push_many(force, t_us, None if disp is None else np.asarray(disp))
        out = []
        s = 0
        for i, d in dets:
            while s < len(states) and states[s][0] <= i:
                latest = states[s][1]
                s += 1
            out.append((i, d.with_contact(latest)))
        self.windows += len(out)
        self.step_seconds = [None] * len(out)
        return out

    def samples_to_decision(self) -> int:
        """Heuristics may decide on any sample: always 1 (the loop never coalesces reads for them)."""
        return 1

    def restart(self, retare: bool = False) -> None:
        """Forget the history (reconnect, discontinuity)."""
        self._det.restart()
        self.contact.reset()
        self.resets += 1


def run_recording(detector: SlipDetector, force: np.ndarray, t_us: np.ndarray | None = None,
                  disp: np.ndarray | None = None) -> list[Detection]:
    """Push a whole recording through ``detector`` (replay and evaluation); returns every Detection. ``disp``: the
    recorded tip displacements, which the heuristic detectors read (the ensemble reads forces only).

    A recording of several sensors (force [N, S, 9, 3]) goes through ``push_many`` in one block: every
    sensor's detections, in sample then sensor order.
    """
    out = []
    ts = np.arange(len(force), dtype=np.int64) * 1000 if t_us is None else t_us
    if np.ndim(force) == 4:
        return [det for _, det in detector.push_many(force, ts, disp)]
    for i in range(len(force)):
        det = detector.push(force[i], int(ts[i]), None if disp is None else disp[i])
        if det is not None:
            out.append(det)
    return out
