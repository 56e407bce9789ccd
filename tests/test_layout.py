"""Imports flow one way (issue 33): the core (``ocpkit/``) never imports the solvers, the studies, the benchmarks or
the command line, and the solvers never import the studies, the benchmarks or the command line. A core module may
name a problem by spec (``ocpkit.problems``), inside a function."""
import ast
from pathlib import Path

import pytest

import ocpkit

ABOVE = {"core": ("ocpkit.solvers", "ocpkit.studies", "ocpkit.benchmarks", "ocpkit.cli"),
         "solvers": ("ocpkit.studies", "ocpkit.benchmarks", "ocpkit.cli")}


def _imports(path: Path):
    """(line, module) of every ocpkit import in the file, at any depth."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("ocpkit"):
            yield node.lineno, node.module
        elif isinstance(node, ast.Import):
            yield from ((node.lineno, a.name) for a in node.names if a.name.startswith("ocpkit"))


@pytest.mark.parametrize("layer", list(ABOVE))
def test_imports_flow_one_way(layer):
    import ocpkit.solvers  # installed as ocpkit.solvers (package-dir)

    root = Path(ocpkit.__file__).parent if layer == "core" else Path(ocpkit.solvers.__path__[0])
    # installed (not editable), ocpkit/ also holds solvers/, studies/ and problems/: the core is the rest
    upper = {"solvers", "studies", "problems", "benchmarks", "cli"}
    files = [f for f in root.rglob("*.py") if layer != "core" or not upper & set(f.parts[len(root.parts):])]
    wrong = [f"{f.relative_to(root)}:{line} imports {module}" for f in files for line, module in _imports(f)
             if module.startswith(ABOVE[layer])]
    assert not wrong, "\n".join(wrong)
