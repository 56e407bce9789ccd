"""A robot or system to control: its true plant, the controller's model, defaults and sampling.

Declare one by subclassing :class:`Problem` and implementing three public hooks — ``dynamics(error)``
(the continuous model as a :class:`~ocpkit.model.dynamics.Model`, inertias scaled by the paper's error multiplier),
``defaults()`` (the OCP's weights and bounds) and ``sample(seed)`` (a seeded start and goal) — with
``name``, ``dt``, ``horizon`` and ``duration`` as class attributes. A robot described by a URDF needs no
code: :meth:`Problem.from_urdf` (a :class:`URDFRobot`).
"""

from __future__ import annotations

import inspect
import os
import sys
import sysconfig
import traceback
from functools import cached_property
from pathlib import Path

import casadi as ca
import numpy as np

from ocpkit._checks import positive
from ocpkit.model.dynamics import Model
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization


class ProblemError(ValueError):
    """A problem's own code failed: importing its file or module, making it, or its dynamics returned NaN.

    The message is one line naming the spec, the user's file and line (``where``, "file:line", or None where no
    line of the user's code is known) and the exception; ``__cause__`` is the original exception (its traceback is
    what ``ocpkit --debug`` prints)."""

    def __init__(self, message: str, where: str | None = None):
        super().__init__(message)
        self.where = where


class NotAProblemError(ProblemError, TypeError):
    """A spec's factory returned, or its name is, something other than a :class:`Problem` (also a TypeError)."""


class DynamicsError(ProblemError, FloatingPointError):
    """A model's dynamics returned NaN or inf at a finite state and input: ``x``, ``u`` and the entries ``rows`` of
    ẋ (also a FloatingPointError, what :func:`~ocpkit.sim.simulate.simulate` raised before)."""

    def __init__(self, message: str, where: str | None = None, *, x=None, u=None, rows=()):
        super().__init__(message, where)
        self.x, self.u, self.rows = x, u, tuple(rows)


def _shown(path: str) -> str:
    """``path`` relative to the working directory when it lies below it, else as given."""
    try:
        rel = os.path.relpath(path)
    except ValueError:
        return path
    return rel if not rel.startswith("..") else path


def where_defined(obj) -> str | None:
    """ "file:line" of the source of a function or class (None where Python does not know it)."""
    obj = inspect.unwrap(obj) if callable(obj) else obj
    code = getattr(getattr(obj, "__func__", obj), "__code__", None)
    try:
        if code is not None:
            return f"{_shown(code.co_filename)}:{code.co_firstlineno}"
        return f"{_shown(inspect.getsourcefile(obj))}:{inspect.getsourcelines(obj)[1]}"
    except (TypeError, OSError):
        return None


def _library_dirs() -> tuple[str, ...]:
    """Folders of code that is not the user's: ocpkit's packages, the standard library and installed packages."""
    dirs = {
        os.path.realpath(p)
        for key in ("stdlib", "platstdlib", "purelib", "platlib")
        if (p := sysconfig.get_paths().get(key))
    }
    for name in ("ocpkit", "ocpkit.problems", "ocpkit.solvers", "ocpkit.studies"):
        module = sys.modules.get(name)
        dirs.update(os.path.realpath(p) for p in getattr(module, "__path__", ()))
    return tuple(d.rstrip(os.sep) + os.sep for d in dirs)


def where_raised(exc: BaseException, own=()) -> str | None:
    """ "file:line" in the user's code where ``exc`` was raised: a SyntaxError's own line, else the innermost frame of
    its traceback in one of the files ``own`` or outside ocpkit, the standard library and installed packages."""
    if isinstance(exc, SyntaxError) and exc.filename and not str(exc.filename).startswith("<") and exc.lineno:
        return f"{_shown(exc.filename)}:{exc.lineno}"
    own = {os.path.realpath(f) for f in own}
    library = _library_dirs()
    for frame in reversed(traceback.extract_tb(exc.__traceback__)):
        name = frame.filename
        if name.startswith("<"):
            continue
        real = os.path.realpath(name)
        if real in own or not real.startswith(library):
            return f"{_shown(name)}:{frame.lineno}"
    return None


def describe(exc: BaseException) -> str:
    """``Type: message`` of an exception on one line (a SyntaxError's message without its location)."""
    text = exc.msg if isinstance(exc, SyntaxError) and exc.msg else str(exc)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    text = lines[0] + (" …" if len(lines) > 1 else "") if lines else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def check_dynamics(model: Model, x, u, *, dt: float | None = None, substeps: int = 1, context: str = "") -> None:
    """Raise :class:`DynamicsError` where ``model``'s ẋ = f(x, u) is NaN or inf at a finite point: at (x, u), and
    with ``dt`` at every stage of the RK4 step (``substeps`` of them) from there. A stage that is itself non-finite
    (the integration overflowed) ends the search: the dynamics did not return NaN there, the step diverged."""
    x = np.asarray(x, dtype=float).ravel()
    u = np.asarray(u, dtype=float).ravel()

    def f(point):
        if not (np.isfinite(point).all() and np.isfinite(u).all()):
            return None
        value = np.asarray(model.f(point, u), dtype=float).ravel()
        if not np.isfinite(value).all():
            raise _dynamics_error(model, point, u, value, context)
        return value

    if f(x) is None or dt is None:
        return
    h = float(dt) / substeps
    xk = x
    for _ in range(substeps):
        k1 = f(xk)
        k2 = f(xk + h / 2 * k1)
        if k2 is None:
            return
        k3 = f(xk + h / 2 * k2)
        if k3 is None:
            return
        k4 = f(xk + h * k3)
        if k4 is None:
            return
        xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if f(xk) is None:
            return


def _dynamics_error(model: Model, x, u, value, context: str) -> DynamicsError:
    rows = np.flatnonzero(~np.isfinite(value))
    what = "NaN" if np.isnan(value).any() else "inf"
    entries = ", ".join(f"xdot[{i}]" for i in rows[:4]) + (" …" if len(rows) > 4 else "")
    origin = getattr(model, "origin", None)
    who = origin[0] if origin else f"the dynamics of model {model.name!r}"
    fmt = lambda v: "[" + ", ".join(repr(float(a)) for a in v) + "]"  # noqa: E731  exact: a NaN may lie at an edge
    where = origin[1] if origin else None
    notes = "; ".join(n for n in ((f"{who.split('(')[0]} is at {where}" if where else ""), context) if n)
    return DynamicsError(
        f"{who} returned {what} in {entries} at x = {fmt(x)}, u = {fmt(u)}" + (f" ({notes})" if notes else ""),
        where,
        x=x.copy(),
        u=u.copy(),
        rows=rows,
    )


class Problem:
    """Base class of every problem. Subclasses implement :meth:`dynamics`, :meth:`defaults` and :meth:`sample`.

    ``model(error)`` is the controller's model with the paper's error multiplier applied (cached per error);
    ``plant()`` is always the true model (error = 1): model error belongs to the controller, never to the
    plant. ``ocp(...)`` assembles the MPC problem from these. Override :meth:`goal_input` when the input that
    holds a goal at rest depends on the goal nonlinearly (gravity compensation).
    """

    name = "problem"
    dt = 0.01
    horizon = 50
    duration = 1.0  # seconds of closed loop in the paper's experiments

    # --- the hooks a problem implements ------------------------------------------------------------------

    def dynamics(self, error: float) -> Model:
        """The continuous model ẋ = f(x, u) with every modelled mass/inertia scaled by ``error`` (1: the truth)."""
        raise NotImplementedError(f"{type(self).__name__} must implement dynamics(error) -> ocpkit.Model")

    def defaults(self) -> dict:
        """OCP keyword arguments: Q, R and bounds (and optionally Q_terminal, u_goal, u_goal_gain, x_min, x_max)."""
        raise NotImplementedError(f"{type(self).__name__} must implement defaults() -> dict with at least Q and R")

    def sample(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Seeded random start and goal states."""
        raise NotImplementedError(f"{type(self).__name__} must implement sample(seed) -> (x0, goal)")

    def goal_input(self) -> ca.Function | None:
        """An extra, goal-dependent input goal x_goal -> u added to u_goal + K x_goal (None: none).

        For a robot under gravity the input that holds q_goal at rest is g(q_goal); without it the cost's R
        term pulls the inputs towards zero and leaves a steady-state error.
        """
        return None

    # --- what the rest of ocpkit calls -------------------------------------------------------------------

    def model(self, error: float = 1.0) -> Model:
        """The controller's model with every modelled mass/inertia scaled by ``error``."""
        error = positive(error, "error")
        if error not in self._models:
            model = self.dynamics(error)
            if not isinstance(model, Model):
                raise TypeError(
                    f"{type(self).__name__}.dynamics({error}) must return an ocpkit.Model, got {type(model).__name__}"
                )
            # who made it, for a message naming the user's hook when its ẋ is NaN (check_dynamics)
            model.origin = (f"{type(self).__name__}.dynamics(error)", where_defined(type(self).dynamics))
            self._models[error] = model
        return self._models[error]

    def plant(self) -> Model:
        """The true system (error multiplier 1)."""
        return self.model(1.0)

    @cached_property
    def _models(self) -> dict:
        return {}

    def ocp(
        self,
        *,
        knots: int | None = None,
        horizon: int | None = None,
        error: float = 1.0,
        parameterization: str | Parameterization = "linear",
        dt: float | None = None,
        **overrides,
    ) -> OCP:
        """The MPC problem: ``knots`` None means traditional MPC (p = T) — unlike the command line, which takes 5
        knots unless told otherwise (:data:`ocpkit.solvers.methods.KNOTS`); other keywords override defaults or set
        the OCP's options, e.g. ``integrator="euler"`` for the controller's prediction (the plant keeps RK4).
        ``parameterization`` is a kind's name (:data:`~ocpkit.model.parameterization.KINDS`) or a Parameterization,
        e.g. ``Parameterization.custom(basis)``, which sets the knots and the horizon (``knots``, ``horizon`` None or
        the same)."""
        if isinstance(parameterization, Parameterization):
            param, T = parameterization, parameterization.horizon
            for name, value in (("knots", knots), ("horizon", horizon)):
                if value is not None and value != getattr(param, name):
                    raise ValueError(f"{name}={value} differs from the parameterization's {getattr(param, name)}")
        else:
            T = self.horizon if horizon is None else horizon
            param = Parameterization.make(parameterization, T, knots)
        kwargs = {**self.defaults(), **overrides}
        args = (self.model(error), self.dt if dt is None else dt, T)
        extra = self.goal_input()
        if extra is None:
            return OCP(*args, parameterization=param, **kwargs)
        return GoalInputOCP(*args, parameterization=param, goal_input=extra, **kwargs)

    @classmethod
    def from_urdf(cls, path, **options) -> "URDFRobot":
        """A torque-controlled robot from a URDF file; see :class:`URDFRobot` for ``options``."""
        return URDFRobot(path, **options)

    def __repr__(self):
        return f"{type(self).__name__}({self.name!r})"


class GoalInputOCP(OCP):
    """An OCP whose input goal is u_g(x_goal) = u_goal + K x_goal + h(x_goal) with a CasADi Function h.

    Everything that reads the input goal — the QPs' expansion point and R term, the fallback, the cost's "input"
    term that IPOPT and EMPC read — goes through :meth:`input_goal` and :meth:`input_error`, both extended here;
    the exported C step generates h into its C (``ocpkit.export``).
    """

    def __init__(self, *args, goal_input: ca.Function, **kwargs):
        super().__init__(*args, **kwargs)
        if not isinstance(goal_input, ca.Function):
            raise TypeError(f"goal_input must be a casadi.Function x_goal -> u, got {type(goal_input).__name__}")
        if (
            goal_input.n_in() != 1
            or goal_input.n_out() != 1
            or goal_input.size_in(0) != (self.nx, 1)
            or goal_input.size_out(0) != (self.nu, 1)
        ):
            raise ValueError(
                f"goal_input must map one ({self.nx}, 1) goal to one ({self.nu}, 1) input, got "
                f"{goal_input.size_in(0) if goal_input.n_in() else None} -> "
                f"{goal_input.size_out(0) if goal_input.n_out() else None}"
            )
        self.goal_input = goal_input

    def input_error(self, u, x_goal):
        """u − u_goal − K x_goal − h(x_goal): the "input" term's residual."""
        return super().input_error(u, x_goal) - self.goal_input(x_goal)

    def input_goal(self, x_goal) -> np.ndarray:
        """u_g = u_goal + K x_goal + h(x_goal), the last one kept: a step asks for it two or three times, and h
        through CasADi's Python interface took 0.35 ms a call on a 7-DoF arm (its gravity torques)."""
        x_goal = np.asarray(x_goal, dtype=float)
        last = self.__dict__.get("_last_input_goal")
        if last is None or not np.array_equal(last[0], x_goal):
            value = super().input_goal(x_goal) + np.asarray(self.goal_input(x_goal), dtype=float).ravel()
            last = self._last_input_goal = (x_goal.copy(), value)
        return last[1].copy()


class URDFRobot(Problem):
    """A torque-controlled robot read from a URDF: state x = [q, q̇], input τ (forces on prismatic joints).

    * Kinematics and inertias come from the URDF through pinocchio (fixed joints merge into their links);
      revolute, continuous and prismatic joints are supported, in a chain or a tree (fingers on a hand). A
      continuous joint is one unbounded angle in q (pinocchio's ``pin_model`` keeps its cos/sin pair).
    * ``locked_joints``: joint names frozen at ``locked_positions`` (a dict name -> value; default 0 clipped
      into the joint's limits); they leave the state and the input.
    * ``damping`` and ``friction`` (viscous b and Coulomb f per joint, friction smoothed as f tanh(q̇ / 0.01)):
      None reads the URDF's ``<dynamics damping friction>``; a scalar or one value per joint overrides it.
    * ``effort_limits``: None reads the URDF's ``<limit effort>`` as the input bounds ±τ_max (a joint
      without one is unbounded); a scalar or one value per joint overrides.
    * ``gravity``: simulate gravity (the URDF world's −9.81 m/s² along z). With ``gravity_compensation`` the
      input goal is g(q_goal), the torque that holds the goal at rest (see :meth:`Problem.goal_input`).
    * ``position_bounds``: the URDF's joint limits as (soft, in LinearMPC) state bounds.
    * Defaults: Q = diag(``q_weight`` per position, ``qd_weight`` per rate), R = ``r_weight`` I, terminal
      weight Q (a heavier one, 10 Q, made the condensed QP of the Panda's light wrist so ill-conditioned —
      condition ~1e9 — that ProxQP ran into its iteration limit on most steps of some starts). ``sample(seed)``: at
      rest, q0 uniform in the middle half of each joint's range (±π/2 for an unlimited joint), the goal q0 plus a
      uniform step of up to ±``step`` per joint, within the limits.
    * ``end_effector``: the frame that task terms aim (``kinematics``, an :class:`ocpkit.model.kinematics.Kinematics`,
      holds every URDF link and joint); None: the deepest link fixed to the last joint of the first serial
      branch (the Panda's ``panda_hand_tcp``). ``link_radius`` (m, an attribute) sizes
      :func:`ocpkit.model.kinematics.spheres_along_links`.
    The error multiplier scales M(q) in the controller's model (not g(q), as for the paper's robots).
    """

    link_radius = 0.06

    def __init__(
        self,
        urdf,
        *,
        locked_joints=(),
        locked_positions=None,
        damping=None,
        friction=None,
        effort_limits=None,
        gravity: bool = True,
        gravity_compensation: bool = True,
        position_bounds: bool = False,
        name: str | None = None,
        dt: float = 0.01,
        horizon: int = 50,
        duration: float = 2.0,
        q_weight: float = 100.0,
        qd_weight: float = 1.0,
        r_weight: float = 1e-3,
        step: float = 0.5,
        end_effector: str | None = None,
    ):
        from ocpkit.model.rigid_body import Chain, load_urdf, position_limits

        self.urdf = str(urdf)
        self.pin_model = load_urdf(urdf, locked_joints=locked_joints, locked_positions=locked_positions)
        self.chain = Chain(self.pin_model)
        self.name = name or f"urdf:{Path(self.urdf).stem}"
        self.dt, self.duration = positive(dt, "dt"), positive(duration, "duration")
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        self.horizon = int(horizon)
        self.damping = self.chain.coefficients(self.pin_model.damping if damping is None else damping, "damping")
        self.friction = self.chain.coefficients(self.pin_model.friction if friction is None else friction, "friction")
        limits = np.asarray(self.pin_model.effortLimit, dtype=float) if effort_limits is None else effort_limits
        self.tau_max = self.chain.coefficients(limits, "effort_limits")
        self.tau_max[self.tau_max == 0] = np.inf  # a URDF without <limit effort> reads as 0
        self.gravity, self.gravity_compensation = bool(gravity), bool(gravity_compensation)
        self.position_bounds = bool(position_bounds)
        self.q_weight, self.qd_weight = positive(q_weight, "q_weight"), positive(qd_weight, "qd_weight")
        self.r_weight, self.step = positive(r_weight, "r_weight"), positive(step, "step")
        lo, hi = position_limits(self.pin_model)
        self.q_min = np.where(np.isfinite(lo) & (lo < hi), lo, -np.inf)
        self.q_max = np.where(np.isfinite(hi) & (lo < hi), hi, np.inf)
        velocity = np.asarray(self.pin_model.velocityLimit, dtype=float)
        self.velocity_limit = np.where(velocity > 0, velocity, np.inf)  # the URDF's <limit velocity>; 0: none
        kin = self.kinematics
        if end_effector is not None and end_effector not in kin.frames:
            raise ValueError(
                f"end_effector {end_effector!r} is not a frame of {self.urdf}; its frames: {', '.join(kin.frames)}"
            )
        self.end_effector = end_effector or kin.tip() or kin.joints[-1]

    @cached_property
    def kinematics(self):
        """The URDF's frames as CasADi expressions of q (an :class:`ocpkit.model.kinematics.Kinematics`)."""
        from ocpkit.model.kinematics import Kinematics

        return Kinematics(self.pin_model)

    @property
    def joint_names(self) -> list[str]:
        return list(self.chain.names)

    def dynamics(self, error: float) -> Model:
        n = self.chain.n
        x, u = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n)
        qdd = self.chain.forward_dynamics(
            x[:n], x[n:], u, damping=self.damping, friction=self.friction, inertia_scale=error, gravity=self.gravity
        )
        names = self.joint_names
        return Model(
            self.name,
            x,
            u,
            ca.vertcat(x[n:], qdd),
            state_names=[f"q_{j}" for j in names] + [f"qd_{j}" for j in names],
            input_names=[f"tau_{j}" for j in names],
        )

    def goal_input(self) -> ca.Function | None:
        if not (self.gravity and self.gravity_compensation):
            return None
        n = self.chain.n
        xg = ca.SX.sym("x_goal", 2 * n)
        return ca.Function("gravity_compensation", [xg], [self.chain.gravity(xg[:n])], ["x_goal"], ["u"])

    def defaults(self) -> dict:
        n = self.chain.n
        Q = np.diag(np.r_[np.full(n, self.q_weight), np.full(n, self.qd_weight)])
        out = {"Q": Q, "R": self.r_weight * np.eye(n), "Q_terminal": Q, "u_min": -self.tau_max, "u_max": self.tau_max}
        if self.position_bounds:
            out["x_min"] = np.r_[self.q_min, np.full(n, -np.inf)]
            out["x_max"] = np.r_[self.q_max, np.full(n, np.inf)]
        return out

    def sample(self, seed: int):
        rng = np.random.default_rng(seed)
        n = self.chain.n
        bounded = np.isfinite(self.q_min) & np.isfinite(self.q_max)
        lo, hi = np.where(bounded, self.q_min, -np.pi), np.where(bounded, self.q_max, np.pi)  # unlimited: ±π/2
        mid, half = (lo + hi) / 2, (hi - lo) / 4
        q0 = rng.uniform(mid - half, mid + half)
        # A prismatic joint's step is scaled to its range (fingers travel centimetres, not half a metre).
        step = np.where(np.array(self.chain.revolute) | ~bounded, self.step, np.minimum(self.step, half))
        qg = np.clip(q0 + rng.uniform(-1.0, 1.0, size=n) * step, self.q_min, self.q_max)
        return np.r_[q0, np.zeros(n)], np.r_[qg, np.zeros(n)]
