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
  The condensing mirrors :class:`~ocpkit.qp.transcription.CondensedQP.build`: Λ_s = [A_d^s E_s F_s e_s],
  Γ_L = Σ_{s≤L} Λ_sᵀQΛ_s and per piece of the parameterization Rᵀ Γ_L R. Γ_L is built in O(log L) products
  (Λ_s = C Â^s for the piece's augmented state [x; v; d; 1], so Γ_2s = Γ_s + (Â^s)ᵀ Γ_s Â^s, Λ_2s = Λ_s Â^s),
  and every product is one small GEMM kernel whose tiles of C stay in vector registers (GCC/Clang vector
  extensions: SSE2, plus AVX2+FMA chosen at run time on CPUs that have them; ``make SIMD=sse2|none``).
  Constants (Q^½, R, the basis' pieces, bounds, the Γ schedule) are static arrays.
* With a task (:mod:`ocpkit.model.task`: cost terms such as a frame's position) its stage and terminal residuals and
  their dense Jacobians are generated per stage (``<name>_task_stage``, ``<name>_task_terminal``), and the step
  adds their Gauss–Newton model about the plan to the condensed QP as :class:`ocpkit.qp.task_rows.TaskRows` does
  (``task_terms`` in ``<name>.c``: the plan's states and ∂r/∂x S piece by piece, ∂r/∂x S as (∂r/∂x Λ_s) R). The
  step's goal is then the whole goal vector [x_goal; targets] (``ocp.goal(...)``, ``NG`` entries).
* With obstacles the robot spheres' centres and Jacobians are generated too (``<name>_spheres``, the obstacles a
  table of constants), and at each of the plan's states the step computes the clearances, keeps the pairs
  :meth:`~ocpkit.qp.task_rows.TaskRows.select` keeps (within ``ACTIVATION`` of the margin, each sphere's closest, a
  bounded number a stage) and appends their rows d + ∂d/∂x S_k (z − z̄) ≥ 0 after the state-bound rows, in the
  Python step's order (``obstacles.in.c``). The QP has room for the bound at every stage (``NO`` rows, the Panda's:
  24 × 50); the rows a step leaves unused are zero and unbounded, and DAQP leaves zero rows out. The rows are hard:
  where they make the QP infeasible (a start inside the margin) the step returns "infeasible" and its fallback
  — :class:`~ocpkit.solvers.qp.LinearMPC` then solves the QP with the obstacle rows softened in Python, as it does
  the soft state bounds — and ``<name>_set_plan`` lets the next step linearize about the plan that answered
  (:meth:`ExportedMPC.set_plan`).

The library names its statuses (``<name>_status_string``: "success" … "exception", as
:data:`ocpkit.status.STATUSES`), why a step is not a success (``<name>_last_reason``, named by
``<name>_reason_string`` as :class:`ocpkit.status.Reason`: codes 1 … in the order of :data:`ocpkit.status.REASONS`,
0 none) and the OCP it was exported for (``<name>_ocp_digest``: sizes and settings, and a
hash of each weight, bound, the model and the task; :mod:`~ocpkit.export.digest`): :class:`ExportedMPC` refuses a
library exported for another OCP, naming what differs.

All memory of one controller lives in a caller-owned struct (``<name>_memory``): several instances run in one
process, each with its own QP-solver memory slot (``MAX_INSTANCES`` in the Makefile, 16 by default).

QP solvers (CasADi conic plugins with code generation in CasADi 3.8):

* ``qrqp`` — CasADi's own active-set solver, generated as plain C: the folder needs nothing else. It can
  report success at a point outside the bounds (seen on nlink:3, T = 50).
* ``daqp`` (default) — links CasADi's shipped ``libdaqpstat.a`` (headers under ``casadi/include``); DAQP's setup
  runs inside each step and allocates there (16 blocks a step: ``tests/test_export_c.py``). CasADi
  3.8's generated call ignores a failed set-up (DAQP's factorization refusing a Hessian that is not positive
  definite) and then reads an uninitialized success flag: in some processes the step reported success with the
  previous, zero answer. :func:`ocpkit.export.qp.fix_daqp_setup` makes the generated function return the set-up's
  flag.
* ``osqp`` — links CasADi's shipped ``libosqpstatic.a``; set up once at init, updated each step; quiet
  (verbose and polishing off unless ``polish=True``).
* ``hpipm`` — refused: CasADi's HPIPM interface needs a stage-wise OCP structure, which the condensed
  QP over knots does not have.

Whatever the solver says, a "solved" answer is accepted only if its KKT certificate holds (:mod:`ocpkit.qp.certificate`,
computed in C: stationarity, primal feasibility, complementarity and dual sign of the answer and its multipliers).

The package: :mod:`~ocpkit.export.generate` writes a folder (:func:`export`), :mod:`~ocpkit.export.render` renders
the C, header, Makefile and README from ``templates/``, :mod:`~ocpkit.export.constants` computes the step's
constants, :mod:`~ocpkit.export.qp` sets up the QP solver, :mod:`~ocpkit.export.digest` describes the OCP,
:mod:`~ocpkit.export.folder` keeps the folder safe,
:mod:`~ocpkit.export.build` runs ``make`` and :mod:`~ocpkit.export.library` loads the library back
(:class:`ExportedMPC`).
"""

from ocpkit.export.build import BuildError, build, check_tools
from ocpkit.export.generate import FORMS, LINEARIZATIONS, QP_SOLVERS, SUPPORTED, Export, export, export_problem
from ocpkit.export.library import ExportedMPC
from ocpkit.export.render import MAX_INSTANCES, OPT_FLAGS, OPT_STEP

__all__ = [
    "BuildError",
    "Export",
    "ExportedMPC",
    "FORMS",
    "LINEARIZATIONS",
    "MAX_INSTANCES",
    "OPT_FLAGS",
    "OPT_STEP",
    "QP_SOLVERS",
    "SUPPORTED",
    "build",
    "check_tools",
    "export",
    "export_problem",
]
