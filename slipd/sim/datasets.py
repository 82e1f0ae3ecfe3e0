"""Simulated data sets: ``offline`` (hexapod-like, v1) and ``transfer`` (gripper trials, v2).

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

SETS = ("offline", "transfer")
SPLITS = ("train", "test")
_SPLIT_BASE = {"train": 0, "test": 1 << 30}
_SET_ID = {"offline": 1, "transfer": 2}

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
OFFCENTRE_MM = 15.0
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
                  name: str | None = None) -> dict[str, Any]:
    """One gripper trial on the v2 sensor. ``grip_fraction`` None = a secure-grip stop trial."""
    spec = dict(OBJECTS[obj_name])
    offcentre = motion == "lift_offcentre"
    spec["com_offset_mm"] = [OFFCENTRE_MM, 0.0] if offcentre else [0.0, 0.0]
    obj = ObjectModel(name=obj_name, **spec)
    kind = "push" if motion == "push" else "lift"
    resist = 0.5 * obj.mass_kg * 9.81
    if grip_fraction is None:
        grip = secure_grip_n(obj, 100.0) if kind == "lift" else 2.0 * resist / obj.mu_s
    else:
        hold = obj.mass_kg * 9.81 / (2 * obj.mu_s) if kind == "lift" else resist / (2 * obj.mu_s)
        if offcentre:
            hold *= 1.0 + OFFCENTRE_MM / 20.0  # the twist needs more grip than the weight alone
        grip = grip_fraction * hold
    effects: list[dict[str, Any]] = [*MEASUREMENT, {"name": "servo_lag"}]
    if kind == "lift":
        effects.append({"name": "gravity"})
    if spec["curvature_1_mm"] > 0:
        effects.append({"name": "curvature"})
    if offcentre:
        effects.append({"name": "offcenter_torque"})
    return {
        "family": "gripper",
        "name": name or f"{obj_name}_{motion}_{level}_{'stop' if grip_fraction is None else f'g{grip_fraction:g}'}",
        "sensor": "v2",
        "object": {"name": obj_name, **spec},
        "grip": {"force_n": round(float(grip), 3)},
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


def dataset_scenes(set_name: str, split: str, count: int | None, seed: int) -> list[tuple[dict, int]]:
    """(scene dict, simulation seed) for every scene of a set."""
    if set_name not in SETS:
        raise ValueError(f"set must be one of {SETS}, got {set_name!r}")
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
                  batch: int = 16, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Simulate and write a data set; returns the index (also written as ``index.json``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    items = dataset_scenes(set_name, split, count, seed)
    import scipy.signal  # noqa: F401  (the lowpass effect's one-off import is not simulation time)

    entries = []
    sim_s = 0.0
    wall = 0.0
    for b0 in range(0, len(items), batch):
        chunk = items[b0: b0 + batch]
        scenes: list[HexapodScene | GripperScene] = [parse_scene(d, d["name"]) for d, _ in chunk]
        t0 = time.perf_counter()
        recs = generate_batch(scenes, [s for _, s in chunk])
        wall += time.perf_counter() - t0
        for k, ((d, s), rec) in enumerate(zip(chunk, recs)):
            i = b0 + k
            fname = f"{i:05d}_{d['name']}.npz"
            rec.save(out / fname)
            sim_s += len(rec) / 1000.0
            entries.append({
                "file": fname, "seed": s, "kind": rec.meta["kind"], "motion": rec.meta["motion"],
                "events": rec.meta["events"], "samples": len(rec), "label_samples": int(rec.label.sum()),
                "scene": d,
            })
        if progress:
            progress(len(chunk))
    index = {
        "set": set_name, "split": split, "seed": seed, "count": len(entries),
        "generator": GENERATOR_VERSION,
        "slip": sum(e["kind"] == "slip" for e in entries), "stop": sum(e["kind"] == "stop" for e in entries),
        "slip_with_onset": sum("onset" in e["events"] for e in entries if e["kind"] == "slip"),
        "simulated_s": round(sim_s, 3), "physics_wall_s": round(wall, 3),
        "speed_ratio": round(sim_s / wall, 1) if wall > 0 else None,
        "recordings": entries,
    }
    (out / "index.json").write_text(json.dumps(index, indent=1))
    return index
