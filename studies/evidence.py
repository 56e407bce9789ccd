"""Verdicts with their uncertainty: the paper's claims decided on per-seed data, with an interval and its n.

A claim about a median ("the 4-knot cost is within 5 % of traditional MPC's") is decided on a distribution-free
confidence interval of that median: the order statistics [x_(k), x_(n+1−k)], whose coverage 1 − 2·P(B ≤ k − 1),
B ~ Binomial(n, ½), holds for any continuous distribution. Comparisons are paired by seed (the same start and
goal): the median of the per-seed ratios (or differences). The verdict is

- **held** when the whole interval lies on the claimed side of the threshold,
- **not held** when the whole interval lies on the other side (or on the threshold where the claim is strict),
- **inconclusive** when it straddles the threshold,
- **not tested** when this run lacks the data (a size not run, hardware not present).

With few seeds the interval cannot reach 95 %: it is then the whole range [min, max], and its coverage (75 % at
n = 3, 87.5 % at n = 4) is printed beside it, so a reader sees how weak the evidence is.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ocpkit.sim.plots import number

HELD, NOT_HELD, INCONCLUSIVE, NOT_TESTED = "held", "not held", "inconclusive", "not tested"
LEVEL = 0.95


@dataclass(frozen=True)
class Interval:
    """A median ``value`` of ``n`` numbers and its distribution-free interval [low, high] of coverage ``coverage``."""

    value: float
    low: float
    high: float
    n: int
    coverage: float

    def text(self, digits: int = 4) -> str:
        """The interval as the report prints it, e.g. 1.02 [0.98, 1.1] (95 %, n = 8); "– (n = 0)" for no data."""
        if self.n == 0:
            return "– (n = 0)"
        return (
            f"{number(self.value, digits)} [{number(self.low, digits)}, {number(self.high, digits)}] "
            f"({number(100 * self.coverage, 3)} %, n = {self.n})"
        )


def quartiles(name: str, values) -> dict:
    """``{name}_median``, ``{name}_q1`` and ``{name}_q3`` of ``values`` (seconds)."""
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return {f"{name}_median": float(median), f"{name}_q1": float(q1), f"{name}_q3": float(q3)}


def median_interval(values, level: float = LEVEL) -> Interval:
    """The median of ``values`` (NaNs dropped) and its order-statistic interval of coverage ≥ ``level``, or the
    whole range and its coverage where n is too small for ``level``."""
    x = np.sort(np.asarray(values, dtype=float).ravel())
    x = x[~np.isnan(x)]
    n = x.size
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0, 0.0)
    k = 1  # the interval [x_(k), x_(n+1-k)], 1-based
    while k + 1 <= (n + 1) // 2 and _coverage(n, k + 1) >= level:
        k += 1
    return Interval(float(np.median(x)), float(x[k - 1]), float(x[n - k]), n, _coverage(n, k))


def _coverage(n: int, k: int) -> float:
    """P(x_(k) ≤ median ≤ x_(n+1−k)) = 1 − 2·P(Binomial(n, ½) ≤ k − 1)."""
    tail = sum(math.comb(n, i) for i in range(k)) / 2**n
    return max(0.0, 1.0 - 2.0 * tail)


def series(rows, metric: str, index="seed", **match):
    """``rows[metric]`` of the rows whose columns equal ``match`` (e.g. ``controller="CEM", links=3``), indexed by
    ``index`` (a column or a list of columns): one side of a :func:`paired` comparison."""
    selected = np.ones(len(rows), dtype=bool)
    for column, value in match.items():
        selected &= (rows[column] == value).to_numpy()
    return rows[selected].set_index(index)[metric]


def paired(a, b, how: str = "ratio") -> np.ndarray:
    """Per-seed a/b (``how="ratio"``) or a − b ("difference") of two pandas Series indexed by seed (or by any key
    they share), over the keys both have."""
    common = a.index.intersection(b.index)
    a, b = a.loc[common].to_numpy(dtype=float), b.loc[common].to_numpy(dtype=float)
    if how == "ratio":
        return a / b
    if how == "difference":
        return a - b
    raise ValueError(f"how must be 'ratio' or 'difference', got {how!r}")


def decide(interval: Interval, threshold: float, claimed: str) -> str:
    """The verdict on "the median is ``claimed`` ``threshold``", ``claimed`` one of "<", "<=", ">", ">="
    (strict: a median equal to the threshold does not hold), or "==" with ``threshold`` a (low, high) band."""
    if interval.n == 0:
        return NOT_TESTED
    lo, hi = interval.low, interval.high
    if claimed == "==":
        band_lo, band_hi = threshold
        if band_lo <= lo and hi <= band_hi:
            return HELD
        return NOT_HELD if hi < band_lo or lo > band_hi else INCONCLUSIVE
    tests = {
        "<": (hi < threshold, lo >= threshold),
        "<=": (hi <= threshold, lo > threshold),
        ">": (lo > threshold, hi <= threshold),
        ">=": (lo >= threshold, hi < threshold),
    }
    if claimed not in tests:
        raise ValueError(f"claimed must be one of <, <=, >, >=, ==, got {claimed!r}")
    holds, fails = tests[claimed]
    return HELD if holds else NOT_HELD if fails else INCONCLUSIVE


def median_claim(values, threshold, claimed: str, level: float = LEVEL) -> tuple[str, str]:
    """(verdict, evidence) for "the median of ``values`` is ``claimed`` ``threshold``" (see :func:`decide`)."""
    interval = median_interval(values, level)
    return decide(interval, threshold, claimed), interval.text()


def proportion(successes: int, n: int, level: float = LEVEL) -> tuple[float, float, float]:
    """A success rate k/n and its exact (Clopper–Pearson) interval of coverage ≥ ``level``."""
    from scipy.stats import beta

    if n == 0:
        return math.nan, math.nan, math.nan
    alpha = 1 - level
    low = 0.0 if successes == 0 else float(beta.ppf(alpha / 2, successes, n - successes + 1))
    high = 1.0 if successes == n else float(beta.ppf(1 - alpha / 2, successes + 1, n - successes))
    return successes / n, low, high


def combine(verdicts) -> str:
    """One verdict for a claim made of parts (every robot, every case): not held if a part is not held, held if
    all are, not tested if none was tested, else inconclusive."""
    verdicts = [v for v in verdicts if v != NOT_TESTED]
    if not verdicts:
        return NOT_TESTED
    if NOT_HELD in verdicts:
        return NOT_HELD
    return HELD if all(v == HELD for v in verdicts) else INCONCLUSIVE


def every(values, predicate, what: str) -> tuple[str, str]:
    """A claim about every run ("never below 1"): (verdict, "k of n runs …") — held when no run of the n violates
    it; no interval, since a single counterexample decides."""
    x = np.asarray(values, dtype=float).ravel()
    x = x[~np.isnan(x)]
    if x.size == 0:
        return NOT_TESTED, "no runs"
    bad = int((~predicate(x)).sum())
    return (HELD if bad == 0 else NOT_HELD), f"{bad} of {x.size} runs {what}"


def timing(verdict: str, loads, cores: int | None = None) -> str:
    """A timing verdict, or "unreliable (load L on N cores)" where the median 1-min load average over the trials
    exceeded the CPUs: timings taken then measure the queue for a core as much as the controller."""
    cores = cores or os.cpu_count() or 1
    load = np.asarray(loads, dtype=float)
    load = load[~np.isnan(load)]
    if verdict == NOT_TESTED or load.size == 0:
        return verdict
    median = float(np.median(load))
    return (
        f"unreliable (load {number(median, 3)} on {cores} cores; {verdict} as measured)" if median > cores else verdict
    )


def on_gpu(devices) -> bool:
    """Whether any of the trials' Taichi devices was a GPU ("cuda")."""
    return any(str(d) == "cuda" for d in devices)
