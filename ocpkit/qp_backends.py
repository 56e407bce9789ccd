"""PLACEHOLDER"""
from ocpkit.controller import EXCEPTION, INFEASIBLE, LIMITED, SUCCESS

# DAQP's exit flags (daqp/include/constants.h): their names and ocpkit statuses, for the Python step
# (solvers/qp.py) and the C step's failures alike.
DAQP_EXIT = {1: ("optimal", SUCCESS), 2: ("soft optimal", SUCCESS), -1: ("infeasible", INFEASIBLE),
             -2: ("cycling", LIMITED), -3: ("unbounded", INFEASIBLE), -4: ("iteration limit", LIMITED),
             -5: ("nonconvex", EXCEPTION), -6: ("overdetermined initial working set", EXCEPTION),
             -7: ("time limit", LIMITED)}


def daqp_exit_name(flag: int) -> str:
    """DAQP's exit flag in words, as a raw status."""
    name = DAQP_EXIT[flag][0] if flag in DAQP_EXIT else f"exit flag {flag}"
    return f"DAQP {name}" + (" (Hessian not positive definite)" if flag == -5 else "")
