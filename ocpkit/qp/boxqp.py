"""Box-constrained convex QP by a primal active-set method: min ½ zᵀPz + qᵀz  s.t.  lo ≤ z ≤ hi.

The textbook primal active-set method (Nocedal & Wright, Algorithm 16.3) specialized to simple
bounds: a working set W holds variables fixed at a bound; each iteration minimizes over the free
variables with W fixed (one Cholesky solve of P's free block), steps towards that minimizer as far
as the box allows, adds the first bound it hits to W, and, once the free minimizer is feasible,
releases the bound whose multiplier (the gradient component) has the wrong sign. The objective never
increases and no working set repeats, so for P ≻ 0 it ends at the exact optimum in finitely many
iterations; warm-started from the previous control step's knots it usually needs one to three. The
sampling planners use it for their Newton candidate: the knot QP's box-constrained optimum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class BoxQPResult:
    """The minimizer ``z``, whether the optimality conditions hold to the tolerance, and iterations used."""

    z: np.ndarray
    converged: bool
    iterations: int


def solve_box_qp(P, q, lo, hi, z0=None, *, tol: float = 1e-9, max_iter: int | None = None) -> BoxQPResult:
    """Minimize ½ zᵀPz + qᵀz over lo ≤ z ≤ hi (P symmetric positive definite, bounds may be ±inf).

    Starts from ``z0`` clipped into the box (zeros if None) with the bounds it touches, where the
    gradient pushes outwards, as the working set. Optimal when the projected gradient
    ‖z − clip(z − (Pz + q))‖∞ ≤ tol·max(1, ‖q‖∞). ``max_iter`` defaults to 3·n + 10.
    """
    P, q = np.asarray(P, dtype=float), np.asarray(q, dtype=float)
    n = q.size
    lo = np.broadcast_to(np.asarray(lo, dtype=float), (n,))
    hi = np.broadcast_to(np.asarray(hi, dtype=float), (n,))
    if P.shape != (n, n):
        raise ValueError(f"P must have shape ({n}, {n}), got {P.shape}")
    if (lo > hi).any():
        raise ValueError(f"lo must be <= hi, got lo={lo.tolist()}, hi={hi.tolist()}")
    max_iter = 3 * n + 10 if max_iter is None else max_iter
    z = np.clip(np.zeros(n) if z0 is None else np.asarray(z0, dtype=float).reshape(n), lo, hi)
    threshold = tol * max(1.0, np.abs(q).max(initial=0.0))
    g = P @ z + q
    fixed = ((z <= lo) & (g > 0)) | ((z >= hi) & (g < 0))
    for iteration in range(max_iter):
        free = ~fixed
        target = z.copy()
        if free.any():  # minimizer over the free variables with the working set held
            Pff = P[np.ix_(free, free)]
            target[free] = np.linalg.solve(Pff, -(q[free] + P[np.ix_(free, fixed)] @ z[fixed]))
        d = target - z
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(d < 0, (lo - z) / d, np.where(d > 0, (hi - z) / d, np.inf))
        room = np.where(free, room, np.inf)
        blocking = int(np.argmin(room))
        if room[blocking] < 1.0:  # a bound is in the way: stop on it and hold it
            z = z + room[blocking] * d
            z[blocking] = lo[blocking] if d[blocking] < 0 else hi[blocking]
            fixed[blocking] = True
            continue
        z = target
        g = P @ z + q
        # Multipliers of the held bounds are ±g: release the one most clearly pushing inwards.
        wrong = np.where(fixed, np.where(z <= lo, -g, g), 0.0)
        release = int(np.argmax(wrong))
        if wrong[release] <= threshold:
            return BoxQPResult(z, _optimal(z, g, lo, hi, threshold), iteration + 1)
        fixed[release] = False
    g = P @ z + q
    return BoxQPResult(z, _optimal(z, g, lo, hi, threshold), max_iter)


def _optimal(z, g, lo, hi, threshold) -> bool:
    return bool(np.abs(z - np.clip(z - g, lo, hi)).max(initial=0.0) <= threshold)
