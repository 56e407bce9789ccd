"""`ocpkit bench faults`: the adversarial matrix (:mod:`ocpkit.benchmarks.faults_matrix`), then the real-time rows
(:mod:`ocpkit.benchmarks.faults_realtime`) and the cache rows (:mod:`ocpkit.benchmarks.faults_cache`)."""

from __future__ import annotations

from ocpkit.benchmarks.faults_cache import cache_rows
from ocpkit.benchmarks.faults_matrix import SOLVERS, format_matrix, matrix
from ocpkit.benchmarks.faults_realtime import format_realtime, realtime_rows


def bench_faults(labels=tuple(SOLVERS), realtime: bool = True, out=print) -> list:
    """Print the matrix ("rec" = the same controller then matched a fresh one on a good problem), then the
    real-time rows (:func:`realtime_rows`) with their measured wall times and statuses, then the cache rows
    (:func:`cache_rows`)."""
    outcomes = matrix(labels)
    out(format_matrix(outcomes))
    bad = [o for o in outcomes if not o.acceptable]
    out(f"{len(outcomes)} cells, {len(bad)} unacceptable")
    if not realtime:
        return outcomes
    rows = realtime_rows()
    out("")
    out(format_realtime(rows))
    out(f"{len(rows)} real-time rows, {sum(not r.acceptable for r in rows)} unacceptable")
    cache = cache_rows(out)
    out("")
    out(format_realtime(cache))
    out(f"{len(cache)} cache rows, {sum(not r.acceptable for r in cache)} unacceptable")
    return outcomes + rows + cache
