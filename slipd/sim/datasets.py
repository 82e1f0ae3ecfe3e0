"""Simulated data sets: ``offline`` (hexapod-like, v1), ``transfer`` (gripper trials, v2), ``robust`` (every
physics family, both sensors, randomised scenario timelines), ``holds`` (long no-slip holds of each type) and
``grips`` (gripper trials whose grip closes at random rates and holds still for random times before the move).

``engine`` (grasps on the MuJoCo engine, ``slipd.sim.engine.draws``: physics written independently of this simulator)
and ``bullet`` (the same scenarios, drawn afresh, on the Bullet engine: a second independent physics) are tagged the
same way (physics family ``engine`` or ``bullet``, the scenario). ``coulomb`` holds ``robust`` scenes and ``grips``
trials drawn afresh with one friction coefficient (kinetic = static, as both engines have).

``robust``, ``holds`` and ``grips`` recordings carry ``meta["physics_family"]`` (one of ``FAMILIES``) and
``meta["scenario"]`` (the scenario kind: ``ROBUST_SCENARIOS`` or ``HOLD_TYPES``), also listed per recording in
``index.json``, so that a family can be left out of training and tested on alone.

Every scene of a set is drawn from a generator seeded by (set, split, seed, index), and its simulation
seed comes from a split-specific range, so the same arguments always give the same files and train
and test never share a seed (``scene_seed``). ``write_dataset`` writes one ``.npz`` per scene
(``Recording.save``) and ``index.json`` (scene parameters, label summary, speed figures).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from slipd.geometry import CORNERS, HEIGHT_OFFSET_MM
from slipd.sim.engine.draws import BULLET_FAMILY, engine_scene
from slipd.sim.engine.draws import PHYSICS_FAMILY as ENGINE_FAMILY
from slipd.sim.physics import compression_for_force, sensor_params
from slipd.sim.scene import (
    GENERATOR_VERSION,
    GripperScene,
    HexapodScene,
    ObjectModel,
    generate_batch,
    parse_scene,
    secure_grip_n,
)

SETS = ("offline", "transfer", "robust", "holds", "grips", "twists", "engine", "bullet", "coulomb", "lights")
SPLITS = ("train", "test")
_SPLIT_BASE = {"train": 0, "test": 1 << 30}
_SET_ID = {"offline": 1, "transfer": 2, "robust": 3, "holds": 4, "grips": 5, "twists": 6, "engine": 7, "bullet": 8,
           "coulomb": 9, "lights": 10}
_ENGINES = ("engine", "bullet")
_TAGGED = ("robust", "holds", "grips", "twists", "engine", "bullet", "coulomb", "lights")

# Effects of a realistic measurement chain, listed by every data-set scene.
MEASUREMENT = [{"name": "lowpass"}, {"name": "noise"}, {"name": "quantisation"}]

OBJECTS: dict[str, dict[str, Any]] = {
    # Filled masses, friction of the gripped face against silicone, size (inertia) and curvature
    # (1/radius; cylinders stand upright, so the curvature runs across the sensor's x axis).
    # Friction is chosen so that the force that just holds each object lies in the method's grip range
    # (8-30 N): at such forces all nine pillars or at least the centre and edges touch, as on the real rig,
    # and an under-grip slips progressively (outer pillars first). With silicone-on-cardboard friction
    # (~0.35) the light objects would slip at 2-5 N, where only the centre pillar touches and incipient
    # slip has no duration to detect.
    "hard_paper_box": {"mass_kg": 0.25, "mu_s": 0.10, "mu_k": 0.08, "size_mm": 80.0, "curvature_1_mm": 0.0},
    "wooden_box": {"mass_kg": 0.5, "mu_s": 0.15, "mu_k": 0.12, "size_mm": 70.0, "curvature_1_mm": 0.0},
    "shampoo_bottle": {"mass_kg": 0.6, "mu_s": 0.15, "mu_k": 0.12, "size_mm": 60.0, "curvature_1_mm": 1 / 40},
    "coffee_jar": {"mass_kg": 0.8, "mu_s": 0.2, "mu_k": 0.16, "size_mm": 90.0, "curvature_1_mm": 1 / 45},
    "pringles_can": {"mass_kg": 0.3, "mu_s": 0.12, "mu_k": 0.1, "size_mm": 75.0, "curvature_1_mm": 1 / 37},
    "thermos_flask": {"mass_kg": 1.0, "mu_s": 0.2, "mu_k": 0.16, "size_mm": 70.0, "curvature_1_mm": 1 / 35},
}
OFFCENTRE_MM = 4.0
"""Centre of mass beside the grasp in off-centre lifts. The secure grip of a stop trial must hold the object (no
gross motion), and the torque of an off-centre weight is held by the grip times the contacts' short lever arms:
``python tools/stabilize.py --holding`` finds every object held by its stop trial's grip at 4 mm (at 1.2-1.3 x the
least grip that holds it), while at 15 mm (generator ``slipd.sim/2``) no grip up to 60 N holds any of them, so
every off-centre "stop" trial turned some 80 degrees under a no-slip label."""
GRIP_FRACTIONS = (0.6, 0.75, 0.9)
"""Slip trials grip at these fractions of the force that would just hold the load."""
TRANSFER_MOTIONS = ("lift", "lift_offcentre", "push")
LEVELS = ("low", "medium", "high")


def scene_seed(set_name: str, split: str, seed: int, index: int) -> int:
    """Simulation seed of scene ``index``: split-specific ranges that never overlap."""
    if split not in _SPLIT_BASE:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if not 0 <= index < 100_000 or not 0 <= seed < 1000:
        raise ValueError("index must be < 100000 and seed in 0..999")
    return _SPLIT_BASE[split] + _SET_ID[set_name] * (1 << 26) + seed * 100_000 + index


OFFLINE_RANGES: dict[str, tuple[float, float]] = {
    # Plate travel at which the least-loaded (corner) pillars start to slip; sets the press depth.
    "first_slip_mm": (0.2, 0.4),
    "mu_s": (0.5, 0.9),
    "mu_k_ratio": (0.75, 0.95),
    "speed_mm_s": (0.5, 5.0),
    "accel_mm_s2": (5.0, 30.0),
    "rot_speed_deg_s": (2.0, 10.0),
    "stop_fraction": (0.15, 0.6),
}
"""Parameter ranges of the offline set (uniform draws), calibrated with ``tools/realism.py``."""
OFFLINE_STOP_PROB = 0.25
HOLD_S = 60.0
"""Length of the still hold of every ``holds`` recording (after its scenario's events)."""


def _depth_for_first_slip(travel_mm: float, mu_s: float, sensor: str = "v1") -> float:
    """Press depth at which a corner pillar's static friction limit is ``travel_mm`` of tip deflection."""
    sp = sensor_params(sensor)
    fz_corner = travel_mm * sp.kt_n_mm / mu_s
    return float(compression_for_force(fz_corner, sp) + HEIGHT_OFFSET_MM[CORNERS[0]])


def offline_scene(rng: np.random.Generator, index: int, stop_prob: float | None = None) -> dict[str, Any]:
    """One hexapod-like scene on the v1 sensor (a dict ready for ``parse_scene``)."""
    r = OFFLINE_RANGES
    kind = str(rng.choice(["translation", "rotation", "both"]))
    stop = bool(rng.random() < (OFFLINE_STOP_PROB if stop_prob is None else stop_prob))
    mu_s = float(rng.uniform(*r["mu_s"]))
    motion: dict[str, Any] = {
        "kind": kind,
        "speed_mm_s": float(rng.uniform(*r["speed_mm_s"])),
        "accel_mm_s2": float(rng.uniform(*r["accel_mm_s2"])),
        "direction_deg": float(rng.uniform(0.0, 360.0)),
        "rot_speed_deg_s": float(rng.uniform(*r["rot_speed_deg_s"])) * float(rng.choice([-1, 1])),
    }
    if kind == "both":
        motion["centre_mm"] = [float(v) for v in rng.uniform(-7.0, 7.0, size=2)]
    if stop:
        motion["stop_fraction"] = float(rng.uniform(*r["stop_fraction"]))
    effects = list(MEASUREMENT)
    if rng.random() < 0.3:
        effects.append({"name": "speed_variation", "amplitude": float(rng.uniform(0.05, 0.3))})
    if rng.random() < 0.3:
        effects.append({"name": "tilt", "angle_deg": float(rng.uniform(0.1, 1.0))})
    if rng.random() < 0.2:
        effects.append({"name": "drift"})
    if rng.random() < 0.2:
        effects.append({"name": "glitches", "rate_hz": 1.0})
    return {
        "family": "hexapod",
        "name": f"offline_{index:05d}_{kind}{'_stop' if stop else ''}",
        "sensor": "v1",
        "contact": {"depth_mm": _depth_for_first_slip(float(rng.uniform(*r["first_slip_mm"])), mu_s)},
        "motion": motion,
        "friction": {"mu_s": mu_s, "mu_k": mu_s * float(rng.uniform(*r["mu_k_ratio"]))},
        "effects": effects,
    }


def gripper_scene(obj_name: str, motion: str, level: str, grip_fraction: float | None,
                  name: str | None = None, close_s: float | None = None, settle_s: float | None = None,
                  sensor: str = "v2", offcentre_mm: float = OFFCENTRE_MM,
                  spec: dict[str, Any] | None = None) -> dict[str, Any]:
    """One gripper trial on the v2 sensor. ``grip_fraction`` None = a secure-grip stop trial.

    ``spec``: the object's mass, friction, size and curvature when it is not one of ``OBJECTS``.

    ``close_s``/``settle_s``: how fast the grip closes and how long it holds still before the arm moves
    (default: the scene defaults, as in the transfer design); the recording grows by the extra settle.
    ``offcentre_mm``: where an off-centre lift puts the centre of mass (a stop trial needs one its grip holds)."""
    if grip_fraction is None and motion == "lift_offcentre" and offcentre_mm != OFFCENTRE_MM:
        raise ValueError(f"a stop trial's secure grip holds an off-centre object at {OFFCENTRE_MM} mm only")
    spec = dict(OBJECTS[obj_name] if spec is None else spec)
    offcentre = motion == "lift_offcentre"
    spec["com_offset_mm"] = [float(offcentre_mm), 0.0] if offcentre else [0.0, 0.0]
    obj = ObjectModel(name=obj_name, **spec)
    kind = "push" if motion == "push" else "lift"
    resist = 0.5 * obj.mass_kg * 9.81
    if grip_fraction is None:
        grip = secure_grip_n(obj, 100.0) if kind == "lift" else 2.0 * resist / obj.mu_s
    else:
        hold = obj.mass_kg * 9.81 / (2 * obj.mu_s) if kind == "lift" else resist / (2 * obj.mu_s)
        if offcentre:
            hold *= 1.0 + offcentre_mm / 20.0  # the twist needs more grip than the weight alone
        grip = grip_fraction * hold
    effects: list[dict[str, Any]] = [*MEASUREMENT, {"name": "servo_lag"}]
    if kind == "lift":
        effects.append({"name": "gravity"})
    if spec["curvature_1_mm"] > 0:
        effects.append({"name": "curvature"})
    if offcentre:
        effects.append({"name": "offcenter_torque"})
    timing: dict[str, Any] = {}
    if close_s is not None or settle_s is not None:
        close, settle = close_s if close_s is not None else 0.3, settle_s if settle_s is not None else 0.2
        timing = {"settle_s": round(settle, 3), "duration_s": round(4.0 + close - 0.3 + settle - 0.2, 3)}
    return {
        "family": "gripper",
        "name": name or f"{obj_name}_{motion}_{level}_{'stop' if grip_fraction is None else f'g{grip_fraction:g}'}",
        "sensor": sensor,
        **timing,
        "object": {"name": obj_name, **spec},
        "grip": {"force_n": round(float(grip), 3), **({"close_s": round(close_s, 3)} if close_s is not None else {})},
        "motion": {"kind": kind, "level": level, **({"push_resist_n": round(resist, 3)} if kind == "push" else {})},
        "trial": "stop" if grip_fraction is None else "slip",
        "effects": effects,
    }


def transfer_design() -> list[dict[str, Any]]:
    """The method's 216-trial design: 6 objects x 3 motions x 3 grip forces x 3 speeds + 54 stop trials."""
    out = []
    for obj in OBJECTS:
        for motion in TRANSFER_MOTIONS:
            for level in LEVELS:
                out.extend(gripper_scene(obj, motion, level, f) for f in GRIP_FRACTIONS)
                out.append(gripper_scene(obj, motion, level, None))
    return out


def dataset_scenes(set_name: str, split: str, count: int | None, seed: int,
                   hold_s: float = HOLD_S) -> list[tuple[dict, int]]:
    """(scene dict, simulation seed) for every scene of a set. ``robust``/``holds`` scene dicts carry their
    tags under ``"_tags"`` (``physics_family``, ``scenario``); ``write_dataset`` moves them into the meta."""
    if set_name not in SETS:
        raise ValueError(f"set must be one of {SETS}, got {set_name!r}")
    if set_name in _TAGGED:
        n = (len(HOLD_TYPES) * 2 * 10 if set_name == "holds" else 200) if count is None else count
        out = []
        for i in range(n):
            rng = np.random.default_rng([_SET_ID[set_name], _SPLIT_BASE[split] >> 20, seed, i])
            d = (robust_scene(rng, i) if set_name == "robust" else grip_scene(rng, i) if set_name == "grips"
                 else twist_scene(rng, i) if set_name == "twists"
                 else engine_scene(rng, i, "mujoco" if set_name == "engine" else "bullet") if set_name in _ENGINES
                 else coulomb_scene(rng, i) if set_name == "coulomb"
                 else light_scene(rng, i) if set_name == "lights"
                 else hold_scene(rng, i, hold_s))
            out.append((d, scene_seed(set_name, split, seed, i)))
        return out
    if set_name == "offline":
        n = 200 if count is None else count
        out = []
        for i in range(n):
            rng = np.random.default_rng([_SET_ID[set_name], _SPLIT_BASE[split] >> 20, seed, i])
            out.append((offline_scene(rng, i), scene_seed(set_name, split, seed, i)))
        return out
    design = transfer_design()
    n = len(design) if count is None else count
    # Repeat the design if more trials are asked for; each repetition gets its own seeds.
    return [(design[i % len(design)], scene_seed(set_name, split, seed, i)) for i in range(n)]


def write_dataset(set_name: str, split: str, out: str | Path, count: int | None = None, seed: int = 0,
                  batch: int = 16, progress: Callable[[int], None] | None = None,
                  hold_s: float = HOLD_S) -> dict[str, Any]:
    """Simulate and write a data set; returns the index (also written as ``index.json``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    items = list(enumerate(dataset_scenes(set_name, split, count, seed, hold_s)))
    if set_name in _TAGGED:
        # Simulate recordings of similar length together (a batch runs as long as its longest scene) and of
        # the same sensor and physics path; files keep their scene index.
        items.sort(key=lambda it: (it[1][0]["family"], it[1][0]["sensor"], _general_path(it[1][0]),
                                   _timeline_s(it[1][0]), it[0]))
    import scipy.signal  # noqa: F401  (the lowpass effect's one-off import is not simulation time)

    entries = []
    sim_s = 0.0
    wall = 0.0
    for b0 in range(0, len(items), batch):
        chunk = items[b0: b0 + batch]
        scenes: list[HexapodScene | GripperScene] = [
            parse_scene({k: v for k, v in d.items() if k != "_tags"}, d["name"]) for _, (d, _) in chunk]
        t0 = time.perf_counter()
        recs = generate_batch(scenes, [s for _, (_, s) in chunk])
        wall += time.perf_counter() - t0
        for (i, (d, s)), rec in zip(chunk, recs):
            fname = f"{i:05d}_{d['name']}.npz"
            tags = d.get("_tags", {})
            rec.meta.update(tags)
            rec.save(out / fname)
            sim_s += len(rec) / 1000.0
            entries.append({
                "file": fname, "seed": s, "kind": rec.meta["kind"], "motion": rec.meta["motion"], **tags,
                "events": rec.meta["events"], "samples": len(rec), "label_samples": int(rec.label.sum()),
                "scene": {k: v for k, v in d.items() if k != "_tags"},
            })
        if progress:
            progress(len(chunk))
    entries.sort(key=lambda e: e["file"])
    index = {
        "set": set_name, "split": split, "seed": seed, "count": len(entries),
        "generator": GENERATOR_VERSION,
        "slip": sum(e["kind"] == "slip" for e in entries), "stop": sum(e["kind"] == "stop" for e in entries),
        "partial": sum(e["kind"] == "partial" for e in entries),
        "slip_with_onset": sum("onset" in e["events"] for e in entries if e["kind"] == "slip"),
        "simulated_s": round(sim_s, 3), "physics_wall_s": round(wall, 3),
        "speed_ratio": round(sim_s / wall, 1) if wall > 0 else None,
        "recordings": entries,
    }
    if set_name in _TAGGED:
        fams = (ENGINE_FAMILY,) if set_name == "engine" else (BULLET_FAMILY,) if set_name == "bullet" else FAMILIES
        index["physics_family"] = {f: sum(e.get("physics_family") == f for e in entries) for f in fams}
        index["scenario"] = {}
        for e in entries:
            index["scenario"][e["scenario"]] = index["scenario"].get(e["scenario"], 0) + 1
    (out / "index.json").write_text(json.dumps(index, indent=1))
    return index


# ---------------------------------------------------------------------------- robustness sets
FAMILIES = ("stick_slip", "viscoelastic", "stribeck", "spread", "calibration")
"""Physics families of the ``robust`` and ``holds`` sets (``spread``/``calibration``: stick-slip with that option)."""
ROBUST_SCENARIOS = ("slip", "stop", "in_contact", "multi", "press", "shear_hold")
_SCENARIO_P = (0.33, 0.2, 0.12, 0.2, 0.07, 0.08)
HOLD_TYPES = ("still_press", "shear_hold", "after_stop", "after_regrasp", "free_air")


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def physics_spec(family: str, rng: np.random.Generator) -> dict[str, Any]:
    """A contact model of ``family`` with randomised parameters (``slipd.sim.contact_models``)."""
    if family == "stick_slip":
        return {"name": "stick_slip"}
    if family == "viscoelastic":
        return {"name": "viscoelastic", "ratio": float(rng.uniform(0.2, 0.6)), "tau_s": _loguniform(rng, 0.05, 2.0)}
    if family == "stribeck":
        return {"name": "stribeck", "vs_mm_s": _loguniform(rng, 0.2, 5.0), "coupling": float(rng.uniform(0.05, 0.4))}
    if family == "spread":
        return {"name": "stick_slip", "spread": {"kt": float(rng.uniform(0.05, 0.25)),
                                                 "height_mm": float(rng.uniform(0.01, 0.08)),
                                                 "mu": float(rng.uniform(0.05, 0.25))}}
    if family == "calibration":
        return {"name": "stick_slip", "calibration": {"rot_deg": float(rng.uniform(1.0, 8.0)),
                                                      "gain": float(rng.uniform(0.02, 0.15))}}
    raise ValueError(f"unknown family {family!r}; known: {FAMILIES}")


def _pre_motion_hold(rng: np.random.Generator) -> float:
    """Still hold before a motion: 0.2 s to 60 s, most of them short (log-uniform in two bands)."""
    return _loguniform(rng, 0.2, 8.0) if rng.random() < 0.85 else _loguniform(rng, 8.0, 60.0)


def _press(rng: np.random.Generator, depth: float, duration: float | None = None) -> dict[str, Any]:
    return {"op": "press", "depth_mm": round(depth, 4),
            "duration_s": round(_loguniform(rng, 0.05, 2.0) if duration is None else duration, 3)}


def _move(rng: np.random.Generator, stop_fraction: float | None = None, fast: bool = False) -> dict[str, Any]:
    r = OFFLINE_RANGES
    kind = str(rng.choice(["translation", "rotation", "both"]))
    speed = float(rng.uniform(*r["speed_mm_s"])) * (2.0 if fast else 1.0)
    accel = _loguniform(rng, 5.0, 300.0 if fast else 100.0)
    rot = float(rng.uniform(*r["rot_speed_deg_s"])) * float(rng.choice([-1, 1]))
    m: dict[str, Any] = {"op": "move", "kind": kind, "speed_mm_s": speed, "accel_mm_s2": accel,
                         "direction_deg": float(rng.uniform(0.0, 360.0)), "rot_speed_deg_s": rot}
    if rng.random() < 0.5:
        m["jerk_mm_s3"] = accel * _loguniform(rng, 5.0, 100.0)  # smoothing over accel/jerk = 10-200 ms
    if kind == "both":
        m["centre_mm"] = [float(v) for v in rng.uniform(-7.0, 7.0, size=2)]
    v_eff = speed if kind == "translation" else abs(np.deg2rad(rot)) * 7.0 if kind == "rotation" else \
        speed + abs(np.deg2rad(rot)) * 7.0
    if stop_fraction is None:
        m["duration_s"] = float(np.clip(2.5 / max(v_eff, 1e-3), 0.5, 6.0))
    else:
        m["stop_fraction"] = round(float(stop_fraction), 4)
    return m


def _hold(lo: float, hi: float, rng: np.random.Generator) -> dict[str, Any]:
    return {"op": "hold", "duration_s": round(_loguniform(rng, lo, hi), 3)}


def _robust_base(rng: np.random.Generator, family: str, sensor: str) -> tuple[dict[str, Any], float]:
    r = OFFLINE_RANGES
    mu_s = float(rng.uniform(*r["mu_s"]))
    depth = _depth_for_first_slip(float(rng.uniform(*r["first_slip_mm"])), mu_s, sensor)
    effects = list(MEASUREMENT)
    if rng.random() < 0.3:
        effects.append({"name": "tilt", "angle_deg": float(rng.uniform(0.1, 1.0))})
    if rng.random() < 0.2:
        effects.append({"name": "drift"})
    if rng.random() < 0.2:
        effects.append({"name": "glitches", "rate_hz": 1.0})
    base = {"family": "hexapod", "sensor": sensor, "physics": physics_spec(family, rng),
            "friction": {"mu_s": mu_s, "mu_k": mu_s * float(rng.uniform(*r["mu_k_ratio"]))},
            "pre_s": round(float(rng.uniform(0.1, 0.5)), 3), "effects": effects}
    return base, depth


def robust_scene(rng: np.random.Generator, index: int) -> dict[str, Any]:
    """One scene of the ``robust`` set: a family (round-robin), a sensor, and a randomised scenario timeline."""
    family = FAMILIES[index % len(FAMILIES)]
    sensor = str(rng.choice(["v1", "v2"]))
    scenario = str(rng.choice(ROBUST_SCENARIOS, p=_SCENARIO_P))
    base, depth = _robust_base(rng, family, sensor)
    pre_hold = {"op": "hold", "duration_s": round(_pre_motion_hold(rng), 3)}
    after = _hold(0.5, 10.0, rng)
    if scenario == "slip":
        tl = [_press(rng, depth), pre_hold, _move(rng), _hold(0.3, 3.0, rng)]
    elif scenario == "stop":
        tl = [_press(rng, depth), pre_hold, _move(rng, float(rng.uniform(0.1, 0.95)), fast=rng.random() < 0.5), after]
    elif scenario == "in_contact":
        stop = rng.random() < 0.4
        tl = [_press(rng, depth, 0.0), pre_hold,
              _move(rng, float(rng.uniform(0.1, 0.95)) if stop else None), _hold(0.3, 3.0, rng)]
    elif scenario == "multi":
        # press, hold, [stop, hold,] slip, hold, release, regrasp, hold, slip or stop, hold
        tl = [_press(rng, depth), pre_hold]
        if rng.random() < 0.5:
            tl += [_move(rng, float(rng.uniform(0.1, 0.95))), _hold(0.3, 8.0, rng)]
        release = {"op": "release", "duration_s": round(float(rng.uniform(0.1, 1.0)), 3)}
        regrasp = _press(rng, depth * float(rng.uniform(0.8, 1.2)))
        tl += [_move(rng), _hold(0.3, 5.0, rng), release, _hold(0.1, 2.0, rng), regrasp, _hold(0.2, 8.0, rng)]
        tl += [_move(rng, float(rng.uniform(0.1, 0.95)) if rng.random() < 0.4 else None), _hold(0.3, 5.0, rng)]
    elif scenario == "press":
        tl = [_press(rng, depth * float(rng.uniform(0.5, 1.5))), _hold(2.0, 30.0, rng)]
    else:  # shear_hold
        tl = [_press(rng, depth), pre_hold, _move(rng, float(rng.uniform(0.3, 0.9))), _hold(2.0, 30.0, rng)]
    return {**base, "name": f"robust_{index:05d}_{family}_{scenario}", "timeline": tl,
            "_tags": {"physics_family": family, "scenario": scenario}}


def grip_scene(rng: np.random.Generator, index: int) -> dict[str, Any]:
    """One recording of the ``grips`` set: a transfer-style gripper trial (default physics, v1 or v2) whose grip
    closes in 0.05-2 s and holds still 0.2-60 s before the arm moves (the transfer design always closes in
    0.3 s and moves 0.2 s later)."""
    obj = str(rng.choice(list(OBJECTS)))
    motion = str(rng.choice(TRANSFER_MOTIONS))
    fraction = None if rng.random() < 0.25 else float(rng.choice(GRIP_FRACTIONS))
    d = gripper_scene(obj, motion, str(rng.choice(LEVELS)), fraction, close_s=_loguniform(rng, 0.05, 2.0),
                      settle_s=_pre_motion_hold(rng), sensor=str(rng.choice(["v1", "v2"])))
    d["name"] = f"grip_{index:05d}_{d['name']}"
    return {**d, "_tags": {"physics_family": "stick_slip", "scenario": "grip"}}


LIGHT_OBJECTS: dict[str, dict[str, float]] = {
    # Objects a gripper holds with a few newtons: the size and curvature of each kind, friction of its face against
    # silicone (cardboard, paper and plastic: higher than ``OBJECTS``' tuned values, which keep the method's grips
    # at 8-30 N).
    "paper_cup": {"size_mm": 70.0, "curvature_1_mm": 1 / 35, "mu": 0.3},
    "empty_box": {"size_mm": 80.0, "curvature_1_mm": 0.0, "mu": 0.4},
    "plastic_bottle": {"size_mm": 65.0, "curvature_1_mm": 1 / 32, "mu": 0.25},
}
LIGHT_HOLD_N = (0.8, 4.0)
"""The grip (N) that just holds a ``lights`` object: drawn first, the mass follows from it and the friction."""


def light_scene(rng: np.random.Generator, index: int) -> dict[str, Any]:
    """One recording of the ``lights`` set: a ``grips``-style trial on a light object (``LIGHT_OBJECTS``, friction
    within 0.7-1.5 x its kind's) whose holding grip is 0.8-4 N (``LIGHT_HOLD_N``), so that slip trials grip at
    0.5-3.6 N, where most pillars carry a fraction of a newton. Every other gripper set grips at 3.7 N or more,
    and a light grasp's slip (all pillars sliding together at a low load) looks like none of theirs."""
    kind = str(rng.choice(list(LIGHT_OBJECTS)))
    k = LIGHT_OBJECTS[kind]
    mu_s = float(k["mu"] * rng.uniform(0.7, 1.5))
    hold = float(rng.uniform(*LIGHT_HOLD_N))
    spec = {"mass_kg": round(hold * 2 * mu_s / 9.81, 4), "mu_s": round(mu_s, 3),
            "mu_k": round(mu_s * float(rng.uniform(0.75, 0.95)), 3), "size_mm": k["size_mm"],
            "curvature_1_mm": k["curvature_1_mm"]}
    fraction = None if rng.random() < 0.25 else round(float(rng.uniform(0.55, 0.92)), 2)
    # No off-centre stop trial: at these grips the secure grip's torque does not hold a light object 4 mm off
    # centre (some turned 50-80 degrees), which a no-slip label would call a hold.
    motion = str(rng.choice(TRANSFER_MOTIONS if fraction is not None else ("lift", "push")))
    d = gripper_scene(kind, motion, str(rng.choice(LEVELS)), fraction, close_s=_loguniform(rng, 0.05, 2.0),
                      settle_s=_pre_motion_hold(rng), sensor=str(rng.choice(["v1", "v2"])), spec=spec)
    d["name"] = f"light_{index:05d}_{d['name']}"
    return {**d, "_tags": {"physics_family": "stick_slip", "scenario": "light"}}


def one_coefficient(d: dict[str, Any]) -> dict[str, Any]:
    """The scene with its kinetic friction coefficient set to the static one (hexapod ``friction`` or gripper
    ``object``): a pillar that starts to slide keeps its force at mu x normal instead of dropping to mu_k x normal."""
    d = dict(d)
    if "friction" in d:
        d["friction"] = {**d["friction"], "mu_k": d["friction"]["mu_s"]}
    if isinstance(d.get("object"), dict) and "mu_s" in d["object"]:
        d["object"] = {**d["object"], "mu_k": d["object"]["mu_s"]}
    return d


def coulomb_scene(rng: np.random.Generator, index: int) -> dict[str, Any]:
    """One recording of the ``coulomb`` set: a ``robust`` scene (even indices) or a ``grips`` trial (odd) with one
    friction coefficient. Every other set draws the kinetic coefficient at 0.75-0.95 of the static one, so every
    slip they hold shows the force drop of breaking away; many real contacts (and both engines) show none, only a
    force that stops growing at mu x normal."""
    d = robust_scene(rng, index // 2) if index % 2 == 0 else grip_scene(rng, index // 2)
    d = one_coefficient(d)
    d["name"] = f"coulomb_{index:05d}_{d['name']}"
    return d


TWIST_OFFSET_MM = (8.0, 20.0)
"""Centre of mass beside the grasp in the ``twists`` set: beyond what any grip within the servo's force holds."""


def twist_scene(rng: np.random.Generator, index: int) -> dict[str, Any]:
    """One recording of the ``twists`` set: an off-centre lift whose centre of mass is 8-20 mm beside the grasp
    (``TWIST_OFFSET_MM``), at the transfer design's grip fractions and levels, with the ``grips`` set's closing and
    settling times, v1 or v2. At such offsets no grip up to the servo's force holds the object (``tools/stabilize.py
    --holding``), so there are no stop trials: every recording is a slip trial, a twist the transfer design's 4 mm
    off-centre lifts do not reach, labelled by the per-pillar truth like every other."""
    obj = str(rng.choice(list(OBJECTS)))
    d = gripper_scene(obj, "lift_offcentre", str(rng.choice(LEVELS)), float(rng.choice(GRIP_FRACTIONS)),
                      close_s=_loguniform(rng, 0.05, 2.0), settle_s=_pre_motion_hold(rng),
                      sensor=str(rng.choice(["v1", "v2"])), offcentre_mm=float(rng.uniform(*TWIST_OFFSET_MM)))
    d["name"] = f"twist_{index:05d}_{d['name']}"
    return {**d, "_tags": {"physics_family": "stick_slip", "scenario": "twist"}}


def hold_scene(rng: np.random.Generator, index: int, hold_s: float = HOLD_S) -> dict[str, Any]:
    """One recording of the ``holds`` set: hold type ``index % 5``, sensor alternating every 5, family
    round-robin every 10; ``hold_s`` of stillness after the scenario's events (none slip)."""
    htype = HOLD_TYPES[index % len(HOLD_TYPES)]
    sensor = ("v1", "v2")[(index // len(HOLD_TYPES)) % 2]
    family = FAMILIES[(index // (2 * len(HOLD_TYPES))) % len(FAMILIES)]
    base, depth = _robust_base(rng, family, sensor)
    depth *= float(rng.uniform(0.6, 1.4))
    long = {"op": "hold", "duration_s": float(hold_s)}
    if htype == "still_press":
        tl = [_press(rng, depth), long]
    elif htype == "shear_hold":
        tl = [_press(rng, depth), _hold(0.2, 2.0, rng), _move(rng, float(rng.uniform(0.3, 0.9))), long]
    elif htype == "after_stop":
        tl = [_press(rng, depth), _hold(0.2, 2.0, rng), _move(rng, float(rng.uniform(0.5, 0.95)), fast=True), long]
    elif htype == "after_regrasp":
        # No shear before the release: unloading a sheared contact makes its tips slide (real slip).
        release = {"op": "release", "duration_s": round(float(rng.uniform(0.1, 0.5)), 3)}
        regrasp = _press(rng, depth * float(rng.uniform(0.8, 1.2)))
        tl = [_press(rng, depth), _hold(0.3, 5.0, rng), release, _hold(0.1, 1.0, rng), regrasp, long]
    else:  # free_air
        tl = [long]
    return {**base, "name": f"hold_{index:05d}_{htype}_{sensor}_{family}", "timeline": tl,
            "_tags": {"physics_family": family, "scenario": htype}}


def _general_path(d: dict[str, Any]) -> bool:
    """True when a scene runs the general contact-model loop rather than the default one."""
    ph = d.get("physics") or {"name": "stick_slip"}
    return ph["name"] != "stick_slip" or "spread" in ph


def _timeline_s(d: dict[str, Any]) -> float:
    """Approximate length of a timeline scene (stop moves count their probe's worst case as 2 s)."""
    if "timeline" not in d:
        return float(d.get("duration_s", 4.0))
    total = float(d.get("pre_s", 0.3))
    for seg in d.get("timeline") or []:
        if seg["op"] == "move":
            total += seg.get("duration_s", 2.0) + 1.0
        else:
            total += seg.get("duration_s", 0.3)
    return total
