"""Argument validation shared by the public constructors: precise errors naming the argument."""

from __future__ import annotations

import numpy as np


def choice(value, choices, name: str):
    """``value`` if it is one of ``choices``, else a ValueError naming the argument and the choices."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def positive(value, name: str) -> float:
    """A finite float > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return v


def integer(value, name: str, minimum: int) -> int:
    """An int >= minimum (bools rejected)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def array(value, name: str, shape: tuple, *, allow_inf: bool = False) -> np.ndarray:
    """A float64 array of the given shape with no NaN (and no inf unless allowed)."""
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be numeric, got {value!r}") from None
    if a.shape != shape:
        if a.size == int(np.prod(shape)) and a.ndim <= 1 and len(shape) == 1:
            a = a.reshape(shape)
        else:
            raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if np.isnan(a).any() or (not allow_inf and np.isinf(a).any()):
        raise ValueError(f"{name} must be {'free of NaN' if allow_inf else 'finite'}, got {a.tolist()}")
    return a


def weight(value, name: str, n: int, *, definite: bool) -> np.ndarray:
    """A symmetric n×n weight: a scalar, a length-n diagonal or a matrix; PSD, or PD if ``definite``."""
    a = np.array(value, dtype=float) if np.ndim(value) else np.full(n, float(value))
    if a.ndim == 1:
        a = np.diag(a) if a.shape == (n,) else a
    a = array(a, name, (n, n))
    if not np.allclose(a, a.T, rtol=1e-12, atol=1e-12):
        raise ValueError(f"{name} must be symmetric")
    lowest = np.linalg.eigvalsh(a).min() if n else 0.0
    tol = 1e-12 * max(1.0, np.abs(a).max(initial=0.0))
    if definite and lowest <= tol:
        raise ValueError(f"{name} must be positive definite (smallest eigenvalue {lowest:.3g})")
    if not definite and lowest < -tol:
        raise ValueError(f"{name} must be positive semidefinite (smallest eigenvalue {lowest:.3g})")
    return a


def bounds(lower, upper, lower_name: str, upper_name: str, n: int):
    """Lower/upper bound vectors (None = unbounded; ±inf allowed) with lower ≤ upper."""
    lo = (
        np.full(n, -np.inf)
        if lower is None
        else array(np.broadcast_to(lower, (n,)) if np.ndim(lower) == 0 else lower, lower_name, (n,), allow_inf=True)
    )
    hi = (
        np.full(n, np.inf)
        if upper is None
        else array(np.broadcast_to(upper, (n,)) if np.ndim(upper) == 0 else upper, upper_name, (n,), allow_inf=True)
    )
    bad = np.flatnonzero(lo > hi)
    if bad.size:
        i = bad[0]
        raise ValueError(f"{lower_name}[{i}] = {lo[i]} is above {upper_name}[{i}] = {hi[i]}")
    return lo, hi
