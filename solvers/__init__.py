"""MPC solvers by name: "qp" (LinearMPC), "rti" (RealTimeIteration), "ipopt" (NonlinearMPC: methods ipopt, sqp,
fatrop), "empc", "cem", "mppi" (sampling on Taichi)."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import import_module

from ocpkit.controller import Controller
from ocpkit.model.ocp import OCP

# solver name -> module defining it (imported only when used: the sampling solvers start Taichi)
_SOLVERS = {"qp": "qp", "rti": "rti", "ipopt": "nlp", "empc": "empc", "cem": "cem", "mppi": "mppi"}


def names() -> list[str]:
    """The registered solver names."""
    return sorted(_SOLVERS)


def make(name: str, ocp: OCP, **options) -> Controller:
    """A controller for ``ocp`` by solver name, with solver-specific options."""
    if name not in _SOLVERS:
        raise ValueError(f"unknown solver {name!r}; known: {', '.join(names())}")
    return import_module(f"ocpkit.solvers.{_SOLVERS[name]}").SOLVERS[name](ocp, **options)


@dataclass(frozen=True)
class Configuration:
    """One way to run a registered solver: its options, the knots it needs ("horizon": p = T, traditional MPC;
    None: any), and the optimum it claims — "convex" (the knot QP about the input goal, which every QP backend,
    form and NLP over the affine model must reach from a cold start), "nlp" (the nonlinear program's KKT point) or
    None (a heuristic or one-iteration method: no optimum claimed)."""

    solver: str
    options: dict = field(default_factory=dict)
    knots: str | None = None
    optimum: str | None = None

    @property
    def label(self) -> str:
        opts = ",".join(f"{k}={v}" for k, v in self.options.items())
        return f"{self.solver}[{opts}]" if opts else self.solver

    def make(self, ocp: OCP) -> Controller:
        return make(self.solver, ocp, **self.options)


# RTI on HPIPM's Riccati interior point (the sparse QP, hard state bounds): traditional MPC (p = T) only.
RTI_HPIPM = Configuration("rti", {"form": "sparse", "qp": "hpipm", "state_bounds": "hard"}, knots="horizon")

# Controllers by name, the one list the benchmarks take (`ocpkit bench nlp|startup --controller NAME`): each
# registered solver as constructed by default, under its own name, and a few variants.
CONTROLLERS = {
    **{name: Configuration(name) for name in _SOLVERS},
    "qp-python": Configuration("qp", {"native": False}),  # LinearMPC without its C step
    "ltv": Configuration("qp", {"linearization": "trajectory"}),  # one real-time iteration, LinearMPC's
    "rti3": Configuration("rti", {"iterations": 3}),
    "rti-hpipm": RTI_HPIPM,
    "fatrop": Configuration("ipopt", {"method": "fatrop"}),
}


# The benchmarks' default controllers (`ocpkit bench nlp` columns, `startup` rows), names of CONTROLLERS; "exported"
# is startup's ExportedMPC (export + build).
BENCHMARKED = {
    "nlp": ("ipopt", "fatrop", "rti", "rti3", "qp", "ltv"),
    "startup": ("qp", "qp-python", "rti", "ipopt", "fatrop", "empc", "cem", "mppi", "exported"),
}


def controller(name: str, ocp: OCP) -> Controller:
    """The controller ``name`` of :data:`CONTROLLERS` for ``ocp``."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}")
    return CONTROLLERS[name].make(ocp)


def _qp_configurations():
    backends = [
        ("condensed", "daqp"),
        ("condensed", "proxqp"),
        ("condensed", "osqp"),
        ("sparse", "proxqp"),
        ("sparse", "osqp"),
    ]
    out = [
        Configuration(
            "qp",
            {"form": form, "qp": qp, "linearization": lin, "native": False},
            optimum="convex" if lin != "trajectory" else None,
        )
        for form, qp in backends
        for lin in ("goal", "plan", "trajectory")
    ]
    out.append(Configuration("qp", {"form": "condensed", "qp": "daqp", "native": True}, optimum="convex"))
    out.append(
        Configuration("qp", {"form": "sparse", "qp": "hpipm", "native": False}, knots="horizon", optimum="convex")
    )
    return out


# Every registered solver's configurations: the contract test (tests/test_contract.py) runs each of them on its
# problems, so a solver or variant joins the contract by being listed here.
CONFIGURATIONS = {
    "qp": _qp_configurations(),
    "ipopt": [
        Configuration("ipopt", {"method": "ipopt"}, optimum="nlp"),
        Configuration("ipopt", {"method": "ipopt", "dynamics": "affine"}, optimum="convex"),
        Configuration("ipopt", {"method": "sqp"}, optimum="nlp"),
        Configuration("ipopt", {"method": "fatrop"}, optimum="nlp"),
    ],
    "rti": [
        Configuration("rti"),
        Configuration("rti", {"form": "sparse"}),
        RTI_HPIPM,
        Configuration("rti", {"iterations": 30, "tol": 1e-10, "state_bounds": "hard"}, optimum="nlp"),
    ],
    **{
        name: [Configuration(name, {"variant": variant, "population": 64}) for variant in ("preconditioned", "paper")]
        for name in ("empc", "cem", "mppi")
    },
}


def configurations() -> list[Configuration]:
    """Every configuration of every registered solver (see :data:`CONFIGURATIONS`)."""
    return [c for name in names() for c in CONFIGURATIONS.get(name, ())]
