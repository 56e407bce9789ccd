"""ocpkit: parameterized and GPU-parallelized real-time MPC for high-DoF robots (Hyatt, Williams, Killpack).

``from ocpkit import Problem, Model`` declares a problem of your own (see ``ocpkit.problem``).
"""
import os

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
