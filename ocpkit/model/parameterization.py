"""Input parameterization: T per-step inputs as a linear map of p knot vectors, u_k = Σ_j φ_kj U_j.

The paper's piecewise-linear knots (Section III-B and "Parameterization" in Section V), move blocking
(zero-order hold) and traditional MPC (the identity, p = T) are one object with different T×p bases.
"""

from __future__ import annotations

import numpy as np

from ocpkit._checks import choice, integer

KINDS = ("linear", "zoh", "identity")


class Parameterization:
    """A T×p basis φ mapping knots U (p, m) to inputs u (T, m): u = φ U."""

    def __init__(self, kind: str, basis: np.ndarray):
        self.kind = kind
        self.basis = np.ascontiguousarray(basis, dtype=float)
        self.basis.setflags(write=False)
        self.horizon, self.knots = self.basis.shape
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
    def identity(cls, horizon: int) -> "Parameterization":
        """Traditional MPC: one knot per step (p = T)."""
        T = integer(horizon, "horizon", 1)
        return cls("identity", np.eye(T))

    @classmethod
    def make(cls, kind: str, horizon: int, knots: int | None = None) -> "Parameterization":
        """By name: "linear", "zoh" or "identity" (knots None or equal to the horizon means traditional MPC)."""
        choice(kind, KINDS, "parameterization")
        if kind == "identity" or knots is None:
            return cls.identity(horizon)
        return cls.linear_interp(horizon, knots) if kind == "linear" else cls.zero_order_hold(horizon, knots)

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


def _sizes(horizon, knots):
    T = integer(horizon, "horizon", 1)
    p = integer(knots, "knots", 1)
    if p > T:
        raise ValueError(f"knots must be <= horizon ({T}), got {p}")
    return T, p


__all__ = ["Parameterization", "KINDS"]
