"""Model manifest: the JSON file beside an ONNX model that says exactly what the model expects.

``models/<name>.json`` sits beside ``models/<name>.onnx``. It records the file's sha256, the graph's
opset, IR version and I/O, the feature layout (a ``FeatureSpec`` dict plus its fields spelled out for
people), the ensemble's size, the decision threshold, where the weights and their training data came
from, and evaluation figures (``metrics``, filled in later by the evaluation tools).

``load_manifest`` is the daemon's gate: it validates the JSON (unknown keys rejected), checks that the
ONNX file exists and its hash matches, and that the graph's input/output names and shapes agree with
the manifest and with the feature spec. Any disagreement raises ``ModelError`` naming the file, the
field and the reason. Nothing here imports torch or onnx (only onnxruntime, a runtime dependency).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from slipd.detect.features import FeatureSpec

FORMAT_VERSION = 1
INPUT_NAMES = ("window", "h")
OUTPUT_NAMES = ("p_slip", "p_members", "h_next")
PILLAR_OUTPUT = "p_pillars"
"""Optional fourth output: P(slip) of each model pillar, [B, P] (the member mean of a per-pillar head)."""


def output_names(pillar_output: bool) -> tuple[str, ...]:
    """The graph's output names, in order, with or without ``PILLAR_OUTPUT``."""
    return (*OUTPUT_NAMES, PILLAR_OUTPUT) if pillar_output else OUTPUT_NAMES
BATCH_DIM = "B"
"""Symbolic name of the dynamic batch dimension in the graph and the manifest."""

Dim = int | str


class ModelError(Exception):
    """A model or its manifest is unusable. ``file``, ``field`` and ``reason`` say where and why."""

    def __init__(self, file: str | os.PathLike[str], field: str, reason: str) -> None:
        self.file = str(file)
        self.field = field
        self.reason = reason
        super().__init__(f"{self.file}: {field}: {reason}")


class TensorInfo(BaseModel):
    """Name, element type and shape of one graph input or output (symbolic dims as strings)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    dtype: Literal["float32"] = "float32"
    shape: list[Dim]


class Manifest(BaseModel):
    """Everything the daemon must know about a model before it feeds it a single window."""

    model_config = ConfigDict(extra="forbid")

    format_version: int = FORMAT_VERSION
    onnx_file: str = Field(description="ONNX file name, relative to the manifest's folder")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    opset: int = Field(ge=17)
    ir_version: int
    precision: Literal["fp32", "fp16", "int8"] = "fp32"
    inputs: list[TensorInfo]
    outputs: list[TensorInfo]
    sample_rate_hz: int
    window: int
    median: int
    stride: int
    pillars: list[int]
    channels: list[str]
    units: Literal["N"] = "N"
    members: int = Field(ge=1)
    hidden: int = Field(ge=1)
    threshold: float = Field(default=0.5, gt=0.0, lt=1.0)
    input_clip: float = Field(
        gt=0.0, description="the graph clips window values to +-input_clip (N) so no finite input can overflow"
    )
    feature_spec: dict[str, Any]
    source: Literal["reference-hexapod", "trained"]
    provenance: dict[str, Any] = Field(default_factory=dict)
    pillar_mapping: str
    metrics: dict[str, Any] = Field(default_factory=dict)

    @property
    def has_pillar_output(self) -> bool:
        """Whether the graph also gives each model pillar's P(slip) (``p_pillars``, a per-pillar head)."""
        return any(t.name == PILLAR_OUTPUT for t in self.outputs)

    @property
    def spec(self) -> FeatureSpec:
        """The feature layout as the ``FeatureSpec`` the feature code uses."""
        return FeatureSpec.from_dict(self.feature_spec)


def check_consistency(manifest: Manifest, path: str | os.PathLike[str]) -> None:
    """The manifest agrees with itself: format version, feature spec, its spelled-out copies, I/O shapes."""
    if manifest.format_version != FORMAT_VERSION:
        raise ModelError(path, "format_version", f"{manifest.format_version} is not supported (expected "
                         f"{FORMAT_VERSION})")
    try:
        spec = manifest.spec
    except (TypeError, ValueError) as exc:
        raise ModelError(path, "feature_spec", f"not a valid FeatureSpec: {exc}") from exc
    # The spelled-out fields are for people; they must say the same as the spec the code uses.
    pairs = {
        "sample_rate_hz": (manifest.sample_rate_hz, spec.rate_hz),
        "window": (manifest.window, spec.window),
        "median": (manifest.median, spec.median),
        "stride": (manifest.stride, spec.step),
        "pillars": (manifest.pillars, list(spec.pillars)),
        "channels": (manifest.channels, list(spec.channels)),
    }
    for key, (mine, theirs) in pairs.items():
        if mine != theirs:
            raise ModelError(path, key, f"{mine!r} disagrees with feature_spec ({theirs!r})")
    outputs = output_names(manifest.has_pillar_output)
    for kind, infos, names in (("inputs", manifest.inputs, INPUT_NAMES), ("outputs", manifest.outputs, outputs)):
        if [t.name for t in infos] != list(names):
            raise ModelError(path, kind, f"must be named {list(names)}, got {[t.name for t in infos]}")
    expected = expected_io(spec.input_size, manifest.members, manifest.hidden, len(spec.pillars))
    for kind, infos in (("inputs", manifest.inputs), ("outputs", manifest.outputs)):
        for t in infos:
            if t.shape != expected[t.name]:
                raise ModelError(
                    path, f"{kind}.{t.name}.shape",
                    f"{t.shape} does not fit the feature spec (T*C = {spec.input_size}), members and hidden size "
                    f"(expected {expected[t.name]})",
                )


def expected_io(input_size: int, members: int, hidden: int, pillars: int = 0) -> dict[str, list[Dim]]:
    """The graph's I/O shapes for a given input size, ensemble size Z, hidden size H (and P model pillars)."""
    return {
        PILLAR_OUTPUT: [BATCH_DIM, pillars],
        "window": [BATCH_DIM, input_size],
        "h": [members, BATCH_DIM, hidden],
        "p_slip": [BATCH_DIM],
        "p_members": [members, BATCH_DIM],
        "h_next": [members, BATCH_DIM, hidden],
    }


def io_infos(input_size: int, members: int, hidden: int, pillars: int = 0
             ) -> tuple[list[TensorInfo], list[TensorInfo]]:
    """``TensorInfo`` lists (inputs, outputs) for the manifest of a graph of this size (``pillars`` > 0: with
    the per-pillar output)."""
    shapes = expected_io(input_size, members, hidden, pillars)
    return (
        [TensorInfo(name=n, shape=shapes[n]) for n in INPUT_NAMES],
        [TensorInfo(name=n, shape=shapes[n]) for n in output_names(pillars > 0)],
    )


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old file or the new one, never a partial one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o644)  # mkstemp makes 0600; a model must be readable by the daemon's user
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def manifest_path_for(onnx_path: str | os.PathLike[str]) -> Path:
    """``models/x.onnx`` -> ``models/x.json``."""
    return Path(onnx_path).with_suffix(".json")


def write_manifest(manifest: Manifest, path: str | os.PathLike[str]) -> None:
    """Write the manifest as indented JSON, atomically."""
    text = json.dumps(manifest.model_dump(mode="json"), indent=2) + "\n"
    atomic_write_bytes(path, text.encode())


def read_manifest(path: str | os.PathLike[str]) -> Manifest:
    """Parse the manifest JSON and check it is consistent (no file or graph checks)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(path, "manifest", "file not found")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(path, "manifest", f"not readable JSON: {exc}") from exc
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "manifest"
        raise ModelError(path, field, err["msg"]) from exc
    check_consistency(manifest, path)
    return manifest


def update_metrics(path: str | os.PathLike[str], metrics: dict[str, Any]) -> Manifest:
    """Merge evaluation/benchmark figures into a manifest's ``metrics`` and rewrite it atomically.

    The ONNX file is not touched, so its hash stays valid. Values must be JSON-serialisable.
    """
    manifest = read_manifest(path)
    manifest.metrics.update(metrics)
    json.dumps(manifest.metrics)  # fail here, before writing, on a non-serialisable value
    write_manifest(manifest, path)
    return manifest


def onnx_path_of(manifest: Manifest, manifest_path: str | os.PathLike[str]) -> Path:
    """Where the manifest's ONNX file lives (relative names resolve against the manifest's folder)."""
    return Path(manifest_path).parent / manifest.onnx_file


def check_session_io(manifest: Manifest, session: Any, onnx_path: str | os.PathLike[str]) -> None:
    """Compare an onnxruntime session's I/O with the manifest; raise ``ModelError`` on any difference."""
    for kind, declared, actual in (
        ("inputs", manifest.inputs, session.get_inputs()),
        ("outputs", manifest.outputs, session.get_outputs()),
    ):
        names = [a.name for a in actual]
        if names != [t.name for t in declared]:
            raise ModelError(onnx_path, kind, f"graph has {names}, manifest declares {[t.name for t in declared]}")
        for t, a in zip(declared, actual):
            if a.type != "tensor(float)":
                raise ModelError(onnx_path, f"{kind}.{t.name}", f"graph element type {a.type}, expected float32")
            # Symbolic dims: onnxruntime reports their names (strings) or None; compare fixed dims exactly and
            # require a symbolic one where the manifest has one.
            shape = [d if isinstance(d, int) else BATCH_DIM for d in a.shape]
            if shape != t.shape:
                raise ModelError(onnx_path, f"{kind}.{t.name}", f"graph shape {a.shape}, manifest says {t.shape}")


def open_session(onnx_path: str | os.PathLike[str], options: Any = None) -> Any:
    """An onnxruntime CPU session; a file onnxruntime cannot parse raises ``ModelError``."""
    from slipd.detect.ort import onnxruntime as ort  # imported here so that manifest-only tools start fast

    try:
        return ort.InferenceSession(str(onnx_path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for corrupt graphs
        raise ModelError(onnx_path, "onnx", f"onnxruntime cannot load the graph: {exc}") from exc


def load_manifest(
    path: str | os.PathLike[str], expected_spec: FeatureSpec | None = None, check_graph: bool = True
) -> Manifest:
    """Validate a manifest and its model; return the manifest.

    Checks, each failing with ``ModelError(file, field, reason)``: the JSON is valid and consistent,
    ``expected_spec`` (the daemon's configured feature layout, if given) equals the manifest's, the
    ONNX file exists, its sha256 matches, and (``check_graph``) onnxruntime loads it and its I/O names,
    element types and shapes are those the manifest declares.
    """
    path = Path(path)
    manifest = read_manifest(path)
    if expected_spec is not None and manifest.spec != expected_spec:
        raise ModelError(
            path,
            "feature_spec",
            f"model expects {manifest.spec.to_dict()}, the configured feature pipeline produces "
            f"{expected_spec.to_dict()}",
        )
    onnx_path = onnx_path_of(manifest, path)
    if not onnx_path.is_file():
        raise ModelError(onnx_path, "onnx_file", "file not found")
    digest = sha256_file(onnx_path)
    if digest != manifest.sha256:
        raise ModelError(onnx_path, "sha256", f"file hash {digest} differs from the manifest's {manifest.sha256}")
    if check_graph:
        check_session_io(manifest, open_session(onnx_path), onnx_path)
    return manifest
