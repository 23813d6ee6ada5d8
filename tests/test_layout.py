"""The package map of docs/design.md: a lower part never imports a higher one, no module
imports another that imports it back (lazy, function-level imports included), and the stages
never read the truth: the generator's and the references' comparisons are facegeo.evaluate's."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "facegeo"

#: Rank of each part of the package (docs/design.md, "Package layout"); a module may import
#: modules of its own rank or lower.
RANKS = {
    "frames": 0, "errors": 0, "checks": 0, "fsutil": 0, "rss": 0, "__init__": 0,
    "geometry": 1,
    "capture": 2,
    "surface": 3,
    "appearance": 4,
    "lighting": 5,
    "render": 6,
    "synth": 7,
    "pipeline": 8,
    # beside the pipeline: the reconstruct run registers it as its last stage, and it reads
    # what the stages wrote (their product files, their rig choices)
    "evaluate": 8,
    # the benchmarks: they run stages and may use the generator and the evaluation
    "bench": 9,
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


# ---------------------------------------------------------------- stages never read the truth

#: The parts whose every module is stage code (DESIGN §2: "Stages make products and never read
#: the truth").
STAGE_PARTS = ("geometry", "surface", "appearance", "lighting", "render")
#: Modules of ``pipeline/`` that are not stages: the cache and the run, the report (the
#: benchmarks are a part of their own, facegeo.bench).
NOT_STAGES = {"facegeo.pipeline", "facegeo.pipeline.cache", "facegeo.pipeline.reconstruct",
              "facegeo.pipeline.report",
              # decode maps made from the truth, for the mesh stage's tests and benchmarks
              # (re-exported by pipeline.mesh; the stage never calls them)
              "facegeo.pipeline._mesh_truth"}

#: Stage modules that still import the generator to compute their errors: the list shrinks as
#: their comparisons move into facegeo.evaluate (issue 37). Each names what is left (none:
#: the fit's and the relight's moved last).
SYNTH_IMPORTS_LEFT: dict[str, str] = {}

#: Stage modules that read ground_truth/ files or [reference] answers through the scan.
#: ``input``: the truth chosen as a stage's input (a diagnostic run with the true rig or mesh,
#: the generator's novel cameras as view specs) — stays; ``metrics``: errors computed in the
#: stage — moves into facegeo.evaluate (issue 37), and the entry with it.
TRUTH_READS_LEFT = {
    "facegeo.pipeline._project_tasks": "input: stage_rig / load_mesh ('ground_truth' rig and "
                                       "mesh; the project stage's, re-exported there)",
    "facegeo.pipeline.fit": "input: the generator's novel cameras as view specs "
                            "(_camera_table)",
    "facegeo.pipeline.decode": "metrics: decode errors against the true geometry",
    "facegeo.pipeline._scan_store": "input: the ground-truth files a decode task fetches from "
                                    "a store for decode's own metrics (goes with decode's)",
    "facegeo.pipeline._fit_image": "metrics: normals against [reference] normals; input: "
                                   "[reference] mask, the pixels fitted",
}

#: Stage modules that import facegeo.evaluate, and why (a shim for callers not yet moved).
EVALUATE_IMPORTS_LEFT = {
    "facegeo.pipeline.project": "run_project(evaluate=True) returns the figures beside the "
                                "stage's; its gt_lights / gt_weight_min defaults are the "
                                "evaluation's",
    "facegeo.pipeline._project_tasks": "the visibility file name a camera's task writes is the "
                                       "evaluation's",
    "facegeo.pipeline.render": "run_render(reference=True) returns the figures beside the "
                               "view's",
    "facegeo.pipeline._render_view": "render_one renders the paper's λ = 1 beside a shrunk "
                                     "view only when a reference exists (has_view_reference)",
}


def _stage_modules(graph: dict[str, set[str]]) -> list[str]:
    return sorted(m for m in graph
                  if _part(m) in STAGE_PARTS
                  or (_part(m) == "pipeline" and m not in NOT_STAGES))


def _reads_truth(path: Path) -> bool:
    """Whether a file calls ``*.ground_truth_path`` / ``*.reference_path`` or imports
    ``facegeo.capture.references`` (the scan's truth and reference answers)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in ("ground_truth_path",
                                                             "reference_path"):
            return True
        if isinstance(node, ast.ImportFrom) and node.module == "facegeo.capture.references":
            return True
    return False


def _path_of(module: str) -> Path:
    p = PKG.parent / module.replace(".", "/")
    return p / "__init__.py" if p.is_dir() else p.with_suffix(".py")


@functools.lru_cache(maxsize=1)
def _graph_once() -> dict[str, set[str]]:
    """:func:`_graph` once for the checks below (parsing every file takes seconds)."""
    return _graph()


def _offenders(graph, test) -> set[str]:
    return {m for m in _stage_modules(graph) if test(m)}


def test_stage_modules_do_not_import_the_generator():
    graph = _graph_once()
    found = _offenders(graph, lambda m: any(d == "facegeo.synth" or d.startswith("facegeo.synth.")
                                            for d in graph[m]))
    new = sorted(found - set(SYNTH_IMPORTS_LEFT))
    assert not new, ("stage modules importing facegeo.synth (compute errors in facegeo.evaluate "
                     "instead):\n" + "\n".join(new))
    moved = sorted(set(SYNTH_IMPORTS_LEFT) - found)
    assert not moved, f"no longer import facegeo.synth: drop from SYNTH_IMPORTS_LEFT: {moved}"


def test_stage_modules_read_no_truth_beyond_the_allow_list():
    graph = _graph_once()
    found = _offenders(graph, lambda m: _reads_truth(_path_of(m)))
    new = sorted(found - set(TRUTH_READS_LEFT))
    assert not new, "stage modules reading ground_truth/ or [reference]:\n" + "\n".join(new)
    moved = sorted(set(TRUTH_READS_LEFT) - found)
    assert not moved, f"read no truth any more: drop from TRUTH_READS_LEFT: {moved}"


def test_stage_modules_import_the_evaluation_only_where_listed():
    graph = _graph_once()
    found = _offenders(graph, lambda m: any(d == "facegeo.evaluate"
                                            or d.startswith("facegeo.evaluate.")
                                            for d in graph[m]))
    new = sorted(found - set(EVALUATE_IMPORTS_LEFT))
    assert not new, "stage modules importing facegeo.evaluate:\n" + "\n".join(new)
    moved = sorted(set(EVALUATE_IMPORTS_LEFT) - found)
    assert not moved, f"no longer import facegeo.evaluate: drop from EVALUATE_IMPORTS_LEFT: {moved}"


def test_the_truth_checks_can_fail(tmp_path):
    """The checks above see a lazy import of the generator and a ground-truth read."""
    f = tmp_path / "stage.py"
    f.write_text("def run(scan):\n    from facegeo.synth.render import load_ground_truth\n"
                 "    return scan.ground_truth_path('rig')\n", encoding="utf-8")
    assert "facegeo.synth.render" in _imports(f)
    assert _reads_truth(f)
    assert "facegeo.pipeline.project" in _stage_modules(_graph_once())
    assert "facegeo.pipeline.reconstruct" not in _stage_modules(_graph_once())
