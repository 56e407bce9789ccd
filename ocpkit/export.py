"""Export the MPC control step as generated C, and load it back as a Controller.

One control step of the paper's condensed convex MPC (Section V-B, V-E) — affine model about (x, ū),
condensed QP  min ½ zᵀPz + qᵀz  s.t. knot and state bounds, QP solve, first input — from the same
description every Python solver uses. ū is the input goal u_g = u_goal + K x_goal (+ h(x_goal), a problem's
goal input such as gravity compensation, generated into the C) (``linearization="goal"``)
or the input the previous plan expects now, ``u_at(shift(plan), 0)`` (``"plan"``), exactly as
:class:`~ocpkit.solvers.qp.LinearMPC` does, so the exported step reproduces LinearMPC's QP and solution.

The generated code stays small at robot scale (its size does not grow with the horizon, and with the state
dimension only through the model):

* ``<name>_casadi.c`` — CasADi code generation of the continuous dynamics and their sparse Jacobians
  f, ∂f/∂x, ∂f/∂u **once** (``<name>_fjac``; a linear model: its constant discrete model), the discrete
  model for the example, and the QP solver.
* ``<name>.c`` — the hand-written step. The affine model: RK4 calling ``<name>_fjac`` four times per substep,
  its sensitivities propagated by sparse-times-dense products (the exact chain rule of ``ocp.affine()``).
  The condensing mirrors :class:`~ocpkit.transcription.CondensedQP.build`: Λ_s = [A_d^s E_s F_s e_s],
  Γ_L = Σ_{s≤L} Λ_sᵀQΛ_s and per piece of the parameterization Rᵀ Γ_L R. Γ_L is built in O(log L) products
  (Λ_s = C Â^s for the piece's augmented state [x; v; d; 1], so Γ_2s = Γ_s + (Â^s)ᵀ Γ_s Â^s, Λ_2s = Λ_s Â^s),
  and every product is one small GEMM kernel whose tiles of C stay in vector registers (GCC/Clang vector
  extensions: SSE2, plus AVX2+FMA chosen at run time on CPUs that have them; ``make SIMD=sse2|none``).
  Constants (Q^½, R, the basis' pieces, bounds, the Γ schedule) are static arrays.
* With a task (:mod:`ocpkit.task`: cost terms such as a frame's position, no obstacles) its stage and terminal
  residuals and their dense Jacobians are generated per stage (``<name>_task_stage``, ``<name>_task_terminal``),
  and the step adds their Gauss–Newton model about the plan to the condensed QP as
  :class:`ocpkit.transcription._TaskRows` does (``task_terms`` in ``<name>.c``: the plan's states and ∂r/∂x S
  piece by piece, ∂r/∂x S as (∂r/∂x Λ_s) R). The step's goal is then the whole goal vector [x_goal; targets]
  (``ocp.goal(...)``, ``NG`` entries). A task with obstacles is refused (its linearized obstacle rows are not in
  the C step).

All memory of one controller lives in a caller-owned struct (``<name>_memory``): several instances run in one
process, each with its own QP-solver memory slot (``MAX_INSTANCES`` in the Makefile, 16 by default).

QP solvers (CasADi conic plugins with code generation in CasADi 3.8):

* ``qrqp`` — CasADi's own active-set solver, generated as plain C: the folder needs nothing else. It can
  report success at a point outside the bounds (seen on nlink:3, T = 50).
* ``daqp`` (default) — links CasADi's shipped ``libdaqpstat.a`` (headers under ``casadi/include``); DAQP's setup
  runs inside each step and allocates there. CasADi 3.8's generated call ignores a failed set-up (DAQP's
  factorization refusing a Hessian that is not positive definite) and then reads an uninitialized success flag:
  in some processes the step reported success with the previous, zero answer. :func:`_fix_daqp_setup` makes the
  generated function return the set-up's flag.

Whatever the solver says, a "solved" answer is accepted only if its KKT certificate holds (:mod:`ocpkit.certificate`,
computed in C: stationarity, primal feasibility, complementarity and dual sign of the answer and its multipliers).
* ``osqp`` — links CasADi's shipped ``libosqpstatic.a``; set up once at init, updated each step; quiet
  (verbose and polishing off unless ``polish=True``).
* ``hpipm`` — refused: CasADi's HPIPM interface needs a stage-wise OCP structure, which the condensed
  QP over knots does not have.
"""
from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from string import Template

import casadi as ca
import numpy as np

from ocpkit._checks import array, choice, integer, positive
from ocpkit.certificate import TESTS, Certificate
from ocpkit.certificate import TOL as CERT_TOL
from ocpkit.controller import EXCEPTION, INFEASIBLE, LIMITED, STATUSES, SUCCESS, Controller, Solution
from ocpkit.ocp import OCP
from ocpkit.problem import check_dynamics
from ocpkit.transcription import ROUNDING_MARGIN, CondensedQP

FORMS = ("condensed", "sparse")
QP_SOLVERS = ("qrqp", "daqp", "osqp", "hpipm")
LINEARIZATIONS = ("goal", "plan", "trajectory")
# (form, qp) pairs whose CasADi code generation is wired here; others get a ValueError saying why.
SUPPORTED = {("condensed", "qrqp"), ("condensed", "daqp"), ("condensed", "osqp")}
_UNSUPPORTED_WHY = {
    "hpipm": "CasADi's HPIPM interface needs a stage-wise OCP structure (per-stage x_k, u_k), which a QP "
             "over parameterization knots does not have",
    "sparse": "only the condensed (small-matrix) form is exported; the sparse form is solved in Python by "
              "LinearMPC(form='sparse')",
}
# The C step's solver return for a "solved" answer whose certificate failed: _CERT_CODE + the test's index in
# ocpkit.certificate.TESTS.
_CERT_CODE = 9001
_ILL_CONDITIONED = 9000  # a QP refused before its solve: Hessian ill-conditioned (QP.not_definite)
MAX_INSTANCES = 16  # QP-solver memory slots per loaded library (CASADI_MAX_NUM_THREADS); a Makefile variable
OPT_FLAGS = "-O2"  # the Makefile's OPT default (generated model and QP solver)
OPT_STEP = "-O3"  # the Makefile's OPT_STEP default (the condensing loops: -O3 vectorizes them)
_SOLVER_NOTE = {
    "qrqp": "qrqp is warm-started from the previous solution; `step` never allocates.",
    "daqp": "CasADi's DAQP code starts DAQP cold and runs its setup, which allocates, inside every step.",
    "osqp": "OSQP is set up (allocating) once in `init` and warm-started; `step` does not allocate.",
}
_UBAR = {"goal": "the input goal u_g = u_goal + K goal (+ the problem's goal input h(goal))",
         "trajectory": "per stage k, the previous plan shifted one step (its inputs and predicted states; a "
                       "rollout of the model at a cold start): real-time iteration",
         "plan": "the input the previous plan expects now (the input goal at a cold start)"}
_CASADI_DIR = Path(ca.__file__).resolve().parent
_LIBS = {"qrqp": "", "daqp": "$(CASADI_DIR)/libdaqpstat.a", "osqp": "$(CASADI_DIR)/libosqpstatic.a"}


class BuildError(RuntimeError):
    """The exported folder could not be built: a tool is missing or ``make`` failed (message is one line
    naming the tool, or make's output)."""


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

    @property
    def c_bytes(self) -> int:
        """Bytes of generated C (sources and headers, the example included)."""
        return sum(p.stat().st_size for p in self.out_dir.iterdir() if p.suffix in (".c", ".h"))


def _check_out_dir(out: Path, force: bool) -> None:
    """``out`` must be absent or an empty folder unless ``force``: a user's files are never overwritten silently.

    ``out`` itself must not be a symbolic link (links above it are ordinary paths) and, with ``force``, must hold
    none: the export and ``make`` replace files by name, and a link there would lead them elsewhere."""
    if out.is_symlink():
        target = Path(os.path.realpath(out))
        kind = "a folder" if target.is_dir() else "a file" if target.exists() else "nothing (a dangling link)"
        raise ValueError(f"out_dir {str(out)!r} is a symbolic link to {target} ({kind}); the export replaces the "
                         f"files of the folder it names and never follows a link there: to export into {target}, "
                         f"name it (--out {target})")
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir {str(out)!r} is a file, not a folder; name a new or empty folder")
    if out.is_dir():
        _refuse_links(out)
    if out.is_dir() and not force:
        held = sorted(p.name for p in out.iterdir())
        if held:
            shown = ", ".join(held[:5]) + (f" and {len(held) - 5} more" if len(held) > 5 else "")
            raise ValueError(f"out_dir {str(out)!r} is not empty (holds {shown}); name a new or empty folder, "
                             "or pass force=True (--force) to overwrite the exported files in it")


def _refuse_links(out: Path) -> None:
    """A ValueError naming the symbolic links directly in ``out``: nothing is exported or built through a link."""
    links = sorted(p for p in out.iterdir() if p.is_symlink())
    if links:
        shown = ", ".join(f"{p.name} -> {os.readlink(p)}" for p in links[:3])
        more = f" and {len(links) - 3} more" if len(links) > 3 else ""
        raise ValueError(f"out_dir {str(out)!r} holds symbolic links ({shown}{more}); ocpkit never writes through "
                         "a link, even with --force: remove them or name a new folder")


def _umask() -> int:
    """This process' umask, read without changing it (os.umask would, for every thread): Linux /proc, else 022."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _place(source: Path, target: Path) -> None:
    """Move the new file ``source`` onto ``target`` (same folder or file system) in one rename: an existing
    ``target`` — a file, a hard link, a symbolic link — is replaced, never opened or written."""
    os.chmod(source, 0o666 & ~_umask())
    os.replace(source, target)


def _write(path: Path, text: str) -> None:
    """Write ``text`` as the file ``path`` by creating a new file beside it and renaming it into place."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        _place(Path(tmp), path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export(ocp: OCP, out_dir, *, form: str = "condensed", qp: str = "daqp", name: str = "mpc",
           eps: float = 1e-9, max_iter: int = 1000, linearization: str = "goal", x0=None, goal=None,
           steps: int = 100, force: bool = False, polish: bool = False, iterations: int = 1,
           tol: float = 0.0) -> Export:
    """Write C sources, header, Makefile, example ``main.c`` and README for the MPC step of ``ocp``.

    ``out_dir`` must be absent or empty unless ``force`` (then the exported files in it are replaced: each is
    written as a new file renamed into place); it must not be a symbolic link nor hold one.
    ``eps`` is the QP solver's tolerance, ``max_iter`` its iteration limit, ``polish`` OSQP's solution
    polishing; ``linearization`` "goal" linearizes about (x, u_g), "plan" about (x, ū) as LinearMPC's option
    of that name, "trajectory" stage by stage along the shifted plan: the real-time iteration of
    :class:`~ocpkit.solvers.nlp.RealTimeIteration`, ``iterations`` Gauss–Newton steps per control step, fewer
    where one moves the plan (knots and predicted states, max norm) by at most ``tol``; ``x0``, ``goal`` (with
    a task the goal vector [x_goal; targets] of ``ocp.goal``) and ``steps`` set the closed loop the example runs
    against the generated discrete model (where given, the dynamics must be finite there: else a DynamicsError
    names them, before any file is written). A task's cost terms are exported; a task with obstacles is refused
    (ValueError)."""
    if not isinstance(ocp, OCP):
        raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
    choice(form, FORMS, "form")
    choice(qp, QP_SOLVERS, "qp")
    if (form, qp) not in SUPPORTED:
        why = _UNSUPPORTED_WHY["sparse" if form == "sparse" else qp]
        raise ValueError(f"qp={qp!r} with form={form!r} cannot be exported: {why}; "
                         f"supported: {sorted(SUPPORTED)}")
    choice(linearization, LINEARIZATIONS, "linearization")
    iterations = integer(iterations, "iterations", 1)
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    if linearization != "trajectory" and (iterations != 1 or tol != 0):
        raise ValueError(f"iterations and tol are options of linearization 'trajectory', not {linearization!r}")
    tf = ocp.task_functions
    if tf is not None and linearization == "trajectory":
        raise ValueError(f"an OCP with a task (terms {ocp.terms[2:]}) cannot be exported with linearization "
                         "'trajectory': the C step's task terms are linearized about the goal's model; use "
                         "linearization 'goal' or 'plan', or the Python step")
    if tf is not None and tf.pairs:
        raise ValueError(f"an OCP with obstacles (task terms {ocp.terms[2:]}, {tf.pairs} robot-sphere/obstacle "
                         "pairs) cannot be exported: the C step has the task's cost terms but not its linearized "
                         "obstacle rows; use LinearMPC's Python step, or a task without obstacles")
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    eps = positive(eps, "eps")
    max_iter = integer(max_iter, "max_iter", 1)
    steps = integer(steps, "steps", 1)
    given = {"the example's start x0": x0 is not None, "the example's goal": goal is not None}
    x0 = np.zeros(ocp.nx) if x0 is None else ocp.check_state(x0, "x0")
    # With a task the goal is [x_goal; targets] (ocp.goal): the step's goal input has ng entries.
    ng = ocp.ng if tf is not None else ocp.nx
    if goal is None:
        goal = np.zeros(ng)
    else:
        goal = ocp.check_goal(goal) if tf is not None else ocp.check_state(goal, "goal")
    for x, label in zip((x0, goal[:ocp.nx]), given):
        if given[label]:  # where the example's closed loop runs: NaN dynamics there are named before any work
            check_dynamics(ocp.model, x, ocp.input_goal(goal[:ocp.nx]), context=label)
    out = Path(out_dir)
    _check_out_dir(out, bool(force))
    out.mkdir(parents=True, exist_ok=True)

    # The joint-space condensing's data; the task's terms are generated below (its Python rows not needed).
    tr = CondensedQP(ocp, task=False)
    na = tr.x_rows.size
    lin, model, jac = _model_functions(ocp, name)
    solver = _conic(qp, name, tr.nz, na, eps, max_iter, polish)
    cg = ca.CodeGenerator(f"{name}_casadi.c", {"with_header": True, "casadi_int": "long long int"})
    all_f = [solver, lin, model]
    if getattr(ocp, "goal_input", None) is not None:  # h(x_goal) of u_g = u_goal + K x_goal + h(x_goal)
        xg = ca.MX.sym("x_goal", ocp.nx)
        all_f.append(ca.Function(f"{name}_goal_input", [xg], [ocp.goal_input(xg)], ["x_goal"], ["u"]))
    task = _task_functions(tf, name) if tf is not None else None
    if task is not None:
        all_f += task
    for f in all_f:
        cg.add(f)
    # CasADi opens its files by name: it writes into a private scratch folder, whose files are then renamed into
    # ``out`` (a link or hard link already there is replaced, never written through).
    scratch = Path(tempfile.mkdtemp(dir=out, prefix=".ocpkit-gen-"))
    try:
        cg.generate(str(scratch) + "/")
        if qp == "daqp":
            _fix_daqp_setup(scratch / f"{name}_casadi.c")
        for path in sorted(scratch.iterdir()):
            _place(path, out / path.name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    sizes = {
        "NX": ocp.nx, "NU": ocp.nu, "KNOTS": ocp.knots, "HORIZON": ocp.horizon, "NZ": tr.nz, "NA": na,
        "NL": ocp.nx + 2 * ocp.nu + 1, "LMAX": max(tr._lengths), "NLEN": len(tr._lengths),
        "NB": int(np.count_nonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max))),
        "NNZ_FX": len(jac[0][0]) if jac else 0, "NNZ_FU": len(jac[1][0]) if jac else 0,
        "SZ_ARG": max(f.sz_arg() for f in all_f), "SZ_RES": max(f.sz_res() for f in all_f),
        "SZ_IW": max(f.sz_iw() for f in all_f), "SZ_W": max(f.sz_w() for f in all_f),
    }
    if task is not None:
        sizes.update(NG=ng, NRS=tf.stage_weight.size, NRT=tf.terminal_weight.size)
    info = Export(out, name, form, qp, linearization, ocp.nx, ocp.nu, ocp.knots, ocp.horizon, na)
    _write(out / f"{name}.h", _header(name, sizes, ocp, form, qp, linearization))
    _write(out / f"{name}.c", _wrapper(name, qp, linearization, tr, jac, tf, iterations, float(tol)))
    _write(out / "main.c", _example(name, x0, goal, steps, ocp.dt, task=tf is not None))
    _write(out / "Makefile", _makefile(name, qp))
    _write(out / "README.md", _readme(info, ocp, eps, max_iter))
    return info


def check_tools() -> None:
    """Raise :class:`BuildError` naming the first of the C compiler (``$CC`` or ``cc``) and ``make`` not on PATH."""
    cc = os.environ.get("CC", "cc").split()[0] if os.environ.get("CC", "").strip() else "cc"
    for tool, why in ((cc, "a C compiler (install gcc or clang, or set CC)"), ("make", "GNU make")):
        if shutil.which(tool) is None:
            raise BuildError(f"`{tool}` not found on PATH: building the exported C step needs {why}")


def build(out_dir, *, target: str = "lib", jobs: int = 2) -> Path:
    """Run the folder's own Makefile (``make lib`` by default, ``jobs`` compiles in parallel); return the folder.

    Raises ValueError if the folder holds no exported Makefile or holds a symbolic link (make would write through
    it), :class:`BuildError` if ``cc`` or ``make`` is missing or the build fails.
    """
    out = Path(out_dir)
    if not (out / "Makefile").is_file():
        raise ValueError(f"out_dir {str(out)!r} holds no exported Makefile")
    _refuse_links(out)  # make writes its objects and library by name
    check_tools()
    proc = subprocess.run(["make", "-s", "-C", str(out), f"-j{integer(jobs, 'jobs', 1)}", target],
                          capture_output=True, text=True)
    if proc.returncode:
        raise BuildError(f"make {target} failed in {out}:\n{proc.stdout}\n{proc.stderr}")
    return out


# ---------------------------------------------------------------------------------------------------
# The model in CasADi: f and its Jacobians generated once, RK4 and its sensitivities as matrix products


def _model_functions(ocp: OCP, name: str):
    """(linearization, model, jacobian sparsity): the Function the C step linearizes with, (x, u) -> x⁺ of
    ``ocp.discrete()``, and for a nonlinear model the row and column indices of ∂f/∂x and ∂f/∂u.

    A linear model's discretization is a constant (matrix exponential): ``<name>_affine`` (x, ū) -> (A_d, B_d,
    w_d) is small. A nonlinear one is RK4 over ``substeps``: ``<name>_fjac`` (x, u) -> (f, ∂f/∂x, ∂f/∂u) is
    generated once (:attr:`Model.jacobian`), its Jacobians kept sparse, and the C step propagates the
    sensitivities through the four stages (dk/dx = J_x(x_s, u) dx_s/dx, …; integrator "euler": its one step) —
    the forward sensitivities ``ocp.affine()`` propagates with dense products, here sparse-times-dense.
    """
    model = ocp.model
    if model.linear:
        xs, us = ca.SX.sym("x", ocp.nx), ca.SX.sym("u", ocp.nu)
        Ad, Bd, wd = model.affine(ocp.dt, ocp.substeps)(xs, us)
        step = model.discrete(ocp.dt, ocp.substeps)(xs, us)
        return (ca.Function(f"{name}_affine", [xs, us], [ca.densify(Ad), ca.densify(Bd), ca.densify(wd)],
                            ["x", "u"], ["Ad", "Bd", "wd"]),
                ca.Function(f"{name}_model", [xs, us], [step], ["x", "u"], ["x_next"]), None)
    x, u, jac = model.x, model.u, model.jacobian
    fj = ca.Function(f"{name}_fjac", [x, u], jac(x, u), ["x", "u"], ["xdot", "fx", "fu"])
    X, U = ca.MX.sym("x", ocp.nx), ca.MX.sym("u", ocp.nu)
    if ocp.integrator == "rk4":  # the example's discrete model: RK4 calling f (generated once), not f inlined 4 times
        f = ca.Function(f"{name}_f", [x, u], [model.xdot], ["x", "u"], ["xdot"])
        h = ocp.dt / ocp.substeps
        xm = X
        for _ in range(ocp.substeps):
            q1 = f(xm, U)
            q2 = f(xm + h / 2 * q1, U)
            q3 = f(xm + h / 2 * q2, U)
            q4 = f(xm + h * q3, U)
            xm = xm + h / 6 * (q1 + 2 * q2 + 2 * q3 + q4)
    else:
        xm = ocp.discrete()(X, U)
    step = ca.Function(f"{name}_model", [X, U], [xm], ["x", "u"], ["x_next"])
    return fj, step, (jac.sparsity_out(1).get_triplet(), jac.sparsity_out(2).get_triplet())


def _task_functions(tf, name: str) -> list:
    """The task's residuals for the C step (``tf``: :class:`ocpkit.task.CompiledTask`, no obstacles), generated
    per stage: ``<name>_task_stage`` (x, u, targets) -> (r, ∂r/∂x, ∂r/∂u) and ``<name>_task_terminal``
    (x, targets) -> (r, ∂r/∂x), the Jacobians dense (column-major); a part without terms is left out."""
    x, u, g = ca.SX.sym("x", tf.nx), ca.SX.sym("u", tf.nu), ca.SX.sym("g", tf.size)
    out = []
    if tf.stage_weight.size:
        r, rx, ru = tf.stage_residual(x, u, g)
        out.append(ca.Function(f"{name}_task_stage", [x, u, g], [r, ca.densify(rx), ca.densify(ru)],
                               ["x", "u", "g"], ["r", "r_x", "r_u"]))
    if tf.terminal_weight.size:
        r, rx = tf.terminal_residual(x, g)
        out.append(ca.Function(f"{name}_task_terminal", [x, g], [r, ca.densify(rx)], ["x", "g"], ["r", "r_x"]))
    return out


# DAQP's exit flags (daqp/include/constants.h): their names and ocpkit statuses, for the Python step
# (solvers/qp.py) and the C step's failures alike.
DAQP_EXIT = {1: ("optimal", SUCCESS), 2: ("soft optimal", SUCCESS), -1: ("infeasible", INFEASIBLE),
             -2: ("cycling", LIMITED), -3: ("unbounded", INFEASIBLE), -4: ("iteration limit", LIMITED),
             -5: ("nonconvex", EXCEPTION), -6: ("overdetermined initial working set", EXCEPTION),
             -7: ("time limit", LIMITED)}
# CasADi 3.8's generated DAQP call: casadi_daqp_solve returns 1 after a failed set-up, which its caller ignores
# before reading d_qp.success, never set on that path. Fixed, the generated function returns DAQP's exit flag on
# any failure (set-up or solve) and 0 on success.
_DAQP_FIX = (("  if (flag<0) return 1;\n", "  if (flag<0) { d->return_status = flag; return 1; }\n"),
             ("  casadi_daqp_solve(d, arg, res, iw, w);\n  if (!d_qp.success) {\n    return -1;\n  }\n",
              "  d_qp.success = 0;\n  casadi_daqp_solve(d, arg, res, iw, w);\n"
              "  if (!d_qp.success) return d->return_status == 1 ? -1 : d->return_status;\n"))


def daqp_exit_name(flag: int) -> str:
    """DAQP's exit flag in words, as a raw status."""
    name = DAQP_EXIT[flag][0] if flag in DAQP_EXIT else f"exit flag {flag}"
    return f"DAQP {name}" + (" (Hessian not positive definite)" if flag == -5 else "")


def _fix_daqp_setup(path: Path) -> None:
    """Make CasADi's generated DAQP function report a failed set-up and DAQP's exit flag (see the module
    docstring). Where CasADi generates other code the file is left as it is: the C step's certificate still refuses
    a stale answer, and the test suite notices (tests/test_certificate.py)."""
    text = path.read_text()
    if all(text.count(old) == 1 for old, _ in _DAQP_FIX):
        for old, new in _DAQP_FIX:
            text = text.replace(old, new)
        _write(path, text)


def _gram_schedule(lengths) -> list[int]:
    """Operations that build Γ_L for each piece length L from Γ_1 (codes of the C step's ``GRAM_OPS``).

    ``DOUBLE`` takes Γ_s, Λ_s to Γ_2s = Γ_s + (Â^s)ᵀ Γ_s Â^s, Λ_2s = Λ_s Â^s; ``INC`` to Γ_s+1 = Γ_s + W_s+1ᵀW_s+1;
    ``RESET`` restarts from s = 1; ``SAVE + i`` stores Γ_L, Λ_L as length i. L is reached by its binary digits
    (a doubling per digit, an increment per one; the first doubling, from s = 1, is an increment) or by
    increments from the length before, whichever costs less (a doubling costs about 2.5 increments at robot
    scale).
    """
    ops, s = [], 1
    for i, L in enumerate(lengths):
        bits = bin(L)[3:]
        chain = 2.5 * len(bits) - 1.5 * bool(bits) + bits.count("1")
        if L - s > chain:
            ops.append(_RESET)
            for k, bit in enumerate(bits):
                ops.append(_INC if k == 0 else _DOUBLE)  # from s = 1 a stage costs half a doubling
                if bit == "1":
                    ops.append(_INC)
        else:
            ops += [_INC] * (L - s)
        s = L
        ops.append(_SAVE + i)
    return ops


_DOUBLE, _INC, _RESET, _SAVE = 1, 2, 3, 10


def _conic(qp: str, name: str, nz: int, na: int, eps: float, max_iter: int, polish: bool) -> ca.Function:
    """The CasADi conic solver for a dense H (nz × nz) and dense A (na × nz), set up for code generation."""
    opts = {"error_on_fail": False, "print_problem": False}
    if qp == "qrqp":
        opts.update(print_iter=False, print_header=False, print_info=False, max_iter=max_iter,
                    constr_viol_tol=eps, dual_inf_tol=eps)
    elif qp == "osqp":
        opts["osqp"] = {"eps_abs": eps, "eps_rel": eps, "max_iter": max_iter, "verbose": False,
                        "polishing": bool(polish)}
        opts.update(warm_start_primal=True, warm_start_dual=True)
        opts.pop("print_problem")
    else:
        opts["daqp"] = {"iter_limit": max_iter, "primal_tol": eps, "dual_tol": eps}
    structure = {"h": ca.Sparsity.dense(nz, nz), "a": ca.Sparsity.dense(na, nz)}
    return ca.conic(f"{name}_qp_solve", qp, structure, opts)


# ---------------------------------------------------------------------------------------------------
# The C around it

def _header(name: str, s: dict, ocp: OCP, form: str, qp: str, lin: str, cert_tol: float = CERT_TOL) -> str:
    N = name.upper()
    defs = "\n".join(f"#define {N}_{k} {v}" for k, v in s.items())
    task = "NG" in s
    about = (f"\n * The task's cost terms ({', '.join(ocp.terms[2:])}) enter the QP by Gauss–Newton about the plan "
             f"(the\n * previous plan shifted a step; the input goal at a cold start) and its predicted states."
             if task else "")
    arrays = (f"x: {N}_NX doubles; goal: {N}_NG doubles, x_goal then the task's targets\n * "
              f"({', '.join(f'{k}: {v}' for k, v in ocp.task.targets.items()) or 'none'}; ocpkit's ocp.goal(...)); "
              f"u: {N}_NU" if task else f"x, goal: {N}_NX doubles; u: {N}_NU")
    task_mem = (f"  /* the task's terms: the plan z̄ linearized about, a stage's x̄, ū, a piece's y = R [1; z̄], the\n"
                f"     residual and Jacobians (column-major), Λ_1 … Λ_LMAX of all states, ∂r/∂x Λ_s, its product\n"
                f"     with R and G = ∂r/∂x S + ∂r/∂u Φ (row-major) */\n"
                f"  double zbar[{N}_NZ], tx[{N}_NX], tu[{N}_NU], ty[{N}_NL], tr[{N}_NR1], trx[{N}_NR1 * {N}_NX], "
                f"tru[{N}_NR1 * {N}_NU];\n"
                f"  double LamA[{N}_LMAX * {N}_NX * {N}_NL], JL[{N}_NR1 * {N}_NL], GX[{N}_NR1 * {N}_NZ1], "
                f"G[{N}_NR1 * {N}_NZ];\n"
                if task else "")
    rti = lin == "trajectory"
    rti_mem = (f"  /* the real-time iteration: each stage's affine model Λ_k = [A_k B_k 0 w_k] (row-major) along\n"
               f"     x̄_k, ū_k (the knots z̄ it linearizes about), the plan's predicted states x_0 … x_T and the\n"
               f"     last good iterate's knots and states */\n"
               f"  double LamK[{N}_HORIZON * {N}_NX * {N}_NL], xbar[{N}_HORIZON * {N}_NX], "
               f"ubark[{N}_HORIZON * {N}_NU];\n"
               f"  double zlin[{N}_NZ], xplan[({N}_HORIZON + 1) * {N}_NX], xgood[({N}_HORIZON + 1) * {N}_NX], "
               f"zgood[{N}_NZ];\n"
               f"  double has_xplan;                                          /* 0 or 1: xplan holds a plan */\n"
               if rti else "")
    rti_api = (f"/* The predicted states x_0 … x_T of the current plan ((HORIZON + 1) x NX row-major); returns 0,\n"
               f"   or 1 where there is none (a cold start or a failed step: the next step linearizes along a\n"
               f"   rollout). */\n"
               f"int {name}_states(const {name}_memory* mem, double* x_pred);\n" if rti else "")
    nr1 = (f"#define {N}_NR1 ({N}_NRS > {N}_NRT ? {N}_NRS : {N}_NRT)  /* residual entries, stage or terminal */\n"
           if task else "")
    return f"""/* {name}.h — exported MPC step for {ocp!r}, {form} QP solved by CasADi's {qp}.
 *
 * Generated by ocpkit.export. One control step: affine model about (x, u_bar), condensed QP, QP solve,
 * first input. u_bar: {_UBAR[lin]}.{about}
 *
 * Usage (any number of instances, up to MAX_INSTANCES in the Makefile live at once per process):
 *   {name}_memory* mem = malloc(sizeof *mem);   // caller-owned: all work space, the plan, warm start
 *   if ({name}_init(mem)) abort();              // once per instance
 *   int status;
 *   {name}_step(mem, x, goal, u, &status);      // each control period
 *   {name}_free(mem);                           // gives the QP solver's memory slot back
 *
 * Arrays: {arrays}; knots: {N}_KNOTS x {N}_NU row-major (knot j, input i at
 * j*{N}_NU + i). Statuses (the same set as ocpkit.controller.STATUSES) are {N}_SUCCESS ... below. On any
 * failure the step returns the safe fallback input (previous plan advanced one step, clipped to the input
 * bounds) and the next step starts without warm start. Instances share no mutable state except the QP
 * solver's slot table: init and free are not thread-safe, steps of different instances are.
 */
#ifndef {N}_H
#define {N}_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {{
#endif

{defs}
#define {N}_NA1 ({N}_NA > 0 ? {N}_NA : 1)
#define {N}_NZ1 ({N}_NZ + 1)
#define {N}_NB1 ({N}_NB > 0 ? {N}_NB : 1)
{nr1}/* A "solved" answer is accepted only if its KKT certificate holds (ocpkit.certificate): stationarity, primal
   feasibility, complementarity and dual sign each within CERT_TOL relative to the data. Otherwise the status is
   {N}_LIMITED and {name}_solver_return gives the failed test's code ({name}_certificate the residuals). With
   DAQP a failed solve's return is DAQP's exit flag: -1 infeasible, -3 unbounded ({N}_INFEASIBLE), -5 nonconvex
   (Hessian not positive definite) and -6 ({N}_EXCEPTION), -2 cycling, -4 iteration limit ({N}_LIMITED). */
#define {N}_CERT_TOL {cert_tol!r}
enum {{ {N}_CERT_STATIONARITY = {_CERT_CODE}, {N}_CERT_PRIMAL, {N}_CERT_COMPLEMENTARITY, {N}_CERT_DUAL_SIGN }};
/* The solver return of a QP refused before its solve (status {N}_EXCEPTION): rounding in its Hessian beyond
   1 % of the curvature the input weight gives (the prediction model diverges over the horizon). */
#define {N}_ILL_CONDITIONED {_ILL_CONDITIONED}

enum {{ {N}_SUCCESS = 0, {N}_LIMITED = 1, {N}_INFEASIBLE = 2, {N}_NAN = 3, {N}_EXCEPTION = 4 }};

/* All memory of one controller instance. Treat as opaque. */
typedef struct {{
  const double* arg[{N}_SZ_ARG];
  double* res[{N}_SZ_RES];
  long long iw[{N}_SZ_IW > 0 ? {N}_SZ_IW : 1];
  double w[{N}_SZ_W > 0 ? {N}_SZ_W : 1];
  /* the affine model: RK4 sensitivities S = [dx/dx0, dx/du] (row-major), or the generated constant model */
  double ug[{N}_NU], ubar[{N}_NU], Ad[{N}_NX * {N}_NX], Bd[{N}_NX * {N}_NU], wd[{N}_NX];
  double xk[{N}_NX], xs[{N}_NX], kq[{N}_NX], kacc[{N}_NX], fx[{N}_NNZ_FX + 1], fu[{N}_NNZ_FU + 1];
  double S[{N}_NX * ({N}_NX + {N}_NU)], Ss[{N}_NX * ({N}_NX + {N}_NU)], D[{N}_NX * ({N}_NX + {N}_NU)];
  double Dacc[{N}_NX * ({N}_NX + {N}_NU)];
  /* the condensing's work space: Λ_1, the running Λ_s and Γ_s, Γ_L and Λ_L per piece length */
  double Lam1[{N}_NX * {N}_NL], LamS[{N}_NX * {N}_NL], LamT[{N}_NX * {N}_NL];
  double W[{N}_NX * ({N}_NL > {N}_NZ1 ? {N}_NL : {N}_NZ1)];
  double Gam1[{N}_NL * {N}_NL], GamS[{N}_NL * {N}_NL], Y[{N}_NL * ({N}_NL > {N}_NZ1 ? {N}_NL : {N}_NZ1)];
  double GamL[{N}_NLEN * {N}_NL * {N}_NL], LamL[{N}_NLEN * {N}_NX * {N}_NL];
  double LamB[{N}_LMAX * {N}_NB1 * {N}_NL], RB[{N}_LMAX * {N}_NB1 * {N}_NZ1];
  double prev[{N}_NX * {N}_NZ1], next[{N}_NX * {N}_NZ1], E2[{N}_NX * {N}_NZ1], Pq[{N}_NZ1 * {N}_NZ1];
  /* the QP */
  double h[{N}_NZ * {N}_NZ], g[{N}_NZ], a[{N}_NA1 * {N}_NZ], lba[{N}_NA1], uba[{N}_NA1];
  double lbx[{N}_NZ], ubx[{N}_NZ];
  double z[{N}_NZ], lam_x[{N}_NZ], lam_a[{N}_NA1];           /* last solution: warm start */
  double z_new[{N}_NZ], lam_x_new[{N}_NZ], lam_a_new[{N}_NA1];
  double plan[{N}_NZ];                                       /* knots of the current plan */
  double cert[4];                                            /* the last solve's certificate residuals */
{task_mem}{rti_mem}  double has_plan, warm;                                     /* 0 or 1 */
  int solver_mem, solver_rc;
}} {name}_memory;

/* Set up one instance (checks out a QP solver memory slot): cold start. Returns 0 on success, 1 when
   all MAX_INSTANCES slots are taken. */
int {name}_init({name}_memory* mem);
/* Forget the plan and warm start (cold start). */
void {name}_reset({name}_memory* mem);
/* One MPC step from state x towards goal state goal: writes u_out and *status, returns *status. */
int {name}_step({name}_memory* mem, const double* x, const double* goal, double* u_out, int* status);
/* The step, also writing the seconds it spent in its three parts: t[0] the affine model, t[1] the condensing
   (the QP's matrices), t[2] the QP solver (0 for the parts a failure skipped). */
int {name}_step_timed({name}_memory* mem, const double* x, const double* goal, double* u_out, int* status,
                      double* t);
/* Copy the current plan's knots (the solution, or the fallback plan after a failure). */
void {name}_knots(const {name}_memory* mem, double* knots);
/* The QP solver's raw return code of the last step (0: solved and certified; see CERT_TOL above). */
int {name}_solver_return(const {name}_memory* mem);
/* The QP solver's name ("daqp", "qrqp", "osqp"). */
const char* {name}_qp_solver(void);
/* The last solve's certificate residuals: stationarity, primal feasibility, complementarity, dual sign. */
void {name}_certificate(const {name}_memory* mem, double* residuals);
/* The condensed QP min ½ zᵀhz + gᵀz s.t. lba <= a z <= uba, lbx <= z <= ubx (h: NZ x NZ, a: NA x NZ, both
   column-major) solved cold and certified as a step's is: writes z and *status, returns *status; the plan is
   kept, the next step starts cold. For tests of the solver and its certificate on QPs of one's own. */
int {name}_solve_qp({name}_memory* mem, const double* h, const double* g, const double* a, const double* lba,
                    const double* uba, const double* lbx, const double* ubx, double* z, int* status);
{rti_api}/* One step of the generated discrete model x_next = F(x, u) the controller predicts with. */
int {name}_model_step({name}_memory* mem, const double* x, const double* u, double* x_next);
/* Give the instance's QP solver memory slot back (safe to call twice); the slot is reused by a later init. */
void {name}_free({name}_memory* mem);
/* sizeof({name}_memory), and the sizes nx, nu, knots, horizon (for foreign-function loaders). */
size_t {name}_memory_size(void);
void {name}_dims(int* nx, int* nu, int* knots, int* horizon);

#ifdef __cplusplus
}}
#endif
#endif
"""


def _c_num(v: float) -> str:
    v = float(v)
    if np.isnan(v):
        return "NAN"
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(v)


def _c_array(v) -> str:
    return "{" + ", ".join(_c_num(e) for e in np.asarray(v, dtype=float).ravel()) + "}"


def _c_const(kind: str, name: str, values) -> str:
    """A static const C array; empty arrays get one dummy entry (C has no zero-length arrays)."""
    values = np.asarray(values).ravel()
    if values.size == 0:
        values = np.zeros(1)
    body = ("{" + ", ".join(str(int(e)) for e in values) + "}" if kind == "int" else _c_array(values))
    return f"static const {kind} {name}[{values.size}] = {body};"


def _constants(tr: CondensedQP, linearization: str, jac, tf=None, iterations: int = 1, tol: float = 0.0) -> str:
    """The step's constants: input goal, shift, bounds, weights, the basis' pieces, the Gram schedule, for
    a nonlinear model RK4's step and the Jacobians' sparsity, with a task (``tf``) its weights and the basis, and
    for the real-time iteration ("trajectory") the basis, each stage's active knot columns and the iterations."""
    ocp = tr.ocp
    n, m, p = tr.n, tr.m, tr.p
    phi = tr.phi
    Sh = np.eye(tr.T, k=1)
    Sh[-1, -1] = 1.0
    M = ocp.parameterization._fit @ Sh @ phi  # knots of the shifted plan: M U (Parameterization.shift)
    K = np.asarray(ocp.u_goal_gain, dtype=float)
    bounded = np.flatnonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max))
    lengths = tr._lengths
    pieces = tr._pieces
    pa = [a for a, _, _, _ in pieces]
    pl = [L for _, L, _, _ in pieces]
    pc = [int(c) for _, _, c, _ in pieces]
    # rhs rows n … n+m−1 hold φ_a ⊗ I and rows n+m … n+2m−1 hold Δ ⊗ I: read φ_a and Δ back per knot.
    pphi = np.zeros((len(pieces), p))
    pdel = np.zeros((len(pieces), p))
    for i, (_, _, c, rhs) in enumerate(pieces):
        for j in range(int(c) // m):
            pphi[i, j] = rhs[n, 1 + j * m]
            pdel[i, j] = rhs[n + m, 1 + j * m]
    ops = _gram_schedule(lengths)
    lines = [
        f"#define DIAG_Q {int(tr.diagonal_Q)}",
        f"#define HAS_DQT {int(np.any(tr._dQT))}",
        f"#define MODEL_RK4 {int(jac is not None)}",
        f"#define EULER {int(ocp.integrator == 'euler')}",
        f"#define EULER_NQ {ocp.model.second_order or 0}",  # semi-implicit over q = x[:nq]; 0: explicit Euler
        f"#define SUBSTEPS {ocp.substeps}",
        f"#define RK_H {_c_num(ocp.dt / ocp.substeps)}",
        f"#define NGRAM_OPS {len(ops)}",
        _c_const("int", "GRAM_OPS", ops),
        f"#define HAS_K {int(np.any(K))}",
        f"#define HAS_GOAL_INPUT {int(getattr(ocp, 'goal_input', None) is not None)}",
        f"#define LIN_PLAN {int(linearization == 'plan')}",
        f"#define NPIECE {len(pieces)}",
        f"#define NB {bounded.size}",
        _c_const("double", "U_GOAL", ocp.u_goal),
        _c_const("double", "R_IN", ocp.R),
        _c_const("double", "R_KNOTS", tr.R_knots),
        f"#define CURVATURE {_c_num(tr.curvature)}  /* P's curvature in exact arithmetic (QP.not_definite) */",
        f"#define ROUNDING_MARGIN {_c_num(ROUNDING_MARGIN)}",
        _c_const("double", "PHI_SUM", tr._phi_sum),
        _c_const("double", "PHI0", phi[0]),
        _c_const("double", "SHIFT", M),
        _c_const("double", "LBX", np.tile(ocp.u_min, p)),
        _c_const("double", "UBX", np.tile(ocp.u_max, p)),
        _c_const("double", "QH", tr._qh),
        _c_const("int", "PIECE_A", pa),
        _c_const("int", "PIECE_L", pl),
        _c_const("int", "PIECE_C", pc),
        _c_const("int", "PIECE_CP", [0] + pc[:-1]),
        _c_const("int", "PIECE_LEN", [lengths.index(L) for L in pl]),
        _c_const("double", "PIECE_PHI", pphi),
        _c_const("double", "PIECE_DELTA", pdel),
    ]
    if linearization == "plan":
        lines.append(_c_const("double", "W0", phi[0] @ M))
    lines.append(f"#define LIN_TRAJ {int(linearization == 'trajectory')}")
    if linearization == "trajectory":
        # x_{k+1} depends on the knots of stages 0 … k only: its [v S] row has 1 + ACTIVE[k] nonzero columns.
        last = np.maximum.accumulate([np.flatnonzero(row).max(initial=0) for row in phi])
        lines += [f"#define ITERATIONS {iterations}", f"#define RTI_TOL {_c_num(tol)}",
                  _c_const("double", "PHI_ALL", phi), _c_const("int", "ACTIVE", (last + 1) * m)]
    if np.any(tr._dQT):
        lines.append(_c_const("double", "DQT", tr._dQT))
    if jac is not None:
        (fxi, fxj), (fui, fuj) = jac
        lines += [_c_const("int", "FX_I", fxi), _c_const("int", "FX_J", fxj),
                  _c_const("int", "FU_I", fui), _c_const("int", "FU_J", fuj)]
    if np.any(K):  # read only under #if HAS_K / #if NB > 0: unused constants would draw warnings
        lines.append(_c_const("double", "K_GOAL", K))
    if bounded.size:
        lines += [_c_const("int", "XB_COMP", bounded), _c_const("double", "XB_LO", ocp.x_min[bounded]),
                  _c_const("double", "XB_HI", ocp.x_max[bounded])]
    if tf is not None:  # the task's Gauss-Newton terms: φ_k of every stage (exact, not the pieces' φ_a + sΔ)
        stage, terminal = tf.stage_weight.size, tf.terminal_weight.size
        lines += [f"#define TASK_STAGE {int(bool(stage))}", f"#define TASK_TERMINAL {int(bool(terminal))}"]
        if stage:
            lines += [_c_const("double", "TASK_PHI", phi), _c_const("double", "TASK_WS", tf.stage_weight)]
        if terminal:
            lines.append(_c_const("double", "TASK_WT", tf.terminal_weight))
    return "\n".join(lines)


_WRAPPER = Template(r"""/* $name.c — one MPC step: the affine model (generated, ${name}_casadi.c), the condensed QP built by the
 * loops below (ocpkit.transcription.CondensedQP.build in C), the QP solve (generated) and the first input. */
#if !defined(_WIN32) && !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 199309L /* clock_gettime for ${name}_step_timed */
#endif
#include <float.h>
#include <math.h>
#include <string.h>
#include <time.h>
#include "$name.h"
#include "${name}_casadi.h"

#define NX ${N}_NX
#define NU ${N}_NU
#define NP ${N}_KNOTS
#define NZ ${N}_NZ
#define NZ1 ${N}_NZ1
#define NA ${N}_NA
#define NL ${N}_NL
#define LMAX ${N}_LMAX
#define NLEN ${N}_NLEN
typedef ${name}_memory mem_t;

$constants

int ${name}_init(mem_t* m) {
  m->solver_mem = ${name}_qp_solve_checkout();
  if (m->solver_mem < 0) return 1;
  ${name}_reset(m);
  return 0;
}

void ${name}_reset(mem_t* m) {
  int i;
  for (i = 0; i < NZ; ++i) m->plan[i] = m->z[i] = m->lam_x[i] = 0;
  for (i = 0; i < ${N}_NA1; ++i) m->lam_a[i] = 0;
  m->has_plan = m->warm = 0;
#if LIN_TRAJ
  m->has_xplan = 0;
#endif
  m->solver_rc = 0;
}

/* CasADi's decref frees every slot (even ones still on its free list) once the count reaches zero, so the
   slots stay allocated for the library's lifetime and are reused by later inits. */
void ${name}_free(mem_t* m) {
  if (m->solver_mem >= 0) ${name}_qp_solve_release(m->solver_mem);
  m->solver_mem = -1;
}

static int all_finite(const double* v, int n) {
  int i;
  for (i = 0; i < n; ++i) if (!isfinite(v[i])) return 0;
  return 1;
}

static int any_nan(const double* v, int n) {
  int i;
  for (i = 0; i < n; ++i) if (isnan(v[i])) return 1;
  return 0;
}

static int any_above(const double* lo, const double* hi, int n) {
  int i;
  for (i = 0; i < n; ++i) if (lo[i] > hi[i]) return 1;
  return 0;
}

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* u_g = u_goal + K goal (+ h(goal), the problem's goal input: gravity compensation): the input the cost pulls
   towards. Returns nonzero if h failed. */
static int input_goal(mem_t* m, const double* goal, double* ug) {
  int i;
  for (i = 0; i < NU; ++i) {
    double s = U_GOAL[i];
#if HAS_K
    int j;
    for (j = 0; j < NX; ++j) s += K_GOAL[i * NX + j] * goal[j];
#endif
    ug[i] = s;
  }
#if HAS_GOAL_INPUT
  {
    double h[NU];
    m->arg[0] = goal; m->res[0] = h;
    if (${name}_goal_input(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
    for (i = 0; i < NU; ++i) ug[i] += h[i];
  }
#else
  (void) m; (void) goal;
#endif
  return 0;
}

/* Controller.fallback: previous plan shifted (input goal at a cold start), clipped; the next step starts cold. */
static int fallback(mem_t* m, double* u_out, int status) {
  int j, l, i;
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double s = 0;
      if (m->has_plan) for (l = 0; l < NP; ++l) s += SHIFT[j * NP + l] * m->plan[l * NU + i];
      else s = m->ug[i];
      m->z_new[j * NU + i] = clip(s, LBX[j * NU + i], UBX[j * NU + i]);
    }
  for (i = 0; i < NU; ++i) {
    double s = 0;
    for (j = 0; j < NP; ++j) s += PHI0[j] * m->z_new[j * NU + i];
    u_out[i] = clip(s, LBX[i], UBX[i]);
  }
  for (i = 0; i < NZ; ++i) m->plan[i] = m->z_new[i];
  m->has_plan = 1;
  m->warm = 0;
#if LIN_TRAJ
  m->has_xplan = 0;  /* the next step linearizes along a rollout of the fallback plan */
#endif
  return status;
}

/* C += A B for an M x NX matrix A with A(i, k) = A[i * ars + k * aks] (row-major: ars = lda, aks = 1; its
   transpose: ars = 1, aks = lda) and row-major B, C. With upper set, tiles wholly below C's diagonal are
   skipped (the lower triangle is then left partial, and is never read). The inner product runs over NX, a
   constant. Tiles of MR rows x 8 (or 4) columns of C stay in vector registers while B's rows, contiguous,
   stream through: GCC/Clang vector extensions, 2 doubles wide (SSE2, any x86-64) and, on x86 CPUs that have
   them, 4 wide with AVX2 and FMA (chosen once at run time; no build flag, the library stays portable). */
#ifndef OCPKIT_SIMD
#define OCPKIT_SIMD 2 /* the Makefile's SIMD: 2 auto (AVX2 where the CPU has it), 1 no AVX2 path, 0 plain C */
#endif
#if (defined(__GNUC__) || defined(__clang__)) && OCPKIT_SIMD >= 1
#define VECTOR_EXT 1
typedef double vec2 __attribute__((vector_size(16), aligned(8), may_alias));
#if (defined(__x86_64__) || defined(__i386__)) && OCPKIT_SIMD >= 2
#define HAVE_AVX2_PATH 1
typedef double vec4 __attribute__((vector_size(32), aligned(8), may_alias));
#endif
#endif

/* One sweep over NX of B's rows through the register block (rows: MR, a constant the compiler unrolls,
   or mr). */
#define TILE_SWEEP(rows, VT, W, NC)                                                                           \
  for (k = 0; k < NX; ++k) {                                                                                  \
    VT b[NC / W];                                                                                             \
    for (v = 0; v < NC / W; ++v) b[v] = *(const VT*) (B + k * ldb + v * W);                                   \
    for (r = 0; r < (rows); ++r) {                                                                            \
      const double a = A[r * ars + k * aks];                                                                  \
      for (v = 0; v < NC / W; ++v) c[r][v] += a * b[v];                                                       \
    }                                                                                                         \
  }

/* A tile: C[0:mr, 0:NC] += A[0:mr, :] B[:, 0:NC], its MR x NC block of C in registers (vectors VT of W). */
#define TILE(name, attr, VT, W, MR, NC)                                                                       \
  attr static void name(int mr, const double* restrict A, int ars, int aks, const double* restrict B, int ldb,\
                        double* restrict C, int ldc) {                                                        \
    VT c[MR][NC / W];                                                                                         \
    int r, v, k;                                                                                              \
    for (r = 0; r < MR; ++r) for (v = 0; v < NC / W; ++v) c[r][v] = (VT){0};                                  \
    if (mr == MR) {                                                                                           \
      TILE_SWEEP(MR, VT, W, NC)                                                                               \
    } else {                                                                                                  \
      TILE_SWEEP(mr, VT, W, NC)                                                                               \
    }                                                                                                         \
    for (r = 0; r < mr; ++r) for (v = 0; v < NC / W; ++v) *(VT*) (C + r * ldc + v * W) += c[r][v];            \
  }

/* gemm_<sfx>: tiles of 8 columns, one of 4, and the last N mod 4 columns through a zero-padded copy of B's
   columns (so that they too run in registers, not as latency-bound dot products). */
#define TILES(sfx, attr, VT, W, MR)                                                                           \
  TILE(tile8_##sfx, attr, VT, W, MR, 8)                                                                       \
  TILE(tile4_##sfx, attr, VT, W, MR, 4)                                                                       \
  attr static void gemm_##sfx(int M, int N, const double* restrict A, int ars, int aks,                       \
                              const double* restrict B, int ldb, double* restrict C, int ldc, int upper) {    \
    const int n8 = N - N % 8, n4 = N - N % 4, nrem = N - n4;                                                  \
    double Bp[NX * 4], Cp[MR * 4];                                                                            \
    int i, j, k, r;                                                                                           \
    for (k = 0; nrem && k < NX; ++k)                                                                          \
      for (j = 0; j < 4; ++j) Bp[k * 4 + j] = j < nrem ? B[k * ldb + n4 + j] : 0.0;                          \
    for (i = 0; i < M; i += MR) {                                                                             \
      const int mr = M - i < MR ? M - i : MR;                                                                 \
      for (j = upper ? (i / 8) * 8 : 0; j < n8; j += 8)                                                       \
        tile8_##sfx(mr, A + i * ars, ars, aks, B + j, ldb, C + i * ldc + j, ldc);                             \
      if (n4 > n8) tile4_##sfx(mr, A + i * ars, ars, aks, B + n8, ldb, C + i * ldc + n8, ldc);                \
      if (nrem) {                                                                                             \
        for (j = 0; j < MR * 4; ++j) Cp[j] = 0;                                                               \
        tile4_##sfx(mr, A + i * ars, ars, aks, Bp, 4, Cp, 4);                                                 \
        for (r = 0; r < mr; ++r)                                                                              \
          for (j = 0; j < nrem; ++j) C[(i + r) * ldc + n4 + j] += Cp[r * 4 + j];                              \
      }                                                                                                       \
    }                                                                                                         \
  }

#if VECTOR_EXT
TILES(v2, , vec2, 2, 2)
#if HAVE_AVX2_PATH
TILES(v4, __attribute__((target("avx2,fma"))), vec4, 4, 4)
#endif
#else
typedef double vec1;
TILES(v1, , vec1, 1, 2)
#endif

#if HAVE_AVX2_PATH
static int use_avx2(void) {
  static int avx2 = -1;  /* an idempotent race at worst: every thread writes the same value */
  if (avx2 < 0) avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return avx2;
}
#endif

static void gemm(int M, int N, const double* restrict A, int ars, int aks, const double* restrict B, int ldb,
                 double* restrict C, int ldc, int upper) {
#if HAVE_AVX2_PATH
  if (use_avx2()) { gemm_v4(M, N, A, ars, aks, B, ldb, C, ldc, upper); return; }
#endif
#if VECTOR_EXT
  gemm_v2(M, N, A, ars, aks, B, ldb, C, ldc, upper);
#else
  gemm_v1(M, N, A, ars, aks, B, ldb, C, ldc, upper);
#endif
}

/* The upper triangle of a row-major n x n matrix copied into its lower one. */
static void symmetrize(double* X, int n) {
  int i, j;
  for (i = 0; i < n; ++i)
    for (j = 0; j < i; ++j) X[i * n + j] = X[j * n + i];
}

/* The augmented state ζ = [x; v; d; 1] of a piece (input v_t = v + t d, d constant) moves by
   ζ_{s+1} = Â ζ_s, and Λ_s = [A^s E_s F_s e_s] = C Â^s (C picks x). out = X Â^b for X (rows x NL, row stride
   ldx) from Λ_b, the x rows of Â^b, whose other rows are [0 I bI 0; 0 0 I 0; 0 0 0 1]. */
static void times_ahat(const double* X, int rows, int ldx, const double* Lb, int b, double* out) {
  int r, u;
  for (r = 0; r < rows; ++r) {
    const double* xr = X + r * ldx;
    double* o = out + r * NL;
    for (u = 0; u < NX; ++u) o[u] = 0;
    for (u = 0; u < NU; ++u) {
      o[NX + u] = xr[NX + u];
      o[NX + NU + u] = b * xr[NX + u] + xr[NX + NU + u];
    }
    o[NL - 1] = xr[NL - 1];
  }
  gemm(rows, NL, X, ldx, 1, Lb, NL, out, NL, 0);
}

/* G += Wᵀ W (upper triangle; row stride ldg) with W = Q^½ (X − x_goal e_oneᵀ) over the first cols columns of X
   (row stride ldx; column one multiplies 1): the stage cost (x_s − x_goal)ᵀ Q (x_s − x_goal) as a form in the
   coordinates of X — ζ for Λ_s, [1; z] for the rows [v S] of the real-time iteration. */
static void add_stage(mem_t* m, const double* X, int cols, int ldx, int one, const double* xg, double* G, int ldg) {
  double* W = m->W;
  int i, j, k;
#if DIAG_Q
  for (i = 0; i < NX; ++i) {
    for (j = 0; j < cols; ++j) W[i * cols + j] = QH[i] * X[i * ldx + j];
    W[i * cols + one] -= QH[i] * xg[i];
  }
  (void) k;
#else
  for (i = 0; i < NX * cols; ++i) W[i] = 0;
  gemm(NX, cols, QH, NX, 1, X, ldx, W, cols, 0);
  for (i = 0; i < NX; ++i) {
    double gx = 0;
    for (k = 0; k < NX; ++k) gx += QH[i * NX + k] * xg[k];
    W[i * cols + one] -= gx;
  }
  (void) j;
#endif
  gemm(cols, cols, W, 1, cols, W, cols, G, ldg, 1);
}

/* Γ += the stage cost of Λ (add_stage), both triangles: the doublings read Γ whole. */
static void add_stage_gram(mem_t* m, const double* Lam, const double* xg, double* Gam) {
  add_stage(m, Lam, NL, NL, NL - 1, xg, Gam, NL);
  symmetrize(Gam, NL);
}

/* Γ_L = Σ_{s≤L} Λ_sᵀ Q Λ_s (goal folded in) and Λ_L for each piece length, by the schedule GRAM_OPS: doublings
   Γ_2s = Γ_s + (Â^s)ᵀ Γ_s Â^s, Λ_2s = Λ_s Â^s and single stages, O(log L) products instead of L. */
static void grams(mem_t* m, const double* xg) {
  double *Lam = m->LamS, *tmp = m->LamT, *Gam = m->GamS, *sw;
  int op, i, s = 1;
  for (i = 0; i < NL * NL; ++i) m->Gam1[i] = 0;
  add_stage_gram(m, m->Lam1, xg, m->Gam1);
  memcpy(Lam, m->Lam1, sizeof m->Lam1);
  memcpy(Gam, m->Gam1, sizeof m->Gam1);
  for (op = 0; op < NGRAM_OPS; ++op) {
    const int code = GRAM_OPS[op];
    if (code == 1) {  /* double */
      times_ahat(Gam, NL, NL, Lam, s, m->Y);
      for (i = 0; i < NU; ++i) {
        double* gv = Gam + (NX + i) * NL;
        double* gd = Gam + (NX + NU + i) * NL;
        const double* yv = m->Y + (NX + i) * NL;
        const double* yd = m->Y + (NX + NU + i) * NL;
        int j;
        for (j = 0; j < NL; ++j) { gv[j] += yv[j]; gd[j] += s * yv[j] + yd[j]; }
      }
      for (i = 0; i < NL; ++i) Gam[(NL - 1) * NL + i] += m->Y[(NL - 1) * NL + i];
      gemm(NL, NL, Lam, 1, NL, m->Y, NL, Gam, NL, 1);
      symmetrize(Gam, NL);
      times_ahat(Lam, NX, NL, Lam, s, tmp);
      s *= 2;
    } else if (code == 2) {  /* one more stage */
      times_ahat(Lam, NX, NL, m->Lam1, 1, tmp);
      add_stage_gram(m, tmp, xg, Gam);
      s += 1;
    } else if (code == 3) {  /* restart from s = 1 */
      memcpy(Lam, m->Lam1, sizeof m->Lam1);
      memcpy(Gam, m->Gam1, sizeof m->Gam1);
      s = 1;
      continue;
    } else {  /* save as length code - 10 */
      memcpy(m->GamL + (code - 10) * NL * NL, Gam, sizeof m->GamS);
      memcpy(m->LamL + (code - 10) * NX * NL, Lam, sizeof m->LamS);
      continue;
    }
    sw = Lam; Lam = tmp; tmp = sw;
  }
}

/* out (rows x (c+1), row stride ldo) = X R for X (rows x NL, stride ldx) and the piece's
   R = [prev; φ_a ⊗ I; Δ ⊗ I; (1, 0 … 0)]; prev's columns past cp are zero (knots not yet active). */
static void times_r(const double* X, int rows, int ldx, const double* prev, int cp, const double* phi,
                    const double* del, int c, double* out, int ldo) {
  int r, j, u, col;
  for (r = 0; r < rows; ++r) {
    const double* xr = X + r * ldx;
    double* o = out + r * ldo;
    o[0] = xr[NL - 1];
    for (j = 0, col = 1; col <= c; ++j)
      for (u = 0; u < NU; ++u, ++col) o[col] = phi[j] * xr[NX + u] + del[j] * xr[NX + NU + u];
  }
  gemm(rows, cp + 1, X, ldx, 1, prev, NZ1, out, ldo, 0);
}

static void finish_qp(mem_t* m, double* prev, const double* xg);

/* The condensed QP about the affine model Λ_1 (CondensedQP.build): h, g, state-bound rows a, lba, uba. */
static void condense(mem_t* m, const double* x, const double* xg) {
  double *prev = m->prev, *next = m->next, *Pq = m->Pq, *Y = m->Y, *sw;
  int pc, i, r, col, s, b;
  grams(m, xg);
#if NB > 0
  /* the bounded rows of Λ_1 … Λ_LMAX (row b of Λ_s at LamB[(s-1) NB + b]) */
  for (b = 0; b < NB; ++b) memcpy(m->LamB + b * NL, m->Lam1 + XB_COMP[b] * NL, NL * sizeof(double));
  for (s = 1; s < LMAX; ++s) times_ahat(m->LamB + (s - 1) * NB * NL, NB, NL, m->Lam1, 1, m->LamB + s * NB * NL);
#endif
  for (i = 0; i < NX * NZ1; ++i) prev[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (i = 0; i < NZ1 * NZ1; ++i) Pq[i] = 0;
  for (pc = 0; pc < NPIECE; ++pc) {
    const int a = PIECE_A[pc], Lp = PIECE_L[pc], c = PIECE_C[pc], cp = PIECE_CP[pc];
    const double *phi = PIECE_PHI + pc * NP, *del = PIECE_DELTA + pc * NP;
    /* Pq[:c+1, :c+1] += Rᵀ (Γ R) (upper half) */
    times_r(m->GamL + PIECE_LEN[pc] * NL * NL, NL, NL, prev, cp, phi, del, c, Y, NZ1);
    for (r = 0; r <= c; ++r) {
      double* pr = Pq + r * NZ1;
      if (r == 0) {
        for (col = 0; col <= c; ++col) pr[col] += Y[(NL - 1) * NZ1 + col];
      } else {
        const int jr = (r - 1) / NU, ur = r - 1 - jr * NU;
        const double f = phi[jr], d = del[jr];
        const double *y1 = Y + (NX + ur) * NZ1, *y2 = Y + (NX + NU + ur) * NZ1;
        if (f != 0 || d != 0) for (col = r; col <= c; ++col) pr[col] += f * y1[col] + d * y2[col];
      }
    }
    gemm(cp + 1, c + 1, prev, 1, NZ1, Y, NZ1, Pq, NZ1, 1);
#if NB > 0
    /* state-bound rows of [v S] at x_{a+1} … x_{a+Lp}: row (k, b) at k*NB + b */
    times_r(m->LamB, Lp * NB, NL, prev, cp, phi, del, c, m->RB, NZ1);
    for (s = 0; s < Lp; ++s)
      for (b = 0; b < NB; ++b) {
        const int ri = (a + s) * NB + b;
        const double* row = m->RB + (s * NB + b) * NZ1;
        for (col = 0; col < NZ; ++col) m->a[ri + NA * col] = col < c ? row[col + 1] : 0.0;
        m->lba[ri] = XB_LO[b] - row[0];
        m->uba[ri] = XB_HI[b] - row[0];
      }
#else
    (void) a; (void) Lp; (void) s; (void) b;
#endif
    /* [v S] at the piece's end: Λ_Lp R */
    times_r(m->LamL + PIECE_LEN[pc] * NX * NL, NX, NL, prev, cp, phi, del, c, next, NZ1);
    for (i = 0; i < NX; ++i)
      for (col = c + 1; col < NZ1; ++col) next[i * NZ1 + col] = 0;
    sw = prev; prev = next; next = sw;
  }
  finish_qp(m, prev, xg);
}

/* The QP from Pq (the upper triangle of Σ_s [1; z]ᵀ[v_s − x_goal, S_s]ᵀ Q [v_s − x_goal, S_s]) and the last
   state's rows prev = [v_T S_T]: the terminal weight's extra (Q_T − Q), then P = S'QS + φᵀφ ⊗ R, q = S'Q(v − x_goal)
   − φᵀ1 ⊗ R u_g and the knot bounds. */
static void finish_qp(mem_t* m, double* prev, const double* xg) {
  double* Pq = m->Pq;
  int i, j, k, col;
  (void) col; (void) prev; (void) xg;  /* used only with a terminal weight other than Q (HAS_DQT) */
  /* terminal weight: (Q_T − Q) on [v − x_goal, S] at x_T */
#if HAS_DQT
  for (i = 0; i < NX; ++i) prev[i * NZ1] -= xg[i];
#if DIAG_Q
  for (i = 0; i < NX; ++i)
    for (col = 0; col < NZ1; ++col) m->E2[i * NZ1 + col] = DQT[i] * prev[i * NZ1 + col];
#else
  for (i = 0; i < NX * NZ1; ++i) m->E2[i] = 0;
  gemm(NX, NZ1, DQT, NX, 1, prev, NZ1, m->E2, NZ1, 0);
#endif
  gemm(NZ1, NZ1, prev, 1, NZ1, m->E2, NZ1, Pq, NZ1, 1);
#endif
  /* P = S'QS + φᵀφ ⊗ R (symmetric by construction), q = S'Q(v − x_goal) − φᵀ1 ⊗ R u_g */
  for (i = 0; i < NZ; ++i)
    for (j = i; j < NZ; ++j) {
      double v = Pq[(1 + i) * NZ1 + 1 + j] + R_KNOTS[i * NZ + j];
      m->h[i + NZ * j] = m->h[j + NZ * i] = v;
    }
  for (i = 0; i < NZ; ++i) {
    const int jk = i / NU, u = i % NU;
    double ru = 0;
    for (k = 0; k < NU; ++k) ru += R_IN[u * NU + k] * m->ug[k];
    m->g[i] = Pq[1 + i] - PHI_SUM[jk] * ru;
    m->lbx[i] = LBX[i];
    m->ubx[i] = UBX[i];
  }
}
${task_c}
#if MODEL_RK4
/* D = J_x S + [0 J_u] with the Jacobians' nonzeros (fx, fu) at (FX_I, FX_J), (FU_I, FU_J); S, D row-major
   NX x (NX + NU): a row of S, contiguous, per nonzero (compiled twice like gemm: SSE2 and AVX2). */
#define SENSITIVITY_RATE(sfx, attr)                                                                           \
  attr static void sensitivity_rate_##sfx(const mem_t* m, const double* restrict S, double* restrict D) {    \
    int q, j;                                                                                                 \
    for (q = 0; q < NX * (NX + NU); ++q) D[q] = 0;                                                            \
    for (q = 0; q < ${N}_NNZ_FX; ++q) {                                                                       \
      const double v = m->fx[q];                                                                              \
      const double* restrict sk = S + FX_J[q] * (NX + NU);                                                    \
      double* restrict di = D + FX_I[q] * (NX + NU);                                                          \
      for (j = 0; j < NX + NU; ++j) di[j] += v * sk[j];                                                       \
    }                                                                                                         \
    for (q = 0; q < ${N}_NNZ_FU; ++q) D[FU_I[q] * (NX + NU) + NX + FU_J[q]] += m->fu[q];                      \
  }
SENSITIVITY_RATE(v2, )
#if HAVE_AVX2_PATH
SENSITIVITY_RATE(v4, __attribute__((target("avx2,fma"))))
#endif

static void sensitivity_rate(const mem_t* m, const double* restrict S, double* restrict D) {
#if HAVE_AVX2_PATH
  if (use_avx2()) { sensitivity_rate_v4(m, S, D); return; }
#endif
  sensitivity_rate_v2(m, S, D);
}

/* D = [J_x J_u] scattered: the rate at the step's start, where S = [I 0] (no products). */
static void jacobian_rate(const mem_t* m, double* restrict D) {
  int q;
  for (q = 0; q < NX * (NX + NU); ++q) D[q] = 0;
  for (q = 0; q < ${N}_NNZ_FX; ++q) D[FX_I[q] * (NX + NU) + FX_J[q]] = m->fx[q];
  for (q = 0; q < ${N}_NNZ_FU; ++q) D[FU_I[q] * (NX + NU) + NX + FU_J[q]] += m->fu[q];
}
#endif

/* L = [A_d B_d 0 w_d] (row-major, NX x NL) of the affine model about (x, ū): RK4 over SUBSTEPS with its
   sensitivities (the generated f, ∂f/∂x, ∂f/∂u at each stage), or the generated constant model of a linear one. */
static int affine_model(mem_t* m, const double* x, const double* u, double* L) {
  int i, j;
#if MODEL_RK4 && EULER
  /* Euler over SUBSTEPS (integrator "euler"), its sensitivities S = ∂x/∂(x_0, u) alongside: semi-implicit for
     x = [q, q̇] (EULER_NQ = nq entries of q), q̇⁺ = q̇ + h q̈(x, u), q⁺ = q + h q̇⁺; explicit (EULER_NQ = 0),
     x⁺ = x + h f(x, u). One f, ∂f/∂x, ∂f/∂u a substep instead of RK4's four. */
  const int nS = NX * (NX + NU), w = NX + NU;
  int sub;
  for (i = 0; i < NX; ++i) m->xk[i] = x[i];
  for (i = 0; i < nS; ++i) m->S[i] = 0;
  for (i = 0; i < NX; ++i) m->S[i * w + i] = 1;
  for (sub = 0; sub < SUBSTEPS; ++sub) {
    m->arg[0] = m->xk; m->arg[1] = u;
    m->res[0] = m->kq; m->res[1] = m->fx; m->res[2] = m->fu;
    if (${name}_fjac(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
    if (sub) sensitivity_rate(m, m->S, m->D);
    else jacobian_rate(m, m->D);
    for (i = EULER_NQ; i < NX; ++i) {
      m->xk[i] += RK_H * m->kq[i];
      for (j = 0; j < w; ++j) m->S[i * w + j] += RK_H * m->D[i * w + j];
    }
    for (i = 0; i < EULER_NQ; ++i) {  /* with the new q̇ */
      m->xk[i] += RK_H * m->xk[EULER_NQ + i];
      for (j = 0; j < w; ++j) m->S[i * w + j] += RK_H * m->S[(EULER_NQ + i) * w + j];
    }
  }
#elif MODEL_RK4
  static const double C_STAGE[4] = {0.0, 0.5 * RK_H, 0.5 * RK_H, RK_H}, W_STAGE[4] = {1.0, 2.0, 2.0, 1.0};
  const int nS = NX * (NX + NU);
  int sub, q;
  for (i = 0; i < NX; ++i) m->xk[i] = x[i];
  for (i = 0; i < nS; ++i) m->S[i] = 0;
  for (i = 0; i < NX; ++i) m->S[i * (NX + NU) + i] = 1;
  for (sub = 0; sub < SUBSTEPS; ++sub) {
    for (i = 0; i < NX; ++i) m->kacc[i] = 0;
    for (i = 0; i < nS; ++i) m->Dacc[i] = 0;
    for (q = 0; q < 4; ++q) {
      const double cq = C_STAGE[q], wq = W_STAGE[q];
      for (i = 0; i < NX; ++i) m->xs[i] = q ? m->xk[i] + cq * m->kq[i] : m->xk[i];
      for (i = 0; i < nS; ++i) m->Ss[i] = q ? m->S[i] + cq * m->D[i] : m->S[i];
      m->arg[0] = m->xs; m->arg[1] = u;
      m->res[0] = m->kq; m->res[1] = m->fx; m->res[2] = m->fu;
      if (${name}_fjac(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
      if (sub || q) sensitivity_rate(m, m->Ss, m->D);
      else jacobian_rate(m, m->D);
      for (i = 0; i < NX; ++i) m->kacc[i] += wq * m->kq[i];
      for (i = 0; i < nS; ++i) m->Dacc[i] += wq * m->D[i];
    }
    for (i = 0; i < NX; ++i) m->xk[i] += RK_H / 6 * m->kacc[i];
    for (i = 0; i < nS; ++i) m->S[i] += RK_H / 6 * m->Dacc[i];
  }
#endif
#if MODEL_RK4
  for (i = 0; i < NX; ++i) {
    const double* si = m->S + i * (NX + NU);
    double* Li = L + i * NL;
    double wi = m->xk[i];
    for (j = 0; j < NX + NU; ++j) { Li[j] = si[j]; wi -= si[j] * (j < NX ? x[j] : u[j - NX]); }
    for (j = 0; j < NU; ++j) Li[NX + NU + j] = 0;
    Li[NL - 1] = wi;
  }
#else
  m->arg[0] = x; m->arg[1] = u;
  m->res[0] = m->Ad; m->res[1] = m->Bd; m->res[2] = m->wd;
  if (${name}_affine(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (i = 0; i < NX; ++i) {  /* Ad, Bd come column-major from CasADi */
    double* Li = L + i * NL;
    for (j = 0; j < NX; ++j) Li[j] = m->Ad[i + NX * j];
    for (j = 0; j < NU; ++j) { Li[NX + j] = m->Bd[i + NX * j]; Li[NX + NU + j] = 0; }
    Li[NL - 1] = m->wd[i];
  }
#endif
  return 0;
}

static double amax(double a, double b) { return a > b ? a : b; }

/* One bound row l <= v <= u with multiplier lam (> 0 at an active upper bound): its primal scale, violation,
   complementarity gap and wrong-sign multiplier folded into s[0..3]. */
static void bound_row(double v, double l, double u, double lam, double* s) {
  if (isfinite(l) || isfinite(u)) s[0] = amax(s[0], fabs(v));
  if (isfinite(l)) { s[0] = amax(s[0], fabs(l)); s[1] = amax(s[1], l - v); }
  if (isfinite(u)) { s[0] = amax(s[0], fabs(u)); s[1] = amax(s[1], v - u); }
  if (lam > 0) { if (isfinite(u)) s[2] = amax(s[2], lam * fabs(u - v)); else s[3] = amax(s[3], lam); }
  if (lam < 0) { if (isfinite(l)) s[2] = amax(s[2], -lam * fabs(v - l)); else s[3] = amax(s[3], -lam); }
}

/* The KKT certificate of the QP's answer (z_new, lam_x_new, lam_a_new), as ocpkit.certificate computes it, in
   CasADi's multiplier convention h z + g + aᵀ lam_a + lam_x = 0: m->cert = the relative residuals of
   stationarity, primal feasibility, complementarity and dual sign; returns the code of the first one above
   CERT_TOL (or NaN), 0 when all hold. A stale or zero answer fails stationarity. */
static int certify(mem_t* m) {
  const double *z = m->z_new, *lx = m->lam_x_new, *la = m->lam_a_new;
  double s[4] = {0, 0, 0, 0}, norms[4] = {0, 0, 0, 0}, stat = 0, s_d, s_p;
  int i, j, r;
  for (i = 0; i < NZ; ++i) {
    double hz = 0, al = 0;
    for (j = 0; j < NZ; ++j) hz += m->h[i + NZ * j] * z[j];
    for (r = 0; r < NA; ++r) al += m->a[r + NA * i] * la[r];
    norms[0] = amax(norms[0], fabs(hz)); norms[1] = amax(norms[1], fabs(m->g[i]));
    norms[2] = amax(norms[2], fabs(al)); norms[3] = amax(norms[3], fabs(lx[i]));
    stat = amax(stat, fabs(hz + m->g[i] + al + lx[i]));
    bound_row(z[i], m->lbx[i], m->ubx[i], lx[i], s);
  }
  for (r = 0; r < NA; ++r) {
    double az = 0;
    for (j = 0; j < NZ; ++j) az += m->a[r + NA * j] * z[j];
    bound_row(az, m->lba[r], m->uba[r], la[r], s);
  }
  s_d = 1 + amax(amax(norms[0], norms[1]), amax(norms[2], norms[3]));
  s_p = 1 + s[0];
  m->cert[0] = stat / s_d;
  m->cert[1] = s[1] / s_p;
  m->cert[2] = s[2] / (s_d * s_p);
  m->cert[3] = s[3] / s_d;
  for (i = 0; i < 4; ++i) if (!(m->cert[i] <= ${N}_CERT_TOL)) return ${N}_CERT_STATIONARITY + i;
  return 0;
}

/* Rounding in h (NZ ε max h_ii) beyond ROUNDING_MARGIN of the curvature h has in exact arithmetic (φᵀφ⊗R): the
   prediction model diverges over the horizon and no solver's answer means anything (QP.not_definite). */
static int ill_conditioned(const mem_t* m) {
  double big = 0;
  int i;
  for (i = 0; i < NZ; ++i) big = amax(big, fabs(m->h[i * (NZ + 1)]));
  return !(NZ * DBL_EPSILON * big <= ROUNDING_MARGIN * CURVATURE);
}

/* The QP in m (h, g, a, lba, uba, lbx, ubx) checked, solved (warm-started from the last solution where m->warm)
   and certified: its status. On a success z_new and the multipliers hold the answer; otherwise
   m->solver_rc says why (the solver's return, or a certificate code). */
static int solve_qp(mem_t* m) {
  int rc;
  m->solver_rc = 0;
  if (!all_finite(m->h, NZ * NZ) || !all_finite(m->g, NZ) || !all_finite(m->a, NA * NZ)
      || any_nan(m->lba, NA) || any_nan(m->uba, NA) || any_nan(m->lbx, NZ) || any_nan(m->ubx, NZ))
    return ${N}_NAN;
  if (any_above(m->lba, m->uba, NA) || any_above(m->lbx, m->ubx, NZ)) return ${N}_INFEASIBLE;
  if (ill_conditioned(m)) {
    m->solver_rc = ${N}_ILL_CONDITIONED;
    return ${N}_EXCEPTION;
  }
  m->arg[0] = m->h; m->arg[1] = m->g; m->arg[2] = m->a; m->arg[3] = m->lba; m->arg[4] = m->uba;
  m->arg[5] = m->lbx; m->arg[6] = m->ubx;
  m->arg[7] = m->warm ? m->z : 0; m->arg[8] = m->warm ? m->lam_x : 0; m->arg[9] = m->warm ? m->lam_a : 0;
  m->arg[10] = 0; m->arg[11] = 0;
  m->res[0] = m->z_new; m->res[1] = 0; m->res[2] = m->lam_a_new; m->res[3] = m->lam_x_new;
  rc = ${name}_qp_solve(m->arg, m->res, (casadi_int*) m->iw, m->w, m->solver_mem);
  m->solver_rc = rc;
  if (rc) return $status_of_rc;
  if (!all_finite(m->z_new, NZ)) return ${N}_NAN;
  rc = certify(m);
  if (rc) {
    m->solver_rc = rc;
    return ${N}_LIMITED;
  }
  return ${N}_SUCCESS;
}

int ${name}_solve_qp(mem_t* m, const double* h, const double* g, const double* a, const double* lba,
                     const double* uba, const double* lbx, const double* ubx, double* z, int* status) {
  memcpy(m->h, h, sizeof m->h);
  memcpy(m->g, g, sizeof m->g);
  if (NA) {
    memcpy(m->a, a, NA * NZ * sizeof(double));
    memcpy(m->lba, lba, NA * sizeof(double));
    memcpy(m->uba, uba, NA * sizeof(double));
  }
  memcpy(m->lbx, lbx, sizeof m->lbx);
  memcpy(m->ubx, ubx, sizeof m->ubx);
  m->warm = 0;
  *status = solve_qp(m);
  memcpy(z, m->z_new, sizeof m->z_new);
  return *status;
}

void ${name}_certificate(const mem_t* m, double* residuals) {
  int i;
  for (i = 0; i < 4; ++i) residuals[i] = m->cert[i];
}

/* Seconds on a monotonic clock (0 where there is none: the split then reads 0). */
static double seconds(void) {
#if defined(CLOCK_MONOTONIC)
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
#else
  return 0.0;
#endif
}

#if LIN_TRAJ
/* The real-time iteration (ocpkit.solvers.nlp.RealTimeIteration, LinearMPC's "trajectory" linearization): the
   model linearized stage by stage along the shifted plan, the condensed QP of these time-varying models, and
   ITERATIONS Gauss–Newton steps, each linearizing along the last one's solution. */

/* ū_k = Σ_j φ_kj z_j for the stages k = 0 … HORIZON−1 (HORIZON x NU, row-major). */
static void stage_inputs(const double* z, double* u) {
  int k, j, i;
  for (k = 0; k < ${N}_HORIZON; ++k)
    for (i = 0; i < NU; ++i) {
      double s = 0;
      for (j = 0; j < NP; ++j) s += PHI_ALL[k * NP + j] * z[j * NU + i];
      u[k * NU + i] = s;
    }
}

/* The trajectory of the first iteration (LinearMPC.shifted_plan): knots z̄ = the plan shifted a step (the input goal
   at a cold start), ū_k = Φ_k z̄, x̄_0 = x and x̄_k the plan's predicted x_{k+1} (a rollout where there is none). */
static void shifted_plan(mem_t* m, const double* x) {
  int j, l, i, k;
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double s = 0;
      if (m->has_plan) for (l = 0; l < NP; ++l) s += SHIFT[j * NP + l] * m->plan[l * NU + i];
      else s = m->ug[i];
      m->zlin[j * NU + i] = s;
    }
  stage_inputs(m->zlin, m->ubark);
  memcpy(m->xbar, x, NX * sizeof(double));
  if (m->has_xplan)
    for (k = 1; k < ${N}_HORIZON; ++k) memcpy(m->xbar + k * NX, m->xplan + (k + 1) * NX, NX * sizeof(double));
}

/* out = L [x; u; 0; 1] = A x + B u + w: the affine model's step. */
static void affine_step(const double* L, const double* x, const double* u, double* out) {
  int i, j;
  for (i = 0; i < NX; ++i) {
    const double* Li = L + i * NL;
    double s = Li[NL - 1];
    for (j = 0; j < NX; ++j) s += Li[j] * x[j];
    for (j = 0; j < NU; ++j) s += Li[NX + j] * u[j];
    out[i] = s;
  }
}

/* Λ_k of every stage about (x̄_k, ū_k); with rollout, x̄_{k+1} = F(x̄_k, ū_k) as it goes. Returns a status. */
static int stage_models(mem_t* m, int rollout) {
  int k;
  for (k = 0; k < ${N}_HORIZON; ++k) {
    double* L = m->LamK + k * NX * NL;
    if (!all_finite(m->xbar + k * NX, NX) || !all_finite(m->ubark + k * NU, NU)) return ${N}_NAN;
    if (affine_model(m, m->xbar + k * NX, m->ubark + k * NU, L)) return ${N}_EXCEPTION;
    if (!all_finite(L, NX * NL)) return ${N}_NAN;
    if (rollout && k + 1 < ${N}_HORIZON) affine_step(L, m->xbar + k * NX, m->ubark + k * NU, m->xbar + (k + 1) * NX);
  }
  return ${N}_SUCCESS;
}

/* The condensed QP of the stage models (CondensedQP.build with one model per stage): the rows [v_k S_k] of
   x_k = S_k z + v_k (prev, NX x NZ1: column 0 is v_k) advance by x_{k+1} = A_k x_k + B_k Φ_k z + w_k, only over the
   columns of the knots active so far (ACTIVE), and each adds its stage cost to Pq. */
static void condense_ltv(mem_t* m, const double* x, const double* xg) {
  double *prev = m->prev, *next = m->next, *sw;
  int i, j, k, u, b, cols = 0;
  for (i = 0; i < NX * NZ1; ++i) prev[i] = next[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (i = 0; i < NZ1 * NZ1; ++i) m->Pq[i] = 0;
  for (k = 0; k < ${N}_HORIZON; ++k) {
    const double* L = m->LamK + k * NX * NL;
    const int c = ACTIVE[k];
    for (i = 0; i < NX; ++i) {
      double* nr = next + i * NZ1;
      for (j = 0; j <= c; ++j) nr[j] = 0;
      nr[0] = L[i * NL + NL - 1];
      for (j = 0; j < NP; ++j) {
        const double f = PHI_ALL[k * NP + j];
        if (f != 0) for (u = 0; u < NU; ++u) nr[1 + j * NU + u] += f * L[i * NL + NX + u];
      }
    }
    gemm(NX, cols + 1, L, NL, 1, prev, NZ1, next, NZ1, 0);
    add_stage(m, next, c + 1, NZ1, 0, xg, m->Pq, NZ1);
#if NB > 0
    for (b = 0; b < NB; ++b) {  /* state-bound rows of x_{k+1}: row (k, b) at k*NB + b */
      const int ri = k * NB + b;
      const double* row = next + XB_COMP[b] * NZ1;
      for (j = 0; j < NZ; ++j) m->a[ri + NA * j] = row[j + 1];
      m->lba[ri] = XB_LO[b] - row[0];
      m->uba[ri] = XB_HI[b] - row[0];
    }
#else
    (void) b;
#endif
    cols = c;
    sw = prev; prev = next; next = sw;
  }
  finish_qp(m, prev, xg);
}

static double max_change(const double* a, const double* b, int n) {
  double d = 0;
  int i;
  for (i = 0; i < n; ++i) d = amax(d, fabs(a[i] - b[i]));
  return d;
}

/* The iterations of one step: their summed split in t (where given). Returns the status; on success the plan,
   its predicted states and the warm start hold the last good iterate. */
static int rti(mem_t* m, const double* x, const double* goal, double* u_out, double* t) {
  const int nxs = (${N}_HORIZON + 1) * NX;
  int it, k, i, rc, done = 0;
  double t0 = 0, t1 = 0, moved = INFINITY;
  shifted_plan(m, x);
  for (it = 0; it < ITERATIONS; ++it) {
    if (t) t0 = seconds();
    rc = stage_models(m, it == 0 && !m->has_xplan);
    if (t) { t1 = seconds(); t[0] += t1 - t0; }
    if (rc == ${N}_SUCCESS) {
      condense_ltv(m, x, goal);
      if (t) { t0 = seconds(); t[1] += t0 - t1; }
      rc = solve_qp(m);
      if (t) t[2] += seconds() - t0;
    }
    if (rc != ${N}_SUCCESS) {
      if (!done) return fallback(m, u_out, rc);
      /* the last good iterate stays the plan; the next step starts the QP cold, as after any failure */
      memcpy(m->plan, m->zgood, sizeof m->zgood);
      memcpy(m->xplan, m->xgood, sizeof m->xgood);
      m->warm = 0;
      break;
    }
    for (i = 0; i < NZ; ++i) { m->plan[i] = m->z[i] = m->z_new[i]; m->lam_x[i] = m->lam_x_new[i]; }
    for (i = 0; i < NA; ++i) m->lam_a[i] = m->lam_a_new[i];
    m->has_plan = m->warm = 1;
    /* the predicted states x_0 … x_T through the stage models */
    memcpy(m->xplan, x, NX * sizeof(double));
    stage_inputs(m->plan, m->ubark);
    for (k = 0; k < ${N}_HORIZON; ++k)
      affine_step(m->LamK + k * NX * NL, m->xplan + k * NX, m->ubark + k * NU, m->xplan + (k + 1) * NX);
    m->has_xplan = 1;
    if (done) moved = amax(max_change(m->plan, m->zgood, NZ), max_change(m->xplan, m->xgood, nxs));
    memcpy(m->zgood, m->plan, sizeof m->zgood);
    memcpy(m->xgood, m->xplan, sizeof m->xgood);
    done = it + 1;
    if (moved <= RTI_TOL) break;
    /* the next iteration linearizes along this one: x̄ = [x; x_1 … x_{T−1}], ū = Φ z (ubark, set above) */
    memcpy(m->xbar + NX, m->xplan + NX, (${N}_HORIZON - 1) * NX * sizeof(double));
  }
  for (i = 0; i < NU; ++i) {
    double s = 0;
    for (k = 0; k < NP; ++k) s += PHI0[k] * m->plan[k * NU + i];
    u_out[i] = s;
  }
  return ${N}_SUCCESS;
}

int ${name}_states(const mem_t* m, double* x_pred) {
  if (!m->has_xplan) return 1;
  memcpy(x_pred, m->xplan, sizeof m->xplan);
  return 0;
}
#endif

int ${name}_step(mem_t* m, const double* x, const double* goal, double* u_out, int* status) {
  return ${name}_step_timed(m, x, goal, u_out, status, 0);
}

int ${name}_step_timed(mem_t* m, const double* x, const double* goal, double* u_out, int* status, double* t) {
  int i, j, rc;
  double t0 = 0, t1 = 0, t2 = 0;
  if (t) { t[0] = t[1] = t[2] = 0; t0 = seconds(); }
  if (input_goal(m, goal, m->ug) || !all_finite(m->ug, NU)) {
    for (i = 0; i < NU; ++i) if (!isfinite(m->ug[i])) m->ug[i] = 0;  /* the cold fallback's input, as in Python */
    *status = fallback(m, u_out, ${N}_NAN);
    return *status;
  }
#if LIN_TRAJ
  (void) j; (void) rc; (void) t0; (void) t1; (void) t2;
  m->solver_rc = 0;
  *status = rti(m, x, goal, u_out, t);
  return *status;
#else
  /* affine model about (x, u_bar) */
  for (i = 0; i < NU; ++i) {
    double s = m->ug[i];
#if LIN_PLAN
    if (m->has_plan) { s = 0; for (j = 0; j < NP; ++j) s += W0[j] * m->plan[j * NU + i]; }
#endif
    m->ubar[i] = s;
  }
  m->solver_rc = 0;
  if (affine_model(m, x, m->ubar, m->Lam1)) {
    *status = fallback(m, u_out, ${N}_EXCEPTION);
    return *status;
  }
  if (!all_finite(m->Lam1, NX * NL)) {
    *status = fallback(m, u_out, ${N}_NAN);
    return *status;
  }
  if (t) { t1 = seconds(); t[0] = t1 - t0; }
  condense(m, x, goal);${task_call}
  if (t) { t2 = seconds(); t[1] = t2 - t1; }
  rc = solve_qp(m);
  if (t) t[2] = seconds() - t2;
  if (rc != ${N}_SUCCESS) {
    *status = fallback(m, u_out, rc);
    return *status;
  }
  for (i = 0; i < NZ; ++i) { m->plan[i] = m->z[i] = m->z_new[i]; m->lam_x[i] = m->lam_x_new[i]; }
  for (i = 0; i < NA; ++i) m->lam_a[i] = m->lam_a_new[i];
  m->has_plan = m->warm = 1;
  /* first input */
  for (i = 0; i < NU; ++i) {
    double s = 0;
    for (j = 0; j < NP; ++j) s += PHI0[j] * m->plan[j * NU + i];
    u_out[i] = s;
  }
  *status = ${N}_SUCCESS;
  return *status;
#endif
}

void ${name}_knots(const mem_t* m, double* knots) {
  int i;
  for (i = 0; i < NZ; ++i) knots[i] = m->plan[i];
}

int ${name}_solver_return(const mem_t* m) { return m->solver_rc; }

const char* ${name}_qp_solver(void) { return "$qp"; }

int ${name}_model_step(mem_t* m, const double* x, const double* u, double* x_next) {
  m->arg[0] = x; m->arg[1] = u; m->res[0] = x_next;
  return ${name}_model(m->arg, m->res, (casadi_int*) m->iw, m->w, 0);
}

size_t ${name}_memory_size(void) { return sizeof(mem_t); }

void ${name}_dims(int* nx, int* nu, int* knots, int* horizon) {
  *nx = NX; *nu = NU; *knots = NP; *horizon = ${N}_HORIZON;
}
""")


# The task's terms in C (ocpkit.transcription._TaskRows.add): inserted after condense where the OCP has a task.
_TASK = Template(r"""/* The task's cost terms, Gauss–Newton about the plan (ocpkit.transcription._TaskRows.add).
   The plan: knots z̄, the previous plan shifted a step (at a cold start the input goal at every knot, clipped to
   the input bounds); its states x̄_k = S_k z̄ + v_k from the QP's own [v S] rows (x̄_0 = x) and inputs
   ū_k = Φ_k z̄ (Φ_k = φ_k ⊗ I). Each residual r_k (weights w) enters as r_k + G_k (z − z̄),
   G_k = ∂r/∂x S_k + ∂r/∂u Φ_k: h += G_kᵀ W G_k, g += G_kᵀ W (r_k − G_k z̄) (h, g: the QP of the cost itself,
   as condense builds them). */

/* The upper triangle of h (column-major) += Gᵀ W G and g += Gᵀ W (r − G z̄) for G (nr x NZ, row-major, zero past
   its first ncol columns) in m->G and r in m->tr. */
static void task_add(mem_t* m, const double* w, int nr, int ncol) {
  double we[${N}_NR1], wg[${N}_NR1];
  int k, i, j;
  for (k = 0; k < nr; ++k) {
    const double* gk = m->G + k * NZ;
    double e = m->tr[k];
    for (j = 0; j < ncol; ++j) e -= gk[j] * m->zbar[j];
    we[k] = w[k] * e;
  }
  for (j = 0; j < ncol; ++j) {
    double* hj = m->h + NZ * j;
    double gj = 0;
    for (k = 0; k < nr; ++k) {
      wg[k] = w[k] * m->G[k * NZ + j];
      gj += m->G[k * NZ + j] * we[k];
    }
    m->g[j] += gj;
    for (i = 0; i <= j; ++i) {
      double v = 0;
      for (k = 0; k < nr; ++k) v += m->G[k * NZ + i] * wg[k];
      hj[i] += v;
    }
  }
}

/* G[:, :c] = ∂r/∂x S for S = Λ_s R, the rows of [v S] at a piece's state s (L: Λ_s; prev, cp, phi, del, c: the
   piece's R as in condense) computed as (∂r/∂x Λ_s) R: nr rows through R instead of NX. */
static void task_jacobian_x(mem_t* m, int nr, const double* L, const double* prev, int cp, const double* phi,
                            const double* del, int c) {
  int a, b, l, col;
  for (a = 0; a < nr; ++a) {
    double* jl = m->JL + a * NL;
    for (l = 0; l < NL; ++l) jl[l] = 0;
    for (b = 0; b < NX; ++b) {
      const double v = m->trx[a + nr * b];
      if (v != 0) for (l = 0; l < NL; ++l) jl[l] += v * L[b * NL + l];
    }
  }
  times_r(m->JL, nr, NL, prev, cp, phi, del, c, m->GX, NZ1);
  for (a = 0; a < nr; ++a)
    for (col = 0; col < c; ++col) m->G[a * NZ + col] += m->GX[a * NZ1 + 1 + col];
}

#if TASK_STAGE
/* Stage k's residual at (x̄_k, ū_k) and its terms; L: Λ_s of x_k in its piece (with prev, cp, p, d, c: the
   piece's R), none at k = 0 (x_0 is given). Returns nonzero if the residual's evaluation failed. */
static int task_stage(mem_t* m, int k, const double* xk, const double* L, const double* prev, int cp,
                      const double* p, const double* d, int c, const double* targets) {
  const double* phi = TASK_PHI + k * NP;
  int a, i, j, col, ncol = L ? c : 0;
  for (i = 0; i < NU; ++i) {
    double s = 0;
    for (j = 0; j < NP; ++j) s += phi[j] * m->zbar[j * NU + i];
    m->tu[i] = s;
  }
  m->arg[0] = xk; m->arg[1] = m->tu; m->arg[2] = targets;
  m->res[0] = m->tr; m->res[1] = m->trx; m->res[2] = m->tru;
  if (${name}_task_stage(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (a = 0; a < ${N}_NRS; ++a) {
    double* ga = m->G + a * NZ;
    for (col = 0; col < NZ; ++col) ga[col] = 0;
    for (j = 0; j < NP; ++j)
      if (phi[j] != 0) {
        for (i = 0; i < NU; ++i) ga[j * NU + i] += phi[j] * m->tru[a + ${N}_NRS * i];
        if (ncol < (j + 1) * NU) ncol = (j + 1) * NU;
      }
  }
  if (L) task_jacobian_x(m, ${N}_NRS, L, prev, cp, p, d, c);
  task_add(m, TASK_WS, ${N}_NRS, ncol);
  return 0;
}
#endif

#if TASK_TERMINAL
/* The terminal residual at x̄_T and its terms; L, prev, cp, p, d, c as in task_stage. */
static int task_terminal(mem_t* m, const double* xT, const double* L, const double* prev, int cp, const double* p,
                         const double* d, int c, const double* targets) {
  int col;
  m->arg[0] = xT; m->arg[1] = targets;
  m->res[0] = m->tr; m->res[1] = m->trx;
  if (${name}_task_terminal(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (col = 0; col < ${N}_NRT * NZ; ++col) m->G[col] = 0;
  task_jacobian_x(m, ${N}_NRT, L, prev, cp, p, d, c);
  task_add(m, TASK_WT, ${N}_NRT, c);
  return 0;
}
#endif

/* The task's terms added to the QP condense built (goal: x_goal, then the targets). The plan's states run forward
   piece by piece as in condense: x̄ = Λ_s y with y = R [1; z̄] the piece's augmented state [x̄_a; v; d; 1]
   (Λ_1 … Λ_LMAX of all states; m->prev holds [v S] at the piece's start). Returns nonzero if a residual's
   evaluation failed. */
static int task_terms(mem_t* m, const double* x, const double* goal) {
  const double* targets = goal + NX;
  double *prev = m->prev, *y = m->ty;
  int pc, i, j, l, s, col;
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double v = 0;
      if (m->has_plan) for (l = 0; l < NP; ++l) v += SHIFT[j * NP + l] * m->plan[l * NU + i];
      else v = clip(m->ug[i], LBX[j * NU + i], UBX[j * NU + i]);
      m->zbar[j * NU + i] = v;
    }
  memcpy(m->LamA, m->Lam1, sizeof m->Lam1);
  for (s = 1; s < LMAX; ++s) times_ahat(m->LamA + (s - 1) * NX * NL, NX, NL, m->Lam1, 1, m->LamA + s * NX * NL);
#if TASK_STAGE
  if (task_stage(m, 0, x, 0, 0, 0, 0, 0, 0, targets)) return 1;
#endif
  for (i = 0; i < NX * NZ1; ++i) prev[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (pc = 0; pc < NPIECE; ++pc) {
    const int a = PIECE_A[pc], Lp = PIECE_L[pc], c = PIECE_C[pc], cp = PIECE_CP[pc];
    const double *phi = PIECE_PHI + pc * NP, *del = PIECE_DELTA + pc * NP;
    for (i = 0; i < NX; ++i) {
      double v = prev[i * NZ1];
      for (col = 0; col < cp; ++col) v += prev[i * NZ1 + 1 + col] * m->zbar[col];
      y[i] = v;
    }
    for (i = 0; i < NU; ++i) {
      double v = 0, dv = 0;
      for (j = 0; j < NP; ++j) { v += phi[j] * m->zbar[j * NU + i]; dv += del[j] * m->zbar[j * NU + i]; }
      y[NX + i] = v;
      y[NX + NU + i] = dv;
    }
    y[NL - 1] = 1;
    for (s = 0; s < Lp; ++s) {
      const double* L = m->LamA + s * NX * NL;  /* Λ_{s+1}: x_{a+s+1} = Λ_{s+1} y */
      for (i = 0; i < NX; ++i) {
        double v = 0;
        for (l = 0; l < NL; ++l) v += L[i * NL + l] * y[l];
        m->tx[i] = v;
      }
      if (a + s + 1 < ${N}_HORIZON) {
#if TASK_STAGE
        if (task_stage(m, a + s + 1, m->tx, L, prev, cp, phi, del, c, targets)) return 1;
#endif
      } else {
#if TASK_TERMINAL
        if (task_terminal(m, m->tx, L, prev, cp, phi, del, c, targets)) return 1;
#endif
      }
    }
    /* [v S] at the piece's end: Λ_Lp R */
    times_r(m->LamA + (Lp - 1) * NX * NL, NX, NL, prev, cp, phi, del, c, m->next, NZ1);
    for (i = 0; i < NX; ++i)
      for (col = 0; col < NZ1; ++col) prev[i * NZ1 + col] = col <= c ? m->next[i * NZ1 + col] : 0.0;
  }
  for (j = 0; j < NZ; ++j)  /* the lower triangle from the upper */
    for (i = 0; i < j; ++i) m->h[j + NZ * i] = m->h[i + NZ * j];
  return 0;
}
""")


def _wrapper(name: str, qp: str, linearization: str, tr: CondensedQP, jac, tf=None, iterations: int = 1,
             tol: float = 0.0) -> str:
    N = name.upper()
    # a nonzero return: qrqp's 4 is "no search direction" (an infeasible or degenerate QP); DAQP's failed exit
    # flags as DAQP_EXIT says (its successes return 0)
    failures = {"qrqp": {4: INFEASIBLE},
                "daqp": {flag: status for flag, (_, status) in DAQP_EXIT.items() if status != SUCCESS}}.get(qp, {})
    status_of_rc = "".join(f"rc == {rc} ? {N}_{status.upper()} : " for rc, status in failures.items()
                           if status != LIMITED) + f"{N}_LIMITED"
    task_c, task_call = "", ""
    if tf is not None:
        task_c = "\n" + _TASK.substitute(name=name, N=N)
        task_call = (f"\n  if (task_terms(m, x, goal)) {{  /* a residual's evaluation failed */\n"
                     f"    *status = fallback(m, u_out, {N}_EXCEPTION);\n    return *status;\n  }}")
    return _WRAPPER.substitute(name=name, N=N, status_of_rc=status_of_rc, qp=qp,
                               constants=_constants(tr, linearization, jac, tf, iterations, tol), task_c=task_c,
                               task_call=task_call)


def _example(name: str, x0, goal, steps: int, dt: float, task: bool = False) -> str:
    N = name.upper()
    ng = f"{N}_NG" if task else f"{N}_NX"  # with a task the goal is [x_goal; targets]
    return f"""/* main.c — closed loop of the exported MPC against the generated discrete model ({steps} steps). */
#define _POSIX_C_SOURCE 199309L /* clock_gettime under -std=c99 */
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
  const double goal[{ng}] = {_c_array(goal)};
  double u[{N}_NU], x_next[{N}_NX], times[{steps}];
  int k, i, status, failures = 0;
  if ({name}_init(&mem)) {{ fprintf(stderr, "init failed\\n"); return 1; }}
  /* warm-up, as a real-time loop does at start-up: the first step's page faults and first allocation are
     not part of the timed loop; reset forgets the plan, so the loop starts cold all the same */
  {name}_step(&mem, x, goal, u, &status);
  {name}_reset(&mem);
  for (k = 0; k < {steps}; ++k) {{
    double t0 = now();
    {name}_step(&mem, x, goal, u, &status);
    times[k] = now() - t0;
    failures += status != {N}_SUCCESS;
    if ({name}_model_step(&mem, x, u, x_next)) {{ fprintf(stderr, "model failed\\n"); return 1; }}
    for (i = 0; i < {N}_NX; ++i) x[i] = x_next[i];
  }}
  qsort(times, {steps}, sizeof(double), cmp);
  printf("steps %d (%.3f s)  failures %d  median step %.1f us  worst %.1f us\\n", {steps}, {steps} * {dt!r},
         failures, 1e6 * times[{steps} / 2], 1e6 * times[{steps} - 1]);
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
    return f"""# Builds the exported MPC step: lib{name}.so (for ocpkit.export.ExportedMPC) and ./example.
# Each source is compiled once (position-independent objects shared by the library and the example).
CC ?= cc
# The generated model and QP solver at OPT; the step's loops (condensing) at OPT_STEP.
OPT ?= {OPT_FLAGS}
OPT_STEP ?= {OPT_STEP}
CFLAGS ?= -fPIC
# QP-solver memory slots per process: how many instances may be live at once.
MAX_INSTANCES ?= {MAX_INSTANCES}
# The condensing's vector code: auto (SSE2, and AVX2+FMA chosen at run time on x86 CPUs that have them),
# sse2 (no AVX2 path), none (plain C loops, any C99 compiler). No -march flag: the library stays portable.
SIMD ?= auto
SIMD_LEVEL = $(if $(filter none,$(SIMD)),0,$(if $(filter sse2,$(SIMD)),1,2))
CPPFLAGS += -DCASADI_MAX_NUM_THREADS=$(MAX_INSTANCES) -DOCPKIT_SIMD=$(SIMD_LEVEL)
{casadi}LDLIBS = {_LIBS[qp]} -lm
OBJ = {name}.o {name}_casadi.o

all: lib example

lib: lib{name}.so

lib{name}.so: $(OBJ)
\t@echo "  LD  $@"
\t@$(CC) $(CFLAGS) -shared -o $@ $(OBJ) $(LDLIBS)

example: main.o $(OBJ)
\t@echo "  LD  $@"
\t@$(CC) $(CFLAGS) -o $@ main.o $(OBJ) $(LDLIBS)

{name}.o: {name}.c {name}.h {name}_casadi.h
\t@echo "  CC  $<"
\t@$(CC) $(CPPFLAGS) $(OPT_STEP) $(CFLAGS) -c -o $@ $<

{name}_casadi.o main.o: %.o: %.c {name}.h {name}_casadi.h
\t@echo "  CC  $<"
\t@$(CC) $(CPPFLAGS) $(OPT) $(CFLAGS) -c -o $@ $<

run: example
\t./example

clean:
\trm -f lib{name}.so example *.o

.PHONY: all lib run clean
"""


def _readme(info: Export, ocp: OCP, eps: float, max_iter: int) -> str:
    n = info.name
    deps = ("none: the sources are self-contained C (C99, libm)." if info.qp == "qrqp" else
            f"CasADi's shipped {info.qp.upper()} headers and static library: `CASADI_DIR` in the Makefile "
            f"points at the casadi Python package (`python -c 'import casadi, os; "
            f"print(os.path.dirname(casadi.__file__))'`); override it with `make CASADI_DIR=...`.")
    tf = ocp.task_functions
    task = "" if tf is None else "\n\n" + textwrap.fill(
        f"The task's cost terms ({', '.join(ocp.terms[2:])}) are part of the QP: `{n}_step`'s goal has "
        f"{ocp.ng} entries (`{n.upper()}_NG`), x_goal then the targets "
        f"({', '.join(f'`{k}`: {v}' for k, v in ocp.task.targets.items()) or 'none'}), as `ocp.goal(...)` "
        f"builds it. Each residual r (its forward kinematics and Jacobians generated by CasADi into "
        f"`{n}_casadi.c`) enters by Gauss–Newton about the plan — the previous plan shifted a step (the input goal "
        f"at every knot at a cold start) and the states the QP predicts from it: r + G (z−z̄), "
        f"G = ∂r/∂x S + ∂r/∂u Φ (`ocpkit.transcription._TaskRows`).", 110)
    return f"""# Exported MPC step `{n}`

Generated by `ocpkit.export` for `{ocp!r}`: {info.form} QP ({info.knots} knots x {info.nu} inputs,
{info.n_constraints} state-bound rows), horizon {info.horizon}, dt = {ocp.dt} s, solved by CasADi's
`{info.qp}` (tolerance {eps:g}, at most {max_iter} iterations).

Each `{n}_step` linearizes the model about the current state x and u_bar, {_UBAR[info.linearization]},
builds the condensed QP (paper Section V-B/V-E), solves it and returns the first input. A solution counts
only if its KKT certificate holds (stationarity, primal feasibility, complementarity and dual sign within
{CERT_TOL:g} relative to the data; `{n}_certificate` gives the residuals). On a failure it returns the previous
plan advanced one step, clipped to the input bounds, and the next step starts cold.
{_SOLVER_NOTE[info.qp]}{task}

## Files

- `{n}.h` — the API (documented in the header): `{n}_init`, `{n}_step`, `{n}_reset`, `{n}_knots`,
  `{n}_model_step`, `{n}_free`; statuses `{n.upper()}_SUCCESS`, `_LIMITED`, `_INFEASIBLE`, `_NAN`,
  `_EXCEPTION`.
- `{n}.c` — the step: RK4 and its sensitivities from the generated f and Jacobians, the condensed QP built
  over the horizon's pieces (Λ_s, Γ_L of `ocpkit.transcription.CondensedQP`, Γ_L by doubling), checks,
  fallback; `{n}_step_timed` also returns the seconds of model, condensing and QP solve. `{n}_casadi.c/.h` —
  CasADi-generated continuous dynamics and sparse Jacobians (once), the discrete model and the QP solver.
- `main.c` — a closed loop against the generated discrete model; `Makefile`.

## Build

    make          # lib{n}.so and ./example (each source compiled once: `OPT ?= {OPT_FLAGS}`, `OPT_STEP ?= {OPT_STEP}`)
    make run      # runs the closed loop, prints median and worst step time and the final state

The condensing's products use SSE2 vectors, and AVX2+FMA where the CPU has them (checked once at run time,
so one build runs on any x86-64); `make SIMD=sse2` leaves the AVX2 path out, `make SIMD=none` builds plain
C loops for compilers without GCC/Clang vector extensions.

Several instances may run in one process: each `{n}_memory` is one controller (`{n}_init` ...
`{n}_free`); at most `MAX_INSTANCES` (Makefile, default {MAX_INSTANCES}) are live at once.

Dependencies: {deps}

In Python: `ocpkit.export.ExportedMPC(ocp, "{info.out_dir.name}")` loads `lib{n}.so` as a Controller.
"""


# ---------------------------------------------------------------------------------------------------
# Loading the built library back into Python


class ExportedMPC(Controller):
    """The compiled exported step (``lib<name>.so`` in ``out_dir``) as a Controller, through ctypes.

    Statuses map one to one onto ocpkit's; on failure the library already returns the fallback input and
    plan, which equal :meth:`Controller.fallback`. ``times`` splits the C step as the DESIGN does, measured in C:
    ``model`` (RK4 and its sensitivities), ``build`` (the condensing), ``solve`` (the QP solver);
    :attr:`step_seconds` is the last whole C step seen from Python (ctypes call included). Each instance owns
    its C memory (several may step in one process, up to the library's ``MAX_INSTANCES``); :meth:`close`, or
    leaving a ``with`` block, gives its QP-solver slot back.
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
        self._step = getattr(lib, f"{name}_step_timed")
        self._step.argtypes = [ctypes.c_void_p] * 6
        self._step.restype = ctypes.c_int
        self._knots = getattr(lib, f"{name}_knots")
        self._knots.argtypes = [ctypes.c_void_p, dbl]
        self._model = getattr(lib, f"{name}_model_step")
        self._model.argtypes = [ctypes.c_void_p, dbl, dbl, dbl]
        self._rc = getattr(lib, f"{name}_solver_return")
        self._certificate = getattr(lib, f"{name}_certificate")
        self._certificate.argtypes = [ctypes.c_void_p, dbl]
        solver_name = getattr(lib, f"{name}_qp_solver")
        solver_name.restype = ctypes.c_char_p
        self.qp = solver_name().decode()
        self._solve_qp = getattr(lib, f"{name}_solve_qp")
        self._solve_qp.argtypes = [ctypes.c_void_p] + [dbl] * 8 + [ctypes.c_void_p]
        self._lib, self.name, self.out_dir = lib, name, Path(out_dir)
        self._free = getattr(lib, f"{name}_free")
        try:  # a "trajectory" step's predicted states
            self._states = getattr(lib, f"{name}_states")
            self._states.argtypes = [ctypes.c_void_p, dbl]
        except AttributeError:
            self._states = None
        self._open = False
        if getattr(lib, f"{name}_init")(self._mem):
            raise RuntimeError(f"{name}_init failed: all QP solver memory slots of {lib_path} are in use "
                               f"(close() other instances, or rebuild with make MAX_INSTANCES=N)")
        self._open = True
        self._status = ctypes.c_int()
        self._status_ptr = ctypes.addressof(self._status)
        self._split = np.zeros(3)
        self.step_seconds = float("nan")
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    path = "C step"

    def __repr__(self):
        return f"ExportedMPC({str(self.out_dir / ('lib' + self.name + '.so'))!r}, {self.ocp!r})"

    def close(self) -> None:
        """Give the instance's C memory back (its QP-solver slot); further steps raise. Safe to call twice."""
        if getattr(self, "_open", False):
            self._free(self._mem)
            self._open = False

    @property
    def closed(self) -> bool:
        return not self._open

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may already be gone
            pass

    def _check_open(self):
        if not self._open:
            raise RuntimeError(f"{self!r} is closed")

    def reset(self) -> None:
        super().reset()
        if getattr(self, "_open", False):
            getattr(self._lib, f"{self.name}_reset")(self._mem)

    def model_step(self, x, u) -> np.ndarray:
        """x⁺ from the library's generated discrete model (the model the controller predicts with)."""
        x = self.ocp.check_state(x, "x")
        u = array(u, "u", (self.ocp.nu,))
        self._check_open()
        out = np.empty(self.ocp.nx)
        if self._model(self._mem, x, u, out):
            raise RuntimeError("generated discrete model failed")
        return out

    def certificate(self) -> Certificate:
        """The KKT certificate the C code computed for its last QP solve (:mod:`ocpkit.certificate`)."""
        self._check_open()
        out = np.zeros(4)
        self._certificate(self._mem, out)
        return Certificate(*out)

    def solve_qp(self, qp) -> tuple[str, np.ndarray]:
        """(status, z) of the C step's QP solve and certificate on ``qp``, a condensed knot QP of this library's size
        (an :class:`ocpkit.transcription.QP` with the knot bounds as its box and state-bound rows after them) — to
        test the solver and the certificate in C on QPs of one's own. The next step starts cold."""
        self._check_open()
        nz = self.ocp.knots * self.ocp.nu
        k = 0 if qp.box is None else len(qp.box)
        if qp.n != nz or qp.b.size:
            raise ValueError(f"qp must have {nz} variables and no equality rows, got {qp.n} and {qp.b.size}")
        lbx, ubx = np.full(nz, -np.inf), np.full(nz, np.inf)
        lbx[qp.box], ubx[qp.box] = qp.l[:k], qp.u[:k]
        C = np.asarray(qp.C.toarray() if hasattr(qp.C, "toarray") else qp.C, dtype=float)[k:]
        col = (lambda v: np.ascontiguousarray(v, dtype=float))
        z, status = np.empty(nz), ctypes.c_int()
        self._solve_qp(self._mem, col(np.asarray(qp.P, dtype=float).T), col(qp.q), col(C.T), col(qp.l[k:]),
                       col(qp.u[k:]), col(lbx), col(ubx), z, ctypes.addressof(status))
        return STATUSES[status.value], z

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        """The C step from ``x``; ``goal``: x_goal, or the whole goal vector [x_goal; targets]. With a task the
        step takes the whole vector: ``goal`` where it is one; from :meth:`solve` (x_goal, its own slice) the
        :attr:`task_goal` it was given. Another caller with a task (LinearMPC) passes the whole vector."""
        self._check_open()
        if self.ocp.task_functions is not None and np.size(goal) != self.ocp.ng:
            if goal is not self._goal:
                raise ValueError(f"this C step has a task: it needs the whole goal vector of {self.ocp.ng} entries "
                                 f"[x_goal; targets] (ocp.goal(...)), got {np.size(goal)}")
            goal = self.task_goal
        u = np.empty(self.ocp.nu)
        knots = np.empty(self.ocp.knots * self.ocp.nu)
        x, goal = np.ascontiguousarray(x), np.ascontiguousarray(goal)
        args = (self._mem, x.ctypes.data, goal.ctypes.data, u.ctypes.data, self._status_ptr, self._split.ctypes.data)
        t0 = time.perf_counter()
        self._step(*args)
        self.step_seconds = time.perf_counter() - t0
        self._knots(self._mem, knots)
        status = STATUSES[self._status.value]
        rc = self._rc(self._mem)
        certificate = self.certificate() if status == SUCCESS or rc >= _CERT_CODE else None  # a QP solved
        raw = _explain_rc(self.name, self.qp, rc, certificate.residuals if certificate else ())
        model, build_s, solve = (float(t) for t in self._split)
        x_pred = None
        if self._states is not None and status == SUCCESS:
            x_pred = np.empty((self.ocp.horizon + 1, self.ocp.nx))
            if self._states(self._mem, x_pred):
                x_pred = None
        return Solution(u=u, knots=knots.reshape(self.ocp.knots, self.ocp.nu), status=status, raw_status=raw,
                        times={"model": model, "build": build_s, "solve": solve}, fallback=status != SUCCESS,
                        certificate=certificate, x_pred=x_pred)


def _explain_rc(name: str, qp: str, rc: int, residuals) -> str:
    """The raw status of a C step whose solver (``qp``) returned ``rc`` (``residuals``: its certificate)."""
    if _CERT_CODE <= rc < _CERT_CODE + len(TESTS):
        test = TESTS[rc - _CERT_CODE]
        return (f"{name}_qp_solve returned 0 but certificate failed: {test} residual "
                f"{residuals[rc - _CERT_CODE]:.3g} > {CERT_TOL:.0e}")
    if rc == _ILL_CONDITIONED:
        return (f"{name}: Hessian ill-conditioned (rounding beyond {ROUNDING_MARGIN:g} x the input weight's "
                f"curvature): the prediction model diverges over the horizon")
    if qp == "daqp" and rc in DAQP_EXIT:
        return f"{name}_qp_solve returned {rc}: {daqp_exit_name(rc)}"
    return f"{name}_qp_solve returned {rc}"


def export_problem(problem_name: str, form: str = "condensed", knots: int | None = 5, horizon: int | None = 100,
                   qp: str = "daqp", out_dir="export", *, seed: int = 0, steps: int = 100,
                   force: bool = False) -> Export:
    """Export a problem by spec (``ocpkit.problems.make``: a registered name, ``module:Name`` or ``file.py:Name``)
    with the example closed loop from ``sample(seed)``; ``out_dir`` absent or empty unless ``force``."""
    from ocpkit.problems import make

    problem = make(problem_name)
    ocp = problem.ocp(knots=knots, horizon=horizon)
    _check_out_dir(Path(out_dir), force)  # before sampling and code generation
    x0, goal = problem.sample(seed)
    return export(ocp, out_dir, form=form, qp=qp, x0=x0, goal=goal, steps=steps, force=force)

