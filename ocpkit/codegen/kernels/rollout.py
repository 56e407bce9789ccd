"""Population rollouts: N candidate knot sets simulated over the horizon, a cost and a violation each.

This is the inner loop of Algorithm 1 (lines 11-17 of the paper's EMPC): each candidate's
knots U (p × m) become inputs through the Parameterization basis (``get_u_from_U``), the
model is stepped T times and the stage and terminal costs are summed:

    J = Σ_{k=0}^{T-1} l(x_k, u_k, g_k, O_k) + l_T(x_T, g_T, O_T),

g_k the goal window's row k (a held goal: every row the same) and O_k the obstacles at stage k (where a task has
obstacles: their penalty is part of l). (The x_0 term is the same for every candidate, so rankings equal the OCP's
objective.) In the same pass the constraints the QPs hold — a task's obstacle clearances and the hard state bounds —
give each candidate its violation V = Σ_{k=1}^{T} v(x_k, O_k) (:func:`violation`), so that planners can select by
constraint domination (feasible first) rather than by the penalized cost alone. The goal and obstacle windows are
kernel data, copied in by :meth:`Rollout.load` each step: a goal or an obstacle that moves compiles nothing.
Dynamics are either the paper's affine model x⁺ = A_d x + B_d u + w_d, refreshed by the
caller each control step, or the full nonlinear discrete model F translated from CasADi
(the paper's future work). Costs are translated CasADi Functions, so non-smooth ones
(if/else, |·|, penalties) are evaluated exactly as written.

Kernels loop over knots and knot parameters at run time instead of unrolling them, so their compile time does not grow
with p (unrolled, it did): the basis enters as its few nonzeros per row
(:class:`SparseRows`), and the knots are read from their array.
"""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import types

import casadi as ca
import numpy as np
import taichi as ti

from ocpkit._checks import choice
from ocpkit.codegen.kernels import runtime
from ocpkit.codegen.kernels.translate import translate

DYNAMICS = ("affine", "nonlinear")


# The state bounds' exact penalty in the fitness, per unit of violation: the soft QP's slack cost at LinearMPC's default
# slack_weight (1e3 on the QP's objective, which is half the rollout cost J).
STATE_BOUND_WEIGHT = 2e3


# A candidate whose violation V is at most this counts as feasible (rounding, in the kernel's float type, of a
# trajectory that touches a constraint; V sums metres of clearance and state units beyond the bounds).
FEASIBILITY_TOLERANCE = 1e-6


def _bound_violations(ocp, x):
    """h_i = the violation of component i's state bound at x, for the components with a finite bound."""
    rows = np.flatnonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max)).tolist()
    lo, hi = (np.where(np.isfinite(b[rows]), b[rows], 0.0) for b in (ocp.x_min, ocp.x_max))
    return ca.fmax(0, ca.DM(lo) - x[rows]) * ca.DM(np.isfinite(ocp.x_min[rows]).astype(float)) + ca.fmax(
        0, x[rows] - ca.DM(hi)
    ) * ca.DM(np.isfinite(ocp.x_max[rows]).astype(float))


def obstacle_count(ocp) -> int:
    """N, the task's obstacles (0: none): with N > 0 the fitness and the violation take the table O (4 × N)."""
    tf = ocp.task_functions
    return tf.table.shape[1] if tf is not None and tf.pairs else 0


def fitness(ocp):
    """(stage (x, u, goal[, O]), terminal (x, goal[, O])): the OCP's cost over its whole goal vector, plus at every
    state x_0 … x_T the exact penalties of what the QPs hold as constraints: a task's obstacles (ocpkit.model.task,
    against the table O, 4 × N: centre and radius of each, an input where the task has obstacles) and the state
    bounds, STATE_BOUND_WEIGHT·Σ_i (h_i + ½h_i²) with h_i the violation of component i's bound."""
    stage, terminal = ocp.cost.stage, ocp.cost.terminal
    N = obstacle_count(ocp)
    x, u, g, O = ca.SX.sym("x", ocp.nx), ca.SX.sym("u", ocp.nu), ca.SX.sym("goal", ocp.ng), ca.SX.sym("O", 4, N)
    penalty = ocp.task_functions.penalty_at(x, O) if N else 0
    if ocp.has_state_bounds:
        h = _bound_violations(ocp, x)
        penalty = penalty + STATE_BOUND_WEIGHT * ca.sum1(h + 0.5 * h * h)
    if isinstance(penalty, int):
        return stage, terminal
    table = [O] if N else []
    return (
        ca.Function("fitness", [x, u, g, *table], [stage(x, u, g) + penalty]),
        ca.Function("fitness_T", [x, g, *table], [terminal(x, g) + penalty]),
    )


def constrained(ocp) -> bool:
    """Whether ``ocp`` holds constraints on its states: a task's obstacles or finite state bounds (without them
    every :func:`violation` is 0)."""
    tf = ocp.task_functions
    return bool(ocp.has_state_bounds or (tf is not None and tf.pairs))


def violation(ocp):
    """v (x[, O]) -> how far one state breaks the constraints the QPs hold: max(0, −min_pairs(d − margin)) over a
    task's obstacle clearances d (ocpkit.model.task) against the table O (4 × N, an input where the task has
    obstacles) plus Σ_i h_i over the state bounds; 0 exactly where x satisfies them. A candidate's violation sums it
    over x_1 … x_T (x_0 is the same for every candidate): a plan that grazes a constraint at many stages counts
    against one that breaks it as much once."""
    N = obstacle_count(ocp)
    x, O = ca.SX.sym("x", ocp.nx), ca.SX.sym("O", 4, N)
    v = ca.SX(0)
    if N:
        v += ca.fmax(0, -ca.mmin(ocp.task_functions.clearance_at(x, O)[0]))
    if ocp.has_state_bounds:
        v += ca.sum1(_bound_violations(ocp, x))
    return ca.Function("violation", [x, O] if N else [x], [v], ["x", "O"] if N else ["x"], ["v"])


class SparseRows:
    """A matrix (r × c) as its nonzeros by row: ``columns[k, s]`` and ``weights[k, s]``, s < ``width`` (the most
    nonzeros of a row, at least 1), columns in increasing order, a shorter row padded with weight 0 at column 0.

    Row k times a vector v is then Σ_s weights[k, s]·v[columns[k, s]]: the dense sum Σ_j M_kj v_j in the same
    order without its exact zeros, so the same value (up to the sign of a zero) for finite v. A
    Parameterization's basis has at most a B-spline's degree + 1 nonzeros per row (piecewise-linear 2, zero-order
    hold and identity 1); its shift matrix can be dense (the linear basis' pseudo-inverse). Kernels read both from
    a section of a :class:`Layout` (:meth:`values`, the columns as floats: exact below 2^24).
    """

    def __init__(self, matrix: np.ndarray):
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.ndim != 2:
            raise ValueError(f"matrix must be 2-D, got shape {matrix.shape}")
        nonzero = matrix != 0
        self.width = max(1, int(nonzero.sum(axis=1).max(initial=0)))
        self.columns = np.zeros((matrix.shape[0], self.width), dtype=np.int32)
        self.weights = np.zeros((matrix.shape[0], self.width))
        for k, row in enumerate(nonzero):
            cols = np.flatnonzero(row)
            self.columns[k, : cols.size] = cols
            self.weights[k, : cols.size] = matrix[k, cols]

    @property
    def size(self) -> int:
        """The section's length: the columns, then the weights, row by row."""
        return 2 * self.columns.size

    def values(self) -> np.ndarray:
        """The section's contents (:attr:`size` floats)."""
        return np.concatenate([self.columns.ravel(), self.weights.ravel()]).astype(np.float64)


class Layout:
    """Named sections of a rollout engine's data: one array on the device, of the engine's float type, the sections
    side by side in the order given. Kernels read a section at its offset, a compile-time constant: the layout is
    part of their key (:func:`ocpkit.codegen.kernels.runtime.shared`)."""

    def __init__(self, sizes: dict):
        self.sizes, self.offsets, total = dict(sizes), {}, 0
        for name, size in self.sizes.items():
            self.offsets[name] = total
            total += int(size)
        self.total = total

    def __getitem__(self, name: str) -> int:
        return self.offsets[name]

    @property
    def key(self) -> tuple:
        return tuple(self.sizes.items())


class Rollout:
    """Rollout engine for ``num_sims`` candidates of ``ocp`` on the Taichi runtime.

    Its arrays live on the device (Taichi ndarrays): ``knots`` (num_sims, p, m) the population, ``picked``
    (num_picked, p, m) the candidates chosen by :meth:`pick` (parents, elites), and ``data`` the sections of
    :attr:`layout`: x_0, the goal and obstacle windows, the affine model, the ``step_sections`` a planner changes every
    step (its seeds …: :meth:`stage`), the basis, then the ``sections`` it sets once (its bounds …: :meth:`write`).
    Kernels take them as arguments, so the kernels are compiled once per shape (:attr:`key`) and serve every engine of
    that shape in the process; Taichi's offline cache keys them by their code, so other processes load them
    (:func:`ocpkit.codegen.kernels.runtime.shared`).

    ``rollout(i, knots, data)`` is a ``@ti.func`` that simulates candidate i and returns its cost J and violation V
    (:func:`violation` summed over x_1 … x_T, on the rollout's ``dynamics``), and ``record(i, knots, data, out)`` one
    that writes them to row i of ``out``, for solver kernels that generate candidates and roll them out in one launch
    (``input_at(i, k, knots, data)``: the ``@ti.func`` of its input u_k).
    ``stage_cost`` (x, u, goal) -> scalar and ``terminal_cost`` (x, goal) -> scalar default to :func:`fitness`
    (the OCP's cost; with a task, its terms and its obstacles' penalty); goal has ``ocp.ng`` entries, stage k's row
    k of the step's goal window and the terminal cost's row T. The violation is the OCP's whatever the costs;
    ``constrained`` says whether it can be nonzero. The fitness and the violation read the ``obstacles`` (N) of the
    task at stage k from row k of the step's obstacle window.

    Each Taichi call that moves an array costs tens of microseconds of launch overhead, more than a small population's
    rollouts, so a control step moves its data in as few calls as possible: :meth:`load` sends x_0, the goal and
    obstacle windows, the affine model and the step sections in one, solver kernels return the costs and violations
    through one output array (:meth:`record`), :meth:`pick` returns what it gathered.
    """

    def __init__(
        self,
        ocp,
        num_sims: int,
        *,
        num_picked: int = 1,
        dynamics: str = "affine",
        stage_cost=None,
        terminal_cost=None,
        precision: str = "float64",
        arch: str = "auto",
        sections: dict | None = None,
        step_sections: dict | None = None,
    ):
        if isinstance(num_sims, bool) or not isinstance(num_sims, (int, np.integer)) or num_sims < 1:
            raise ValueError(f"num_sims must be a positive integer, got {num_sims!r}")
        if (
            isinstance(num_picked, bool)
            or not isinstance(num_picked, (int, np.integer))
            or not 1 <= num_picked <= num_sims
        ):
            raise ValueError(f"num_picked must be an integer in [1, num_sims={num_sims}], got {num_picked!r}")
        choice(dynamics, DYNAMICS, "dynamics")
        self.ftype, self.ntype = runtime.float_types(precision)
        self.arch = runtime.init(arch)
        n, m = ocp.nx, ocp.nu
        basis = np.asarray(ocp.parameterization.basis, dtype=np.float64)
        T, p = basis.shape
        self.num_sims, self.nx, self.nu, self.horizon, self.num_knots = int(num_sims), n, m, T, p
        self.dynamics, self.precision = dynamics, precision
        self.constrained = constrained(ocp)
        ng = self.ng = ocp.ng
        N = self.obstacles = obstacle_count(ocp)
        # the declared obstacles at every stage, (T+1, N, 4): load()'s default
        self._declared = np.broadcast_to(ocp.task_functions.table.T if N else np.zeros((0, 4)), (T + 1, N, 4))
        for name, cost, inputs in (
            ("stage_cost", stage_cost, [(n, 1), (m, 1), (ng, 1)]),
            ("terminal_cost", terminal_cost, [(n, 1), (ng, 1)]),
        ):
            if cost is not None:
                _check_signature(name, cost, inputs, [(1, 1)])
        if stage_cost is None or terminal_cost is None:
            stage_default, terminal_default = fitness(ocp)
            stage_cost = stage_default if stage_cost is None else stage_cost
            terminal_cost = terminal_default if terminal_cost is None else terminal_cost
        # Each translated function returns (cost, violation) at its state: one expression graph, so the kinematics
        # that the obstacle penalty and the clearance violation share are computed once.
        v = violation(ocp)
        x, u, g, O = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("goal", ng), ca.SX.sym("O", 4, N)
        table = O if N else None
        stage = translate(_with_violation("stage_terms", stage_cost, v, [x, u, g], table), precision=precision)
        terminal = translate(_with_violation("terminal_terms", terminal_cost, v, [x, g], table), precision=precision)
        discrete = None
        if dynamics == "nonlinear":
            discrete = ocp.discrete()
            _check_signature("ocp.discrete()", discrete, [(n, 1), (m, 1)], [(n, 1)])
            discrete = translate(discrete, precision=precision)
        rows = SparseRows(basis)
        model = {"A": n * n, "B": n * m, "w": n} if dynamics == "affine" else {}
        windows = {"x0": n, "goal": (T + 1) * ng, "obstacles": (T + 1) * 4 * N}
        self.layout = Layout({**windows, **model, **(step_sections or {}), "basis": rows.size, **(sections or {})})
        self._step_sections = frozenset(step_sections or ())
        shape = (n, m, T, p, ng, N, rows.width, precision, self.arch)
        functions = tuple(f.path.stem for f in (stage, terminal, discrete) if f is not None)
        self.key = (*shape, dynamics, functions, self.layout.key)
        kernels = runtime.shared(
            ("rollout", *self.key),
            lambda: _kernels(shape, self.layout, stage.func, terminal.func, discrete and discrete.func),
        )
        self.input_at, self.rollout, self.record = kernels.input_at, kernels.rollout, kernels.record
        self._evaluate_all, self._gather = kernels.evaluate_all, kernels.gather
        self.knots = ti.ndarray(self.ftype, (num_sims, p, m))
        self.picked = ti.ndarray(self.ftype, (num_picked, p, m))
        self.data = ti.ndarray(self.ftype, (max(1, self.layout.total),))
        self.write("basis", rows.values())
        self._upload_buffer = np.zeros(self.layout["basis"], dtype=self.ntype)  # load()'s: its own, then the staged
        self._per_step = sum(windows.values()) + sum(model.values())  # load()'s own: x_0, the windows, the model

    def write(self, section: str, values) -> None:
        """Copy ``values`` (the section's size, any shape) into ``section`` of :attr:`data`, in one launch."""
        if section in self._step_sections:
            raise ValueError(f"section {section!r} changes every step: stage() it, load() sends it")
        runtime.write(self.data, self._values(section, values), self.layout[section])

    def stage(self, section: str, values) -> None:
        """Keep ``values`` (the section's size, any shape) for step section ``section``: the next :meth:`load` sends
        them with x_0 (and every later one, until staged again)."""
        if section not in self._step_sections:
            raise ValueError(f"section {section!r} is not a step section ({sorted(self._step_sections)})")
        start = self.layout[section]
        self._upload_buffer[start : start + self.layout.sizes[section]] = self._values(section, values)

    def _values(self, section: str, values) -> np.ndarray:
        values = np.asarray(values, dtype=self.ntype).ravel()
        if values.size != self.layout.sizes[section]:
            raise ValueError(f"section {section!r} takes {self.layout.sizes[section]} values, got {values.size}")
        return values

    def load(self, x0: np.ndarray, goal: np.ndarray, affine=None, obstacles=None) -> None:
        """Copy the initial state x_0, the goal (ng entries: the goal state, then a task's targets) held over the
        horizon or its window (T+1, ng), row k stage k's, the obstacles at every stage (T+1, N, 4) (centre, radius;
        None: where the task declares them), with affine dynamics this step's model ``affine`` = (A_d, B_d, w_d) for
        x⁺ = A_d x + B_d u + w_d, and the step sections (:meth:`stage`) to the device in one launch (no compiling)."""
        n, m, T, N = self.nx, self.nu, self.horizon, self.obstacles
        if (affine is None) != (self.dynamics != "affine"):
            raise ValueError(
                "affine (A_d, B_d, w_d) is required with dynamics='affine' and "
                f"not accepted with dynamics={self.dynamics!r}"
            )
        if obstacles is not None and not N:
            raise ValueError("obstacles given, but this OCP's task has no obstacles")
        window = np.asarray(goal, dtype=np.float64)
        window = _matrix("goal", window, (T + 1, self.ng)) if window.ndim == 2 else _vector("goal", window, self.ng)
        window = np.broadcast_to(window, (T + 1, self.ng))
        table = _matrix("obstacles", self._declared if obstacles is None else obstacles, (T + 1, N, 4))
        parts = [_vector("x0", x0, n), window.ravel(), table.ravel()]
        if affine is not None:
            A_d, B_d, w_d = affine
            parts += [_matrix("A_d", A_d, (n, n)).ravel(), _matrix("B_d", B_d, (n, m)).ravel(), _vector("w_d", w_d, n)]
        np.concatenate(parts, out=self._upload_buffer[: self._per_step], casting="same_kind")
        runtime.write(self.data, self._upload_buffer)

    def results(self, count: int | None = None) -> np.ndarray:
        """A host array for :meth:`record`'s output: (count, 2), count defaulting to ``num_sims``."""
        return np.empty((self.num_sims if count is None else count, 2), dtype=self.ntype)

    def evaluate(self, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Roll out the candidates ``knots`` (num_sims, p, m); returns their costs and violations."""
        knots = np.asarray(knots, dtype=np.float64)
        shape = (self.num_sims, self.num_knots, self.nu)
        if knots.shape != shape:
            raise ValueError(f"knots must have shape {shape}, got {knots.shape}")
        self.knots.from_numpy(knots.astype(self.ntype))
        out = self.results()
        self._evaluate_all(self.knots, self.data, out)
        return out[:, 0].astype(np.float64), out[:, 1].astype(np.float64)

    def pick(self, indices: np.ndarray) -> np.ndarray:
        """Copy candidates ``indices`` (best first) into ``picked[0:len(indices)]`` on the device;
        returns them, (len(indices), p, m), on the host."""
        indices = np.asarray(indices, dtype=np.int32).reshape(-1)
        count = indices.size
        if not 1 <= count <= self.picked.shape[0] or indices.min() < 0 or indices.max() >= self.num_sims:
            raise ValueError(
                f"indices must be 1..{self.picked.shape[0]} candidate numbers in "
                f"[0, {self.num_sims}), got {indices.tolist()}"
            )
        out = np.empty((count, self.num_knots, self.nu), dtype=self.ntype)
        self._gather(indices, self.knots, self.picked, out)
        return out.astype(np.float64)


def _kernels(shape, layout, stage, terminal, discrete):
    """The engine's ``@ti.func``s and kernels for one shape: (n, m, T, p, ng, N, basis width, precision, arch), the
    data's ``layout``, the translated ``stage`` and ``terminal`` fitness and, with nonlinear dynamics, the model F
    (``discrete``; None: affine). Every array is an argument, every size and offset a compile-time constant."""
    n, m, T, p, ng, N, width, precision, arch = shape
    F = runtime.float_types(precision)[0]
    o = layout.offsets
    serial = runtime.serial_transfers()

    if discrete is None:
        oA, oB, ow = o["A"], o["B"], o["w"]
        # Both forms unroll the rows and loop over the columns (a full unroll compiles far longer
        # at nlink:13). On the CPU, one dot product per row (measured faster: its n accumulators
        # would not fit in registers). On CUDA, the column loop outside: each column's n
        # multiply-adds are independent, so a thread issues them back to back instead of waiting
        # on one row's running sum (measured faster per generation on an H100, the launch
        # overhead subtracted).
        column_outer = arch == "cuda"

        @ti.func
        def step(x, u, data: ti.template()):
            xn = ti.Vector([data[ow + r] for r in ti.static(range(n))], dt=F)
            if ti.static(column_outer):
                for c in range(n):
                    xc = x[c]
                    for r in ti.static(range(n)):
                        xn[r] += data[oA + r * n + c] * xc
                for c in range(m):
                    uc = u[c]
                    for r in ti.static(range(n)):
                        xn[r] += data[oB + r * m + c] * uc
            else:
                for r in ti.static(range(n)):
                    s = xn[r]
                    for c in range(n):
                        s += data[oA + r * n + c] * x[c]
                    for c in range(m):
                        s += data[oB + r * m + c] * u[c]
                    xn[r] = s
            return xn
    else:

        @ti.func
        def step(x, u, data: ti.template()):
            return discrete(x, u)

    ox, og, oO, ob = o["x0"], o["goal"], o["obstacles"], o["basis"]
    weights = ob + T * width  # the basis' weights, after its columns

    @ti.func
    def input_at(i, k, knots: ti.template(), data: ti.template()):
        """u_k = Σ_j φ_kj U_j of candidate i, over the nonzeros of the basis' row k."""
        u = ti.Vector.zero(F, m)
        for s in ti.static(range(width)):
            j = ti.cast(data[ob + k * width + s], ti.i32)
            phi = data[weights + k * width + s]
            for a in ti.static(range(m)):
                u[a] += phi * knots[i, j, a]
        return u

    @ti.func
    def goal_at(k, data: ti.template()):
        return ti.Vector([data[og + k * ng + r] for r in ti.static(range(ng))], dt=F)

    if N:

        @ti.func
        def table_at(k, data: ti.template()):
            return ti.Vector([data[oO + k * 4 * N + r] for r in ti.static(range(4 * N))], dt=F)

        stage_with, terminal_with = stage, terminal
    else:  # no obstacles: the fitness takes no table; a placeholder stands for it

        @ti.func
        def table_at(k, data: ti.template()):
            return ti.Vector.zero(F, 1)

        @ti.func
        def stage_with(x, u, g, table):
            return stage(x, u, g)

        @ti.func
        def terminal_with(x, g, table):
            return terminal(x, g)

    @ti.func
    def rollout(i, knots: ti.template(), data: ti.template()):
        x = ti.Vector([data[ox + r] for r in ti.static(range(n))], dt=F)
        J = ti.cast(0.0, F)
        V = ti.cast(0.0, F)
        for k in range(T):
            u = input_at(i, k, knots, data)
            terms = stage_with(x, u, goal_at(k, data), table_at(k, data))
            J += terms[0]
            if k > 0:
                V += terms[1]
            x = step(x, u, data)
        terms = terminal_with(x, goal_at(T, data), table_at(T, data))
        return J + terms[0], V + terms[1]

    @ti.func
    def record(i, knots: ti.template(), data: ti.template(), out: ti.template()):
        """Roll out candidate i into row i of ``out`` (num, 2): its cost, its violation."""
        J, V = rollout(i, knots, data)
        out[i, 0] = J
        out[i, 1] = V

    @ti.kernel
    def evaluate_all(knots: ti.types.ndarray(), data: ti.types.ndarray(), out: ti.types.ndarray()):
        for i in range(knots.shape[0]):
            record(i, knots, data, out)

    @ti.kernel
    def gather(
        indices: ti.types.ndarray(), knots: ti.types.ndarray(), picked: ti.types.ndarray(), out: ti.types.ndarray()
    ):
        ti.loop_config(serialize=serial)
        for r, j, a in ti.ndrange(indices.shape[0], p, m):
            v = knots[indices[r], j, a]
            picked[r, j, a] = v
            out[r, j, a] = v

    return types.SimpleNamespace(
        input_at=input_at, rollout=rollout, record=record, evaluate_all=evaluate_all, gather=gather
    )


def _with_violation(name, cost, v, args, table=None) -> ca.Function:
    """(args[, table]) -> [cost; v(x[, table])], x = args[0], as one SX Function with common subexpressions merged;
    ``table`` the obstacles (4 × N) where the task has them, an input of the fitness (:func:`fitness`) and the
    violation, not of a cost of ``args`` alone (a user's)."""
    extra = [] if table is None else [table]
    try:
        terms = ca.vertcat(cost(*args, *extra[: cost.n_in() - len(args)]), v(args[0], *extra))
    except RuntimeError as exc:
        raise TypeError(f"{cost.name()!r} cannot be evaluated on SX symbols (the kernels translate SX): {exc}") from exc
    return ca.Function(name, args + extra, [ca.cse(terms)])


def _check_signature(name, function, inputs, outputs) -> None:
    if not isinstance(function, ca.Function):
        raise TypeError(f"{name} must be a casadi.Function, got {type(function).__name__}")
    got_in = [tuple(function.size_in(j)) for j in range(function.n_in())]
    got_out = [tuple(function.size_out(j)) for j in range(function.n_out())]
    if got_in != inputs or got_out != outputs:
        raise ValueError(f"{name} must map inputs of shapes {inputs} to outputs {outputs}, got {got_in} -> {got_out}")


def _vector(name, value, size) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64).reshape(-1)
    if value.shape != (size,):
        raise ValueError(f"{name} must have {size} entries, got {value.size}")
    return value


def _matrix(name, value, shape) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
    return value
