"""Crocoddyl (loco-3d/crocoddyl) as a peer of ocpkit's nonlinear MPC: the same OCP solved by its FDDP.

Crocoddyl is the reference DDP library for arms; the comparison is only fair on the very same problem, so
:class:`ShootingOCP` builds ocpkit's OCP (``ocpkit.model.ocp``) out of Crocoddyl's C++ models and checks that it is:

* dynamics: ``DifferentialActionModelFreeFwdDynamics`` on the problem's pinocchio model (``pin_model``): the ABA
  with the armature, as :meth:`ocpkit.model.rigid_body.Chain.forward_dynamics`. Crocoddyl's free dynamics have no joint
  damping b q̇ or friction (its C++ actuation models map u alone to τ), so the comparison runs the problems
  without them (:func:`undamped`). Construction checks ẋ against ``ocp.model.f`` at seeded random states.
* integrator: the OCP's (``ocp.integrator``, one step a dt): ``IntegratedActionModelRK`` (RK4) for "rk4", ocpkit's
  default; ``IntegratedActionModelEuler`` (semi-implicit, Crocoddyl's default) for "euler", ocpkit's semi-implicit
  Euler for x = [q, q̇].
* cost: ocpkit's Σ_{k=0}^{T-1} (x_k − x_g)ᵀQ(x_k − x_g) + (u_k − u_g)ᵀR(u_k − u_g) + (x_T − x_g)ᵀQ_T(x_T − x_g),
  the constant x_0 term left out, no factor ½, u_g = ``ocp.input_goal`` (gravity compensation on URDF robots).
  Crocoddyl's weighted quadratic activation is ½ Σ w_i r_i² and an integrated model's running cost is dt times
  the differential one: the weights are 2 diag(Q) / dt, etc. Its RK4 model integrates the running cost by the
  same RK4 quadrature (the state term at the four stage states, not at x_k), so with RK4 the state term of x_k
  (k = 1 … T−1) sits on its own node before node k's dynamics: an ``ActionModelLQR`` without input (x⁺ = x, cost
  xᵀQx − 2 x_gᵀQx), ocpkit's term less the constant x_gᵀQx_g (``ShootingOCP.offset``). These T − 1 extra nodes
  are cheap next to the RK4 nodes (the state term inside the RK4 node, Crocoddyl's integrated cost, would be
  another OCP). With Euler the running cost is dt ℓ(x_k, u_k) already: one node per step, the first without
  its state term.
* input bounds: ``SolverBoxFDDP`` (FDDP with the box-QP backward pass) wherever the OCP bounds the inputs.

Crocoddyl has no knot parameterization: it solves traditional MPC, p = T, and is compared with ocpkit on
``problem.ocp(knots=None)``. Its solves are timed as its own benchmarks time them (``benchmark/*_optctrl.py``):
C++ models, ``solve`` called from Python, one thread per problem (``nthreads`` 1: its default, one OpenMP thread
per core, makes ``calc`` + ``calcDiff`` hostage to the machine's other processes). Passing the node lists from Python
is a small part of a solve.
The solve-by-solve comparison with ocpkit's IPOPT and RTI: :mod:`ocpkit.benchmarks.crocoddyl_compare`.
"""

from __future__ import annotations

import time
from functools import cache

import numpy as np

from ocpkit import problems as registry
from ocpkit._checks import integer, positive
from ocpkit.controller import Controller
from ocpkit.status import LIMITED, NAN, SUCCESS, Solution
from ocpkit.model.ocp import OCP

INSTALL = 'pip install "ocpkit[peers]"'
# |ẋ_Crocoddyl − ẋ_ocpkit| allowed at the construction check, relative to max(1, |ẋ|): both are the ABA in
# double precision (1e-13 measured on the Panda), so anything beyond is a different model.
DYNAMICS_TOL = 1e-9
# FDDP's th_stop for a converged solve at stationarity 1e-6, the peers' common tolerance (CrocoddylMPC's docstring).
TH_STOP_KKT = 1e-12


def require():
    """The crocoddyl module, or an ImportError that says how to install it (also where crocoddyl's library and the
    installed pinocchio disagree: see :func:`_mismatch`)."""
    try:
        import crocoddyl
    except ImportError:
        raise ImportError(f"the crocoddyl peer needs the crocoddyl package: {INSTALL}") from None
    mismatch = _mismatch()
    if mismatch:
        raise ImportError(mismatch)
    return crocoddyl


@cache
def _mismatch() -> str | None:
    """Why crocoddyl cannot be used with the installed pinocchio, or None.

    libcrocoddyl compiles pinocchio's algorithms against the pinocchio headers of its build and shares pinocchio's
    Model and Data with the installed libpinocchio, with no version check: crocoddyl 3.2.1's wheel with pin 4.1.0
    returned the accelerations of an arm without gravity (pin 4.0.0: equal to ``pinocchio.aba``). One pendulum
    under gravity tells them apart."""
    import crocoddyl
    import pinocchio as pin

    model = pin.Model()
    joint = model.addJoint(0, pin.JointModelRY(), pin.SE3.Identity(), "joint")
    model.appendBodyToJoint(joint, pin.Inertia(1.0, np.array([0.0, 0.0, 0.5]), 0.01 * np.eye(3)), pin.SE3.Identity())
    state = crocoddyl.StateMultibody(model)
    dynamics = crocoddyl.DifferentialActionModelFreeFwdDynamics(
        state, crocoddyl.ActuationModelFull(state), crocoddyl.CostModelSum(state, 1)
    )
    data, x = dynamics.createData(), np.array([0.3, 0.0])
    dynamics.calc(data, x, np.zeros(1))
    reference = pin.aba(model, model.createData(), x[:1], x[1:], np.zeros(1))
    if np.allclose(data.xout, reference, rtol=1e-9, atol=1e-12):
        return None
    return (
        f"crocoddyl {crocoddyl.__version__} and pinocchio {pin.__version__} disagree on a pendulum's "
        f"acceleration ({float(data.xout[0]):.6g} against pinocchio.aba's {float(reference[0]):.6g} rad/s²): "
        f"libcrocoddyl was built for another libpinocchio (crocoddyl 3.2.1 for pin 4.0.0): {INSTALL} installs "
        "a matching pair"
    )


def available() -> bool:
    """Whether crocoddyl can be imported."""
    try:
        require()
    except ImportError:
        return False
    return True


def undamped(spec):
    """The problem of ``spec`` without joint damping and friction, which Crocoddyl's free dynamics lack.

    The shipped torque-controlled robots (``nlink``, ``puma560``, URDF robots such as ``panda``) read their
    ``damping`` (and ``friction``) attributes when their model is first made; other problems come back unchanged.
    """
    problem = registry.make(spec)
    if problem._models:
        raise ValueError(f"problem {spec!r} has made its model already; undamped needs a fresh problem")
    for name in ("damping", "friction"):
        if hasattr(problem, name):
            setattr(problem, name, np.zeros_like(np.asarray(getattr(problem, name), dtype=float)))
    return problem


def rollout(ocp: OCP, x0, inputs) -> np.ndarray:
    """States x_0 … x_T (T+1, n) of ocpkit's discrete model from x0 under ``inputs`` (T, m)."""
    U = np.asarray(inputs, dtype=float)
    X = np.asarray(ocp.discrete().mapaccum(U.shape[0])(x0, U.T), dtype=float)
    return np.vstack([x0, X.T])


def objective(ocp: OCP, goal, states, inputs) -> float:
    """ocpkit's cost (``ocp.cost``) of states x_0 … x_T and inputs u_0 … u_{T−1}:
    Σ_{k=1}^{T−1} ℓ(x_k, u_k) + the input term of u_0 + ℓ_T(x_T), the x_0 term left out as ocpkit does."""
    X, U = np.asarray(states, dtype=float), np.asarray(inputs, dtype=float)
    T = U.shape[0]
    if X.shape != (T + 1, ocp.nx) or U.shape != (T, ocp.nu):
        raise ValueError(f"states must be ({T + 1}, {ocp.nx}) and inputs ({T}, {ocp.nu}), got {X.shape}, {U.shape}")
    xg = np.asarray(goal, dtype=float)[: ocp.nx]
    starts = np.vstack([xg, X[1:T]])  # x_0's state error counted as zero
    stage = np.asarray(ocp.cost.stage.map(T)(starts.T, U.T, np.repeat(xg[:, None], T, axis=1)), dtype=float)
    return float(stage.sum()) + float(ocp.cost.terminal(X[T], xg))


class ShootingOCP:
    """ocpkit's OCP as a Crocoddyl ``ShootingProblem`` for one start and goal (see the module docstring).

    ``problem`` supplies the pinocchio model (``pin_model``) of ``ocp.model``; ``ocp`` must be traditional MPC
    (p = T), without a task or state bounds (FDDP has none), with diagonal Q, Q_T and R and one integrator step
    (RK4 or semi-implicit Euler, ``ocp.integrator``) a dt. ``set(x0, goal)`` rebuilds the node models when the
    goal changes and moves x0 otherwise; ``nodes`` and ``trajectory`` translate between ocpkit's (x_0 … x_T,
    u_0 … u_{T−1}) and the node lists, ``rollout`` makes the node lists of inputs and their states by Crocoddyl's
    dynamics.
    """

    def __init__(self, problem, ocp: OCP):
        self.croc = require()
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        self.integrator = ocp.integrator
        if ocp.parameterization.kind != "identity":
            raise ValueError(
                f"ocp has {ocp.knots} knots over a horizon of {ocp.horizon}: Crocoddyl solves "
                "traditional MPC only, build it with problem.ocp(knots=None)"
            )
        if ocp.task is not None:
            raise ValueError("ocp has a task: the Crocoddyl peer builds the state and input terms only")
        if ocp.has_state_bounds:
            raise ValueError("ocp has state bounds, which FDDP cannot hold")
        for name in ("Q", "Q_terminal", "R"):
            W = getattr(ocp, name)
            if np.any(W != np.diag(np.diag(W))):
                raise ValueError(f"ocp.{name} is not diagonal: Crocoddyl's weighted quadratic activation is")
        if ocp.model.linear or ocp.substeps != 1:
            how = (
                "the exact discretization of a linear model"
                if ocp.model.linear
                else f"{ocp.substeps} {ocp.integrator} substeps"
            )
            raise ValueError(f"ocp predicts with {how}, a Crocoddyl node with one {ocp.integrator} step a dt")
        pin_model = getattr(problem, "pin_model", None)
        if pin_model is None:
            raise ValueError(
                f"problem {getattr(problem, 'name', problem)!r} has no pinocchio model (pin_model) "
                "for Crocoddyl's multibody dynamics"
            )
        if (2 * pin_model.nv, pin_model.nv) != (ocp.nx, ocp.nu) or pin_model.nq != pin_model.nv:
            raise ValueError(
                f"problem {problem.name!r}: its pinocchio model (nq {pin_model.nq}, nv {pin_model.nv}) "
                f"is not the torque-controlled x = [q, q̇] of ocp (nx {ocp.nx}, nu {ocp.nu})"
            )
        self.ocp, self.name = ocp, problem.name
        croc = self.croc
        self.state = croc.StateMultibody(pin_model)
        self.actuation = croc.ActuationModelFull(self.state)
        self.check_dynamics()
        self.problem, self.goal, self.offset = None, None, 0.0

    def differential(self, state_weights=None, input_weights=None, goal=None, input_goal=None):
        """Crocoddyl's free forward dynamics with the weighted (½ Σ w r²) state and input terms given."""
        croc, state, m = self.croc, self.state, self.ocp.nu
        costs = croc.CostModelSum(state, m)
        if state_weights is not None:
            costs.addCost(
                "state",
                croc.CostModelResidual(
                    state, croc.ActivationModelWeightedQuad(state_weights), croc.ResidualModelState(state, goal, m)
                ),
                1.0,
            )
        if input_weights is not None:
            costs.addCost(
                "input",
                croc.CostModelResidual(
                    state, croc.ActivationModelWeightedQuad(input_weights), croc.ResidualModelControl(state, input_goal)
                ),
                1.0,
            )
        return croc.DifferentialActionModelFreeFwdDynamics(state, self.actuation, costs)

    def check_dynamics(self, samples: int = 3) -> None:
        """Raise a ValueError unless Crocoddyl's ẋ equals ``ocp.model.f`` at seeded random states and inputs."""
        ocp, n = self.ocp, self.ocp.nx // 2
        model = self.differential()
        data = model.createData()
        rng = np.random.default_rng(0)
        scale = np.where(np.isfinite(ocp.u_max), ocp.u_max, 1.0)
        for _ in range(samples):
            x, u = rng.uniform(-1.0, 1.0, ocp.nx), rng.uniform(-1.0, 1.0, ocp.nu) * scale
            model.calc(data, x, u)
            ours = np.asarray(ocp.model.f(x, u), dtype=float).ravel()[n:]
            gap = float(np.abs(data.xout - ours).max() / max(1.0, np.abs(ours).max()))
            if not gap <= DYNAMICS_TOL:
                raise ValueError(
                    f"problem {self.name!r}: Crocoddyl's free forward dynamics differ from ocp.model by {gap:.3g} "
                    f"(relative) at x = {np.round(x, 3).tolist()}: the model has terms Crocoddyl lacks (joint damping "
                    "or friction: use ocpkit.benchmarks.crocoddyl_peer.undamped; a model error multiplier; servo "
                    "inputs)"
                )

    def set(self, x0, goal) -> bool:
        """Point the problem at x0 and ``goal``; True when the node models were (re)built for a new goal."""
        x0 = np.asarray(x0, dtype=float)
        if self.goal is not None and np.array_equal(goal, self.goal):
            self.problem.x0 = x0
            return False
        self.goal = np.array(goal, dtype=float)
        self.problem = self._build(x0, self.goal)
        self.problem.nthreads = 1  # Crocoddyl's default is a thread per core (see the module docstring)
        return True

    def _build(self, x0, goal):
        croc, ocp, dt, T = self.croc, self.ocp, self.ocp.dt, self.ocp.horizon
        ug = ocp.input_goal(goal)
        wq, wr, wt = (2.0 * np.diag(W) for W in (ocp.Q, ocp.R, ocp.Q_terminal))
        terminal = croc.IntegratedActionModelEuler(self.differential(wt, goal=goal), 0.0)
        if self.integrator == "euler":
            first = self._bounded(
                croc.IntegratedActionModelEuler(self.differential(input_weights=wr / dt, input_goal=ug), dt)
            )
            step = self._bounded(croc.IntegratedActionModelEuler(self.differential(wq / dt, wr / dt, goal, ug), dt))
            self.offset = 0.0
            return croc.ShootingProblem(x0, [first] + [step] * (T - 1), terminal)
        step = self._bounded(
            croc.IntegratedActionModelRK(self.differential(input_weights=wr / dt, input_goal=ug), croc.RKType.four, dt)
        )
        n = ocp.nx  # x_k's state term (k = 1 … T−1) on a node of its own before node k's dynamics
        hold = croc.ActionModelLQR(
            np.eye(n),
            np.zeros((n, 0)),
            2.0 * ocp.Q,
            np.zeros((0, 0)),
            np.zeros((n, 0)),
            np.zeros(n),
            -2.0 * ocp.Q @ goal,
            np.zeros(0),
        )
        self.offset = (T - 1) * float(goal @ ocp.Q @ goal)
        return croc.ShootingProblem(x0, [step] + [hold, step] * (T - 1), terminal)

    def _bounded(self, model):
        model.u_lb, model.u_ub = self.ocp.u_min, self.ocp.u_max
        return model

    @property
    def bounded(self) -> bool:
        return bool(np.isfinite(self.ocp.u_min).any() or np.isfinite(self.ocp.u_max).any())

    def nodes(self, states, inputs):
        """Node lists (xs, us) of ocpkit's states x_0 … x_T (T+1, n) and inputs (T, m)."""
        X = np.asarray(states, dtype=float)
        if self.integrator == "euler":
            return list(X), self._input_nodes(inputs)
        xs = [X[0]] + [X[k] for k in range(1, len(X) - 1) for _ in (0, 1)] + [X[-1]]
        return xs, self._input_nodes(inputs)

    def rollout(self, inputs):
        """Node lists (xs, us) of ``inputs`` (T, m), xs their rollout from x0 by Crocoddyl's own dynamics."""
        us = self._input_nodes(inputs)
        return list(self.problem.rollout(us)), us

    def _input_nodes(self, inputs):
        U = np.asarray(inputs, dtype=float)
        if self.integrator == "euler":
            return list(U)
        none = np.zeros(0)  # the input of a state-term node
        return [U[0]] + [u for k in range(1, len(U)) for u in (none, U[k])]

    def trajectory(self, xs, us):
        """ocpkit's (states (T+1, n), inputs (T, m)) of node lists."""
        if self.integrator == "euler":
            return np.array(xs), np.array(us)
        return np.array([xs[0]] + list(xs[1::2])), np.array(us[0::2])

    def cost(self, states, inputs) -> float:
        """Crocoddyl's total cost (``ShootingProblem.calc``) of ocpkit's states and inputs, plus ``offset``."""
        xs, us = self.nodes(states, inputs)
        return float(self.problem.calc(xs, us)) + self.offset


class CrocoddylMPC(Controller):
    """MPC by Crocoddyl's FDDP (BoxFDDP under input bounds) on :class:`ShootingOCP`, as an ocpkit Controller.

    A cold step starts FDDP from the states held at x and the input goal (clipped), as NonlinearMPC starts
    IPOPT; later steps from the previous inputs shifted one step and their rollout from x, a feasible guess (the
    shifted states, whose appended last state leaves a gap, took BoxFDDP 20–23 iterations a step on the Puma
    560 instead of 3: tiny steps while its regularization climbed to 1e3). A step is a success when FDDP converges
    (expected decrease below ``th_stop``, Crocoddyl's default 1e-9) within ``max_iter`` iterations; otherwise
    the fallback, status "limited".

    ``converge`` False is the real-time analogue (as acados' SQP-RTI and ocpkit's RTI take one Gauss–Newton
    iteration a step): the plan after ``max_iter`` iterations (1: one FDDP iteration, backward pass and line
    search, from the warm start) is the step's answer whether or not FDDP has converged, and the next warm start.

    FDDP's stopping test (Crocoddyl 3.2) is its expected decrease |d₁ + ½d₂| = ½ Σ Q_uᵀQ_uu⁻¹Q_u ≤ ``th_stop``
    (without gaps): a squared, Q_uu⁻¹-weighted stationarity. ``th_stop`` 1e-12 (:data:`TH_STOP_KKT`) leaves
    ‖Q_u‖∞ ≤ 1e-6 at exit (measured, Puma 560 and nlink:13, T = 50: 1.4e-8 and 1.5e-7 to 9.6e-7; Crocoddyl's
    default 1e-9 left 1.3e-5 on nlink:13).
    """

    def __init__(
        self,
        problem,
        ocp: OCP,
        *,
        max_iter: int = 100,
        th_stop: float = 1e-9,
        warm_start: bool = True,
        converge: bool = True,
        raise_on_fail: bool = False,
    ):
        self.shooting = ShootingOCP(problem, ocp)
        self.converge = bool(converge)
        self.max_iter = integer(max_iter, "max_iter", 1)
        self.th_stop = positive(th_stop, "th_stop")
        self.warm_start = bool(warm_start)
        self.solver = None
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    def __repr__(self):
        mode = "" if self.converge else f", {self.max_iter} iteration{'s' if self.max_iter > 1 else ''} a step"
        return f"CrocoddylMPC({self.shooting.integrator}{mode}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        self._warm = None  # the inputs (T, m) of the last converged solve

    def _discard(self) -> None:
        self._warm = None

    def prepare(self, x, goal):
        """The problem at (x, goal) and the initial guess: node lists xs, us and whether xs is their rollout."""
        sh = self.shooting
        if sh.set(x, goal) or self.solver is None:
            croc = sh.croc
            self.solver = (croc.SolverBoxFDDP if sh.bounded else croc.SolverFDDP)(sh.problem)
            self.solver.th_stop = self.th_stop
        if self._warm is None or not self.warm_start:
            return (*sh.nodes(np.tile(x, (self.ocp.horizon + 1, 1)), self.goal_knots(goal)), False)
        return (*sh.rollout(np.vstack([self._warm[1:], self._warm[-1:]])), True)

    def one_iteration(self, x, goal) -> float:
        """Seconds of one FDDP iteration from the cold guess (Crocoddyl's benchmarks: ``solve`` with maxiter 1)."""
        self._warm = None
        xs, us, feasible = self.prepare(x, goal)
        start = time.perf_counter()
        self.solver.solve(xs, us, 1, feasible)
        return time.perf_counter() - start

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        t0 = time.perf_counter()
        xs, us, feasible = self.prepare(x, goal)
        t1 = time.perf_counter()
        converged = self.solver.solve(xs, us, self.max_iter, feasible)
        t2 = time.perf_counter()
        solver = self.solver
        iterations = solver.iter + 1 if converged else solver.iter
        times = {"model": 0.0, "build": t1 - t0, "solve": t2 - t1}
        X, U = self.shooting.trajectory(solver.xs, solver.us)
        if not (np.isfinite(X).all() and np.isfinite(U).all()):
            self._warm = None
            return self.fallback(NAN, "FDDP returned non-finite states or inputs", times, iterations)
        if not converged and self.converge:
            self._warm = None
            return self.fallback(
                LIMITED,
                f"FDDP not converged in {iterations} iterations (expected decrease "
                f"{solver.stop:.3g}, th_stop {self.th_stop:g})",
                times,
                iterations,
            )
        self._warm = U
        return Solution(
            u=U[0].copy(),
            knots=U,
            status=SUCCESS,
            iterations=iterations,
            x_pred=X,
            times=times,
            raw_status=f"FDDP {'converged' if converged else 'stopped'} after {iterations} iterations (expected "
            f"decrease {solver.stop:.3g})",
        )
