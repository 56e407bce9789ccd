"""NonlinearMPC's methods and the arguments each takes, with their meaning and default there: the one table that
NonlinearMPC checks its arguments against and the command line's option check reads (no solver is imported here,
so `ocpkit --help` stays fast)."""
from __future__ import annotations

from typing import NamedTuple

DYNAMICS = ("nonlinear", "affine")
HESSIANS = ("gauss-newton", "exact")


class Argument(NamedTuple):
    """What one of NonlinearMPC's arguments means for a method, and its default there."""

    meaning: str
    default: object = None


_GAUSS_NEWTON = Argument("gauss-newton (derivatives from the per-stage affine model) or exact (CasADi's AD of the "
                         "whole NLP)", "gauss-newton")
_AFFINE = {"dynamics": Argument("the prediction model: nonlinear (the discrete model F) or affine (about (x, ū))",
                                "nonlinear"),
           "linearization": Argument("the affine model's expansion input, with dynamics 'affine'", "goal")}

# method -> the arguments it takes (besides ocp, warm_start, raise_on_fail); an argument given that its method does
# not take is refused, naming the methods that do.
METHODS = {
    "ipopt": {**_AFFINE, "hessian": _GAUSS_NEWTON,
              "max_iter": Argument("IPOPT's iterations", 200),
              "time_limit": Argument("IPOPT's max_wall_time in seconds (NonlinearMPC.ceiling, 10 s, without one)"),
              "options": Argument("IPOPT's options, e.g. {'tol': 1e-10}")},
    "sqp": {**_AFFINE, "hessian": _GAUSS_NEWTON,
            "max_iter": Argument("sqpmethod's SQP iterations", 200),
            "time_limit": Argument("seconds, checked after each SQP iteration (NonlinearMPC.ceiling without one)"),
            "options": Argument("CasADi sqpmethod's options, e.g. {'qpsol': 'osqp'} (default qrqp)")},
    "fatrop": {"hessian": _GAUSS_NEWTON,
               "max_iter": Argument("fatrop's iterations", 200),
               "options": Argument("fatrop's options, e.g. {'tol': 1e-10}")},
}


def taking(argument: str) -> list[str]:
    """The methods that take ``argument``."""
    return [method for method, arguments in METHODS.items() if argument in arguments]
