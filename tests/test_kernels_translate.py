"""CasADi -> Taichi translation: the generated kernels evaluate exactly what CasADi evaluates."""

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.codegen.kernels.translate import SUPPORTED_OPERATIONS, translate


pytestmark = pytest.mark.usefixtures("taichi_arch")


def _random_inputs(function, seed, batch=16, scale=1.0):
    rng = np.random.default_rng(seed)
    return [scale * rng.normal(size=(batch, *function.size_in(j))) for j in range(function.n_in())]


def assert_matches_casadi(function, inputs, tol=1e-10):
    """Every output of the translated function equals CasADi's, sample by sample."""
    outputs = translate(function)(*inputs)
    for s in range(inputs[0].shape[0]):
        reference = function(*(value[s] for value in inputs))
        reference = reference if isinstance(reference, (list, tuple)) else [reference]
        for got, ref in zip(outputs, reference):
            ref = np.array(ref)
            np.testing.assert_allclose(got[s], ref, rtol=tol, atol=tol * max(1.0, np.abs(ref).max()))


def test_every_supported_operation_matches_casadi():
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    a = ca.fabs(x) + 0.5  # a positive argument for log, sqrt and pow
    c = ca.tanh(y) * 0.9  # in (-1, 1) for asin and acos
    exprs = [
        x + y,
        x - y,
        x * y,
        x / (a + 1),
        -x,
        2 * x,
        x**2,
        1 / a,
        a**y,
        ca.constpow(a, 2.5),
        ca.sqrt(a),
        ca.exp(x),
        ca.log(a),
        ca.sin(x),
        ca.cos(x),
        ca.tan(c),
        ca.asin(c),
        ca.acos(c),
        ca.atan(x),
        ca.atan2(x, y),
        ca.sinh(x),
        ca.cosh(x),
        ca.tanh(x),
        ca.hypot(x, y),
        ca.fabs(x),
        ca.floor(3 * x),
        ca.ceil(3 * x),
        ca.fmin(x, y),
        ca.fmax(x, y),
        ca.sign(x),
        ca.copysign(x, y),
        x < y,
        x <= y,
        x == ca.floor(x),
        x != y,
        ca.logic_not(x > 0),
        ca.logic_and(x > 0, y > 0),
        ca.logic_or(x > 0, y > 0),
        ca.if_else(x > y, x * y, x - y),
        ca.if_else(x > 0, 1.5, -2.0),
    ]
    f = ca.Function("ops", [x, y], [ca.vertcat(*exprs)])
    ops = {
        name
        for name in dir(ca)
        if name.startswith("OP_") and any(f.instruction_id(k) == getattr(ca, name) for k in range(f.n_instructions()))
    }
    assert ops <= set(SUPPORTED_OPERATIONS)
    inputs = _random_inputs(f, seed=0, batch=64, scale=2.0)
    inputs[0][:4] = np.array([0.0, 1.0, -2.0, 3.0]).reshape(4, 1, 1)  # exact ties for ==, floor, sign
    inputs[1][:4] = inputs[0][:4]
    assert_matches_casadi(f, inputs)


def test_matrix_inputs_outputs_and_structural_zeros():
    x, M = ca.SX.sym("x", 3), ca.SX.sym("M", 3, 2)
    f = ca.Function("mat", [x, M], [ca.mtimes(M.T, x), M.T, ca.SX(2, 2), ca.diag(x)])
    assert_matches_casadi(f, _random_inputs(f, seed=1))


@pytest.mark.parametrize("name", ["pendulum", "pendulum:linear", "nlink:2", "nlink:7", "puma560"])
def test_problem_dynamics_and_costs_match_casadi(name):
    ocp = problems.make(name).ocp(knots=3)
    n, m = ocp.nx, ocp.nu
    rng = np.random.default_rng(2)
    x = rng.uniform(-2, 2, size=(8, n, 1))
    u = rng.uniform(ocp.u_min, ocp.u_max, size=(8, m)).reshape(8, m, 1)
    goal = rng.uniform(-2, 2, size=(8, n, 1))
    assert_matches_casadi(ocp.cost.stage, [x, u, goal])
    assert_matches_casadi(ocp.cost.terminal, [x, goal])
    if name == "puma560":
        pytest.skip("Puma 560 discrete dynamics take ~45 s to compile: see the slow test")
    assert_matches_casadi(ocp.discrete(), [x, u])
    if n <= 4:  # the affine Jacobians of the bigger models are 10⁵ instructions
        assert_matches_casadi(ocp.affine(), [x, u])


@pytest.mark.slow
def test_puma560_dynamics_match_casadi():
    ocp = problems.make("puma560").ocp(knots=3)
    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 2, size=(8, ocp.nx, 1))
    u = rng.uniform(ocp.u_min, ocp.u_max, size=(8, ocp.nu)).reshape(8, ocp.nu, 1)
    assert_matches_casadi(ocp.discrete(), [x, u])


def test_non_smooth_cost_matches_casadi():
    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("x_goal", 2)
    e = x - g
    dead_zone = ca.fmax(ca.fabs(e[0]) - 0.1, 0)
    penalty = ca.if_else(ca.fabs(x[1]) > 1.0, 1e3, 0.0)
    f = ca.Function("l", [x, u, g], [10 * dead_zone + penalty + 0.01 * ca.fabs(u)])
    assert_matches_casadi(f, _random_inputs(f, seed=4, batch=64))


def test_float32_translation_is_close():
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.sin(x[0]) * x[1] + ca.exp(-(x[1] ** 2))])
    (got,) = translate(f, precision="float32")(np.array([[[0.3], [1.2]]]))
    np.testing.assert_allclose(got[0], np.array(f([0.3, 1.2])), rtol=1e-6)


def test_generated_source_is_cached_by_function_hash():
    x = ca.SX.sym("x")
    first = translate(ca.Function("g", [x], [x * 3]))
    again = translate(ca.Function("g", [x], [x * 3]))
    other = translate(ca.Function("g", [x], [x * 4]))
    assert first.path == again.path != other.path
    assert "def evaluate(i0):" in first.path.read_text()


def test_mx_function_is_expanded():
    x = ca.MX.sym("x", 2)
    f = ca.Function("mx", [x], [ca.dot(x, x) + ca.sin(x[0])])
    assert_matches_casadi(f, _random_inputs(f, seed=5))


def test_unsupported_operation_is_named():
    x = ca.SX.sym("x")
    with pytest.raises(ValueError, match="OP_ERF"):
        translate(ca.Function("e", [x], [ca.erf(x)]))


def test_bad_arguments():
    x = ca.SX.sym("x")
    with pytest.raises(TypeError, match="function"):
        translate(lambda v: v)
    with pytest.raises(ValueError, match="precision"):
        translate(ca.Function("f", [x], [x]), precision="float16")
    with pytest.raises(ValueError, match="free variables"):
        translate(ca.Function("f", [x], [x * ca.SX.sym("p")], {"allow_free": True}))
    with pytest.raises(ValueError, match="shape"):
        translate(ca.Function("f", [x], [x]))(np.zeros((3, 2)))


def test_damaged_or_planted_cache_entry_is_rewritten_not_executed(taichi_arch, tmp_path, monkeypatch):
    """A truncated or tampered kernel file is replaced by the fresh translation, with a warning."""
    import sys
    import warnings

    import casadi as ca

    from ocpkit.codegen.kernels import translate as tr

    monkeypatch.setattr(tr, "cache_dir", lambda: tmp_path)
    x = ca.SX.sym("x", 2)
    fn = ca.Function("planted_check", [x], [ca.sin(x[0]) * x[1] + 3.25])
    first = tr.translate(fn)
    text = first.path.read_text()
    for bad in (text[: len(text) // 2], "raise SystemExit('planted code ran')\n"):
        first.path.write_text(bad)
        for name in [n for n in sys.modules if n.startswith("ocpkit_kernel_")]:
            monkeypatch.delitem(sys.modules, name)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            again = tr.translate(fn)
        assert any("differs from its translation" in str(w.message) for w in caught)
        assert again.path.read_text() == text
