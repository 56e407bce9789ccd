"""Issue 45, item 4: one vocabulary. Every controller's arguments, their meaning and default, are one table
(ocpkit.solvers.methods.ARGUMENTS) that the constructors, the command line and the benchmarks read."""

import inspect
from importlib import import_module

import pytest

from ocpkit import solvers
from ocpkit.cli import _parser, options
from ocpkit.problems import make
from ocpkit.solvers import methods
from ocpkit.solvers.methods import ARGUMENTS, KNOTS, METHODS, Argument


def _signature_defaults(cls) -> dict:
    """Each keyword's default as the class's constructors take it, the subclass's first (a subclass passes the rest
    on in ``**options``)."""
    out = {}
    for klass in cls.__mro__:
        parameters = inspect.signature(klass.__init__).parameters.values()
        for parameter in parameters:
            if parameter.kind is parameter.KEYWORD_ONLY:
                out.setdefault(parameter.name, parameter.default)
        if not any(parameter.kind is parameter.VAR_KEYWORD for parameter in parameters):
            return out


def _cls(name: str):
    pytest.importorskip("taichi") if name in options.SAMPLING else None
    return import_module(f"ocpkit.solvers.{solvers._SOLVERS[name]}").SOLVERS[name]


@pytest.mark.parametrize("name", solvers.names())
def test_every_controller_takes_its_defaults_from_the_table(name):
    """The table names every keyword argument of every registered solver, with the signature's default (None in
    NonlinearMPC's signature: the method's, from METHODS), and nothing else."""
    taken = _signature_defaults(_cls(name))
    table = ARGUMENTS[name]
    per_method = set().union(*METHODS.values()) if name == "ipopt" else set()
    internal = {"num_picked"}  # SamplingMPC's: set by each planner, not the user's
    if name == "rti":
        internal.add("linearization")  # LinearMPC's, refused: RealTimeIteration linearizes along its iterate
    assert set(taken) - internal == set(table) | per_method, name
    for argument, entry in table.items():
        assert taken[argument] == entry.default, (name, argument)
    for argument in per_method:
        assert taken[argument] is None, argument


def test_nonlinear_mpc_takes_each_methods_defaults_from_the_table():
    from ocpkit.solvers.nlp import NonlinearMPC

    ocp = make("pendulum").ocp(horizon=10, knots=3)
    for method, table in METHODS.items():
        ctrl = NonlinearMPC(ocp, method=method)
        resolved = {
            "hessian": ctrl.hessian,
            "max_iter": ctrl.max_iter,
            "dynamics": ctrl.dynamics,
            "linearization": ctrl.linearization,
        }
        for argument, value in resolved.items():
            if argument in table:
                assert value == table[argument].default, (method, argument)


def test_the_default_qp_backend_by_form_is_the_tables():
    from ocpkit.solvers import qp

    assert qp.DEFAULT_QP == methods.QP_BY_FORM


def _actions(parser, command: str) -> dict:
    """option name -> argparse action of ``ocpkit COMMAND``."""
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    return {s[2:]: a for a in sub._actions for s in a.option_strings if s.startswith("--")}


def _solver_defaults(option: str) -> dict:
    """solver -> the table's default of ``option`` there, for the solvers that take it."""
    out = {}
    for name in solvers.names():
        try:
            out[name] = options.default(name, option)
        except KeyError:
            pass
    return out


@pytest.mark.parametrize("option", list(options._SOLVER_OPTIONS))
def test_the_command_lines_solver_options_say_the_tables_defaults(option):
    """A solver's option defaults to None on the command line (given or not: one that does not apply is refused) and
    the solver takes the table's default, which its help names."""
    action = _actions(_parser(), "simulate")[option]
    assert action.default is None
    found = _solver_defaults(option)
    assert found, f"--{option} names no argument of the table"
    text = " ".join(action.help.split())
    for value in set(found.values()) - {None}:
        assert f"default {value}" in text, (option, value, text)
    if None in found.values():  # --qp: by form
        assert all(f"{qp} for {form}" in text for form, qp in methods.QP_BY_FORM.items()), text


def test_the_command_lines_help_and_filled_defaults_come_from_the_table(monkeypatch):
    """Change a default in the table and the command line's help says it, and the configuration it checks options
    against takes it."""
    monkeypatch.setitem(methods.EMPC, "population", Argument("rollouts", 4321))
    monkeypatch.setitem(methods.RTI, "iterations", Argument("iterations", 7))
    monkeypatch.setitem(methods.EMPC, "dynamics", Argument("the rollout model", "nonlinear"))
    monkeypatch.setitem(methods.EMPC, "variant", Argument("the variant", "paper"))
    simulate, export = _actions(_parser(), "simulate"), _actions(_parser(), "export")
    assert "(default 4321)" in simulate["population"].help
    assert "(default 7, the real-time iteration)" in simulate["iterations"].help
    assert export["iterations"].default == 7
    args = _parser().parse_args(["simulate", "pendulum", "--solver", "empc"])
    config = options._Config(args)
    assert (config.dynamics, config.variant) == ("nonlinear", "paper")


def test_the_knots_the_command_line_and_the_benchmarks_take_and_the_apis():
    """The difference, stated once: Problem.ocp's knots=None is traditional MPC (p = T); the command line and the
    benchmarks take KNOTS, and both say so."""
    from ocpkit.benchmarks import nlp, startup
    from ocpkit.model.problem import Problem

    assert options.DEFAULT_KNOTS is KNOTS == startup.KNOTS
    assert inspect.signature(nlp.bench_nlp).parameters["knots"].default == KNOTS
    ocp = make("pendulum").ocp(horizon=12)
    assert ocp.knots == ocp.horizon == 12
    assert "unlike the command line" in Problem.ocp.__doc__
    knots = _actions(_parser(), "simulate")["knots"]
    assert f"default {KNOTS}" in knots.help and "Problem.ocp(knots=None) is traditional MPC" in knots.help


def test_the_benchmarks_default_controllers_are_one_list():
    from ocpkit.benchmarks import nlp, startup

    assert nlp.CONTROLLERS == solvers.BENCHMARKED["nlp"] and startup.CONTROLLERS == solvers.BENCHMARKED["startup"]
    assert set(solvers.BENCHMARKED["nlp"]) | set(solvers.BENCHMARKED["startup"]) - {"exported"} <= set(
        solvers.CONTROLLERS
    )
    text = " ".join(_actions(_parser(), "bench")["controller"].help.split())
    assert all(" ".join(solvers.BENCHMARKED[what]) in text for what in ("nlp", "startup"))
