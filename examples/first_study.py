"""Getting started: a first study — the pendulum's actual cost over knot counts and seeds, stored and resumable.

Run it as ``python first_study.py [OUT_DIR]``: every finished trial is stored in ``OUT_DIR/results.sqlite``, so a
second run computes nothing and prints the same table.
"""

import sys

from ocpkit import LinearMPC, make, simulate
from ocpkit.runs.study import Study, grid, run
from ocpkit.sim.metrics import actual_cost


def trial(knots: int, seed: int) -> dict:
    """One closed loop from the seeded start and goal: the cost the plant actually incurred."""
    problem = make("pendulum")
    ocp = problem.ocp(knots=knots)
    x0, goal = problem.sample(seed)
    traj = simulate(problem.plant(), LinearMPC(ocp), x0, goal, duration=1.0)
    return {"cost": actual_cost(traj, ocp), "successes": traj.successes}


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "results/first_study"
    study = Study("first_study", trial, grid(knots=[2, 5], seeds=2))  # 2 knot counts × seeds 0, 1
    df = run(study, out, workers=1, progress=False)
    print(df.pivot_table(index="seed", columns="knots", values="cost"))
