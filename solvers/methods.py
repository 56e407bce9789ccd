"""The controllers' vocabulary: every registered solver's user-facing arguments with their meaning and default, in
one table (:data:`ARGUMENTS`, NonlinearMPC's per method in :data:`METHODS`). The constructors take their defaults
from it, the command line's options read it (their help and the defaults it fills in) and so do the benchmarks where
they name a default. No solver is imported here, so `ocpkit --help` stays fast.

Where one name has different defaults it means a different thing, said here once:

* ``max_iter`` is the iteration limit of the controller's own solver in one solve: a QP backend's (qp, and each QP
  of rti: active-set or ADMM iterations, cheap; 10,000) or an NLP solver's (ipopt: IPOPT's, sqpmethod's or fatrop's
  iterations, each a factorization of the KKT system; 200). The sampling planners take none (their preconditioner's
  DAQP, not an argument, stops at 1,000).
* ``dynamics`` is the prediction model. NonlinearMPC, the reference for the nonlinear program, predicts with the
  nonlinear model F by default; the sampling planners roll out the affine model re-linearized every step by
  default (quick to compile and stable over the horizon; :mod:`ocpkit.solvers.sampling` says when to choose F).
* ``state_bounds``: LinearMPC's default follows its backend (hard for hpipm, which supports no other, else soft);
  the real-time iteration's is soft.
* The knot count p: :meth:`ocpkit.model.problem.Problem.ocp`'s ``knots=None`` is traditional MPC, p = T (the OCP
  the API is asked for, unchanged); the command line and the benchmarks take :data:`KNOTS` knots (capped at the
  horizon), the docs' examples and the size the C step and the Taichi kernels compile quickly for.
"""

from __future__ import annotations

from typing import NamedTuple

KNOTS = 5  # the command line's and the benchmarks' knot count p (Problem.ocp's knots=None: p = T)
DYNAMICS = ("nonlinear", "affine")
HESSIANS = ("gauss-newton", "exact")
VARIANTS = ("preconditioned", "paper")
QP_BY_FORM = {"condensed": "daqp", "sparse": "proxqp"}  # LinearMPC's backend where qp is None, by form


class Argument(NamedTuple):
    """What one of a controller's arguments means, and its default there."""

    meaning: str
    default: object = None


_LINEARIZATION = Argument(
    "the affine model's expansion input: goal (the goal's input) or plan (the input the previous plan expects now)",
    "goal",
)
_TIME_LIMIT = Argument("seconds a control step may take (None: no budget)")
_RAISE = Argument("raise on a failed step instead of returning the fallback", False)
_THREADS = Argument("BLAS/OpenMP threads inside a step (None: no limit)", 1)
_WARM_START = Argument("start each solve from the previous one, shifted a step", True)
_COMMON = {"time_limit": _TIME_LIMIT, "raise_on_fail": _RAISE, "threads": _THREADS}

# LinearMPC: the knot QP.
LINEAR = {
    "form": Argument("the QP transcription: condensed (the knots only) or sparse (states too)", "condensed"),
    "qp": Argument(f"the QP backend: proxqp, osqp, daqp or hpipm (None: by form, {QP_BY_FORM})"),
    "max_iter": Argument("the QP backend's iterations per solve", 10_000),
    "eps": Argument("the QP backend's tolerance", 1e-9),
    "linearization": Argument(
        f"{_LINEARIZATION.meaning}, or trajectory (stage by stage along the shifted plan)", "goal"
    ),
    "state_bounds": Argument(
        "soft (an exact penalty of weight slack_weight) or hard (None: hard for hpipm, else soft)"
    ),
    "slack_weight": Argument("the soft state bounds' penalty weight", 1e3),
    "native": Argument("run the step as compiled C (None: as the OCP's compiled policy says)"),
    "warm_start": _WARM_START,
    "gains": Argument(
        "compute Solution.gains, the first input's feedback gain du0/dx0 of the solved QP (runs the Python step)", False
    ),
    **_COMMON,
}

# RealTimeIteration: LinearMPC's arguments (but linearization: always along its iterate) and its own.
RTI = {
    "iterations": Argument("Gauss-Newton SQP iterations per control step", 1),
    "tol": Argument("stop iterating once the plan moves less than this (max norm; 0: all iterations)", 0.0),
    **{name: argument for name, argument in LINEAR.items() if name != "linearization"},
    "state_bounds": Argument("soft or hard", "soft"),
}

_GAUSS_NEWTON = Argument(
    "gauss-newton (derivatives from the per-stage affine model) or exact (CasADi's AD of the whole NLP)", "gauss-newton"
)
_AFFINE = {
    "dynamics": Argument(
        "the prediction model: nonlinear (the discrete model F) or affine (about (x, ū))", "nonlinear"
    ),
    "linearization": Argument(f"{_LINEARIZATION.meaning}, with dynamics 'affine'", "goal"),
}

# NonlinearMPC's methods -> the arguments each takes besides those of NONLINEAR; an argument given that its method
# does not take is refused, naming the methods that do.
METHODS = {
    "ipopt": {
        **_AFFINE,
        "hessian": _GAUSS_NEWTON,
        "max_iter": Argument("IPOPT's iterations", 200),
        "time_limit": Argument("IPOPT's max_wall_time in seconds (NonlinearMPC.ceiling, 10 s, without one)"),
        "options": Argument("IPOPT's options, e.g. {'tol': 1e-10}"),
    },
    "sqp": {
        **_AFFINE,
        "hessian": _GAUSS_NEWTON,
        "max_iter": Argument("sqpmethod's SQP iterations", 200),
        "time_limit": Argument("seconds, checked after each SQP iteration (NonlinearMPC.ceiling without one)"),
        "options": Argument("CasADi sqpmethod's options, e.g. {'qpsol': 'osqp'} (default qrqp)"),
    },
    "fatrop": {
        "hessian": _GAUSS_NEWTON,
        "max_iter": Argument("fatrop's iterations", 200),
        "options": Argument("fatrop's options, e.g. {'tol': 1e-10}"),
    },
}

# NonlinearMPC: the arguments of every method (the rest by method, METHODS; None in its signature: the method's).
NONLINEAR = {
    "method": Argument(f"how the NLP is solved: {', '.join(METHODS)}", "ipopt"),
    "warm_start": Argument("start each solve from the previous primal and dual solution, shifted a step", True),
    "raise_on_fail": _RAISE,
}

# The sampling planners (SamplingMPC), then each one's own.
SAMPLING = {
    "population": Argument("rollouts per generation", 1024),
    "generations": Argument("generations per control step", 1),
    "variant": Argument("preconditioned (by the knot QP) or paper (the plain algorithm)", "preconditioned"),
    "dynamics": Argument(
        "the rollout model: affine (re-linearized every step) or nonlinear (the discrete model F)", "affine"
    ),
    "stage_cost": Argument("a CasADi Function (x, u, goal) replacing the OCP's stage cost in the fitness"),
    "terminal_cost": Argument("a CasADi Function (x, goal) replacing the OCP's terminal cost in the fitness"),
    "precision": Argument("the kernels' float type: float64 or float32", "float64"),
    "arch": Argument("Taichi's arch: auto, cpu or cuda", "auto"),
    "seed": Argument("the random stream's seed", 0),
    "linearization": _LINEARIZATION,
    **_COMMON,
}
_SIGMA = Argument(
    "paper: the std in input units (None: 10 % of each input's range); preconditioned: in whitened units (None: 1)"
)
EMPC = {
    **SAMPLING,
    "num_parents": Argument("the best candidates kept as parents", 16),
    "scales": Argument("preconditioned: the whitened mutation scale's log-uniform range (None: (1e-2, 1e2))"),
    "sigma": Argument("paper: the mutation std in input units (None: 10 % of each input's range)"),
    "shrink_distance": Argument("paper: the distance to the goal below which the std shrinks (None: never)"),
    "sigma_min": Argument("paper: the shrunk std (None: sigma / 10)"),
}
CEM = {
    **SAMPLING,
    "num_elites": Argument("the best candidates the Gaussian is refitted to", 32),
    "sigma": _SIGMA,
    "sigma_min": Argument("the std's floor (None: sigma / 100)"),
    "smoothing": Argument("α in mean ← α·mean + (1−α)·elite mean (and so the std)", 0.0),
}
MPPI = {
    **SAMPLING,
    "sigma": _SIGMA,
    "temperature": Argument("λ of the weights exp(−(J − min J)/λ), in the cost's units", 1.0),
}

# Registered solver name (ocpkit.solvers.names()) -> its arguments besides the OCP.
ARGUMENTS = {"qp": LINEAR, "rti": RTI, "ipopt": NONLINEAR, "empc": EMPC, "cem": CEM, "mppi": MPPI}


def taking(argument: str) -> list[str]:
    """NonlinearMPC's methods that take ``argument``."""
    return [method for method, arguments in METHODS.items() if argument in arguments]
