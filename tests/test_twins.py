"""The Python/C twins (issue 45, item 2): each piece of math the exported C step (ocpkit/export/templates) writes a
second time, against its Python original on the same inputs, to 1e-12 relative to the data's scale.

tests/c/twins.c includes the rendered ``mpc.c`` and exposes its static functions; it is built in an exported folder
in place of ``mpc.o`` and loaded with ctypes. Two problems: the pendulum (linear basis, diagonal Q, a state bound)
and nlink:3 (zero-order-hold basis, dense Q, a terminal weight, three state bounds), both exported with
linearization "trajectory", whose ``mpc.c`` holds the one-model condensing too.

=====================  =========================================  =================================================
twin                   Python                                     C (step.in.c)
=====================  =========================================  =================================================
RK4 sensitivities      ocpkit.model.dynamics._affine              affine_model, sensitivity_rate
LTI condensing         CondensedQP._cost_lti (backward pass)      condense, grams (forward, Gram doubling)
LTV condensing         CondensedQP._predict_ltv, _cost_ltv        condense_ltv
KKT certificate        ocpkit.qp.certificate.certify              certify, bound_row
ill-conditioning       QP.not_definite (rounding test)            ill_conditioned
fallback and shift     Controller.fallback ("plan"), .shift       fallback, shifted_knots
RTI iterations         RealTimeIteration._solve, shifted_plan     rti, shifted_plan, stage_models
=====================  =========================================  =================================================
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ocpkit.export import export
from ocpkit.problems import make
from ocpkit.qp.certificate import certify
from ocpkit.qp.quadratic_program import QP, ROUNDING_MARGIN
from ocpkit.qp.transcription import CondensedQP
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")

TOL = 1e-12  # relative to the data's scale (max |entry| of the Python side)
ITERATIONS = 3  # the exported real-time iteration's Gauss–Newton steps
# The real-time iteration's answers are QP solutions: their QPs agree to 1e-14 (LTV condensing, sensitivities), and
# DAQP's answer carries that times P's condition number (4.6e5 for nlink:3's QPs; 120 the pendulum's). Measured:
# 1.9e-12 (nlink:3), 1.6e-14 (pendulum).
RTI_TOL = 1e-10


def _ocp(case: str):
    problem = make(case)
    if case == "pendulum":
        return problem, problem.ocp(knots=5, horizon=50, x_min=[-np.inf, -6.0], x_max=[np.inf, 6.0], compiled=False)
    rng = np.random.default_rng(0)
    M = rng.normal(size=(6, 6))
    big = np.r_[np.full(3, np.inf), np.full(3, 10.0)]  # |q̇_i| <= 10
    return problem, problem.ocp(
        knots=4,
        horizon=30,
        parameterization="zoh",
        Q=np.eye(6) + 0.1 * M @ M.T,
        Q_terminal=100 * np.eye(6),
        x_min=-big,
        x_max=big,
        compiled=False,
    )


class Twins:
    """The C twins of one exported step (tests/c/twins.c), each called with numpy arrays."""

    def __init__(self, out: Path, ocp):
        shutil.copy(Path(__file__).parent / "c" / "twins.c", out)
        for target in (["twins.o", "CFLAGS=-fPIC -O3"], ["lib", "OBJ=twins.o mpc_casadi.o"]):
            proc = subprocess.run(["make", "-s", "-C", str(out), *target], check=False, capture_output=True, text=True)
            assert proc.returncode == 0, proc.stdout + proc.stderr
        self.lib = ctypes.CDLL(str(out / "libmpc.so"))
        self.lib.mpc_memory_size.restype = ctypes.c_size_t
        self.mem = ctypes.create_string_buffer(self.lib.mpc_memory_size())
        assert self.lib.mpc_init(self.mem) == 0
        n, m, p, T = ocp.nx, ocp.nu, ocp.knots, ocp.horizon
        nb = int(np.count_nonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max)))
        self.n, self.m, self.nz, self.na, self.nl = n, m, m * p, T * nb, n + 2 * m + 1

    def __call__(self, name: str, *arrays) -> int:
        """twins_<name>(mem, arrays…): None passes NULL; the arrays (row-major; h and a column-major: pass their
        transposes) are written in place."""
        args = [None if a is None else _buffer(a).ctypes.data_as(ctypes.c_void_p) for a in arrays]
        return getattr(self.lib, "twins_" + name)(self.mem, *args)

    def qp(self):
        """The QP in the C memory: h, g, a (NA x NZ), lba, uba, lbx, ubx."""
        nz, na = self.nz, max(self.na, 1)
        out = [np.zeros((nz, nz)), np.zeros(nz), np.zeros((nz, na))] + [np.zeros(k) for k in (na, na, nz, nz)]
        self("qp", *out)
        out[0], out[2] = out[0].T, out[2].T
        return out

    def close(self):
        self.lib.mpc_free(self.mem)


@pytest.fixture(scope="module", params=["pendulum", "nlink:3"])
def twins(request, tmp_path_factory):
    problem, ocp = _ocp(request.param)
    out = export(
        ocp, tmp_path_factory.mktemp("twins") / "exp", linearization="trajectory", iterations=ITERATIONS
    ).out_dir
    c = Twins(out, ocp)
    yield problem, ocp, c
    c.close()


def _buffer(a) -> np.ndarray:
    """``a`` as row-major doubles: itself where it already is (an output), else a copy."""
    return np.ascontiguousarray(a, dtype=float)


def _rel(c, py) -> float:
    """max |c − py| over the Python side's scale (max |py|, at least 1)."""
    c, py = np.asarray(c, dtype=float), np.asarray(py, dtype=float)
    return float(np.abs(c - py).max(initial=0.0) / max(1.0, np.abs(py).max(initial=0.0)))


def _L(Ad, Bd, wd, m: int) -> np.ndarray:
    """Λ = [A_d B_d 0 w_d] (n x NL) of an affine model, as the C step holds it."""
    n = Ad.shape[0]
    return np.hstack([Ad, Bd, np.zeros((n, m)), np.reshape(wd, (n, 1))])


def _points(problem, ocp, count: int = 3):
    """(x, goal, u) samples: the problem's start and goal states, an input about the input goal."""
    rng = np.random.default_rng(1)
    for seed in range(count):
        x, goal = problem.sample(seed)
        yield x, goal, ocp.input_goal(goal) + 0.3 * rng.normal(size=ocp.nu)


def _python_qp(ocp, L, x, goal) -> QP:
    """CondensedQP.build about one model Λ (n x NL) or stage models (T x n x NL), hard state bounds."""
    n, m = ocp.nx, ocp.nu
    return CondensedQP(ocp).build(L[..., :n], L[..., n : n + m], L[..., -1], x, goal)


def _check_qp(c: Twins, qp: QP):
    """The C memory's QP against the Python one: h = P, g = q, the knot bounds and the state-bound rows."""
    h, g, a, lba, uba, lbx, ubx = c.qp()
    nbox = qp.box.size
    assert nbox == c.nz  # every knot bounded: C's lbx, ubx are the box
    rows = np.asarray(qp.C)[nbox:]
    diffs = [_rel(h, qp.P), _rel(g, qp.q), _rel(lbx, qp.l[:nbox]), _rel(ubx, qp.u[:nbox])]
    if c.na:
        diffs += [_rel(a, rows), _rel(lba, qp.l[nbox:]), _rel(uba, qp.u[nbox:])]
    assert max(diffs) <= TOL, diffs


def test_rk4_sensitivities(twins):
    """affine_model (RK4 and its sensitivities, sparse Jacobians) = ocp.affine() (the integrator on tangents)."""
    problem, ocp, c = twins
    worst = 0.0
    for x, _, u in _points(problem, ocp):
        L = np.zeros((c.n, c.nl))
        assert c("affine_model", x, u, L) == 0
        worst = max(worst, _rel(L, _L(*(np.asarray(v) for v in ocp.affine()(x, u)), c.m)))
    assert worst <= TOL


def test_lti_condensing(twins):
    """condense (Λ_s by Gram doubling, forward over the pieces) = CondensedQP.build about one model (backward)."""
    problem, ocp, c = twins
    for x, goal, u in _points(problem, ocp):
        L = _L(*(np.asarray(v) for v in ocp.affine()(x, u)), c.m)
        c("condense_lti", L, ocp.input_goal(goal), x, goal)
        _check_qp(c, _python_qp(ocp, L, x, goal))


def test_ltv_condensing(twins):
    """condense_ltv = CondensedQP.build with one model per stage, along a rollout of a random plan."""
    problem, ocp, c = twins
    rng = np.random.default_rng(2)
    ctrl = LinearMPC(ocp, native=False)
    for x, goal, u in _points(problem, ocp):
        us = ocp.parameterization.inputs(u + 0.2 * rng.normal(size=(ocp.knots, ocp.nu)))
        xs = ctrl.rollout(x, us)[:-1]
        A, B, w = ctrl.affine_models(xs, us)
        LamK = np.stack([_L(A[k], B[k], w[k], c.m) for k in range(ocp.horizon)])
        c("condense_ltv", LamK, ocp.input_goal(goal), x, goal)
        _check_qp(c, _python_qp(ocp, LamK, x, goal))


def test_kkt_certificate(twins):
    """certify in C = ocpkit.qp.certificate.certify on answers that fail each test: z and multipliers of both signs
    (some on infinite bounds), in CasADi's convention h z + g + aᵀ λ_a + λ_x = 0, ocpkit's w = [λ_x; λ_a]."""
    problem, ocp, c = twins
    rng = np.random.default_rng(3)
    x, goal, u = next(_points(problem, ocp))
    qp = _python_qp(ocp, _L(*(np.asarray(v) for v in ocp.affine()(x, u)), c.m), x, goal)
    nbox, na = qp.box.size, c.na
    h = np.asarray(qp.P).T  # column-major
    a = np.asarray(qp.C)[nbox:].T if na else np.zeros(c.nz)
    l, hi = qp.l.copy(), qp.u.copy()
    l[nbox::3] = -np.inf  # some rows bounded above only: their negative multipliers fail the dual sign
    res = LinearMPC(ocp, state_bounds="hard", native=False)._backend.solve(qp, None, None)
    worst = 0.0
    for scale in (0.0, 1e-9, 1e-3, 1.0):  # the solution, then further and further from it
        z = res.z + scale * rng.normal(size=c.nz)
        w = res.w + scale * rng.normal(size=qp.l.size)
        cert = np.zeros(4)
        bound = [l[nbox:], hi[nbox:]] if na else [np.zeros(1), np.zeros(1)]
        c("certify", h, qp.q, a, *bound, l[:nbox], hi[:nbox], z, w[:nbox], w[nbox:] if na else np.zeros(1), cert)
        ref = certify(QP(qp.P, qp.q, qp.A, qp.b, qp.C, l, hi, box=qp.box), z, None, w).residuals
        worst = max(worst, _rel(cert, ref))
    assert worst <= TOL


def test_ill_conditioning(twins):
    """ill_conditioned = QP.not_definite's rounding test (n ε max P_ii against ROUNDING_MARGIN × the curvature), the
    same verdict on either side of the threshold to one part in 1e12, and exactly at it."""
    problem, ocp, c = twins
    tr = CondensedQP(ocp)
    P = np.array(tr.build(*ocp.affine()(*next(_points(problem, ocp))[::2]), np.zeros(ocp.nx), np.zeros(ocp.nx)).P)
    edge = ROUNDING_MARGIN * tr.curvature / (c.nz * np.finfo(float).eps)
    for f in (0.5, 1 - TOL, 1.0, 1 + TOL, 2.0):
        Pf = P * (edge * f / np.abs(np.diag(P)).max())
        py = QP(
            Pf,
            np.zeros(c.nz),
            np.zeros((0, c.nz)),
            np.zeros(0),
            np.zeros((0, c.nz)),
            np.zeros(0),
            np.zeros(0),
            curvature=tr.curvature,
        ).not_definite(factorize=False)
        assert bool(c("ill_conditioned", Pf)) == (py is not None), f
    assert c("ill_conditioned", P) == 0


def test_fallback_and_shift(twins):
    """fallback (shifted_knots by the SHIFT matrix, clipped) = Controller.fallback's plan replay (Parameterization
    .shift, clipped), warm and cold; the first input clipped alike. (Python's check of the replayed plan, and the
    brake where it fails, is a layer above the C's: ExportedMPC answers a refused C step with Controller.fallback.)"""
    problem, ocp, c = twins
    rng = np.random.default_rng(4)
    ctrl = LinearMPC(ocp, native=False)
    worst = 0.0
    for x, goal, u in _points(problem, ocp):
        ug = ocp.input_goal(goal)
        over = np.tile(ug, (ocp.knots, 1)) + 0.1 * rng.normal(size=(ocp.knots, ocp.nu))
        over[:2, 0] = 1.5 * ocp.u_max[0]  # beyond the bound: clipped
        for plan in (None, over):
            uc, kc = np.zeros(ocp.nu), np.zeros((ocp.knots, ocp.nu))
            c("fallback", plan, ug, uc, kc)
            ctrl.plan, ctrl._goal, ctrl._x, ctrl._refused = plan, goal, np.zeros(ocp.nx), 0  # at rest: a safe plan
            sol = ctrl.fallback("limited", "twin")
            assert sol.path == "fallback (plan)"
            worst = max(worst, _rel(kc, sol.knots), _rel(uc, sol.u))
    assert worst <= TOL


def test_rti_shifted_plan(twins):
    """The first linearization trajectory of the real-time iteration: shifted_plan and stage_models (x held where
    there are no predicted states) = LinearMPC.shifted_plan (the plan shifted, its states or x held)."""
    problem, ocp, c = twins
    rng = np.random.default_rng(5)
    ctrl = LinearMPC(ocp, linearization="trajectory", native=False)
    T, n, m = ocp.horizon, ocp.nx, ocp.nu
    for x, goal, u in _points(problem, ocp):
        plan = u + 0.2 * rng.normal(size=(ocp.knots, m))
        xplan = ctrl.rollout(x + 0.01, ocp.parameterization.inputs(plan))
        for p, xp in ((None, None), (plan, None), (plan, xplan)):
            xbar, ubar = np.zeros((T, n)), np.zeros((T, m))
            assert c("shifted_plan", p, xp, ocp.input_goal(goal), x, xbar, ubar) == 0
            ctrl.plan, ctrl._x_plan = p, xp
            xs, us = ctrl.shifted_plan(x, goal)
            assert max(_rel(xbar, xs), _rel(ubar, us)) <= TOL


def test_rti_iterations(twins):
    """The C step's ITERATIONS Gauss–Newton steps = RealTimeIteration's in Python (hard state bounds, DAQP in both)
    along a closed loop: knots, first input and predicted states."""
    problem, ocp, c = twins
    py = RealTimeIteration(ocp, iterations=ITERATIONS, state_bounds="hard", native=False, eps=1e-12)
    n, m, p, T = ocp.nx, ocp.nu, ocp.knots, ocp.horizon
    status = ctypes.c_int()
    x, goal = problem.sample(0)
    F = ocp.discrete()
    worst = 0.0
    c.lib.mpc_reset(c.mem)
    for _ in range(5):
        uc, kc, xc = np.zeros(m), np.zeros((p, m)), np.zeros((T + 1, n))
        ptr = [v.ctypes.data_as(ctypes.c_void_p) for v in (x, goal, uc)]
        assert c.lib.mpc_step(c.mem, *ptr, ctypes.byref(status)) == 0 == status.value
        c.lib.mpc_knots(c.mem, kc.ctypes.data_as(ctypes.c_void_p))
        assert c.lib.mpc_states(c.mem, xc.ctypes.data_as(ctypes.c_void_p)) == 0
        sol = py.solve(x, goal)
        assert sol.ok and f"RTI {ITERATIONS} of {ITERATIONS}" in sol.raw_status
        worst = max(worst, _rel(kc, sol.knots), _rel(uc, sol.u), _rel(xc, sol.x_pred))
        x = np.asarray(F(x, sol.u)).ravel()
    assert worst <= RTI_TOL, worst
