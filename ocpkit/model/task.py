"""A task beyond the joint-space goal: named, weighted cost terms and spherical obstacles, for every controller.

The OCP's cost (ocpkit.model.ocp) is a sum of named terms. Two are built in and always there — "state",
(x − x_goal)ᵀQ(x − x_goal), and "input", (u − u_g)ᵀR(u − u_g) — and a :class:`Task` adds more, each a
weighted least-squares residual in the style of Crocoddyl's ``CostModelSum``::

    term_i = Σ_k r_i(x_k, u_k, target_i)ᵀ W_i r_i(x_k, u_k, target_i)   (stage, k = 0 … T−1; terminal: x_T)

with W_i = diag(weight) and ``active`` switching a term off. Targets are part of the goal: with a task the goal
vector that ``solve(x, goal)`` takes is [x_goal; target_1; target_2; …] (:meth:`ocpkit.model.ocp.OCP.goal` builds it
by name), so a frame-position target moves at run time like a joint goal.

Obstacles are spheres in the world; the robot is approximated by spheres fixed in its frames
(:mod:`ocpkit.model.kinematics`). Each pair's clearance d = ‖c_robot(q) − c_obstacle‖ − r_robot − r_obstacle must stay
at or above ``margin`` at x_1 … x_T. Each controller takes this in the way that suits it:

* NonlinearMPC (IPOPT, SQP): nonlinear inequality constraints d ≥ margin at every predicted state.
* LinearMPC and real-time iteration: the constraints linearized about the plan, as rows of the QP for the pairs
  within ``ACTIVATION`` of their margin (each robot sphere's ``ROWS_PER_SPHERE`` closest obstacles, at most
  ``ROWS_PER_STAGE`` a stage), treated as the state bounds are: DAQP solves them hard and, only where the
  hard QP is infeasible (a start already inside the margin), softened; ProxQP and OSQP solve the soft QP, an exact
  penalty: one slack s_k ≥ 0 per stage with such rows, cost ``obstacle_weight``·(s_k + ½s_k²).
* EMPC, CEM, MPPI: the same penalty in the rollout fitness, with h_k = max(0, margin − min d at x_k) in place of
  the slack: ``obstacle_weight``·(h_k + ½h_k²) per stage (``penalty``).

Residuals are CasADi expressions, so the QPs take their Gauss–Newton model (ocpkit.qp.transcription), IPOPT their
exact derivatives and the sampling kernels their translation (ocpkit.codegen.kernels.translate).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ocpkit._checks import positive
from ocpkit.model.task_functions import CompiledTask

# A stage's linearized obstacle rows enter the QP only where some pair's clearance at the plan is within this
# many metres of the margin (a plan this far from every obstacle will not reach one within a step).
ACTIVATION = 0.1
# The QPs' obstacle rows are bounded (ocpkit.qp.task_rows.TaskRows.select): each robot sphere's closest obstacles, at
# most this many, and at most this many rows a stage (the closest pairs first; the Panda has 23 spheres).
ROWS_PER_SPHERE, ROWS_PER_STAGE = 2, 24
# reach()'s obstacle penalty weight (per metre of violation, and its square): far above the multipliers of a clearance
# constraint under its default position weight, so the exact penalty keeps the constraint wherever it can be met.
REACH_OBSTACLE_WEIGHT = 1e5
# The largest link radius and |margin| (m) a task takes. The arms ocpkit models span 0.6-1.5 m (Puma 560, Panda,
# Baxter) and a robot cell a few metres: 10 m is beyond any of them, while 1e6 m (a unit slip) makes every obstacle
# a collision that no plan can clear.
MAX_LENGTH = 10.0
# A position target farther from the world origin than this many times the robot's size (its farthest frame at
# q = 0) is a typo or a unit slip, not a reach: 100 x leaves room for targets beyond reach (the loop then stalls, as
# it should), and keeps the squared position cost far from overflow (a target at 1e300 m made every step NaN).
WORKSPACE_FACTOR = 100.0


def length(value, name: str, *, signed: bool = False) -> float:
    """A length in metres within MAX_LENGTH: > 0, or any sign within ±MAX_LENGTH when ``signed`` (a margin)."""
    if not signed:
        v = positive(value, name)
    else:
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be a number (m), got {value!r}") from None
    if not np.isfinite(v) or abs(v) > MAX_LENGTH:
        span = f"within ±{MAX_LENGTH:g} m" if signed else f"> 0 and at most {MAX_LENGTH:g} m"
        raise ValueError(f"{name} must be {span} (a robot's scale), got {value!r}")
    return v


class FixedFrameError(ValueError):
    """A target for ``frame``, a frame fixed to the world; ``reason`` is the message after the frame's name (for a
    caller that names the frame itself)."""

    def __init__(self, frame: str, reason: str):
        super().__init__(f"frame {frame!r} {reason}")
        self.frame, self.reason = frame, reason


def check_frame(kinematics, frame: str) -> str:
    """``frame`` if it names a frame that moves with the joints; a frame fixed to the world ("universe", a base
    link) cannot be brought anywhere, so a target for it is refused (:class:`FixedFrameError`)."""
    q = ca.SX.sym("q", kinematics.n)

    def moves(name):  # an unknown frame fails here, with its name and the model's frames
        R, p = kinematics.placement(q, name)
        return ca.depends_on(ca.vertcat(p, ca.vec(R)), q)

    if not moves(frame):
        moving = [f for f in kinematics.frames if moves(f)]
        raise FixedFrameError(
            frame,
            "is fixed to the world (it does not move with the joints); a target needs one of "
            f"the robot's moving frames: {', '.join(moving)}",
        )
    return frame


def workspace_radius(kinematics) -> float:
    """The farthest a position target may lie from the world origin (m): WORKSPACE_FACTOR × the robot's size, its
    farthest frame from the origin at q = 0 (at least 0.1 m)."""
    q = ca.SX.sym("q", kinematics.n)
    frames = ca.Function("frames", [q], [ca.horzcat(*(kinematics.position(q, f) for f in kinematics.frames))])
    size = float(np.linalg.norm(np.asarray(frames(np.zeros(kinematics.n))), axis=0).max())
    return WORKSPACE_FACTOR * max(size, 0.1)


def check_point(point, radius: float, name: str) -> np.ndarray:
    """A position target (3 finite numbers) within ``radius`` m of the world origin (:func:`workspace_radius`)."""
    p = _vector(point, name, 3)
    scale = float(np.abs(p).max())
    distance = scale * float(np.linalg.norm(p / scale)) if scale else 0.0  # no overflow at 1e300
    if distance > radius:
        raise ValueError(
            f"{name} {p.tolist()} is {distance:.3g} m from the world origin, beyond the robot's "
            f"plausible workspace ({radius:.3g} m, {WORKSPACE_FACTOR:g} × its size); give it in metres"
        )
    return p


def check_rotation(value, name: str) -> np.ndarray:
    """A rotation target as its 9 entries row by row: a 3 × 3 orthonormal matrix with determinant +1."""
    R = _vector(value, name, 9).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} must be a rotation matrix (orthonormal, determinant +1), got {R.tolist()}")
    return R.ravel()


def _vector(value, name: str, size: int | None = None) -> np.ndarray:
    a = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    if size is not None and a.size == 1 and size > 1:
        a = np.full(size, float(a[0]))
    if (size is not None and a.size != size) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be {size or 'some'} finite number(s), got {np.asarray(value).tolist()}")
    return a


class Term:
    """A named least-squares cost term r(x, u, target)ᵀ diag(weight) r at the stages and/or the terminal state.

    ``residual(x, u, target)`` returns a CasADi column (x, u, target are SX columns of nx, nu and
    ``target_size`` entries; a terminal term's residual must not depend on u). ``weight`` is a scalar or one
    value per residual entry (≥ 0); ``terminal_weight`` (default ``weight``) weights x_T when ``terminal``.
    ``active=False`` keeps the term declared but leaves it out of every controller's cost. ``target_check``
    (target, name) -> target, if given, validates a target when the goal is built
    (:meth:`ocpkit.model.ocp.OCP.goal`)."""

    def __init__(
        self,
        name: str,
        residual,
        weight=1.0,
        *,
        target_size: int = 0,
        stage: bool = True,
        terminal: bool = False,
        terminal_weight=None,
        active: bool = True,
        target_check=None,
    ):
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"a term's name must be a Python identifier (it names its target), got {name!r}")
        if name in ("state", "input", "x_goal"):
            raise ValueError(f"term name {name!r} is taken by the OCP's built-in terms")
        if not callable(residual):
            raise TypeError(f"term {name!r}: residual must be callable (x, u, target) -> CasADi column")
        if not (stage or terminal):
            raise ValueError(f"term {name!r} is neither a stage nor a terminal term")
        self.name, self.residual = name, residual
        self.target_size = int(target_size)
        self.stage, self.terminal, self.active = bool(stage), bool(terminal), bool(active)
        self._weight, self._terminal_weight = weight, terminal_weight
        self.target_check = target_check

    def __repr__(self):
        where = "+".join(w for w, on in (("stage", self.stage), ("terminal", self.terminal)) if on)
        return f"{type(self).__name__}({self.name!r}, {where}{'' if self.active else ', inactive'})"

    def expression(self, x, u, target):
        """The residual column and its weights (stage, terminal) for these symbols."""
        r = ca.vec(self.residual(x, u, target))
        if not isinstance(r, ca.SX):
            r = ca.SX(r)
        w = _vector(self._weight, f"term {self.name!r}: weight", r.numel())
        wT = (
            w
            if self._terminal_weight is None
            else _vector(self._terminal_weight, f"term {self.name!r}: terminal_weight", r.numel())
        )
        if (w < 0).any() or (wT < 0).any():
            raise ValueError(f"term {self.name!r}: weights must be >= 0")
        if self.terminal and ca.depends_on(r, u):
            raise ValueError(f"term {self.name!r} is a terminal term but its residual depends on u")
        return r, w, wT


def _frame_term(default_name: str, target_size: int):
    """Make ``pieces(kinematics, frame) -> (residual, target_check)`` a frame term's constructor, ``(kinematics, frame,
    weight=1.0, *, name=default_name, stage=True, terminal=True, terminal_weight=None, active=True) -> Term``: the
    frame checked first (:func:`check_frame`), the keywords handed on to :class:`Term` with a target of
    ``target_size`` entries."""

    def make(pieces):
        def constructor(
            kinematics,
            frame: str,
            weight=1.0,
            *,
            name: str = default_name,
            stage: bool = True,
            terminal: bool = True,
            terminal_weight=None,
            active: bool = True,
        ) -> Term:
            check_frame(kinematics, frame)
            residual, target_check = pieces(kinematics, frame)
            return Term(
                name,
                residual,
                weight,
                target_size=target_size,
                stage=stage,
                terminal=terminal,
                terminal_weight=terminal_weight,
                active=active,
                target_check=target_check,
            )

        constructor.__name__ = constructor.__qualname__ = pieces.__name__
        constructor.__doc__ = pieces.__doc__
        return constructor

    return make


@_frame_term("position", 3)
def FramePosition(kinematics, frame: str):
    """p_frame(q) − target: a frame's world position (3 entries) towards a target point given in the goal (within
    :func:`workspace_radius` of the world origin)."""
    radius = None  # computed at the first goal, once

    def check(target, where):
        nonlocal radius
        radius = workspace_radius(kinematics) if radius is None else radius
        return check_point(target, radius, where)

    return lambda x, u, target: kinematics.position(x[: kinematics.n], frame) - target, check


@_frame_term("orientation", 9)
def FrameOrientation(kinematics, frame: str):
    """½ vee(R_tᵀR − RᵀR_t): a frame's orientation R(q) towards a target rotation R_t (the goal carries its 9
    entries row by row). It is sin θ times the rotation axis of R_tᵀR: zero at the target, smooth everywhere."""

    def residual(x, u, target):
        R = kinematics.placement(x[: kinematics.n], frame)[0]
        # The target is R_t row by row; CasADi's reshape fills column by column, so it gives R_tᵀ.
        A = ca.mtimes(ca.reshape(target, 3, 3), R)
        A = A - A.T  # 2 sin θ [a]x for R_tᵀR = exp(θ [a]x)
        return 0.5 * ca.vertcat(A[2, 1], A[0, 2], A[1, 0])

    return residual, check_rotation


def JointLimitBarrier(
    q_min,
    q_max,
    weight=1e3,
    *,
    margin: float = 0.05,
    name: str = "joint_limits",
    terminal: bool = True,
    active: bool = True,
) -> Term:
    """A C¹ barrier at the joint limits: max(0, q − (q_max − margin)) + min(0, q − (q_min + margin)) per joint
    (zero inside the limits shrunk by ``margin``, linear beyond: quadratic cost). Infinite limits are skipped."""
    lo, hi = np.asarray(q_min, dtype=float).ravel(), np.asarray(q_max, dtype=float).ravel()
    if lo.shape != hi.shape or (lo > hi).any():
        raise ValueError(f"q_min and q_max must have one entry per joint and q_min <= q_max, got {lo} and {hi}")
    idx = np.flatnonzero(np.isfinite(lo) & np.isfinite(hi))
    margin = float(margin)

    def residual(x, u, target):
        q = x[ca.DM(idx.tolist())] if idx.size else ca.SX(0, 1)
        return ca.fmax(0, q - ca.DM(hi[idx] - margin)) + ca.fmin(0, q - ca.DM(lo[idx] + margin))

    return Term(name, residual, weight, terminal=terminal, active=active)


def UserTerm(
    name: str,
    residual,
    weight=1.0,
    *,
    target_size: int = 0,
    stage: bool = True,
    terminal: bool = False,
    terminal_weight=None,
    active: bool = True,
) -> Term:
    """Any residual: a callable (x, u, target) -> CasADi column, or a casadi.Function of (x, u) or (x, u, target)."""
    if isinstance(residual, ca.Function):
        fn = residual
        if fn.n_in() not in (2, 3) or fn.n_out() != 1:
            raise ValueError(
                f"term {name!r}: a Function residual takes (x, u) or (x, u, target) and returns one "
                f"column; got {fn.n_in()} inputs and {fn.n_out()} outputs"
            )
        residual = (lambda x, u, t: fn(x, u)) if fn.n_in() == 2 else (lambda x, u, t: fn(x, u, t))
    return Term(
        name,
        residual,
        weight,
        target_size=target_size,
        stage=stage,
        terminal=terminal,
        terminal_weight=terminal_weight,
        active=active,
    )


@dataclass(frozen=True)
class Sphere:
    """An obstacle: a ball of ``radius`` (m) about ``center`` (x, y, z in the world frame)."""

    center: tuple
    radius: float

    def __post_init__(self):
        object.__setattr__(self, "center", tuple(_vector(self.center, "Sphere center", 3)))
        object.__setattr__(self, "radius", positive(self.radius, "Sphere radius"))

    @classmethod
    def parse(cls, text: str) -> "Sphere":
        """A sphere from "x,y,z,r" (the CLI's ``--obstacle``)."""
        try:
            values = [float(v) for v in str(text).split(",")]
        except ValueError:
            values = []
        if len(values) != 4:
            raise ValueError(f"an obstacle is 'x,y,z,r' (centre and radius in metres), got {text!r}")
        return cls(tuple(values[:3]), values[3])


@dataclass
class Task:
    """Cost terms and obstacles added to an OCP (see the module docstring).

    ``terms``: :class:`Term` s (names unique). ``obstacles``: :class:`Sphere` s; they need ``kinematics`` (an
    :class:`ocpkit.model.kinematics.Kinematics`) and ``robot`` (its :class:`~ocpkit.model.kinematics.RobotSphere` s).
    ``margin`` is the clearance kept (m); ``obstacle_weight`` the exact penalty's weight in the QPs and the
    sampling planners' fitness."""

    terms: list = field(default_factory=list)
    obstacles: list = field(default_factory=list)
    kinematics: object = None
    robot: list = field(default_factory=list)
    margin: float = 0.01
    obstacle_weight: float = 1e4

    def __post_init__(self):
        self.terms, self.obstacles, self.robot = list(self.terms), list(self.obstacles), list(self.robot)
        names = [t.name for t in self.terms]
        for t in self.terms:
            if not isinstance(t, Term):
                raise TypeError(f"Task terms must be ocpkit.model.task.Term, got {type(t).__name__}")
        if len(set(names)) != len(names):
            raise ValueError(f"Task term names must be unique, got {names}")
        for o in self.obstacles:
            if not isinstance(o, Sphere):
                raise TypeError(f"Task obstacles must be ocpkit.model.task.Sphere, got {type(o).__name__}")
        if self.obstacles and (self.kinematics is None or not self.robot):
            raise ValueError(
                "a Task with obstacles needs kinematics= and robot= (the robot's spheres, e.g. "
                "ocpkit.model.kinematics.spheres_along_links(problem.kinematics, problem.link_radius))"
            )
        self.margin = length(self.margin, "margin", signed=True)
        self.obstacle_weight = positive(self.obstacle_weight, "obstacle_weight")

    def check_target(self, name: str, value) -> np.ndarray:
        """Term ``name``'s target as the goal holds it (its own ``target_check`` applied)."""
        term = next(t for t in self.terms if t.name == name)
        return value if term.target_check is None else term.target_check(value, name)

    @property
    def active_terms(self) -> list:
        return [t for t in self.terms if t.active]

    @property
    def targets(self) -> dict:
        """Target name -> size, in the goal vector's order (every declared term, active or not)."""
        return {t.name: t.target_size for t in self.terms if t.target_size}

    @property
    def target_size(self) -> int:
        return sum(self.targets.values())

    @property
    def pairs(self) -> int:
        """Robot-sphere/obstacle pairs: the clearances per state."""
        return len(self.robot) * len(self.obstacles)

    def compile(self, nx: int, nu: int) -> CompiledTask:
        """The task's CasADi Functions for an OCP of nx states and nu inputs (:mod:`ocpkit.model.task_functions`)."""
        return CompiledTask(self, nx, nu)


def clearances(kinematics, robot, obstacles, q_rows) -> np.ndarray:
    """The true clearance (m, no margin) at each configuration (rows of ``q_rows``, (M, n)): the smallest distance
    between the surfaces of a robot sphere (:class:`ocpkit.model.kinematics.RobotSphere`) and an obstacle; negative:
    they overlap, a collision. ``obstacles``: :class:`Sphere` s, or where they are at each configuration, (M, N, 4)
    (centre, radius; moving obstacles)."""
    from ocpkit.model.kinematics import sphere_centers

    q_rows = np.atleast_2d(np.asarray(q_rows, dtype=float))
    radii = np.array([s.radius for s in robot])
    C = np.asarray(sphere_centers(kinematics, robot).map(len(q_rows))(q_rows.T)).reshape(3, len(q_rows), len(robot))
    if not isinstance(obstacles, np.ndarray):
        obstacles = np.array([[[*o.center, o.radius] for o in obstacles]] * len(q_rows), dtype=float)
    out = np.full(len(q_rows), np.inf)
    for j in range(obstacles.shape[1]):
        centre, radius = obstacles[:, j, :3].T[:, :, None], obstacles[:, j, 3][:, None]
        d = np.linalg.norm(C - centre, axis=0) - radii[None, :] - radius
        out = np.minimum(out, d.min(axis=1))
    return out


def reach(
    problem,
    obstacles=(),
    *,
    frame: str | None = None,
    position_weight: float = 1e3,
    terminal_weight: float | None = None,
    margin: float = 0.01,
    link_radius: float | None = None,
    obstacle_weight: float = REACH_OBSTACLE_WEIGHT,
    velocity_limits: bool = True,
    terms=(),
    **ocp_options,
):
    """The OCP "bring ``frame`` to a point, clear of ``obstacles``" for a robot problem with ``kinematics``.

    Cost: the frame-position term "position" (``position_weight`` per m² at every stage and, ``terminal_weight``,
    by default the same, at x_T: ten times as much made the light-wristed Panda's condensed QP ill-conditioned
    beyond what a QP solver can answer), the problem's velocity weights as the "state" term (its joint-angle
    weights set to zero: the posture is free) and its input term. Obstacles (:class:`Sphere` s, or "x,y,z,r"
    strings) are kept ``margin`` away from spheres of ``link_radius`` (default the problem's) along the robot's links
    (both within ``MAX_LENGTH``). ``terms``: more :class:`Term` s, such as :func:`FrameOrientation`, another frame's
    :func:`FramePosition` or :func:`JointLimitBarrier`. Other keywords go to ``problem.ocp`` (``knots``,
    ``horizon``, ...). The goal is ``ocp.goal(x_ref, position=p, **the other terms' targets)``; a position target
    beyond :func:`workspace_radius` is refused there.

    ``velocity_limits``: the robot's joint velocity limits (``problem.velocity_limit``, a URDF's ``<limit
    velocity>``) as the OCP's state bounds — soft in LinearMPC, constraints for IPOPT, a penalty in the sampling
    planners. Without them a reach across the workspace saturated the Panda's torques from the first step, its
    joints passed 4 rad/s within 40 ms, the prediction model diverged and 17 of 24 closed loops failed (seeds 1–6,
    four linearizations); with them, none."""
    from ocpkit.model.kinematics import spheres_along_links

    kinematics = getattr(problem, "kinematics", None)
    if kinematics is None:
        raise ValueError(
            f"{problem!r} has no kinematics: a reach task needs a robot problem with frames "
            "(nlink, puma560, baxter, panda, a URDF)"
        )
    frame = frame or problem.end_effector
    obstacles = [o if isinstance(o, Sphere) else Sphere.parse(o) for o in obstacles]
    radius = problem.link_radius if link_radius is None else length(link_radius, "link_radius")
    weight = positive(position_weight, "position_weight")
    terminal = weight if terminal_weight is None else positive(terminal_weight, "terminal_weight")
    task = Task(
        [FramePosition(kinematics, frame, weight, terminal_weight=terminal), *terms],
        obstacles,
        kinematics=kinematics if obstacles else None,
        robot=spheres_along_links(kinematics, radius) if obstacles else (),
        margin=margin,
        obstacle_weight=obstacle_weight,
    )
    defaults = problem.defaults()
    nq = kinematics.n
    if "Q" not in ocp_options:
        Q = np.array(defaults["Q"], dtype=float)
        Q[:nq, :] = 0.0
        Q[:, :nq] = 0.0
        ocp_options.update(Q=Q, Q_terminal=Q)
    limit = getattr(problem, "velocity_limit", None)
    if velocity_limits and limit is not None and np.isfinite(limit).any() and not {"x_min", "x_max"} & set(ocp_options):
        x_min, x_max = (
            np.array(defaults.get(key, np.full(2 * nq, sign * np.inf)), dtype=float)
            for key, sign in (("x_min", -1.0), ("x_max", 1.0))
        )
        x_min[nq:], x_max[nq:] = np.maximum(x_min[nq:], -limit), np.minimum(x_max[nq:], limit)
        ocp_options.update(x_min=x_min, x_max=x_max)
    return problem.ocp(task=task, **ocp_options)
