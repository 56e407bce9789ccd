"""The exported folder's text files, rendered from the C, header, Makefile and README templates under
``templates/`` (Jinja2: ``{{ value }}``, ``{% if %}`` blocks on their own lines; files named ``*.in.c`` and
``*.in.h`` so editors treat them as C)."""

from __future__ import annotations

import re
from pathlib import Path

import casadi as ca
import jinja2

from ocpkit.qp.certificate import TOL as CERT_TOL
from ocpkit.status import INFEASIBLE, LIMITED, REASONS, SOFT, STATUSES, SUCCESS, Reason
from ocpkit.export.constants import CERT_CODE, CERT_NAMES, ILL_CONDITIONED, c_array, step_constants
from ocpkit.qp.daqp import DAQP_EXIT, DAQP_REASON
from ocpkit.model.task import ACTIVATION, ROWS_PER_SPHERE
from ocpkit.model.ocp import OCP
from ocpkit.qp.transcription import CondensedQP

MAX_INSTANCES = 16  # QP-solver memory slots per loaded library (CASADI_MAX_NUM_THREADS); a Makefile variable
OPT_FLAGS = "-O2"  # the Makefile's OPT default (generated model and QP solver)
OPT_STEP = "-O3"  # the Makefile's OPT_STEP default (the condensing loops: -O3 vectorizes them)
C_STATUSES = STATUSES[: STATUSES.index(SOFT)]  # the C step's statuses, numbered 0 … 4 (it never answers "soft")
_SOLVER_NOTE = {
    "qrqp": "qrqp is warm-started from the previous solution; `step` never allocates.",
    "daqp": "CasADi's DAQP code starts DAQP cold and runs its setup, which allocates, inside every step.",
    "osqp": "OSQP is set up (allocating) once in `init` and warm-started; `step` does not allocate.",
}
_UBAR = {
    "goal": "the input goal u_g = u_goal + K goal (+ the problem's goal input h(goal))",
    "trajectory": "per stage k, the previous plan shifted one step (its inputs and predicted states; a "
    "rollout of the model at a cold start): real-time iteration",
    "plan": "the input the previous plan expects now (the input goal at a cold start)",
}
_CASADI_DIR = Path(ca.__file__).resolve().parent
_LIBS = {"qrqp": "", "daqp": "$(CASADI_DIR)/libdaqpstat.a", "osqp": "$(CASADI_DIR)/libosqpstatic.a"}

_TEMPLATES = jinja2.Environment(
    loader=jinja2.PackageLoader("ocpkit.export", "templates"),
    undefined=jinja2.StrictUndefined,
    keep_trailing_newline=True,
    trim_blocks=True,
    lstrip_blocks=True,
    autoescape=False,
)


def _failures(qp: str) -> tuple[dict, str]:
    """The QP solver's failed returns the C step names, return → (C name, status, reason name: NONE where the return
    says none), and where they come from; any other nonzero return is "limited", for no reason said."""
    if qp == "qrqp":
        return (
            {
                4: ("QRQP_NO_SEARCH_DIRECTION", INFEASIBLE, Reason.QP_INFEASIBLE.name),
                -1: ("QRQP_MAX_ITER", LIMITED, Reason.ITERATION_LIMIT.name),
            },
            "qrqp's 4: an infeasible or degenerate QP, -1: its iteration limit",
        )
    if qp == "daqp":
        return (
            {
                flag: (
                    "DAQP_" + re.sub(r"\W+", "_", name).upper(),
                    status,
                    DAQP_REASON[flag].name if flag in DAQP_REASON else "NONE",
                )
                for flag, (name, status) in DAQP_EXIT.items()
                if status != SUCCESS
            },
            "DAQP's exit flags, ocpkit.qp.daqp.DAQP_EXIT and DAQP_REASON",
        )
    return {}, ""


def _render(template: str, **values) -> str:
    return _TEMPLATES.get_template(template).render(**values)


def _task_values(ocp: OCP, code: bool) -> dict:
    """The task's terms and targets in words (``code``: target names as Markdown code), and its obstacles: how many,
    the robot's spheres, the margin and the rows' bound (:meth:`ocpkit.qp.task_rows.TaskRows.select`)."""
    targets = ", ".join(f"`{k}`: {v}" if code else f"{k}: {v}" for k, v in ocp.task.targets.items())
    task = ocp.task
    return {
        "terms": ", ".join(ocp.terms[2:]),
        "targets": targets or "none",
        "n_obstacles": len(task.obstacles),
        "robot_spheres": len(task.robot),
        "margin": f"{task.margin:g}",
        "activation": f"{ACTIVATION:g}",
        "per_sphere": ROWS_PER_SPHERE,
    }


def header(name: str, sizes: dict, ocp: OCP, form: str, qp: str, linearization: str) -> str:
    """``<name>.h``: the API, the sizes (``sizes``: macro name → value) and the memory struct."""
    task = ocp.task_functions is not None
    return _render(
        "header.in.h",
        name=name,
        N=name.upper(),
        sizes=sizes,
        ocp=repr(ocp),
        form=form,
        qp=qp,
        statuses=C_STATUSES,
        reasons=REASONS,
        ubar=_UBAR[linearization],
        task=task,
        obstacles=task and ocp.task_functions.pairs > 0,
        rti=linearization == "trajectory",
        cert_tol=repr(CERT_TOL),
        cert_code=CERT_CODE,
        cert_names=list(CERT_NAMES.values()),
        ill_conditioned=ILL_CONDITIONED,
        **(_task_values(ocp, code=False) if task else {}),
    )


def step(
    name: str,
    qp: str,
    linearization: str,
    tr: CondensedQP,
    jac,
    digest: list[str],
    tf=None,
    iterations: int = 1,
    tol: float = 0.0,
    obstacle_rows: int = 0,
) -> str:
    """``<name>.c``: the step around the generated model and QP solver, with its constants (``digest``: the OCP's
    entries, :func:`ocpkit.export.digest.ocp_entries`; ``obstacle_rows``: the most clearance rows a stage, 0 without
    obstacles)."""
    failures, failures_source = _failures(qp)
    return _render(
        "step.in.c",
        name=name,
        N=name.upper(),
        qp=qp,
        failures=failures,
        failures_source=failures_source,
        task=tf is not None,
        statuses=C_STATUSES,
        reasons=REASONS,
        cert_names=list(CERT_NAMES.values()),
        digest=digest,
        obstacles=bool(obstacle_rows),
        constants=step_constants(tr, linearization, jac, tf, iterations, tol, obstacle_rows),
    )


def example(
    name: str, x0, goal, steps: int, dt: float, task: bool = False, obstacles: bool = False, reference: int = 0
) -> str:
    """``main.c``: a closed loop of ``steps`` steps from ``x0`` towards ``goal`` against the generated model; with
    ``reference`` (its rows) along the rows of ``reference.csv`` by the window step instead."""
    return _render(
        "main.in.c",
        name=name,
        N=name.upper(),
        x0=c_array(x0),
        goal=c_array(goal),
        steps=steps,
        dt=repr(dt),
        task=task,
        obstacles=obstacles,
        reference=reference,
    )


def makefile(name: str, qp: str) -> str:
    """``Makefile``: the library and the example, the QP solver's static library from CasADi's package."""
    return _render(
        "Makefile.in",
        name=name,
        opt=OPT_FLAGS,
        opt_step=OPT_STEP,
        max_instances=MAX_INSTANCES,
        library=_LIBS[qp],
        casadi_dir=_CASADI_DIR,
    )


def readme(info, ocp: OCP, eps: float, max_iter: int, reference: bool = False) -> str:
    """``README.md``: what the folder holds (``info``: the :class:`~ocpkit.export.Export`; ``reference``: the example
    follows reference.csv), how to build it."""
    task = ocp.task_functions is not None
    return _render(
        "README.in.md",
        name=info.name,
        N=info.name.upper(),
        ocp=repr(ocp),
        form=info.form,
        knots=info.knots,
        nu=info.nu,
        n_constraints=info.n_constraints,
        horizon=info.horizon,
        dt=ocp.dt,
        qp=info.qp,
        eps=f"{eps:g}",
        max_iter=max_iter,
        ubar=_UBAR[info.linearization],
        cert_tol=f"{CERT_TOL:g}",
        solver_note=_SOLVER_NOTE[info.qp],
        task=task,
        obstacle_rows=info.obstacle_rows,
        ng=ocp.ng if task else None,
        opt=OPT_FLAGS,
        opt_step=OPT_STEP,
        max_instances=MAX_INSTANCES,
        folder=info.out_dir.name,
        reference=reference,
        **(_task_values(ocp, code=True) if task else {}),
    )
