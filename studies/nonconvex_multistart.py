"""IPOPT multi-start, the non-convex suite's strongest gradient baseline (:mod:`ocpkit.studies.nonconvex`): the
NonlinearMPC of :mod:`ocpkit.solvers.nlp` solved from several initial guesses, the best converged one kept.

A cold solve (the first step after a reset, or the step after a failed one) tries ``starts`` guesses: NonlinearMPC's
own cold start (states held at x_0, knots at the input goal), then ``starts`` − 1 random plans, knots uniform within
the input bounds (seeded: a run is repeatable), each rolled out on the model as NonlinearMPC does with a user's
initial guess. With ``every_step`` every step does so, the first guess the warm start. The answer is the converged
solve of least NLP objective (a later start replaces the best only if it is lower by :data:`BETTER`, relative); a
guess that fails (not converged, limited) is dropped, and the step fails only when all do; after such a step, the
steps try NonlinearMPC's own start alone until one converges (on the 3-link arm's limits case IPOPT failed step after
step, and 8 starts of 50 iterations each a step took minutes a run). With a ``time_limit``
(the whole step's budget, every start together) a start begins only while NonlinearMPC's own check says a solve
still fits in what is left: the budget decides how many starts run.
"""

from __future__ import annotations

import numpy as np

from ocpkit._checks import integer
from ocpkit.status import Reason
from ocpkit.solvers.nlp import NonlinearMPC


BETTER = 1e-6  # a later start replaces the best only if its objective is lower by this much (relative): not rounding


class _Recording:
    """The NLP solver Function, remembering the objective of its last call (``f``)."""

    def __init__(self, solver):
        self.solver, self.f = solver, np.nan

    def __call__(self, **args):
        res = self.solver(**args)
        self.f = float(res["f"])
        return res

    def stats(self):
        return self.solver.stats()


class MultiStartNLP(NonlinearMPC):
    """NonlinearMPC (IPOPT by default) with ``starts`` initial guesses per cold solve (every step with
    ``every_step``), the converged one of least objective kept (module docstring); ``seed`` keys the random guesses.
    Other keywords are NonlinearMPC's."""

    def __init__(self, ocp, *, starts: int = 8, every_step: bool = False, seed: int = 0, **options):
        self.starts = integer(starts, "starts", 1)
        self.every_step = bool(every_step)
        self.seed = integer(seed, "seed", 0)
        super().__init__(ocp, **options)

    def __repr__(self):
        return f"MultiStartNLP({self.starts} starts, {self.method}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        self.draws = 0  # random guesses drawn since the reset: with the seed, it keys the next one
        self.starts_run = self.steps_run = self.random_wins = 0  # see random_win_rate
        self.objectives: list = []  # the last multi-start step's NLP objective per start (NaN: not converged)
        self._stuck = False  # every start of the last multi-start step failed: one start a step until one converges

    @property
    def random_win_rate(self) -> float:
        """The share of multi-start steps whose answer came from a random guess (NaN before any)."""
        return self.random_wins / self.steps_run if self.steps_run else float("nan")

    def _nlpsol(self):
        return _Recording(super()._nlpsol())

    def _solve(self, x, goal):
        if self.guess is not None or self._stuck or not (self.every_step or self._warm is None):
            sol = super()._solve(x, goal)
            self._stuck = self._stuck and not sol.ok
            return sol
        ocp, best, kept, times, iterations, tried = self.ocp, None, None, {}, 0, 0
        self.objectives = []
        for start in range(self.starts):
            if start:
                rng = np.random.default_rng([self.seed, self.draws])
                self.draws += 1
                self.guess = rng.uniform(ocp.u_min, ocp.u_max, size=(ocp.knots, ocp.nu))
            warm = self._warm
            try:
                sol = super()._solve(x, goal)
            finally:
                self.guess = None
            for part, t in sol.times.items():
                times[part] = times.get(part, 0.0) + t
            iterations += sol.iterations
            tried += 1
            self.objectives.append(self._solver.f if sol.ok else np.nan)
            if sol.ok and (best is None or self._solver.f < best[1] - BETTER * abs(best[1])):
                best, kept = (sol, self._solver.f, start), self._warm
            if sol.reason is Reason.TIME_BUDGET:
                break  # no room left for another start
            self._warm = warm  # every start from the same warm start
        self.steps_run += 1
        self.starts_run += tried
        if best is None:
            self._warm, self._stuck = None, True
            return sol
        sol, f, start = best
        self._warm = kept
        self.random_wins += int(start > 0)
        sol.raw_status = f"{sol.raw_status}; best of {tried} starts: start {start}, objective {f:.6g}"
        sol.times, sol.iterations = times, iterations
        return sol


SOLVERS = {"multistart": MultiStartNLP}
