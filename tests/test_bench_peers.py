"""`ocpkit bench peers` (issue 48's like-for-like tables): p = T rows and knot rows in tables of their own, a peer not
installed skipped with one line, Crocoddyl's FDDP one iteration a step and converged where it is importable, and
acados in `ocpkit bench step` (the linear case) where installed."""

import argparse

import numpy as np
import pytest

from ocpkit.benchmarks import acados_install, crocoddyl_peer, peers
from ocpkit.cli.bench import bench_command

ACADOS = acados_install.missing()
CROCODDYL = peers._crocoddyl_missing()


def test_tables_apart_and_absent_peers_said(capfd):
    """Whatever is installed: every knot row (p inputs: ocpkit's knots and blocks, acados' coarse grid) sits in the
    knots table, every p = T row in the p = T table, printed in that order; IPOPT is the reference (ratio 1); the
    seeds start at FIRST_SEED; a peer not installed gets one line and no row."""
    rows = peers.bench_peers(["nlink:2"], ("rk4",), horizon=10, knots=2, samples=1, steps=3)
    out = capfd.readouterr().out
    tables = {r["table"]: set() for r in rows}
    for r in rows:
        tables[r["table"]].add(r["controller"])
    expected = {"p = T": {"ipopt", "ipopt 1e-6", "rti", "rti hpipm"}, "knots": {"rti 2 knots", "rti 2 blocks"}}
    if ACADOS is None:
        expected["p = T"] |= {"acados rti erk", "acados sqp"}
        expected["knots"] |= {"acados rti erk"}
    else:
        assert f"no acados rows: {ACADOS}" in out
    if CROCODDYL is None:
        expected["p = T"] |= {"fddp 1 it", "fddp"}
    else:
        assert f"no crocoddyl rows: {CROCODDYL}" in out
    assert tables == expected
    assert all(
        r["grid"] == ("p=2" if r["controller"].startswith("rti 2") else "N=2") for r in rows if r["table"] == "knots"
    )
    assert all(r["grid"] == "N=10" for r in rows if r["table"] == "p = T")
    assert "seed from 100 x 3 steps" in out and "load" in out
    p_t, knots = out.index("\np = T:"), out.index("\nknots:")
    assert p_t < knots and "p=2" not in out[p_t:knots] and "N=10" not in out[knots:]
    by = {(r["table"], r["controller"]): r for r in rows}
    assert by[("p = T", "ipopt")]["cost_ratio"] == 1.0
    assert all(r["fallbacks"] == 0 and np.isfinite(r["cost_ratio"]) and r["steps"] == 3 for r in rows)
    assert by[("p = T", "rti")]["iterations"] == 1.0
    assert all(r["worst_ms"] >= r["step_ms"] and r["max_ms"] >= r["worst_ms"] for r in rows)


def test_knots_must_divide_the_horizon():
    with pytest.raises(ValueError, match="divide the horizon"):
        peers.bench_peers(["nlink:2"], horizon=10, knots=3, echo=False)


def test_cli_narrows_the_must_show(monkeypatch):
    """`ocpkit bench peers --problem … --integrator … --seed …` reaches bench_peers as its arguments; --quick is
    a small grid."""
    seen = {}
    monkeypatch.setattr(peers, "bench_peers", lambda **kwargs: seen.update(kwargs))
    args = argparse.Namespace(
        what="peers", quick=False, arch=None, precision=None, busy=None, controller=None,
        problem=["panda"], integrator="euler", seed=200,
    )  # fmt: skip
    assert bench_command(args) == 0
    assert seen == {"problems": ["panda"], "integrators": ("euler",), "first_seed": 200}
    seen.clear()
    assert bench_command(argparse.Namespace(**{**vars(args), "problem": None, "integrator": None, "seed": None})) == 0
    assert seen == {}  # the must-show's own defaults
    seen.clear()
    bench_command(
        argparse.Namespace(**{**vars(args), "quick": True, "problem": None, "integrator": None, "seed": None})
    )
    assert seen["samples"] == 1 and seen["steps"] <= 5


needs_crocoddyl = pytest.mark.skipif(CROCODDYL is not None, reason=f"Crocoddyl peer unavailable: {CROCODDYL}")


@needs_crocoddyl
def test_crocoddyl_rows_one_iteration_and_converged():
    """FDDP's rows: one iteration a step (its RTI analogue, never a fallback) and converged to th_stop 1e-12, whose
    closed loop is IPOPT's (the same optimum every step), with ‖Q_u‖∞ ≤ 1e-6 at exit."""
    rows = peers.bench_peers(["nlink:2"], ("rk4",), horizon=10, knots=2, samples=2, steps=5, echo=False)
    by = {r["controller"]: r for r in rows if r["table"] == "p = T"}
    one, full = by["fddp 1 it"], by["fddp"]
    assert one["iterations"] == 1.0 and one["fallbacks"] == 0 and one["iteration_ms"] == one["step_ms"]
    assert full["iterations"] > 1.0 and full["fallbacks"] == 0
    assert full["cost_ratio"] == pytest.approx(1.0, abs=1e-5) and full["worst_ratio"] == pytest.approx(1.0, abs=1e-5)
    prob = crocoddyl_peer.undamped("nlink:3")
    ocp = prob.ocp(knots=None, horizon=20)
    x0, goal = prob.sample(100)
    ctrl = crocoddyl_peer.CrocoddylMPC(prob, ocp, th_stop=crocoddyl_peer.TH_STOP_KKT)
    assert ctrl.solve(x0, goal).ok
    assert max(np.abs(q).max() for q in ctrl.solver.Qu if len(q)) <= peers.KKT_TOL
