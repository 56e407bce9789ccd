"""The house by its layers: every module belongs to one layer, imports flow only downward, and no modules import each
other in a circle.

Layers, lowest first (a unit is a package, or the named top-level modules, of one layer):

 0. base       ``ocpkit`` (its version; its ``__getattr__`` offers the public API, below), ``_checks``, ``numeric``,
               ``status`` (statuses, Solution, OperationCosts)
 1. codegen    ``ocpkit.codegen``: CasADi Functions compiled to C (``compiled``, ``builder``, ``cache``), Taichi kernels
 2. model      ``ocpkit.model``: dynamics, rigid body, kinematics, parameterization, task, OCP, problem
 3. problems   ``ocpkit.problems`` (the shipped robots, problems by spec) and ``ocpkit.qp`` (transcription, backends,
    / qp       certificate, box QP): neither imports the other
 4. control    ``ocpkit.controller``, ``ocpkit.safety``
 5. export     ``ocpkit.export``: the controller as generated C, and LinearMPC's compiled step (``native``)
 6. sim, runs, ``ocpkit.sim`` (closed loop, plants, metrics, pictures), ``ocpkit.runs`` (study infrastructure),
    solvers    ``ocpkit.solvers``: none imports another
 7. studies    ``ocpkit.studies``
 8. cli        ``ocpkit.cli`` (it names the benchmarks by computed name only)
 9. benchmarks ``ocpkit.benchmarks`` (some drive the command line)

A module may import modules of its own unit and of units in lower layers, at module level or inside a function
alike (``if TYPE_CHECKING:`` imports count too). The one exception is ``ocpkit/__init__.py``'s ``__getattr__``: the
public API (``from ocpkit import OCP, LinearMPC, …``), imported on first use, is the facade over every layer.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import ocpkit
import ocpkit.problems
import ocpkit.solvers  # installed as ocpkit.solvers (package-dir)
import ocpkit.studies

LAYERS = (
    {"base": ("ocpkit", "ocpkit._checks", "ocpkit.numeric", "ocpkit.status")},
    {"codegen": ("ocpkit.codegen",)},
    {"model": ("ocpkit.model",)},
    {"problems": ("ocpkit.problems",), "qp": ("ocpkit.qp",)},
    {"control": ("ocpkit.controller", "ocpkit.safety")},
    {"export": ("ocpkit.export",)},
    {"sim": ("ocpkit.sim",), "runs": ("ocpkit.runs",), "solvers": ("ocpkit.solvers",)},
    {"studies": ("ocpkit.studies",)},
    {"cli": ("ocpkit.cli",)},
    {"benchmarks": ("ocpkit.benchmarks",)},
)
PACKAGES = {
    "ocpkit": ocpkit,
    "ocpkit.problems": ocpkit.problems,
    "ocpkit.solvers": ocpkit.solvers,
    "ocpkit.studies": ocpkit.studies,
}
PUBLIC = ("OCP", "LinearMPC", "NonlinearMPC", "EvolutionaryMPC", "simulate", "make", "Model", "Problem", "URDFRobot")


def _modules() -> dict[str, Path]:
    """Every module of the package, by name, wherever it is installed (editable or not)."""
    found = {}
    for package, module in PACKAGES.items():
        root = Path(module.__path__[0])
        for path in sorted(root.rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if package == "ocpkit" and parts[0] in ("problems", "solvers", "studies"):
                continue  # installed (not editable), ocpkit/ also holds them: found under their own name
            found[".".join([package] + parts[:-1] + ([] if parts[-1] == "__init__" else parts[-1:]))] = path
    return found


MODULES = _modules()


def _unit(name: str) -> tuple[int, str]:
    """(layer, unit) of module ``name``: its longest listed prefix (``ocpkit`` itself only by exact name)."""
    best = None
    for layer, units in enumerate(LAYERS):
        for unit, prefixes in units.items():
            for prefix in prefixes:
                if (name == prefix or (prefix != "ocpkit" and name.startswith(prefix + "."))) and (
                    best is None or len(prefix) > best[2]
                ):
                    best = (layer, unit, len(prefix))
    assert best is not None, f"{name} is in no layer: add it to LAYERS in {__file__}"
    return best[:2]


def _imports(name: str, path: Path):
    """(line, imported module) of every ocpkit import of module ``name``, at any depth, but the facade's."""
    tree = ast.parse(path.read_text())
    facade = set()
    if name == "ocpkit":
        facade = {
            id(n) for f in tree.body if isinstance(f, ast.FunctionDef) and f.name == "__getattr__" for n in ast.walk(f)
        }
    package = path.name == "__init__.py"
    for node in ast.walk(tree):
        if id(node) in facade:
            continue
        if isinstance(node, ast.Import):
            yield from ((node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "ocpkit")
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = name.split(".") if package else name.split(".")[:-1]
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            if base.split(".")[0] != "ocpkit":
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield node.lineno, sub if sub in MODULES else base


def _graph() -> dict[str, dict[str, int]]:
    """module -> {imported module: first line}."""
    graph = {}
    for name, path in MODULES.items():
        edges = graph.setdefault(name, {})
        for line, target in _imports(name, path):
            while target not in MODULES and "." in target:
                target = target.rpartition(".")[0]
            if target in MODULES and target != name:
                edges.setdefault(target, line)
    return graph


def test_every_module_is_in_a_layer():
    assert len(MODULES) > 50
    for name in MODULES:
        _unit(name)


def test_imports_flow_downward():
    wrong = []
    for name, edges in _graph().items():
        layer, unit = _unit(name)
        for target, line in edges.items():
            their_layer, their_unit = _unit(target)
            if their_unit != unit and their_layer >= layer:
                wrong.append(
                    f"{MODULES[name].name} ({name}, {unit}):{line} imports {target} ({their_unit}, "
                    f"layer {their_layer} >= {layer})"
                )
    assert not wrong, "\n".join(wrong)


def _cycles(graph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
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
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph)))
    try:
        for v in graph:
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return found


def test_no_import_circles():
    graph = _graph()
    assert not _cycles(graph), _cycles(graph)
    # the test finds one where there is one
    graph["ocpkit.model.ocp"] = {**graph["ocpkit.model.ocp"], "ocpkit.controller": 1}
    assert any("ocpkit.controller" in c and "ocpkit.model.ocp" in c for c in _cycles(graph))


def test_the_public_api_is_importable_from_the_package_and_loads_on_first_use():
    code = (
        "import sys, ocpkit; light = sorted(m for m in sys.modules if m.startswith('ocpkit.')); "
        f"from ocpkit import {', '.join(PUBLIC)}; print(light, sorted(ocpkit.__all__))"
    )
    # cwd outside the checkout, whose ocpkit/ would shadow the installed package (`python -c` puts the cwd first)
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=Path(__file__).parent
    ).stdout.split("\n")[0]
    assert out == f"[] {sorted(PUBLIC)}"
    from ocpkit import EvolutionaryMPC, LinearMPC, NonlinearMPC, make, simulate
    from ocpkit.problems import make as make_problem
    from ocpkit.sim.simulate import simulate as simulate_loop
    from ocpkit.solvers.empc import EvolutionaryMPC as EMPC
    from ocpkit.solvers.nlp import NonlinearMPC as NMPC
    from ocpkit.solvers.qp import LinearMPC as LMPC

    assert (make, simulate, LinearMPC, NonlinearMPC, EvolutionaryMPC) == (make_problem, simulate_loop, LMPC, NMPC, EMPC)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ocpkit.nope  # noqa: B018
