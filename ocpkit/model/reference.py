"""What moves: a goal that follows a reference in time, and obstacles that move, previewed over the horizon.

Every controller's step takes a goal *window* — the goal vector g (``ng`` entries: x_goal, then the task's targets,
as :meth:`ocpkit.model.ocp.OCP.goal` builds it) at each stage k = 0 … T of the horizon, (T+1, ng) — and, with a
task's obstacles, an obstacle window, (T+1, N, 4): each obstacle's centre and radius at each stage. A held goal is
the window of one row repeated (``solve(x, goal)`` with a vector), and the task's declared obstacles the window of
its table repeated. Stage k's terms read row k; the terminal terms row T; the clearances at x_k row k.

:class:`Reference` gives the goal as a function of time, from samples (piecewise linear), a callable or a file, and
its window at the step's time t: g(t + k·dt). :class:`ObstaclePath` gives the obstacles' centres and radii as a
function of time, and a window that predicts them over the horizon at constant velocity (the velocity now, by
finite differences unless given).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from ocpkit._checks import array, positive


class Reference:
    """A goal that moves: g(t), the goal vector of ``ng`` entries at time t (s).

    ``Reference(times, goals)``: samples (H,) and (H, ng), times increasing; g is linear between samples and held
    beyond the first and last. ``Reference.from_function(fn, ng)``: fn(t) -> the goal vector.
    ``Reference.load(path, ocp)``: a CSV or NPZ file with a column "t" and one per goal entry, named as
    :meth:`ocpkit.model.ocp.OCP.goal_names` (a state's name, a target's entry such as "position[0]"); goal entries
    not in the file stay zero. (A rotation target interpolated between samples is not a rotation; sample it
    finely, or give a function.)"""

    def __init__(self, times, goals):
        goals = np.asarray(goals, dtype=float)
        if goals.ndim != 2:
            raise ValueError(f"goals must be (samples, ng), got shape {goals.shape}")
        times = array(times, "times", (goals.shape[0],))
        if goals.shape[0] == 0 or not np.isfinite(goals).all():
            raise ValueError("goals must be at least one row of finite numbers")
        if np.any(np.diff(times) <= 0):
            raise ValueError("times must increase strictly")
        self.times, self.goals, self.ng = times, goals, goals.shape[1]
        self._function = None
        self.preview = True

    @classmethod
    def from_function(cls, function, ng: int) -> "Reference":
        """g(t) = ``function(t)``, a vector of ``ng`` entries."""
        if not callable(function):
            raise TypeError(f"function must be callable t -> goal, got {type(function).__name__}")
        ref = cls([0.0], np.zeros((1, int(ng))))
        ref._function = function
        return ref

    @classmethod
    def load(cls, path, ocp, default=None) -> "Reference":
        """A reference from a CSV (header row of column names) or NPZ file (one array per column name); goal
        entries the file does not name take ``default``'s (a goal vector; zero where not given)."""
        names = ocp.goal_names()
        columns = _columns(path, "reference", names)
        goals = np.tile(np.zeros(len(names)) if default is None else ocp.check_goal(default), (columns["t"].size, 1))
        for i, name in enumerate(names):
            if name in columns:
                goals[:, i] = columns[name]
        return cls(columns["t"], goals)

    def at(self, t: float) -> np.ndarray:
        """g(t)."""
        if self._function is not None:
            return np.asarray(self._function(float(t)), dtype=float).ravel()
        return np.array([np.interp(t, self.times, column) for column in self.goals.T])

    def without_preview(self) -> "Reference":
        """The same reference with no preview: each window holds g(t), the present value (a held goal updated every
        step, what a loop that cannot see ahead does)."""
        held = copy.copy(self)
        held.preview = False
        return held

    def window(self, t: float, dt: float, horizon: int) -> np.ndarray:
        """The goals the step at time t previews: g(t + k·dt), k = 0 … T, as (T+1, ng); without preview g(t) in
        every row."""
        if not self.preview:
            return np.tile(self.at(t), (horizon + 1, 1))
        ts = t + dt * np.arange(horizon + 1)
        if self._function is not None:
            return np.array([self.at(s) for s in ts])
        return np.column_stack([np.interp(ts, self.times, column) for column in self.goals.T])


def _columns(path, what: str, names: list[str]) -> dict:
    """The named columns of a CSV (a header row) or NPZ file, with "t" (s) and otherwise only ``names``."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path) as data:
            columns = {name: np.asarray(data[name], dtype=float).ravel() for name in data.files}
    elif path.suffix == ".csv":
        table = np.genfromtxt(path, delimiter=",", names=True, deletechars="", dtype=float)
        columns = {name: np.atleast_1d(table[name]) for name in table.dtype.names}
    else:
        raise ValueError(f"{what} file {path}: a .csv or .npz file, got {path.suffix or 'no suffix'}")
    if "t" not in columns:
        raise ValueError(f"{what} file {path} has no column 't' (the time, s)")
    unknown = sorted(set(columns) - set(names) - {"t"})
    if unknown:
        raise ValueError(f"{what} file {path}: unknown column(s) {unknown}; it takes {names}")
    return columns


class ObstaclePath:
    """Obstacles that move: ``function(t)`` -> (N, 4), each obstacle's centre (m) and radius at time t.

    :meth:`window` predicts them over the horizon at constant velocity: centre + v·k·dt, with v ``velocity(t)``
    -> (N, 3) where given, else the centre's backward difference over ``dt`` (a step's worth of motion, as a
    tracker of the obstacle would measure it); ``predict=False`` holds them where they are."""

    def __init__(self, function, velocity=None, *, predict: bool = True):
        if not callable(function) or (velocity is not None and not callable(velocity)):
            raise TypeError("function (and velocity, if given) must be callables of the time t")
        self.function, self.velocity, self.predict = function, velocity, bool(predict)

    @classmethod
    def load(cls, path, obstacles, *, predict: bool = True) -> "ObstaclePath":
        """Obstacles moving as a CSV or NPZ file says: a column "t" and, for obstacle i of the task's ``obstacles``
        (:class:`ocpkit.model.task.Sphere` s, where they start), columns "obstacle<i>_x", "_y", "_z", "_radius"
        (linear between rows, held beyond; an obstacle or column the file leaves out stays as declared)."""
        fields = ("x", "y", "z", "radius")
        names = [f"obstacle{i}_{f}" for i in range(len(obstacles)) for f in fields]
        columns = _columns(path, "obstacle path", names)
        table = np.array([[*o.center, o.radius] for o in obstacles], dtype=float)
        times = columns["t"]
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"obstacle path file {path}: times must increase strictly")
        rows = np.repeat(table[None], times.size, axis=0)
        for i in range(len(obstacles)):
            for j, f in enumerate(fields):
                rows[:, i, j] = columns.get(f"obstacle{i}_{f}", rows[:, i, j])
        if (rows[..., 3] <= 0).any():
            raise ValueError(f"obstacle path file {path}: radii must be > 0")
        return cls(
            lambda t: np.array([[np.interp(t, times, rows[:, i, j]) for j in range(4)] for i in range(len(obstacles))]),
            predict=predict,
        )

    def at(self, t: float) -> np.ndarray:
        """The obstacles at time t, (N, 4)."""
        return np.atleast_2d(np.asarray(self.function(float(t)), dtype=float))

    def window(self, t: float, dt: float, horizon: int) -> np.ndarray:
        """(T+1, N, 4): the obstacles at stages k = 0 … T of a step at time t."""
        dt = positive(dt, "dt")
        now = self.at(t)
        out = np.repeat(now[None], horizon + 1, axis=0)
        if self.predict:
            v = (
                np.asarray(self.velocity(float(t)), dtype=float).reshape(-1, 3)
                if self.velocity is not None
                else (now[:, :3] - self.at(t - dt)[:, :3]) / dt
            )
            out[:, :, :3] += dt * np.arange(horizon + 1)[:, None, None] * v[None]
        return out
