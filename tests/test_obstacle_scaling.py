"""Many obstacles (issue 43 §4): clearances as one pair's Function mapped over a table of obstacles, so that 1,000
spheres build and step on the Panda; the QP's obstacle rows bounded. Checked against independent numpy geometry
(ocpkit.model.task.clearances, and per pair here) and against CasADi's own derivative of the mapped clearances."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from ocpkit.model.kinematics import sphere_centers, spheres_along_links
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC
from ocpkit.model.task import ACTIVATION, ROWS_PER_SPHERE, ROWS_PER_STAGE, Sphere, Task, clearances, reach
from ocpkit.qp.task_rows import TaskRows


@pytest.fixture(scope="module")
def panda():
    return make("panda")


def _balls(count: int, seed: int, centre=(0.3, 0.0, 0.5), spread=0.4):
    rng = np.random.default_rng(seed)
    return [
        Sphere(tuple(np.asarray(centre) + rng.uniform(-spread, spread, 3)), float(rng.uniform(0.01, 0.08)))
        for _ in range(count)
    ]


def _task(problem, obstacles, margin=0.01):
    kin = problem.kinematics
    return Task([], obstacles, kinematics=kin, robot=spheres_along_links(kin, problem.link_radius), margin=margin)


def test_clearance_grows_with_the_robot_not_the_pairs(panda):
    """1,000 obstacles make the same expression as one: 23 spheres × 1,000 obstacles written out pair by pair were a
    19 MB C file (41 minutes to compile)."""
    one, many = (_task(panda, _balls(count, 0)).compile(14, 7) for count in (1, 1000))
    assert many.pairs == 1000 * one.pairs
    for name in ("clearance", "penalty"):
        assert getattr(many, name).n_instructions() == getattr(one, name).n_instructions() < 20, name
    sizes = []
    for tf in (one, many):
        gen = ca.CodeGenerator("clearance.c")
        gen.add(tf.clearance)
        gen.add(tf.penalty)
        sizes.append(len(gen.dump()))
    assert sizes[1] < sizes[0] + 200_000  # the table of 1,000 obstacles, 4 numbers each, and no more


def test_mapped_clearances_equal_numpy_pair_by_pair(panda):
    kin = panda.kinematics
    obstacles = _balls(7, 1)
    task = _task(panda, obstacles, margin=0.02)
    tf = task.compile(14, 7)
    rng = np.random.default_rng(2)
    Q = rng.uniform(-1.5, 1.5, (6, 7))
    X = np.hstack([Q, rng.normal(size=(6, 7))])
    d, D = (np.asarray(a) for a in tf.clearance.map(6)(X.T))
    # numpy, pair by pair: robot spheres outer
    C = np.asarray(sphere_centers(kin, task.robot).map(6)(Q.T)).reshape(3, 6, -1)
    want = np.array(
        [
            [
                np.linalg.norm(C[:, t, i] - o.center) - s.radius - o.radius - task.margin
                for i, s in enumerate(task.robot)
                for o in obstacles
            ]
            for t in range(6)
        ]
    )
    np.testing.assert_allclose(d.T, want, atol=1e-14)
    np.testing.assert_allclose(tf.pair_clearances(C).reshape(6, -1), want, atol=1e-14)
    np.testing.assert_allclose(d.min(axis=0) + task.margin, clearances(kin, task.robot, obstacles, Q), atol=1e-14)
    # the Jacobian: CasADi's derivative of the clearances evaluated symbolically (the mapped calls unrolled)
    x = ca.SX.sym("x", 14)
    exact = ca.Function("exact", [x], [ca.jacobian(tf.clearance(x)[0], x)])
    for t in range(6):
        np.testing.assert_allclose(D[:, 14 * t : 14 * (t + 1)], np.asarray(exact(X[t])), atol=1e-13)
    assert not D[:, 7:14].any()  # no velocity dependence
    # the penalty of the sampling planners: w (h + h²/2), h the deepest violation of the margin
    h = np.maximum(0.0, -want.min(axis=1))
    np.testing.assert_allclose(np.asarray(tf.penalty.map(6)(X.T)).ravel(), task.obstacle_weight * (h + h * h / 2))
    # the table as an input: moved obstacles without a new Function
    moved = [Sphere(tuple(np.asarray(o.center) + 0.1), o.radius) for o in obstacles]
    table = np.array([[*o.center, o.radius] for o in moved]).T
    again = _task(panda, moved, margin=0.02).compile(14, 7)
    np.testing.assert_allclose(
        np.asarray(tf.clearance_at(X[0], table)[0]), np.asarray(again.clearance(X[0])[0]), atol=1e-15
    )


def test_row_selection_keeps_each_spheres_closest_and_bounds_a_stage():
    T, k, N = 6, 30, 40
    rows = TaskRows.__new__(TaskRows)  # select() needs only its bounds
    rows.activation, rows.per_sphere, rows.per_stage = ACTIVATION, ROWS_PER_SPHERE, ROWS_PER_STAGE
    d = np.random.default_rng(3).uniform(-0.05, 0.5, (T, k, N))
    d[0] = 1.0  # a stage far from everything: no row
    d[1, :, 1:] = 1.0  # one obstacle: every sphere near it keeps its row
    stage, sphere, obstacle = rows.select(d)
    assert (stage != 0).all() and (d[stage, sphere, obstacle] < ACTIVATION).all()
    assert np.array_equal(np.sort(sphere[stage == 1]), np.flatnonzero(d[1, :, 0] < ACTIVATION))
    for t in range(2, T):
        near = d[t] < ACTIVATION
        closest = np.argsort(np.where(near, d[t], np.inf), axis=1)[:, :ROWS_PER_SPHERE]
        candidates = {(i, int(j)) for i in range(k) for j in closest[i] if near[i, j]}
        picked = set(zip(sphere[stage == t].tolist(), obstacle[stage == t].tolist()))
        assert picked <= candidates and len(picked) == min(len(candidates), ROWS_PER_STAGE)
        assert max(d[t][p] for p in picked) <= min(d[t][p] for p in candidates - picked)
    assert np.bincount(stage).max() == ROWS_PER_STAGE
    order = stage * k * N + sphere * N + obstacle
    assert np.array_equal(order, np.sort(order))  # by stage, then pair


def test_rows_are_the_clearance_functions_linearization(panda):
    """TaskRows' rows (numpy, from the spheres' kinematics) equal d + D S (z − z̄) from ``clearance``, the mapped
    Function, for every pair within the activation distance when the bound is lifted."""
    ocp = reach(panda, _balls(12, 4, spread=0.25), compiled=False, horizon=8, knots=4)
    rows = TaskRows(ocp, obstacles=True)
    rows.per_sphere = rows.per_stage = 10**6
    T, n, nz = ocp.horizon, ocp.nx, ocp.nu * ocp.knots
    rng = np.random.default_rng(5)
    x0 = np.r_[panda.sample(0)[0][:7], np.zeros(7)]
    SV = np.concatenate([x0[:, None] + 0.05 * rng.normal(size=(T, n, 1)), 1e-3 * rng.normal(size=(T, n, nz))], axis=2)
    knots = rng.normal(size=(ocp.knots, ocp.nu))
    C, lo, stage = rows.add(np.zeros((nz, nz)), np.zeros(nz), SV, x0, ocp.goal(x0, position=[0.4, 0, 0.4])[n:], knots)
    X = SV @ np.r_[1.0, knots.ravel()]
    d, D = (np.asarray(a) for a in ocp.task_functions.clearance.map(T)(X.T))
    D = D.reshape(-1, T, n).transpose(1, 0, 2)
    k, pair = np.nonzero(d.T < ACTIVATION)
    assert k.size > 10 and np.array_equal(stage, k)
    want = np.einsum("ra,raj->rj", D[k, pair], SV[k, :, 1:])
    np.testing.assert_allclose(C, want, atol=1e-12)
    np.testing.assert_allclose(lo, want @ knots.ravel() - d.T[k, pair], atol=1e-12)


def test_thousand_spheres_build_and_step(panda, monkeypatch):
    """1,000 spheres near the Panda: reach, LinearMPC and a first step; the step's QP has at most ROWS_PER_STAGE
    obstacle rows a stage."""
    x0 = panda.sample(0)[0]
    robot = spheres_along_links(panda.kinematics, panda.link_radius)
    centres = np.asarray(sphere_centers(panda.kinematics, robot)(x0[:7]))
    radii = np.array([s.radius for s in robot])
    balls = [
        b
        for b in _balls(3000, 6, spread=0.6)
        if (np.linalg.norm(centres.T - b.center, axis=1) - radii - b.radius).min() > 0.02
    ]
    assert len(balls) >= 1000
    ocp = reach(panda, balls[:1000], compiled=False)
    assert ocp.task_functions.pairs == 1000 * len(robot)
    ctrl = LinearMPC(ocp, linearization="trajectory")
    seen = []
    add = TaskRows.add
    monkeypatch.setattr(TaskRows, "add", lambda self, *a: seen.append(add(self, *a)) or seen[-1])
    sol = ctrl.solve(x0, ocp.goal(x0, position=[0.4, 0.0, 0.4]))
    assert np.isfinite(sol.u).all() and seen and seen[0] is not None
    counts = np.bincount(seen[0][2])
    assert 0 < counts.max() <= ROWS_PER_STAGE, counts
