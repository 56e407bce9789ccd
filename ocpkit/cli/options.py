"""The solver and OCP that the command line's options ask for: each option checked against the solver it applies to,
the knot count and the OCP."""

from __future__ import annotations

from ocpkit import solvers
from ocpkit.controller import LINEARIZATIONS, TRAJECTORY
from ocpkit.solvers.methods import ARGUMENTS, DYNAMICS, METHODS, VARIANTS  # noqa: F401 - the parser's choices
from ocpkit.solvers.methods import KNOTS as DEFAULT_KNOTS

SPEC_HELP = (
    "problem spec: a registered name (pendulum, pendulum:linear, pendulum:paper, cartpole, nlink:N with N = 1…13, "
    "puma560, puma560:paper (no terminal weight), baxter, panda, urdf:FILE), package.module:Name or "
    "path/to/file.py:Name (a Problem subclass, instance or factory; ':arg' passes through)"
)
# The solvers' arguments, their meaning and defaults, and the knot count p of solve, simulate and export unless
# --knots or --parameterization identity says otherwise (DEFAULT_KNOTS; Problem.ocp's knots=None is p = T) come from
# the one table, ocpkit.solvers.methods, which imports no solver: `ocpkit --help` does not import them (half a
# second). The backends are written out; tests/test_cli.py checks them against solvers.qp.QP_SOLVERS.
NLP_METHODS = tuple(METHODS)
QP_SOLVERS = ("qp", "rti")  # the solvers that take --form and --qp: LinearMPC and the real-time iteration's QPs
QP_BACKENDS = ("proxqp", "osqp", "daqp", "hpipm")
SAMPLING = ("empc", "cem", "mppi")
# What `ocpkit export` offers: the (form, qp) pairs ocpkit.export generates (its SUPPORTED; tests/test_cli.py checks),
# DAQP first, the default.
EXPORT_FORMS = ("condensed",)
EXPORT_QPS = ("daqp", "qrqp", "osqp")


def _with_methods(option: str) -> str:
    """Solver ipopt with the methods that take ``option`` (solvers.methods.METHODS), in the command line's words."""
    return f"solver ipopt with --method {' or '.join(m for m in METHODS if option in METHODS[m])}"


# Solver-specific options: where each applies, as (test of the configuration, where it applies in words). A given
# option that does not apply is an error naming it and the solver, never silently dropped.
_SOLVER_OPTIONS = {
    "form": (lambda c: c.solver in QP_SOLVERS, f"solvers {', '.join(QP_SOLVERS)}"),
    "qp": (lambda c: c.solver in QP_SOLVERS, f"solvers {', '.join(QP_SOLVERS)}"),
    "method": (lambda c: c.solver == "ipopt", "solver ipopt"),
    "iterations": (lambda c: c.solver == "rti", "solver rti"),
    "dynamics": (
        lambda c: "dynamics" in METHODS.get(c.method, ()) or c.solver in SAMPLING,
        f"{_with_methods('dynamics')}, and solvers {', '.join(SAMPLING)}",
    ),
    "linearization": (
        lambda c: c.solver == "qp" or c.dynamics == "affine" or c.variant == "preconditioned",
        f"solver qp, {_with_methods('linearization')} and --dynamics affine, and solvers "
        f"{', '.join(SAMPLING)} unless --dynamics nonlinear --variant paper (they linearize nothing)",
    ),
    **{
        name: (lambda c: c.solver in SAMPLING, f"solvers {', '.join(SAMPLING)}")
        for name in ("population", "generations", "arch", "variant")
    },
}


class _Config:
    """The solver configuration the command line asks for, with the solvers' defaults filled in (None: not
    this solver's setting)."""

    def __init__(self, args):
        self.solver = args.solver
        self.method = (args.method or ARGUMENTS["ipopt"]["method"].default) if args.solver == "ipopt" else None
        self.dynamics = self.variant = None
        if "dynamics" in METHODS.get(self.method, ()):
            self.dynamics = args.dynamics or METHODS[self.method]["dynamics"].default
        elif args.solver in SAMPLING:
            self.dynamics = args.dynamics or ARGUMENTS[args.solver]["dynamics"].default
            self.variant = args.variant or ARGUMENTS[args.solver]["variant"].default

    def describe(self, option: str) -> str:
        """The configuration in the words of the command line, with what decides whether ``option`` applies."""
        settings = [f"--method {self.method}"] if self.method else []
        if option == "linearization":
            settings += [f"--{k} {v}" for k, v in (("dynamics", self.dynamics), ("variant", self.variant)) if v]
        return f"solver {self.solver!r}" + (f" with {' '.join(settings)}" if settings else "")


def default(solver: str, argument: str):
    """The default of ``solver``'s ``argument`` (ocpkit.solvers.methods; ipopt: its default method's)."""
    table = ARGUMENTS[solver]
    if argument not in table and solver == "ipopt":
        table = METHODS[table["method"].default]
    return table[argument].default


def solver_options(args) -> dict:
    """The solver's keyword arguments from the command line; an option that does not apply to the chosen solver
    (and method, dynamics, variant) is a ValueError naming both."""
    if args.solver not in solvers.names():
        raise ValueError(f"unknown solver {args.solver!r}; known: {', '.join(solvers.names())}")
    config = _Config(args)
    given = {k: getattr(args, k) for k in _SOLVER_OPTIONS if getattr(args, k) is not None}
    for option in given:
        applies, where = _SOLVER_OPTIONS[option]
        if not applies(config):
            why = (
                " (it always linearizes along its iterate)"
                if option == "linearization" and config.solver == "rti"
                else ""
            )
            raise ValueError(f"--{option} does not apply to {config.describe(option)}{why}: it applies to {where}")
    if given.get("linearization") == TRAJECTORY and args.solver != "qp":
        raise ValueError(
            f"--linearization trajectory applies to solver qp only; {config.describe('')} takes "
            f"{' or '.join(LINEARIZATIONS)}"
        )
    return given


def knot_count(problem, args) -> int | None:
    """The knot count p of the OCP (None: traditional MPC, p = T): --knots, or DEFAULT_KNOTS capped at the horizon."""
    if args.parameterization == "identity":
        if args.knots is not None:
            raise ValueError(
                f"--knots {args.knots} does not apply to --parameterization identity (traditional MPC "
                f"has one knot per step, p = T); give one of them"
            )
        return None
    if args.knots is not None:
        return args.knots
    T = problem.horizon if args.horizon is None else args.horizon
    return min(DEFAULT_KNOTS, T) if T >= 1 else DEFAULT_KNOTS  # a bad horizon: the OCP's own check names it


def make_ocp(problem, args, **options):
    return problem.ocp(
        knots=knot_count(problem, args),
        horizon=args.horizon,
        parameterization=args.parameterization,
        integrator=args.integrator,
        **options,
    )
