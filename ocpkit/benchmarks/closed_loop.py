"""A controller's closed loops on a problem's plant, summarized as one row of a benchmark table (``ocpkit bench
nlp`` and the peers' tables), and the machine load printed beside every timing."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np

from ocpkit.sim.metrics import actual_cost
from ocpkit.sim.simulate import simulate


def closed_loop(prob, ctrl, ocp, cases, duration: float, parts=("model", "build", "solve")) -> dict:
    """``ctrl``'s closed loops on ``prob``'s plant from each (x0, goal) of ``cases`` for ``duration`` seconds: the
    median, 90th percentile and maximum of its step times (ms) and the medians of their ``parts`` (keys of
    ``Solution.times``), the summed actual cost (on ``ocp``'s weights), the fallbacks, the median final error
    max |x_T − x_goal|, the steps, their median iterations and what answered most of them (``Solution.path``)."""
    times, cost, fallbacks, errors, split, iterations = [], 0.0, 0, [], {part: [] for part in parts}, []
    paths = Counter()
    for x0, goal in cases:
        ctrl.reset()
        traj = simulate(prob.plant(), ctrl, x0, goal, duration)
        times += list(traj.times())
        for part in split:
            split[part] += list(traj.times(part))
        cost += actual_cost(traj, ocp)
        fallbacks += traj.fallbacks
        errors.append(float(np.abs(traj.x[-1] - goal).max()))
        paths.update(s.path for s in traj.solutions)
        iterations += [s.iterations for s in traj.solutions]
    return {
        "step_ms": 1e3 * float(np.median(times)),
        "p90_ms": 1e3 * float(np.percentile(times, 90)),
        "max_ms": 1e3 * float(np.max(times)),
        "cost": cost,
        "fallbacks": fallbacks,
        "final_error": float(np.median(errors)),
        "steps": len(times),
        "iterations": float(np.median(iterations)),
        "path": paths.most_common(1)[0][0],
        **{f"{part}_ms": 1e3 * float(np.median(v)) for part, v in split.items()},
    }


def load() -> str:
    """The 1-, 5- and 15-minute load averages, and the CPUs they compare to."""
    return f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} CPUs"
