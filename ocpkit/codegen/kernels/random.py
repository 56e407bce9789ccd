"""Counter-based random numbers for population kernels.

Every draw is a hash of (seed, generation counter, candidate, slot), so it does not depend
on how Taichi spreads the population over threads: the same seed gives the same population,
bit for bit, on any number of CPU threads (every random draw takes a seed).
"""

# No "from __future__ import annotations": Taichi reads the annotations as types.
import math

import numpy as np
import taichi as ti


def seed_key(seed: int) -> int:
    """A well-mixed 32-bit key for a non-negative integer ``seed``."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(np.random.SeedSequence(int(seed)).generate_state(1, dtype=np.uint32)[0])


@ti.func
def _mix(h: ti.u32) -> ti.u32:
    # "lowbias32" integer hash (C. Wellons, hash-prospector): full avalanche in 32 bits.
    h ^= h >> 16
    h *= ti.u32(0x7FEB352D)
    h ^= h >> 15
    h *= ti.u32(0x846CA68B)
    h ^= h >> 16
    return h


@ti.func
def uniform(key: ti.u32, counter: ti.u32, i: ti.i32, slot: ti.i32) -> ti.f64:
    """U(0, 1), open at both ends."""
    h = _mix(_mix(_mix(key ^ _mix(counter)) + ti.cast(i, ti.u32)) + ti.cast(slot, ti.u32))
    return (ti.cast(h, ti.f64) + 0.5) * (1.0 / 4294967296.0)


@ti.func
def normal(key: ti.u32, counter: ti.u32, i: ti.i32, slot: ti.i32) -> ti.f64:
    """N(0, 1) by Box–Muller; its own stream, independent of ``uniform`` at the same slot."""
    a = uniform(key ^ ti.u32(0x9E3779B9), counter, i, 2 * slot)
    b = uniform(key ^ ti.u32(0x9E3779B9), counter, i, 2 * slot + 1)
    return ti.sqrt(-2.0 * ti.log(a)) * ti.cos(2.0 * math.pi * b)
