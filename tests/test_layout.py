"""The package map of docs/design.md: a lower part never imports a higher one, and no module
imports another that imports it back (lazy, function-level imports included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "facegeo"

#: Rank of each part of the package (docs/design.md, "Package layout"); a module may import
#: modules of its own rank or lower.
RANKS = {
    "frames": 0, "errors": 0, "checks": 0, "fsutil": 0, "__init__": 0,
    "geometry": 1,
    "capture": 2,
    "surface": 3,
    "appearance": 4,
    "lighting": 5,
    "render": 6,
    "synth": 7,
    "pipeline": 8,
    "cli": 9, "__main__": 9,
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(path: Path) -> set[str]:
    """Every ``facegeo…`` module a file imports, anywhere in the file (TYPE_CHECKING too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("facegeo")}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.startswith("facegeo"):
                found.add(node.module)
                # ``from facegeo.capture import scan`` imports the module facegeo.capture.scan
                for a in node.names:
                    if (PKG.parent / (node.module + "." + a.name).replace(".", "/")).with_suffix(
                        ".py"
                    ).exists():
                        found.add(node.module + "." + a.name)
    return found


def _graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for p in PKG.rglob("*.py")}


def test_every_part_has_a_rank():
    parts = {_part(m) for m in _graph()}
    assert parts <= set(RANKS), f"parts without a rank in the layout: {parts - set(RANKS)}"


def test_no_upward_imports():
    upward = []
    for module, deps in _graph().items():
        for dep in deps:
            if RANKS[_part(dep)] > RANKS[_part(module)]:
                upward.append(f"{module} imports {dep}")
    assert not upward, "imports of a higher part:\n" + "\n".join(sorted(upward))


def test_no_import_cycles_between_modules():
    graph = _graph()
    graph = {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}
    # A package's __init__ importing its own children is not a cycle worth flagging.
    for m in graph:
        graph[m] = {d for d in graph[m] if not d.startswith(m + ".")}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [m, d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("dep, module", [("facegeo.synth.skin", "facegeo.geometry.rig")])
def test_rank_check_can_fail(dep, module):
    """The check above would flag a geometry module importing the generator."""
    assert RANKS[_part(dep)] > RANKS[_part(module)]
