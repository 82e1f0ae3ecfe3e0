"""Two published heuristic incipient-slip detectors, re-implemented as baselines.

Neither paper released code or thresholds; both are written here from their descriptions (as cited by
Wang et al., section I) with every parameter exposed, and tuned by ``tune_*`` on a training split.

Shared front end (``SpeedFrontEnd``): per pillar, the tangential tip deflection ``(dx, dy)`` in mm
(from the sensor's displacement output; or ``(fx, fy) / k_t`` when no displacement is given) and the
normal force ``fz`` go through the daemon's own feature pipeline (``slipd.detect.features``: sanitise, tare,
clip, causal median of 21 samples). Every ``stride`` samples the tangential *deflection speed* of each
pillar is the filtered deflection change over the last ``lag`` samples. While a pillar's tip sticks to
the object its deflection follows the object, so its deflection speed is the object's speed there; once
the tip slides its deflection stops growing and the speed falls. The streaming path (``FeatureStream``)
and the batch path (``batch_windows``, used by the tuner) give bit-identical windows, so both paths
compute the same speeds and the same alarms.

(a) ``ReferencePillarDetector`` (Khamis, Xia, Redmond, ICRA 2021): the in-contact pillar with the
    highest normal force is the reference (it sticks longest); when the reference moves
    (speed >= ``min_ref_speed``) and another in-contact pillar's speed falls below
    ``ratio * reference speed``, that pillar has started to slip: incipient slip. Blind to rotations
    about the reference pillar (it does not move), as the paper notes.
(b) ``DecelerationDetector`` (Ulloa, Bulens, Redmond, IEEE Sensors 2022): a pillar whose speed falls
    below ``drop * (its own maximum over the last memory_s)``, having reached at least ``min_peak_speed``,
    has decelerated; it means incipient slip when at least one other in-contact pillar still moves
    (speed >= ``moving_speed``). Works for rotations too, since every pillar is its own reference.

Both raise the alarm after ``confirm`` consecutive flagged decisions and report a continuous score in
``p_slip``/``risk`` (how far the worst pillar has dropped; 0 when the rule does not apply).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from slipd.detect.decision import Detection
from slipd.detect.features import FeatureSpec, FeatureStream, batch_windows, stretch_offset
from slipd.geometry import CONTACT_THRESHOLD_N, N_PILLARS

_P = TypeVar("_P", "ReferencePillarParams", "DecelerationParams", "FrontEndParams")

TANGENTIAL_STIFFNESS_N_PER_MM = 3.5
"""k_t of a v2 pillar: converts tangential force to deflection when no displacement is recorded."""


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class FrontEndParams:
    """Speed estimation shared by both heuristics.

    stride: samples between decisions (5 -> 200 Hz); lag: samples over which a speed is measured
    (10 ms: long enough to average out 1-sample noise, short against a slip onset); median: the causal
    median width of the feature pipeline; rate_hz: sample rate; contact_n: normal force (N, tared) above
    which a pillar is in contact (the SDK's threshold).
    """

    stride: int = 5
    lag: int = 10
    median: int = 21
    rate_hz: int = 1000
    contact_n: float = CONTACT_THRESHOLD_N


@dataclass(frozen=True)
class ReferencePillarParams:
    """Parameters of the reference-pillar heuristic (speeds in mm/s)."""

    ratio: float = 0.4
    """A pillar slower than ratio * reference speed is slipping."""
    min_ref_speed: float = 1.0
    """The reference must move at least this fast (mm/s), else nothing is judged (holds, stops)."""
    min_pillars: int = 1
    """How many slowed pillars raise a flag."""
    confirm: int = 2
    """Consecutive flagged decisions before the alarm."""


@dataclass(frozen=True)
class DecelerationParams:
    """Parameters of the per-pillar deceleration heuristic (speeds in mm/s)."""

    drop: float = 0.4
    """A pillar below drop * its recent maximum speed has decelerated."""
    min_peak_speed: float = 1.0
    """Its recent maximum must be at least this (mm/s): a pillar that never moved cannot decelerate."""
    moving_speed: float = 1.0
    """Another in-contact pillar at or above this speed (mm/s) is still moving."""
    memory_s: float = 0.2
    """How far back 'recent maximum' looks (s)."""
    confirm: int = 2
    """Consecutive flagged decisions before the alarm."""


# --------------------------------------------------------------------------- front end
def baseline_samples(force: np.ndarray, disp: np.ndarray | None = None) -> np.ndarray:
    """[N, 9, 3] rows of (tangential deflection x, y in mm; fz in N) from raw force and optional disp."""
    force = np.asarray(force, np.float32)
    out = np.empty(force.shape, np.float32)
    if disp is not None:
        out[..., :2] = np.asarray(disp, np.float32)[..., :2]
    else:
        out[..., :2] = force[..., :2] / np.float32(TANGENTIAL_STIFFNESS_N_PER_MM)
    out[..., 2] = force[..., 2]
    return out


class SpeedFrontEnd:
    """Per-pillar tangential deflection speed (mm/s) and normal force (N), every ``stride`` samples."""

    def __init__(self, params: FrontEndParams | None = None, offset: np.ndarray | None = None) -> None:
        self.params = p = params or FrontEndParams()
        if p.lag < 1 or p.stride < 1:
            raise ValueError(f"lag and stride must be >= 1 (got {p.lag}, {p.stride})")
        window = max(p.lag + 1, p.stride)
        self.spec = FeatureSpec(
            pillars=tuple(range(N_PILLARS)), channels=("fx", "fy", "fz"), window=window,
            median=p.median, rate_hz=p.rate_hz, stride=p.stride,
        )
        self.offset = np.zeros((N_PILLARS, 3), np.float32) if offset is None else np.asarray(offset, np.float32)
        self.stream = FeatureStream(self.spec, self.offset)

    def set_offset(self, offset: np.ndarray) -> None:
        """The tare offset ([9, 3] of ``baseline_samples``) from the next sample on."""
        self.offset = np.asarray(offset, np.float32)
        self.stream.set_offset(self.offset)

    def reset(self) -> None:
        """Forget the history (a new recording or reconnect)."""
        self.stream.reset()

    def speeds_from_windows(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[K, W*27] filtered windows -> ([K, 9] tangential speed mm/s, [K, 9] normal force N)."""
        w = windows.reshape(len(windows), self.spec.window, N_PILLARS, 3)
        delta = w[:, -1, :, :2] - w[:, -1 - self.params.lag, :, :2]
        speed = np.hypot(delta[..., 0], delta[..., 1]) * (self.params.rate_hz / self.params.lag)
        return speed.astype(np.float32), w[:, -1, :, 2].copy()

    def push(self, sample: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """One [9, 3] sample of ``baseline_samples``; returns ([9] speed, [9] fz) when a decision is due."""
        win = self.stream.push(sample)
        if win is None:
            return None
        speed, fz = self.speeds_from_windows(win[None])
        return speed[0], fz[0]

    def batch(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whole recording of ``baseline_samples``: ([K, 9] speed, [K, 9] fz, [K] sample index of each decision)."""
        wins, ends = batch_windows(samples, self.spec, self.offset)
        speed, fz = self.speeds_from_windows(wins)
        return speed, fz, ends


# --------------------------------------------------------------------------- rules (vectorised over decisions)
def reference_pillar_flags(
    speed: np.ndarray, fz: np.ndarray, p: ReferencePillarParams, contact_n: float = CONTACT_THRESHOLD_N
) -> tuple[np.ndarray, np.ndarray]:
    """Rule (a) for [K, 9] speeds and normal forces: ([K] flag, [K] score in 0..1)."""
    contact = fz > contact_n
    ref = np.argmax(np.where(contact, fz, -np.inf), axis=1)
    rows = np.arange(len(speed))
    v_ref = speed[rows, ref]
    others = contact.copy()
    others[rows, ref] = False
    judged = contact.any(axis=1) & (v_ref >= p.min_ref_speed)
    ratio = np.where(others, speed / np.maximum(v_ref, 1e-9)[:, None], np.inf)
    slowed = (ratio < p.ratio).sum(axis=1)
    flag = judged & (slowed >= p.min_pillars)
    worst = np.min(ratio, axis=1)
    score = np.where(judged & np.isfinite(worst), np.clip(1.0 - worst, 0.0, 1.0), 0.0)
    return flag, score


def recent_max(speed: np.ndarray, memory: int) -> np.ndarray:
    """[K, 9] maximum of each pillar's speed over the last ``memory`` decisions (including the current)."""
    out = speed.copy()
    for k in range(1, min(memory, len(speed))):
        np.maximum(out[k:], speed[:-k], out=out[k:])
    return out


def deceleration_flags(
    speed: np.ndarray, peak: np.ndarray, fz: np.ndarray, p: DecelerationParams, contact_n: float = CONTACT_THRESHOLD_N
) -> tuple[np.ndarray, np.ndarray]:
    """Rule (b) for [K, 9] speeds, their recent maxima and normal forces: ([K] flag, [K] score in 0..1)."""
    contact = fz > contact_n
    decel = contact & (peak >= p.min_peak_speed) & (speed < p.drop * peak)
    moving = contact & (speed >= p.moving_speed)
    # Another pillar moves: some moving pillar other than a decelerated one. A pillar cannot be both,
    # since drop * peak <= peak, so "any moving" while "any decelerated" means a different pillar moves.
    flag = decel.any(axis=1) & moving.any(axis=1)
    drop_depth = np.where(decel, 1.0 - speed / np.maximum(peak, 1e-9), 0.0)
    score = np.where(moving.any(axis=1), drop_depth.max(axis=1), 0.0)
    return np.asarray(flag), np.clip(score, 0.0, 1.0)


def confirm_flags(flag: np.ndarray, confirm: int) -> np.ndarray:
    """Alarm where the last ``confirm`` decisions (including this one) were all flagged."""
    if confirm <= 1:
        return flag.copy()
    idx = np.arange(len(flag))
    last_clear = np.maximum.accumulate(np.where(~flag, idx, -1))
    return flag & (idx - last_clear >= confirm)


def _memory_decisions(p: DecelerationParams, fe: FrontEndParams) -> int:
    return max(1, round(p.memory_s * fe.rate_hz / fe.stride))


# --------------------------------------------------------------------------- detectors
class _HeuristicDetector:
    """Common streaming machinery: same interface as ``slipd.detect.detector.Detector``."""

    name = "heuristic"
    params: Any  # each subclass's own parameter dataclass

    def __init__(self, frontend: FrontEndParams | None, offset: np.ndarray | None, history: int) -> None:
        self.frontend = SpeedFrontEnd(frontend, offset)
        self.index = -1
        # The last ``history`` speed rows, oldest first. Speeds are >= 0 and the rows start at 0, so a maximum over
        # them is the maximum over the rows seen so far.
        self._recent = np.zeros((history, N_PILLARS), np.float32)
        self._run = 0
        self._alarm = False
        self._confirm = 1

    def restart(self, retare: bool = False) -> None:
        """Forget all history (``retare`` is accepted for interface parity; the offset is kept)."""
        self.frontend.reset()
        self._recent[:] = 0
        self._run = 0
        self._alarm = False

    def push(self, force: np.ndarray, t_us: int = 0, disp: np.ndarray | None = None) -> Detection | None:
        """Feed one raw sample ([9, 3] force, optional [9, 3] displacement); a Detection every ``stride`` samples."""
        out = self.push_many(np.asarray(force)[None], [t_us], None if disp is None else np.asarray(disp)[None])
        return out[0][1] if out else None

    def push_many(self, force: np.ndarray, t_us: Sequence[int] | np.ndarray,
                  disp: np.ndarray | None = None) -> list[tuple[int, Detection]]:
        """A block of raw samples ([k, 9, 3] force, optional [k, 9, 3] displacement): ``(i, detection)`` for each
        sample ``i`` that decides. The front end takes the block in one pass (``FeatureStream.push_many``: the same
        windows, bit for bit, as one push per sample) and the rule runs on all of its decisions at once; only the
        confirmation count goes decision by decision. A daemon reading 1 kHz then pays per block, not per sample."""
        force = np.asarray(force)
        k = len(force)
        base = self.index + 1
        self.index += k
        if not k:
            return []
        wins = self.frontend.stream.push_many(baseline_samples(force, None if disp is None else np.asarray(disp)))
        if not wins:
            return []
        speed, fz = self.frontend.speeds_from_windows(np.stack([w for _, w in wins]))
        flags, scores = self._rule_on_block(speed, fz)
        out = []
        confirm = max(1, self._confirm)
        for (i, _), flag, score in zip(wins, flags.tolist(), scores.tolist(), strict=True):
            self._run = self._run + 1 if flag else 0
            alarm = self._run >= confirm
            rising = alarm and not self._alarm
            self._alarm = alarm
            out.append((i, Detection(base + i, int(t_us[i]), float(score), float(score), bool(alarm), bool(rising))))
        return out

    def _rule_on_block(self, speed: np.ndarray, fz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rule on a block's decisions in order ([K, 9] speeds and normal forces), each with the speeds of the
        decisions before it: ([K] flag, [K] score). Keeps the last ``history`` speeds for the next block."""
        h = len(self._recent)
        rows = np.concatenate([self._recent, speed])  # decision j's history: the h rows that end with its own
        flags, scores = self._rule_rows(speed, fz, rows)
        self._recent = rows[-h:].copy()
        return flags, scores

    def run(self, force: np.ndarray, disp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batch path over a whole recording: ([K] sample index, [K] alarm, [K] score). Same result as ``push``."""
        speed, fz, ends = self.frontend.batch(baseline_samples(force, disp))
        flag, score = self._batch_rule(speed, fz)
        return ends, confirm_flags(flag, self._confirm), score

    # Subclass hooks: the rule on a block's decisions (``history``: the speeds kept from before, oldest first, then the
    # block's own: decision j's recent speeds are rows j + 1 .. j + h) and on a whole recording.
    def _rule_rows(self, speed: np.ndarray, fz: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _batch_rule(self, speed: np.ndarray, fz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class ReferencePillarDetector(_HeuristicDetector):
    """Khamis-style reference-pillar velocity-drop detector (see the module docstring)."""

    name = "reference_pillar"
    params: ReferencePillarParams

    def __init__(
        self,
        params: ReferencePillarParams | None = None,
        frontend: FrontEndParams | None = None,
        offset: np.ndarray | None = None,
    ) -> None:
        super().__init__(frontend, offset, history=1)
        self.params = params or ReferencePillarParams()
        self._confirm = self.params.confirm

    def _rule_rows(self, speed: np.ndarray, fz: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return reference_pillar_flags(speed, fz, self.params, self.frontend.params.contact_n)

    def _batch_rule(self, speed: np.ndarray, fz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return reference_pillar_flags(speed, fz, self.params, self.frontend.params.contact_n)


class DecelerationDetector(_HeuristicDetector):
    """Ulloa-style per-pillar deceleration detector (see the module docstring)."""

    name = "deceleration"
    params: DecelerationParams

    def __init__(
        self,
        params: DecelerationParams | None = None,
        frontend: FrontEndParams | None = None,
        offset: np.ndarray | None = None,
    ) -> None:
        fe = frontend or FrontEndParams()
        self.params = params or DecelerationParams()
        super().__init__(fe, offset, history=_memory_decisions(self.params, fe))
        self._confirm = self.params.confirm

    def _rule_rows(self, speed: np.ndarray, fz: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h = len(self._recent)
        # Each decision's maximum over its last h speeds, its own included (a few decisions a block: one reduction
        # each costs less than ``recent_max``'s h passes).
        peak = np.stack([history[j + 1 : j + 1 + h].max(axis=0) for j in range(len(speed))])
        return deceleration_flags(speed, peak, fz, self.params, self.frontend.params.contact_n)

    def _batch_rule(self, speed: np.ndarray, fz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        peak = recent_max(speed, _memory_decisions(self.params, self.frontend.params))
        return deceleration_flags(speed, peak, fz, self.params, self.frontend.params.contact_n)


BASELINES = {"reference_pillar": (ReferencePillarDetector, ReferencePillarParams),
             "deceleration": (DecelerationDetector, DecelerationParams)}
CONFIRMED_RULE = "reference_pillar"
"""The heuristic the model confirms (``slipd.detect.confirmed``, ``decision.confirm_rule``)."""


def make_baseline(
    name: str, params: dict[str, Any] | None = None, frontend: dict[str, Any] | None = None,
    offset: np.ndarray | None = None,
) -> _HeuristicDetector:
    """Build a baseline detector by name from plain dicts (as stored in the tuned JSON).

    Raises ValueError naming the baseline and the unknown parameter.
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; choose from {sorted(BASELINES)}")
    fe = _from_dict(FrontEndParams, frontend or {}, "frontend")
    if name == "reference_pillar":
        return ReferencePillarDetector(_from_dict(ReferencePillarParams, params or {}, name), fe, offset)
    return DecelerationDetector(_from_dict(DecelerationParams, params or {}, name), fe, offset)


def _from_dict(cls: type[_P], d: Mapping[str, Any], where: str) -> _P:
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{where}: unknown parameter(s) {unknown}; known: {sorted(known)}")
    return cls(**d)


def baseline_offset(force: np.ndarray, disp: np.ndarray | None, stretch: tuple[int, int]) -> np.ndarray:
    """Tare offset of the baseline samples over an unloaded ``stretch`` [start, stop) of a recording."""
    return stretch_offset(baseline_samples(force, disp), stretch)


# --------------------------------------------------------------------------- tuned parameters on disk
def save_params(path: str | Path, tuned: dict[str, Any]) -> Path:
    """Write ``{name: {"params": {...}, "frontend": {...}, ...}}`` as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(tuned, indent=2, sort_keys=True) + "\n")
    return path


def load_params(path: str | Path, name: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """(params, frontend) of baseline ``name`` from a tuned JSON file; errors name the file and key."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read baseline parameters ({exc})") from exc
    if name not in data:
        raise ValueError(f"{path}: no entry {name!r} (has {sorted(data)})")
    entry = data[name]
    return dict(entry.get("params", {})), dict(entry.get("frontend", {}))


def params_dict(det: _HeuristicDetector) -> dict[str, Any]:
    """The detector's parameters as plain dicts (for reports and the tuned JSON)."""
    return {"params": asdict(det.params), "frontend": asdict(det.frontend.params)}
