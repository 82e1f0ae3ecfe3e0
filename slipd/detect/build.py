"""One place builds a detector from a config: the daemon, replay, the rig and the offline tools call
``build_detector``. It sits above ``detector`` (one sensor), ``multisensor`` (several sensors, one model call)
and the heuristics, so none of them needs to know about the others.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slipd.config.load import check_against_manifest
from slipd.config.schema import DecisionConfig
from slipd.detect.baselines import CONFIRMED_RULE, ReferencePillarDetector, load_params, make_baseline
from slipd.detect.confirmed import ConfirmedDetector
from slipd.detect.decision import Decision
from slipd.detect.detector import Detector, HeuristicDetector, SlipDetector
from slipd.detect.multisensor import MultiDetector
from slipd.models import PACKAGE_DIR as PACKAGED

if TYPE_CHECKING:
    from slipd.config import SlipdConfig
    from slipd.detect.ensemble import Ensemble


def build_detector(
    cfg: SlipdConfig | None,
    ensemble: Ensemble,
    *,
    offset: np.ndarray | None = None,
    tare_samples: int | None = None,
    sensors: int | None = None,
) -> SlipDetector:
    """The one place a detector is built from a config: the daemon, replay and the rig all call it.

    ``cfg`` None means the model's own stride and threshold with the default config's decision rule
    (``DecisionConfig``: no hysteresis, two decisions in a row, the press hold), as evaluation uses.
    The tare: an explicit ``offset`` ([9, 3], or [S, 9, 3] one per sensor) wins; else ``tare_samples`` (a
    start-up tare of that many samples; 0 means the sensor zeroes itself, offset 0); else the config's ``sensor.tare``.
    ``sensors``: the arrays per frame (default: the config's ``sensor.sensors``, else 1); with more than
    one, a ``slipd.detect.multisensor.MultiDetector`` of one ``Detector`` per sensor, one model call for all.
    """
    spec = ensemble.feature_spec
    if cfg is not None and cfg.model.stride:
        spec = spec.with_(stride=cfg.model.stride)
    rule = cfg.decision if cfg is not None else DecisionConfig()  # no config: the default config's rule
    if offset is None:
        if tare_samples is None:
            startup = cfg is not None and cfg.sensor.tare == "startup"
            tare_samples = cfg.sensor.tare_samples if cfg is not None and startup else 0
        if tare_samples == 0:
            offset = np.zeros((9, 3), np.float32)
    if cfg is not None and cfg.model.detector != "onnx":
        if (sensors or cfg.sensor.sensors) > 1:
            raise ValueError(f"model.detector {cfg.model.detector!r} reads one sensor; sensor.sensors is "
                             f"{sensors or cfg.sensor.sensors} (use the onnx detector for two fingers)")
        # A published heuristic instead of the ensemble (comparisons on the rig); it has no start-up tare of
        # its own, so it expects a zeroed sensor (tare: bias_command).
        return HeuristicDetector(cfg.model.detector, baseline_params_path(cfg), offset)
    if sensors is None:
        sensors = cfg.sensor.sensors if cfg is not None else 1
    det: Detector | MultiDetector
    if sensors > 1:
        offset = None if offset is None else np.broadcast_to(np.asarray(offset, np.float32), (sensors, 9, 3))
        det = MultiDetector([
            Detector(ensemble, build_decision(rule, ensemble.threshold), spec,
                     offset=None if offset is None else offset[s], tare_samples=tare_samples or 0,
                     row=s, rows=sensors, press_rise=rule.press_rise)
            for s in range(sensors)
        ])
    else:
        det = Detector(ensemble, build_decision(rule, ensemble.threshold), spec, offset=offset,
                       tare_samples=tare_samples or 0, press_rise=rule.press_rise)
    if cfg is not None and rule.confirm_rule is not None:
        return confirmed_detector(det, baseline_params_path(cfg), rule.confirm_rule, rule.confirm_within_ms, offset)
    return det


def confirmed_detector(model: Detector | MultiDetector, params_path: Path, level: float, within_ms: float,
                       offset: np.ndarray | None = None) -> ConfirmedDetector:
    """``model`` (one sensor's or several) with the reference-pillar rule of ``params_path``, one per sensor,
    confirmed at ``level`` (``decision.confirm_rule``); ``offset`` the forces' tare ([9, 3] or [S, 9, 3]; the rules'
    normal forces take it, their displacements none), else the members' start-up tare or zero."""
    params, frontend = load_params(params_path, CONFIRMED_RULE)
    rules = []
    for _ in getattr(model, "detectors", [model]):
        rule = make_baseline(CONFIRMED_RULE, params, frontend)
        assert isinstance(rule, ReferencePillarDetector)
        rules.append(rule)
    det = ConfirmedDetector(model, rules, level, round(within_ms * 1000))
    if offset is not None:
        det.set_offset(offset)
    return det


def config_problems(cfg: SlipdConfig, manifest: Any, source: str) -> list[str]:
    """Everything that refuses ``cfg`` with this model before a device is opened (``slipd check-config``, ``slipd
    run``, ``slipd replay``): the config against the manifest, and a heuristic detector's parameters readable (the
    daemon loads them when it builds its detector, which is after the devices were opened and told to hold)."""
    problems = check_against_manifest(cfg, manifest, source)
    rule = cfg.model.detector if cfg.model.detector != "onnx" else CONFIRMED_RULE if cfg.decision.confirm_rule else None
    if rule is not None:
        try:
            load_params(baseline_params_path(cfg), rule)
        except ValueError as exc:
            problems.append(f"{source}: model.baseline_params: {exc}")
    return problems


def baseline_params_path(cfg: SlipdConfig) -> Path:
    """The tuned parameters a heuristic detector (and ``decision.confirm_rule``'s rule) reads:
    ``model.baseline_params``, else those tuned on gripper lifts beside the manifest (``baselines_transfer.json``: the
    rig, the evaluation's hold-out tables and the confirmed rule's figures use them), else ``baselines.json`` there;
    a model without either (one trained here) takes the packaged models' tuned parameters."""
    if cfg.model.baseline_params is not None:
        return cfg.model.baseline_params
    for folder in (cfg.model.manifest.parent, PACKAGED):
        for name in ("baselines_transfer.json", "baselines.json"):
            if (folder / name).is_file():
                return folder / name
    return cfg.model.manifest.parent / "baselines.json"  # (none anywhere: the error names the usual place)


def build_decision(rule: DecisionConfig, model_threshold: float) -> Decision:
    """A config's decision section as the ``Decision`` it asks for (the threshold: the section's, else the
    model's; the limit guard); the press hold is the detector's (``rule.press_rise``)."""
    return Decision(threshold=rule.effective_threshold(model_threshold), hysteresis=rule.hysteresis,
                    min_consecutive=rule.min_consecutive, limit_guard=rule.limit_guard,
                    limit_guard_decisions=rule.limit_guard_decisions)
