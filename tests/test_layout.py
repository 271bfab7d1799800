"""The repository's layout holds: the product (common/, services/) has no import cycles, never
imports the lab (training/), keeps its functions under 60 lines, and its wheel carries no
training code, lab history or weights."""

import ast
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "training")
MAX_FUNCTION_LINES = 60


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


def _imports(path: Path, known: dict) -> set[str]:
    """Project modules `path` imports, at the top or inside functions."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out.update(n for n in names if n in known)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = _modules()
    # a package's own __init__ importing its submodules is no cycle with them
    return {m: {t for t in _imports(p, mods) if t != m and not m.startswith(t + ".")}
            for m, p in mods.items()}


def test_no_import_cycles(graph):
    assert _cycles(graph) == []


def test_the_product_never_imports_the_lab(graph):
    bad = sorted((m, t) for m, ts in graph.items() if not m.startswith("training")
                 for t in ts if t.startswith("training"))
    assert bad == []


def test_no_product_function_is_over_60_lines():
    long = []
    for pkg in ("common", "services"):
        for path in (REPO / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > MAX_FUNCTION_LINES:
                        long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} {lines}")
    assert long == []


def test_the_wheel_holds_no_training_code_history_or_weights(tmp_path):
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps",
                          "-q", "-w", str(tmp_path)],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    if res.returncode != 0:
        pytest.skip(f"pip wheel could not build here: {res.stderr[-500:]}")
    (wheel,) = tmp_path.glob("roadmap-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert not [n for n in names if n.startswith("training/") or n.endswith((".pt", "HISTORY.md"))]
    assert "common/models/roadseg.onnx" in names and "services/bench/runner.py" in names
