"""Several sensors, one model call: a gripper whose two fingers each carry a PapillArray.

Each sensor has its own ``Detector`` (feature stream, tare, contact gate, decision: the one detection
path of ``slipd.detect.detector``), and its own GRU states: row ``s`` of the ensemble's streams. Both
sensors arrive in the same frames, so their windows end on the same samples; for each such sample the
windows of the sensors whose contact gate is open go through the ensemble in **one** call
(``Ensemble.step_rows``, batch B = number of sensors) instead of one call per sensor.

A slip on either finger is a slip of the grasp: every ``Detection`` names its ``sensor``, and the loop
reacts to a rising edge on any of them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from slipd.detect.decision import Detection
from slipd.detect.detector import Detector, top_rise
from slipd.detect.features import FeatureStream, StreamGroup
from slipd.geometry import CONTACT_THRESHOLD_N


class MultiDetector:
    """The detectors of ``len(detectors)`` sensors (``Detector(row=s, rows=S)``) behind the ``SlipDetector``
    interface; samples are [.., S, 9, 3]."""

    def __init__(self, detectors: Sequence[Detector]) -> None:
        if not detectors or any(d.row != s or d.rows != len(detectors) for s, d in enumerate(detectors)):
            raise ValueError("detectors must be rows 0..S-1 of S sharing one ensemble")
        self.detectors = list(detectors)
        self.sensors = len(detectors)
        self._all_rows = np.ones(self.sensors, bool)
        self._all_rows.flags.writeable = False  # handed to every call where all sensors step: nobody may change it
        self._rows: np.ndarray | None = None  # ``_rows_of``'s buffer
        self.ensemble = detectors[0].ensemble
        # Detectors that share their filtered windows with the contact state and filter every column (the shipped
        # model's layout): their feature streams run the common block as one (``StreamGroup``).
        self._group = StreamGroup([d.features for d in self.detectors]) if self.sensors > 1 and all(
            d._shared and d.features._all_cols for d in self.detectors) else None
        # The contact gates' free-air baselines side by side (each gate writes its row in place), and buffers for a
        # window end's tared normal forces of every sensor: ``_gates`` checks all sensors in one pass.
        self._baselines = np.zeros((self.sensors, 9), np.float64)
        for s, d in enumerate(self.detectors):
            self._baselines[s] = d.gate._baseline
            d.gate._baseline = self._baselines[s]
        self._fz_pressed = np.zeros((self.sensors, 9), np.float32)
        self._fz_pressed_flat = self._fz_pressed.reshape(-1)
        self._zeros_flat = np.zeros(self.sensors * 9, np.float32)
        self.last_step_s: float | None = None
        self.step_seconds: list[float | None] = []
        """Model call time behind each returned detection: on the first stepped sensor of a call, None on
        the others (one call, one observation)."""
        self.clean_block = False
        """The latest ``push_many``'s block went through the sensors' streams together, whole (``StreamGroup``: every
        value finite and within the clip), none of it through the start-up tare."""

    def _rows_of(self, windows: list[np.ndarray]) -> np.ndarray:
        """The sensors' windows side by side [S, len]: ``np.stack`` into one buffer kept for the next call (the model
        call copies it into its own input)."""
        rows = self._rows
        if rows is None or rows.shape[1] != len(windows[0]):
            rows = self._rows = np.empty((self.sensors, len(windows[0])), np.float32)
        for s, w in enumerate(windows):
            rows[s] = w
        return rows

    @property
    def windows(self) -> int:
        """Windows the model stepped on since the last contact change, fewest over the sensors."""
        return min(d.windows for d in self.detectors)

    @property
    def resets(self) -> int:
        """Contact losses and restarts, all sensors together."""
        return sum(d.resets for d in self.detectors)

    @property
    def offset(self) -> np.ndarray:
        """The tare offsets in use ([S, 9, 3])."""
        return np.stack([d.offset for d in self.detectors])

    @property
    def feature_streams(self) -> list[FeatureStream]:
        """Each sensor's feature stream (its non-finite and clipped counters)."""
        return [d.features for d in self.detectors]

    def samples_to_decision(self) -> int:
        """Samples still to push until the next decision (the same for every sensor)."""
        return min([d.samples_to_decision() for d in self.detectors])  # (a list: a generator's frames cost more)

    def set_offset(self, offset: np.ndarray) -> None:
        """Each sensor's tare offset ([S, 9, 3]) from the next sample on (``Detector.set_offset``)."""
        for d, o in zip(self.detectors, np.asarray(offset).reshape(self.sensors, 9, 3), strict=True):
            d.set_offset(o)

    def restart(self, retare: bool = False) -> None:
        """Forget every sensor's history and state (reconnect, counter discontinuity)."""
        for d in self.detectors:
            d.restart(retare)

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """Feed one sample [S, 9, 3]; the most urgent of the sensors' detections (a rising edge, then an
        alarm, then the highest p_slip), or None. ``push_many`` returns all of them."""
        dets = [d for _, d in self.push_many(np.asarray(force)[None], [t_us])]
        if not dets:
            return None
        return max(dets, key=lambda d: (d.rising_edge, d.alarm, d.valid, d.p_slip if d.valid else -1.0))

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """Feed a block [k, S, 9, 3]; ``(i, detection)`` for each sensor's decision on sample ``i``, in sample
        then sensor order (``disp`` unused, as in ``Detector``)."""
        x = np.asarray(force, dtype=np.float32)
        subs = self.detectors
        if x.ndim != 4 or x.shape[1:] != (self.sensors, 9, 3):
            raise ValueError(f"force must be [k, {self.sensors}, 9, 3], got {x.shape}")
        k = len(x)
        out: list[tuple[int, Detection]] = []
        self.step_seconds = []
        self.clean_block = False
        i = 0
        while i < k and not self._tared():
            # The start-up tare holds samples back and replays them: rare, sample by sample (each sensor's
            # replayed windows step its own row).
            for s, d in enumerate(subs):
                det = d.push(x[i, s], int(t_us[i]))
                if det is not None:
                    out.append((i, det))
                    self.step_seconds.append(d.last_step_s)
            i += 1
        if i == k:
            return out
        base = subs[0].index + 1 - i  # sample index of x[0]
        n0 = subs[0].features.samples_seen
        nb = subs[0].spec.n_base
        for d in subs:
            d.index += k - i
        # The common block through every sensor's feature stream at once: each window end's model windows and filtered
        # rows of all sensors side by side; otherwise sensor by sensor. Same samples into every stream: the windows end
        # on the same samples.
        block = x[i:] if i else x
        group = self._group.push_views(block) if self._group is not None else None
        self.clean_block = group is not None and i == 0
        if group is None:
            wins = [d.feature_windows(block[:, s]) for s, d in enumerate(subs)]
            ends = [j for j, _, _, _ in wins[0]]
        else:
            ends = [j for j, _, _, _ in group]
        for m, j in enumerate(ends):
            kk = i + j
            t, idx = int(t_us[kk]), base + kk
            gated = self._gates(group[m][3], t, idx) if group is not None else [
                d._gate(x[kk, s], t, idx) for s, d in enumerate(subs)]
            # Every sensor in contact (a grasp, decision after decision): one array made once, no new one per call.
            stepped = gated.count(None)
            active = self._all_rows if stepped == len(gated) else np.array([g is None for g in gated])
            p = ok = None
            step_s: float | None = None
            if stepped:
                if group is not None:
                    # The sensors' model windows in rows, one per sensor (row s is sensor s's window, as its own stream
                    # returns it).
                    batch = self._stacked_rows(group[m][1])
                else:
                    batch = self._rows_of([w[m][1] for w in wins])
                t0 = time.perf_counter()  # the model call alone (the inference metric)
                p, _, ok = self.ensemble.step_rows(batch, subs[0].phase(n0 + j + 1), active)
                step_s = time.perf_counter() - t0
                self.last_step_s = step_s
            # The call's outputs as plain values once (indexing an array per sensor makes a numpy scalar each time).
            ps, oks = (p.tolist(), ok.tolist()) if p is not None and ok is not None else ([], [])
            pillar_rows = self.ensemble.pillar_rows
            for s, d in enumerate(subs):
                det = gated[s]
                f_s: np.ndarray | None
                if group is not None:
                    f_s, state = group[m][2][:, s * nb : (s + 1) * nb], None
                else:
                    f_s, state = wins[s][m][2], wins[s][m][3]
                if det is None:
                    valid = bool(oks[s])
                    if valid and pillar_rows is not None:
                        d.set_pillars(pillar_rows[s])
                    else:
                        d.pillar_p = None
                    # (``Detector.contact_state``, without its call)
                    det = d._finish(float(ps[s]), valid, t, idx,
                                    state if f_s is None else d.contact.state(f_s, d.pillar_p))
                    d.last_step_s = step_s
                    self.step_seconds.append(step_s)
                    step_s = None
                else:
                    self.step_seconds.append(None)
                    d.pillar_p = None
                    det = det.with_contact(d.contact_state(f_s, state))
                out.append((kk, det))
        return out

    def _tared(self) -> bool:
        """Every sensor past its start-up tare (a loop: ``all`` over a generator costs more, once per block)."""
        for d in self.detectors:  # noqa: SIM110 -- the generator costs more
            if not d._tared:
                return False
        return True

    def _gates(self, tared: np.ndarray, t_us: int, index: int) -> list[Detection | None]:
        """Every sensor's ``Detector._gate`` on one window end's frame, tared by the stream group (``tared`` [S * 27],
        the sensors side by side, the prepared row of a common block: finite, within the clip, so the same values as
        the frame less its offsets), the arithmetic of all sensors in one pass (the same operations on the same values,
        row by row)."""
        flat = tared[2::3]  # (every sensor's nine normal forces in a row: 27 columns a sensor, three a pillar)
        np.maximum(flat, self._zeros_flat, out=self._fz_pressed_flat)
        loads = np.add.reduce(self._fz_pressed, axis=1).tolist()
        fz = flat.reshape(self.sensors, 9)
        tops = [top_rise(z, b) for z, b in zip(fz.tolist(), self._baselines.tolist(), strict=True)]
        out: list[Detection | None] = []
        thr = CONTACT_THRESHOLD_N
        for s, d in enumerate(self.detectors):
            if d.press_rise is None and not d.contact_gate:
                out.append(None)
                continue
            top = tops[s]
            if not d.contact_gate:
                touching = None
            elif math.isfinite(top):
                touching = top > thr
            else:  # (rare: an infinite or no finite pillar; ``touching`` tells them apart)
                touching = d.gate.touching(fz[s])
            out.append(d._gated(fz[s], loads[s], touching, t_us, index))
        return out

    def _stacked_rows(self, windows: np.ndarray) -> np.ndarray:
        """A ``StreamGroup`` window (flattened [window, S * n_channels], the sensors side by side per sample) as the
        sensors' model windows in rows [S, window * n_channels], into the buffer ``_rows_of`` keeps."""
        width = len(windows) // self.sensors
        rows = self._rows
        if rows is None or rows.shape[1] != width:
            rows = self._rows = np.empty((self.sensors, width), np.float32)
        t = self.detectors[0].spec.window
        # (slice assignment: np.copyto's copy without its Python-level dispatcher)
        rows.reshape(self.sensors, t, -1)[...] = windows.reshape(t, self.sensors, -1).transpose(1, 0, 2)
        return rows
