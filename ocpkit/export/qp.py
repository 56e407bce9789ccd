"""The QP solver inside the exported step: CasADi's conic plugin set up for code generation, and the repair of
CasADi 3.8's generated DAQP call (see the package docstring)."""

from __future__ import annotations

from pathlib import Path

import casadi as ca

from ocpkit.export.folder import write

# CasADi 3.8's generated DAQP call: casadi_daqp_solve returns 1 after a failed set-up, which its caller ignores
# before reading d_qp.success, never set on that path. Fixed, the generated function returns DAQP's exit flag on
# any failure (set-up or solve) and 0 on success.
_DAQP_FIX = (
    ("  if (flag<0) return 1;\n", "  if (flag<0) { d->return_status = flag; return 1; }\n"),
    (
        "  casadi_daqp_solve(d, arg, res, iw, w);\n  if (!d_qp.success) {\n    return -1;\n  }\n",
        "  d_qp.success = 0;\n  casadi_daqp_solve(d, arg, res, iw, w);\n"
        "  if (!d_qp.success) return d->return_status == 1 ? -1 : d->return_status;\n",
    ),
)


def fix_daqp_setup(path: Path) -> None:
    """Make CasADi's generated DAQP function report a failed set-up and DAQP's exit flag (see the package
    docstring). Where CasADi generates other code the file is left as it is: the C step's certificate still refuses
    a stale answer, and the test suite notices (tests/test_certificate.py)."""
    text = path.read_text()
    if all(text.count(old) == 1 for old, _ in _DAQP_FIX):
        for old, new in _DAQP_FIX:
            text = text.replace(old, new)
        write(path, text)


def conic(qp: str, name: str, nz: int, na: int, eps: float, max_iter: int, polish: bool) -> ca.Function:
    """The CasADi conic solver for a dense H (nz × nz) and dense A (na × nz), set up for code generation."""
    opts = {"error_on_fail": False, "print_problem": False}
    if qp == "qrqp":
        opts.update(
            print_iter=False,
            print_header=False,
            print_info=False,
            max_iter=max_iter,
            constr_viol_tol=eps,
            dual_inf_tol=eps,
        )
    elif qp == "osqp":
        opts["osqp"] = {
            "eps_abs": eps,
            "eps_rel": eps,
            "max_iter": max_iter,
            "verbose": False,
            "polishing": bool(polish),
        }
        opts.update(warm_start_primal=True, warm_start_dual=True)
        opts.pop("print_problem")
    else:
        opts["daqp"] = {"iter_limit": max_iter, "primal_tol": eps, "dual_tol": eps}
    structure = {"h": ca.Sparsity.dense(nz, nz), "a": ca.Sparsity.dense(na, nz)}
    return ca.conic(f"{name}_qp_solve", qp, structure, opts)
