"""The layers stay visible: the core has no import cycle and no imports hidden in functions, and the
layers above it (envs, training, benchmarks, notebooks) use public names only."""

from __future__ import annotations

import ast
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "jaxlimits"


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


# _xla_flags must run before jax is first imported (it sets XLA_FLAGS), so its one jax import is deferred
DEFERRED_IMPORTS_ALLOWED = {"jaxlimits._xla_flags"}


def _core_modules():
    return {_module_name(p): p for p in CORE.rglob("*.py")}


def test_core_has_no_function_level_imports_and_no_cycle():
    modules = _core_modules()
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and name not in DEFERRED_IMPORTS_ALLOWED:
                inner = [n for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom))]
                assert not inner, f"{name}.{node.name} imports inside a function (line {inner[0].lineno})"
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxlimits"):
                deps.add(node.module)
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("jaxlimits")}
        graph[name] = {d for d in deps if d in modules and d != name}
    state = {}

    def visit(node, stack):
        state[node] = "open"
        for dep in graph[node]:
            if state.get(dep) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack + [node, dep]))
            if dep not in state:
                visit(dep, stack + [node])
        state[node] = "done"

    for node in graph:
        if node not in state:
            visit(node, [])
    assert len(graph) > 20  # the walk saw the core


def _sources_above_the_core():
    for folder in ("envs", "training", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            yield path, path.read_text().splitlines()
    for path in (ROOT / "notebooks").glob("*.ipynb"):
        cells = json.loads(path.read_text())["cells"]
        yield path, [line for c in cells if c["cell_type"] == "code" for line in "".join(c["source"]).splitlines()]


def test_layers_above_the_core_use_public_names():
    seen = 0
    for path, lines in _sources_above_the_core():
        seen += 1
        for i, line in enumerate(lines, 1):
            code = line.split("#")[0]
            assert "jaxlimits._src" not in code, f"{path.relative_to(ROOT)}:{i} imports jaxlimits._src: {line.strip()}"
            if "mujoco.mjx._src" in code:
                assert "#" in line, (
                    f"{path.relative_to(ROOT)}:{i}: mjx._src without a comment saying why: {line.strip()}"
                )
    assert seen > 20
