"""`ocpkit bench NAME`: a benchmark of :mod:`ocpkit.benchmarks`, with the options the command line gives it."""

from __future__ import annotations

from ocpkit import problems

# `ocpkit bench NAME`: module in ocpkit.benchmarks, function, keyword arguments of --quick.
BENCHMARKS = {
    "qp": ("qp", "bench_qp", {"problems": ("pendulum:linear", "pendulum", "nlink:3"), "samples": 10}),
    "empc": ("empc", "bench_empc", {"links": (1, 7, 13), "populations": (256, 1024), "horizons": (100,)}),
    "export": ("export", "bench_export", {"problems": ["pendulum", "nlink:2", "nlink:3"]}),
    "model": ("model", "bench_model", {"links": (1, 7, 13), "states": 5}),
    "nlp": ("nlp", "bench_nlp", {"problems": ["pendulum", "nlink:2", "nlink:3"], "samples": 1, "steps": 5}),
    "faults": ("faults", "bench_faults", {}),
    "step": ("step", "bench_step", {"links": (1, 7, 13), "steps": 10}),
    "task": ("task", "bench_task", {"problems": ("panda",), "steps": 100, "seeds": 1}),
    "sensitivities": ("sensitivities", "bench_sensitivities", {"problems": ("puma560", "nlink:7"), "repeats": 50}),
    "startup": ("startup", "bench_startup", {"problems": ("nlink:13",), "controllers": ("qp", "rti", "empc")}),
    "peers": ("peers", "bench_peers", {"problems": ["nlink:3"], "horizon": 20, "samples": 1, "steps": 5}),
}
# Benchmarks that take --problem (their `problems` argument).
PROBLEM_BENCHMARKS = ("qp", "export", "nlp", "task", "startup", "peers")
# `ocpkit bench --help`: what each benchmark prints.
HELP = (
    "qp, empc, export, model, nlp, faults, step, task, sensitivities, startup: see ocpkit.benchmarks; "
    "peers: the like-for-like tables of acados (SQP-RTI p = T and coarse grid, SQP converged), Crocoddyl (FDDP one "
    "iteration a step and converged) and ocpkit (RTI C step p = T and 5 knots, IPOPT): Puma 560, Panda, nlink:13, "
    "T = 50, RK4 and Euler, ms a step and closed-loop cost / IPOPT's, 5 seeds from 100 (never tuned on) x 50 steps "
    "(--seed moves them, --problem and --integrator narrow the grid; 5-10 min on 2 idle cores once built, the "
    "first run compiles acados' solvers for minutes more; a peer not installed is skipped with one line)"
)


def bench_command(args):
    """`ocpkit bench NAME`: the benchmark with its --quick sizes or the options given."""
    import importlib

    module, function, quick = BENCHMARKS[args.what]
    options = {k: getattr(args, k) for k in ("arch", "precision") if getattr(args, k) is not None}
    if options and args.what != "empc":
        raise ValueError(f"--{next(iter(options))} applies to `ocpkit bench empc` only")
    if args.busy is not None:
        if args.what != "step":
            raise ValueError("--busy applies to `ocpkit bench step` only")
        if args.busy < 0:
            raise ValueError(f"--busy must be >= 0, got {args.busy}")
        options["busy"] = args.busy
    # option: {benchmark: (its keyword, type)}
    chosen = {
        "controller": {"nlp": ("controllers", tuple), "startup": ("controllers", tuple)},
        "integrator": {"nlp": ("integrator", str), "peers": ("integrators", lambda name: (name,))},
        "seed": {"nlp": ("first_seed", int), "startup": ("seed", int), "peers": ("first_seed", int)},
    }
    for option, where in chosen.items():
        value = getattr(args, option)
        if value is not None:
            if args.what not in where:
                raise ValueError(f"--{option} applies to `ocpkit bench {'|'.join(where)}` only")
            keyword, kind = where[args.what]
            options[keyword] = kind(value)
    kwargs = dict(quick) if args.quick else {}
    if args.problem:
        if args.what not in PROBLEM_BENCHMARKS:
            raise ValueError(f"--problem applies to `ocpkit bench {'|'.join(PROBLEM_BENCHMARKS)}` only")
        for spec in args.problem:
            problems.make(spec)  # a bad spec fails before any benchmark starts
        kwargs["problems"] = list(args.problem)
    bench = getattr(importlib.import_module(f"ocpkit.benchmarks.{module}"), function)
    bench(**kwargs, **options)
    return 0
