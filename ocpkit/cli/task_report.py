"""How a run did on the reach task of the command line (:mod:`ocpkit.cli.task`): the frame's final distance to the
target, the smallest clearance and the collisions, as a report, one line of text and the figure's task panel."""

from __future__ import annotations

import numpy as np

from ocpkit.cli.task import Reach


def reach_panels(problem, ocp, task: Reach, xs) -> dict:
    """The figure's task panel: the frame's distance to the target and (with obstacles) the smallest clearance, at
    every state of ``xs``."""
    positions, clearance = _reach_series(problem, ocp, task, xs)
    panels = {f"{task.frame} to target": np.linalg.norm(positions - task.target, axis=1)}
    if clearance is not None:
        panels["min clearance"] = clearance
    return panels


def _reach_series(problem, ocp, task: Reach, xs, moving=None):
    """The frame's positions (N, 3) along the states ``xs`` (N, nx) and the smallest clearance at each (None without
    obstacles): distance from a robot sphere's surface to an obstacle's (where they are at each state, (N, n, 4),
    with ``moving``)."""
    from ocpkit.model.task import clearances

    xs = np.atleast_2d(np.asarray(xs, dtype=float))
    kin = problem.kinematics
    positions = kin.positions(task.frame, xs[:, : kin.n])
    if not task.obstacles:
        return positions, None
    obstacles = ocp.task.obstacles if moving is None else moving
    return positions, clearances(ocp.task.kinematics, ocp.task.robot, obstacles, xs[:, : kin.n])


def reach_report(
    problem, ocp, task: Reach, xs, dt: float | None = None, success_while_colliding: int | None = None, moving=None
) -> dict:
    """How the states ``xs`` (N, nx) did on the task: the frame's distance to the target at the last state, and the
    smallest clearance — distance from a robot sphere's surface to an obstacle's — over all states (negative: they
    overlap, a collision; ``moving``: where the obstacles were at each state); for a closed loop,
    ``success_while_colliding``: the steps reported "success" whose next state collides. With an orientation
    target, the frame's final angle to it (rad); with more frames' targets, each one's final distance."""
    positions, closest = _reach_series(problem, ocp, task, xs, moving)
    q = np.atleast_2d(xs)[-1, : problem.kinematics.n]
    report = {
        "frame": task.frame,
        "target": task.target.tolist(),
        "final_position": positions[-1].tolist(),
        "final_distance": float(np.linalg.norm(positions[-1] - task.target)),
        "obstacles": [[*map(float, o.center), float(o.radius)] for o in task.obstacles],
        "margin": ocp.task.margin,
        "min_clearance": None,
        "collisions": 0,
        "first_collision": None,
        "states": len(positions),
    }
    if closest is not None:
        hit = np.flatnonzero(closest < 0)
        report.update(
            min_clearance=float(closest.min()),
            collisions=int(hit.size),
            first_collision=None if not hit.size else int(hit[0]) if dt is None else float(hit[0] * dt),
        )
    if task.orientation is not None:
        R = np.asarray(problem.kinematics.function(task.frame)(q)[1])
        cosine = (np.trace(task.orientation.reshape(3, 3).T @ R) - 1) / 2
        report["final_orientation_error"] = float(np.arccos(np.clip(cosine, -1.0, 1.0)))
    if task.frame_targets:
        report["frame_targets"] = [
            {
                "frame": t.frame,
                "target": t.target.tolist(),
                "final_distance": float(
                    np.linalg.norm(np.asarray(problem.kinematics.function(t.frame)(q)[0]).ravel() - t.target)
                ),
            }
            for t in task.frame_targets
        ]
    if success_while_colliding is not None:
        report["success_while_colliding"] = int(success_while_colliding)
    return report


def reach_line(report: dict, what: str) -> str:
    """The report as one line of text."""
    line = (
        f"reach: {report['frame']} {report['final_distance']:.4f} m from the target "
        f"{point_text(report['target'])} {what}"
    )
    if "final_orientation_error" in report:
        line += f", {report['final_orientation_error']:.4f} rad from its orientation"
    for t in report.get("frame_targets", ()):
        line += f"; {t['frame']} {t['final_distance']:.4f} m from {point_text(t['target'])}"
    n = len(report["obstacles"])
    if not n:
        return line + "; no obstacles"
    first = report["first_collision"]
    when = (
        ""
        if first is None
        else f", first at t = {first:.2f} s"
        if isinstance(first, float)
        else f", first at step {first}"
    )
    collided = (
        f"COLLIDED in {report['collisions']} of {report['states']} states{when}"
        if report["collisions"]
        else f"no collision in {report['states']} states"
    )
    if report["collisions"] and "success_while_colliding" in report:
        collided += f", {report['success_while_colliding']} steps reported success while colliding"
    return (
        line + f"; min clearance {report['min_clearance']:.4f} m to {n} obstacle{'s' * (n > 1)} "
        f"(margin {report['margin']:g} m); {collided}"
    )


def point_text(v) -> str:
    """A point as "(x, y, z)", each number in its shortest form."""
    return "(" + ", ".join(f"{a:g}" for a in v) + ")"
