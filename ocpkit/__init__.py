"""ocpkit: parameterized and GPU-parallelized real-time MPC for high-DoF robots (Hyatt, Williams, Killpack).

``from ocpkit import Problem, Model`` declares a problem of your own (see ``ocpkit.problem``).
"""
import os

# The package version (pyproject.toml reads it from here); bumped by hand with a CHANGELOG.md entry. Study trials
# record it, and it is what `ocpkit.study.package_version()` reports even in an editable install not reinstalled.
__version__ = "0.9.0"

# Taichi prints a banner to stdout on import; keep stdout clean for `--json` output and reports.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

__all__ = ["Model", "Problem", "URDFRobot"]


def __getattr__(name):
    # Imported on first use so that `import ocpkit` (the CLI's start-up, worker processes) stays light.
    if name == "Model":
        from ocpkit.model import Model
        return Model
    if name in ("Problem", "URDFRobot"):
        from ocpkit import problem
        return getattr(problem, name)
    raise AttributeError(f"module 'ocpkit' has no attribute {name!r}")
