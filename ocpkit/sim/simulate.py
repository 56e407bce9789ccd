"""Closed-loop simulation: a controller at its control rate against a plant integrated more finely.

What counts as success. A step counts as a success only with status "success": the solver's answer certified and its
plan keeping the task's clearances and hard state bounds (:class:`ocpkit.controller.Controller`). A "soft" step applied
the solver's input but is not a success (its plan broke a clearance or a state bound: its reason and violation); a
fallback step applied the controller's safe input instead of the solver's. Steps say nothing about the task as a
whole: a loop whose every step succeeds can stop short of its target. :meth:`Trajectory.progress` gives that
loop-level verdict — "reached", "stalled" or "moving" — and :meth:`Trajectory.success_while_colliding` counts the
steps whose success the plant's next state contradicts.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ocpkit._checks import array, integer, positive
from ocpkit.controller import Controller
from ocpkit.status import SOFT, SUCCESS, Solution
from ocpkit.model.dynamics import Model
from ocpkit.model.problem import check_dynamics
from ocpkit.model.reference import ObstaclePath, Reference

# The loop-level verdict (Trajectory.progress) on the task error e(t): the frame's distance to its target point (m),
# or for a joint goal the state error max_i |x_i − x_goal,i| (the state's units, rad and rad/s for an arm).
REACHED, STALLED, MOVING = "reached", "stalled", "moving"
TOLERANCE = 0.01  # e at the last state within this: reached (1 cm, as the reach study's success)
WINDOW = 0.5  # s: the last stretch of the run over which a loop short of its target must still change e
STILL = 1e-3  # e's range (max − min) over that window at or below this: stalled (1 mm in 0.5 s: > 25 s per 5 cm)


@dataclass(frozen=True)
class Progress:
    """A closed loop's verdict on its task (module docstring): ``verdict`` "reached" (``final``, the error at the last
    state, within ``tolerance``), else "stalled" (the error's range over the last ``window`` seconds, ``change``, at
    most ``still``: no progress) or "moving" (it still changed, or the run is shorter than the window and ``change``
    is NaN). ``error`` is the task error at every state; ``what`` says which error it is, in ``unit``."""

    verdict: str
    error: np.ndarray
    final: float
    change: float
    what: str
    unit: str
    tolerance: float
    window: float
    still: float

    def to_dict(self) -> dict:
        """JSON-ready: the verdict, which error, its final value and change over the window, and the thresholds."""
        return {
            "verdict": self.verdict,
            "error": self.what,
            "unit": self.unit,
            "final": self.final,
            "change": None if np.isnan(self.change) else self.change,
            "tolerance": self.tolerance,
            "window": self.window,
            "still": self.still,
        }

    def text(self) -> str:
        """One line: the verdict and the numbers it rests on."""
        u = f" {self.unit}" if self.unit else ""
        line = (
            f"verdict: {self.verdict.upper() if self.verdict == STALLED else self.verdict} — {self.what} "
            f"{self.final:.4f}{u} at the end ({'within' if self.verdict == REACHED else 'not within'} "
            f"{self.tolerance:g}{u})"
        )
        if self.verdict == REACHED:
            return line
        if np.isnan(self.change):
            return line + f"; the run is shorter than the {self.window:g} s window"
        return line + (
            f", changed {self.change:.4f}{u} over the last {self.window:g} s "
            + (
                f"(at most {self.still:g}{u}: no progress)"
                if self.verdict == STALLED
                else f"(more than {self.still:g}{u}: still moving)"
            )
        )


def _tally(labels) -> str:
    """Labels counted, most frequent first ("limited 3, infeasible 1"; "" when none)."""
    counts: dict = {}
    for label in labels:
        counts[label] = counts.get(label, 0) + 1
    return _tally_text(counts)


def _tally_text(counts: dict) -> str:
    return ", ".join(f"{label} {n}" for label, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def summed_tallies(texts) -> str:
    """Tallies as a Trajectory writes them ("C step 990, fallback (plan) 10"; a label may hold ", ") summed over runs,
    most frequent first; "–" when none."""
    counts: dict = {}
    for text in texts:
        for label, n in re.findall(r"(.+?) (\d+)(?:, |$)", str(text)):
            counts[label] = counts.get(label, 0) + int(n)
    return _tally_text(counts) or "–"


@dataclass
class Trajectory:
    """A closed-loop run: times t (H+1,), states x (H+1, n), applied inputs u (H, m) and every Solution.

    ``goal`` is the goal vector (with a moving reference: the reference at the last time); ``reference`` the
    reference at every recorded time, (H+1, ng), where the goal moved (None: held); ``obstacles`` the task's
    obstacles at every recorded time, (H+1, N, 4), where they moved (None: where the task declares them)."""

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    goal: np.ndarray
    solutions: list = field(default_factory=list)
    reference: np.ndarray | None = None
    obstacles: np.ndarray | None = None

    def goals(self) -> np.ndarray:
        """The goal at every recorded time, (H+1, ng): the reference's, or the held goal repeated."""
        return (
            self.reference if self.reference is not None else np.broadcast_to(self.goal, (len(self.t), len(self.goal)))
        )

    def targets(self, ocp, term: str = "position") -> np.ndarray:
        """Task term ``term``'s target at every recorded time, (H+1, its size): its entries of :meth:`goals` (named
        "<term>[i]" by :meth:`ocpkit.model.ocp.OCP.goal_names`), the moving target point of a frame-position term."""
        names = ocp.goal_names()
        if f"{term}[0]" not in names:
            targets = sorted(getattr(ocp.task, "targets", None) or {})
            raise ValueError(f"the OCP's goal has no target of term {term!r}; targets: {targets or 'none'}")
        first = names.index(f"{term}[0]")
        return self.goals()[:, first : first + ocp.task.targets[term]]

    def tracking_error(
        self, kinematics=None, frame: str | None = None, targets=None, *, states: int | None = None, delay: int = 0
    ) -> np.ndarray:
        """The distance to the reference at every recorded time, (H+1,): with ``kinematics``, ``frame`` and
        ``targets`` (the target point at every recorded time, (H+1, 3), :meth:`targets`), the frame's distance (m)
        to it; without them max_i |x_i − x_ref,i| over the first ``states`` entries of x (default all; the joint
        angles: ``kinematics.n``). ``delay``: against the reference that many steps late (held at its first value
        before the start), for the lag."""
        missing = [
            name for name, v in (("kinematics", kinematics), ("frame", frame), ("targets", targets)) if v is None
        ]
        if missing and len(missing) < 3:
            raise ValueError(
                f"the tracking error of a frame needs kinematics, frame and targets; {missing[0]} is missing "
                f"(none of them: the state error)"
            )
        late = np.maximum(np.arange(len(self.t)) - integer(delay, "delay", 0), 0)
        if missing:  # none of them: the state error
            n = self.x.shape[1] if states is None else integer(states, "states", 1)
            return np.abs(self.x[:, :n] - self.goals()[late, :n]).max(axis=1)
        targets = array(targets, "targets", (len(self.t), 3))
        return np.linalg.norm(kinematics.positions(frame, self.x[:, : kinematics.n]) - targets[late], axis=1)

    @property
    def statuses(self) -> list[str]:
        return [s.status for s in self.solutions]

    @property
    def successes(self) -> int:
        """How many steps are successes: status "success" only (a "soft" step is not one)."""
        return sum(s.status == SUCCESS for s in self.solutions)

    @property
    def fallbacks(self) -> int:
        """How many steps applied a fallback input because the solver failed."""
        return sum(s.fallback for s in self.solutions)

    def fallback_causes(self) -> str:
        """The fallback steps by status, most frequent first ("limited 3, infeasible 1"; "" when none)."""
        return _tally(s.status for s in self.solutions if s.fallback)

    def paths(self) -> str:
        """What answered the steps (each Solution's ``path``: "C step", "fallback (plan)", …), most frequent first."""
        return _tally(s.path or "unnamed" for s in self.solutions)

    @property
    def soft_steps(self) -> int:
        """How many steps were "soft": the solver's input applied, its plan breaking a clearance or state bound."""
        return sum(s.status == SOFT for s in self.solutions)

    def soft_causes(self) -> str:
        """The soft steps by the kind of constraint broken (their ``reason``; "soft" where none is said), most frequent
        first ("clearance 4, state bound 1")."""
        return _tally(str(s.reason or SOFT) for s in self.solutions if s.status == SOFT)

    def clearances(self, ocp) -> np.ndarray:
        """The true clearance (m, no margin) of ``ocp``'s task at every state: the smallest distance between the
        surfaces of a robot sphere and an obstacle (negative: a collision; +inf without obstacles)."""
        from ocpkit.model.task import clearances

        task = getattr(ocp, "task", None)
        if task is None or not task.obstacles:
            return np.full(len(self.x), np.inf)
        return clearances(
            task.kinematics,
            task.robot,
            task.obstacles if self.obstacles is None else self.obstacles,
            self.x[:, : task.kinematics.n],
        )

    def success_while_colliding(self, ocp) -> int:
        """How many steps reported "success" while the plant's next state collides with an obstacle of ``ocp``'s
        task (true clearance < 0): a success the plant contradicts."""
        colliding = self.clearances(ocp)[1:] < 0
        return int(sum(s.status == SUCCESS and hit for s, hit in zip(self.solutions, colliding)))

    def progress(
        self,
        kinematics=None,
        frame: str | None = None,
        target=None,
        *,
        tolerance: float = TOLERANCE,
        window: float = WINDOW,
        still: float = STILL,
    ) -> Progress:
        """The loop-level verdict on the task (:class:`Progress`): with ``kinematics`` (an
        :class:`ocpkit.model.kinematics.Kinematics`, ``problem.kinematics``), ``frame`` and ``target`` (x, y, z), the
        frame's distance (m) to the target point; without them the joint goal's state error max_i |x_i − x_goal,i|.
        Defaults: reached within 1 cm (TOLERANCE), stalled when the error stays within 1 mm (STILL) over the last
        0.5 s (WINDOW)."""
        tolerance, still = positive(tolerance, "tolerance"), positive(still, "still")
        window = positive(window, "window")
        given = [name for name, v in (("kinematics", kinematics), ("frame", frame), ("target", target)) if v is None]
        if given and len(given) < 3:
            raise ValueError(
                f"progress towards a frame's target needs kinematics, frame and target; {given[0]} is "
                f"missing (none of them: the joint goal's state error)"
            )
        if given:
            error = np.abs(self.x - self.goals()[:, : self.x.shape[1]]).max(axis=1)
            what, unit = "max |x − x_goal|", ""
        else:
            target = np.asarray(target, dtype=float).ravel()
            if target.shape != (3,) or not np.isfinite(target).all():
                raise ValueError(f"target must be a point x, y, z (m), got {np.asarray(target).tolist()}")
            error = np.linalg.norm(kinematics.positions(frame, self.x[:, : kinematics.n]) - target, axis=1)
            what, unit = f"{frame}'s distance to the target", "m"
        span = int(round(window / (self.t[1] - self.t[0]))) if len(self.t) > 1 else len(self.t)
        tail = error[-(span + 1) :]
        change = float(tail.max() - tail.min()) if len(error) > span else float("nan")
        final = float(error[-1])
        verdict = REACHED if final <= tolerance else STALLED if change <= still else MOVING
        return Progress(verdict, error, final, change, what, unit, tolerance, window, still)

    def times(self, key: str = "total") -> np.ndarray:
        """Per-step solve times (s) of one kind: "model", "build", "solve" or "total"."""
        return np.array([s.times[key] for s in self.solutions])

    def animate(self, path, problem, **options):
        """The run as an animated GIF of ``problem``'s robot at ``path`` (:func:`ocpkit.sim.animation.animate`)."""
        from ocpkit.sim.animation import animate  # matplotlib loads only when a picture is asked for

        return animate(self, path, problem, **options)


def simulate(
    plant,
    controller: Controller,
    x0,
    goal,
    duration: float,
    *,
    dt: float | None = None,
    plant_substeps: int = 10,
    callback=None,
    obstacles=None,
) -> Trajectory:
    """Run ``controller`` for ``duration`` seconds at its control period ``dt`` (default: its OCP's dt).

    ``goal``: a goal vector held, or a :class:`ocpkit.model.reference.Reference` followed: the step at time t gets
    its window over the horizon (the controller previews the reference). ``obstacles``: an
    :class:`ocpkit.model.reference.ObstaclePath` moving the task's obstacles (its window at each step); None: they
    stay where the task declares them.

    The plant, an ocpkit Model, is integrated with RK4 over ``plant_substeps`` sub-steps per control period, input
    held (zero-order hold). Any other plant has ``nx``, ``nu`` and ``stepper(dt, substeps)`` returning its step
    F(x, u) -> x⁺ over one period in ``plant_substeps`` sub-steps (:class:`ocpkit.sim.mujoco_plant.MuJoCoPlant`).
    ``callback(k, x, solution)``, if given, is called after every step.
    """
    model = isinstance(plant, Model)
    if not model and not callable(getattr(plant, "stepper", None)):
        raise TypeError(
            f"plant must be an ocpkit Model or a plant with stepper(dt, substeps) (a MuJoCoPlant), got "
            f"{type(plant).__name__}"
        )
    if not isinstance(controller, Controller):
        raise TypeError(f"controller must be an ocpkit Controller, got {type(controller).__name__}")
    ocp = controller.ocp
    if (plant.nx, plant.nu) != (ocp.nx, ocp.nu):
        raise ValueError(f"plant has (nx, nu) = {(plant.nx, plant.nu)}, the controller {(ocp.nx, ocp.nu)}")
    dt = ocp.dt if dt is None else positive(dt, "dt")
    duration = positive(duration, "duration")
    steps = int(round(duration / dt))
    substeps = integer(plant_substeps, "plant_substeps", 1)
    step = plant.rk4(dt, substeps) if model else plant.stepper(dt, substeps)
    x0 = ocp.check_state(x0, "x0")
    reference = goal if isinstance(goal, Reference) else None
    if reference is not None and reference.ng != ocp.ng:
        raise ValueError(f"the reference has {reference.ng} entries per goal, the OCP's goal {ocp.ng}")
    if obstacles is not None and not isinstance(obstacles, ObstaclePath):
        raise TypeError(f"obstacles must be an ocpkit ObstaclePath or None, got {type(obstacles).__name__}")
    goal = None if reference is not None else ocp.check_goal(goal)
    times = np.arange(steps + 1) * dt
    xs = np.empty((steps + 1, ocp.nx))
    us = np.empty((steps, ocp.nu))
    xs[0] = x0
    solutions: list[Solution] = []
    controller.reset()
    for k in range(steps):
        window = goal if reference is None else reference.window(times[k], ocp.dt, ocp.horizon)
        moved = None if obstacles is None else obstacles.window(times[k], ocp.dt, ocp.horizon)
        sol = controller.solve(xs[k], window, **({} if moved is None else {"obstacles": moved}))
        solutions.append(sol)
        us[k] = sol.u
        xs[k + 1] = np.asarray(step(xs[k], sol.u), dtype=float).ravel()
        if not np.isfinite(xs[k + 1]).all():
            if model:  # the plant's own dynamics returning NaN are named as such (a DynamicsError)
                check_dynamics(
                    plant,
                    xs[k],
                    sol.u,
                    dt=dt,
                    substeps=plant_substeps,
                    context=f"the plant, closed-loop step {k + 1} from t = {k * dt:.6g} s",
                )
            what = "the plant's RK4 step diverged (its dynamics stayed finite)" if model else f"{plant!r} diverged"
            raise FloatingPointError(
                f"plant state became non-finite at step {k + 1} from x = {xs[k].tolist()}, "
                f"u = {sol.u.tolist()}: {what}; more plant_substeps or a smaller dt may help"
            )
        if callback is not None:
            callback(k, xs[k + 1], sol)
    moved = None if obstacles is None else np.array([obstacles.at(t) for t in times])
    if reference is None:
        return Trajectory(t=times, x=xs, u=us, goal=goal, solutions=solutions, obstacles=moved)
    goals = np.array([ocp.check_goal(reference.at(t), f"the reference at t = {t:g}") for t in times])
    return Trajectory(t=times, x=xs, u=us, goal=goals[-1], solutions=solutions, reference=goals, obstacles=moved)
