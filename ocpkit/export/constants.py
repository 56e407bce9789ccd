"""The numbers the exported C step is built from, written as C: its constants (input goal, shift, bounds, weights, the
basis' pieces, the Γ schedule, the model's sparsity, the task's weights) and the named codes the C and Python share
(the Γ schedule's operations, the certificate's return codes): each table here is the one both sides read."""

from __future__ import annotations

import numpy as np

from ocpkit.qp.certificate import TESTS
from ocpkit.qp.quadratic_program import ROUNDING_MARGIN
from ocpkit.model.task import ACTIVATION, ROWS_PER_SPHERE
from ocpkit.qp.transcription import CondensedQP

# The C step's solver return for a "solved" answer whose certificate failed: CERT_CODE + the test's index in
# ocpkit.qp.certificate.TESTS, named <N>_CERT_<name> in the header.
CERT_CODE = 9001
CERT_NAMES = dict(zip(TESTS, ("STATIONARITY", "PRIMAL", "COMPLEMENTARITY", "DUAL_SIGN")))
ILL_CONDITIONED = 9000  # a QP refused before its solve: Hessian ill-conditioned (QP.not_definite)
# The Γ schedule's operations (gram_schedule), GRAM_<name> in the C step; SAVE + i saves length i.
GRAM_CODES = {"DOUBLE": 1, "INC": 2, "RESET": 3, "SAVE": 10}
DOUBLE, INC, RESET, SAVE = (GRAM_CODES[k] for k in ("DOUBLE", "INC", "RESET", "SAVE"))


def gram_schedule(lengths) -> list[int]:
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
            ops.append(RESET)
            for k, bit in enumerate(bits):
                ops.append(INC if k == 0 else DOUBLE)  # from s = 1 a stage costs half a doubling
                if bit == "1":
                    ops.append(INC)
        else:
            ops += [INC] * (L - s)
        s = L
        ops.append(SAVE + i)
    return ops


def _c_num(v: float) -> str:
    v = float(v)
    if np.isnan(v):
        return "NAN"
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(v)


def c_array(v) -> str:
    return "{" + ", ".join(_c_num(e) for e in np.asarray(v, dtype=float).ravel()) + "}"


def _c_const(kind: str, name: str, values) -> str:
    """A static const C array; empty arrays get one dummy entry (C has no zero-length arrays)."""
    values = np.asarray(values).ravel()
    if values.size == 0:
        values = np.zeros(1)
    body = "{" + ", ".join(str(int(e)) for e in values) + "}" if kind == "int" else c_array(values)
    return f"static const {kind} {name}[{values.size}] = {body};"


def step_constants(
    tr: CondensedQP, linearization: str, jac, tf=None, iterations: int = 1, tol: float = 0.0, obstacle_rows: int = 0
) -> str:
    """The step's constants: input goal, shift, bounds, weights, the basis' pieces, the Gram schedule, for
    a nonlinear model RK4's step and the Jacobians' sparsity, with a task (``tf``) its weights and the basis, with
    obstacles (``obstacle_rows`` a stage at most) their table and the rows' bound, and for the real-time iteration
    ("trajectory") the basis, each stage's active knot columns and the iterations."""
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
    ops = gram_schedule(lengths)
    lines = [
        "enum { " + ", ".join(f"GRAM_{name} = {code}" for name, code in GRAM_CODES.items()) + " };",
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
        _c_const("int", "PIECE_C", pc),
        _c_const("int", "PIECE_CP", [0] + pc[:-1]),
        _c_const("int", "PIECE_LEN", [lengths.index(L) for L in pl]),
        _c_const("double", "PIECE_PHI", pphi),
        _c_const("double", "PIECE_DELTA", pdel),
    ]
    # the pieces' first stage and length: read by the state-bound and task rows and the goal window's terms
    lines += [_c_const("int", "PIECE_A", pa), _c_const("int", "PIECE_L", pl)]
    if linearization == "plan":
        lines.append(_c_const("double", "W0", phi[0] @ M))
    lines.append(f"#define LIN_TRAJ {int(linearization == 'trajectory')}")
    if linearization == "trajectory":
        # x_{k+1} depends on the knots of stages 0 … k only: its [v S] row has 1 + ACTIVE[k] nonzero columns.
        last = np.maximum.accumulate([np.flatnonzero(row).max(initial=0) for row in phi])
        lines += [
            f"#define ITERATIONS {iterations}",
            f"#define RTI_TOL {_c_num(tol)}",
            _c_const("double", "PHI_ALL", phi),
            _c_const("int", "ACTIVE", (last + 1) * m),
        ]
    if np.any(tr._dQT):
        lines.append(_c_const("double", "DQT", tr._dQT))
    if jac is not None:
        (fxi, fxj), (fui, fuj) = jac
        lines += [
            _c_const("int", "FX_I", fxi),
            _c_const("int", "FX_J", fxj),
            _c_const("int", "FU_I", fui),
            _c_const("int", "FU_J", fuj),
        ]
    if np.any(K):  # read only under #if HAS_K / #if NB > 0: unused constants would draw warnings
        lines.append(_c_const("double", "K_GOAL", K))
    if bounded.size:
        lines += [
            _c_const("int", "XB_COMP", bounded),
            _c_const("double", "XB_LO", ocp.x_min[bounded]),
            _c_const("double", "XB_HI", ocp.x_max[bounded]),
        ]
    if tf is not None:  # the task's Gauss-Newton terms: φ_k of every stage (exact, not the pieces' φ_a + sΔ)
        stage, terminal = tf.stage_weight.size, tf.terminal_weight.size
        lines += [f"#define TASK_STAGE {int(bool(stage))}", f"#define TASK_TERMINAL {int(bool(terminal))}"]
        if stage:
            lines += [_c_const("double", "TASK_PHI", phi), _c_const("double", "TASK_WS", tf.stage_weight)]
        if terminal:
            lines.append(_c_const("double", "TASK_WT", tf.terminal_weight))
    if obstacle_rows:  # TaskRows.select's bound, the obstacles (centre, radius) and each robot sphere's reach
        lines += [
            f"#define ACTIVATION {_c_num(ACTIVATION)}",
            f"#define ROWS_PER_SPHERE {ROWS_PER_SPHERE}",
            _c_const("double", "OBSTACLES", tf.table.T),
            _c_const("double", "SPHERE_REACH", tf.radii),
        ]  # radius + margin
    return "\n".join(lines)
