"""Write docs/configuration.md from the config schema: every section, key, type, default, bound and
description comes from the pydantic models in ``slipd.config.schema``; the exit codes from ``slipd.cli``.

    python tools/config_reference.py --out docs/configuration.md     (make config-reference)
    python tools/config_reference.py --check docs/configuration.md   (exit 1 when the file is stale)

tests/test_docs.py regenerates the text in memory and fails when the committed file differs, so a
field added to the schema without running this is caught in CI.
"""

from __future__ import annotations

import argparse
import sys
import types
import typing
from pathlib import Path
from typing import Any

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from slipd import cli
from slipd.config import schema
from slipd.config.load import MAX_YAML_DEPTH, MAX_YAML_NODES

# The meaning of each exit code. The numbers are read from slipd.cli; a new EXIT_* constant without a
# line here fails the generator (and so the docs test).
EXIT_MEANINGS = {
    "EXIT_OK": ("success", "`check-config`: the config and its model are valid; `run`: stopped by SIGTERM, "
                "SIGINT or another stop signal (SIGQUIT, SIGUSR1, SIGUSR2, ...)"),
    "EXIT_RUNTIME": ("runtime failure", "the loop failed after start-up; `replay`: an unreadable recording "
                                        "(one line naming the file and the part at fault)"),
    "EXIT_USAGE": ("usage error", "bad command line; `slipd sim` without the `sim` extra"),
    "EXIT_CONFIG": ("invalid configuration", "one line per problem: `file:line: key.path: reason`; also a config "
                                             "refused as input (alias bomb, nesting, size), and `ros2` or `viz` "
                                             "enabled without its extra installed (`check-config` and `run`, before "
                                             "any device is opened)"),
    "EXIT_MODEL": ("invalid model", "manifest missing or inconsistent with its ONNX file (sha256, opset, shapes, "
                                    "feature layout)"),
    "EXIT_DEVICE": ("device failure at start-up", "a sensor or servo port missing or not openable, the arm's "
                                                  "controller not answering; one line, nothing opened"),
    "EXIT_RESOURCE": ("resource unavailable at start-up", "`run`: the metrics port (`metrics.host`:`metrics.port`) "
                      "cannot be bound, e.g. in use by another process; one line, before any device is opened"),
}
UNIT = Path(__file__).resolve().parents[1] / "systemd" / "slipd.service"


def _no_restart() -> set[int]:
    """The exit codes the systemd unit does not restart on (``RestartPreventExitStatus=``)."""
    codes: set[int] = set()
    for line in UNIT.read_text().splitlines():
        if line.startswith("RestartPreventExitStatus="):
            codes |= {int(c) for c in line.split("=", 1)[1].split() if c.isdigit()}
    return codes


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " | ".join(f"`{a}`" if isinstance(a, str) else f"`{a!r}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args)
    if origin in (list, tuple):
        inner = ", ".join(_type_name(a) for a in args if a is not Ellipsis)
        return f"list of {inner}" if inner else "list"
    if annotation is type(None):
        return "null"
    if isinstance(annotation, type):
        return {"str": "string", "int": "integer", "float": "number", "bool": "boolean", "Path": "path"}.get(
            annotation.__name__, annotation.__name__)
    return str(annotation).replace("typing.", "")


def _bounds(info: FieldInfo) -> str:
    out = []
    symbols = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<", "min_length": "length >=", "max_length": "length <="}
    for meta in info.metadata:
        for attr, sym in symbols.items():
            value = getattr(meta, attr, None)
            if value is not None and isinstance(meta, (annotated_types.BaseMetadata,)):
                out.append(f"{sym} {value}")
    return ", ".join(out)


def _default(info: FieldInfo) -> str:
    if info.is_required():
        return "**required**"
    if info.default_factory is not None:
        value = info.default_factory()  # type: ignore[call-arg]
    else:
        value = info.default
    if value is PydanticUndefined:
        return "**required**"
    if value is None:
        return "`null`"
    if isinstance(value, BaseModel):
        return "(section defaults)"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(str(v) for v in value) + "]`"
    return f"`{value}`"


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _section(name: str, info: FieldInfo) -> list[str]:
    model = info.annotation
    assert isinstance(model, type) and issubclass(model, BaseModel)
    req = "required section" if info.is_required() else "optional section"
    lines = [f"## `{name}`: {_cell(info.description or '')}", ""]
    doc = " ".join((model.__doc__ or "").split())
    if doc:
        lines += [f"{doc} ({req}, `{model.__name__}`)", ""]
    lines += ["| key | type | default | bounds | description |", "|---|---|---|---|---|"]
    for key, field in model.model_fields.items():
        if not field.description:
            raise SystemExit(f"{model.__name__}.{key}: no description (every config field needs one)")
        lines.append(f"| `{name}.{key}` | {_cell(_type_name(field.annotation))} | {_cell(_default(field))} | "
                     f"{_cell(_bounds(field))} | {_cell(field.description)} |")
    return [*lines, ""]


def _exit_codes() -> list[str]:
    codes = {n: getattr(cli, n) for n in dir(cli) if n.startswith("EXIT_") and isinstance(getattr(cli, n), int)}
    missing = sorted(set(codes) - set(EXIT_MEANINGS))
    if missing:
        raise SystemExit(f"slipd.cli defines {missing} without a meaning in tools/config_reference.py")
    lines = ["## Exit codes", "",
             "Every subcommand returns one of these (`slipd.cli`). The unit (`systemd/slipd.service`) does not "
             "restart on the ones marked *no restart* (its `RestartPreventExitStatus=`): they do not heal by "
             "trying again.", "",
             "| code | name | meaning | details |", "|---|---|---|---|"]
    no_restart = _no_restart()
    for name, code in sorted(codes.items(), key=lambda kv: kv[1]):
        meaning, details = EXIT_MEANINGS[name]
        flag = " (*no restart*)" if code in no_restart else ""
        lines.append(f"| {code} | `{name}` | {meaning}{flag} | {_cell(details)} |")
    return [*lines, ""]


def render() -> str:
    """The whole reference as Markdown (deterministic: the same schema gives the same bytes)."""
    out = [
        "# Configuration reference",
        "",
        "<!-- GENERATED by tools/config_reference.py from slipd/config/schema.py and slipd/cli.py: "
        "do not edit; run `make config-reference`. tests/test_docs.py fails when this file is stale. -->",
        "",
        "One YAML file (`/etc/slipd/slipd.yaml` on a robot; `config/slipd.yaml` in the repository is the "
        "annotated example, `config/sim.yaml` the simulated rig's). `slipd check-config FILE` validates it and "
        "its model without touching hardware. Every section rejects unknown keys (with a suggestion for a "
        "misspelt one) and every error names the file, the line, the key path and the reason:",
        "",
        "```",
        "/etc/slipd/slipd.yaml:42: gripper.secure_pwm: Input should be less than or equal to 885 (got 900)",
        "```",
        "",
        "Relative paths resolve against the config file's folder; `~` and `$VARS` are expanded (an unset "
        "variable is an error). `model.manifest` may name a packaged model by its bare name "
        "(`slip_ensemble_int8`; `slipd models` lists them) or a manifest by path.",
        "",
        f"**Bounded input.** A file over {schema.MAX_CONFIG_BYTES} bytes, one that expands to more than "
        f"{MAX_YAML_NODES} values once its YAML aliases are expanded (an alias bomb), one nested deeper than "
        f"{MAX_YAML_DEPTH} levels, or an alias that refers to its own anchor is refused with exit code 3 and "
        "the line where it happens; duplicate keys are errors.",
        "",
        "Sections: " + ", ".join(f"[`{n}`](#{n})" for n in schema.SlipdConfig.model_fields) + ".",
        "",
    ]
    for name, info in schema.SlipdConfig.model_fields.items():
        out += [f'<a id="{name}"></a>', "", *_section(name, info)]
    out += _exit_codes()
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write (``--out``) or check (``--check``) the reference."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", type=Path, help="write the reference here")
    g.add_argument("--check", type=Path, help="exit 1 when this file differs from the generated text")
    args = p.parse_args(argv)
    text = render()
    if args.check is not None:
        current = args.check.read_text() if args.check.exists() else ""
        if current != text:
            print(f"{args.check}: stale; run `make config-reference`", file=sys.stderr)
            return 1
        print(f"{args.check}: up to date")
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
