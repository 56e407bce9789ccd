"""Pictures of motion for the reproduce report: one short closed loop per robot family, animated (ocpkit.sim.animation).

Not a study (nothing is stored or resumed): three seeded LinearMPC runs (5 knots) against ocpkit's plant — the
pendulum to its joint goal, the planar 3-link arm and the Panda reaching a point past a sphere (the docs'
examples) — each written as a GIF beside the report and embedded in it with what the run reached.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ocpkit import problems, solvers
from ocpkit.sim import animation
from ocpkit.sim.plots import number
from ocpkit.sim.simulate import simulate
from ocpkit.model.task import Sphere, clearances, reach

FOLDER = "motion"  # beside report.md
KNOTS = 5  # the command line's default


@dataclass(frozen=True)
class Scene:
    """One closed loop to picture: a problem from its seeded start, to the seeded joint goal or (``target``) a point
    for its end effector past ``obstacles``."""

    problem: str
    caption: str
    duration: float
    seed: int = 0
    target: tuple | None = None
    obstacles: tuple = ()


SCENES = (
    Scene("pendulum", "pendulum, to its joint goal (the dashed pose)", 2.0),
    Scene(
        "nlink:3",
        "planar 3-link chain, the tip to a point past a sphere",
        2.0,
        target=(0.3, 0.5, 0.0),
        obstacles=(Sphere((0.55, 0.2, 0.0), 0.08),),
    ),
    Scene(
        "panda",
        "Panda (3-D arm), the hand to a point past a sphere",
        2.0,
        target=(0.4, 0.0, 0.3),
        obstacles=(Sphere((0.4, -0.25, 0.35), 0.08),),
    ),
)


def picture(scene: Scene, out_dir) -> tuple[Path, str]:
    """Run ``scene`` and write its GIF into ``out_dir``/motion; (the GIF, one line saying what the run reached)."""
    pb = problems.make(scene.problem)
    x0, goal = pb.sample(scene.seed)
    if scene.target is None:
        ocp = pb.ocp(knots=KNOTS)
    else:
        ocp = reach(pb, scene.obstacles, knots=KNOTS)
        goal = ocp.goal(x0, position=scene.target)
    ctrl = solvers.make("qp", ocp)
    traj = simulate(pb.plant(), ctrl, x0, goal, scene.duration)
    n = len(x0) // 2
    if scene.target is None:
        reached = f"largest joint error at the end {number(np.abs(traj.x[-1, :n] - goal[:n]).max(), 3)} rad"
    else:
        kin = pb.kinematics
        distance = np.linalg.norm(kin.positions(pb.end_effector, traj.x[-1:, :n])[0] - np.asarray(scene.target))
        closest = clearances(kin, ocp.task.robot, ocp.task.obstacles, traj.x[:, :n]).min()
        reached = (
            f"{pb.end_effector} {number(distance, 3)} m from the target, smallest clearance {number(closest, 3)} m"
        )
    start = time.perf_counter()
    path = animation.animate(
        traj,
        Path(out_dir) / FOLDER / f"{scene.problem.replace(':', '')}.gif",
        pb,
        target=scene.target,
        obstacles=scene.obstacles,
        title=f"{scene.problem}, LinearMPC",
    )
    drawn = time.perf_counter() - start
    line = (
        f"{scene.caption}: LinearMPC ({KNOTS} knots), {scene.duration:g} s from seed {scene.seed}; {reached}; "
        f"{path.stat().st_size / 1e3:.0f} kB, drawn in {drawn:.1f} s"
    )
    return path, line


def section(out_dir) -> str:
    """The report's "Pictures of motion" part: every scene's GIF (paths relative to the report) and its line."""
    parts = [
        "### Pictures of motion",
        "",
        "The robot's motion in short seeded closed loops (ocpkit's plant), drawn from its forward kinematics as a "
        "stick figure with the end effector's path; the time is in each frame. `ocpkit simulate … --animate "
        "FILE.gif` draws any run this way.",
        "",
    ]
    for scene in SCENES:
        path, line = picture(scene, out_dir)
        parts += [f"![{scene.caption}]({path.relative_to(Path(out_dir)).as_posix()})", "", line, ""]
    return "\n".join(parts)
