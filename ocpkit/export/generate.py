"""Writing an exported folder: the generated model, task and QP solver (CasADi code generation), then the step,
header, example, Makefile and README rendered from the templates (:mod:`ocpkit.export.render`)."""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ocpkit._checks import choice, integer, positive
from ocpkit.export import render
from ocpkit.export.digest import ocp_entries
from ocpkit.export.folder import check_out_dir, place, write
from ocpkit.export.qp import conic, fix_daqp_setup
from ocpkit.model.ocp import OCP
from ocpkit.model.problem import check_dynamics
from ocpkit.model.task import ROWS_PER_SPHERE, ROWS_PER_STAGE
from ocpkit.qp.transcription import CondensedQP

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
    n_constraints: int  # state-bound rows
    obstacle_rows: int = 0  # the most linearized clearance rows a step appends after them (a task with obstacles)

    @property
    def library(self) -> Path:
        """The shared library ``make`` builds in the folder."""
        return self.out_dir / f"lib{self.name}.so"

    @property
    def c_bytes(self) -> int:
        """Bytes of generated C (sources and headers, the example included)."""
        return sum(p.stat().st_size for p in self.out_dir.iterdir() if p.suffix in (".c", ".h"))


def export(
    ocp: OCP,
    out_dir,
    *,
    form: str = "condensed",
    qp: str = "daqp",
    name: str = "mpc",
    eps: float = 1e-9,
    max_iter: int = 1000,
    linearization: str = "goal",
    x0=None,
    goal=None,
    steps: int = 100,
    force: bool = False,
    polish: bool = False,
    iterations: int = 1,
    tol: float = 0.0,
    reference=None,
) -> Export:
    """Write C sources, header, Makefile, example ``main.c`` and README for the MPC step of ``ocp``.

    ``out_dir`` must be absent or empty unless ``force`` (then the exported files in it are replaced: each is
    written as a new file renamed into place); it must not be a symbolic link nor hold one.
    ``eps`` is the QP solver's tolerance, ``max_iter`` its iteration limit, ``polish`` OSQP's solution
    polishing; ``linearization`` "goal" linearizes about (x, u_g), "plan" about (x, ū) as LinearMPC's option
    of that name, "trajectory" stage by stage along the shifted plan: the real-time iteration of
    :class:`~ocpkit.solvers.rti.RealTimeIteration`, ``iterations`` Gauss–Newton steps per control step, fewer
    where one moves the plan (knots and predicted states, max norm) by at most ``tol``; ``x0``, ``goal`` (with
    a task the goal vector [x_goal; targets] of ``ocp.goal``) and ``steps`` set the closed loop the example runs
    against the generated discrete model (where given, the dynamics must be finite there: else a DynamicsError
    names them, before any file is written). ``reference``: the goal at each of the example's steps and beyond,
    (``steps`` + T + 1, ng) rows (a :class:`~ocpkit.model.reference.Reference`'s ``window(0, dt, steps + T)``): written
    to ``reference.csv``, which the example reads and follows with the window step (``<name>_step_window``, each step
    the rows k … k + T), in place of ``goal``. A task's cost terms and obstacles are exported (linearization "goal" or
    "plan"), its obstacles as hard clearance rows (see the package docstring)."""
    if not isinstance(ocp, OCP):
        raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
    choice(form, FORMS, "form")
    choice(qp, QP_SOLVERS, "qp")
    if (form, qp) not in SUPPORTED:
        why = _UNSUPPORTED_WHY["sparse" if form == "sparse" else qp]
        raise ValueError(f"qp={qp!r} with form={form!r} cannot be exported: {why}; supported: {sorted(SUPPORTED)}")
    choice(linearization, LINEARIZATIONS, "linearization")
    iterations = integer(iterations, "iterations", 1)
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    if linearization != "trajectory" and (iterations != 1 or tol != 0):
        raise ValueError(f"iterations and tol are options of linearization 'trajectory', not {linearization!r}")
    tf = ocp.task_functions
    if tf is not None and linearization == "trajectory":
        raise ValueError(
            f"an OCP with a task (terms {ocp.terms[2:]}) cannot be exported with linearization "
            "'trajectory': the C step's task terms are linearized about the goal's model; use "
            "linearization 'goal' or 'plan', or the Python step"
        )
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    eps = positive(eps, "eps")
    max_iter = integer(max_iter, "max_iter", 1)
    steps = integer(steps, "steps", 1)
    given = {"the example's start x0": x0 is not None, "the example's goal": goal is not None}
    x0 = np.zeros(ocp.nx) if x0 is None else ocp.check_state(x0, "x0")
    # With a task the goal is [x_goal; targets] (ocp.goal): the step's goal input has ng entries.
    ng = ocp.ng if tf is not None else ocp.nx
    if reference is not None:
        reference = np.asarray(reference, dtype=float)
        if reference.shape != (steps + ocp.horizon + 1, ng) or not np.isfinite(reference).all():
            raise ValueError(
                f"reference must be {steps + ocp.horizon + 1} rows (steps + T + 1) of {ng} finite goal entries, got "
                f"shape {reference.shape}"
            )
        given["the example's goal"] = True
        goal = reference[0]
    if goal is None:
        goal = np.zeros(ng)
    else:
        goal = ocp.check_goal(goal) if tf is not None else ocp.check_state(goal, "goal")
    for x, label in zip((x0, goal[: ocp.nx]), given):
        if given[label]:  # where the example's closed loop runs: NaN dynamics there are named before any work
            check_dynamics(ocp.model, x, ocp.input_goal(goal[: ocp.nx]), context=label)
    out = Path(out_dir)
    check_out_dir(out, bool(force))
    out.mkdir(parents=True, exist_ok=True)

    # The joint-space condensing's data; the task's terms are generated below (its Python rows not needed).
    tr = CondensedQP(ocp, task=False)
    na = tr.x_rows.size
    nos = rows_a_stage(tf) if tf is not None and tf.pairs else 0  # clearance rows a stage at most
    no = ocp.horizon * nos  # the QP's rows after the state bounds'
    lin, model, jac = _model_functions(ocp, name)
    solver = conic(qp, name, tr.nz, na + no, eps, max_iter, polish)
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
            fix_daqp_setup(scratch / f"{name}_casadi.c")
        for path in sorted(scratch.iterdir()):
            place(path, out / path.name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    sizes = {
        "NX": ocp.nx,
        "NU": ocp.nu,
        "KNOTS": ocp.knots,
        "HORIZON": ocp.horizon,
        "NZ": tr.nz,
        "NA": na + no,
        "NL": ocp.nx + 2 * ocp.nu + 1,
        "LMAX": max(tr._lengths),
        "NLEN": len(tr._lengths),
        "NB": int(np.count_nonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max))),
        "NNZ_FX": len(jac[0][0]) if jac else 0,
        "NNZ_FU": len(jac[1][0]) if jac else 0,
        "SZ_ARG": max(f.sz_arg() for f in all_f),
        "SZ_RES": max(f.sz_res() for f in all_f),
        "SZ_IW": max(f.sz_iw() for f in all_f),
        "SZ_W": max(f.sz_w() for f in all_f),
    }
    if task is not None:
        sizes.update(NG=ng, NRS=tf.stage_weight.size, NRT=tf.terminal_weight.size)
    if no:
        spheres, obstacles = tf.radii.size, tf.table.shape[1]
        sizes.update(NO=no, NOS=nos, NK=spheres, NOB=obstacles, NOC=spheres * min(ROWS_PER_SPHERE, obstacles))
    info = Export(out, name, form, qp, linearization, ocp.nx, ocp.nu, ocp.knots, ocp.horizon, na, no)
    write(out / f"{name}.h", render.header(name, sizes, ocp, form, qp, linearization))
    write(
        out / f"{name}.c",
        render.step(name, qp, linearization, tr, jac, ocp_entries(ocp), tf, iterations, float(tol), nos),
    )
    rows = 0 if reference is None else len(reference)
    write(out / "main.c", render.example(name, x0, goal, steps, ocp.dt, tf is not None, bool(no), rows))
    if rows:
        names = ocp.goal_names()
        write(
            out / "reference.csv",
            ",".join(names) + "\n" + "".join(",".join(map(repr, map(float, r))) + "\n" for r in reference),
        )
    write(out / "Makefile", render.makefile(name, qp))
    write(out / "README.md", render.readme(info, ocp, eps, max_iter, reference=bool(rows)))
    return info


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
        return (
            ca.Function(
                f"{name}_affine",
                [xs, us],
                [ca.densify(Ad), ca.densify(Bd), ca.densify(wd)],
                ["x", "u"],
                ["Ad", "Bd", "wd"],
            ),
            ca.Function(f"{name}_model", [xs, us], [step], ["x", "u"], ["x_next"]),
            None,
        )
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


def general_rows(ocp: OCP) -> int:
    """The exported QP's general rows: the state-bound rows, then room for the obstacles' rows at every stage."""
    tf = ocp.task_functions
    bounded = np.count_nonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max))
    return ocp.horizon * (int(bounded) + (rows_a_stage(tf) if tf is not None and tf.pairs else 0))


def rows_a_stage(tf) -> int:
    """The most clearance rows one stage can have under :meth:`ocpkit.qp.task_rows.TaskRows.select`'s bound (``tf``:
    :class:`ocpkit.model.task.CompiledTask` with obstacles): the QP has room for them at every stage."""
    return min(ROWS_PER_STAGE, tf.radii.size * min(ROWS_PER_SPHERE, tf.table.shape[1]))


def _task_functions(tf, name: str) -> list:
    """The task's functions for the C step (``tf``: :class:`ocpkit.model.task.CompiledTask`), generated per stage:
    ``<name>_task_stage`` (x, u, targets) -> (r, ∂r/∂x, ∂r/∂u) and ``<name>_task_terminal`` (x, targets) -> (r,
    ∂r/∂x), the Jacobians dense (column-major); a part without terms is left out. With obstacles ``<name>_spheres``
    (x) -> (C, C_x): the robot spheres' centres and their Jacobians as ``tf.spheres`` gives them, from which the step
    computes the clearances and their gradients as TaskRows does in numpy."""
    x, u, g = ca.SX.sym("x", tf.nx), ca.SX.sym("u", tf.nu), ca.SX.sym("g", tf.size)
    out = []
    if tf.stage_weight.size:
        r, rx, ru = tf.stage_residual(x, u, g)
        out.append(
            ca.Function(
                f"{name}_task_stage",
                [x, u, g],
                [r, ca.densify(rx), ca.densify(ru)],
                ["x", "u", "g"],
                ["r", "r_x", "r_u"],
            )
        )
    if tf.terminal_weight.size:
        r, rx = tf.terminal_residual(x, g)
        out.append(ca.Function(f"{name}_task_terminal", [x, g], [r, ca.densify(rx)], ["x", "g"], ["r", "r_x"]))
    if tf.pairs:
        out.append(ca.Function(f"{name}_spheres", [x], list(tf.spheres(x)), ["x"], ["C", "C_x"]))
    return out


def export_problem(
    problem_name: str,
    form: str = "condensed",
    knots: int | None = 5,
    horizon: int | None = 100,
    qp: str = "daqp",
    out_dir="export",
    *,
    seed: int = 0,
    steps: int = 100,
    force: bool = False,
) -> Export:
    """Export a problem by spec (``ocpkit.problems.make``: a registered name, ``module:Name`` or ``file.py:Name``)
    with the example closed loop from ``sample(seed)``; ``out_dir`` absent or empty unless ``force``."""
    from ocpkit.problems import make

    problem = make(problem_name)
    ocp = problem.ocp(knots=knots, horizon=horizon)
    check_out_dir(Path(out_dir), force)  # before sampling and code generation
    x0, goal = problem.sample(seed)
    return export(ocp, out_dir, form=form, qp=qp, x0=x0, goal=goal, steps=steps, force=force)
