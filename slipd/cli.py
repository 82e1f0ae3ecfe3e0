"""Command line: ``slipd run | sim | replay | convert | check-config | models | version`` (also ``python -m slipd``).

Every subcommand and every exit code lives here; the packages below raise typed errors
(``ConfigError``, ``ModelError``, ``RecordingError``, ``DeviceError``) and this module turns them into
one line on stderr and an exit code. Each subcommand imports its package only when it runs, so
``slipd check-config`` stays fast and ``slipd run`` never imports the simulator, torch or matplotlib.

Exit codes (docs/configuration.md):
    0 success; 1 runtime failure; 2 usage error; 3 invalid configuration; 4 invalid model;
    5 device failure at start-up; 6 a resource of this machine unavailable at start-up (the metrics port in use).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from slipd import __version__

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, EXIT_CONFIG, EXIT_MODEL, EXIT_DEVICE, EXIT_RESOURCE = 0, 1, 2, 3, 4, 5, 6


def _err(text: object) -> None:
    print(text, file=sys.stderr)


# ---------------------------------------------------------------------------------------------- run
def cmd_run(args: argparse.Namespace) -> int:
    """``slipd run --config FILE``: config, model, devices, then the loop (the daemon's own order)."""
    import logging

    from slipd.config import ConfigError
    from slipd.daemon.service import DeviceError, ResourceError, StopRequested, prepare
    from slipd.detect.manifest import ModelError
    from slipd.io.sensor import SensorError

    try:
        service = prepare(args.config)
    except StopRequested:
        return EXIT_OK  # asked to stop during start-up: what was opened is closed again
    except ConfigError as exc:
        _err(exc)
        return EXIT_CONFIG
    except ModelError as exc:
        _err(f"{args.config}: model.manifest: {exc}")
        return EXIT_MODEL
    except DeviceError as exc:
        _err(f"slipd: {exc}")
        return EXIT_DEVICE
    except ResourceError as exc:
        _err(f"slipd: {exc}")
        return EXIT_RESOURCE
    try:
        service.run()
    except StopRequested:
        return EXIT_OK  # before the loop took the signals over; the devices were closed
    except SensorError as exc:  # the port exists but cannot be opened (busy, not a tty): a device at start-up
        _err(f"slipd: sensor: {exc}")
        return EXIT_DEVICE
    except Exception:
        logging.getLogger("slipd").exception("daemon failed")
        return EXIT_RUNTIME
    return EXIT_OK


# ---------------------------------------------------------------------------------------------- check-config
def cmd_check_config(args: argparse.Namespace) -> int:
    """``slipd check-config FILE``: 0 valid, 3 invalid config (an enabled section's extra not installed included),
    4 invalid model. Touches no hardware."""
    from slipd.config import ConfigError, load_config, permission_warnings, summary
    from slipd.daemon.preflight import extra_problems
    from slipd.detect.build import config_problems
    from slipd.detect.manifest import ModelError, load_manifest

    path = Path(args.config)
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        _err(exc)
        return EXIT_CONFIG
    for w in permission_warnings(path):
        _err(w)
    try:
        manifest = load_manifest(cfg.model.manifest)
    except ModelError as exc:
        _err(f"{path}: model.manifest: {exc}")
        return EXIT_MODEL
    problems = config_problems(cfg, manifest, str(path)) + extra_problems(cfg, str(path))
    if problems:
        _err("\n".join(problems))
        return EXIT_CONFIG
    print(f"OK {path}: {summary(cfg, manifest)}")
    return EXIT_OK


# ---------------------------------------------------------------------------------------------- replay
def cmd_replay(args: argparse.Namespace) -> int:
    """Print the alarms (rising edges) with their times; optional JSON of every decision."""
    from slipd import models
    from slipd.config import ConfigError, load_config
    from slipd.detect.build import config_problems
    from slipd.detect.ensemble import Ensemble
    from slipd.detect.manifest import ModelError
    from slipd.detect.replay import replay
    from slipd.recording import Recording, RecordingError

    if args.sample == (args.recording is not None):
        _err("slipd replay: give a RECORDING or --sample (the packaged sample), not both")
        return EXIT_USAGE
    if args.sample:
        args.recording = str(models.SAMPLE_RECORDING)
    cfg = None
    if args.config:
        try:
            cfg = load_config(args.config)
        except ConfigError as exc:
            _err(exc)
            return EXIT_CONFIG
    rec = None
    if not args.model and cfg is None:
        # The recording names the model that decided it: replay with that one where it is packaged.
        try:
            rec = Recording.load(args.recording)
        except RecordingError as exc:
            _err(f"slipd replay: {exc}")
            return EXIT_RUNTIME
    try:
        if args.model:
            model = models.packaged(args.model) if models.is_name(args.model) else Path(args.model)
        elif cfg is not None:
            model = cfg.model.manifest
        else:
            model = _packaged_by_sha(rec.meta.get("model_sha256") if rec is not None else None) or \
                models.packaged(models.DEFAULT_MODEL)
        ensemble = Ensemble.load(model)
    except (ModelError, FileNotFoundError) as exc:
        _err(f"slipd replay: {exc}")
        return EXIT_MODEL
    if cfg is not None:
        problems = config_problems(cfg, ensemble.manifest, str(args.config))
        if problems:  # as check-config and run refuse it
            _err("\n".join(problems))
            return EXIT_CONFIG
    if args.json:  # checked before the output, not after it
        out_path = Path(args.json).resolve()
        target = out_path if out_path.exists() else out_path.parent
        problem = ("its folder does not exist" if not out_path.parent.is_dir() else "is a folder" if out_path.is_dir()
                   else "cannot be written" if not os.access(target, os.W_OK) else None)
        if problem:
            _err(f"slipd replay: --json {args.json}: {problem}")
            return EXIT_USAGE
    try:
        rec = rec or Recording.load(args.recording)
    except RecordingError as exc:
        _err(f"slipd replay: {exc}")
        return EXIT_RUNTIME
    try:
        dets = replay(rec, ensemble, cfg)
    except (ValueError, TypeError) as exc:
        # What the recording's metadata asks of the decision path and cannot be (a tare stretch beyond its end, a
        # tare offset of the wrong shape, two sensors for a one-sensor detector): one line, not a traceback.
        _err(f"slipd replay: {args.recording}: {' '.join(str(exc).split())}")
        return EXIT_RUNTIME
    alarms = [d for d in dets if d.rising_edge]
    t0 = int(rec.t_us[0]) if len(rec) else 0
    print(f"{args.recording}: {len(rec)} samples, {len(dets)} decisions, {len(alarms)} alarm(s)")
    # The daemon's recordings name the model that decided them. Replaying with another one is how models are
    # compared, but its decisions are then not the ones the robot saw: say so, rather than let them pass for those.
    recorded_sha = rec.meta.get("model_sha256")
    recorded_sha = recorded_sha if isinstance(recorded_sha, str) else None
    if recorded_sha is not None and recorded_sha != ensemble.manifest.sha256:
        print(f"  recorded with model sha256 {recorded_sha[:16]}, replayed with {ensemble.manifest.sha256[:16]} "
              f"({model}): these are not the decisions the daemon made")
    finger = rec.sensors > 1
    for d in alarms:
        on = f" on sensor {d.sensor}" if finger else ""
        print(f"  alarm{on} at sample {d.index}  t={(d.t_us - t0) / 1e6:.3f} s  p_slip={d.p_slip:.3f}"
              f"  risk={d.risk:.2f}")
    onset = rec.onset_index()
    if onset is not None:
        print(f"  labelled onset at sample {onset}  t={(int(rec.t_us[onset]) - t0) / 1e6:.3f} s")
    bad, blind = nonfinite_runs(rec)
    if bad:
        # The live daemon is blind on such a run (the sensor_nonfinite fail-safe) where the replay only holds values.
        at = "" if blind is None else f"; the daemon would fail safe (sensor_nonfinite) at t={(blind - t0) / 1e6:.3f} s"
        print(f"  {bad} sample(s) not finite{at}")
    if args.json:
        # Each decision with its contact state (the slip map, friction estimate, contact risk, grip, load).
        decisions: list[dict[str, Any]] = [
            {"index": d.index, "t_us": d.t_us, "p_slip": d.p_slip, "alarm": d.alarm, "risk": d.risk,
             **(d.contact.to_dict() if d.contact is not None else {})} for d in dets
        ]
        out: dict[str, Any] = {
            "recording": str(args.recording),
            "model": str(model),
            "model_sha256": ensemble.manifest.sha256,
            "recorded_model_sha256": recorded_sha,
            "alarms": [d.index for d in alarms],
            "decisions": decisions,
        }
        if bad:
            out["nonfinite_samples"] = bad
            out["failsafe_t_us"] = blind
        if finger:
            out["sensors"] = rec.sensors
            out["alarm_sensors"] = [d.sensor for d in alarms]
            for entry, d in zip(decisions, dets):
                entry["sensor"] = d.sensor
        if rec.friction_est is not None:
            # The PapillArray controller's own estimate at the same sample, beside slipd's ``friction``.
            est = rec.friction_est if rec.friction_est.ndim == 2 else rec.friction_est[:, None]
            for entry, d in zip(decisions, dets):
                v = float(est[min(d.index, len(est) - 1), d.sensor])
                entry["controller_friction"] = None if v != v else round(v, 4)  # NaN: it reported none
        try:
            Path(args.json).write_text(json.dumps(out, indent=1))
        except OSError as exc:
            _err(f"slipd replay: --json {args.json}: cannot write ({exc.strerror or exc})")
            return EXIT_RUNTIME
    if bad == len(rec) and len(rec):
        _err(f"slipd replay: {args.recording}: no finite sample: nothing was decided on")
        return EXIT_RUNTIME
    return EXIT_OK


# ---------------------------------------------------------------------------------------------- convert
CONVERT_SUFFIXES = (".mcap", ".npz", ".csv")


def cmd_convert(args: argparse.Namespace) -> int:
    """``slipd convert IN OUT``: a recording from one format into another, by the files' endings (the same samples,
    truth and metadata; replay decides identically on both)."""
    from slipd.recording import Recording, RecordingError, write_sdk_csv
    from slipd.recording_mcap import write_mcap

    for given in (args.input, args.output):
        if Path(given).suffix.lower() not in CONVERT_SUFFIXES:
            _err(f"slipd convert: {given}: unknown format (the name must end in {', '.join(CONVERT_SUFFIXES)})")
            return EXIT_USAGE
    out = Path(args.output)
    if not out.parent.is_dir():
        _err(f"slipd convert: {out}: its folder does not exist")
        return EXIT_USAGE
    try:
        rec = Recording.load(args.input)
    except RecordingError as exc:
        _err(f"slipd convert: {exc}")
        return EXIT_RUNTIME
    suffix = out.suffix.lower()
    try:
        if suffix == ".mcap":
            write_mcap(rec, out)
        elif suffix == ".csv":
            write_sdk_csv(rec, out)
        else:
            rec.save(out)
    except OSError as exc:
        _err(f"slipd convert: {out}: cannot write ({exc.strerror or exc})")
        return EXIT_RUNTIME
    print(f"{args.input} -> {out}: {len(rec)} samples, {rec.sensors} sensor(s)")
    return EXIT_OK


def _packaged_by_sha(sha: object) -> Path | None:
    """The packaged model whose graph has this sha256 (a recording's ``model_sha256``), or None."""
    from slipd import models
    from slipd.detect.manifest import ModelError, load_manifest

    if not isinstance(sha, str):
        return None
    for name in models.names():
        try:
            if load_manifest(models.packaged(name), check_graph=False).sha256 == sha:
                return models.packaged(name)
        except (ModelError, FileNotFoundError):
            continue
    return None


def nonfinite_runs(rec: Any) -> tuple[int, int | None]:
    """Samples of ``rec`` with a non-finite force (any sensor), and the t_us at which a run of them first outlasts
    what the daemon bridges (``NONFINITE_BRIDGE_S``: there it goes blind and fails safe), or None."""
    import numpy as np

    from slipd.daemon.loop import NONFINITE_BRIDGE_S

    force = np.asarray(rec.force)
    bad = ~np.isfinite(force.reshape(len(force), -1)).all(axis=1)
    bridge = max(1, round(NONFINITE_BRIDGE_S * rec.rate_hz))
    run = 0
    for k in np.flatnonzero(bad).tolist():
        run = run + 1 if k and bad[k - 1] else 1
        if run > bridge:
            return int(bad.sum()), int(rec.t_us[k])
    return int(bad.sum()), None


# ---------------------------------------------------------------------------------------------- models
def cmd_models(args: argparse.Namespace) -> int:
    """List the packaged models: name, sha256 of the graph, and the figures their manifest records."""
    from slipd import models
    from slipd.detect.manifest import ModelError, load_manifest

    status = EXIT_OK
    for name in models.names():
        try:
            m = load_manifest(models.packaged(name))
        except ModelError as exc:
            _err(f"{name}: {exc}")
            status = EXIT_MODEL
            continue
        scalars = {k: v for k, v in m.metrics.items() if isinstance(v, (int, float, str))}
        figures = ", ".join(f"{k} {v}" for k, v in sorted(scalars.items())) or "no figures recorded"
        print(f"{name}  sha256 {m.sha256[:16]}  {m.members} members, window {m.window}, stride {m.stride}, "
              f"threshold {m.threshold:g}  [{figures}]")
    return status


# ---------------------------------------------------------------------------------------------- sim
def cmd_sim(args: argparse.Namespace) -> int:
    """The closed-loop simulated rig (needs the ``sim`` extra)."""
    import importlib.util

    # Checked before anything runs: the rig imports matplotlib only to draw its plot, at the end.
    missing = [m for m in ("scipy", "matplotlib") if importlib.util.find_spec(m) is None]
    if missing:
        _err(f"slipd sim: install slipd[sim] (missing: {', '.join(missing)})")
        return EXIT_USAGE
    from slipd.config import ConfigError
    from slipd.sim.rig import DEFAULT_CONFIG, DEFAULT_SCENE, main_sim
    from slipd.sim.scene import SceneError

    for given, default, what in ((args.scene, DEFAULT_SCENE, "--scene"), (args.config, DEFAULT_CONFIG, "--config")):
        path = Path(given) if given else default
        if not path.is_file():
            _err(f"slipd sim: {what} {path}: file not found")
            return EXIT_USAGE
    if args.duration is not None and not args.duration > 0:
        _err(f"slipd sim: --duration {args.duration}: must be > 0 seconds")
        return EXIT_USAGE
    try:
        return main_sim(args)
    except ConfigError as exc:
        _err(exc)
        return EXIT_CONFIG
    except SceneError as exc:
        _err(f"slipd sim: {exc}")
        return EXIT_USAGE


def cmd_version(args: argparse.Namespace) -> int:
    """Print the version."""
    print(f"slipd {__version__}")
    return EXIT_OK


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slipd", description="Incipient-slip detection daemon for the PapillArray")
    sub = p.add_subparsers(dest="command", required=True)

    def add(name: str, handler: Callable[[argparse.Namespace], int], help_: str) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_)
        sp.set_defaults(handler=handler)
        return sp

    run = add("run", cmd_run, "run the daemon (sensor -> model -> arm/gripper)")
    run.add_argument("--config", "-c", required=True, help="YAML configuration file")

    chk = add("check-config", cmd_check_config, "validate a configuration file and its model; touches no hardware")
    chk.add_argument("config", help="YAML configuration file")

    rep = add("replay", cmd_replay, "run a recording through the daemon's decision path offline and print alarms")
    rep.add_argument("recording", nargs="?", default=None, help=".mcap or .npz recording, or Contactile SDK CSV log")
    rep.add_argument("--sample", action="store_true",
                     help="replay the packaged sample instead (a simulated lift that slips, 1.5 s)")
    rep.add_argument("--model", "-m", default=None,
                     help="packaged model name or manifest path (.json); default: the config's, else the packaged "
                          "model the recording names (its model_sha256), else the shipped one")
    rep.add_argument("--config", "-c", default=None, help="optional YAML config (decision settings)")
    rep.add_argument("--json", default=None, help="write the alarms and probabilities as JSON")

    conv = add("convert", cmd_convert, "convert a recording between .mcap, .npz and the Contactile SDK CSV")
    conv.add_argument("input", help="recording to read (.mcap, .npz or .csv)")
    conv.add_argument("output", help="recording to write; its ending picks the format (.mcap, .npz or .csv)")

    add("models", cmd_models, "list the packaged models (name, sha256, figures)")

    sim = add("sim", cmd_sim, "closed-loop simulated rig: physics + emulated devices + the daemon")
    sim.add_argument("--scene", default=None,
                     help="scene YAML (default: the packaged thermos_flask_undergrip; others in config/scenes/)")
    sim.add_argument("--config", "-c", default=None,
                     help="daemon config for the rig (default: the packaged sim.yaml; config/sim.yaml in a checkout)")
    sim.add_argument("--duration", type=float, default=None, help="seconds to run (default: the scene's)")
    sim.add_argument("--plot", default="out/sim.png", help="where to write the plot ('' for none)")
    sim.add_argument("--no-reaction", action="store_true", help="detect but do not react (control run)")
    sim.add_argument("--detector", choices=["onnx", "deceleration", "reference_pillar"], default=None,
                     help="override the config's model.detector (the ensemble or a published heuristic)")

    add("version", cmd_version, "print the version")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``slipd`` console script."""
    args = _parser().parse_args(argv)
    handler: Callable[[argparse.Namespace], int] = args.handler
    return int(handler(args) or 0)
