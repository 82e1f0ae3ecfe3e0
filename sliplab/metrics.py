"""The method's evaluation metrics as pure functions over (scene truth, decisions).

Definitions (``../shared/reference/method.md`` "Metrics", paper section IV):

offline success
    A *slip* sequence is a true positive when its **first** alarm falls in
    ``[onset - 0.3 s, gross-slip time]``; an alarm before that window is ``early``, one after it
    ``late``, none at all ``missed``. A *stop* (or hold) sequence is a true negative when it has no
    alarm at all, else a false positive. A *partial* sequence (some pillars slid and stuck again, the grasp
    held) has no outcome under either criterion; how many of them alarmed is counted apart.
confusion matrix
    Rows: truth (slip / stop); columns: outcome (detected in time / not). ``tp`` + ``fn`` = slip
    sequences (``fn`` = early + late + missed), ``fp`` + ``tn`` = stop sequences.
detection latency
    first alarm time - labelled onset, over the true positives (the paper's figure 4c); negative
    means the alarm came before the labelled onset (allowed down to -0.3 s).
online success (gripper / transfer scenes)
    A slip trial succeeds when its first alarm falls between motion start ``T_m`` and gross slip
    ``T_g``; gross slip is the first time the object's motion relative to the finger exceeds 2 mm
    (translation) or 2 deg (rotation). A stop trial succeeds when it has no alarm. Trials keep their
    design label (slip / stop) as in the paper; a slip trial whose object never passes 2 mm / 2 deg
    has ``T_g`` = the end of the recording.
D_norm
    Object displacement relative to the finger at the first alarm divided by 2 mm, or its rotation
    divided by 2 deg; the mean of both for combined motions. (The paper normalises the *robot's*
    displacement since ``T_m``; the simulator gives us the relative object motion, which is what the
    threshold of gross slip is defined on, so D_norm <= 1 exactly when the alarm precedes T_g.)
false alarms per hour
    Rising edges of the alarm on no-slip recordings (stop and hold scenes) divided by their total
    duration.

Times are seconds from a recording's first sample, like the ``events`` in a recording's meta.
Everything returned is a dataclass whose ``to_dict()`` is JSON-serialisable.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

EARLY_TOLERANCE_S = 0.3
"""Alarms up to this long before the labelled onset count (the label's own uncertainty)."""
GROSS_TRANSLATION_MM = 2.0
GROSS_ROTATION_DEG = 2.0

SLIP_KINDS = ("slip",)
NO_SLIP_KINDS = ("stop", "hold")
PARTIAL_KINDS = ("partial",)
"""A partial slip that stopped by itself: some pillars slid, then stuck again, and the grasp held (no gross slip).
Neither criterion has an answer for it: an alarm reacts to a real slip that did not need it, silence ignores one
that happened to stop. It is left out of both criteria and counted apart (``Summary.partial_alarmed``)."""


# --------------------------------------------------------------------------- truth
@dataclass
class SceneTruth:
    """What the simulator (or a labelled recording) says happened in one scene.

    ``object_motion`` [N, 3] (mm, mm, deg relative to the finger) and ``t_s`` [N] are kept for D_norm
    and are left out of ``to_dict``.
    """

    name: str
    kind: str
    duration_s: float
    motion: str = ""
    family: str = ""
    """Scene family from the simulator ("hexapod", "gripper"); online metrics are skipped for hexapod scenes,
    whose ``object_motion`` is the surface pose rather than the object's motion relative to the finger."""
    onset_s: float | None = None
    gross_slip_s: float | None = None
    motion_start_s: float | None = None
    motion_stop_s: float | None = None
    online_gross_s: float | None = None
    t_s: np.ndarray | None = field(default=None, repr=False)
    object_motion: np.ndarray | None = field(default=None, repr=False)

    @property
    def is_slip(self) -> bool:
        """True for a slip sequence, False for stop / hold / partial."""
        return self.kind in SLIP_KINDS

    @property
    def is_partial(self) -> bool:
        """True for a partial slip that stopped by itself (no outcome under either criterion)."""
        return self.kind in PARTIAL_KINDS

    def to_dict(self) -> dict:
        """JSON form (without the arrays)."""
        d = asdict(self)
        d.pop("t_s")
        d.pop("object_motion")
        return d

    @classmethod
    def from_recording(cls, rec, name: str = "") -> SceneTruth:
        """Truth of a ``slipd.recording.Recording``.

        Onset: first sample labelled incipient slip (``label``), else ``events["onset"]``; none where the events put
        gross slip on the onset itself (no incipient stage: such a slip is scored online only).
        Gross slip (offline criterion): first sample after the onset where the incipient label ends
        (all considered pillars slipped), else ``events["gross_slip"]``, else the end of the recording.
        Online gross slip: first sample where ``object_motion`` (relative to its value at motion start)
        exceeds 2 mm or 2 deg, else ``events["gross_motion"]``; not for hexapod scenes (no online trial).
        """
        t_s = (np.asarray(rec.t_us, np.int64) - int(rec.t_us[0])) / 1e6 if len(rec) else np.zeros(0)
        duration = float(t_s[-1] + (1.0 / rec.rate_hz)) if len(t_s) else 0.0
        meta = rec.meta or {}
        events = {k: float(v) for k, v in (meta.get("events") or {}).items() if v is not None}
        label = rec.label
        has_label = label is not None and bool(np.any(label))
        kind = str(meta.get("kind") or ("slip" if has_label else "stop"))
        kinds = SLIP_KINDS + NO_SLIP_KINDS + PARTIAL_KINDS
        if kind not in kinds:
            raise ValueError(f"{name or 'recording'}: meta kind {kind!r} is not one of {kinds}")
        onset = gross = None
        if has_label:
            on = int(np.argmax(label > 0))
            onset = float(t_s[on])
            after = np.flatnonzero(label[on:] == 0)
            gross = float(t_s[on + after[0]]) if len(after) else None
        onset = onset if onset is not None else events.get("onset")
        if gross is None:
            gross = events.get("gross_slip", duration if onset is not None else None)
        if not has_label and onset is not None and gross is not None and gross <= onset:
            # Every considered pillar began to slide on the same sample (one pillar carried the whole grasp): the
            # slip had no incipient stage, so the offline criterion has no window; the online one still scores it.
            onset = gross = None
        motion_start = events.get("motion_start")
        family = str(meta.get("family", ""))
        online_gross = None
        if family != "hexapod":
            if rec.object_motion is not None and len(t_s):
                online_gross = gross_slip_time(t_s, rec.object_motion, motion_start)
            if online_gross is None:
                online_gross = events.get("gross_motion")
        return cls(
            name=name,
            kind=kind,
            duration_s=duration,
            motion=str(meta.get("motion", "")),
            family=family,
            onset_s=onset,
            gross_slip_s=gross if kind in SLIP_KINDS else None,
            motion_start_s=motion_start,
            motion_stop_s=events.get("motion_stop"),
            online_gross_s=online_gross if kind in SLIP_KINDS else None,
            t_s=t_s,
            object_motion=None if rec.object_motion is None or family == "hexapod"
            else np.asarray(rec.object_motion, np.float64),
        )


def gross_slip_time(t_s: np.ndarray, object_motion: np.ndarray, motion_start_s: float | None = None) -> float | None:
    """First time the relative object motion exceeds 2 mm or 2 deg (None if never).

    Motion is measured from its value at ``motion_start_s`` (or the first sample), so a grasp that
    settles before the robot moves does not count.
    """
    rel = _relative_motion(t_s, object_motion, motion_start_s)
    over = (np.hypot(rel[:, 0], rel[:, 1]) > GROSS_TRANSLATION_MM) | (np.abs(rel[:, 2]) > GROSS_ROTATION_DEG)
    if motion_start_s is not None:
        over &= t_s >= motion_start_s
    idx = np.flatnonzero(over)
    return float(t_s[idx[0]]) if len(idx) else None


def _relative_motion(t_s: np.ndarray, object_motion: np.ndarray, motion_start_s: float | None) -> np.ndarray:
    om = np.asarray(object_motion, np.float64)
    i0 = 0 if motion_start_s is None else int(min(np.searchsorted(t_s, motion_start_s), len(om) - 1))
    return om - om[i0]


def motion_components(motion: str) -> tuple[bool, bool]:
    """(uses translation, uses rotation) of a motion type name.

    ``rotation`` -> rotation only; names with both ``trans``/``lin`` and ``rot``, or ``both`` /
    ``combined`` / ``+``, or an off-centre grasp (``lift_offcentre``: the object sinks and turns) -> both;
    anything else is a translation (lifts, pushes, slides).
    """
    m = motion.lower()
    rot = "rot" in m or "twist" in m or "torque" in m
    both = ("both" in m or "combined" in m or "+" in m or "offcent" in m
            or (rot and ("trans" in m or "lin" in m)))
    if both:
        return True, True
    if rot:
        return False, True
    return True, False


def d_norm_at(truth: SceneTruth, t_alarm_s: float) -> float | None:
    """D_norm of the relative object motion at ``t_alarm_s`` (None without object motion)."""
    if truth.object_motion is None or truth.t_s is None or not len(truth.t_s):
        return None
    rel = _relative_motion(truth.t_s, truth.object_motion, truth.motion_start_s)
    i = int(min(np.searchsorted(truth.t_s, t_alarm_s), len(rel) - 1))
    trans = float(np.hypot(rel[i, 0], rel[i, 1])) / GROSS_TRANSLATION_MM
    rot = abs(float(rel[i, 2])) / GROSS_ROTATION_DEG
    use_t, use_r = motion_components(truth.motion)
    if use_t and use_r:
        return (trans + rot) / 2
    return rot if use_r else trans


# --------------------------------------------------------------------------- decisions
@dataclass
class Trace:
    """The decisions of one scene: time (s from the first sample), probability, alarm state, edges."""

    t_s: list[float]
    p_slip: list[float]
    alarm: list[bool]
    rising_edge: list[bool]
    contact_risk: list[float] = field(default_factory=list)
    """Each decision's contact risk (``slipd.detect.contact``: what the limit guard reads), NaN where the detection
    carries no contact state; empty for a trace built without detections."""

    @classmethod
    def from_detections(cls, detections: Iterable, t_us: np.ndarray) -> Trace:
        """Build from ``Detection`` objects; times come from each decision's sample ``index``.

        (The index, not ``Detection.t_us``, is authoritative: decisions replayed from a tare buffer
        carry the time of the sample that released them.)
        """
        t_us = np.asarray(t_us, np.int64)
        t0 = int(t_us[0]) if len(t_us) else 0
        ts, ps, al, re, cr = [], [], [], [], []
        for d in detections:
            if not getattr(d, "valid", True):
                continue
            ts.append((int(t_us[min(d.index, len(t_us) - 1)]) - t0) / 1e6)
            ps.append(float(d.p_slip))
            al.append(bool(d.alarm))
            re.append(bool(d.rising_edge))
            contact = getattr(d, "contact", None)
            cr.append(float("nan") if contact is None else float(contact.risk))
        return cls(ts, ps, al, re, cr)

    def first_alarm_s(self) -> float | None:
        """Time of the first decision with the alarm raised, or None."""
        for t, a in zip(self.t_s, self.alarm):
            if a:
                return t
        return None

    def n_rising_edges(self) -> int:
        """Number of times the alarm switched on (an alarm already on at the first decision counts)."""
        n = sum(self.rising_edge)
        if self.alarm and self.alarm[0] and not self.rising_edge[0]:
            n += 1
        return n

    def to_dict(self) -> dict:
        """JSON form."""
        return asdict(self)


# --------------------------------------------------------------------------- per scene
@dataclass
class SceneResult:
    """Every figure of one scene."""

    name: str
    kind: str
    motion: str
    duration_s: float
    first_alarm_s: float | None
    offline_outcome: str | None
    """tp, early, late, missed (slip) or tn, fp (stop / hold); None for a slip without a labelled onset."""
    latency_s: float | None
    online_outcome: str | None
    """success, early, late, missed (slip) or tn, fp (stop); None without motion-start truth."""
    d_norm: float | None
    rising_edges: int

    @property
    def offline_success(self) -> bool:
        """TP or TN."""
        return self.offline_outcome in ("tp", "tn")

    def to_dict(self) -> dict:
        """JSON form."""
        return asdict(self)


def offline_outcome(truth: SceneTruth, first_alarm_s: float | None) -> str | None:
    """The offline criterion for one sequence: tp / early / late / missed, or tn / fp.

    None for a slip sequence without a labelled onset (no pillar was labelled slipping, e.g. a gripper trial
    whose object moved without a labelled incipient stretch): the criterion is undefined there, so such
    sequences are left out of the offline figures and counted as ``offline_unlabelled``. None for a partial slip.
    """
    if truth.is_partial:
        return None
    if not truth.is_slip:
        return "tn" if first_alarm_s is None else "fp"
    if truth.onset_s is None:
        return None
    if first_alarm_s is None:
        return "missed"
    if first_alarm_s < truth.onset_s - EARLY_TOLERANCE_S:
        return "early"
    gross = truth.gross_slip_s if truth.gross_slip_s is not None else math.inf
    return "late" if first_alarm_s > gross else "tp"


def online_outcome(truth: SceneTruth, first_alarm_s: float | None) -> str | None:
    """The online criterion: success when the first alarm is in [T_m, T_g].

    None for hexapod scenes, partial slips and slip scenes without a motion start.
    """
    if truth.family == "hexapod" or truth.is_partial:
        return None
    if not truth.is_slip:
        return "tn" if first_alarm_s is None else "fp"
    if truth.motion_start_s is None:
        return None
    if first_alarm_s is None:
        return "missed"
    if first_alarm_s < truth.motion_start_s:
        return "early"
    gross = truth.online_gross_s if truth.online_gross_s is not None else math.inf
    return "late" if first_alarm_s > gross else "success"


def scored_outcome(truth: SceneTruth, first_alarm_s: float | None, criterion: str = "auto") -> str | None:
    """One sequence under the criterion the figures use: "online", "offline", or "auto" (online for gripper
    trials, offline for hexapod scenes). A hit is "tp" under both (the online criterion calls it "success")."""
    online = criterion == "online" or (criterion == "auto" and truth.family == "gripper")
    out = online_outcome(truth, first_alarm_s) if online else offline_outcome(truth, first_alarm_s)
    return "tp" if out == "success" else out


def evaluate_scene(truth: SceneTruth, trace: Trace) -> SceneResult:
    """All per-scene figures from the truth and the decisions."""
    first = trace.first_alarm_s()
    off = offline_outcome(truth, first)
    latency = first - truth.onset_s if off == "tp" and truth.onset_s is not None else None
    dn = d_norm_at(truth, first) if truth.is_slip and first is not None else None
    return SceneResult(
        name=truth.name,
        kind=truth.kind,
        motion=truth.motion,
        duration_s=truth.duration_s,
        first_alarm_s=first,
        offline_outcome=off,
        latency_s=latency,
        online_outcome=online_outcome(truth, first),
        d_norm=dn,
        rising_edges=trace.n_rising_edges(),
    )


# --------------------------------------------------------------------------- summaries
@dataclass
class Confusion:
    """Slip/stop confusion matrix. tp: slip detected in time; fn: slip not (early, late, missed);
    fp: stop with an alarm; tn: stop without."""

    tp: int = 0
    fn: int = 0
    fp: int = 0
    tn: int = 0

    @property
    def n(self) -> int:
        """Number of sequences."""
        return self.tp + self.fn + self.fp + self.tn

    @property
    def success_rate(self) -> float | None:
        """(TP + TN) / N: the paper's success rate."""
        return (self.tp + self.tn) / self.n if self.n else None

    @property
    def balanced_success(self) -> float | None:
        """Mean of the slip and stop success rates (robust to few stop sequences)."""
        rates = [r for r in (_ratio(self.tp, self.tp + self.fn), _ratio(self.tn, self.tn + self.fp)) if r is not None]
        return sum(rates) / len(rates) if rates else None

    def to_dict(self) -> dict:
        """JSON form, with the rates."""
        d = asdict(self)
        d.update(n=self.n, success_rate=self.success_rate, balanced_success=self.balanced_success)
        return d


def _ratio(a: int, b: int) -> float | None:
    return a / b if b else None


@dataclass
class Distribution:
    """Summary of a sample of values (all None when empty)."""

    n: int
    mean: float | None
    median: float | None
    p10: float | None
    p90: float | None
    min: float | None
    max: float | None

    @classmethod
    def of(cls, values: Sequence[float]) -> Distribution:
        """Summarise ``values`` (None entries ignored)."""
        v = np.asarray([x for x in values if x is not None], np.float64)
        if not len(v):
            return cls(0, None, None, None, None, None, None)
        return cls(
            n=len(v),
            mean=float(v.mean()),
            median=float(np.median(v)),
            p10=float(np.percentile(v, 10)),
            p90=float(np.percentile(v, 90)),
            min=float(v.min()),
            max=float(v.max()),
        )

    def to_dict(self) -> dict:
        """JSON form."""
        return asdict(self)


@dataclass
class Summary:
    """Figures over a set of scenes."""

    n_scenes: int
    offline: Confusion
    offline_failures: dict[str, int]
    offline_unlabelled: int
    """Slip sequences without a labelled onset, left out of ``offline``."""
    latency_s: Distribution
    online: Confusion | None
    online_failures: dict[str, int]
    d_norm: Distribution
    """D_norm at the first alarm of online successes."""
    false_alarms: int
    no_slip_hours: float
    false_alarms_per_hour: float | None
    partial: int = 0
    """Partial slips that stopped by themselves, left out of both criteria ..."""
    partial_alarmed: int = 0
    """... and how many of them raised the alarm."""

    def to_dict(self) -> dict:
        """JSON form."""
        return {
            "n_scenes": self.n_scenes,
            "offline": self.offline.to_dict(),
            "offline_failures": dict(self.offline_failures),
            "offline_unlabelled": self.offline_unlabelled,
            "latency_s": self.latency_s.to_dict(),
            "online": None if self.online is None else self.online.to_dict(),
            "online_failures": dict(self.online_failures),
            "d_norm": self.d_norm.to_dict(),
            "false_alarms": self.false_alarms,
            "no_slip_hours": self.no_slip_hours,
            "false_alarms_per_hour": self.false_alarms_per_hour,
            "partial": self.partial,
            "partial_alarmed": self.partial_alarmed,
        }


def confusion(results: Iterable[SceneResult], online: bool = False) -> Confusion:
    """Confusion matrix of the offline (default) or online outcomes; scenes without an outcome are skipped."""
    c = Confusion()
    for r in results:
        o = r.online_outcome if online else r.offline_outcome
        if o is None:
            continue
        if o in ("tp", "success"):
            c.tp += 1
        elif o in ("early", "late", "missed"):
            c.fn += 1
        elif o == "fp":
            c.fp += 1
        elif o == "tn":
            c.tn += 1
    return c


def false_alarms_per_hour(results: Iterable[SceneResult]) -> tuple[int, float, float | None]:
    """(rising edges, hours, edges per hour) over the no-slip (stop / hold) scenes."""
    edges, seconds = 0, 0.0
    for r in results:
        if r.kind in NO_SLIP_KINDS:
            edges += r.rising_edges
            seconds += r.duration_s
    hours = seconds / 3600.0
    return edges, hours, (edges / hours if hours > 0 else None)


def summarize(results: Sequence[SceneResult]) -> Summary:
    """Aggregate per-scene results into the method's figures."""
    off_fail: dict[str, int] = {}
    on_fail: dict[str, int] = {}
    for r in results:
        if r.offline_outcome in ("early", "late", "missed", "fp"):
            off_fail[r.offline_outcome] = off_fail.get(r.offline_outcome, 0) + 1
        if r.online_outcome in ("early", "late", "missed", "fp"):
            on_fail[r.online_outcome] = on_fail.get(r.online_outcome, 0) + 1
    on = confusion(results, online=True)
    edges, hours, per_hour = false_alarms_per_hour(results)
    return Summary(
        n_scenes=len(results),
        offline=confusion(results),
        offline_failures=off_fail,
        offline_unlabelled=sum(r.offline_outcome is None and r.kind in SLIP_KINDS for r in results),
        latency_s=Distribution.of([r.latency_s for r in results if r.offline_outcome == "tp"]),
        online=on if any(r.online_outcome is not None and r.kind in SLIP_KINDS for r in results) else None,
        online_failures=on_fail,
        d_norm=Distribution.of([r.d_norm for r in results if r.online_outcome == "success"]),
        false_alarms=edges,
        no_slip_hours=hours,
        false_alarms_per_hour=per_hour,
        partial=sum(r.kind in PARTIAL_KINDS for r in results),
        partial_alarmed=sum(r.kind in PARTIAL_KINDS and r.first_alarm_s is not None for r in results),
    )
