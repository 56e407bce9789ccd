import numpy as np
import pytest

from ocpkit.model.parameterization import Parameterization


def test_paper_T5_p3_basis():
    # ΔT = 2: u_0 = U_0, u_1 = ½U_0 + ½U_1, u_2 = U_1, u_3 = ½U_1 + ½U_2, u_4 = U_2 (Section V-D example).
    expected = np.array([[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1]])
    np.testing.assert_array_equal(Parameterization.linear_interp(5, 3).basis, expected)


@pytest.mark.parametrize("T,p", [(50, 2), (50, 7), (100, 5), (13, 13), (7, 1), (1, 1)])
def test_linear_interp_properties(T, p):
    phi = Parameterization.linear_interp(T, p).basis
    np.testing.assert_allclose(phi.sum(axis=1), 1.0, atol=1e-15)  # convex combinations
    assert (phi >= 0).all() and ((phi > 0).sum(axis=1) <= 2).all()  # at most two knots per step
    if p > 1:
        assert phi[0, 0] == 1.0 and phi[-1, -1] == 1.0  # knots at the first and last step
        # Matches the paper's floating-point definition idx1 = floor(k/ΔT), c = (k − idx1 ΔT)/ΔT.
        dT = (T - 1) / (p - 1)
        for k in range(T):
            idx1 = int(np.floor(k / dT + 1e-12))
            c = (k - idx1 * dT) / dT
            assert phi[k, idx1] == pytest.approx(1 - c, abs=1e-12)


def test_p_equal_T_is_identity():
    np.testing.assert_array_equal(Parameterization.linear_interp(9, 9).basis, np.eye(9))
    np.testing.assert_array_equal(Parameterization.make("linear", 9, None).basis, np.eye(9))


def test_zoh_blocks():
    phi = Parameterization.zero_order_hold(10, 3).basis
    assert (phi.sum(axis=1) == 1).all()
    assert phi[:, 0].sum() + phi[:, 1].sum() + phi[:, 2].sum() == 10
    assert (np.diff(phi.argmax(axis=1)) >= 0).all()


def test_u_at_inputs_fit_and_shift():
    par = Parameterization.linear_interp(11, 3)
    U = np.array([[1.0, -1.0], [3.0, 0.0], [-2.0, 2.0]])
    u = par.inputs(U)
    assert u.shape == (11, 2)
    for k in range(11):
        np.testing.assert_allclose(par.u_at(U, k), u[k])
    np.testing.assert_allclose(par.fit(u), U, atol=1e-12)
    # Identity: shifting is an exact advance by one step with the last input held.
    ident = Parameterization.identity(4)
    Ui = np.arange(8.0).reshape(4, 2)
    np.testing.assert_array_equal(ident.shift(Ui), np.r_[Ui[1:], Ui[-1:]])


@pytest.mark.parametrize(
    "args,match",
    [
        ((5, 6), "knots must be <= horizon"),
        ((5, 0), "knots must be >= 1"),
        ((0, 1), "horizon must be >= 1"),
        ((5, 2.5), "knots must be an integer"),
    ],
)
def test_bad_sizes(args, match):
    with pytest.raises((ValueError, TypeError), match=match):
        Parameterization.linear_interp(*args)


def test_bad_kind_and_knot_shape():
    with pytest.raises(ValueError, match="parameterization must be one of"):
        Parameterization.make("spline", 5, 3)
    with pytest.raises(ValueError, match="U must have shape"):
        Parameterization.linear_interp(5, 3).inputs(np.zeros((2, 1)))
