"""Verdicts with uncertainty (issue 32): the median's distribution-free interval has the coverage it states, and the
verdict follows the interval's position against the threshold."""

import numpy as np
import pandas as pd
import pytest

from ocpkit.studies.evidence import (
    HELD,
    INCONCLUSIVE,
    NOT_HELD,
    NOT_TESTED,
    Interval,
    combine,
    decide,
    every,
    median_claim,
    median_interval,
    paired,
    proportion,
    series,
    timing,
)


@pytest.mark.parametrize("n, coverage", [(3, 0.75), (4, 0.875), (8, 1 - 2 / 256), (15, 1 - 2 * 576 / 2**15)])
def test_stated_coverage_is_the_binomial_one(n, coverage):
    interval = median_interval(np.arange(n, dtype=float))
    assert interval.n == n and interval.coverage == pytest.approx(coverage)
    assert interval.value == pytest.approx(np.median(np.arange(n)))


@pytest.mark.parametrize("n", [5, 12, 30])
def test_interval_covers_the_true_median_as_often_as_stated(n):
    """Monte Carlo on a skewed law (lognormal, median 1): the order-statistic interval's hit rate equals its
    stated coverage (binomial standard error ~0.002 at 20,000 draws)."""
    rng = np.random.default_rng(0)
    stated = median_interval(np.zeros(n)).coverage
    hits = 0
    draws = 20_000
    for sample in rng.lognormal(0.0, 1.0, size=(draws, n)):
        i = median_interval(sample)
        hits += i.low <= 1.0 <= i.high
    assert abs(hits / draws - stated) < 0.01
    assert stated >= 0.95 or n <= 5


def test_verdicts_follow_the_interval():
    assert decide(Interval(0.9, 0.8, 0.95, 8, 0.99), 1.0, "<") == HELD
    assert decide(Interval(1.1, 1.0, 1.2, 8, 0.99), 1.0, "<") == NOT_HELD  # on the threshold: a strict claim fails
    assert decide(Interval(1.0, 0.9, 1.1, 8, 0.99), 1.0, "<") == INCONCLUSIVE
    assert decide(Interval(1.0, 1.0, 1.0, 15, 0.96), 1.0, "<") == NOT_HELD  # identical costs are not "down"
    assert decide(Interval(1.0, 1.0, 1.0, 15, 0.96), 1.0, "<=") == HELD
    assert decide(Interval(1.0, 0.999, 1.0005, 8, 0.99), (0.999, 1.001), "==") == HELD
    assert decide(Interval(2.0, 1.5, 2.5, 8, 0.99), (0.8, 1.25), "==") == NOT_HELD
    assert decide(median_interval([]), 1.0, "<") == NOT_TESTED
    with pytest.raises(ValueError, match="claimed"):
        decide(Interval(1, 1, 1, 1, 0.5), 1.0, "!=")


def test_the_issues_examples():
    """0.01 % apart on medians but overlapping per-seed spreads: inconclusive, not "not held"."""
    lower = pd.Series([1.0, 1.2, 6.9, 1.1, 1.3, 2.0, 1.05, 1.104757], index=range(8))
    higher = pd.Series([1.0, 1.3, 3.6, 1.2, 1.0, 1.5, 1.1, 1.104895], index=range(8))
    verdict, evidence = median_claim(paired(lower, higher), 1.0, ">")
    assert verdict == INCONCLUSIVE and "n = 8" in evidence
    three_seeds = median_claim([0.9987, 1.02, 0.71], 1.0, "<")  # one low seed does not carry "dips below 1"
    assert three_seeds[0] == INCONCLUSIVE and "75 %" in three_seeds[1]


def test_paired_aligns_by_seed_and_every_counts_counterexamples():
    a = pd.Series([2.0, 4.0, 9.0], index=[0, 1, 2])
    b = pd.Series([1.0, 2.0], index=[1, 0])
    np.testing.assert_allclose(paired(a, b), [1.0, 4.0])  # seed 0: 2 / 2, seed 1: 4 / 1; seed 2 unpaired
    np.testing.assert_allclose(paired(a, b, "difference"), [0.0, 3.0])
    rows = pd.DataFrame(
        {
            "controller": ["QP", "EMPC", "QP", "EMPC"],
            "links": [3, 3, 3, 6],
            "seed": [0, 0, 1, 0],
            "cost": [1.0, 2.0, 3.0, 4.0],
        }
    )
    assert series(rows, "cost", controller="QP").to_dict() == {0: 1.0, 1: 3.0}
    assert series(rows, "cost", ["links", "seed"], controller="EMPC").to_dict() == {(3, 0): 2.0, (6, 0): 4.0}
    assert every([1.0, 1.2, 0.99], lambda x: x >= 1, "below 1") == (NOT_HELD, "1 of 3 runs below 1")
    assert every([], lambda x: x >= 1, "below 1")[0] == NOT_TESTED


def test_combine_timing_and_proportion():
    assert combine([HELD, HELD]) == HELD and combine([HELD, INCONCLUSIVE]) == INCONCLUSIVE
    assert combine([HELD, NOT_HELD, INCONCLUSIVE]) == NOT_HELD and combine([NOT_TESTED]) == NOT_TESTED
    assert timing(HELD, [1.0, 1.5], cores=2) == HELD
    assert timing(HELD, [7.0, 11.0], cores=2).startswith("unreliable (load 9 on 2 cores")
    assert timing(HELD, [2.04, 2.04], cores=2).startswith("unreliable (load 2.04 on")
    rate, low, high = proportion(4, 5)
    assert rate == 0.8 and low == pytest.approx(0.2836, abs=1e-4) and high == pytest.approx(0.9949, abs=1e-4)
    assert proportion(5, 5)[2] == 1.0 and proportion(0, 5)[1] == 0.0
