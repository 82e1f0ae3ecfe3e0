"""``slipd replay RECORDING``: run a recording through the daemon's own decision path, offline.

The recording's samples go through the same ``Detector`` (features -> ensemble -> decision) that
the live loop feeds from the serial reader, as fast as possible, so the alarms printed here are the
alarms the daemon raises on the same frames (a test checks it against the live loop on a pty).

Tare, in order of precedence: the offset the daemon used (``meta["tare_offset"]``, written by the
recorder), the configuration's tare (``--config``), the recording's unloaded stretch
(``meta["tare_samples"]``), the model's default stretch.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from slipd.decision import Decision
from slipd.detector import Detection, Detector, run_recording
from slipd.features import tare_offset
from slipd.recording import Recording

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "models" / "slip_ensemble.json"


def detector_for(rec: Recording, ensemble: Any, cfg: Any = None) -> Detector:
    """The Detector the daemon would build for this recording (see the module docstring for the tare)."""
    spec = ensemble.feature_spec
    threshold, hysteresis, consecutive = ensemble.threshold, 0.0, 1
    if cfg is not None:
        if cfg.model.stride:
            spec = spec.with_(stride=cfg.model.stride)
        threshold = cfg.decision.effective_threshold(ensemble.threshold)
        hysteresis = cfg.decision.hysteresis
        consecutive = cfg.decision.min_consecutive
    decision = Decision(threshold=threshold, hysteresis=hysteresis, min_consecutive=consecutive)
    if "tare_offset" in rec.meta:
        return Detector(ensemble, decision, spec, offset=np.asarray(rec.meta["tare_offset"], np.float32))
    if cfg is not None:
        if cfg.sensor.tare == "startup":
            return Detector(ensemble, decision, spec, tare_samples=cfg.sensor.tare_samples)
        return Detector(ensemble, decision, spec, offset=np.zeros((9, 3), np.float32))
    a, b = rec.meta.get("tare_samples", spec.tare_samples)
    if a == 0:
        return Detector(ensemble, decision, spec, tare_samples=int(b))
    return Detector(ensemble, decision, spec, offset=tare_offset(rec.force, int(a), int(b)))


def replay(rec: Recording, ensemble: Any, cfg: Any = None) -> list[Detection]:
    """Every decision the daemon makes on ``rec``."""
    ensemble.reset()
    return run_recording(detector_for(rec, ensemble, cfg), rec.force, rec.t_us)


def main_replay(args: Any) -> int:
    """CLI handler: print the alarms (rising edges) with their times; optional JSON of every decision."""
    from slipd.__main__ import EXIT_CONFIG, EXIT_MODEL, EXIT_OK, EXIT_RUNTIME
    from slipd.ensemble import Ensemble
    from slipd.manifest import ModelError
    from slipd.recording import RecordingError

    cfg = None
    if args.config:
        from slipd.config import ConfigError, load_config

        try:
            cfg = load_config(args.config)
        except ConfigError as exc:
            print(exc, file=sys.stderr)
            return EXIT_CONFIG
    model = Path(args.model) if args.model else (cfg.model.manifest if cfg is not None else DEFAULT_MODEL)
    try:
        ensemble = Ensemble.load(model)
    except ModelError as exc:
        print(f"slipd replay: {exc}", file=sys.stderr)
        return EXIT_MODEL
    try:
        rec = Recording.load(args.recording)
    except RecordingError as exc:
        print(f"slipd replay: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    dets = replay(rec, ensemble, cfg)
    alarms = [d for d in dets if d.rising_edge]
    t0 = int(rec.t_us[0]) if len(rec) else 0
    print(f"{args.recording}: {len(rec)} samples, {len(dets)} decisions, {len(alarms)} alarm(s)")
    for d in alarms:
        print(f"  alarm at sample {d.index}  t={(d.t_us - t0) / 1e6:.3f} s  p_slip={d.p_slip:.3f}  risk={d.risk:.2f}")
    onset = rec.onset_index()
    if onset is not None:
        print(f"  labelled onset at sample {onset}  t={(int(rec.t_us[onset]) - t0) / 1e6:.3f} s")
    if args.json:
        out = {
            "recording": str(args.recording),
            "model": str(model),
            "alarms": [d.index for d in alarms],
            "decisions": [{"index": d.index, "t_us": d.t_us, "p_slip": d.p_slip, "alarm": d.alarm} for d in dets],
        }
        Path(args.json).write_text(json.dumps(out, indent=1))
    return EXIT_OK
