"""The acados peer: installed beside the project's CasADi without replacing it, the same OCP as ocpkit's, SQP at
IPOPT's optimum, SQP-RTI in closed loop on both grids, and its tables in ``ocpkit bench nlp``. Every check that
loads acados runs in a process of its own (``acados_install.isolated``): loaded into the test process, its HPIPM and
BLASFEO crashed a later test of CasADi's HPIPM plugin."""

import subprocess
import sys

import numpy as np
import pytest

from ocpkit import problems as registry
from ocpkit.benchmarks import acados_install
from ocpkit.benchmarks.crocoddyl_peer import objective, rollout
from ocpkit.benchmarks.nlp import bench_nlp
from ocpkit.solvers.nlp import NonlinearMPC

MISSING = acados_install.missing()
needs_acados = pytest.mark.skipif(MISSING is not None, reason=f"acados peer unavailable: {MISSING}")


def test_absent_peer_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setenv(acados_install.ENV, str(tmp_path))
    monkeypatch.delitem(sys.modules, "acados_template", raising=False)
    assert acados_install.INSTALL in acados_install.missing()
    with pytest.raises(ImportError, match=r"python -m ocpkit\.benchmarks\.acados_install"):
        bench_nlp(["nlink:2"], samples=1, steps=2, controllers=("acados",), echo=False)


@needs_acados
def test_project_casadi_stays_ours():
    """The wheel's own CasADi 3.7 (built for CPython 3.12) lies in the peer's folder, never on the path: after the
    peer is set up, ``import casadi`` is still the project's."""
    import casadi

    assert (acados_install.folder() / "casadi").is_dir()
    code = (
        "from ocpkit.benchmarks.acados_install import require; require(); import casadi, acados_template; "
        "print(casadi.__version__, casadi.__file__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    version, path = out.strip().splitlines()[-1].split(" ", 1)
    assert (version, path) == (casadi.__version__, casadi.__file__)
    assert str(acados_install.folder()) not in path


def optimum(spec, dynamics, integrator, seed=0):
    from ocpkit.benchmarks.acados_peer import AcadosMPC

    prob = registry.make(spec)
    ocp = prob.ocp(knots=None, horizon=50, integrator=integrator)
    x0, goal = prob.sample(seed)
    ours, theirs = NonlinearMPC(ocp).solve(x0, goal), AcadosMPC(ocp, dynamics=dynamics, nlp="sqp").solve(x0, goal)
    assert ours.ok and theirs.ok, (ours.raw_status, theirs.raw_status)
    assert theirs.iterations > 1
    costs = [objective(ocp, goal, rollout(ocp, x0, s.knots), s.knots) for s in (ours, theirs)]
    return ocp, costs, ours, theirs


@needs_acados
@pytest.mark.parametrize(
    "spec, dynamics, integrator",
    [("nlink:3", "erk", "rk4"), ("nlink:3", "discrete", "rk4"), ("nlink:3", "discrete", "euler")],
)
def test_sqp_reaches_ipopts_optimum(spec, dynamics, integrator):
    """Same OCP, same integrator: acados' converged SQP plan is IPOPT's p = T optimum (3e-14 to 3e-12 relative
    cost measured), input bounds active."""
    acados_install.isolated(_sqp_reaches_ipopts_optimum, spec, dynamics, integrator)


def _sqp_reaches_ipopts_optimum(spec, dynamics, integrator):
    ocp, costs, ours, theirs = optimum(spec, dynamics, integrator)
    assert costs[1] == pytest.approx(costs[0], rel=1e-6)
    assert np.isclose(np.abs(theirs.knots), ocp.u_max).any()
    np.testing.assert_allclose(theirs.knots, ours.knots, atol=1e-4 * ocp.u_max[0])


@needs_acados
def test_sqp_reaches_ipopts_optimum_on_the_puma():
    """The Puma 560 (acados' ERK generated from ocpkit's rigid-body model: 20 s to build, once): 3e-14 measured."""
    costs = acados_install.isolated(_costs, "puma560", "erk", "rk4")
    assert costs[1] == pytest.approx(costs[0], rel=1e-6)


def _costs(spec, dynamics, integrator):
    return optimum(spec, dynamics, integrator)[1]


@needs_acados
def test_rti_closed_loop_on_both_grids():
    """SQP-RTI at p = T and on the coarse grid (N = p intervals of T/p steps, the zero-order hold's knots) runs a
    closed loop without fallbacks; the coarse grid's plan is p inputs held T/p steps each."""
    acados_install.isolated(_rti_closed_loop_on_both_grids)


def _rti_closed_loop_on_both_grids():
    from ocpkit.benchmarks.acados_peer import AcadosMPC, grid
    from ocpkit.sim.simulate import simulate

    prob = registry.make("nlink:3")
    x0, goal = prob.sample(1)
    for ocp, N in ((prob.ocp(knots=None, horizon=20), 20), (prob.ocp(knots=4, horizon=20, parameterization="zoh"), 4)):
        ctrl = AcadosMPC(ocp)
        assert grid(ocp) == (N, 20 // N)
        traj = simulate(prob.plant(), ctrl, x0, goal, 0.3)
        assert traj.fallbacks == 0 and all(s.ok for s in traj.solutions)
        assert traj.solutions[-1].knots.shape == (N, ocp.nu)
        assert 0 < traj.solutions[-1].times["acados"] <= traj.solutions[-1].times["solve"]
        assert np.abs(traj.x[-1] - goal).max() < np.abs(x0 - goal).max()
    with pytest.raises(ValueError, match="divide the horizon"):
        AcadosMPC(prob.ocp(knots=3, horizon=20, parameterization="zoh"))
    with pytest.raises(ValueError, match="zero-order hold"):
        AcadosMPC(prob.ocp(knots=4, horizon=20))
    with pytest.raises(ValueError, match="discrete"):
        AcadosMPC(prob.ocp(knots=None, horizon=20, integrator="euler"), dynamics="erk")


@needs_acados
def test_bench_nlp_acados_tables(capfd):
    """The tables come from a process of their own (the child's output reaches the terminal: capfd, not capsys), and
    this one never loads acados."""
    rows = bench_nlp(["nlink:2"], samples=1, steps=3, horizon=10, knots=2, controllers=("acados",), integrator="rk4")
    out = capfd.readouterr().out
    assert not acados_install.loaded()
    assert "nlink:2, rk4, p = T" in out and "nlink:2, rk4, knots" in out and "load" in out
    tables = {(r["table"], r["controller"]): r for r in rows}
    assert set(tables) == {
        ("p = T", "ipopt"),
        ("p = T", "rti"),
        ("p = T", "rti sparse"),
        ("p = T", "acados erk"),
        ("p = T", "acados sqp"),
        ("knots", "rti linear"),
        ("knots", "rti zoh"),
        ("knots", "acados erk"),
    }
    assert tables[("p = T", "acados erk")]["grid"] == "N=10" and tables[("knots", "acados erk")]["grid"] == "N=2"
    assert all(r["fallbacks"] == 0 and np.isfinite(r["cost_ratio"]) for r in rows)
    assert tables[("p = T", "acados sqp")]["cost_ratio"] == pytest.approx(1.0, rel=1e-3)
    # RTI's sparse QP at p = T beside its default, the condensed QP: one closed loop to the backends' tolerance
    rti, sparse = tables[("p = T", "rti")], tables[("p = T", "rti sparse")]
    assert sparse["cost_ratio"] == pytest.approx(rti["cost_ratio"], rel=1e-8)


@needs_acados
def test_casadis_hpipm_and_acados_refuse_to_share_a_process():
    """Loaded together they crashed (a segmentation fault): each refuses a process where the other is loaded."""
    acados_install.isolated(_hpipm_after_acados)
    acados_install.isolated(_acados_after_hpipm)


def _hpipm_after_acados():
    from ocpkit.solvers.qp import LinearMPC

    acados_install.require()
    prob = registry.make("nlink:2")
    x0, goal = prob.sample(0)
    sol = LinearMPC(prob.ocp(knots=None, horizon=10), form="sparse", qp="hpipm").solve(x0, goal)
    assert not sol.ok and "acados" in sol.raw_status, sol.raw_status


def _acados_after_hpipm():
    from ocpkit.solvers.qp import LinearMPC

    prob = registry.make("nlink:2")
    x0, goal = prob.sample(0)
    assert LinearMPC(prob.ocp(knots=None, horizon=10), form="sparse", qp="hpipm").solve(x0, goal).ok
    assert acados_install.casadi_hpipm_loaded()
    with pytest.raises(RuntimeError, match="process of its own"):
        acados_install.require()


@needs_acados
def test_bench_step_acados_rows():
    """`ocpkit bench step`'s acados rows: its QP on ocpkit's affine model at p = T gives the first input of
    ocpkit's traditional QP (1e-8 measured), and on the coarse grid of the knots runs; both from a process of their
    own (this one has CasADi's HPIPM loaded by the traditional row)."""
    from ocpkit.benchmarks.step import bench_step

    lines = []
    rows = bench_step(links=(2,), horizons=(10,), knots=2, steps=4, rounds=1, busy=0, fresh=0, out=lines.append)
    by = {r["solver"]: r for r in rows}
    same, coarse = by["acados p=T hpipm (SQP-RTI: its QP)"], by["acados coarse grid N=2 hpipm (SQP-RTI)"]
    assert same["status"] == coarse["status"] == "success"
    assert same["u0_diff"] < 1e-6 and same["iterations"] >= 1
    assert np.isfinite(coarse["u0_diff"]) and coarse["median"] > 0
    assert not acados_install.loaded()


def test_bench_step_without_acados_says_so(tmp_path, monkeypatch):
    from ocpkit.benchmarks.step import bench_step

    monkeypatch.setenv(acados_install.ENV, str(tmp_path))
    lines = []
    rows = bench_step(links=(1,), horizons=(10,), knots=2, steps=2, rounds=1, busy=0, fresh=0, out=lines.append)
    assert lines[0].startswith("no acados rows: acados not installed")
    assert not any(r["solver"].startswith("acados") for r in rows)
