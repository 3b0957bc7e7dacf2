"""The layers read at a glance: model <- workers <- service <- bench <- cli, no import cycle between
modules (imports inside functions and type-only ones under `if TYPE_CHECKING:` count: a cycle
hidden there is still one for a reader), and the API process loads no training stack (PyTorch, Ray,
PyAV), checked in a fresh interpreter."""

import ast
import json
import subprocess
import sys
from pathlib import Path

from tests.helpers import ROOT

LAYERS = ["model", "workers", "service", "bench", "cli"]  # each may import only the ones before it


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for layer in LAYERS for p in (ROOT / layer).rglob("*.py")}


def imports_of(name: str) -> set[str]:
    """Our modules `name` imports anywhere in its file, type-only imports included (a package's own
    __init__ counts when it is the target, not as every submodule's parent)."""
    path, found = MODULES[name], set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: imports_of(name) for name in MODULES}


def cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in GRAPH[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(GRAPH)))
    for v in sorted(GRAPH):
        if v not in index:
            connect(v)
    return out


def test_the_graph_sees_the_imports_it_must():
    assert "service.jobs.attempt" in GRAPH["service.dispatcher"]
    assert "workers.render.job" in GRAPH["service.jobs.render"]
    # an import inside a function counts too, and so does a type-only one
    assert "service.jobs.parent" in GRAPH["service.view_worker"]
    assert "model.methods.base" in GRAPH["model.methods.spec"]
    assert "bench.cli" in GRAPH["cli.main"]


def test_no_module_imports_itself_back():
    assert cycles() == []


def test_each_layer_imports_only_the_layers_below_it():
    upward = sorted(
        (name, target)
        for name, targets in GRAPH.items()
        for target in targets
        if LAYERS.index(target.split(".")[0]) > LAYERS.index(name.split(".")[0])
    )
    assert upward == []


def test_the_api_app_loads_no_training_stack(tmp_path):
    from service.db import upgrade
    from service.settings import Settings

    upgrade(Settings(data_dir=tmp_path).db_url)
    script = f"""
import json, resource, sys, time
started = time.perf_counter()
from service.api.app import create_app
from service.settings import Settings
create_app(Settings(data_dir={str(tmp_path)!r}))
seconds = time.perf_counter() - started
heavy = sorted(m for m in ("torch", "ray", "av", "numpy", "PIL", "matplotlib") if m in sys.modules)
print(json.dumps({{"heavy": heavy, "seconds": seconds,
                   "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}}))
"""
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["heavy"] == [], report
