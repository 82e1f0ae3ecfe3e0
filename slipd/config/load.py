"""Reading the YAML config: bounded input, line numbers in every error, validation by the schema.

``load_config`` raises ``ConfigError`` whose message has one line per problem, each naming the file, the
line where the YAML has one, the key path and the reason::

    /etc/slipd/slipd.yaml:42: gripper.secure_pwm: Input should be less than or equal to 885 (got 900)
"""

from __future__ import annotations

import difflib
import os
import re
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from slipd.config.schema import (
    _REPR,
    MAX_CONFIG_BYTES,
    ConfigError,
    FieldProblem,
    SlipdConfig,
    _SectionProblem,
)

# ---------------------------------------------------------------------------------------------- loading
MAX_YAML_NODES = 20_000
"""Most values (scalars, lists, mappings, keys) a config may expand to, aliases counted at full size.

The shipped config has about 120. An alias is a shared reference: cheap to parse, but everything
after parsing (line numbers, validation, error messages) walks it once per use, so ten lines of
nested aliases (a "billion laughs") would make ``check-config`` run for minutes in gigabytes.
"""

MAX_YAML_DEPTH = 32
"""Deepest nesting of lists and mappings; the schema needs 3, the composer recurses per level."""


class _Refused(yaml.MarkedYAMLError):
    """Input that is valid YAML but refused as a config (too large once expanded, too deep, recursive)."""

    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(None, None, problem, mark)


class _Loader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys (YAML would silently keep the last one) and bounds the
    document while it is composed: expanded size (aliases at the size of what they point to), depth,
    and self-referencing anchors. The bounds are checked before anything walks the tree."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._expanded = 0  # values so far in the document with every alias expanded
        self._sizes: dict[int, int] = {}  # id(node) -> its expanded size, for the aliases that reuse it
        self._open: list[int] = [0]  # expanded size accumulated by each node being composed
        self._open_anchors: set[str] = set()

    def _count(self, size: int, mark: Any, what: str) -> None:
        self._expanded += size
        self._open[-1] += size
        if self._expanded > MAX_YAML_NODES:
            raise _Refused(f"{what} makes the document expand to more than {MAX_YAML_NODES} values "
                           f"(nested aliases: a YAML alias bomb?)", mark)

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        event: Any = self.peek_event()  # type: ignore[no-untyped-call]
        if isinstance(event, yaml.AliasEvent):
            if event.anchor in self._open_anchors:
                raise _Refused(f"alias *{event.anchor} refers to its own anchor (a recursive value)",
                               event.start_mark)
            node = super().compose_node(parent, index)  # raises on an undefined alias
            self._count(self._sizes.get(id(node), 1), event.start_mark, f"alias *{event.anchor}")
            return node
        if len(self._open) > MAX_YAML_DEPTH:
            raise _Refused(f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)
        anchor = getattr(event, "anchor", None)
        if anchor is not None:
            self._open_anchors.add(anchor)
        self._open.append(0)
        try:
            node = super().compose_node(parent, index)
        finally:
            inner = self._open.pop()
            if anchor is not None:
                self._open_anchors.discard(anchor)
        self._sizes[id(node)] = 1 + inner
        self._open[-1] += 1 + inner
        self._expanded += 1
        if self._expanded > MAX_YAML_NODES:
            raise _Refused(f"more than {MAX_YAML_NODES} values in one config", event.start_mark)
        return node


def _construct_mapping(loader: _Loader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: dict[Any, yaml.Node] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark, f"found duplicate key {key!r}", key_node.start_mark
                )
            seen[key] = key_node
        except TypeError:
            pass  # unhashable key: construct_mapping below reports it with its position
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)

# YAML 1.2's core schema for plain scalars instead of PyYAML's YAML 1.1: 1.1 reads ``0100`` as octal (64),
# ``1:30`` as sexagesimal (90) and ``yes`` / ``no`` / ``on`` / ``off`` as booleans, none of which an engineer who writes
# a position, a timeout or a force means. Here ``0100`` is 100, ``1:30`` a string (refused where a number is due), and
# only true / false are booleans (a boolean key still takes yes / no: the schema reads those strings).
_INT_TAG, _FLOAT_TAG, _BOOL_TAG = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float", "tag:yaml.org,2002:bool")
_Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in (_INT_TAG, _FLOAT_TAG, _BOOL_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(_BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
_Loader.add_implicit_resolver(_INT_TAG, re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
_Loader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))


def _construct_int(loader: _Loader, node: yaml.ScalarNode) -> int:
    return int(loader.construct_scalar(node), 10)  # decimal, leading zeros and all (1.1's would read octal)


_Loader.add_constructor(_INT_TAG, _construct_int)


def _key_lines(node: yaml.Node | None, prefix: tuple[Any, ...] = ()) -> dict[tuple[Any, ...], int]:
    """Map key paths to 1-based line numbers, so validation errors can point into the file."""
    lines: dict[tuple[Any, ...], int] = {}
    if isinstance(node, yaml.MappingNode):
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode):
                path = (*prefix, k.value)
                lines[path] = k.start_mark.line + 1
                lines.update(_key_lines(v, path))
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            path = (*prefix, i)
            lines[path] = v.start_mark.line + 1
            lines.update(_key_lines(v, path))
    return lines


def _allowed_keys(loc: tuple[Any, ...]) -> list[str] | None:
    """Field names of the section that ``loc`` (ending at an unknown key) sits in."""
    model: Any = SlipdConfig
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        if field is None or not (isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)):
            return None
        model = field.annotation
    return list(model.model_fields)


def _fmt_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int) and not isinstance(part, bool):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _short(value: Any) -> str:
    return _REPR.repr(value)


def _problems(exc: ValidationError, source: str, lines: Mapping[tuple[Any, ...], int]) -> list[str]:
    """One line per pydantic error: ``file:line: key.path: reason (got value)``."""
    out = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        reason = err["msg"]
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, _SectionProblem):
            loc, reason = cause.loc, cause.reason
        elif isinstance(cause, FieldProblem):
            loc, reason = (*loc, cause.field), cause.reason
        elif err["type"] == "extra_forbidden":
            allowed = _allowed_keys(loc)
            reason = "unknown key"
            if allowed:
                close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
                reason += f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(allowed)})"
        elif err["type"] == "missing":
            reason = "required key is missing"
        elif err["type"] == "value_error" and reason.startswith("Value error, "):
            reason = reason[len("Value error, ") :]
        if err["type"] not in ("missing", "extra_forbidden") and not isinstance(cause, FieldProblem):
            reason += f" (got {_short(err.get('input'))})"
        line = None
        for n in range(len(loc), 0, -1):  # the deepest key of the path that the file has
            if loc[:n] in lines:
                line = lines[loc[:n]]
                break
        where = f"{source}:{line}" if line else source
        out.append(f"{where}: {_fmt_loc(loc)}: {reason}")
    return out


def parse_config(
    text: str, source: str = "<config>", base_dir: str | os.PathLike[str] | None = None
) -> SlipdConfig:
    """Validate YAML text; ``source`` names it in errors, ``base_dir`` anchors relative paths."""
    try:
        loader = _Loader(text)
        try:
            node = loader.get_single_node()
            data = loader.construct_document(node) if node is not None else None
        except ValueError as exc:
            # PyYAML raises chr()'s ValueError for an escape beyond U+10FFFF ("\U00110000"), not a YAMLError.
            at = loader.get_mark()
            raise ConfigError([f"{source}:{at.line + 1}:{at.column + 1}: YAML syntax error: {exc}"]) from None
        finally:
            loader.dispose()
    except _Refused as exc:
        mark = exc.problem_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        raise ConfigError([f"{where}: refused: {exc.problem}"]) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        problem = " ".join(str(p) for p in (exc.context, exc.problem) if p)
        raise ConfigError([f"{where}: YAML syntax error: {problem}"]) from None
    except yaml.YAMLError as exc:  # reader errors (control characters) carry a position, not a mark
        raise ConfigError([f"{source}: YAML error: {exc}".replace("\n", " ")]) from None
    except RecursionError:
        raise ConfigError([f"{source}: YAML nested too deeply"]) from None
    if data is None:
        raise ConfigError([f"{source}: the file is empty; expected a mapping with sensor, model, gripper, arm, ..."])
    if not isinstance(data, dict):
        raise ConfigError([f"{source}: top level must be a mapping of sections, got {type(data).__name__}"])
    return _validate(data, source, base_dir, _key_lines(node))


def _validate(
    data: Mapping[str, Any],
    source: str,
    base_dir: str | os.PathLike[str] | None,
    lines: Mapping[tuple[Any, ...], int] | None = None,
) -> SlipdConfig:
    try:
        return SlipdConfig.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise ConfigError(_problems(exc, source, lines or {})) from None
    except RecursionError:
        raise ConfigError([f"{source}: values nested too deeply"]) from None


def config_from_dict(
    data: Mapping[str, Any], source: str = "<dict>", base_dir: str | os.PathLike[str] | None = None
) -> SlipdConfig:
    """Validate an already-parsed mapping (tests, the simulated rig)."""
    return _validate(data, source, base_dir)


def load_config(path: str | os.PathLike[str]) -> SlipdConfig:
    """Read and validate a YAML config file; raise ``ConfigError`` naming the file, key path and reason."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError([f"{path}: {size} bytes is too large for a config file (limit {MAX_CONFIG_BYTES})"])
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError([f"{path}: cannot read ({exc.strerror or exc})"]) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{path}: not UTF-8 text (byte {exc.start})"]) from None
    return parse_config(text, str(path), path.resolve().parent)


def override(cfg: SlipdConfig, updates: Mapping[str, Any]) -> SlipdConfig:
    """A copy of ``cfg`` with dotted keys replaced (``{"sensor.port": "/dev/pts/3"}``), validated again.

    Paths in ``cfg`` are already absolute; a relative path in ``updates`` resolves against the
    current directory.
    """
    data = cfg.model_dump()
    for dotted, value in updates.items():
        parts = dotted.split(".")
        node = data
        for part in parts[:-1]:
            if not isinstance(node.get(part), dict):
                raise ConfigError([f"<override>: {dotted}: no such section {part!r}"])
            node = node[part]
        node[parts[-1]] = value
    return _validate(data, "<override>", Path.cwd())


# ---------------------------------------------------------------------------------------------- check-config
def summary(cfg: SlipdConfig, manifest: Any = None) -> str:
    """One line saying what this config will drive."""
    thr = cfg.decision.threshold
    if thr is None and manifest is not None:
        thr = manifest.threshold
    parts = [
        f"sensor {cfg.sensor.port} @ {cfg.sensor.rate_hz} Hz (tare {cfg.sensor.tare})",
        f"model {cfg.model.manifest.name}" + (f" ({manifest.sha256[:12]})" if manifest is not None else ""),
        f"threshold {thr:.3g}" if thr is not None else "threshold from manifest",
        f"actions {'+'.join(cfg.reaction.actions) or 'none'}" + (" graded" if cfg.reaction.graded else ""),
    ]
    g = cfg.gripper
    parts.append(f"gripper id {g.id} p{g.protocol:g} on {g.port}" if g.enabled else "gripper off")
    parts.append(f"arm {cfg.arm.host} ({cfg.arm.stop_method})" if cfg.arm.enabled else "arm off")
    parts.append(f"metrics {cfg.metrics.host}:{cfg.metrics.port}" if cfg.metrics.enabled else "metrics off")
    parts.append(f"recorder {cfg.recorder.directory}" if cfg.recorder.enabled else "recorder off")
    return "; ".join(parts)


def check_against_manifest(cfg: SlipdConfig, manifest: Any, source: str) -> list[str]:
    """Problems between the config and a loaded model manifest (rate, stride, threshold)."""
    problems = []
    if cfg.sensor.rate_hz != manifest.sample_rate_hz:
        problems.append(
            f"{source}: sensor.rate_hz: {cfg.sensor.rate_hz} Hz, but the model was trained at "
            f"{manifest.sample_rate_hz} Hz"
        )
    stride = cfg.model.stride
    if stride and (stride > manifest.window or manifest.window % stride):
        problems.append(f"{source}: model.stride: must divide the model's window ({manifest.window}), got {stride}")
    thr = cfg.decision.effective_threshold(manifest.threshold)
    if thr - cfg.decision.hysteresis <= 0:
        problems.append(
            f"{source}: decision.hysteresis: must be smaller than the threshold ({thr}), got {cfg.decision.hysteresis}"
        )
    return problems


def permission_warnings(path: str | os.PathLike[str]) -> list[str]:
    """Warnings about who may change the config (it decides what the robot does)."""
    mode = Path(path).stat().st_mode
    warnings = []
    if mode & stat.S_IWOTH:
        warnings.append(f"warning: {path} is world-writable; anyone on this machine can change what the robot does "
                        f"(chmod o-w)")
    return warnings
