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
latest p_slip and risk and no contact state). One sensor; the rule reads the recorded tip displacements where given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slipd.detect.baselines import ReferencePillarDetector
from slipd.detect.decision import Decision, Detection
from slipd.detect.detector import Detector
from slipd.detect.features import FeatureStream
from slipd.geometry import N_PILLARS

HISTORY = 64
"""Raw samples kept for the rule's restart: its median (21), speed lag (10) and stride (5) reach back 36."""
RING = 16 * HISTORY
"""The ring's buffer, in samples."""


class ConfirmedDetector:
    """``model`` (one sensor's ``Detector``) and ``rule`` behind the ``SlipDetector`` interface (see the module)."""

    def __init__(self, model: Detector, rule: ReferencePillarDetector, level: float, within_us: int) -> None:
        if not 0.0 < level <= 1.0:
            raise ValueError(f"confirm level must be in (0, 1], got {level}")
        if within_us <= 0:
            raise ValueError(f"confirm window must be positive, got {within_us} us")
        self.model = model
        self.rule = rule
        self.level = float(level)
        self.within_us = int(within_us)
        self._stride = rule.frontend.spec.step
        # The ring: a linear buffer of many histories, the newest samples at ``_end`` (a block's samples are one copy;
        # the last history moves to the front once the buffer is full).
        self._ring_f = np.zeros((RING, N_PILLARS, 3), np.float32)
        self._ring_d = np.zeros((RING, N_PILLARS, 3), np.float32)
        self._end = 0
        self.last_step_s: float | None = None
        self.step_seconds: list[float | None] = []
        self.clean_block = False
        self.rule_blocks = 0
        """Blocks the rule ran on since the start: a still hold keeps it near 0 (the rule costs nothing there)."""
        self.restart()

    # The members' pipeline stands for the detector where the loop asks (non-finite counters, the tare offset).
    @property
    def features(self) -> FeatureStream:
        return self.model.features

    @property
    def decision(self) -> Decision:
        """The members' decision rule (a reload changes it in place)."""
        return self.model.decision

    @property
    def press_rise(self) -> float | None:
        return self.model.press_rise

    @press_rise.setter
    def press_rise(self, value: float | None) -> None:
        self.model.press_rise = value

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
        """The members' tare offset ([9, 3] forces), and the rule's normal forces' (its tangential inputs are the
        tip displacements, which a force offset does not describe)."""
        self.model.set_offset(offset)
        rule_offset = self.rule.frontend.offset.copy()
        rule_offset[:, 2] = np.asarray(offset, np.float32).reshape(N_PILLARS, 3)[:, 2]
        self.rule.frontend.offset = rule_offset
        self.rule.frontend.stream.set_offset(rule_offset)

    def restart(self, retare: bool = False) -> None:
        """Forget both parts' history and state (reconnect, counter discontinuity)."""
        if hasattr(self, "_seen"):  # (the model starts fresh when built)
            self.model.restart(retare)
        self.rule.restart()
        self._seen = 0  # samples since the start: the rule's decisions fall on multiples of its stride from here
        self._filled = 0  # samples in the ring
        self._end = 0
        self._running = False
        self._armed_until = -1  # t_us before which the members' level confirms the rule (exclusive)
        self._m_alarm = False
        self._m_p = 0.0
        self._m_risk = 0.0
        self._r_alarm = False
        self._alarm = False

    def samples_to_decision(self) -> int:
        """The members' next decision, or the rule's while it runs (its alarm may come between theirs)."""
        due = self.model.samples_to_decision()
        if self._running:
            spec, n = self.rule.frontend.spec, self.rule.frontend.stream.samples_seen
            rule_due = spec.window - n if n < spec.window else spec.step - (n - spec.window) % spec.step
            due = min(due, rule_due)
        return due

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """One raw sample [9, 3]; the latest decision it made, if any (``push_many`` returns all)."""
        out = self.push_many(np.asarray(force)[None], [t_us], None if disp is None else np.asarray(disp)[None])
        return out[-1][1] if out else None

    def push_many(
        self, force: np.ndarray, t_us: Sequence[int] | np.ndarray, disp: np.ndarray | Sequence[np.ndarray] | None = None
    ) -> list[tuple[int, Detection]]:
        """A block [k, 9, 3] (``disp`` the tip displacements, for the rule): ``(i, detection)`` per decision, in
        sample order (see the module)."""
        force = np.asarray(force, np.float32)
        moved = None if disp is None else np.asarray(disp, np.float32)
        k = len(force)
        base = self.model.index + 1
        mdets = self.model.push_many(force, t_us)
        self.clean_block = self.model.clean_block
        msteps = self.model.step_seconds
        level = self.level
        start = self._running
        if not start:
            for _, d in mdets:  # (NaN, an invalid decision's p_slip, is below any level)
                if d.p_slip >= level:
                    start = True
                    break
        if not start:
            # The common case, the rule at rest: the fused alarm is the members' (the rule's counts only while it
            # runs), and a detection changes only where the fused rising edge is not the members' own.
            self._keep(force, moved)
            self._seen += k
            for j, (_, md) in enumerate(mdets):
                if md.valid:
                    self._m_alarm, self._m_p, self._m_risk = md.alarm, md.p_slip, md.risk
                    rising = md.alarm and not self._alarm
                    if rising != md.rising_edge:
                        mdets[j] = (mdets[j][0], md._replace(rising_edge=rising))
                    self._alarm = md.alarm
            self.step_seconds = msteps
            self.last_step_s = self.model.last_step_s
            return mdets
        if not self._running:
            self._start_rule(moved is not None)
        rdets = self.rule.push_many(force, t_us, moved)
        self.rule_blocks += 1
        self._keep(force, moved)
        out: list[tuple[int, Detection]] = []
        steps: list[float | None] = []
        a = r = 0
        while a < len(mdets) or r < len(rdets):
            i = min(mdets[a][0] if a < len(mdets) else k, rdets[r][0] if r < len(rdets) else k)
            t = int(t_us[i])
            det: Detection | None = None
            if a < len(mdets) and mdets[a][0] == i:
                det, step = mdets[a][1], msteps[a]
                a += 1
                if det.valid:
                    self._m_alarm, self._m_p, self._m_risk = det.alarm, det.p_slip, det.risk
                    if det.p_slip >= level:
                        self._armed_until = t + self.within_us
            if r < len(rdets) and rdets[r][0] == i:
                self._r_alarm = rdets[r][1].alarm
                r += 1
            alarm = self._m_alarm or (self._r_alarm and t < self._armed_until)
            rising = alarm and not self._alarm
            changed = alarm != self._alarm
            self._alarm = alarm
            if det is not None:
                if det.valid:
                    det = det._replace(alarm=alarm, rising_edge=rising)
                out.append((i, det))
                steps.append(step)
            elif changed:  # a rule decision between the members' that moves the alarm
                out.append((i, Detection(base + i, t, self._m_p, self._m_risk, alarm, rising)))
                steps.append(None)
        if self._running and k and int(t_us[-1]) >= self._armed_until:
            self._running = False  # the window has passed: the rule rests until the members reach the level again
            self._r_alarm = False
        self._seen += k
        self.step_seconds = steps
        self.last_step_s = self.model.last_step_s
        return out

    def _start_rule(self, with_disp: bool) -> None:
        """Restart the rule on the ring's samples, from the oldest at a multiple of its stride (its decisions on the
        samples of a rule that ran since the start)."""
        self.rule.restart()
        start = self._seen - self._filled
        skip = (-start) % self._stride
        n = self._filled - skip
        end = self._end
        replayed = self.rule.push_many(self._ring_f[end - n : end], np.zeros(n, np.int64),
                                       self._ring_d[end - n : end] if with_disp else None) if n > 0 else []
        self._running = True
        self._r_alarm = bool(replayed and replayed[-1][1].alarm)  # its latest decision's alarm holds until its next

    def _keep(self, force: np.ndarray, disp: np.ndarray | None) -> None:
        """The block's last samples into the ring (oldest first)."""
        k = min(len(force), HISTORY)
        if not k:
            return
        end = self._end
        if end + k > RING:
            keep = min(end, HISTORY - k)
            self._ring_f[:keep] = self._ring_f[end - keep : end]
            self._ring_d[:keep] = self._ring_d[end - keep : end]
            end = keep
        self._ring_f[end : end + k] = force[-k:]
        if disp is not None:
            self._ring_d[end : end + k] = disp[-k:]
        self._end = end + k
        self._filled = min(HISTORY, self._filled + k)
