"""Reliability: the adversarial matrix over every solver, recovery, and same seed → same run."""

import numpy as np
import pytest

from ocpkit import problems, solvers
from ocpkit.benchmarks.faults_matrix import BUDGET, SOLVERS, format_matrix, matrix
from ocpkit.sim.simulate import simulate


def test_adversarial_matrix_every_solver():
    outcomes = matrix()
    print("\n" + format_matrix(outcomes))
    bad = [o for o in outcomes if not o.acceptable]
    assert not bad, [(o.case, o.solver, o.result) for o in bad]
    for o in outcomes:
        if o.case == "time budget 1 µs":
            assert o.seconds < 1e-6 + BUDGET, (o.solver, o.seconds)  # budget plus a small overhead
    runtime = [o for o in outcomes if o.recovered is not None]
    assert runtime and all(o.recovered for o in runtime)


@pytest.mark.parametrize("label", list(SOLVERS))
def test_same_seed_same_closed_loop(label):
    problem = problems.make("pendulum")
    x0, goal = problem.sample(4)
    name, options = SOLVERS[label]
    runs = [
        simulate(problem.plant(), solvers.make(name, problem.ocp(knots=3), **options), x0, goal, 0.1) for _ in range(2)
    ]
    np.testing.assert_array_equal(runs[0].u, runs[1].u)
    np.testing.assert_array_equal(runs[0].x, runs[1].x)
