"""The optimal control problem: model, time step, horizon, quadratic cost, bounds and parameterization.

The paper's MPC problem (eq. mpc_problem) with a zero-order-hold discrete model:

    min  Σ_{k=0}^{T-1} (u_k − u_g)ᵀ R (u_k − u_g) + Σ_{k=1}^{T-1} (x_k − x_goal)ᵀ Q (x_k − x_goal)
         + (x_T − x_goal)ᵀ Q_T (x_T − x_goal)
    s.t. x_{k+1} = F(x_k, u_k),  u = φ U (the parameterization),  u_min ≤ u_k ≤ u_max,  x_min ≤ x_k ≤ x_max.

x_0 is the measured state, so its cost term is a constant and is left out. The input goal is u_g = u_goal + K x_goal
with K = ``u_goal_gain`` (zero by default, the paper's u_goal = 0): for a robot whose inputs are servo set points
(Baxter) the input that holds the goal is the goal position itself. Every solver reads this one description: the QPs
through its affine model, IPOPT through F, EMPC through the translated kernels.

The two quadratic sums are the cost's built-in terms "state" and "input" (:class:`ocpkit.model.cost.Cost`, the cost
as named terms that every solver reads); a :class:`ocpkit.model.task.Task` adds named, weighted terms (frame
position and orientation targets, joint-limit barriers, user residuals) and obstacles. The goal is then
[x_goal; the terms' targets] (``ng`` entries, :meth:`OCP.goal`); without a task it is x_goal.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit._checks import array, bounds, choice, integer, positive, weight
from ocpkit.codegen.compiled import SwitchingFunction, compile_function, compile_in_background
from ocpkit.model.cost import Cost
from ocpkit.model.dynamics import INTEGRATORS, Model
from ocpkit.numeric import BufferedFunction
from ocpkit.model.parameterization import Parameterization
from ocpkit.model.task import Task

# The default path (``compiled`` not given) compiles the affine model in the background only from this size up
# (CasADi VM instructions of the continuous Jacobian, Model.jacobian, which the affine model evaluates 4 times
# per RK4 step): below it the VM takes tens of µs and a compile would only cost CPU. nlink:3 has 822, nlink:5 3k,
# nlink:7 6.5k, nlink:13 24k.
BACKGROUND_MIN_INSTRUCTIONS = 2_000


class OCP:
    """A validated MPC problem; see the module docstring for the objective and constraints.

    ``integrator`` is how the controller predicts a nonlinear model over a step dt (``substeps`` sub-steps each):
    "rk4" or "euler" (semi-implicit for x = [q, q̇]; one Jacobian a sub-step instead of four, see
    :data:`ocpkit.model.dynamics.INTEGRATORS`). The plant the simulator integrates is not affected.
    """

    def __init__(
        self,
        model: Model,
        dt: float,
        horizon: int,
        Q,
        R,
        *,
        Q_terminal=None,
        u_goal=None,
        u_goal_gain=None,
        u_min=None,
        u_max=None,
        x_min=None,
        x_max=None,
        parameterization: Parameterization | None = None,
        substeps: int = 1,
        integrator: str = "rk4",
        compiled: bool | None = None,
        task: Task | None = None,
    ):
        if not isinstance(model, Model):
            raise TypeError(f"model must be an ocpkit Model, got {type(model).__name__}")
        n, m = model.nx, model.nu
        self.model = model
        self.dt = positive(dt, "dt")
        self.horizon = integer(horizon, "horizon", 1)
        self.substeps = integer(substeps, "substeps", 1)
        self.integrator = choice(integrator, INTEGRATORS, "integrator")
        self.compiled = None if compiled is None else bool(compiled)
        self.nx, self.nu = n, m
        self.Q = weight(Q, "Q", n, definite=False)
        self.R = weight(R, "R", m, definite=True)
        self.Q_terminal = self.Q if Q_terminal is None else weight(Q_terminal, "Q_terminal", n, definite=False)
        self.u_goal = np.zeros(m) if u_goal is None else bounds(u_goal, u_goal, "u_goal", "u_goal", m)[0]
        if not np.all(np.isfinite(self.u_goal)):
            raise ValueError(f"u_goal must be finite, got {self.u_goal.tolist()}")
        self.u_goal_gain = np.zeros((m, n)) if u_goal_gain is None else array(u_goal_gain, "u_goal_gain", (m, n))
        self.u_min, self.u_max = bounds(u_min, u_max, "u_min", "u_max", m)
        self.x_min, self.x_max = bounds(x_min, x_max, "x_min", "x_max", n)
        if parameterization is None:
            parameterization = Parameterization.identity(self.horizon)
        if not isinstance(parameterization, Parameterization):
            raise TypeError(f"parameterization must be a Parameterization, got {type(parameterization).__name__}")
        if parameterization.horizon != self.horizon:
            raise ValueError(f"parameterization has horizon {parameterization.horizon}, the OCP {self.horizon}")
        if not parameterization.convex and np.any(np.isfinite(np.r_[self.u_min, self.u_max])):
            raise ValueError(
                f"input bounds need a parameterization whose rows are convex combinations (nonnegative, summing to "
                f"1): the QPs and planners bound the knots, which bounds u = φU only then; {parameterization.kind!r} "
                f"has another basis (drop u_min/u_max or use such a basis)"
            )
        self.parameterization = parameterization
        self._compiled_affine = None  # compiled=True: the compiled model; None: the switching one, once made
        self.knots = parameterization.knots
        if task is not None and not isinstance(task, Task):
            raise TypeError(f"task must be an ocpkit.model.task.Task or None, got {type(task).__name__}")
        self.task = task
        # The task's Functions (None without a task, or with no active term and no obstacle: nothing changes)
        self.task_functions = None if task is None or not (task.active_terms or task.obstacles) else task.compile(n, m)
        self.ng = n + (0 if task is None else task.target_size)
        self._cost = None
        self._task_maps = None  # task_maps(), once made

    def __repr__(self):
        integrator = "" if self.integrator == "rk4" else f", integrator={self.integrator!r}"
        return (
            f"OCP({self.model.name!r}, dt={self.dt}, horizon={self.horizon}, "
            f"{self.parameterization.kind} knots={self.knots}{integrator})"
        )

    @property
    def terms(self) -> list[str]:
        """The cost's active terms by name: "state" and "input" (Q, R), then the task's (:attr:`cost`)."""
        return self.cost.names

    def goal(self, x_goal=None, **targets) -> np.ndarray:
        """The goal vector [x_goal; targets in the task's order] (x_goal zero where not given); every target named."""
        x_goal = np.zeros(self.nx) if x_goal is None else self.check_state(x_goal, "x_goal")
        sizes = self.task.targets if self.task is not None else {}
        unknown = sorted(set(targets) - set(sizes))
        if unknown:
            raise ValueError(f"no task term named {unknown[0]!r} takes a target; targets: {sorted(sizes) or 'none'}")
        missing = [name for name in sizes if name not in targets]
        if missing:
            raise ValueError(f"goal needs a target for {', '.join(repr(m) for m in missing)}")
        # a rotation target may come as a 3 × 3 matrix: its rows, in order
        parts = [x_goal] + [
            self.task.check_target(name, array(np.ravel(targets[name]), name, (size,))) for name, size in sizes.items()
        ]
        return np.concatenate(parts)

    def check_goal(self, goal, name: str = "goal") -> np.ndarray:
        """The goal as a finite float64 vector of ``ng`` entries (x_goal, then the task's targets)."""
        if self.ng != self.nx and np.size(goal) == self.nx:
            raise ValueError(
                f"{name} has {self.nx} entries (a state) but this OCP's task needs {self.ng}: "
                f"x_goal and the targets {sorted(self.task.targets)}; build it with ocp.goal(...)"
            )
        return array(goal, name, (self.ng,))

    @property
    def cost(self) -> Cost:
        """The cost as named terms ("state", "input", then the task's), built once: :class:`ocpkit.model.cost.Cost`."""
        if self._cost is None:
            self._cost = Cost(self)
        return self._cost

    def input_error(self, u, x_goal):
        """u − u_g(x_goal) as a CasADi expression: the "input" term's residual (u_g as :meth:`input_goal`)."""
        return u - ca.DM(self.u_goal) - ca.mtimes(ca.DM(self.u_goal_gain), x_goal)

    def goal_names(self) -> list[str]:
        """The goal vector's entries by name: the model's state names, then each target's entries as
        "<term>[i]" (a reference file's columns, :meth:`ocpkit.model.reference.Reference.load`)."""
        sizes = self.task.targets if self.task is not None else {}
        return list(self.model.state_names) + [f"{name}[{i}]" for name, size in sizes.items() for i in range(size)]

    def goal_window(self, goal, name: str = "goal") -> np.ndarray:
        """The goal at every stage k = 0 … T, (T+1, ng): a goal vector (``ng`` entries) held, or a window as given
        (a :class:`ocpkit.model.reference.Reference`'s), finite numbers either way (:meth:`goal` checks targets)."""
        if np.ndim(goal) == 2:
            return array(goal, name, (self.horizon + 1, self.ng))
        return np.broadcast_to(self.check_goal(goal, name), (self.horizon + 1, self.ng))

    def obstacle_window(self, obstacles=None, name: str = "obstacles") -> np.ndarray | None:
        """The task's obstacles at every stage k = 0 … T, (T+1, N, 4) (centre, radius): None (the declared ones),
        (N, 4) held, or (T+1, N, 4) as given (an :class:`ocpkit.model.reference.ObstaclePath`'s window). None where
        the task has no obstacles (then ``obstacles`` must be None)."""
        from ocpkit.model.task import MAX_LENGTH

        declared = self.task.obstacles if self.task is not None else []
        if not declared:
            if obstacles is not None:
                raise ValueError(f"{name} given, but this OCP's task declares no obstacles to move")
            return None
        N, T = len(declared), self.horizon
        if obstacles is None:
            table = np.array([[*o.center, o.radius] for o in declared], dtype=float)
            return np.broadcast_to(table, (T + 1, N, 4))
        if np.ndim(obstacles) == 2:
            window = np.broadcast_to(array(obstacles, name, (N, 4)), (T + 1, N, 4))
        else:
            window = array(obstacles, name, (T + 1, N, 4))
        radii = window[..., 3]
        if (radii <= 0).any() or (radii > MAX_LENGTH).any() or (np.abs(window[..., :3]) > 1e3 * MAX_LENGTH).any():
            raise ValueError(
                f"{name}: radii must be > 0 and at most {MAX_LENGTH:g} m, centres within "
                f"{1e3 * MAX_LENGTH:g} m, got radii {np.unique(radii).tolist()[:5]}"
            )
        return window

    def guess_knots(self, initial_guess, name: str = "initial_guess") -> np.ndarray:
        """A user's plan as knots (p, m): knots as given, or inputs over the horizon (T, m) fitted by least squares
        (exact when they lie in the parameterization's span)."""
        guess = np.asarray(initial_guess, dtype=float)
        p, T, m = self.knots, self.horizon, self.nu
        if guess.shape == (p, m):
            return array(guess, name, (p, m))
        if guess.shape == (T, m):
            return self.parameterization.fit(array(guess, name, (T, m)))
        raise ValueError(f"{name} must be knots ({p}, {m}) or inputs over the horizon ({T}, {m}), got {guess.shape}")

    @property
    def has_state_bounds(self) -> bool:
        return bool(np.isfinite(self.x_min).any() or np.isfinite(self.x_max).any())

    def input_goal(self, x_goal) -> np.ndarray:
        """u_g = u_goal + K x_goal: the input the cost pulls towards for this goal."""
        return self.u_goal + self.u_goal_gain @ np.asarray(x_goal, dtype=float)

    def discrete(self) -> ca.Function:
        """The discrete model F(x, u) -> x⁺ every solver predicts with."""
        return self.model.discrete(self.dt, self.substeps, self.integrator)

    def affine(self) -> ca.Function:
        """The affine model (x̄, ū) -> (A_d, B_d, w_d) of :meth:`discrete`.

        ``compiled=True``: compiled C, compiled here and now (see :mod:`ocpkit.codegen.compiled`: faster for large
        robots after a one-off compile, cached by hash). ``compiled=False``: CasADi's virtual machine.
        Not given (default): the virtual machine, which switches by itself to the compiled C as soon as a compile
        started in the background at this first call finishes (models of ``BACKGROUND_MIN_INSTRUCTIONS`` and
        more; a :class:`ocpkit.codegen.compiled.SwitchingFunction`); without a C compiler, the VM with one warning."""
        fn = self.model.affine(self.dt, self.substeps, self.integrator)
        if not (
            self.compiled
            or (self.compiled is None and self.model.jacobian.n_instructions() >= BACKGROUND_MIN_INSTRUCTIONS)
        ):
            return fn
        if self._compiled_affine is None:
            self._compiled_affine = self._compile(fn)
        current = self._compiled_affine
        if isinstance(current, SwitchingFunction) and current.compiled() is not None:
            return current.compiled()
        return current

    def _compile(self, fn: ca.Function) -> ca.Function:
        """``fn`` as compiled C under the ``compiled`` policy: True compiles it here and now; None in the background,
        the VM answering meanwhile (a :class:`ocpkit.codegen.compiled.SwitchingFunction`; the VM alone, with one
        warning, without a C compiler)."""
        if self.compiled:
            return compile_function(fn)
        future = compile_in_background(fn)
        return fn if future is None else SwitchingFunction(fn, future)

    def task_maps(self) -> dict:
        """The task's functions over the horizon on numpy buffers, made once and shared by every QP of this OCP (hard
        and soft, a sampling planner's preconditioner, the plan certificate): "stage" (the stage residuals and
        Jacobians mapped over the T stages), "terminal", "spheres" (the robot spheres' centres and their Jacobians
        at x_1 … x_T, from which the clearances to every obstacle follow in numpy: ``CompiledTask.pair_clearances``);
        None where the task has none. The residuals are compiled under the ``compiled`` policy (False: the VM). The
        spheres stay on the VM, too cheap to be worth a compile per OCP; the clearances are not mapped over the
        horizon, a Function that would grow with the obstacles."""
        if self._task_maps is None:
            tf, T = self.task_functions, self.horizon

            def fast(fn):
                return BufferedFunction(fn if self.compiled is False else self._compile(fn))

            self._task_maps = {
                "stage": fast(tf.stage_residual.map(T)) if tf.stage_weight.size else None,
                "terminal": fast(tf.terminal_residual) if tf.terminal_weight.size else None,
                "spheres": BufferedFunction(tf.spheres.map(T)) if tf.pairs else None,
            }
        return self._task_maps

    def check_state(self, x, name: str = "x") -> np.ndarray:
        """x as a finite float64 vector of length nx, or a ValueError naming ``name``."""
        return array(x, name, (self.nx,))
