"""Recordings as MCAP files: the frames, slipd's decisions and what happened around them, on named channels.

An ``.mcap`` recording holds everything a ``.npz`` one does (``slipd.recording.Recording``: the samples, the
simulator's truth, ``meta``), so ``slipd replay`` decides identically on either, and it opens in Foxglove or any
MCAP reader as time series. Messages are JSON with a JSON Schema per channel (the MCAP ``json`` message encoding):
this needs only the ``mcap`` package, and every value can be read back exactly (a float32 written as its double
repr parses back to the same float32).

Channels (``log_time`` is the sensor's clock, ``t_us`` * 1000 ns; ``sample`` the index into the recording):

    /slipd/frames/s<S>   slipd.PillarFrame   per sample and sensor: force and disp (9 pillars x, y, z in SDK order,
                                             pillar-major), each pillar's tangential force, the controller's own
                                             friction estimate
    /slipd/pillars/s<S>  foxglove.SceneUpdate each pillar's force as a 3D arrow, 50 a second (a 3D panel shows them)
    /slipd/decisions     slipd.Decision      per decision: sensor, p_slip, alarm, risk, threshold, the slip map
                                             (nine pillars' P(slip)), friction estimate
    /slipd/events        foxglove.Log        alarms and fail-safes that started a recording, with their causes
    /slipd/reactions     slipd.Reaction      a reaction sent to a device (arm stop, gripper tighten) and its answer
    /slipd/state         slipd.GripArmState  grip force (N) and arm speed (mm/s) where the producer knows them
    /slipd/truth         slipd.Truth         simulator truth: per-pillar slip, incipient-slip label, object motion

Metadata records: ``slipd.recording`` (the layout this reader needs: sensors, sample count, which optional arrays
exist), ``slipd.meta`` (the recording's ``meta`` as JSON), ``slipd.config`` and ``slipd.model`` (the daemon's
configuration and the model manifest, when ``meta`` carries them under ``config`` / ``model``).

Writing is atomic (a temporary file renamed into place): a crash leaves the finished file or none.

This module is the MCAP codec; ``slipd.recording`` builds its ``Recording`` from what ``read_arrays`` returns
(``Recording.load`` reads ``.mcap`` files through it).
"""

from __future__ import annotations

import json
import math
import time
import zlib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np

from slipd.geometry import N_PILLARS, PILLAR_XY_MM

MAGIC = b"\x89MCAP0\r\n"
FORMAT_VERSION = "1"
YIELD_EVERY = 8
"""Messages written between two releases of the interpreter's lock (a few hundred microseconds of work)."""
TOPIC_FRAMES = "/slipd/frames/s{}"
TOPIC_PILLARS = "/slipd/pillars/s{}"
TOPIC_DECISIONS = "/slipd/decisions"
TOPIC_EVENTS = "/slipd/events"
TOPIC_REACTIONS = "/slipd/reactions"
TOPIC_STATE = "/slipd/state"
TOPIC_TRUTH = "/slipd/truth"

_TIME = {
    "type": "object", "title": "time", "description": "sensor clock (t_us) as seconds and nanoseconds",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
    "required": ["sec", "nsec"],
}
_NUM_OR_NULL = {"type": ["number", "null"]}


def _numbers(n: int, what: str, nullable: bool = False) -> dict[str, Any]:
    return {"type": "array", "items": _NUM_OR_NULL if nullable else {"type": "number"}, "minItems": n,
            "maxItems": n, "description": what}


SCHEMAS: dict[str, dict[str, Any]] = {
    "slipd.PillarFrame": {
        "type": "object", "title": "slipd.PillarFrame",
        "description": "one sensor sample: the nine pillars of one PapillArray",
        "properties": {
            "timestamp": _TIME,
            "sample": {"type": "integer", "description": "index of the sample in the recording"},
            "t_us": {"type": "integer", "description": "sensor timestamp, microseconds"},
            "sensor": {"type": "integer", "description": "sensor array (finger), 0-based"},
            "force": _numbers(3 * N_PILLARS, "fx, fy, fz of pillars 0..8 (N), pillar-major; null: not finite", True),
            "disp": _numbers(3 * N_PILLARS, "dx, dy, dz of pillars 0..8 (mm), pillar-major; null: not finite", True),
            "tangential": _numbers(N_PILLARS, "hypot(fx, fy) of each pillar (N)", True),
            "controller_friction": {"type": ["number", "null"],
                                    "description": "the sensor controller's friction estimate; null: none"},
        },
        "required": ["timestamp", "sample", "t_us", "sensor", "force", "disp", "tangential"],
    },
    "slipd.Decision": {
        "type": "object", "title": "slipd.Decision", "description": "one decision of the slip detector",
        "properties": {
            "timestamp": _TIME,
            "t_us": {"type": "integer", "description": "timestamp of the sample that completed the window"},
            "sensor": {"type": "integer"},
            "p_slip": {"type": "number", "description": "the ensemble's fused P(slip)"},
            "alarm": {"type": "boolean"},
            "risk": {"type": ["number", "null"], "description": "risk of the decision 0..1; null: not recorded"},
            "threshold": {"type": ["number", "null"], "description": "the alarm threshold on p_slip"},
            "pillar_slip": {"type": ["array", "null"], "items": _NUM_OR_NULL, "description":
                            "the slip map: P(slip) of pillars 0..8; null: the decision carried no contact state"},
            "contact_risk": {"type": ["number", "null"], "description": "load-weighted share of the contact at risk"},
            "friction": {"type": ["number", "null"], "description": "friction coefficient estimated by slipd"},
        },
        "required": ["timestamp", "t_us", "sensor", "p_slip", "alarm"],
    },
    "foxglove.Log": {
        "type": "object", "title": "foxglove.Log", "description": "a log message (Foxglove's well-known schema)",
        "properties": {
            "timestamp": _TIME,
            "level": {"type": "integer", "description": "1 debug, 2 info, 3 warning, 4 error, 5 fatal"},
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
        },
        "required": ["timestamp", "level", "message", "name", "file", "line"],
    },
    "slipd.Reaction": {
        "type": "object", "title": "slipd.Reaction", "description": "a command sent to a device, and its answer",
        "properties": {
            "timestamp": _TIME,
            "t_us": {"type": "integer", "description": "sensor time at which it was sent"},
            "action": {"type": "string", "description": "stop_arm, tighten_gripper, grip_force, ..."},
            "state": {"type": "string", "description": "sent, acked or failed (the daemon's); reached (the simulated "
                      "device received it)"},
            "detail": {"type": "string"},
        },
        "required": ["timestamp", "t_us", "action", "state"],
    },
    "slipd.GripArmState": {
        "type": "object", "title": "slipd.GripArmState", "description": "grip and arm state",
        "properties": {"timestamp": _TIME, "t_us": {"type": "integer"},
                       "grip_n": {"type": ["number", "null"], "description": "grip force (N)"},
                       "arm_speed_mm_s": {"type": ["number", "null"], "description": "arm (finger) speed (mm/s)"}},
        "required": ["timestamp", "t_us"],
    },
    "slipd.Truth": {
        "type": "object", "title": "slipd.Truth", "description": "what the simulator knows and a sensor does not",
        "properties": {
            "timestamp": _TIME, "sample": {"type": "integer"}, "t_us": {"type": "integer"},
            "slip": {"type": ["array", "null"], "items": {"type": "boolean"}, "description": "pillars 0..8 sliding"},
            "label": {"type": ["integer", "null"], "description": "1: incipient slip"},
            "object_motion": {"type": ["array", "null"], "items": {"type": "number"},
                              "description": "object motion relative to the finger: x mm, y mm, rotation deg"},
            "slipping": {"type": ["integer", "null"], "description": "pillars sliding (count)"},
            "translation_mm": {"type": ["number", "null"], "description": "hypot of the object motion's x and y"},
        },
        "required": ["timestamp", "sample", "t_us"],
    },
}
class McapRecordingError(ValueError):
    """An MCAP file that is not a slipd recording, or a broken one (one line, without the file name)."""


class RecordingLike(Protocol):
    """What ``write_mcap`` reads of a ``slipd.recording.Recording``."""

    t_us: np.ndarray
    force: np.ndarray
    disp: np.ndarray
    slip: np.ndarray | None
    label: np.ndarray | None
    object_motion: np.ndarray | None
    friction_est: np.ndarray | None
    meta: dict[str, Any]

    def __len__(self) -> int: ...

    @property
    def sensors(self) -> int: ...

    def sensor(self, s: int) -> Any: ...


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}, "required": list("xyz")}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}, "required": list("xyzw")}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}, "required": list("rgba")}
_EMPTY = {"type": "array", "maxItems": 0}
SCHEMAS["foxglove.SceneUpdate"] = {
    "type": "object", "title": "foxglove.SceneUpdate",
    "description": "each pillar's force as an arrow from its tip (Foxglove's well-known schema; the arrows alone)",
    "properties": {
        "deletions": _EMPTY,
        "entities": {"type": "array", "items": {
            "type": "object", "title": "foxglove.SceneEntity",
            "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                "lifetime": _TIME, "frame_locked": {"type": "boolean"}, "metadata": _EMPTY,
                "arrows": {"type": "array", "items": {
                    "type": "object", "title": "foxglove.ArrowPrimitive",
                    "properties": {
                        "pose": {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT},
                                 "required": ["position", "orientation"]},
                        "shaft_length": {"type": "number"}, "shaft_diameter": {"type": "number"},
                        "head_length": {"type": "number"}, "head_diameter": {"type": "number"}, "color": _COLOR},
                    "required": ["pose", "shaft_length", "shaft_diameter", "head_length", "head_diameter", "color"]}},
                **{k: _EMPTY for k in ("cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")},
            },
            "required": ["timestamp", "frame_id", "id", "lifetime", "frame_locked", "arrows"]}},
    },
    "required": ["deletions", "entities"],
}
SCENE_EVERY = 20
"""One pillar-arrows message per this many samples (50 a second at 1 kHz)."""
ARROW_M_PER_N = 0.004
"""Arrow length per newton of pillar force (the pillars sit 7 mm apart)."""

_TOPIC_SCHEMA = {TOPIC_DECISIONS: "slipd.Decision", TOPIC_EVENTS: "foxglove.Log", TOPIC_REACTIONS: "slipd.Reaction",
                 TOPIC_STATE: "slipd.GripArmState", TOPIC_TRUTH: "slipd.Truth"}


def schema_of(topic: str) -> str:
    """The schema name of one of slipd's channels."""
    if topic.startswith("/slipd/frames/"):
        return "slipd.PillarFrame"
    if topic.startswith("/slipd/pillars/"):
        return "foxglove.SceneUpdate"
    return _TOPIC_SCHEMA[topic]


def _rotation_from_x(v: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) that turns +x onto the direction of ``v`` (Foxglove's arrows point along
    +x)."""
    n = float(np.linalg.norm(v))
    if n == 0.0:
        return 0.0, 0.0, 0.0, 1.0
    u = v / n
    # The half-way vector between +x and u: q = (x cross h, x . h).
    h = u + np.array([1.0, 0.0, 0.0])
    hn = float(np.linalg.norm(h))
    if hn < 1e-9:  # u is -x: half a turn about z
        return 0.0, 0.0, 1.0, 0.0
    h /= hn
    return 0.0, float(-h[2]), float(h[1]), float(h[0])


def pillar_scene(t_us: int, sensor: int, force: np.ndarray) -> dict[str, Any]:
    """A ``foxglove.SceneUpdate``: each pillar's force ([9, 3], N) as an arrow from its place on the sensor (metres,
    frame ``slipd_sensor<S>``), ``ARROW_M_PER_N`` long per newton."""
    arrows = []
    for p in range(N_PILLARS):
        f = force[p].astype(np.float64)
        if not np.isfinite(f).all():
            continue
        length = float(np.linalg.norm(f)) * ARROW_M_PER_N
        qx, qy, qz, qw = _rotation_from_x(f)
        arrows.append({
            "pose": {"position": {"x": float(PILLAR_XY_MM[p, 0]) / 1e3, "y": float(PILLAR_XY_MM[p, 1]) / 1e3,
                                  "z": 0.0},
                     "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}},
            "shaft_length": length * 0.8, "shaft_diameter": 0.0008, "head_length": length * 0.2,
            "head_diameter": 0.0016, "color": {"r": 0.1, "g": 0.5, "b": 1.0, "a": 1.0}})
    stamp = _stamp(t_us)
    entity = {"timestamp": stamp, "frame_id": f"slipd_sensor{sensor}", "id": "pillars",
              "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": [], "arrows": arrows,
              **{k: [] for k in ("cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")}}
    return {"deletions": [], "entities": [entity]}


def _stamp(t_us: int) -> dict[str, int]:
    t = max(0, int(t_us))
    return {"sec": t // 1_000_000, "nsec": (t % 1_000_000) * 1000}


def _finite(values: list[float]) -> list[float] | list[float | None]:
    """JSON has no NaN: a value that is not finite is written as null (read back as NaN)."""
    if all(map(math.isfinite, values)):
        return values  # the common case, without a copy
    return [v if math.isfinite(v) else None for v in values]


def _opt(v: Any) -> float | None:
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def decision_rows(decisions: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """The recorder's ``meta["decisions"]`` (columns) as one dict per decision."""
    n = len(decisions.get("t_us", ()))
    cols = {k: list(v) for k, v in decisions.items() if isinstance(v, (list, tuple)) and len(v) == n}
    return [{k: cols[k][i] for k in cols} for i in range(n)]


def trigger_events(trigger: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The alarm or fail-safe that started a recording and the fail-safes named inside it, as event dicts."""
    if not trigger:
        return []
    out = [dict(trigger)]
    out += [dict(e) for e in trigger.get("events", []) if isinstance(e, Mapping)]
    for e in out:
        e.pop("events", None)
    return out


class _Writer:
    """The ``mcap`` writer with slipd's channels registered on first use."""

    def __init__(self, stream: IO[bytes]) -> None:
        from mcap.writer import CompressionType, Writer

        self.w = Writer(stream, compression=CompressionType.ZSTD)
        self.w.start(profile="", library="slipd")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._added = 0

    def channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            name = schema_of(topic)
            sid = self._schemas.get(name)
            if sid is None:
                sid = self.w.register_schema(name, "jsonschema", json.dumps(SCHEMAS[name]).encode())
                self._schemas[name] = sid
            cid = self.w.register_channel(topic, "json", sid)
            self._channels[topic] = cid
        return cid

    def add(self, topic: str, t_us: int, message: dict[str, Any], seq: int = 0) -> None:
        ns = max(0, int(t_us)) * 1000
        self.w.add_message(self.channel(topic), ns, json.dumps(message, separators=(",", ":")).encode(), ns, seq)
        self._added += 1
        if self._added % YIELD_EVERY == 0:
            # This is Python work that holds the interpreter's lock; the daemon writes on its recorder thread, and the
            # control loop would otherwise wait up to the switch interval (5 ms) for the lock at each of its wake-ups.
            time.sleep(0)


def write_mcap(
    rec: RecordingLike,
    path: str | Path,
    *,
    decisions: Iterable[Mapping[str, Any]] | None = None,
    events: Iterable[Mapping[str, Any]] = (),
    reactions: Iterable[Mapping[str, Any]] = (),
    state: Mapping[str, np.ndarray] | None = None,
    threshold: float | None = None,
) -> Path:
    """Write ``rec`` as an MCAP recording (atomically: ``path``.tmp renamed into place).

    ``decisions``: dicts with t_us, sensor, p_slip, alarm and optionally risk, pillar_slip, contact_risk, friction;
    default: ``meta["decisions"]`` (the recorder's). ``events``: dicts with t_us, reason and details (alarms,
    fail-safes); ``meta["trigger"]`` and its events are added. ``reactions``: dicts with t_us, action, state
    (sent / acked / failed), detail. ``state``: arrays aligned with the samples, ``grip_n`` and/or
    ``arm_speed_mm_s``. ``threshold``: the alarm threshold written with each decision (default ``meta["threshold"]``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = rec.meta
    if decisions is None:
        d = meta.get("decisions")
        decisions = decision_rows(d) if isinstance(d, Mapping) else []
    if not reactions and isinstance(meta.get("reactions"), list):
        reactions = [r for r in meta["reactions"] if isinstance(r, Mapping) and "t_us" in r and "action" in r]
    if threshold is None and isinstance(meta.get("threshold"), (int, float)):
        threshold = float(meta["threshold"])
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        w = _Writer(fh)
        _write_frames(w, rec)
        _write_truth(w, rec)
        for k, row in enumerate(decisions):
            w.add(TOPIC_DECISIONS, int(row["t_us"]), decision_message(row, threshold), k)
        all_events = [*events, *trigger_events(meta.get("trigger") or {})]
        for e in sorted(all_events, key=lambda e: int(e.get("t_us", 0))):
            t = int(e.get("t_us", 0))
            reason = str(e.get("reason", "event"))
            details = {k: v for k, v in e.items() if k not in ("t_us", "reason")}
            level = 4 if reason == "failsafe" else 3 if reason == "alarm" else 2
            w.add(TOPIC_EVENTS, t, {"timestamp": _stamp(t), "level": level, "name": "slipd",
                                    "message": f"{reason}: {json.dumps(details, sort_keys=True, default=str)}",
                                    "file": "", "line": 0})
        for r in reactions:
            t = int(r["t_us"])
            w.add(TOPIC_REACTIONS, t, {"timestamp": _stamp(t), "t_us": t, "action": str(r["action"]),
                                       "state": str(r.get("state", "sent")), "detail": str(r.get("detail", ""))})
        if state:
            grip = state.get("grip_n")
            speed = state.get("arm_speed_mm_s")
            for i, t in enumerate(rec.t_us.tolist()):
                w.add(TOPIC_STATE, t, {"timestamp": _stamp(t), "t_us": t,
                                       "grip_n": None if grip is None else _opt(grip[i]),
                                       "arm_speed_mm_s": None if speed is None else _opt(speed[i])}, i)
        _write_metadata(w, rec)
        w.w.finish()  # type: ignore[no-untyped-call]
    tmp.replace(path)
    return path


def decision_message(row: Mapping[str, Any], threshold: float | None) -> dict[str, Any]:
    """A ``slipd.Decision`` message from a decision's dict (t_us, sensor, p_slip, alarm; optionally risk, pillar_slip,
    contact_risk, friction)."""
    t = int(row["t_us"])
    pill = row.get("pillar_slip")
    return {
        "timestamp": _stamp(t), "t_us": t, "sensor": int(row.get("sensor", 0)), "p_slip": float(row["p_slip"]),
        "alarm": bool(row["alarm"]), "risk": _opt(row.get("risk")), "threshold": threshold,
        "pillar_slip": None if pill is None else _finite([math.nan if v is None else float(v) for v in pill]),
        "contact_risk": _opt(row.get("contact_risk")), "friction": _opt(row.get("friction")),
    }


def frame_message(t_us: int, sample: int, sensor: int, force: np.ndarray, disp: np.ndarray,
                  controller_friction: float | None = None) -> dict[str, Any]:
    """A ``slipd.PillarFrame`` message from one sensor's sample (``force``, ``disp`` [9, 3])."""
    f = force.astype(np.float64)
    return _frame_dict(t_us, sample, sensor, f.ravel().tolist(), disp.astype(np.float64).ravel().tolist(),
                       np.hypot(f[:, 0], f[:, 1]).round(6).tolist(), controller_friction)


def _frame_dict(t: int, i: int, s: int, force: list[float], disp: list[float], tangential: list[float],
                friction: float | None) -> dict[str, Any]:
    return {"timestamp": _stamp(t), "sample": i, "t_us": t, "sensor": s, "force": _finite(force),
            "disp": _finite(disp), "tangential": _finite(tangential), "controller_friction": _opt(friction)}


def _write_frames(w: _Writer, rec: RecordingLike) -> None:
    n = len(rec)
    t_list = rec.t_us.tolist()
    for s in range(rec.sensors):
        one = rec.sensor(s)
        # float32 -> float64 is exact, and a double's repr parses back to it: the reader recovers every float32.
        force = one.force.reshape(n, 3 * N_PILLARS).astype(np.float64)
        tang = np.hypot(one.force[:, :, 0].astype(np.float64), one.force[:, :, 1]).round(6)
        f_rows, d_rows = force.tolist(), one.disp.reshape(n, 3 * N_PILLARS).astype(np.float64).tolist()
        t_rows = tang.tolist()
        fr = None if one.friction_est is None else one.friction_est.astype(np.float64).tolist()
        topic = TOPIC_FRAMES.format(s)
        for i in range(n):
            w.add(topic, t_list[i], _frame_dict(t_list[i], i, s, f_rows[i], d_rows[i], t_rows[i],
                                                None if fr is None else fr[i]), i)
        for i in range(0, n, SCENE_EVERY):
            w.add(TOPIC_PILLARS.format(s), t_list[i], pillar_scene(t_list[i], s, one.force[i]), i)


def _write_truth(w: _Writer, rec: RecordingLike) -> None:
    if rec.slip is None and rec.label is None and rec.object_motion is None:
        return
    slip = None if rec.slip is None else rec.slip.tolist()
    label = None if rec.label is None else rec.label.tolist()
    motion = None if rec.object_motion is None else rec.object_motion.astype(np.float64).tolist()
    count = None if rec.slip is None else rec.slip.sum(1).tolist()
    trans = None if rec.object_motion is None else np.hypot(rec.object_motion[:, 0].astype(np.float64),
                                                            rec.object_motion[:, 1]).round(6).tolist()
    for i, t in enumerate(rec.t_us.tolist()):
        w.add(TOPIC_TRUTH, t, {
            "timestamp": _stamp(t), "sample": i, "t_us": t,
            "slip": None if slip is None else slip[i], "label": None if label is None else label[i],
            "object_motion": None if motion is None else motion[i],
            "slipping": None if count is None else count[i], "translation_mm": None if trans is None else trans[i],
        }, i)


def _write_metadata(w: _Writer, rec: RecordingLike) -> None:
    layout = {"format": FORMAT_VERSION, "samples": str(len(rec)), "sensors": str(rec.sensors),
              "friction_est": str(rec.friction_est is not None).lower(),
              "truth": ",".join(k for k in ("slip", "label", "object_motion") if getattr(rec, k) is not None)}
    w.w.add_metadata("slipd.recording", layout)
    text = json.dumps(rec.meta, sort_keys=True, default=str)
    # MCAP checks the chunks' CRCs, not the metadata records': this one carries its own.
    w.w.add_metadata("slipd.meta", {"json": text, "crc32": str(zlib.crc32(text.encode()))})
    for key, name in (("config", "slipd.config"), ("model", "slipd.model")):
        value = rec.meta.get(key)
        if isinstance(value, Mapping):
            w.w.add_metadata(name, {k: json.dumps(v, sort_keys=True, default=str) for k, v in value.items()})


# ---------------------------------------------------------------------- reading
def read_arrays(path: str | Path) -> dict[str, Any]:
    """The arrays and ``meta`` of an MCAP recording written by ``write_mcap`` (``slipd.recording.Recording``'s
    fields). ``OSError`` when it cannot be read; ``McapRecordingError`` (one line) when it is not such a file."""
    with open(path, "rb") as fh:
        head = fh.read(len(MAGIC))
        if head != MAGIC:
            what = "empty file" if not head else f"starts with {head[:8]!r}"
            raise McapRecordingError(f"not an MCAP recording ({what})")
        fh.seek(0)
        return _read(fh)


def _read(fh: IO[bytes]) -> dict[str, Any]:
    import struct

    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.stream_reader import CRCValidationError
    from zstandard import ZstdError

    try:
        # The chunks' CRCs: a flipped bit inside a frame would otherwise pass as a different force.
        reader = make_reader(fh, validate_crcs=True)
        meta_records = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        layout = meta_records.get("slipd.recording")
        if layout is None:
            raise McapRecordingError("no slipd.recording metadata (not written by slipd, or cut short)")
        try:
            n, sensors = int(layout["samples"]), int(layout["sensors"])
        except (KeyError, ValueError):
            raise McapRecordingError(f"slipd.recording metadata: bad layout {layout}") from None
        meta: dict[str, Any] = {}
        if "slipd.meta" in meta_records:
            text = meta_records["slipd.meta"].get("json", "{}")
            crc = meta_records["slipd.meta"].get("crc32")
            if crc is not None and crc != str(zlib.crc32(text.encode())):
                raise McapRecordingError("slipd.meta: CRC mismatch (the file is corrupted)")
            try:
                meta = json.loads(text)
            except json.JSONDecodeError as exc:
                raise McapRecordingError(f"slipd.meta: not JSON: {exc}") from None
            if not isinstance(meta, dict):
                raise McapRecordingError("slipd.meta: not a JSON object")
        t_us = np.zeros(n, np.int64)
        force = np.full((n, sensors, N_PILLARS, 3), np.nan, np.float32)
        disp = np.full((n, sensors, N_PILLARS, 3), np.nan, np.float32)
        fric = np.full((n, sensors), np.nan, np.float32)
        seen = np.zeros((n, sensors), bool)
        truth_keys = set(filter(None, layout.get("truth", "").split(",")))
        slip = np.zeros((n, N_PILLARS), bool) if "slip" in truth_keys else None
        label = np.zeros(n, np.uint8) if "label" in truth_keys else None
        motion = np.zeros((n, 3), np.float32) if "object_motion" in truth_keys else None
        frame_topics = [TOPIC_FRAMES.format(s) for s in range(sensors)]
        topics = frame_topics + ([TOPIC_TRUTH] if truth_keys else [])
        for _schema, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
            try:
                m = json.loads(message.data)
                i = int(m["sample"])
                if not 0 <= i < n:
                    raise McapRecordingError(f"{channel.topic}: sample {i} outside 0..{n - 1}")
                if channel.topic == TOPIC_TRUTH:
                    if slip is not None:
                        slip[i] = m["slip"]
                    if label is not None:
                        label[i] = m["label"]
                    if motion is not None:
                        motion[i] = m["object_motion"]
                    continue
                s = int(m["sensor"])
                t_us[i] = int(m["t_us"])
                force[i, s] = np.array(m["force"], np.float64).reshape(N_PILLARS, 3)  # null -> NaN
                disp[i, s] = np.array(m["disp"], np.float64).reshape(N_PILLARS, 3)
                cf = m.get("controller_friction")
                fric[i, s] = np.nan if cf is None else cf
                seen[i, s] = True
            except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
                if isinstance(exc, McapRecordingError):
                    raise
                raise McapRecordingError(f"{channel.topic}: message {message.sequence}: {_one_line(exc)}") from None
    except McapRecordingError:
        raise
    except (McapError, CRCValidationError, ZstdError, EOFError, struct.error, UnicodeDecodeError, KeyError,
            IndexError, OverflowError, MemoryError) as exc:  # what the reader meets in a corrupted file
        raise McapRecordingError(f"broken MCAP file ({_one_line(exc)})") from None
    if not seen.all():
        i, s = (int(v) for v in np.argwhere(~seen)[0])
        raise McapRecordingError(f"{TOPIC_FRAMES.format(s)}: sample {i} missing ({int((~seen).sum())} in all)")
    one = sensors == 1
    return {"t_us": t_us, "force": force[:, 0] if one else force, "disp": disp[:, 0] if one else disp, "slip": slip,
            "label": label, "object_motion": motion, "meta": meta,
            "friction_est": (fric[:, 0] if one else fric) if layout.get("friction_est") == "true" else None}


def channels(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topic -> (schema name, message count) of an MCAP file, from its summary."""
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    if summary is None or summary.statistics is None:
        raise McapRecordingError(f"{path}: no summary section")
    counts = summary.statistics.channel_message_counts
    return {c.topic: (summary.schemas[c.schema_id].name, counts.get(cid, 0)) for cid, c in summary.channels.items()}
