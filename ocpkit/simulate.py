"""Closed-loop simulation: a controller at its control rate against a plant integrated more finely."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ocpkit._checks import integer, positive
from ocpkit.controller import Controller, Solution
from ocpkit.model import Model
from ocpkit.problem import check_dynamics


@dataclass
class Trajectory:
    """A closed-loop run: times t (H+1,), states x (H+1, n), applied inputs u (H, m) and every Solution."""

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    goal: np.ndarray
    solutions: list = field(default_factory=list)

    @property
    def statuses(self) -> list[str]:
        return [s.status for s in self.solutions]

    @property
    def fallbacks(self) -> int:
        """How many steps applied a fallback input because the solver failed."""
        return sum(s.fallback for s in self.solutions)

    def fallback_causes(self) -> str:
        """The fallback steps by status, most frequent first ("limited 3, infeasible 1"; "" when none)."""
        counts: dict = {}
        for s in self.solutions:
            if s.fallback:
                counts[s.status] = counts.get(s.status, 0) + 1
        return ", ".join(f"{status} {n}" for status, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))

    def times(self, key: str = "total") -> np.ndarray:
        """Per-step solve times (s) of one kind: "model", "build", "solve" or "total"."""
        return np.array([s.times[key] for s in self.solutions])

    def animate(self, path, problem, **options):
        """The run as an animated GIF of ``problem``'s robot at ``path`` (:func:`ocpkit.animation.animate`)."""
        from ocpkit.animation import animate  # matplotlib loads only when a picture is asked for
        return animate(self, path, problem, **options)


def simulate(plant, controller: Controller, x0, goal, duration: float, *, dt: float | None = None,
             plant_substeps: int = 10, callback=None) -> Trajectory:
    """Run ``controller`` for ``duration`` seconds at its control period ``dt`` (default: its OCP's dt).

    The plant, an ocpkit Model, is integrated with RK4 over ``plant_substeps`` sub-steps per control period, input
    held (zero-order hold). Any other plant has ``nx``, ``nu`` and ``stepper(dt, substeps)`` returning its step
    F(x, u) -> x⁺ over one period in ``plant_substeps`` sub-steps (:class:`ocpkit.mujoco_plant.MuJoCoPlant`).
    ``callback(k, x, solution)``, if given, is called after every step.
    """
    model = isinstance(plant, Model)
    if not model and not callable(getattr(plant, "stepper", None)):
        raise TypeError(f"plant must be an ocpkit Model or a plant with stepper(dt, substeps) (a MuJoCoPlant), got "
                        f"{type(plant).__name__}")
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
    goal = ocp.check_goal(goal)
    xs = np.empty((steps + 1, ocp.nx))
    us = np.empty((steps, ocp.nu))
    xs[0] = x0
    solutions: list[Solution] = []
    controller.reset()
    for k in range(steps):
        sol = controller.solve(xs[k], goal)
        solutions.append(sol)
        us[k] = sol.u
        xs[k + 1] = np.asarray(step(xs[k], sol.u), dtype=float).ravel()
        if not np.isfinite(xs[k + 1]).all():
            if model:  # the plant's own dynamics returning NaN are named as such (a DynamicsError)
                check_dynamics(plant, xs[k], sol.u, dt=dt, substeps=plant_substeps,
                               context=f"the plant, closed-loop step {k + 1} from t = {k * dt:.6g} s")
            what = "the plant's RK4 step diverged (its dynamics stayed finite)" if model else f"{plant!r} diverged"
            raise FloatingPointError(f"plant state became non-finite at step {k + 1} from x = {xs[k].tolist()}, "
                                     f"u = {sol.u.tolist()}: {what}; more plant_substeps or a smaller dt may help")
        if callback is not None:
            callback(k, xs[k + 1], sol)
    return Trajectory(t=np.arange(steps + 1) * dt, x=xs, u=us, goal=goal, solutions=solutions)
