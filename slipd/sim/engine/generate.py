"""Engine scenes -> recordings: input profiles from the timeline, the engine run, truth, labels, the sensor model.

The measurement goes through the simulator's one sensor chain (``scene._finish``: the scene's signal effects, the
reported displacements carrying the force error, saturation), and the labels follow the same rule as every other
scene (``slipd.sim.labels``). ``scene.generate_batch`` hands both in as ``Rules``, so that this module does
not import ``scene`` back.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slipd.geometry import N_PILLARS
from slipd.recording import Recording
from slipd.sim import effects as fx
from slipd.sim.engine.model import BulletParams, ObjectGeometry
from slipd.sim.engine.spec import EngineScene, GripSeg, HoldSeg, LiftSeg, LoadSeg
from slipd.sim.engine.stepping import EngineOutput, EngineSim
from slipd.sim.labels import considered_pillars
from slipd.sim.physics import DT_S, sensor_params

STOP_RETRIES = 2
"""A stop that still slid is run again halted earlier (0.8x its load each time)."""


@dataclass(frozen=True)
class Rules:
    """What every scene shares: the path from physics output to a recording, the label rule, gross motion."""

    finish: Callable[..., Recording]
    label_rule: Callable[..., tuple[np.ndarray, int | None, int | None]]
    gross_mm: float
    gross_deg: float


@dataclass
class Profiles:
    """Per-sample inputs of the engine and where each lift / load segment sits."""

    grip: np.ndarray
    accel: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    moves: list[dict] = field(default_factory=list)
    """{op, start, end (sample after the segment), stop (bool), segment index}."""


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _lift_profile(seg: LiftSeg) -> np.ndarray:
    """Acceleration (mm/s^2) per sample of a trapezoidal move over ``distance_mm``."""
    v, a, dist = seg.speed_mm_s, seg.accel_mm_s2, seg.distance_mm
    t_acc = v / a
    if a * t_acc**2 > dist:  # never reaches the speed: a triangle
        t_acc = float(np.sqrt(dist / a))
        t_cruise = 0.0
    else:
        t_cruise = (dist - a * t_acc**2) / v
    n_acc, n_cruise = max(1, round(t_acc / DT_S)), round(t_cruise / DT_S)
    return np.concatenate([np.full(n_acc, a), np.zeros(n_cruise), np.full(n_acc, -a)])


def gravity_vector(sc: EngineScene) -> np.ndarray:
    g = sc.gravity
    d, o = np.deg2rad(g.direction_deg), np.deg2rad(g.out_of_plane_deg)
    return g.g_m_s2 * np.array([np.cos(o) * np.cos(d), np.cos(o) * np.sin(d), np.sin(o)])


def profiles(sc: EngineScene, stop_samples: dict[int, int] | None = None, probe: int | None = None) -> Profiles:
    """The scene's input profiles. ``stop_samples``: for a stop segment, after how many samples its load stops
    growing; ``probe``: the stop segment run as an open ramp (the profile ends with it)."""
    stop_samples = stop_samples or {}
    g = gravity_vector(sc)
    pre = round(sc.pre_s / DT_S)
    grip = [np.zeros(pre)]
    finger_acc = [np.zeros((pre, 2))]  # mm/s^2 in the sensor plane
    load_f = [np.zeros((pre, 3))]
    load_t = [np.zeros((pre, 3))]
    g_now, f_now, t_now = 0.0, np.zeros(3), np.zeros(3)
    moves = []
    k = pre
    g_unit = g / max(np.linalg.norm(g), 1e-12)
    for si, seg in enumerate(sc.timeline):
        if isinstance(seg, GripSeg | HoldSeg):
            n = max(1, round(seg.duration_s / DT_S))
            if isinstance(seg, GripSeg):
                gr = g_now + (seg.force_n - g_now) * _smoothstep((np.arange(n) + 1) / n)
                g_now = seg.force_n
            else:
                gr = np.full(n, g_now)
            grip.append(gr)
            finger_acc.append(np.zeros((n, 2)))
            load_f.append(np.repeat(f_now[None], n, 0))
            load_t.append(np.repeat(t_now[None], n, 0))
        elif isinstance(seg, LiftSeg):
            acc = _lift_profile(seg)
            n = len(acc)
            d = seg.direction_deg if seg.direction_deg is not None else np.rad2deg(np.arctan2(-g[1], -g[0]))
            unit = np.array([np.cos(np.deg2rad(d)), np.sin(np.deg2rad(d))])
            grip.append(np.full(n, g_now))
            finger_acc.append(acc[:, None] * unit)
            load_f.append(np.repeat(f_now[None], n, 0))
            load_t.append(np.repeat(t_now[None], n, 0))
            moves.append({"op": "lift", "start": k, "end": k + n, "stop": False, "segment": si, "unit": unit})
        else:
            assert isinstance(seg, LoadSeg)
            n = max(1, round(seg.duration_s / DT_S))
            grow = np.arange(1, n + 1) * DT_S * seg.rate
            if seg.stop_fraction is not None and probe != si:
                grow[stop_samples.get(si, n):] = grow[min(stop_samples.get(si, n), n) - 1]
            if seg.op == "push":
                a = np.deg2rad(seg.direction_deg)
                df = grow[:, None] * np.array([np.cos(a), np.sin(a), 0.0])
                dt = np.zeros((n, 3))
            elif seg.op == "twist":
                df = np.zeros((n, 3))
                dt = grow[:, None] * 1e-3 * np.array([0.0, 0.0, 1.0 if seg.direction_deg >= 0 else -1.0])
            else:  # fill: added mass along gravity
                df = grow[:, None] * 1e-3 * np.linalg.norm(g) * g_unit
                dt = np.zeros((n, 3))
            grip.append(np.full(n, g_now))
            finger_acc.append(np.zeros((n, 2)))
            load_f.append(f_now + df)
            load_t.append(t_now + dt)
            f_now, t_now = f_now + df[-1], t_now + dt[-1]
            moves.append({"op": seg.op, "start": k, "end": k + n, "stop": seg.stop_fraction is not None,
                          "segment": si})
            if probe == si:
                k += n
                break
        k += n
    acc2 = np.concatenate(finger_acc)
    # The table carries the weight until the first lift has travelled ``liftoff_mm``.
    lifts = [m for m in moves if m["op"] == "lift"]
    carried = np.ones(k)
    if lifts:
        first = lifts[0]
        seg = sc.timeline[first["segment"]]
        along = acc2 @ first["unit"]
        along[: first["start"]] = 0.0
        travel = np.cumsum(np.cumsum(along) * DT_S) * DT_S
        carried = np.clip(1.0 - travel / seg.liftoff_mm, 0.0, 1.0)
        carried[first["end"]:] = 0.0
    share = 1.0 - carried
    # The object's acceleration field in the finger's frame: the grasp's share of gravity and of the arm's
    # acceleration (a translating frame adds -a to every body; the table holds the rest).
    accel = share[:, None] * (g[None] - np.column_stack([acc2 * 1e-3, np.zeros(k)]))
    return Profiles(np.concatenate(grip), accel, np.concatenate(load_f), np.concatenate(load_t), moves)


def object_geometry(sc: EngineScene) -> ObjectGeometry:
    o = sc.object
    return ObjectGeometry(o.shape, o.mass_kg, o.mu, o.size_mm, o.radius_mm, edge_mm=o.edge_mm,
                          jaw_mu=o.jaw_mu if o.jaw_mu is not None else o.mu, jaw_kt_n_mm=o.jaw_kt_n_mm,
                          offset_mm=(float(o.offset_mm[0]), float(o.offset_mm[1])))


def simulate(sc: EngineScene, prof: Profiles) -> EngineOutput:
    params = sc.engine_params()
    if isinstance(params, BulletParams):
        from slipd.sim.engine.bullet import BulletSim  # pybullet only where a scene asks for it

        bullet = BulletSim(sensor_params(sc.sensor), object_geometry(sc), params)
        try:
            return bullet.run(prof.grip, prof.accel, prof.force, prof.torque)
        finally:
            bullet.close()
    sim = EngineSim(sensor_params(sc.sensor), object_geometry(sc), params)
    return sim.run(prof.grip, prof.accel, prof.force, prof.torque)


def considered(out: EngineOutput, start: int) -> np.ndarray:
    """Pillars the labels consider at a segment's start (``slipd.sim.labels``, as every scene's labels use)."""
    return considered_pillars(out.force[start, :, 2])


def gross_motion(pose: np.ndarray, start: int, rules: Rules) -> int | None:
    rel = pose - pose[start]
    big = (np.hypot(rel[:, 0], rel[:, 1]) > rules.gross_mm) | (np.abs(rel[:, 2]) > rules.gross_deg)
    big[:start] = False
    return int(np.argmax(big)) if big.any() else None


def labels(prof: Profiles, out: EngineOutput,
           rules: Rules) -> tuple[tuple[np.ndarray, int | None, int | None], list[dict]]:
    """Union of every non-stop segment's labels, each from its start until the next lift / load segment."""
    n = len(out.slip)
    label = np.zeros(n, np.uint8)
    first: tuple[int | None, int | None] = (None, None)
    items = []
    for j, mv in enumerate(prof.moves):
        end = prof.moves[j + 1]["start"] if j + 1 < len(prof.moves) else n
        cons = considered(out, mv["start"])
        item = {"op": mv["op"], "stop": mv["stop"], "start_s": mv["start"] * DT_S, "end_s": mv["end"] * DT_S}
        if mv["stop"]:
            item["truth_slip"] = bool(out.slip[mv["start"]: end, cons].any())
        else:
            gm = gross_motion(out.pose[:end], mv["start"], rules)
            lab, onset, gross = rules.label_rule(out.slip[:end], cons, mv["start"], gm)
            item["onset_s"] = onset * DT_S if onset is not None else None
            item["gross_slip_s"] = gross * DT_S if gross is not None else None
            if onset is not None and gross is None and not out.slip[end - 1, cons].any():
                # Some pillars slid and stuck again before the next move, and the object never passed the gross
                # threshold: a partial slip that stopped by itself. The grasp held, so nothing is labelled.
                item["partial"] = True
            else:
                label[:end] |= lab
                if first == (None, None) and onset is not None:
                    first = (onset, gross)
        items.append(item)
    return (label, *first), items


def kind(onset: int | None, items: list[dict], moved: bool) -> str:
    """The recording's kind: a slip when a move slipped to gross slip; else partial when a move's partial slip
    stopped by itself; else a stop (moves, none slipped) or a hold (no move)."""
    if onset is not None:
        return "slip"
    if any(it.get("partial") for it in items):
        return "partial"
    return "stop" if moved else "hold"


def _stop_segment(sc: EngineScene) -> int | None:
    for i, s in enumerate(sc.timeline):
        if isinstance(s, LoadSeg) and s.stop_fraction is not None:
            return i
    return None


def run_scene(sc: EngineScene, rules: Rules) -> tuple[Profiles, EngineOutput, dict]:
    """Physics of one scene, stops resolved: (profiles, engine output, stop details)."""
    si = _stop_segment(sc)
    info: dict = {}
    stops: dict[int, int] = {}
    if si is not None:
        probe = profiles(sc, probe=si)
        pout = simulate(sc, probe)
        mv = probe.moves[-1]
        cons = considered(pout, mv["start"])
        _, onset, _ = rules.label_rule(pout.slip, cons, mv["start"])
        seg = sc.timeline[si]
        assert isinstance(seg, LoadSeg)
        limit = (onset - mv["start"]) if onset is not None else mv["end"] - mv["start"]
        stops[si] = max(1, int(seg.stop_fraction * limit))
        info = {"probe_onset_s": onset * DT_S if onset is not None else None, "limit_samples": limit}
    prof = profiles(sc, stops)
    out = simulate(sc, prof)
    if si is not None:
        for attempt in range(STOP_RETRIES):
            mv = next(m for m in prof.moves if m["segment"] == si)
            j = prof.moves.index(mv)
            end = prof.moves[j + 1]["start"] if j + 1 < len(prof.moves) else len(out.slip)
            if not out.slip[mv["start"]: end, considered(out, mv["start"])].any():
                break
            stops[si] = max(1, int(stops[si] * 0.8))
            prof = profiles(sc, stops)
            out = simulate(sc, prof)
            info["retries"] = attempt + 1
        info["stop_load_samples"] = stops[si]
    return prof, out, info


def generate_engine(scenes: list[EngineScene], seeds: list[int], rules: Rules) -> list[Recording]:
    """Simulate engine scenes one by one (each has its own model) and finish them like every other scene."""
    recs = []
    for sc, seed in zip(scenes, seeds):
        prof, out, info = run_scene(sc, rules)
        n = len(out.slip)
        lab, items = labels(prof, out, rules)
        start = prof.moves[0]["start"] if prof.moves else None
        ctx = fx.SimContext(family="engine", n=n, t_s=np.arange(n) * DT_S,
                            motion_start=start if start is not None else n)
        motion = out.pose - (out.pose[start] if start is not None else 0.0)
        res = {"force": out.force, "disp": out.disp, "slip": out.slip}
        gm = gross_motion(out.pose, start, rules) if start is not None else None
        eff = sc.build_effects()
        mtype = "+".join(sorted({m["op"] for m in prof.moves})) or "none"
        rec = rules.finish(sc, eff, seed, ctx, res, motion, sensor_params(sc.sensor).to_dict(), mtype, gm, labels=lab)
        rec.meta["kind"] = kind(lab[1], items, bool(prof.moves))
        if start is None:
            rec.meta["events"].pop("motion_start", None)
        rec.meta["physics"] = {"name": sc.physics.get("name"), **sc.engine_params().model_dump(mode="json")}
        grip = prof.grip[start] if start is not None else float(prof.grip.max())
        rec.meta["engine"] = {"moves": items, **info, "grip_at_motion_n": float(grip),
                              "pillars_in_contact": int(considered(out, start if start is not None else n - 1).sum())}
        recs.append(rec)
    return recs


__all__ = ["N_PILLARS", "Profiles", "Rules", "generate_engine", "profiles", "run_scene"]
