"""``out/sim.mcap``: one closed-loop rig run as an MCAP recording that opens in Foxglove (deploy/foxglove/slipd.json).

It holds the frames the daemon received (the physics' measured forces less the bias the emulated sensor applied on
the daemon's bias command), slipd's decisions on them (the daemon's detector and decision settings, replayed on
these frames: ``slipd replay out/sim.mcap`` gives the same alarms), the daemon's live alarm from its log, the
reactions as the emulated devices received them (the UR stop, the servo's goal writes), the grip force and arm
speed, and the physics' truth (per-pillar slip, the incipient-slip label, the object's motion relative to the
finger). The live alarm and the replayed one can differ by a decision or two: the live detector started on the
unloaded frames before the timeline (its stride's phase and its state come from there).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slipd.config import load_config, override
from slipd.detect.ensemble import Ensemble
from slipd.detect.replay import replay
from slipd.recording import Recording
from slipd.recording_mcap import write_mcap
from slipd.sim.labels import motion_labels
from slipd.sim.physics import DT_S

SERVO_GOAL_ADDRESSES = {116: "goal_position", 100: "goal_pwm", 30: "goal_position", 102: "goal_current"}


def run_recording(physics: Any, result: Any) -> Recording:
    """The frames the daemon received from the timeline's start, with the physics' truth, as a Recording."""
    n = physics.steps
    start = round(physics.timeline_start_s / DT_S)  # the emulator frame at which the timeline began
    bias = np.asarray(getattr(physics, "sensor_bias", np.zeros((9, 3), np.float32)), np.float32)
    force = physics.force[:n] - bias  # float32 - float32, as the emulator computes it
    disp = physics.disp[:n] - np.asarray(getattr(physics, "sensor_bias_disp", np.zeros((9, 3))), np.float32)
    lift = physics.lift_index or 0
    # The truth label as the run's summary computes it (``rig.summarise``), by every scene's rule.
    if n > lift:
        labels, _, _ = motion_labels(physics.slip[:n], physics.force[lift, :, 2], lift)
    else:
        labels = np.zeros(n, np.uint8)
    events = {k: v for k, v in (("lift", result.lift_start_s), ("onset", result.onset_s),
                                ("gross_slip", result.gross_slip_s), ("alarm_live", result.alarm_s)) if v is not None}
    return Recording(
        t_us=(np.arange(n, dtype=np.int64) + start) * 1000, force=force, disp=disp, slip=physics.slip[:n],
        label=np.asarray(labels[:n], np.uint8), object_motion=physics.motion[:n] - physics.motion[lift],
        meta={"source": "slipd-sim", "scene": result.scene, "seed": int(physics.seed), "events": events,
              "rate_hz": 1000.0, "tare_offset": np.zeros((9, 3)).tolist(), "reaction": bool(result.reaction)},
    )


def write_run_mcap(physics: Any, result: Any, config_path: str | Path, path: str | Path = "out/sim.mcap",
                   overrides: dict[str, Any] | None = None) -> tuple[Path, list[int]]:
    """Write the run to ``path``; returns it and the replayed alarms' sample indices (rising edges)."""
    cfg = load_config(config_path)
    if overrides:
        cfg = override(cfg, overrides)
    rec = run_recording(physics, result)
    ensemble = Ensemble.load(cfg.model.manifest, threads=1)
    rec.meta["model_sha256"] = ensemble.manifest.sha256
    threshold = cfg.decision.threshold if cfg.decision.threshold is not None else ensemble.manifest.threshold
    rec.meta["threshold"] = float(threshold)
    rec.meta["config"] = cfg.model_dump(mode="json")
    dets = replay(rec, ensemble, cfg)
    decisions = [{"t_us": d.t_us, "sensor": d.sensor, "p_slip": d.p_slip, "alarm": d.alarm, "risk": d.risk,
                  "pillar_slip": None if d.contact is None else list(d.contact.pillar_slip),
                  "contact_risk": None if d.contact is None else d.contact.risk,
                  "friction": None if d.contact is None else d.contact.friction} for d in dets if d.valid]
    t0 = int(rec.t_us[0]) if len(rec) else 0
    events = [{"t_us": t0 + round(s * 1e6), "reason": name} for name, s in rec.meta["events"].items()]
    for d in dets:
        if d.rising_edge:
            events.append({"t_us": d.t_us, "reason": "alarm", "p_slip": round(d.p_slip, 4), "sensor": d.sensor,
                           "source": "replay"})
    reactions = _reactions(physics, rec)
    state = {"grip_n": physics.grip[: len(rec)].astype(np.float64),
             "arm_speed_mm_s": physics.arm_speed[: len(rec)].astype(np.float64)}
    out = write_mcap(rec, path, decisions=decisions, events=events, reactions=reactions, state=state,
                     threshold=float(threshold))
    return out, [d.index for d in dets if d.rising_edge]


def _reactions(physics: Any, rec: Recording) -> list[dict[str, Any]]:
    """What the emulated devices received after the lift began, at the sample they received it."""
    mono = physics.mono[: len(rec)]
    if not len(mono):
        return []
    t_lift = mono[physics.lift_index or 0]

    def t_us_at(t: float) -> int:
        i = min(int(np.searchsorted(mono, t)), len(mono) - 1)
        return int(rec.t_us[i])

    out: list[dict[str, Any]] = []
    ur = getattr(physics, "ur_state", None)
    if ur is not None and ur.stop_count and ur.last_stop_received_t > 0:
        out.append({"t_us": t_us_at(ur.last_stop_received_t), "action": "stop_arm", "state": "reached",
                    "detail": f"{ur.stop_count} stop(s) at the UR controller"})
    for w in getattr(physics, "servo_writes", []):
        if w.t >= t_lift and w.address in SERVO_GOAL_ADDRESSES:
            value = int.from_bytes(bytes(w.data[:4]), "little")
            out.append({"t_us": t_us_at(w.t), "action": "tighten_gripper", "state": "reached",
                        "detail": f"{SERVO_GOAL_ADDRESSES[w.address]} {value}"})
    return sorted(out, key=lambda r: r["t_us"])
