"""The ``engine`` data set's scenes: randomised grasps on the engine, each tagged with its scenario.

Scenarios (``ENGINE_SCENARIOS``), drawn in turn so every split has all of them:

``lift_slip``    an under-gripped lift (0.5-0.95 of the grip that holds the load) at the method's arm speeds and
                 faster;
``secure_lift``  a lift at 1.8-3 x the grip that holds the load (should never alarm);
``light_grasp``  a total grip of 0.8-3 N on an object (20-500 g) that it holds or not, lifted;
``curved``       a thin cylinder or a sphere (possibly centred between pillars) that loads two or three pillars;
``slow_load``    a secure lift, then a load that grows slowly until it slips: a container being filled, or a
                 slow push or twist;
``stop``         a secure lift, then a push, twist or filling that stops at 0.5-0.95 of its stick limit;
``hold``         a secure lift, then a long still hold (5-12 s), sometimes a press (the grip rises) first;
``push_twist``   a secure grasp, then a push or a twist that grows past the limit (fast or slow).

Objects: boxes, cylinders across and along the finger, spheres and edges; 20 g-1.5 kg; friction 0.2-1.2; grip
0.5-40 N; gravity in any direction of the sensor plane and up to 30 degrees out of it. Timing is randomised
(the pause before the grip, how fast it closes, the still time before and after each event).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slipd.sim.engine.model import SHAPES
from slipd.sim.physics import sensor_params

ENGINE_SCENARIOS = ("lift_slip", "secure_lift", "light_grasp", "curved", "slow_load", "stop", "hold", "push_twist")
PHYSICS_FAMILY = "engine"
BULLET_FAMILY = "bullet"
"""The ``bullet`` set: the same scenarios drawn afresh and run on the second engine (``physics: {name: bullet}``)."""
MEASUREMENT = [{"name": "lowpass"}, {"name": "noise"}, {"name": "quantisation"}]
G = 9.81
ARM_LEVELS = ((4.0, 10.0), (10.0, 50.0), (40.0, 100.0), (100.0, 500.0), (250.0, 1500.0))
"""(speed mm/s, acceleration mm/s^2): the method's UR levels (low, medium, high) and two faster ones."""
MAX_GRIP_N = 40.0


def _lu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _object(rng: np.random.Generator, shape: str | None = None, mass: tuple[float, float] = (0.05, 1.5),
            curved_small: bool = False) -> dict[str, Any]:
    shape = shape or str(rng.choice(SHAPES))
    o: dict[str, Any] = {"shape": shape, "mass_kg": round(_lu(rng, *mass), 4),
                         "mu": round(float(rng.uniform(0.2, 1.2)), 3)}
    if shape in ("box", "edge"):
        o.update(size_mm=round(float(rng.uniform(30.0, 100.0)), 1), radius_mm=round(float(rng.uniform(8.0, 40.0)), 1))
        if shape == "edge":
            o["edge_mm"] = round(float(rng.uniform(-5.0, 5.0)), 2)
    else:
        r = (6.0, 18.0) if curved_small else (12.0, 60.0)
        o.update(radius_mm=round(_lu(rng, *r), 1), size_mm=round(float(rng.uniform(40.0, 150.0)), 1))
        if curved_small and rng.random() < 0.5:
            # Centred between pillars: a sphere then loads two, a cylinder two rows.
            o["offset_mm"] = [round(float(rng.choice([-3.5, 3.5])), 2), 0.0] if shape != "cylinder_across" else \
                [0.0, round(float(rng.choice([-3.5, 3.5])), 2)]
    o["jaw_mu"] = round(o["mu"] * float(rng.uniform(0.7, 1.3)), 3)
    o["jaw_kt_n_mm"] = round(_lu(rng, 8.0, 40.0), 2)
    return o


def _gravity(rng: np.random.Generator) -> dict[str, Any]:
    out = float(rng.uniform(-30.0, 30.0)) if rng.random() < 0.4 else 0.0
    return {"g_m_s2": G, "direction_deg": round(float(rng.uniform(0.0, 360.0)), 1), "out_of_plane_deg": round(out, 1)}


def _arm(rng: np.random.Generator, fast: bool = True) -> tuple[float, float]:
    v, a = ARM_LEVELS[int(rng.integers(0, len(ARM_LEVELS) if fast else 3))]
    return v * float(rng.uniform(0.8, 1.2)), a * float(rng.uniform(0.8, 1.2))


def holding_grip(obj: dict[str, Any], gravity: dict[str, Any], accel_mm_s2: float, sensor: str = "v2") -> float:
    """Grip (N) that just carries the in-plane load (weight plus the arm's acceleration).

    The load splits between the pillars and the jaw's pad by their stiffness, and the pillars' share is held by
    unevenly loaded tips (the outer ones, with less normal force, saturate first: about 60 % of mu x grip is
    available before the first slides), so the grip must satisfy both the jaw-plus-pillars limit and the pillars'
    own. An out-of-plane pull towards the jaw takes its share off the sensor's normal force, so it is added."""
    o = np.deg2rad(gravity["out_of_plane_deg"])
    load = obj["mass_kg"] * (G * np.cos(o) + accel_mm_s2 * 1e-3)
    mu, jaw_mu = obj["mu"], obj.get("jaw_mu", obj["mu"])
    k_pillars = 9 * sensor_params(sensor).kt_n_mm
    share = k_pillars / (k_pillars + obj.get("jaw_kt_n_mm", 20.0))
    need = max(load / (mu + jaw_mu), share * load / (0.6 * mu))
    return float(need + max(0.0, obj["mass_kg"] * G * np.sin(o)))


def _lift(rng: np.random.Generator, fast: bool = True) -> dict[str, Any]:
    v, a = _arm(rng, fast)
    return {"op": "lift", "speed_mm_s": round(v, 2), "accel_mm_s2": round(a, 1),
            "distance_mm": round(float(np.clip(v * rng.uniform(0.3, 1.2), 3.0, 80.0)), 2)}


def _hold(rng: np.random.Generator, lo: float, hi: float) -> dict[str, Any]:
    return {"op": "hold", "duration_s": round(_lu(rng, lo, hi), 3)}


def _grasp(rng: np.random.Generator, grip: float) -> list[dict[str, Any]]:
    """Close the grip at a random rate and hold still a random time before the arm moves."""
    return [{"op": "grip", "force_n": round(float(np.clip(grip, 0.5, MAX_GRIP_N)), 3),
             "duration_s": round(_lu(rng, 0.05, 1.0), 3)}, _hold(rng, 0.1, 2.0)]


def _load(rng: np.random.Generator, obj: dict[str, Any], grip: float, slow: bool,
          lifted: bool = True) -> dict[str, Any]:
    """A growing load that passes the grasp's stick limit within its duration (push, twist or filling)."""
    op = str(rng.choice(["push", "twist", "fill"]))
    capacity = (obj["mu"] + obj.get("jaw_mu", obj["mu"])) * grip
    spare = max(capacity - (obj["mass_kg"] * G if lifted else 0.0), 0.2)  # N of tangential capacity left
    t_limit = _lu(rng, 1.5, 3.0) if slow else _lu(rng, 0.3, 1.2)  # about when the load reaches it
    if op == "push":
        rate = spare / t_limit
    elif op == "twist":
        rate = spare * 25.0 / t_limit  # N mm/s: the pillars' and the pad's lever arms are millimetres to centimetres
    else:
        rate = spare / G * 1e3 / t_limit  # g/s
    d = {"op": op, "rate": round(float(rate), 4), "duration_s": round(t_limit * 2.5, 3)}
    if op == "push":
        d["direction_deg"] = round(float(rng.uniform(0.0, 360.0)), 1)
    elif op == "twist":
        d["direction_deg"] = float(rng.choice([-1.0, 1.0]))
    return d


def _slip_turn(index: int) -> bool:
    """Seven in ten rounds of the scenarios under-grip (a fixed share: each split gets it exactly)."""
    return (index // len(ENGINE_SCENARIOS)) % 10 in (0, 1, 3, 4, 6, 7, 9)


def engine_scene(rng: np.random.Generator, index: int, engine: str = "mujoco") -> dict[str, Any]:
    """One scene of the ``engine`` set (``engine="bullet"``: of the ``bullet`` set), a dict for ``parse_scene`` with
    ``_tags``."""
    scenario = ENGINE_SCENARIOS[index % len(ENGINE_SCENARIOS)]
    sensor = str(rng.choice(["v1", "v2"]))
    grav = _gravity(rng)
    if scenario == "curved":
        obj = _object(rng, shape=str(rng.choice(["cylinder_across", "cylinder_along", "sphere"])), mass=(0.02, 0.4),
                      curved_small=True)
    else:
        obj = _object(rng)
    lift = _lift(rng)
    need = holding_grip(obj, grav, lift["accel_mm_s2"], sensor)
    secure = float(rng.uniform(1.8, 3.0)) * (2.0 if obj["shape"] == "sphere" else 1.0)
    tl: list[dict[str, Any]]
    if scenario == "light_grasp":
        # The grip first (0.8-3 N), then an object that this grip holds or not.
        slip = _slip_turn(index)
        grip = float(rng.uniform(0.8, 3.0))
        per_kg = holding_grip({**obj, "mass_kg": 1.0}, grav, lift["accel_mm_s2"], sensor)
        obj["mass_kg"] = round(float(np.clip(grip / per_kg * (rng.uniform(1.0, 3.0) if slip else 1.0 / secure),
                                             0.02, 0.5)), 4)
        tl = [*_grasp(rng, grip), lift, _hold(rng, 0.3, 2.0)]
    elif scenario in ("lift_slip", "curved"):
        slip = scenario == "lift_slip" or _slip_turn(index)
        grip = need * (float(rng.uniform(0.3, 0.9)) if slip else secure)
        tl = [*_grasp(rng, grip), lift, _hold(rng, 0.3, 2.0)]
    elif scenario == "secure_lift":
        tl = [*_grasp(rng, need * secure), lift, _hold(rng, 0.3, 2.0)]
    elif scenario in ("slow_load", "stop"):
        grip = min(need * secure, MAX_GRIP_N)
        load = _load(rng, obj, grip, slow=scenario == "slow_load")
        if scenario == "stop":
            load["stop_fraction"] = round(float(rng.uniform(0.5, 0.95)), 3)
        tl = [*_grasp(rng, grip), lift, _hold(rng, 0.2, 1.5), load, _hold(rng, 0.3, 2.0)]
    elif scenario == "hold":
        grip = min(need * secure, MAX_GRIP_N)
        tl = [*_grasp(rng, grip), lift, _hold(rng, 0.2, 1.0)]
        if rng.random() < 0.4:  # a press: the grip rises while held
            tl.append({"op": "grip", "force_n": round(min(grip * float(rng.uniform(1.2, 2.0)), MAX_GRIP_N), 3),
                       "duration_s": round(_lu(rng, 0.1, 1.0), 3)})
        tl.append(_hold(rng, 5.0, 12.0))
    else:  # push_twist: on the table (no lift), a load past the limit
        grip = float(np.clip(_lu(rng, 1.0, 30.0), 0.5, MAX_GRIP_N))
        load = _load(rng, obj, grip, slow=rng.random() < 0.3, lifted=False)
        if load["op"] == "fill":
            load = {**load, "op": "push", "direction_deg": round(float(rng.uniform(0.0, 360.0)), 1),
                    "rate": round(load["rate"] * G * 1e-3, 4)}
        tl = [*_grasp(rng, grip), load, _hold(rng, 0.3, 1.5)]
    effects = list(MEASUREMENT)
    if rng.random() < 0.2:
        effects.append({"name": "drift"})
    if rng.random() < 0.2:
        effects.append({"name": "glitches", "rate_hz": 1.0})
    family = BULLET_FAMILY if engine == "bullet" else PHYSICS_FAMILY
    return {"family": "engine", "name": f"{family}_{index:05d}_{scenario}_{obj['shape']}", "sensor": sensor,
            "physics": {"name": engine}, "object": obj, "gravity": grav,
            "pre_s": round(float(rng.uniform(0.1, 0.5)), 3), "timeline": tl, "effects": effects,
            "_tags": {"physics_family": family, "scenario": scenario}}
