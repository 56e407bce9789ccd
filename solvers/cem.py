"""CrossEntropyMPC: the cross-entropy method over the knots, on EMPC's rollout engine.

Each generation draws the population from a Gaussian over the knots, keeps the ``num_elites``
best candidates — by constraint domination (:func:`ocpkit.solvers.sampling.best_first`) in both variants: the
feasible by cost, then the least violating — and refits the Gaussian to them (Rubinstein's CEM, as in MuJoCo MPC's
cross-entropy planner). The preconditioned variant (default) draws and refits in the coordinates
whitened by the knot QP's Hessian and evaluates the seeds in every population
(:mod:`ocpkit.solvers.sampling`); "paper" uses per-parameter stds in input coordinates. The mean
carries over to the next control step shifted one step in time; preconditioned, the step starts from
whichever of it and the seeds rolls out cheapest (the refit alone moves the mean only about σ per
generation). Preconditioned, a draw that leaves the input bounds is shortened along its ray, not clipped
(:class:`GaussianSampling`, ``TRUNCATED``): clipped, the elite mean left a bound the plan should hold. The std
restarts at σ each step. u is the mean's input at t = 0, unless with obstacles or state bounds the best elite
dominates the mean (:meth:`GaussianSampling._final`).
"""

from __future__ import annotations

import numpy as np

from ocpkit._checks import integer
from ocpkit.solvers.methods import CEM
from ocpkit.solvers.gaussian import GaussianSampling


class CrossEntropyMPC(GaussianSampling):
    """CEM with ``population`` samples, ``num_elites`` kept, initial std ``sigma`` (see
    :class:`GaussianSampling`), floor ``sigma_min`` (default σ/100) and ``smoothing`` α ∈ [0, 1):
    mean ← α·mean + (1−α)·elite mean (same for the std)."""

    TRUNCATED = True

    def __init__(
        self,
        ocp,
        *,
        population: int = CEM["population"].default,
        num_elites: int = CEM["num_elites"].default,
        sigma=None,
        generations: int = CEM["generations"].default,
        sigma_min=None,
        smoothing: float = CEM["smoothing"].default,
        **options,
    ):
        population = integer(population, "population", 2)
        self.num_elites = integer(num_elites, "num_elites", 2)
        if self.num_elites > population:
            raise ValueError(f"num_elites must be <= population ({population}), got {num_elites}")
        smoothing = float(smoothing)
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"smoothing must be in [0, 1), got {smoothing}")
        self.smoothing = smoothing
        super().__init__(
            ocp, population=population, generations=generations, num_picked=self.num_elites, sigma=sigma, **options
        )
        self.sigma_min = (
            np.asarray(self.sigma, dtype=float) / 100
            if sigma_min is None
            else np.broadcast_to(np.asarray(sigma_min, dtype=float), np.shape(self.sigma)).copy()
        )
        if not (np.isfinite(self.sigma_min).all() and (self.sigma_min >= 0).all()):
            raise ValueError(f"sigma_min must be finite and >= 0, got {np.ravel(self.sigma_min).tolist()}")

    def _start(self, x, goal, cold):
        self.mean = self._start_distribution(getattr(self, "mean", None), cold)

    def _generation(self, cold):
        self._sample(self.mean)
        idx = self._ranked(self.num_elites)
        self._best_index = int(idx[0])
        elites = self._pick(idx)
        elite_mean = elites.mean(axis=0)
        spread = (
            self.preconditioner.whitened(elites, elite_mean)
            if self.preconditioned
            else elites.reshape(len(elites), -1) - elite_mean.ravel()
        ).std(axis=0)
        floor = np.broadcast_to(self.sigma_min, self.mean.shape).ravel()
        a = self.smoothing
        self.mean = a * self.mean + (1 - a) * elite_mean
        self.std = np.maximum(a * self.std + (1 - a) * spread, floor)
        return self._outcome(idx[0])

    def _result(self, best):
        self.mean, best = self._final(self.mean, best, self._best_index)
        return self.mean, best


SOLVERS = {"cem": CrossEntropyMPC}
