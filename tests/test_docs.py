"""The documentation stays true to the tree: README size and layout table, links and anchors, the
generated configuration reference, the code named by the overview, the udev rule quoted by install.md."""

from __future__ import annotations

import ast
import importlib
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
PYTHON = ROOT / ".venv" / "bin" / "python"
PAGES = [README, *sorted(DOCS.glob("*.md"))]


def _python() -> str:
    return str(PYTHON) if PYTHON.exists() else sys.executable


def _table(text: str, header: str) -> list[list[str]]:
    """Rows of the Markdown table whose header line starts with ``header``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def test_readme_and_results_are_short_and_the_readme_has_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= 150
    assert len((DOCS / "results.md").read_text().splitlines()) <= 350
    assert "make sim" in text and "make test" in text
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    for target in set(re.findall(r"`make ([\w-]+)", text)):
        assert target in targets, f"README names `make {target}`, which the Makefile lacks"


def test_readme_layout_table_matches_the_tree():
    rows = _table(README.read_text(), "| path | what |")
    paths = [re.fullmatch(r"`([^`]+)`", row[0]).group(1) for row in rows]
    assert len(paths) >= 15
    missing = [p for p in paths if not (ROOT / p).exists() or (p.endswith("/") and not (ROOT / p).is_dir())]
    assert missing == [], f"README layout names paths that do not exist: {missing}"
    # ...and every package of slipd and every top-level folder that holds project files is in the table.
    packages = {f"{p.relative_to(ROOT).parent}/" for p in (ROOT / "slipd").glob("*/__init__.py")}
    assert packages <= set(paths), packages - set(paths)
    folders = {"config/", "deploy/", "docs/", "systemd/", "tools/", "tests/"}
    assert folders <= set(paths), folders - set(paths)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = page.read_text()
    heads = {_slug(h) for h in re.findall(r"^#{1,6} (.+)$", text, re.M)}
    return heads | set(re.findall(r'<a id="([^"]+)"></a>', text))


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_links_and_anchors_resolve(page):
    text = page.read_text()
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links or page.name == "configuration.md"
    broken = []
    for link in links:
        if re.match(r"^[a-z]+://", link):
            continue
        target, _, anchor = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        if not path.exists() or (anchor and path.suffix == ".md" and anchor not in _anchors(path)):
            broken.append(link)
    assert broken == [], f"{page.name}: broken links {broken}"


def test_configuration_reference_is_generated_and_current():
    """Regenerated in memory (``--check``) and compared with the committed file."""
    r = subprocess.run([_python(), "tools/config_reference.py", "--check", "docs/configuration.md"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"{r.stderr.strip()} (run `make config-reference`)"


def test_configuration_reference_check_catches_a_stale_file(tmp_path):
    stale = tmp_path / "configuration.md"
    shutil.copy(DOCS / "configuration.md", stale)
    stale.write_text(stale.read_text().replace("| `sensor.rate_hz` |", "| `sensor.rate` |"))
    r = subprocess.run([_python(), str(ROOT / "tools" / "config_reference.py"), "--check", str(stale)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "stale" in r.stderr


def test_configuration_reference_documents_every_field_and_exit_code():
    from slipd import cli
    from slipd.config import SlipdConfig

    text = (DOCS / "configuration.md").read_text()
    for section, info in SlipdConfig.model_fields.items():
        for key, field in info.annotation.model_fields.items():
            row = next((line for line in text.splitlines() if line.startswith(f"| `{section}.{key}` |")), None)
            assert row is not None, f"{section}.{key} missing from docs/configuration.md"
            assert " ".join(field.description.split())[:40].replace("|", "\\|") in row
    codes = _table(text, "| code | name |")
    documented = {int(row[0]): row[1].strip("`") for row in codes}
    defined = {getattr(cli, n): n for n in dir(cli) if n.startswith("EXIT_")}
    assert documented == defined


def _qualified_names(text: str) -> set[str]:
    """Dotted names starting with ``slipd.``, in prose, code spans and the diagram (not file paths)."""
    return set(re.findall(r"(?<![\w/.-])slipd(?:\.\w+)+", text))


def _resolve(name: str) -> object:
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)  # AttributeError: the page names something that is not there
        return obj
    raise ModuleNotFoundError(name)


def test_overview_names_real_code():
    text = (DOCS / "overview.md").read_text()
    names = _qualified_names(text)
    assert len(names) >= 25
    unresolved = []
    for name in sorted(names):
        try:
            _resolve(name)
        except (ImportError, AttributeError) as exc:
            unresolved.append(f"{name} ({exc})")
    assert unresolved == [], "docs/overview.md names code that does not exist:\n" + "\n".join(unresolved)
    # The frame's path, in the order the page follows it.
    path = ["slipd.io.sensor", "slipd.io.pts", "Daemon._on_frames", "Detector.push_many", "FeatureStream.push_views",
            "Ensemble.step", "Decision.advance", "Reaction.on_alarm", "DeviceWorker.submit", "URArm.stop",
            "DynamixelGripper.tighten"]
    positions = [text.index(p) for p in path]
    assert positions == sorted(positions)


def test_overview_short_method_names_exist():
    """``Daemon._on_block`` and the like: a class of that name in slipd/ defines that method."""
    methods: dict[str, set[str]] = {}
    for path in (ROOT / "slipd").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                methods.setdefault(node.name, set()).update(
                    n.name for n in node.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))
    text = (DOCS / "overview.md").read_text()
    named = set(re.findall(r"(?<![\w.])([A-Z]\w+)\.(_?[a-z]\w*)", text))
    assert len(named) >= 8
    missing = [f"{c}.{m}" for c, m in sorted(named) if m not in methods.get(c, set())]
    assert missing == [], missing


def test_overview_names_every_worker_thread():
    """Each ``DeviceWorker("name")`` the daemon creates is a thread ``slipd-name`` in the threads table."""
    names = set()
    for path in (ROOT / "slipd" / "daemon").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "DeviceWorker" and node.args
                    and isinstance(node.args[0], ast.Constant)):
                names.add(node.args[0].value)
    assert {"arm", "gripper", "recorder"} <= names
    rows = _table((DOCS / "overview.md").read_text(), "| thread | what runs on it |")
    threads = {row[0].strip("`") for row in rows}
    assert {f"slipd-{n}" for n in names} <= threads, threads


def test_install_page_quotes_the_udev_rule():
    rule = [line for line in (ROOT / "deploy" / "udev" / "99-slipd.rules").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    assert any("latency_timer" in line for line in rule) and any("SYMLINK+=" in line for line in rule)
    text = (DOCS / "install.md").read_text()
    for line in rule:
        assert line in text
    for needle in ("dialout", "/etc/slipd", "systemd/slipd.service", "/opt/slipd/bin/pip install"):
        assert needle in text


def test_no_work_log_references_in_the_tree():
    """Code, comments, config and docs describe the product as it is; the history is in git."""
    files = subprocess.run(["git", "ls-files", "-z", "*.py", "*.md", "*.yaml", "*.yml", "*.service", "Makefile"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split("\0")
    pattern = re.compile(r"session [0-9]|issue [0-9]|issue-[0-9]", re.I)
    hits = []
    for name in filter(None, files):
        path = ROOT / name
        if path.is_file() and not path.is_symlink():
            hits += [f"{name}:{n}" for n, line in enumerate(path.read_text().splitlines(), 1) if pattern.search(line)]
    assert hits == [], hits
