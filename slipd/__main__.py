"""Command line: ``slipd run | sim | replay | check-config | version`` (also ``python -m slipd``).

Each subcommand's work lives in its own module, imported only when that subcommand runs, so that
``slipd check-config`` stays fast and ``slipd run`` never imports torch or matplotlib.

Exit codes (documented in README.md):
    0 success; 1 runtime failure; 2 usage error; 3 invalid configuration; 4 invalid model;
    5 device failure at start-up.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from slipd import __version__

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, EXIT_CONFIG, EXIT_MODEL, EXIT_DEVICE = 0, 1, 2, 3, 4, 5


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slipd", description="Incipient-slip detection daemon for the PapillArray")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run the daemon (sensor -> model -> arm/gripper)")
    run.add_argument("--config", "-c", required=True, help="YAML configuration file")
    run.set_defaults(handler="slipd.control:main_run")

    chk = sub.add_parser("check-config", help="validate a configuration file and its model; touches no hardware")
    chk.add_argument("config", help="YAML configuration file")
    chk.set_defaults(handler="slipd.config:main_check")

    rep = sub.add_parser("replay", help="run a recording through the daemon's loop offline and print alarms")
    rep.add_argument("recording", help=".npz recording or Contactile SDK CSV log")
    rep.add_argument("--model", "-m", default=None, help="model manifest (.json); default: the shipped model")
    rep.add_argument("--config", "-c", default=None, help="optional YAML config (decision settings)")
    rep.add_argument("--json", default=None, help="write the alarms and probabilities as JSON")
    rep.set_defaults(handler="slipd.replay:main_replay")

    sim = sub.add_parser("sim", help="closed-loop simulated rig: physics + emulated devices + the daemon")
    sim.add_argument("--scene", default=None, help="scene YAML (default: config/scenes/default.yaml)")
    sim.add_argument("--config", "-c", default=None, help="daemon config for the rig (default: config/sim.yaml)")
    sim.add_argument("--duration", type=float, default=None, help="seconds to run (default: the scene's)")
    sim.add_argument("--plot", default="out/sim.png", help="where to write the plot ('' for none)")
    sim.add_argument("--no-reaction", action="store_true", help="detect but do not react (control run)")
    sim.add_argument("--detector", choices=["onnx", "deceleration", "reference_pillar"], default=None,
                     help="override the config's model.detector (the ensemble or a published heuristic)")
    sim.set_defaults(handler="slipd.sim.rig:main_sim")

    ver = sub.add_parser("version", help="print the version")
    ver.set_defaults(handler=None)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``slipd`` console script."""
    args = _parser().parse_args(argv)
    if args.handler is None:
        print(f"slipd {__version__}")
        return EXIT_OK
    module_name, func_name = args.handler.split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    return int(func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
