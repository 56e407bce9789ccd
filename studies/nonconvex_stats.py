"""Paired statistics of the non-convex suite (:mod:`ocpkit.studies.nonconvex`): two controllers run on the same
seeds (the same start, target and obstacles), compared seed by seed.

- **Success, McNemar's exact test.** Of n paired runs, b seeds where A succeeds and B misses, c where B succeeds and
  A misses (the discordant pairs; the concordant ones say nothing about a difference). Under "A and B succeed equally
  often", b ~ Binomial(b + c, ½); the two-sided exact p-value is min(1, 2·P(Binomial(b + c, ½) ≤ min(b, c))). Its
  dual is an interval: the share of discordant pairs A wins, b / (b + c), with its exact (Clopper–Pearson) interval —
  "A succeeds where B misses more often than the reverse" is held when the whole interval lies above ½.
- **Cost, a paired order-statistic interval.** The per-seed ratios (or differences) A/B over the seeds both have,
  their median and the distribution-free interval of :func:`ocpkit.studies.evidence.median_interval`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ocpkit.studies.evidence import INCONCLUSIVE, NOT_TESTED, Interval, decide, median_interval, paired, proportion


def binomial_cdf_half(k: int, n: int) -> float:
    """P(Binomial(n, ½) ≤ k), exactly (integer sums, one division)."""
    if k < 0:
        return 0.0
    return sum(math.comb(n, i) for i in range(min(k, n) + 1)) / 2**n


def mcnemar_exact(b: int, c: int) -> float:
    """The two-sided exact McNemar p-value of ``b`` and ``c`` discordant pairs (1 when there are none)."""
    if b < 0 or c < 0:
        raise ValueError(f"discordant counts must be >= 0, got {b} and {c}")
    if b + c == 0:
        return 1.0
    return min(1.0, 2.0 * binomial_cdf_half(min(b, c), b + c))


@dataclass(frozen=True)
class PairedSuccess:
    """A against B on ``n`` shared seeds: ``both`` succeed, ``a_only`` (b), ``b_only`` (c), ``neither``; McNemar's
    exact ``p``, and A's share of the discordant pairs with its exact interval (NaN when there are none)."""

    n: int
    both: int
    a_only: int
    b_only: int
    neither: int
    p: float
    share: float
    low: float
    high: float

    def text(self, a: str = "A", b: str = "B") -> str:
        """E.g. "A only 5, B only 1 of n = 30 (McNemar exact p = 0.22; A's share of the discordant 0.83 [0.36, 1])"."""
        from ocpkit.sim.plots import number

        share = (
            f"; {a}'s share of the discordant {number(self.share, 2)} [{number(self.low, 2)}, {number(self.high, 2)}]"
            if self.a_only + self.b_only
            else ""
        )
        counts = f"{a} only {self.a_only}, {b} only {self.b_only} of n = {self.n}"
        return f"{counts} (McNemar exact p = {number(self.p, 2)}{share})"

    def verdict(self) -> str:
        """ "A succeeds where B misses more often than the reverse": held when the exact interval of A's share of the
        discordant pairs lies above ½, not held when it lies at or below ½, inconclusive when it straddles ½ or there
        is no discordant pair (no evidence either way); not tested without shared seeds."""
        if self.n == 0:
            return NOT_TESTED
        if self.a_only + self.b_only == 0:
            return INCONCLUSIVE
        return decide(Interval(self.share, self.low, self.high, self.a_only + self.b_only, 0.95), 0.5, ">")


def paired_success(a, b) -> PairedSuccess:
    """Success of A against B, two boolean pandas Series indexed by the same keys (seed, or case and seed), over the
    keys both have."""
    common = a.index.intersection(b.index)
    x, y = a.loc[common].to_numpy(dtype=bool), b.loc[common].to_numpy(dtype=bool)
    b_, c_ = int((x & ~y).sum()), int((~x & y).sum())
    share, low, high = proportion(b_, b_ + c_) if b_ + c_ else (math.nan, math.nan, math.nan)
    return PairedSuccess(
        int(x.size), int((x & y).sum()), b_, c_, int((~x & ~y).sum()), mcnemar_exact(b_, c_), share, low, high
    )


def paired_interval(a, b, how: str = "ratio") -> Interval:
    """The median of the per-seed a/b (or a − b) over the keys both Series have, with its order-statistic interval."""
    values = paired(a, b, how)
    return median_interval(values[np.isfinite(values)])
