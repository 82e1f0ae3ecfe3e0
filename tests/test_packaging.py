"""The package as installed: the daemon imports none of the extras, imports run downwards only
(design.md section 2, "the house"), no import cycles, and the packaged sample recording.

The wheel itself is built and installed into a fresh virtual environment by ``make wheel-test``
(which ``.ci/run`` runs after ``make test``).
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from slipd import models
from slipd.recording import Recording

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "slipd"
LAB = ROOT / "sliplab"
PYTHON = ROOT / ".venv" / "bin" / "python"
SLIPD = ROOT / ".venv" / "bin" / "slipd"

# What `pip install slipd` does not bring (the sim, train and dev extras) and the two parts of slipd
# that need them.
EXTRAS = ("torch", "scipy", "matplotlib", "tqdm", "onnx", "hypothesis", "pytest", "zenoh", "rosbags", "foxglove")
OFFLINE = ("slipd.sim", "sliplab")


def _python() -> str:
    return str(PYTHON) if PYTHON.exists() else sys.executable


def _slipd() -> list[str]:
    return [str(SLIPD)] if SLIPD.exists() else [_python(), "-m", "slipd"]


# ---------------------------------------------------------------------------------------------- lean daemon
def test_daemon_imports_none_of_the_extras(tmp_path):
    """Import the daemon's modules and run the subcommands an edge machine uses (their lazy imports
    included) in a fresh interpreter, then look at what ``sys.modules`` holds."""
    code = f"""
import json, sys
import slipd.cli, slipd.daemon.loop, slipd.daemon.service, slipd.detect.replay
from slipd.models import SAMPLE_RECORDING
assert slipd.cli.main(["check-config", {str(ROOT / "config" / "slipd.yaml")!r}]) == 0
assert slipd.cli.main(["replay", str(SAMPLE_RECORDING)]) == 0
assert slipd.cli.main(["models"]) == 0
print(json.dumps(sorted(sys.modules)))
"""
    r = subprocess.run([_python(), "-c", code], capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    loaded = json.loads(r.stdout.strip().splitlines()[-1])
    assert "onnxruntime" in loaded and "slipd.daemon.loop" in loaded  # the check sees real imports
    extra = [m for m in loaded if m.split(".")[0] in EXTRAS or m.startswith(tuple(p + "." for p in OFFLINE))
             or m in OFFLINE]
    assert extra == [], f"the daemon imported the extras' modules: {extra}"


def test_extras_are_not_runtime_dependencies():
    """The installed distribution's metadata: requirements without an ``extra ==`` marker are what
    ``pip install slipd`` brings."""
    reqs = metadata.requires("slipd") or []
    names = [re.split(r"[\s<>=!~;\[]", r, maxsplit=1)[0] for r in reqs if "extra ==" not in r]
    runtime = {n.lower().replace("_", "-") for n in names}
    extras = {"torch", "scipy", "matplotlib", "tqdm", "onnx", "eclipse-zenoh", "rosbags", "foxglove-sdk"}
    assert runtime.isdisjoint(extras), runtime
    assert {"numpy", "onnxruntime", "pyyaml", "pydantic"} <= runtime


# ---------------------------------------------------------------------------------------------- the house
GROUND = {"slipd", "slipd.metrics", "slipd.recording", "slipd.recording_mcap", "slipd.geometry", "slipd.models"}


def _wing(module: str) -> str:
    """The floor of the house a module sits on."""
    if module in GROUND:
        return "ground"
    if module in ("slipd.cli", "slipd.__main__"):
        return "cli"
    if module.split(".")[0] == "sliplab":
        return "lab"
    wing = module.split(".")[1]
    assert wing in ("config", "io", "detect", "daemon", "sim"), f"{module}: not in any wing of the house"
    return wing


# Which floors each floor may import (design.md section 2): imports run downwards only.
ALLOWED = {
    "ground": {"ground"},
    "config": {"ground", "config"},
    "io": {"ground", "config", "io"},
    "detect": {"ground", "config", "io", "detect"},
    "daemon": {"ground", "config", "io", "detect", "daemon"},
    "sim": {"ground", "config", "io", "detect", "daemon", "sim"},
    "cli": {"ground", "config", "io", "detect", "daemon", "sim", "cli"},
    "lab": {"ground", "config", "io", "detect", "daemon", "sim", "lab"},
}


def _modules() -> dict[str, Path]:
    out = {}
    for p in [*PKG.rglob("*.py"), *LAB.rglob("*.py")]:
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = p
    return out


def _in_type_checking(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def import_graph() -> dict[str, list[tuple[str, int, bool]]]:
    """module -> [(imported slipd module, line, runs at import time)] for every import in slipd/,
    at any depth (a function's lazy import is still a dependency of the module)."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, list[tuple[str, int, bool]]] = {}
    for mod, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        edges = []
        for node in ast.walk(tree):
            targets: list[str | None] = []
            if isinstance(node, ast.Import):
                targets = [resolve(a.name) for a in node.names if a.name.split(".")[0] in ("slipd", "sliplab")]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{base}" if base else pkg
                if base.split(".")[0] in ("slipd", "sliplab"):
                    targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else resolve(base) for a in node.names]
            # Executed when the module is imported: not inside a function, not under TYPE_CHECKING.
            at_import = not _in_type_checking(node, parents) and not any(
                isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef)) for p in _ancestors(node, parents))
            edges += [(t, node.lineno, at_import) for t in targets if t and t != mod]
        graph[mod] = edges
    return graph


def _ancestors(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> list[ast.AST]:
    out = []
    while node in parents:
        node = parents[node]
        out.append(node)
    return out


def test_the_graph_sees_the_imports_it_checks():
    graph = import_graph()
    assert ("slipd.detect.detector", True) in {(t, a) for t, _, a in graph["slipd.daemon.loop"]}
    assert "slipd.daemon.service" in {t for t, _, _ in graph["slipd.cli"]}  # a lazy import counts
    assert "slipd.io.pts" in {t for t, _, _ in graph["slipd.io.sensor"]}


def test_imports_run_downwards_only():
    graph = import_graph()
    upward = [
        f"{mod} ({_wing(mod)}) imports {target} ({_wing(target)}), line {line}"
        for mod, edges in sorted(graph.items())
        for target, line, _ in edges
        if _wing(target) not in ALLOWED[_wing(mod)]
    ]
    assert upward == [], "\n".join(upward)


def test_nothing_outside_the_lab_imports_it_and_the_runtime_never_imports_the_simulator():
    graph = import_graph()
    bad = [f"{mod} -> {t}:{line}" for mod, edges in graph.items() for t, line, _ in edges
           if (t.startswith("sliplab") and _wing(mod) != "lab")
           or (t.startswith("slipd.sim") and _wing(mod) in ("ground", "config", "io", "detect", "daemon"))]
    assert bad == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                scc = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    scc.append(top)
                    if top == node:
                        break
                if len(scc) > 1:
                    found.append(sorted(scc))
    return found


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    """Counting every import, lazy ones included: a cycle hidden in a function is still a knot in the
    design (``baselines`` <-> ``detector`` was one). A package's ``__init__`` re-exporting its own
    modules is not a cycle unless a module imports the package back."""
    graph = {mod: {t for t, _, _ in edges} for mod, edges in import_graph().items()}
    assert _cycles(graph) == []


# ---------------------------------------------------------------------------------------------- package data
def test_package_data_ships_every_model_file():
    """Everything in slipd/models/ that the daemon reads is matched by the package-data patterns,
    so the wheel carries what the repository runs from."""
    # pyproject.toml: "slipd.models" = ["*.onnx", ...] under [tool.setuptools.package-data]
    line = re.search(r'^"slipd\.models"\s*=\s*\[(.*)\]', (ROOT / "pyproject.toml").read_text(), re.M)
    assert line, "no package data for slipd.models"
    globs = re.findall(r'"([^"]+)"', line.group(1))
    files = [p for p in models.PACKAGE_DIR.iterdir() if p.is_file() and p.suffix != ".py"]
    assert files
    unshipped = [p.name for p in files if not any(p.match(g) for g in globs)]
    assert unshipped == []
    assert models.SAMPLE_RECORDING.parent == models.PACKAGE_DIR


def test_sample_recording_is_small_and_a_slip_trial():
    path = models.SAMPLE_RECORDING
    assert path.stat().st_size < 200_000
    rec = Recording.load(path)
    assert len(rec) == 1500 and rec.rate_hz == pytest.approx(1000.0)
    assert rec.meta["kind"] == "slip" and rec.onset_index() == 1038
    assert rec.events["gross_slip"] == pytest.approx(1.346)


def test_sample_recording_comes_from_its_command(tmp_path):
    """``make sample`` regenerates the shipped file; same arrays, same meta (the simulator is seeded)."""
    pytest.importorskip("scipy")
    from slipd.sim.scene import generate, load_scene, parse_scene

    sc = load_scene(ROOT / "config" / "scenes" / "hexapod_translation.yaml")
    sc = parse_scene({**sc.model_dump(mode="json"), "duration_s": 1.5}, "sample")
    fresh = Recording.load(generate(sc, seed=0).save(tmp_path / "sample.npz"))
    shipped = Recording.load(models.SAMPLE_RECORDING)
    # Bit-identical on the machine that wrote it; another CPU's SIMD exp/sin may differ in the last
    # ulp, so the floats get a tolerance far below the signal (forces of newtons, noise of 10 mN).
    assert np.array_equal(fresh.t_us, shipped.t_us)
    for name in ("force", "disp", "object_motion"):
        assert np.allclose(getattr(fresh, name), getattr(shipped, name), rtol=1e-4, atol=1e-4), name
    assert (fresh.slip != shipped.slip).mean() < 1e-3 and abs(int(fresh.label.sum()) - int(shipped.label.sum())) <= 3
    assert fresh.onset_index() == pytest.approx(shipped.onset_index(), abs=2)
    assert {k: v for k, v in fresh.meta.items() if k != "events"} == {
        k: v for k, v in shipped.meta.items() if k != "events"}
    assert fresh.events == pytest.approx(shipped.events, abs=2e-3)
    assert "sample_slip.npz" in (ROOT / "Makefile").read_text()


def test_replay_the_packaged_sample_through_the_cli():
    r = subprocess.run([*_slipd(), "replay", str(models.SAMPLE_RECORDING)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].endswith(": 1500 samples, 147 decisions, 1 alarm(s)"), r.stdout
    assert lines[1].startswith("  alarm at sample ") and "labelled onset at sample 1038" in r.stdout


def test_ci_runs_the_wheel_test():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert "make test" in ci and "make wheel-test" in ci
    assert "\nwheel-test:" in (ROOT / "Makefile").read_text()


def test_mx28_emulator_parts_keep_their_old_import_path():
    """The emulated MX-28 is split into its wire codec, control table and jaw model; every public name
    of the parts is still importable from ``slipd.sim.devices.mx28`` (the same object), and the codec
    and the jaw model stand alone (no slipd import: each is a leaf)."""
    pytest.importorskip("scipy")
    from slipd.sim.devices import dynamixel_protocol, jaw_model, mx28, mx28_control_table

    for part in (dynamixel_protocol, mx28_control_table, jaw_model):
        public = [n for n in vars(part) if not n.startswith("_") and getattr(vars(part)[n], "__module__",
                                                                            part.__name__) == part.__name__]
        assert public
        for name in public:
            if name in ("annotations", "dataclass", "deque", "math", "Iterable"):
                continue
            assert getattr(mx28, name) is getattr(part, name), name
            assert name in mx28.__all__, name
    graph = import_graph()
    for leaf in ("slipd.sim.devices.dynamixel_protocol", "slipd.sim.devices.jaw_model",
                 "slipd.sim.devices.mx28_control_table"):
        assert graph[leaf] == [], (leaf, graph[leaf])
    assert {t for t, _, _ in graph["slipd.sim.devices.mx28"]} == {
        "slipd.sim.devices.dynamixel_protocol", "slipd.sim.devices.jaw_model", "slipd.sim.devices.mx28_control_table"}
