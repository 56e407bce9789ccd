"""The non-convex suite (issue 49): reaches whose straight path is blocked — behind one sphere, behind a staggered
wall of three, through a narrow passage between two, to a target near the joint limits — on the planar 3- and 7-link
arms and the Panda (full size only: its sampling kernels compile for minutes), by every controller at its default
and at an equal time budget per step; success with exact intervals, and EMPC against each baseline seed by seed.

Cases: :mod:`ocpkit.studies.nonconvex_cases` (drawn from seed 490 000 + s: seeds never used in development).
Controllers and trials: :mod:`ocpkit.studies.nonconvex_trials` (IPOPT multi-start:
:mod:`ocpkit.studies.nonconvex_multistart`). Statistics: :mod:`ocpkit.studies.nonconvex_stats`. Report:
:mod:`ocpkit.studies.nonconvex_report`. A trial succeeds when the end effector ends within 1 cm of the target with
true clearance ≥ 0 at every recorded state (and, in the limits case, no joint more than 0.01 rad beyond its limit).
"""

from __future__ import annotations

from ocpkit._checks import choice
from ocpkit.runs.study import Study, grid
from ocpkit.studies.nonconvex_cases import CASES, ROBOTS
from ocpkit.studies.nonconvex_report import report_section
from ocpkit.studies.nonconvex_trials import CONTROLLERS, IPOPT, trial

NAME = "nonconvex"
TITLE = "Non-convex reaches: blocked straight paths, every controller at its default and at an equal step budget"
PER_SEED = "success"
# A robot a size leaves out has 0 seeds. budget: seconds a step for the budgeted controllers (the control period).
# The quick size leaves out IPOPT at its default: IPOPT ×8 starts from IPOPT's own cold start and warm-starts as it
# does, and plain IPOPT was a fifth of the quick grid's time.
SIZES = {
    "quick": {
        "seeds": {"nlink:3": 1, "nlink:7": 0, "panda": 0},
        "controllers": [c for c in CONTROLLERS if c != IPOPT],
        "duration": 2.0,
        "horizon": 30,
        "population": 256,
        "arch": "cpu",
        "budget": 0.01,
    },
    "full": {
        "seeds": {"nlink:3": 30, "nlink:7": 30, "panda": 30},
        "controllers": list(CONTROLLERS),
        "duration": 3.0,
        "horizon": 50,
        "population": 1024,
        "arch": "auto",
        "budget": 0.01,
    },
}


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    trials = []
    for robot in ROBOTS:
        if s["seeds"].get(robot):
            trials += grid(
                robot=robot,
                case=list(CASES),
                controller=s["controllers"],
                horizon=s["horizon"],
                duration=s["duration"],
                population=s["population"],
                arch=s["arch"],
                budget=s["budget"],
                seeds=s["seeds"][robot],
            )
    return Study(NAME, trial, trials)


def report(df, out_dir) -> str:
    return report_section(df, out_dir, TITLE)
