"""The Gaussian search of CEM and MPPI on the sampling planners' frame (:mod:`ocpkit.solvers.sampling`): knots drawn
around a mean, preconditioned by the knot QP's Hessian, and the plan returned by constraint domination."""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import numpy as np
import taichi as ti

from ocpkit._checks import array, positive
from ocpkit.codegen.kernels import runtime
from ocpkit.codegen.kernels.random import normal
from ocpkit.solvers.sampling import SEEDS, SamplingMPC, best_first, clip_func, excess, seed_func


class GaussianSampling(SamplingMPC):
    """Base of CEM and MPPI: each generation draws knots z = μ + G ε, ε ~ N(0, I), clipped to the input
    bounds; candidate 0 is μ itself so the incumbent is always evaluated, and with the preconditioned
    variant candidates 1 and 2 are the seeds. G is diag(std) in input coordinates ("paper") or
    L⁻ᵀ diag(std) with std in whitened units ("preconditioned"): see :meth:`_sample`.

    Preconditioned, each control step's μ starts at the best by rollout (constraint domination) of the incumbent
    (the shifted mean, or the holding input at a cold start) and the seeds (:meth:`_start_distribution`). A Gaussian of
    σ whitened units moves its mean by about σ per generation, and a seed among the elites weighs only
    1/num_elites in CEM's refit: from an incumbent far from the knot QP's optimum (the cart-pole's holding
    input: ~600 whitened units, 10³× the Newton candidate's cost) CEM never arrived while the plant fell.

    ``sigma``: with "paper", the initial std in input units (scalar or per input; default 10 % of each
    input's range); with "preconditioned", in whitened units (a scalar; default 1: a draw then adds
    about ‖ε‖² ≈ p·m to the rollout cost of the QP's quadratic model).

    The plan returned is the final μ unless, with obstacles or state bounds, the last generation's best candidate
    dominates it (:meth:`_final`): an average of collision-free plans can collide (two ways around a ball).

    ``TRUNCATED`` (CEM's, preconditioned): a draw that leaves the input bounds is shortened along its ray,
    z = μ + t·G ε with the largest t ≤ 1 that keeps z within them, instead of clipped. Clipping moves a draw along
    the input axes, which the whitening makes stiff: on nlink:3 following a reference whose plan holds a torque at
    its bound, 97–100 % of the draws were clipped and landed 39–57 whitened units from μ (the draw itself: about
    √(p·m) = 3), CEM's elite mean 15–30 units (a rollout cost 200–1000 against the Newton seed's 0.6–60), and it
    tracked worse with the reference's preview than holding its present value. Shortened, a draw costs at most what
    it would unclipped on the QP's quadratic model.
    """

    TRUNCATED = False

    def __init__(self, ocp, *, sigma=None, **options):
        super().__init__(ocp, **options)
        eng = self.engine
        F = eng.ftype
        N, p, m = eng.num_sims, eng.num_knots, eng.nu
        d = p * m
        if self.preconditioned:
            self.sigma = 1.0 if sigma is None else positive(sigma, "sigma")
        else:
            span = ocp.u_max - ocp.u_min
            self.sigma = 0.1 * span if sigma is None else array(np.broadcast_to(sigma, span.shape), "sigma", span.shape)
            if (self.sigma < 0).any():
                raise ValueError(f"sigma must be >= 0, got {self.sigma.tolist()}")
        seeded = SEEDS if self.preconditioned else 0
        self._gaussian_kernel, self._evaluate_kernel = runtime.shared(
            ("gaussian", seeded, *eng.key), lambda: _kernels(eng.record, F, p, m, seeded, eng.layout)
        )
        self._distribution = np.empty((1 + d, d), dtype=eng.ntype)
        # As in the population, a smaller one holds fewer seeds.
        self._centers = min(N, 1 + SEEDS) if self.preconditioned else 1

    def _evaluate(self, candidates) -> np.ndarray:
        """Roll out a few candidates (each (p, m)) in one small launch, counted as ``generations``; their (cost,
        violation) rows. They overwrite the population's first places."""
        results = self.engine.results(len(candidates))
        eng = self.engine
        self._launch(
            self._evaluate_kernel, np.ascontiguousarray(candidates, dtype=eng.ntype), eng.knots, eng.data, results
        )
        return results

    def _final(self, mean: np.ndarray, best: tuple[float, float], index: int) -> tuple[np.ndarray, tuple]:
        """The plan to return (and carry to the next step) and its (cost, violation): ``mean``, unless with
        constraints the last generation's best candidate (number ``index``, of (cost, violation) ``best``)
        dominates it by feasibility: the mean violates, the candidate less. Without constraints the mean is not
        rolled out and ``best`` is returned."""
        if not self.engine.constrained:
            return mean, best
        candidate = self._pick([index])[0]  # before the mean's rollout takes the population's first place
        outcome = self._evaluate(mean[None])
        if excess(np.asarray([best]))[0] < excess(outcome)[0]:
            return candidate, best
        return mean, (float(outcome[0, 0]), float(outcome[0, 1]))

    def _start_distribution(self, mean: np.ndarray, cold: bool) -> np.ndarray:
        """This step's starting mean; the std restarts at σ. The incumbent is the step's initial guess, else the
        shifted mean, or at a cold start the holding input (preconditioned) or the input goal (paper).
        Preconditioned, the incumbent and the seeds are rolled out first (one small launch) and the best by
        constraint domination starts the search; a tie keeps the incumbent."""
        ocp = self.ocp
        if self._guess is not None:
            start = self._guess
        elif not cold:
            start = self._shifted(mean, 1 + self._missed)
        elif self.preconditioned:
            start = self.preconditioner.hold
        else:
            start = self.goal_knots(self._goal)
        d = ocp.knots * ocp.nu
        self.std = np.full(d, self.sigma) if self.preconditioned else np.tile(self.sigma, ocp.knots)
        if self.preconditioned:
            pre = self.preconditioner
            centers = (start, pre.newton, pre.hold)[: self._centers]
            start = centers[int(best_first(self._evaluate(centers), 1)[0])]
        return start

    def _sample(self, mean: np.ndarray) -> None:
        """Roll out one population drawn around ``mean`` (p, m) with the current ``self.std`` (one call:
        the distribution goes in, the costs and violations come back in ``self._results``)."""
        dist = self._distribution
        dist[0] = mean.ravel()
        dist[1:] = self.preconditioner.whiten * self.std if self.preconditioned else np.diag(self.std)
        eng = self.engine
        counter = self.counter & 0xFFFFFFFF
        truncate = int(self.preconditioned and self.TRUNCATED)
        self._launch(
            self._gaussian_kernel, self.key, counter, truncate, dist, eng.knots, eng.data, self._eps, self._results
        )


def _kernels(record, F, p, m, seeded, layout):
    """(generation, evaluate): the population drawn around a distribution and rolled out, and a few given candidates
    rolled out; ``seeded``: how many seeds (the "preconditioner" section) follow the mean, 0 for none. The generation's
    ``truncate`` (run time: one kernel for CEM and MPPI) scales each draw G ε along its ray to the input bounds
    (:class:`GaussianSampling`) before the clip, which then only absorbs rounding."""
    d = p * m
    bounds = layout["bounds"]
    clip = clip_func(bounds, m)
    seed = seed_func(layout["preconditioner"], d, p, m) if seeded else None

    # Run-time loops over the knots and parameters: unrolled, the kernel's compile time grew with p·m.
    @ti.kernel
    def generation(
        key: ti.u32,
        counter: ti.u32,
        truncate: ti.i32,
        distribution: ti.types.ndarray(),
        knots: ti.types.ndarray(),
        data: ti.types.ndarray(),
        eps: ti.types.ndarray(),
        out: ti.types.ndarray(),
    ):
        for i in range(knots.shape[0]):
            t = ti.cast(1.0, F)  # the share of the draw taken
            if i > seeded:
                for c in range(d):
                    eps[i, c] = ti.cast(normal(key, counter, i, c), F)
                for j in range(p):  # the draw G ε, held in the candidate's place until it is scaled
                    for a in range(m):
                        r = j * m + a
                        acc = ti.cast(0.0, F)
                        for c in range(d):
                            acc += ti.cast(distribution[1 + r, c], F) * eps[i, c]
                        knots[i, j, a] = acc
                        if truncate:
                            room = ti.select(acc > 0, data[bounds + m + a], data[bounds + a])
                            if acc != 0:
                                t = ti.min(t, (room - ti.cast(distribution[0, r], F)) / acc)
                t = ti.max(t, ti.cast(0.0, F))
            for j in range(p):
                for a in range(m):
                    r = j * m + a
                    v = ti.cast(distribution[0, r], F)
                    # Only a compile-time condition drops the seeds' code where there are none ("paper"):
                    # `ti.static(seeded) and …` is a run-time `and`, whose body Taichi still compiles.
                    if ti.static(seeded > 0):
                        if 1 <= i <= seeded:
                            v = seed(i - 1, j, a, data)
                    if i > seeded:
                        v += t * knots[i, j, a]
                    knots[i, j, a] = clip(v, a, data)
            record(i, knots, data, out)

    @ti.kernel
    def evaluate(
        candidates: ti.types.ndarray(), knots: ti.types.ndarray(), data: ti.types.ndarray(), out: ti.types.ndarray()
    ):
        for i in range(candidates.shape[0]):  # into the population's first places, clipped as there
            for j in range(p):
                for a in range(m):
                    knots[i, j, a] = clip(ti.cast(candidates[i, j, a], F), a, data)
            record(i, knots, data, out)

    return generation, evaluate
