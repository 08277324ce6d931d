"""The house rules, checked on the source: imports run downhill and the runtime never needs torch.

- No import circles among the project's modules (``engine``, ``models``, ``export``, ``demos``, ``tools``),
  counting every import, at module level or inside a function; importing one's own ancestor package is not
  an edge (Python always runs it first).
- Nothing in ``engine/`` but the command-line entry point (``engine/cli.py``, which dispatches ``train`` and
  ``export``) imports ``torch``, ``models``, ``export``, ``demos`` or ``tools``, anywhere in the file; the one
  exception is the torch library (not the project's torch-side code) in ``engine.predict.torch_onnx``, the
  optional GPU runner of the exported graphs, which imports it inside functions only.
- Every ``engine`` module imports in a fresh interpreter in which importing torch fails.
"""
from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("engine", "models", "export", "demos", "tools")
UPHILL = ("torch", "models", "export", "demos", "tools")
#: engine modules allowed to import the torch library (inside functions: every engine module imports without it)
TORCH_RUNNERS = ("engine.predict.torch_onnx",)


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _imported_names(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Every dotted name ``path`` imports (absolute; ``from a import b`` gives ``a.b`` when that is a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            out.update(f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names)
    return out


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        edges = set()
        for target in _imported_names(name, path, modules):
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):
                edges.add(target)
        graph[name] = edges
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_circle_finder_finds_a_circle():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_has_no_circles():
    assert _circles(_graph()) == []


def test_the_runtime_imports_nothing_torch_side():
    modules = _modules()
    uphill = []
    for name, path in modules.items():
        if not name.startswith("engine") or name == "engine.cli":
            continue
        for target in _imported_names(name, path, modules):
            top = target.split(".")[0]
            if top in UPHILL and not (top == "torch" and name in TORCH_RUNNERS):
                uphill.append(f"{name} imports {target}")
    assert uphill == []


def test_every_engine_module_imports_without_torch():
    names = [name for name in _modules() if name.startswith("engine")]
    script = textwrap.dedent(f"""
        import importlib, importlib.abc, sys

        class NoTorch(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name == "torch" or name.startswith("torch."):
                    raise ImportError("torch is not installed here")
                return None

        sys.meta_path.insert(0, NoTorch())
        for name in {names!r}:
            importlib.import_module(name)
        assert "torch" not in sys.modules
        print(len({names!r}))
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert int(result.stdout.strip()) == len(names) > 40
