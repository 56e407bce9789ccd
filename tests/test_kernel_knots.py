"""The population kernels loop over knots at run time (issue 31): the basis enters by its nonzeros per row, which
must give the Parameterization's inputs, and traditional MPC's p = T = 100 knots build and step, on the arch of
`pytest --arch`."""

import numpy as np
import pytest
import taichi as ti
from scipy.interpolate import BSpline

from ocpkit import problems
from ocpkit.status import SUCCESS
from ocpkit.codegen.kernels import runtime
from ocpkit.codegen.kernels.rollout import Rollout, SparseRows
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.solvers.cem import CrossEntropyMPC
from ocpkit.solvers.empc import EvolutionaryMPC

pytestmark = pytest.mark.usefixtures("taichi_arch")


def test_write_fills_a_section_of_a_device_array_in_one_quiet_launch(capfd):
    """runtime.write copies a host array into a device array from an offset and leaves the rest alone, and Taichi
    prints nothing doing it (a struct-for with serialize warned once per field in every planner's construction)."""
    data = ti.ndarray(ti.f64, (6,))
    data.from_numpy(np.zeros(6))
    runtime.write(data, np.array([1.0, 2.0, 3.0]), 2)
    np.testing.assert_array_equal(data.to_numpy(), [0.0, 0.0, 1.0, 2.0, 3.0, 0.0])
    assert "[W " not in capfd.readouterr().err


def test_shared_builds_once_per_key():
    built = []
    first = runtime.shared(("test", 1), lambda: built.append(1) or object())
    assert runtime.shared(("test", 1), lambda: built.append(2) or object()) is first
    assert runtime.shared(("test", 2), lambda: built.append(3) or object()) is not first
    assert built == [1, 3]


def test_sparse_rows_hold_each_rows_nonzeros_in_column_order():
    M = np.array([[0.0, 2.0, 0.0, -1.0], [0.0, 0.0, 0.0, 0.0], [3.0, 4.0, 5.0, 1e-300]])
    rows = SparseRows(M)
    columns, weights = rows.columns, rows.weights
    assert rows.width == 4 and columns.shape == weights.shape == (3, 4)
    np.testing.assert_array_equal(columns[0, :2], [1, 3])
    np.testing.assert_array_equal(columns[2], [0, 1, 2, 3])
    np.testing.assert_array_equal(weights[1], 0.0)  # an all-zero row is padding only
    dense = np.zeros_like(M)
    for k in range(M.shape[0]):
        np.add.at(dense[k], columns[k], weights[k])
    np.testing.assert_array_equal(dense, M)
    np.testing.assert_array_equal(rows.values(), np.r_[columns.ravel(), weights.ravel()])  # the section, in order
    assert rows.size == 24 and SparseRows(np.zeros((2, 3))).width == 1
    with pytest.raises(ValueError, match="matrix"):
        SparseRows(np.zeros(3))


def _cubic_bspline(horizon, knots):
    """Clamped cubic B-splines on equally spaced breakpoints, evaluated at the steps: up to 4 nonzeros a row."""
    degree = 3
    breaks = np.linspace(0.0, horizon - 1.0, knots - degree + 1)
    t = np.r_[[0.0] * degree, breaks, [horizon - 1.0] * degree]
    return BSpline.design_matrix(np.arange(horizon, dtype=float), t, degree).toarray()


@pytest.mark.parametrize("kind", ["linear", "zoh", "identity", "bspline"])
def test_kernel_inputs_equal_the_parameterization(kind):
    problem = problems.make("nlink:2")
    T, p, N = 23, 7, 5
    if kind == "bspline":  # not a named Parameterization: built from its basis
        param = Parameterization(kind, _cubic_bspline(T, p))
        assert (param.basis != 0).sum(axis=1).max() == 4
    else:
        param = Parameterization.make(kind, T, p)
    ocp = OCP(problem.model(1.0), problem.dt, T, parameterization=param, **problem.defaults())
    engine = Rollout(ocp, N)
    U = np.random.default_rng(0).uniform(ocp.u_min, ocp.u_max, size=(N, ocp.knots, ocp.nu))
    engine.knots.from_numpy(U)
    input_at, m = engine.input_at, ocp.nu

    @ti.kernel
    def inputs(knots: ti.types.ndarray(), data: ti.types.ndarray(), out: ti.types.ndarray()):
        for i, k in ti.ndrange(N, T):
            u = input_at(i, k, knots, data)
            for a in ti.static(range(m)):
                out[i, k, a] = u[a]

    got = np.empty((N, T, m))
    inputs(engine.knots, engine.data, got)
    expected = np.array([param.inputs(knots) for knots in U])
    np.testing.assert_allclose(got, expected, rtol=1e-14, atol=1e-14 * np.abs(U).max())
    if kind in ("zoh", "identity"):  # one weight 1.0 a row: the knots themselves
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("cls", [EvolutionaryMPC, CrossEntropyMPC])
def test_traditional_mpc_with_100_knots_builds_and_steps(cls):
    """p = T = 100 (d = 300 parameters): unrolled, these kernels compiled for hours."""
    problem = problems.make("nlink:3")
    ocp = problem.ocp(knots=None, horizon=100)
    assert ocp.knots == 100
    x0, goal = problem.sample(0)
    ctrl = cls(ocp, population=64, seed=0)
    first = ctrl.solve(x0, goal)
    parents = ctrl.engine.picked.to_numpy()
    second = ctrl.solve(x0, goal)
    for sol in (first, second):
        assert sol.status == SUCCESS and not sol.fallback, sol.raw_status
        assert sol.knots.shape == (100, 3) and np.all(sol.knots >= ocp.u_min) and np.all(sol.knots <= ocp.u_max)
    population = ctrl.engine.knots.to_numpy()
    if cls is EvolutionaryMPC:  # the elites: the last step's parents shifted by the kernel's sparse S, as numpy does
        np.testing.assert_array_equal(population[: ctrl.num_parents], ctrl._shifted(parents[: ctrl.num_parents]))
    else:  # candidates 1 and 2: the seeds, clipped
        pre = ctrl.preconditioner
        np.testing.assert_array_equal(population[1:3], np.clip([pre.newton, pre.hold], ocp.u_min, ocp.u_max))
