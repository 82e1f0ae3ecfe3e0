"""Scenario timelines: a hexapod scene as a sequence of events, so that *when* things happen is part of the
scene and can be randomised (a detector must not learn our scripts' clock).

``timeline:`` in a hexapod scene is a list of segments, run in order after ``pre_s`` unloaded:

``{op: press, depth_mm, duration_s}``   press (smoothstep) from the current depth to ``depth_mm``;
                                        ``duration_s: 0`` as the first segment = the recording starts in
                                        contact (already pressed from its first sample).
``{op: hold, duration_s}``              nothing moves.
``{op: move, kind, speed_mm_s, accel_mm_s2, jerk_mm_s3, direction_deg, rot_speed_deg_s, centre_mm,
  duration_s, stop_fraction}``          ramp up (trapezoid, smoothed to the jerk limit when ``jerk_mm_s3`` is
                                        given), cruise ``duration_s``, ramp down to rest. With
                                        ``stop_fraction`` the move is a *stop*: it halts so that the plate
                                        comes to rest at that fraction of the travel at which the first
                                        considered pillar would slip (found by a probe run, as for ``stop``
                                        scenes), and is never labelled.
``{op: release, duration_s, lift_mm}``  lift the plate off (depth to ``-lift_mm``); tips out of contact
                                        relax to zero. A press after a release is a regrasp.

Truth and labels: per-pillar slip is the physics' sliding state throughout. The label is the method's
incipient-slip rule applied to every non-stop move on its own (from the move's start until all of its
considered pillars slide, or until the plate is at rest again); the recording's label is their union. The recording's
``kind`` is ``slip`` with any non-stop move, ``stop`` with stop moves only, ``hold`` without moves.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from slipd.sim.physics import DT_S

PROBE_S = 10.0
"""Longest probe of a stop move (motion continued until the first pillar slips)."""


class _P(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Press(_P):
    op: Literal["press"]
    depth_mm: float = Field(..., ge=0.0, le=3.0)
    duration_s: float = Field(0.3, ge=0.0, le=10.0)


class Hold(_P):
    op: Literal["hold"]
    duration_s: float = Field(..., gt=0.0, le=3600.0)


class Move(_P):
    op: Literal["move"]
    kind: Literal["translation", "rotation", "both"] = "translation"
    speed_mm_s: float = Field(5.0, ge=0.0, le=100.0)
    accel_mm_s2: float = Field(50.0, gt=0.0)
    jerk_mm_s3: float | None = Field(None, gt=0.0)
    direction_deg: float = 0.0
    rot_speed_deg_s: float = Field(10.0, ge=-360.0, le=360.0)
    centre_mm: tuple[float, float] = (0.0, 0.0)
    duration_s: float = Field(1.0, ge=0.0, le=600.0)
    """Cruise time (slip moves) before ramping down."""
    stop_fraction: float | None = Field(None, gt=0.0, lt=1.0)


class Release(_P):
    op: Literal["release"]
    duration_s: float = Field(0.3, gt=0.0, le=10.0)
    lift_mm: float = Field(0.5, gt=0.0, le=5.0)


Segment = Annotated[Press | Hold | Move | Release, Field(discriminator="op")]


def ramp_s(m: Move) -> float:
    """Time to cruise speed (rotations: a tip 7 mm from the centre sees the acceleration)."""
    if m.kind == "rotation":
        return float(np.deg2rad(abs(m.rot_speed_deg_s))) * 7.0 / m.accel_mm_s2
    return m.speed_mm_s / m.accel_mm_s2


def _smooth(speed: np.ndarray, m: Move) -> np.ndarray:
    """Jerk limit: a causal moving average over accel / jerk turns the trapezoid into an S-curve (same travel)."""
    if m.jerk_mm_s3 is None:
        return speed
    w = max(1, round(m.accel_mm_s2 / m.jerk_mm_s3 / DT_S))
    if w <= 1:
        return speed
    return np.convolve(np.concatenate([speed, np.zeros(w - 1)]), np.ones(w) / w)[: len(speed) + w - 1]


def _stop_index(ramp: float, target_q: float, limit: int) -> int:
    """Samples of ramping up (then cruising) after which ramping down ends at or before progress ``target_q``."""
    k = np.arange(limit)
    speed = np.minimum(k * DT_S / ramp, 1.0) if ramp > 0 else np.ones(limit)
    q = np.cumsum(speed) * DT_S
    final = q + speed**2 * max(ramp, DT_S) / 2.0
    ok = np.nonzero(final <= target_q)[0]
    return int(ok[-1]) if len(ok) else 0


def _move_speed(m: Move, up_to: int | None, probe: int | None) -> np.ndarray:
    """Normalised speed (1 = cruise) of one move, sample by sample, until rest.

    ``up_to``: samples before the ramp down starts (stop moves, resolved); default: ramp + cruise.
    ``probe``: an open-ended probe of that many samples (ramp up, cruise, never stop)."""
    ramp = ramp_s(m)
    rn = max(1, round(ramp / DT_S))
    if probe is not None:
        k = np.arange(probe)
        return np.minimum((k + 1) / rn, 1.0)
    if up_to is None:
        up_to = rn + round(m.duration_s / DT_S)
    k = np.arange(up_to)
    up = np.minimum((k + 1) / rn, 1.0)
    v0 = up[-1] if len(up) else 0.0
    down_n = int(np.ceil(v0 * rn))
    down = np.maximum(v0 - (np.arange(down_n) + 1) / rn, 0.0)
    return _smooth(np.concatenate([up, down, [0.0]]), m)


class Built:
    """Input profiles of one timeline: ``depth`` [N], ``pose_t`` [N,2], ``pose_th`` [N] and the events."""

    def __init__(self) -> None:
        self.depth: list[np.ndarray] = []
        self.pose_t: list[np.ndarray] = []
        self.pose_th: list[np.ndarray] = []
        self.moves: list[dict] = []
        """Per move: index (segment), kind, start, end (sample after rest), stop (bool), stop_index."""
        self.segments: list[dict] = []
        self.probe: int | None = None
        """Segment index of the stop move being probed (the timeline ends there)."""
        self.starts_in_contact = False


def build(timeline: list, pre: int, stops: dict[int, int]) -> Built:
    """The profiles of a timeline. ``stops``: resolved stop moves, segment index -> samples of motion before
    the ramp down. The first unresolved stop move is probed: motion continues for ``PROBE_S`` and the
    timeline ends there (``Built.probe``)."""
    out = Built()
    depth, t, th = 0.0, np.zeros(2), 0.0
    k = 0

    def emit(d: np.ndarray, tt: np.ndarray, thh: np.ndarray) -> None:
        nonlocal k
        out.depth.append(d)
        out.pose_t.append(tt)
        out.pose_th.append(thh)
        k += len(d)

    first_press = timeline and timeline[0].op == "press" and timeline[0].duration_s == 0.0
    if first_press:
        depth = timeline[0].depth_mm
        out.starts_in_contact = True
    emit(np.full(pre, depth), np.zeros((pre, 2)), np.zeros(pre))
    for i, seg in enumerate(timeline):
        start = k
        if seg.op in ("press", "release"):
            target = seg.depth_mm if seg.op == "press" else -seg.lift_mm
            m = round(seg.duration_s / DT_S)
            if m > 0:
                r = (np.arange(m) + 1) / m
                d = depth + (target - depth) * r * r * (3 - 2 * r)
                emit(d, np.repeat(t[None], m, 0), np.full(m, th))
            depth = target
        elif seg.op == "hold":
            m = round(seg.duration_s / DT_S)
            emit(np.full(m, depth), np.repeat(t[None], m, 0), np.full(m, th))
        else:
            is_stop = seg.stop_fraction is not None
            probe = round(PROBE_S / DT_S) if is_stop and i not in stops else None
            speed = _move_speed(seg, stops.get(i), probe)
            q = np.cumsum(speed) * DT_S
            v = seg.speed_mm_s if seg.kind != "rotation" else 0.0
            w = np.deg2rad(seg.rot_speed_deg_s) if seg.kind != "translation" else 0.0
            a = np.deg2rad(seg.direction_deg)
            trans = (v * q)[:, None] * np.array([np.cos(a), np.sin(a)])
            dth = w * q
            c = np.asarray(seg.centre_mm, np.float64)
            rel = t - c
            cs, sn = np.cos(dth), np.sin(dth)
            tt = np.stack([cs * rel[0] - sn * rel[1], sn * rel[0] + cs * rel[1]], 1) + c + trans
            emit(np.full(len(q), depth), tt, th + dth)
            t, th = tt[-1].copy(), float(th + dth[-1])
            out.moves.append({"segment": i, "kind": seg.kind, "start": start, "end": k, "stop": is_stop,
                              "stop_index": start + stops[i] if i in stops else None})
            if probe is not None:
                out.probe = i
                out.segments.append({"op": seg.op, "start": start, "end": k})
                break
        out.segments.append({"op": seg.op, "start": start, "end": k})
    return out


def arrays(b: Built) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth [N], pose_t [N,2], pose_th [N]) of a built timeline."""
    return np.concatenate(b.depth), np.concatenate(b.pose_t), np.concatenate(b.pose_th)


def stop_samples(m: Move, onset_q: float | None, probe_q_end: float) -> int:
    """Samples of motion before the ramp down of a stop move, from the probe's progress at the first slip."""
    target = m.stop_fraction * (onset_q if onset_q is not None else probe_q_end)
    return _stop_index(ramp_s(m), target, round(PROBE_S / DT_S))


def probe_progress(m: Move) -> np.ndarray:
    """Normalised progress of a probe run of ``m`` (as ``build`` emits it)."""
    return np.cumsum(_move_speed(m, None, round(PROBE_S / DT_S))) * DT_S
