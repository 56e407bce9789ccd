"""Input parameterization: T per-step inputs as a linear map of p knot vectors, u_k = Σ_j φ_kj U_j.

The paper's piecewise-linear knots (Section III-B and "Parameterization" in Section V), move blocking
(zero-order hold), clamped B-splines (the paper's future work), a user-supplied basis (e.g. learned from
demonstrations) and traditional MPC (the identity, p = T) are one object with different T×p bases.
"""

from __future__ import annotations

import numpy as np

from ocpkit._checks import choice, integer

# The kinds made by name (Parameterization.make); a user-supplied basis is Parameterization.custom's "custom".
KINDS = ("linear", "zoh", "bspline", "identity")


class Parameterization:
    """A T×p basis φ mapping knots U (p, m) to inputs u (T, m): u = φ U."""

    def __init__(self, kind: str, basis: np.ndarray):
        self.kind = kind
        self.basis = np.ascontiguousarray(basis, dtype=float)
        self.basis.setflags(write=False)
        self.horizon, self.knots = self.basis.shape
        # Every u_k a convex combination of knots (rows ≥ 0 summing to 1): bounded knots bound every input.
        self.convex = bool(np.all(self.basis >= 0) and np.allclose(self.basis.sum(axis=1), 1.0, rtol=0, atol=1e-12))
        # Knot pseudo-inverse: least-squares knots of a given input trajectory (warm starts).
        self._fit = np.linalg.pinv(self.basis)

    def __repr__(self):
        return f"Parameterization({self.kind!r}, horizon={self.horizon}, knots={self.knots})"

    @classmethod
    def linear_interp(cls, horizon: int, knots: int) -> "Parameterization":
        """Piecewise-linear inputs through p equally spaced knots, the first at k = 0 and the last at k = T−1.

        ΔT = (T−1)/(p−1); at step k, idx1 = floor(k/ΔT), idx2 = idx1 + 1, c = (k − idx1 ΔT)/ΔT and
        u_k = (1−c) U_idx1 + c U_idx2. p = 1 is one constant input. Computed in exact integer arithmetic.
        """
        T, p = _sizes(horizon, knots)
        basis = np.zeros((T, p))
        if p == 1:
            basis[:, 0] = 1.0
            return cls("linear", basis)
        for k in range(T):
            # k/ΔT = k (p−1)/(T−1): integer numerator and denominator avoid floor() rounding errors.
            idx1, rem = divmod(k * (p - 1), T - 1)
            c = rem / (T - 1)
            basis[k, idx1] = 1.0 - c
            if c:
                basis[k, idx1 + 1] = c
        return cls("linear", basis)

    @classmethod
    def zero_order_hold(cls, horizon: int, knots: int) -> "Parameterization":
        """Move blocking: the horizon split into p nearly equal blocks, each holding one knot constant."""
        T, p = _sizes(horizon, knots)
        basis = np.zeros((T, p))
        basis[np.arange(T), (np.arange(T) * p) // T] = 1.0
        return cls("zoh", basis)

    @classmethod
    def bspline(cls, horizon: int, knots: int, degree: int = 3) -> "Parameterization":
        """Clamped uniform B-spline inputs: p control points (the knots U), degree d, sampled at t_k = k/(T−1).

        The knot vector on [0, 1] repeats 0 and 1 d+1 times with p−d−1 equally spaced interior knots; φ_kj is
        the j-th B-spline basis function at t_k (Cox–de Boor), so u_0 = U_0, u_{T−1} = U_{p−1} and every u_k is a
        convex combination of at most d+1 neighbouring knots (bounded knots bound the inputs). Needs p ≥ d+1.
        """
        T, p = _sizes(horizon, knots)
        d = integer(degree, "degree", 1)
        if p < d + 1:
            raise ValueError(f"knots must be >= degree + 1 = {d + 1} for a degree-{d} B-spline, got {p}")
        t = np.r_[np.zeros(d), np.linspace(0.0, 1.0, p - d + 1), np.ones(d)]
        s = np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1)
        # degree 0: the indicator of [t_j, t_j+1), the last non-empty span closed at 1
        last = len(t) - d - 2
        B = np.array([(t[j] <= s) & ((s < t[j + 1]) | ((j == last) & (s == 1.0))) for j in range(len(t) - 1)], float).T
        for q in range(1, d + 1):
            nxt = np.zeros((T, len(t) - 1 - q))
            for j in range(len(t) - 1 - q):
                for lo, hi, col, rising in ((t[j], t[j + q], j, True), (t[j + 1], t[j + q + 1], j + 1, False)):
                    if hi > lo:
                        w = (s - lo) / (hi - lo) if rising else (hi - s) / (hi - lo)
                        nxt[:, j] += w * B[:, col]
            B = nxt
        return cls("bspline", _full_rank(B, "the B-spline basis"))

    @classmethod
    def custom(cls, basis) -> "Parameterization":
        """A user-supplied T×p basis (learned, from demonstrations …): finite, p ≤ T, full column rank.

        Knot bounds bound the inputs only where every row is a convex combination (:attr:`convex`); an OCP with
        input bounds refuses another basis."""
        try:
            B = np.array(basis, dtype=float)
        except (TypeError, ValueError):
            raise TypeError(f"basis must be a numeric T×p matrix, got {basis!r}") from None
        if B.ndim != 2 or 0 in B.shape:
            raise ValueError(f"basis must be a non-empty 2-D T×p matrix, got shape {B.shape}")
        if not np.all(np.isfinite(B)):
            raise ValueError("basis must be finite (no NaN or inf)")
        if B.shape[1] > B.shape[0]:
            raise ValueError(f"basis must have at most as many columns (knots) as rows (horizon), got shape {B.shape}")
        return cls("custom", _full_rank(B, "basis"))

    @classmethod
    def identity(cls, horizon: int) -> "Parameterization":
        """Traditional MPC: one knot per step (p = T)."""
        T = integer(horizon, "horizon", 1)
        return cls("identity", np.eye(T))

    @classmethod
    def make(cls, kind: str, horizon: int, knots: int | None = None) -> "Parameterization":
        """By name: "linear", "zoh", "bspline" (cubic) or "identity" (knots None means traditional MPC)."""
        choice(kind, KINDS, "parameterization")
        if kind == "identity" or knots is None:
            return cls.identity(horizon)
        return {"linear": cls.linear_interp, "zoh": cls.zero_order_hold, "bspline": cls.bspline}[kind](horizon, knots)

    def inputs(self, U) -> np.ndarray:
        """Per-step inputs (T, m) from knots (p, m)."""
        return self.basis @ self._knots(U)

    def u_at(self, U, k: int) -> np.ndarray:
        """The input at step k from knots (the paper's get_u_from_U)."""
        if not 0 <= k < self.horizon:
            raise ValueError(f"k must be in [0, {self.horizon}), got {k}")
        return self.basis[k] @ self._knots(U)

    def fit(self, u) -> np.ndarray:
        """Knots (p, m) whose trajectory is closest to u (T, m) in least squares."""
        u = np.asarray(u, dtype=float)
        if u.ndim != 2 or u.shape[0] != self.horizon:
            raise ValueError(f"u must have shape ({self.horizon}, m), got {u.shape}")
        return self._fit @ u

    # C twin: step.in.c shifted_knots() (the SHIFT matrix); parity: tests/test_twins.py
    def shift(self, U, steps: int = 1) -> np.ndarray:
        """Knots of the plan advanced by ``steps`` (last input held): the warm start of the next control step."""
        u = self.inputs(U)
        u = np.concatenate([u[steps:], np.repeat(u[-1:], min(steps, self.horizon), axis=0)])[: self.horizon]
        return self.fit(u)

    def _knots(self, U) -> np.ndarray:
        U = np.asarray(U, dtype=float)
        if U.ndim != 2 or U.shape[0] != self.knots:
            raise ValueError(f"U must have shape ({self.knots}, m), got {U.shape}")
        return U


def _full_rank(basis, name):
    """``basis`` if its columns are linearly independent (each knot set gives its own inputs), else a ValueError."""
    rank = np.linalg.matrix_rank(basis)
    if rank < basis.shape[1]:
        raise ValueError(f"{name} must have full column rank {basis.shape[1]}, got rank {rank}")
    return basis


def _sizes(horizon, knots):
    T = integer(horizon, "horizon", 1)
    p = integer(knots, "knots", 1)
    if p > T:
        raise ValueError(f"knots must be <= horizon ({T}), got {p}")
    return T, p


__all__ = ["Parameterization", "KINDS"]
