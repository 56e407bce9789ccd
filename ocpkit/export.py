"""Export the whole MPC control step as generated C, and load it back as a Controller.

One control step of the paper's condensed convex MPC (Section V-B, V-E) — affine model about (x, ū),
condensed QP  min ½ zᵀPz + qᵀz  s.t. knot and state bounds, QP solve, first input — is written in CasADi
from the same description every Python solver uses (``ocp.affine()``, the parameterization basis, Q, R,
bounds) and code-generated with CasADi's CodeGenerator. ū is u_goal (``linearization="goal"``) or the
input the previous plan expects now, ``u_at(shift(plan), 0)`` (``"plan"``), exactly as
:class:`~ocpkit.solvers.qp.LinearMPC` does, so the exported step reproduces LinearMPC's QP and solution. A small hand-written wrapper keeps the plan and warm start in a
caller-owned memory struct (no allocation in ``step``) and applies the controller's fallback on failure.

QP solvers (CasADi conic plugins with code generation in CasADi 3.8):

* ``qrqp`` — CasADi's own active-set solver, generated as plain C: the folder needs nothing else. It can
  report success at a point outside the bounds (seen on nlink:3, T = 50), so every step checks the bound
  violation of the returned point and treats more than ``FEAS_TOL`` as a failure.
* ``daqp`` (default) — links CasADi's shipped ``libdaqpstat.a`` (headers under ``casadi/include``); DAQP's setup
  runs inside each step and allocates there.
* ``osqp`` — links CasADi's shipped ``libosqpstatic.a``; set up once at init, updated each step.
* ``hpipm`` — refused: CasADi's HPIPM interface needs a stage-wise OCP structure, which the condensed
  QP over knots does not have.
"""
from __future__ import annotations

import ctypes
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ocpkit._checks import array, choice, integer, positive
from ocpkit.controller import STATUSES, SUCCESS, Controller, Solution
from ocpkit.ocp import OCP
from ocpkit.transcription import CondensedQP

FORMS = ("condensed", "sparse")
QP_SOLVERS = ("qrqp", "daqp", "osqp", "hpipm")
LINEARIZATIONS = ("goal", "plan")
# (form, qp) pairs whose CasADi code generation is wired here; others get a ValueError saying why.
SUPPORTED = {("condensed", "qrqp"), ("condensed", "daqp"), ("condensed", "osqp")}
_UNSUPPORTED_WHY = {
    "hpipm": "CasADi's HPIPM interface needs a stage-wise OCP structure (per-stage x_k, u_k), which a QP "
             "over parameterization knots does not have",
    "sparse": "only the condensed (small-matrix) form is exported; the sparse form is solved in Python by "
              "LinearMPC(form='sparse')",
}
FEAS_TOL = 1e-6  # largest bound violation accepted from a QP solver that reports success
_VIOLATED = 9999  # solver return code the C step reports for a "solved" point violating bounds
_SOLVER_NOTE = {
    "qrqp": "qrqp is warm-started from the previous solution; `step` never allocates.",
    "daqp": "CasADi's DAQP code starts DAQP cold and runs its setup, which allocates, inside every step.",
    "osqp": "OSQP is set up (allocating) once in `init` and warm-started; `step` does not allocate.",
}
_UBAR = {"goal": "the goal input u_goal",
         "plan": "the input the previous plan expects now (u_goal at a cold start)"}
_CASADI_DIR = Path(ca.__file__).resolve().parent
_LIBS = {"qrqp": "", "daqp": "$(CASADI_DIR)/libdaqpstat.a", "osqp": "$(CASADI_DIR)/libosqpstatic.a"}


@dataclass
class Export:
    """What :func:`export` wrote: the folder, the C name prefix and the problem sizes."""

    out_dir: Path
    name: str
    form: str
    qp: str
    linearization: str
    nx: int
    nu: int
    knots: int
    horizon: int
    n_constraints: int

    @property
    def library(self) -> Path:
        """The shared library ``make`` builds in the folder."""
        return self.out_dir / f"lib{self.name}.so"


def export(ocp: OCP, out_dir, *, form: str = "condensed", qp: str = "daqp", name: str = "mpc",
           eps: float = 1e-9, max_iter: int = 1000, linearization: str = "goal", x0=None, goal=None,
           steps: int = 100) -> Export:
    """Write C sources, header, Makefile, example ``main.c`` and README for the MPC step of ``ocp``.

    ``eps`` is the QP solver's tolerance, ``max_iter`` its iteration limit; ``linearization`` "goal"
    linearizes about (x, u_goal), "plan" about (x, ū) as LinearMPC's option of that name; ``x0``, ``goal`` and
    ``steps`` set the closed loop the example runs against the generated discrete model.
    """
    if not isinstance(ocp, OCP):
        raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
    choice(form, FORMS, "form")
    choice(qp, QP_SOLVERS, "qp")
    if (form, qp) not in SUPPORTED:
        why = _UNSUPPORTED_WHY["sparse" if form == "sparse" else qp]
        raise ValueError(f"qp={qp!r} with form={form!r} cannot be exported: {why}; "
                         f"supported: {sorted(SUPPORTED)}")
    choice(linearization, LINEARIZATIONS, "linearization")
    if np.any(ocp.u_goal_gain):
        raise ValueError("ocp.u_goal_gain is nonzero: the exported step supports a constant input goal only")
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    eps = positive(eps, "eps")
    max_iter = integer(max_iter, "max_iter", 1)
    steps = integer(steps, "steps", 1)
    x0 = np.zeros(ocp.nx) if x0 is None else ocp.check_state(x0, "x0")
    goal = np.zeros(ocp.nx) if goal is None else ocp.check_state(goal, "goal")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    funcs = _condensed_functions(ocp, name, linearization)
    solver = _conic(qp, name, funcs["qp_data"], eps, max_iter)
    cg = ca.CodeGenerator(f"{name}_casadi.c", {"with_header": True, "casadi_int": "long long int"})
    all_f = [solver, *funcs.values()]
    for f in all_f:
        cg.add(f)
    cg.generate(str(out) + "/")

    qd = funcs["qp_data"]
    sizes = {
        "NX": ocp.nx, "NU": ocp.nu, "KNOTS": ocp.knots, "HORIZON": ocp.horizon,
        "NZ": ocp.knots * ocp.nu, "NA": qd.sparsity_out("a").size1(),
        "NNZ_H": qd.sparsity_out("h").nnz(), "NNZ_A": qd.sparsity_out("a").nnz(),
        "SZ_ARG": max(f.sz_arg() for f in all_f), "SZ_RES": max(f.sz_res() for f in all_f),
        "SZ_IW": max(f.sz_iw() for f in all_f), "SZ_W": max(f.sz_w() for f in all_f),
    }
    info = Export(out, name, form, qp, linearization, ocp.nx, ocp.nu, ocp.knots, ocp.horizon, sizes["NA"])
    (out / f"{name}.h").write_text(_header(name, sizes, ocp, form, qp, linearization))
    (out / f"{name}.c").write_text(_wrapper(name, qp))
    (out / "main.c").write_text(_example(name, x0, goal, steps, ocp.dt))
    (out / "Makefile").write_text(_makefile(name, qp))
    (out / "README.md").write_text(_readme(info, ocp, eps, max_iter))
    return info


def build(out_dir, *, target: str = "lib") -> Path:
    """Run the folder's own Makefile (``make lib`` by default) and return the folder."""
    out = Path(out_dir)
    if not (out / "Makefile").is_file():
        raise ValueError(f"out_dir {str(out)!r} holds no exported Makefile")
    proc = subprocess.run(["make", "-C", str(out), target], capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"make {target} failed in {out}:\n{proc.stdout}\n{proc.stderr}")
    return out


# ---------------------------------------------------------------------------------------------------
# The step's mathematics in CasADi


def _condensed_functions(ocp: OCP, name: str, linearization: str) -> dict:
    """CasADi Functions of the condensed step: QP data, first input, fallback and the discrete model.

    qp_data(x, goal, plan, warm) -> (h, g, a, lba, uba, lbx, ubx) is CondensedQP.build about
    (x, ū) with ū = u_at(shift(plan), 0) when linearizing about the plan and ``warm``, else u_goal; S and v
    by the recursion
    S_k = A_d S_{k−1} + B_d (φ_k ⊗ I), v_k = A_d v_{k−1} + w_d, then P = Σ S_kᵀQ_kS_k + φᵀφ⊗R,
    q = Σ S_kᵀQ_k(v_k − x_goal) − φᵀ1 ⊗ R u_goal; knot bounds as simple bounds on z, state bounds as rows.
    """
    tr = CondensedQP(ocp)
    n, m, T, p = tr.n, tr.m, tr.T, tr.p
    phi = tr.phi
    I_m = np.eye(m)
    # Knots of the shifted plan, M U with M = pinv(φ) Sh φ (Parameterization.shift as a matrix).
    Sh = np.eye(T, k=1)
    Sh[-1, -1] = 1.0
    M = ocp.parameterization._fit @ Sh @ phi
    shift_z = ca.DM(ca.sparsify(ca.DM(np.kron(M, I_m))))
    E = [ca.sparsify(ca.DM(np.kron(phi[k:k + 1], I_m))) for k in range(T)]  # u_k = E_k z

    x, goal = ca.MX.sym("x", n), ca.MX.sym("goal", n)
    plan, warm = ca.MX.sym("plan", p * m), ca.MX.sym("warm")
    u_bar = (ca.if_else(warm, ca.mtimes(E[0], ca.mtimes(shift_z, plan)), ca.DM(ocp.u_goal), True)
             if linearization == "plan" else ca.MX(ca.DM(ocp.u_goal)))
    Ad, Bd, wd = ocp.affine()(x, u_bar)

    P = ca.MX(ca.DM(tr.R_knots))
    q = ca.MX(ca.DM(tr.q_knots(np.zeros(n))))
    S_rows, v_rows = [], []
    S, v = ca.mtimes(Bd, E[0]), ca.mtimes(Ad, x) + wd
    for k in range(T):
        if k:
            S = ca.mtimes(Ad, S) + ca.mtimes(Bd, E[k])
            v = ca.mtimes(Ad, v) + wd
        QS = ca.mtimes(ca.sparsify(ca.DM(tr.Qs[k])), S)
        P = P + ca.mtimes(S.T, QS)
        q = q + ca.mtimes(QS.T, v - goal)
        S_rows.append(S)
        v_rows.append(v)
    P = 0.5 * (P + P.T)
    if tr.x_rows.size:
        rows = [int(r) for r in tr.x_rows]
        A = ca.vertcat(*S_rows)[rows, :]
        vx = ca.vertcat(*v_rows)[rows]
        lba, uba = ca.DM(tr.x_lo) - vx, ca.DM(tr.x_hi) - vx
    else:
        A, lba, uba = ca.MX(0, p * m), ca.MX(0, 1), ca.MX(0, 1)
    lbx = ca.MX(ca.DM(np.tile(ocp.u_min, p)))
    ubx = ca.MX(ca.DM(np.tile(ocp.u_max, p)))
    qp_data = ca.Function(f"{name}_qp_data", [x, goal, plan, warm], [ca.densify(P), q, A, lba, uba, lbx, ubx],
                          ["x", "goal", "plan", "warm"], ["h", "g", "a", "lba", "uba", "lbx", "ubx"])

    z = ca.MX.sym("z", p * m)
    first_input = ca.Function(f"{name}_first_input", [z], [ca.mtimes(E[0], z)], ["z"], ["u"])

    # Controller.fallback: previous plan shifted one step (u_goal knots at a cold start), clipped to bounds.
    clip = lambda e, lo, hi: ca.fmin(ca.fmax(e, ca.DM(lo)), ca.DM(hi))  # noqa: E731
    knots = clip(ca.if_else(warm, ca.mtimes(shift_z, plan), ca.DM(np.tile(ocp.u_goal, p)), True),
                 np.tile(ocp.u_min, p), np.tile(ocp.u_max, p))
    fallback = ca.Function(f"{name}_fallback", [plan, warm],
                           [knots, clip(ca.mtimes(E[0], knots), ocp.u_min, ocp.u_max)],
                           ["plan", "has_plan"], ["knots", "u"])

    # Largest bound violation of a solution: CasADi's qrqp can report success at an infeasible point.
    a = ca.MX.sym("a", qp_data.sparsity_out("a"))
    lo_a, hi_a = ca.MX.sym("lba", A.shape[0]), ca.MX.sym("uba", A.shape[0])
    lo_x, hi_x = ca.MX.sym("lbx", p * m), ca.MX.sym("ubx", p * m)
    az = ca.mtimes(a, z)
    viol = ca.mmax(ca.vertcat(lo_x - z, z - hi_x, lo_a - az, az - hi_a, ca.DM(0.0)))
    violation = ca.Function(f"{name}_violation", [a, z, lo_a, hi_a, lo_x, hi_x], [viol],
                            ["a", "z", "lba", "uba", "lbx", "ubx"], ["violation"])

    xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
    model = ca.Function(f"{name}_model", [xs, us], [ocp.discrete()(xs, us)], ["x", "u"], ["x_next"])
    return {"qp_data": qp_data, "first_input": first_input, "fallback": fallback, "violation": violation,
            "model": model}


def _conic(qp: str, name: str, qp_data: ca.Function, eps: float, max_iter: int) -> ca.Function:
    """The CasADi conic solver for QP data with qp_data's sparsity, set up for code generation."""
    opts = {"error_on_fail": False, "print_problem": False}
    if qp == "qrqp":
        opts.update(print_iter=False, print_header=False, print_info=False, max_iter=max_iter,
                    constr_viol_tol=eps, dual_inf_tol=eps)
    elif qp == "osqp":
        opts["osqp"] = {"eps_abs": eps, "eps_rel": eps, "max_iter": max_iter, "verbose": False,
                        "polishing": True}
        opts.update(warm_start_primal=True, warm_start_dual=True)
        opts.pop("print_problem")
    else:
        opts["daqp"] = {"iter_limit": max_iter, "primal_tol": eps, "dual_tol": eps}
    structure = {"h": qp_data.sparsity_out("h"), "a": qp_data.sparsity_out("a")}
    return ca.conic(f"{name}_qp_solve", qp, structure, opts)


# ---------------------------------------------------------------------------------------------------
# The C around it


def _header(name: str, s: dict, ocp: OCP, form: str, qp: str, lin: str, feas_tol: float = FEAS_TOL) -> str:
    N = name.upper()
    defs = "\n".join(f"#define {N}_{k} {v}" for k, v in s.items())
    return f"""/* {name}.h — exported MPC step for {ocp!r}, {form} QP solved by CasADi's {qp}.
 *
 * Generated by ocpkit.export. One control step: affine model about (x, u_bar), condensed QP, QP solve,
 * first input. u_bar: {_UBAR[lin]}.
 *
 * Usage:
 *   static {name}_memory mem;              // caller-owned; holds all work space, the plan, warm start
 *   if ({name}_init(&mem)) abort();        // once
 *   int status;
 *   {name}_step(&mem, x, goal, u, &status);  // each control period; never allocates
 *
 * Arrays: x, goal: {N}_NX doubles; u: {N}_NU; knots: {N}_KNOTS x {N}_NU row-major (knot j, input i at
 * j*{N}_NU + i). Statuses (the same set as ocpkit.controller.STATUSES) are {N}_SUCCESS ... below. On any
 * failure the step returns the safe fallback input (previous plan advanced one step, clipped to the input
 * bounds) and the next step starts without warm start.
 */
#ifndef {N}_H
#define {N}_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {{
#endif

{defs}
#define {N}_NA1 ({N}_NA > 0 ? {N}_NA : 1)
/* Bound violation above which a reported solution is rejected (status {N}_EXCEPTION, solver return
   {N}_VIOLATED). */
#define {N}_FEAS_TOL {feas_tol!r}
#define {N}_VIOLATED {_VIOLATED}

enum {{ {N}_SUCCESS = 0, {N}_LIMITED = 1, {N}_INFEASIBLE = 2, {N}_NAN = 3, {N}_EXCEPTION = 4 }};

/* All memory of one controller instance. Treat as opaque. */
typedef struct {{
  const double* arg[{N}_SZ_ARG];
  double* res[{N}_SZ_RES];
  long long iw[{N}_SZ_IW > 0 ? {N}_SZ_IW : 1];
  double w[{N}_SZ_W > 0 ? {N}_SZ_W : 1];
  double h[{N}_NNZ_H], g[{N}_NZ], a[{N}_NNZ_A > 0 ? {N}_NNZ_A : 1], lba[{N}_NA1], uba[{N}_NA1];
  double lbx[{N}_NZ], ubx[{N}_NZ];
  double z[{N}_NZ], lam_x[{N}_NZ], lam_a[{N}_NA1];           /* last solution: warm start */
  double z_new[{N}_NZ], lam_x_new[{N}_NZ], lam_a_new[{N}_NA1];
  double plan[{N}_NZ];                                       /* knots of the current plan */
  double has_plan, warm;                                     /* 0 or 1 */
  int solver_mem, solver_rc;
}} {name}_memory;

/* Set up one instance (checks out the QP solver's memory): cold start. Returns 0 on success. */
int {name}_init({name}_memory* mem);
/* Forget the plan and warm start (cold start). */
void {name}_reset({name}_memory* mem);
/* One MPC step from state x towards goal state goal: writes u_out and *status, returns *status. */
int {name}_step({name}_memory* mem, const double* x, const double* goal, double* u_out, int* status);
/* Copy the current plan's knots (the solution, or the fallback plan after a failure). */
void {name}_knots(const {name}_memory* mem, double* knots);
/* The QP solver's raw return code of the last step (0: solved). */
int {name}_solver_return(const {name}_memory* mem);
/* One step of the generated discrete model x_next = F(x, u) the controller predicts with. */
int {name}_model_step({name}_memory* mem, const double* x, const double* u, double* x_next);
/* Release the QP solver's memory. */
void {name}_free({name}_memory* mem);
/* sizeof({name}_memory), and the sizes nx, nu, knots, horizon (for foreign-function loaders). */
size_t {name}_memory_size(void);
void {name}_dims(int* nx, int* nu, int* knots, int* horizon);

#ifdef __cplusplus
}}
#endif
#endif
"""


def _wrapper(name: str, qp: str) -> str:
    N = name.upper()
    # qrqp returns 4 when it finds no search direction (an infeasible or degenerate QP).
    infeasible = "rc == 4" if qp == "qrqp" else "0"
    return f"""/* {name}.c — the control step around the CasADi-generated functions in {name}_casadi.c. */
#include <math.h>
#include "{name}.h"
#include "{name}_casadi.h"

int {name}_init({name}_memory* m) {{
  {name}_qp_solve_incref();
  m->solver_mem = {name}_qp_solve_checkout();
  if (m->solver_mem < 0) return 1;
  {name}_reset(m);
  return 0;
}}

void {name}_reset({name}_memory* m) {{
  int i;
  for (i = 0; i < {N}_NZ; ++i) m->plan[i] = m->z[i] = m->lam_x[i] = 0;
  for (i = 0; i < {N}_NA1; ++i) m->lam_a[i] = 0;
  m->has_plan = m->warm = 0;
  m->solver_rc = 0;
}}

void {name}_free({name}_memory* m) {{
  if (m->solver_mem >= 0) {name}_qp_solve_release(m->solver_mem);
  {name}_qp_solve_decref();
  m->solver_mem = -1;
}}

static int all_finite(const double* v, int n) {{
  int i;
  for (i = 0; i < n; ++i) if (!isfinite(v[i])) return 0;
  return 1;
}}

static int any_nan(const double* v, int n) {{
  int i;
  for (i = 0; i < n; ++i) if (isnan(v[i])) return 1;
  return 0;
}}

static int any_above(const double* lo, const double* hi, int n) {{
  int i;
  for (i = 0; i < n; ++i) if (lo[i] > hi[i]) return 1;
  return 0;
}}

/* Controller.fallback: previous plan shifted, clipped; the next step starts cold. */
static int fallback({name}_memory* m, double* u_out, int status) {{
  m->arg[0] = m->plan; m->arg[1] = &m->has_plan;
  m->res[0] = m->z_new; m->res[1] = u_out;
  if ({name}_fallback(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return {N}_EXCEPTION;
  {{ int i; for (i = 0; i < {N}_NZ; ++i) m->plan[i] = m->z_new[i]; }}
  m->has_plan = 1;
  m->warm = 0;
  return status;
}}

int {name}_step({name}_memory* m, const double* x, const double* goal, double* u_out, int* status) {{
  int i, rc;
  double viol;
  /* QP data about (x, u_bar) */
  m->arg[0] = x; m->arg[1] = goal; m->arg[2] = m->plan; m->arg[3] = &m->has_plan;
  m->res[0] = m->h; m->res[1] = m->g; m->res[2] = m->a; m->res[3] = m->lba; m->res[4] = m->uba;
  m->res[5] = m->lbx; m->res[6] = m->ubx;
  m->solver_rc = 0;
  if ({name}_qp_data(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) {{
    *status = fallback(m, u_out, {N}_EXCEPTION);
    return *status;
  }}
  if (!all_finite(m->h, {N}_NNZ_H) || !all_finite(m->g, {N}_NZ) || !all_finite(m->a, {N}_NNZ_A)
      || any_nan(m->lba, {N}_NA) || any_nan(m->uba, {N}_NA) || any_nan(m->lbx, {N}_NZ)
      || any_nan(m->ubx, {N}_NZ)) {{
    *status = fallback(m, u_out, {N}_NAN);
    return *status;
  }}
  if (any_above(m->lba, m->uba, {N}_NA) || any_above(m->lbx, m->ubx, {N}_NZ)) {{
    *status = fallback(m, u_out, {N}_INFEASIBLE);
    return *status;
  }}
  /* QP solve, warm-started from the previous solution */
  m->arg[0] = m->h; m->arg[1] = m->g; m->arg[2] = m->a; m->arg[3] = m->lba; m->arg[4] = m->uba;
  m->arg[5] = m->lbx; m->arg[6] = m->ubx;
  m->arg[7] = m->warm ? m->z : 0; m->arg[8] = m->warm ? m->lam_x : 0; m->arg[9] = m->warm ? m->lam_a : 0;
  m->arg[10] = 0; m->arg[11] = 0;
  m->res[0] = m->z_new; m->res[1] = 0; m->res[2] = m->lam_a_new; m->res[3] = m->lam_x_new;
  rc = {name}_qp_solve(m->arg, m->res, (casadi_int*) m->iw, m->w, m->solver_mem);
  m->solver_rc = rc;
  if (!all_finite(m->z_new, {N}_NZ)) {{
    *status = fallback(m, u_out, {N}_NAN);
    return *status;
  }}
  if (rc) {{
    *status = fallback(m, u_out, ({infeasible}) ? {N}_INFEASIBLE : {N}_LIMITED);
    return *status;
  }}
  m->arg[0] = m->a; m->arg[1] = m->z_new; m->arg[2] = m->lba; m->arg[3] = m->uba; m->arg[4] = m->lbx;
  m->arg[5] = m->ubx; m->res[0] = &viol;
  if ({name}_violation(m->arg, m->res, (casadi_int*) m->iw, m->w, 0) || !(viol <= {N}_FEAS_TOL)) {{
    m->solver_rc = {N}_VIOLATED;
    *status = fallback(m, u_out, {N}_EXCEPTION);
    return *status;
  }}
  for (i = 0; i < {N}_NZ; ++i) {{ m->plan[i] = m->z[i] = m->z_new[i]; m->lam_x[i] = m->lam_x_new[i]; }}
  for (i = 0; i < {N}_NA; ++i) m->lam_a[i] = m->lam_a_new[i];
  m->has_plan = m->warm = 1;
  /* first input */
  m->arg[0] = m->plan; m->res[0] = u_out;
  if ({name}_first_input(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) {{
    *status = fallback(m, u_out, {N}_EXCEPTION);
    return *status;
  }}
  *status = {N}_SUCCESS;
  return *status;
}}

void {name}_knots(const {name}_memory* m, double* knots) {{
  int i;
  for (i = 0; i < {N}_NZ; ++i) knots[i] = m->plan[i];
}}

int {name}_solver_return(const {name}_memory* m) {{ return m->solver_rc; }}

int {name}_model_step({name}_memory* m, const double* x, const double* u, double* x_next) {{
  m->arg[0] = x; m->arg[1] = u; m->res[0] = x_next;
  return {name}_model(m->arg, m->res, (casadi_int*) m->iw, m->w, 0);
}}

size_t {name}_memory_size(void) {{ return sizeof({name}_memory); }}

void {name}_dims(int* nx, int* nu, int* knots, int* horizon) {{
  *nx = {N}_NX; *nu = {N}_NU; *knots = {N}_KNOTS; *horizon = {N}_HORIZON;
}}
"""


def _c_array(v) -> str:
    return "{" + ", ".join(repr(float(e)) for e in np.asarray(v, dtype=float).ravel()) + "}"


def _example(name: str, x0, goal, steps: int, dt: float) -> str:
    N = name.upper()
    return f"""/* main.c — closed loop of the exported MPC against the generated discrete model ({steps} steps). */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "{name}.h"

static double now(void) {{
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}}

static int cmp(const void* a, const void* b) {{
  double d = *(const double*) a - *(const double*) b;
  return (d > 0) - (d < 0);
}}

int main(void) {{
  static {name}_memory mem;
  double x[{N}_NX] = {_c_array(x0)};
  const double goal[{N}_NX] = {_c_array(goal)};
  double u[{N}_NU], x_next[{N}_NX], times[{steps}];
  int k, i, status, failures = 0;
  if ({name}_init(&mem)) {{ fprintf(stderr, "init failed\\n"); return 1; }}
  for (k = 0; k < {steps}; ++k) {{
    double t0 = now();
    {name}_step(&mem, x, goal, u, &status);
    times[k] = now() - t0;
    failures += status != {N}_SUCCESS;
    if ({name}_model_step(&mem, x, u, x_next)) {{ fprintf(stderr, "model failed\\n"); return 1; }}
    for (i = 0; i < {N}_NX; ++i) x[i] = x_next[i];
  }}
  qsort(times, {steps}, sizeof(double), cmp);
  printf("steps %d (%.3f s)  failures %d  median step %.1f us\\n", {steps}, {steps} * {dt!r}, failures,
         1e6 * times[{steps} / 2]);
  printf("x_final");
  for (i = 0; i < {N}_NX; ++i) printf(" %.6f", x[i]);
  printf("\\ngoal   ");
  for (i = 0; i < {N}_NX; ++i) printf(" %.6f", goal[i]);
  printf("\\n");
  {name}_free(&mem);
  return failures == {steps};
}}
"""


def _makefile(name: str, qp: str) -> str:
    casadi = f"CASADI_DIR ?= {_CASADI_DIR}\nCPPFLAGS += -I$(CASADI_DIR)/include\n" if _LIBS[qp] else ""
    return f"""# Builds the exported MPC step: lib{name}.so (for ocpkit.export.ExportedMPC) and the example.
CC ?= cc
CFLAGS ?= -O2 -fPIC
{casadi}LDLIBS = {_LIBS[qp]} -lm
SRC = {name}.c {name}_casadi.c

all: lib example

lib: lib{name}.so

lib{name}.so: $(SRC) {name}.h {name}_casadi.h
\t$(CC) $(CPPFLAGS) $(CFLAGS) -shared -o $@ $(SRC) $(LDLIBS)

example: $(SRC) main.c {name}.h {name}_casadi.h
\t$(CC) $(CPPFLAGS) $(CFLAGS) -o $@ main.c $(SRC) $(LDLIBS)

run: example
\t./example

clean:
\trm -f lib{name}.so example

.PHONY: all lib run clean
"""


def _readme(info: Export, ocp: OCP, eps: float, max_iter: int) -> str:
    n = info.name
    deps = ("none: the sources are self-contained C (C99, libm)." if info.qp == "qrqp" else
            f"CasADi's shipped {info.qp.upper()} headers and static library: `CASADI_DIR` in the Makefile "
            f"points at the casadi Python package (`python -c 'import casadi, os; "
            f"print(os.path.dirname(casadi.__file__))'`); override it with `make CASADI_DIR=...`.")
    return f"""# Exported MPC step `{n}`

Generated by `ocpkit.export` for `{ocp!r}`: {info.form} QP ({info.knots} knots x {info.nu} inputs,
{info.n_constraints} state-bound rows), horizon {info.horizon}, dt = {ocp.dt} s, solved by CasADi's
`{info.qp}` (tolerance {eps:g}, at most {max_iter} iterations).

Each `{n}_step` linearizes the model about the current state x and u_bar, {_UBAR[info.linearization]},
builds the condensed QP (paper Section V-B/V-E), solves it and returns the first input. A solution
that violates the bounds by more than {FEAS_TOL:g} counts as a failure. On a failure it returns the previous
plan advanced one step, clipped to the input bounds, and the next step starts cold.
{_SOLVER_NOTE[info.qp]}

## Files

- `{n}.h` — the API (documented in the header): `{n}_init`, `{n}_step`, `{n}_reset`, `{n}_knots`,
  `{n}_model_step`, `{n}_free`; statuses `{n.upper()}_SUCCESS`, `_LIMITED`, `_INFEASIBLE`, `_NAN`,
  `_EXCEPTION`.
- `{n}.c` — the step around the generated functions; `{n}_casadi.c/.h` — CasADi-generated QP data,
  QP solver, first input, fallback and discrete model.
- `main.c` — a closed loop against the generated discrete model; `Makefile`.

## Build

    make          # lib{n}.so and ./example
    make run      # runs the closed loop, prints median step time and the final state

Dependencies: {deps}

In Python: `ocpkit.export.ExportedMPC(ocp, "{info.out_dir.name}")` loads `lib{n}.so` as a Controller.
"""


# ---------------------------------------------------------------------------------------------------
# Loading the built library back into Python


class ExportedMPC(Controller):
    """The compiled exported step (``lib<name>.so`` in ``out_dir``) as a Controller, through ctypes.

    Statuses map one to one onto ocpkit's; on failure the library already returns the fallback input and
    plan, which equal :meth:`Controller.fallback`. ``times["solve"]`` is the whole C step.
    """

    def __init__(self, ocp: OCP, out_dir, *, name: str = "mpc", raise_on_fail: bool = False):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        lib_path = Path(out_dir) / f"lib{name}.so"
        if not lib_path.is_file():
            raise ValueError(f"out_dir {str(out_dir)!r} has no lib{name}.so; run export() and build() first")
        lib = ctypes.CDLL(str(lib_path.resolve()))
        dims = [ctypes.c_int() for _ in range(4)]
        getattr(lib, f"{name}_dims")(*map(ctypes.byref, dims))
        dims = tuple(d.value for d in dims)
        if dims != (ocp.nx, ocp.nu, ocp.knots, ocp.horizon):
            raise ValueError(f"library {lib_path} was exported for (nx, nu, knots, horizon) = {dims}, "
                             f"ocp has {(ocp.nx, ocp.nu, ocp.knots, ocp.horizon)}")
        dbl = np.ctypeslib.ndpointer(dtype=np.float64, flags="C_CONTIGUOUS")
        size = getattr(lib, f"{name}_memory_size")
        size.restype = ctypes.c_size_t
        self._mem = ctypes.create_string_buffer(size())
        self._step = getattr(lib, f"{name}_step")
        self._step.argtypes = [ctypes.c_void_p] * 5
        self._step.restype = ctypes.c_int
        self._knots = getattr(lib, f"{name}_knots")
        self._knots.argtypes = [ctypes.c_void_p, dbl]
        self._model = getattr(lib, f"{name}_model_step")
        self._model.argtypes = [ctypes.c_void_p, dbl, dbl, dbl]
        self._rc = getattr(lib, f"{name}_solver_return")
        self._lib, self.name, self.out_dir = lib, name, Path(out_dir)
        if getattr(lib, f"{name}_init")(self._mem):
            raise RuntimeError(f"{name}_init failed: no QP solver memory left in {lib_path}")
        self._status = ctypes.c_int()
        self._status_ptr = ctypes.addressof(self._status)
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    def __repr__(self):
        return f"ExportedMPC({str(self.out_dir / ('lib' + self.name + '.so'))!r}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        getattr(self._lib, f"{self.name}_reset")(self._mem)

    def model_step(self, x, u) -> np.ndarray:
        """x⁺ from the library's generated discrete model (the model the controller predicts with)."""
        x = self.ocp.check_state(x, "x")
        u = array(u, "u", (self.ocp.nu,))
        out = np.empty(self.ocp.nx)
        if self._model(self._mem, x, u, out):
            raise RuntimeError("generated discrete model failed")
        return out

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        u = np.empty(self.ocp.nu)
        knots = np.empty(self.ocp.knots * self.ocp.nu)
        x, goal = np.ascontiguousarray(x), np.ascontiguousarray(goal)
        args = (self._mem, x.ctypes.data, goal.ctypes.data, u.ctypes.data, self._status_ptr)
        t0 = time.perf_counter()
        self._step(*args)
        elapsed = time.perf_counter() - t0
        self._knots(self._mem, knots)
        status = STATUSES[self._status.value]
        rc = self._rc(self._mem)
        raw = ("solved point violates the bounds" if rc == _VIOLATED else f"{self.name}_qp_solve returned {rc}")
        return Solution(u=u, knots=knots.reshape(self.ocp.knots, self.ocp.nu), status=status, raw_status=raw,
                        times={"model": 0.0, "build": 0.0, "solve": elapsed}, fallback=status != SUCCESS)


def export_problem(problem_name: str, form: str = "condensed", knots: int | None = 5, horizon: int | None = 100,
                   qp: str = "daqp", out_dir="export", *, seed: int = 0, steps: int = 100) -> Export:
    """Export a problem by spec (``ocpkit.problems.make``: a registered name, ``module:Name`` or ``file.py:Name``)
    with the example closed loop from ``sample(seed)``."""
    from ocpkit.problems import make

    problem = make(problem_name)
    ocp = problem.ocp(knots=knots, horizon=horizon)
    if getattr(ocp, "goal_input", None) is not None:
        raise ValueError(f"{problem_name}: its input goal depends on the goal nonlinearly ({ocp.goal_input.name()}); "
                         "the exported C step supports a constant input goal only (for a URDF robot: "
                         "gravity_compensation=False)")
    x0, goal = problem.sample(seed)
    return export(ocp, out_dir, form=form, qp=qp, x0=x0, goal=goal, steps=steps)

