"""The members' alarm, and the reference-pillar rule's alarm where the members lean towards a slip.

The rule (``slipd.detect.baselines.ReferencePillarDetector``) sees an incipient slip as soon as a pillar stops
following the heaviest one, often tens of milliseconds before the members call it, but alone it also alarms on
stops and on long holds. Confirmed by the members it keeps their quiet: its alarm counts only while the members'
P(slip) reached ``level`` at one of their decisions in the last ``within_us`` (a decision ``t_m`` with
``t - within_us < t_m <= t``). The fused alarm is the members' alarm or such a confirmed rule alarm; its rising edge
is the reaction's trigger, as with the members alone.

The rule runs only while it can count: from the block in which the members first reach the level until a block ends
past the window. It is then restarted on the last ``HISTORY`` samples before that block (kept in a ring), which is more
than its median, speed lag and confirmation reach back, with its decisions on the same samples as a rule running since
the detector's start (the replay starts on a multiple of its stride), so it decides as if it had run all along. A
still hold with the members near 0 costs the members' path and the ring alone.

Decisions: the members' own (each with the fused alarm), and a decision of the rule's between two of theirs only where
it changes the fused alarm (a contact state, p_slip and risk are the members': such a decision carries the members'
latest p_slip and risk and no contact state). The rule reads the recorded tip displacements where given.

Several sensors (``slipd.detect.multisensor.MultiDetector``): a rule per sensor, each confirmed by that sensor's
members, as each finger decides on its own. The tare: the rule takes the members' start-up tare stretch (its own
inputs averaged over the same samples), or the offset it was built with (the sensor's bias command: zero).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slipd.detect.baselines import ReferencePillarDetector, baseline_samples
from slipd.detect.decision import Detection
from slipd.detect.detector import Detector
from slipd.detect.features import FeatureStream, tare_offset
from slipd.detect.multisensor import MultiDetector
from slipd.geometry import N_PILLARS

HISTORY = 64
"""Raw samples kept for the rule's restart: its median (21), speed lag (10) and stride (5) reach back 36."""
RING = 16 * HISTORY
"""The ring's buffer, in samples."""


class ConfirmedDetector:
    """``model`` (a ``Detector``, or a ``MultiDetector`` of S sensors) and one ``rules[s]`` per sensor behind the
    ``SlipDetector`` interface (see the module)."""

    def __init__(self, model: Detector | MultiDetector, rules: Sequence[ReferencePillarDetector], level: float,
                 within_us: int) -> None:
        if not 0.0 < level <= 1.0:
            raise ValueError(f"confirm level must be in (0, 1], got {level}")
        if within_us <= 0:
            raise ValueError(f"confirm window must be positive, got {within_us} us")
        self.model = model
        self._members: list[Detector] = list(getattr(model, "detectors", [model]))
        self.sensors = len(self._members)
        if len(rules) != self.sensors:
            raise ValueError(f"{len(rules)} rules for {self.sensors} sensors")
        self.rules = list(rules)
        self.level = float(level)
        self.within_us = int(within_us)
        self._stride = rules[0].frontend.spec.step
        s = self.sensors
        # The ring: a linear buffer of many histories, the newest samples at ``_end`` (a block's samples are one copy;
        # the last history moves to the front once the buffer is full).
        self._ring_f = np.zeros((RING, s, N_PILLARS, 3), np.float32)
        self._ring_d = np.zeros((RING, s, N_PILLARS, 3), np.float32)
        self._flat_f = self._ring_f.reshape(RING, -1)  # (the same memory, a sample a row: a block is one copy)
        self._flat_d = self._ring_d.reshape(RING, -1)
        # The members' start-up tare stretch, kept for the rules' own offsets (``_tare_rules``).
        self._tare_n = self._members[0].tare_samples
        self._tare_f = np.zeros((max(self._tare_n, 1), s, N_PILLARS, 3), np.float32)
        self._tare_d = np.zeros((max(self._tare_n, 1), s, N_PILLARS, 3), np.float32)
        self._tare_k = 0
        self._tare_disp = False
        self.last_step_s: float | None = None
        self.step_seconds: list[float | None] = []
        self.clean_block = False
        self.rule_blocks = 0
        """Blocks a rule ran on since the start: a still hold keeps it near 0 (the rule costs nothing there)."""
        self._reset()

    # Where the loop asks about the detector, the members answer (non-finite counters, the tare offset, the decision
    # rule a reload changes in place).
    @property
    def feature_streams(self) -> list[FeatureStream]:
        return [d.features for d in self._members]

    @property
    def detectors(self) -> list[Detector]:
        return self._members

    @property
    def windows(self) -> int:
        return self.model.windows

    @property
    def resets(self) -> int:
        return self.model.resets

    @property
    def offset(self) -> np.ndarray:
        return self.model.offset

    def set_offset(self, offset: np.ndarray) -> None:
        """The members' tare offset (forces: [9, 3], or [S, 9, 3]), and the rules' normal forces' (their tangential
        inputs are the tip displacements, which a force offset does not describe)."""
        self.model.set_offset(offset)
        forces = np.asarray(offset, np.float32).reshape(self.sensors, N_PILLARS, 3)
        for rule, f in zip(self.rules, forces, strict=True):
            rule_offset = rule.frontend.offset.copy()
            rule_offset[:, 2] = f[:, 2]
            rule.frontend.set_offset(rule_offset)

    def restart(self, retare: bool = False) -> None:
        """Forget both parts' history and state (reconnect, counter discontinuity); ``retare`` as the members'."""
        self.model.restart(retare)
        for rule in self.rules:
            rule.restart()
        self._reset()

    def _reset(self) -> None:
        self._tared = self._model_tared()
        if not self._tared:
            self._tare_k = 0  # the members' tare starts (again): so does the rules'
        s = self.sensors
        self._seen = 0  # samples since the start: the rule's decisions fall on multiples of its stride from here
        self._filled = 0  # samples in the ring
        self._end = 0
        self._running = [False] * s
        self._armed_until = [-1] * s  # t_us before which the members' level confirms the rule (exclusive)
        self._m_alarm = [False] * s
        self._m_p = [0.0] * s
        self._m_risk = [0.0] * s
        self._r_alarm = [False] * s
        self._alarm = [False] * s

    def samples_to_decision(self) -> int:
        """The members' next decision, or a running rule's (its alarm may come between theirs)."""
        due = self.model.samples_to_decision()
        for rule, running in zip(self.rules, self._running, strict=True):
            if running:
                due = min(due, rule.frontend.stream.samples_to_window())
        return due

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """One raw sample ([9, 3], or [S, 9, 3]); the latest decision it made, if any (``push_many`` returns all)."""
        out = self.push_many(np.asarray(force)[None], [t_us], None if disp is None else np.asarray(disp)[None])
        return out[-1][1] if out else None

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """A block ([k, 9, 3], or [k, S, 9, 3]; ``disp`` the tip displacements, for the rules): ``(i, detection)`` per
        decision, in sample then sensor order (see the module)."""
        force = np.asarray(force, np.float32)
        k = len(force)
        x = force.reshape(k, self.sensors, N_PILLARS, 3)
        moved = None if disp is None else np.asarray(disp, np.float32).reshape(k, self.sensors, N_PILLARS, 3)
        if not self._tared:
            self._keep_tare(x, moved)
        base = self._members[0].index + 1
        mdets = self.model.push_many(force, t_us)
        if not self._tared and self._model_tared():
            self._tare_rules()
            self._tared = True
        self.clean_block = self.model.clean_block
        msteps = self.model.step_seconds
        self.last_step_s = self.model.last_step_s
        level = self.level
        starting: list[int] = []
        for _, d in mdets:  # (NaN, an invalid decision's p_slip, is below any level)
            if d.p_slip >= level and not self._running[d.sensor] and d.sensor not in starting:
                starting.append(d.sensor)
        if not starting and True not in self._running:
            # The common case, every rule at rest: the fused alarm is the members' (a rule's counts only while it
            # runs), and a detection changes only where the fused rising edge is not the members' own.
            self._keep(x, moved)
            self._seen += k
            m_alarm, fused = self._m_alarm, self._alarm
            for j, (_, md) in enumerate(mdets):
                if md.valid:
                    s = md.sensor
                    m_alarm[s], self._m_p[s], self._m_risk[s] = md.alarm, md.p_slip, md.risk
                    rising = md.alarm and not fused[s]
                    if rising != md.rising_edge:
                        mdets[j] = (mdets[j][0], md._replace(rising_edge=rising))
                    fused[s] = md.alarm
            self.step_seconds = msteps
            return mdets
        for s in starting:
            self._start_rule(s, moved is not None)
        m_at = {(i, md.sensor): a for a, (i, md) in enumerate(mdets)}  # (sample, sensor) -> members' decision
        r_at: dict[tuple[int, int], Detection] = {}  # (sample, sensor) -> the rule's
        for s, rule in enumerate(self.rules):
            if self._running[s]:
                for i, rd in rule.push_many(x[:, s], t_us, None if moved is None else moved[:, s]):
                    r_at[(i, s)] = rd
        self.rule_blocks += 1
        self._keep(x, moved)
        out: list[tuple[int, Detection]] = []
        steps: list[float | None] = []
        for key in sorted(m_at.keys() | r_at.keys()):
            i, s = key
            t = int(t_us[i])
            a = m_at.get(key)
            det = None if a is None else mdets[a][1]
            if det is not None and det.valid:
                self._m_alarm[s], self._m_p[s], self._m_risk[s] = det.alarm, det.p_slip, det.risk
                if det.p_slip >= level:
                    self._armed_until[s] = t + self.within_us
            ruled = r_at.get(key)
            if ruled is not None:
                self._r_alarm[s] = ruled.alarm
            alarm = self._m_alarm[s] or (self._r_alarm[s] and t < self._armed_until[s])
            rising = alarm and not self._alarm[s]
            changed = alarm != self._alarm[s]
            self._alarm[s] = alarm
            rule_only = alarm and not self._m_alarm[s]
            if det is not None:
                if det.valid and (det.alarm != alarm or det.rising_edge != rising or rule_only):
                    det = det._replace(alarm=alarm, rising_edge=rising, rule_only=rule_only)
                out.append((i, det))
                steps.append(None if a is None else msteps[a])
            elif changed:  # a rule decision between the members' that moves the alarm
                out.append((i, Detection(base + i, t, self._m_p[s], self._m_risk[s], alarm, rising, True, s, None,
                                         rule_only)))
                steps.append(None)
        last = int(t_us[-1]) if k else None
        for s in range(self.sensors):
            if self._running[s] and last is not None and last >= self._armed_until[s]:
                self._running[s] = False  # the window has passed: the rule rests until the members reach the level
                self._r_alarm[s] = False
        self._seen += k
        self.step_seconds = steps
        return out

    def _model_tared(self) -> bool:
        for d in self._members:  # noqa: SIM110 -- (a loop: all() over a generator costs more, once per block)
            if not d._tared:
                return False
        return True

    def _keep_tare(self, x: np.ndarray, disp: np.ndarray | None) -> None:
        """Samples of the members' start-up tare stretch, for the rules' own offsets."""
        take = min(len(x), self._tare_n - self._tare_k)
        if take > 0:
            self._tare_f[self._tare_k : self._tare_k + take] = x[:take]
            if disp is not None:
                self._tare_d[self._tare_k : self._tare_k + take] = disp[:take]
                self._tare_disp = True
            self._tare_k += take

    def _tare_rules(self) -> None:
        """The members tared on their stretch: each rule's offset from the same samples (its inputs, as the evaluation
        tares a heuristic on a recording's unloaded stretch)."""
        n = self._tare_k
        for s, rule in enumerate(self.rules):
            samples = baseline_samples(self._tare_f[:n, s], self._tare_d[:n, s] if self._tare_disp else None)
            rule.frontend.set_offset(tare_offset(samples, 0, n))

    def _start_rule(self, s: int, with_disp: bool) -> None:
        """Restart sensor ``s``'s rule on the ring's samples, from the oldest at a multiple of its stride (its decisions
        on the samples of a rule that ran since the start)."""
        rule = self.rules[s]
        rule.restart()
        start = self._seen - self._filled
        skip = (-start) % self._stride
        n = self._filled - skip
        end = self._end
        replayed = rule.push_many(self._ring_f[end - n : end, s], np.zeros(n, np.int64),
                                  self._ring_d[end - n : end, s] if with_disp else None) if n > 0 else []
        self._running[s] = True
        self._r_alarm[s] = bool(replayed and replayed[-1][1].alarm)  # its latest decision's alarm holds until its next

    def _keep(self, x: np.ndarray, disp: np.ndarray | None) -> None:
        """The block's last samples into the ring (oldest first)."""
        k = len(x)
        if k > HISTORY:
            x, k = x[-HISTORY:], HISTORY
            disp = None if disp is None else disp[-HISTORY:]
        elif not k:
            return
        end = self._end
        if end + k > RING:
            keep = min(end, HISTORY - k)
            self._flat_f[:keep] = self._flat_f[end - keep : end]
            self._flat_d[:keep] = self._flat_d[end - keep : end]
            end = keep
        self._flat_f[end : end + k] = x.reshape(k, -1)
        if disp is not None:
            self._flat_d[end : end + k] = disp.reshape(k, -1)
        self._end = end + k
        filled = self._filled + k
        self._filled = filled if filled < HISTORY else HISTORY
