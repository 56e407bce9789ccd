"""ocpkit: parameterized and GPU-parallelized real-time MPC for high-DoF robots (Hyatt, Williams, Killpack).

``from ocpkit import OCP, LinearMPC, NonlinearMPC, EvolutionaryMPC, simulate, make`` is the public API (``make``: a
problem by spec); ``from ocpkit import Problem, Model`` declares a problem of your own (see ``ocpkit.model.problem``).
The package's layers, lowest first: ``status`` and the checks, ``codegen``, ``model``, ``qp`` (and ``problems``),
``controller`` and ``safety``, ``export``, then ``sim``, ``runs`` and ``solvers``; ``studies``, ``cli`` and
``benchmarks`` on top (``tests/test_layout.py`` holds the order).
"""

import os

# The package version (pyproject.toml reads it from here); bumped by hand with a CHANGELOG.md entry. Study trials
# record it, and it is what `ocpkit.runs.study.package_version()` reports even in an editable install not reinstalled.
__version__ = "0.17.0"

# Taichi prints a banner to stdout on import; keep stdout clean for `--json` output and reports.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

__all__ = ["OCP", "LinearMPC", "NonlinearMPC", "EvolutionaryMPC", "simulate", "make", "Model", "Problem", "URDFRobot"]


def __getattr__(name):
    # The public API over every layer, imported on first use so that `import ocpkit` (the CLI's start-up, worker
    # processes) stays light. `make` is the problem registry's (ocpkit.problems.make); a controller by name is
    # ocpkit.solvers.make.
    if name == "OCP":
        from ocpkit.model.ocp import OCP

        return OCP
    if name == "LinearMPC":
        from ocpkit.solvers.qp import LinearMPC

        return LinearMPC
    if name == "NonlinearMPC":
        from ocpkit.solvers.nlp import NonlinearMPC

        return NonlinearMPC
    if name == "EvolutionaryMPC":
        from ocpkit.solvers.empc import EvolutionaryMPC

        return EvolutionaryMPC
    if name == "simulate":
        from ocpkit.sim.simulate import simulate

        return simulate
    if name == "make":
        from ocpkit.problems import make

        return make
    if name == "Model":
        from ocpkit.model.dynamics import Model

        return Model
    if name in ("Problem", "URDFRobot"):
        from ocpkit.model import problem

        return getattr(problem, name)
    raise AttributeError(f"module 'ocpkit' has no attribute {name!r}")
