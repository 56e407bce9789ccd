"""EMPC vs parameterized and traditional convex-solver MPC on N-link robots (paper Section VI-A/B, Figs. 11–13).

Each controller runs the robot from a seeded random start to a seeded random goal, both at rest, at
100 Hz with a 100-step horizon: traditional MPC (large matrix; HPIPM, which reaches the same optimum as
the paper's OSQP several times faster, so the 13-link robot fits the quick run), parameterized MPC with 3
knot points (small matrix, on LinearMPC's default backend, DAQP; the paper used OSQP), EMPC with 3 knot
points and 1 or 3 generations per control step, both preconditioned (the default,
:mod:`ocpkit.solvers.sampling`) and as the paper prints Algorithm 1, and the preconditioned CEM and MPPI on
the same engine. Warm starts are on, as in the paper. Measured: actual cost, its ratio to traditional MPC on
the same start and goal, the final error, the optimization solve time and the MPC solve time of every step. Each
number Section VI-B's text states is printed beside ours, quoted, with a fidelity verdict (:func:`paper_values`).
"""

from __future__ import annotations

import json

import numpy as np

from ocpkit import problems, solvers
from ocpkit.sim import plots
from ocpkit._checks import choice
from ocpkit.codegen.kernels.runtime import current_arch
from ocpkit.export.native import wanted
from ocpkit.sim.metrics import actual_cost
from ocpkit.sim.simulate import Trajectory, simulate
from ocpkit.solvers.methods import EMPC
from ocpkit.runs.store import Store
from ocpkit.runs.study import Study, grid
from ocpkit.studies.calibration import setup_table, stated
from ocpkit.studies.closed_loop import run_record, steady
from ocpkit.sim.plots import number
from ocpkit.studies.evidence import NOT_TESTED, combine, median_claim, on_gpu, paired, quartiles, series, timing
from ocpkit.studies.report import ANSWERED, Claim, answered, markdown_table, section, timing_context, trials_line
from ocpkit.qp.transcription import CondensedQP

NAME = "comparison"
TITLE = "EMPC vs parameterized and traditional MPC on N-link robots (Figs. 11–13)"
HORIZON = 100
REFERENCE = "traditional"
QP = "knots 3 (QP)"
SLIGHTLY = 1.2  # "costs < 20 % more", "slightly worse": a cost ratio below this
PAPER_GPU = "faster from 10 links on, on either GPU (GTX 750 Ti, GTX Titan X; Fig. 12)"
# The sentences of Section VI-B that state a number, quoted: paper_values prints each beside ours.
QUOTES = {
    "extra": "VI-B: 'The increased cost for any robot except the one link however is generally pretty small, accruing "
    "less than 20% more cost when using the convex solver.' (read: above 0, below 20 %)",
    "crossover": "VI-B: 'one iteration EMPC using either of the GPUs we presented has faster optimization solve times "
    "than traditional MPC for ten or more links.'",
    "generations": "VI-B: 'By increasing the number of iterations in EMPC by a factor of three we seem to have also "
    "increased the solve time by about the same factor.'",
    "gpus": "VI-B: 'by using the larger GPU, the solve time is decreased by about three ms, but this three ms decrease "
    "does not seem affected by the number of links.'",
}
# label -> (solver, knot points (None: p = T), options)
CONTROLLERS = {
    REFERENCE: ("qp", None, {"form": "sparse", "qp": "hpipm"}),
    "knots 3 (QP)": ("qp", 3, {"form": "condensed"}),  # LinearMPC's default backend (DAQP), as users run it
    "EMPC 1 gen": ("empc", 3, {"generations": 1}),
    "EMPC 3 gen": ("empc", 3, {"generations": 3}),
    "EMPC 1 gen (paper)": ("empc", 3, {"generations": 1, "variant": "paper"}),
    "EMPC 3 gen (paper)": ("empc", 3, {"generations": 3, "variant": "paper"}),
    "CEM": ("cem", 3, {}),
    "MPPI": ("mppi", 3, {}),
}
SAMPLING = ("empc", "cem", "mppi")
SAMPLE_LINKS = 6  # the robot of the paper's sample joint-angle response
# quick: 5 s runs, not the paper's 10 s (the last 5 s, near the goal, add little cost and half the time: issue 47's
# ten-minute main job); the report says which it ran
SIZES = {
    "quick": {"links": [1, 3, 6, 9, 13], "seeds": 3, "duration": 5.0, "population": 1024, "arch": "cpu"},
    "full": {"links": list(range(1, 14)), "seeds": 10, "duration": 10.0, "population": 1024, "arch": "auto"},
}


def setup(ok):
    """Each setting of the run ``ok`` (its trials): (setting, value, source), from the paper (Sections V-C and VI-A,
    quoted) or ours (why) — the settings a run chooses (duration, robots, seeds, population, device) read from it."""
    robot = problems.make("nlink:1")
    weights = robot.defaults()
    duration = float(ok["duration"].iloc[0])
    sampling = ok["controller"].map(lambda c: CONTROLLERS[c][0] in SAMPLING)
    devices = ", ".join(sorted(set(ok.loc[sampling, "device"]))) or "none run"
    links = sorted(int(n) for n in ok["links"].unique())
    paper_duration = "paper VI-A: 'perform control at 100 Hz for ten seconds'"
    return (
        (
            "robots",
            "planar N-link, each link 1 kg, 0.25 m, workspace perpendicular to gravity",
            "paper V-C: 'Each link is assumed to be the same mass (1 kg) and length (.25m)'",
        ),
        (
            "links run",
            ", ".join(map(str, links)),
            "paper VI-A: 'robots with one to thirteen links'"
            + ("" if links == list(range(1, 14)) else "; ours: a subset"),
        ),
        ("link inertia", "uniform rod, m l²/12 about its centre", "ours: the paper prints none"),
        ("damping b", number(robot.damping), "paper V-C: 'b is a viscous damping coefficient (.01)'"),
        (
            "torque limit",
            f"|τ| ≤ {number(robot.tau_max)} N·m per joint",
            "paper V-C: 'enforce a torque constraint of two Nm at each joint'",
        ),
        (
            "Q, R",
            f"Q = {_identity(weights['Q'])}, R = {_identity(weights['R'])}",
            "ours: the paper prints none ('The same exact cost function and weightings are used for both MPC methods')",
        ),
        (
            "terminal weight",
            f"{number(weights['Q_terminal'][0, 0] / weights['Q'][0, 0])} Q",
            "ours: eq. mpc_problem has no terminal term; nlink's default, which keeps "
            "its 0.5 s horizons from ringing on 7 links (the same for every controller)",
        ),
        (
            "dt, rate, horizon",
            f"0.01 s, 100 Hz, T = {HORIZON}",
            "paper VI-A: 'The horizon used for MPC is 100 time steps with each step representing .01s'",
        ),
        (
            "closed loop",
            f"{number(duration)} s, rest to rest",
            paper_duration
            if duration == 10
            else f"ours: {paper_duration}; a shorter run (its last seconds, near the goal, "
            "add little cost and much time)",
        ),
        (
            "start, goal",
            f"at rest, each angle uniform in [−{number(robot.sample_range, 3)}, {number(robot.sample_range, 3)}] rad",
            "paper VI-A: 'initial and goal positions sampled from a uniform random distribution' (range ours)",
        ),
        ("start/goal pairs", f"{ok['seed'].nunique()} per robot", "ours: the paper says 'several trials'"),
        (
            "knots",
            "3, piecewise linear (parameterized QP and the sampling planners)",
            "paper VI-A: 'The parameterized versions of MPC are using only three knot points'",
        ),
        (
            "traditional MPC",
            "large matrix on HPIPM, warm-started",
            "ours: the paper used OSQP ('We again use OSQP'); HPIPM reaches the same optimum several times faster, so "
            "the 13-link robot fits the quick run",
        ),
        (
            "parameterized QP",
            "small matrix on DAQP, warm-started",
            "ours: the paper used OSQP; DAQP is LinearMPC's default backend, as users run it",
        ),
        (
            "parameterized QP's step",
            _native_links(links),
            "ours: LinearMPC's default (ocpkit.export.native.wanted: on a smaller model the Python step is already "
            "fast); the C step's solve is ~20× shorter, so its times drop where it takes over (what answered each "
            "step: the table of how the steps were answered)",
        ),
        (
            "warm starts",
            "on",
            "paper VI-B: 'the solvers are allowed to warm start themselves with a previous solution'",
        ),
        (
            "EMPC generations",
            "1 and 3 per control step",
            "paper VI-A: 'a variant of EMPC which performs three iterations of the evolutionary algorithm'",
        ),
        (
            "EMPC population, parents",
            f"{int(ok['population'].iloc[0])} rollouts, {EMPC['num_parents'].default} parents",
            "ours: the paper calls numSims and numParents 'tune-able parameters' and prints no values",
        ),
        (
            "EMPC variants",
            "preconditioned (default) and the paper's Algorithm 1 (paper)",
            "ours: Algorithm 1 as printed cannot follow the knot QP's valley on these robots (DESIGN: sampling "
            "planners); both reported",
        ),
        ("CEM, MPPI", "3 knots, preconditioned", "ours: not in the paper; on the same engine for comparison"),
        (
            "device (sampling planners)",
            devices,
            "paper VI-A: 'two different GPUs (an NVIDIA GeForce GTX 750 Ti and an NVIDIA GeForce GTX Titan X)'",
        ),
        (
            "optimization solve time",
            "the solver's own time (EMPC: its generations and preconditioner)",
            "paper VI-A: 'corresponds to the \"run time\" reported by the OSQP solver'",
        ),
        (
            "MPC solve time",
            "optimization + building the QP matrices + linearization",
            "paper VI-A: 'The time taken to construct these matrices plus the optimization solve time'; ours adds "
            "the linearization, which the paper leaves out (its median in the notes)",
        ),
        (
            "actual cost",
            "the MPC cost summed over the closed loop",
            "paper VI-A: 'evaluating the cost function used in MPC over the ten second simulation'",
        ),
        (
            "statistic",
            "per robot: median over start/goal pairs of the per-pair ratio",
            "ours: the paper's figures do not say",
        ),
    )


def _native_links(links) -> str:
    """Which of the robots ``links`` the default LinearMPC runs as a compiled C step (the Python step the others)."""
    native = [n for n in links if wanted(problems.make(f"nlink:{n}").ocp(knots=3, horizon=HORIZON))]
    if not native:
        return "the Python step"
    contiguous = native == list(range(native[0], native[-1] + 1))
    run = f"{native[0]}–{native[-1]}" if contiguous else ", ".join(map(str, native))
    return f"compiled C (the whole step) for {run} links, the Python step for the others"


def _identity(weight) -> str:
    """A multiple of the identity as written: "I", "0.01 I"."""
    w = weight[0, 0]
    return "I" if w == 1 else f"{number(w)} I"


def trial(links: int, controller: str, duration: float, population: int, arch: str, record: bool, seed: int) -> dict:
    """One closed-loop run of ``controller`` on the ``links``-link robot from start/goal ``seed``.

    ``population`` and ``arch`` (Taichi: "cpu", "cuda" or "auto") configure the sampling planners and are
    ignored by the QP controllers; their own random streams are seeded with ``seed`` too. ``record`` adds the trajectory
    (t, x, u, goal) to the result.
    """
    choice(controller, tuple(CONTROLLERS), "controller")
    solver, knots, options = CONTROLLERS[controller]
    if solver in SAMPLING:
        options = {**options, "population": population, "arch": arch, "seed": seed}
    pb = problems.make(f"nlink:{links}")
    ocp = pb.ocp(knots=knots, horizon=HORIZON)
    x0, goal = pb.sample(seed)
    ctrl = solvers.make(solver, ocp, **options)
    steady(ctrl, x0, goal)  # on an empty cache the 3-knot QP's C step lands mid-run otherwise
    traj = simulate(pb.plant(), ctrl, x0, goal, duration)
    result = {
        "actual_cost": actual_cost(traj, ocp),
        "hessian_condition": hessian_condition(pb, ctrl, x0, goal),
        **quartiles("solve", traj.times("solve")),
        **quartiles("total", traj.times("total")),
        "model_median": float(np.median(traj.times("model"))),
        **run_record(traj, ctrl),
        "final_error": float(np.abs(traj.x[-1] - goal).max()),
        "device": current_arch() if solver in SAMPLING else "cpu",
    }
    if record:
        result.update(t=traj.t, x=traj.x, u=traj.u, goal=goal)
    return result


def hessian_condition(problem, ctrl, x0, goal) -> float:
    """Condition number of the 3-knot small matrix QP's Hessian P at the start: how anisotropic the cost
    landscape is that every optimizer, EMPC's isotropic mutations included, has to search."""
    ocp = problem.ocp(knots=3, horizon=HORIZON)
    eigenvalues = np.linalg.eigvalsh(CondensedQP(ocp).build(*ctrl.affine_model(x0, goal, "goal"), x0, goal).P)
    return float(eigenvalues[-1] / eigenvalues[0])


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    trials = grid(
        links=s["links"],
        controller=list(CONTROLLERS),
        duration=s["duration"],
        population=s["population"],
        arch=s["arch"],
        record=False,
        seeds=s["seeds"],
    )
    for t in trials:
        t["record"] = t["links"] == SAMPLE_LINKS and t["seed"] == 0
    return Study(NAME, trial, trials)


def row_arrays(df, row, out_dir) -> dict:
    """The arrays stored with the trial in row ``row`` of a study table ``df`` from ``out_dir``.

    The row is matched to its stored trial by value, since a table column mixes what the trials' parameters
    kept apart: a None among numbers reads back as NaN, an int among floats as a float.
    """
    wanted = {name: df.at[row, name] for name in df.attrs["params"]}

    def same(stored, value) -> bool:
        if stored is None or value is None:
            return stored is None and (value is None or value != value)
        return stored == value

    study = df.at[row, "study"]
    with Store(out_dir) as store:
        for key in store.provenance(study):
            params = json.loads(key)
            if all(same(params.get(name), value) for name, value in wanted.items()):
                return store.arrays(study, params)
    raise KeyError(f"no stored trial of study {study!r} with params {wanted}")


def responses(trajectories: dict, path, *, title: str, joint_names=None):
    """Joint angles against time, one panel per labelled trajectory, goals dotted (the paper's sample responses)."""
    n = len(trajectories)
    # each panel its own y-range: one robot, but controllers that hardly move would be flat on a shared one
    fig, axes = plots.figure(n, 1, figsize=(8, 2.4 * n), sharex=True, squeeze=False)
    for ax, (label, traj) in zip(axes[:, 0], trajectories.items()):
        n_q = traj.x.shape[1] // 2
        for i in range(n_q):
            ax.plot(
                traj.t, traj.x[:, i], color=f"C{i % 10}", lw=1.2, label=joint_names[i] if joint_names else f"q{i + 1}"
            )
            ax.axhline(traj.goal[i], color=f"C{i % 10}", ls=":", lw=0.8)
        ax.set_ylabel("angle [rad]")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    plots.legend_outside(axes[0, 0])  # outside: it hides no trace
    axes[-1, 0].set_xlabel("time [s]")
    plots.set_title(fig, title)  # constrained layout puts it above the panel titles
    return plots.save(fig, path)


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"]
    trials = trials_line(
        df,
        {
            "robots": df["links"].nunique(),
            "controllers": df["controller"].nunique(),
            "start/goal seeds": df["seed"].nunique(),
        },
    )
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    reference = ok[ok["controller"] == REFERENCE].set_index(["links", "seed"])
    keys = list(zip(ok["links"], ok["seed"]))
    ok = ok.assign(
        ratio=[c / reference["actual_cost"].get(k, np.nan) for c, k in zip(ok["actual_cost"], keys)],
        extra_error=[e - reference["final_error"].get(k, np.nan) for e, k in zip(ok["final_error"], keys)],
    )
    order = [c for c in CONTROLLERS if c in set(ok["controller"])]
    seeds = ok["seed"].nunique()
    figs = []
    tables = {"The set-up: each setting, from the paper (quoted) or ours (why)": markdown_table(setup_table(setup(ok)))}

    def per_robot(values, how):
        return ok.pivot_table(index="links", columns="controller", values=values, aggfunc=how)[order]

    ratio, worst = per_robot("ratio", "median"), per_robot("ratio", "max")

    def per_seed(values, controllers):
        return {
            c: [ok.loc[(ok["links"] == links) & (ok["controller"] == c), values].values for links in ratio.index]
            for c in controllers
        }

    # Ratios near 1 and ratios in the hundreds in separate panels, each on its own scale, so none hides another.
    shown = [c for c in order if c != REFERENCE]
    near = [c for c in shown if ratio[c].max() <= 2]
    figs.append(
        plots.lines(
            ratio.index,
            per_seed("ratio", shown),
            out_dir / "comparison_cost_ratio",
            xlabel="number of links",
            ylabel="actual cost / traditional MPC's (ratio)",
            log=True,
            panels=[g for g in (near, [c for c in shown if c not in near]) if g],
            counts=True,
            dodge=True,
            references=[(1.0, "1: traditional MPC")],
            spread_label=f"shaded: quartiles over {seeds} start/goal pairs",
            title=f"Actual cost relative to traditional MPC ({seeds} start/goal pairs per robot; line: median)",
        )
    )
    tables[f"Median actual cost ratio to traditional MPC over {seeds} start/goal pairs"] = markdown_table(ratio)
    tables["Worst (largest) actual cost ratio to traditional MPC over the start/goal pairs"] = markdown_table(worst)
    final = per_robot("final_error", "median")
    tables["Median final error max |x − x_goal| at the end of the run [rad, rad/s]"] = markdown_table(final)
    extra = per_robot("extra_error", "max")
    tables["Worst final error above traditional MPC's on the same start/goal [rad, rad/s]"] = markdown_table(extra)
    for metric, what in (("solve_median", "optimization solve time"), ("total_median", "MPC solve time")):
        med = per_robot(metric, "median") * 1e3
        figs.append(
            plots.lines(
                med.index,
                {c: [1e3 * v for v in s] for c, s in per_seed(metric, order).items()},
                out_dir / f"comparison_{metric}",
                xlabel="number of links",
                ylabel=f"per-step median {what} [ms]",
                log=True,
                counts=True,
                dodge=True,
                spread_label=f"shaded: quartiles over {seeds} start/goal pairs",
                title=f"Median {what} per control step (line: median over the runs)",
            )
        )
        tables[f"Median over trials of the per-step median {what} [ms]"] = markdown_table(med)
    sample = ok[ok["record"].astype(bool)]
    if len(sample):
        trajs = {}
        for row in sample.index:
            a = row_arrays(df, row, out_dir)
            trajs[df.at[row, "controller"]] = Trajectory(t=a["t"], x=a["x"], u=a["u"], goal=a["goal"])
        trajs = {c: trajs[c] for c in order if c in trajs}
        figs.insert(
            0,
            responses(
                trajs,
                out_dir / "comparison_sample_response",
                title=f"{SAMPLE_LINKS}-link robot, start/goal seed 0: joint angles (dotted: goals)",
            ),
        )
    stated_values = paper_values(ok)
    tables[
        "The paper's Section VI-B numbers beside ours (quoted; verdict: within the paper's printed precision or not)"
    ] = markdown_table(stated_values)
    tables[ANSWERED] = answered(ok)
    return section(
        TITLE,
        figs,
        tables,
        trials=trials + " " + timing_context(ok),
        notes=_notes(ok, ratio, worst, final, extra, order) + [_stated_note(stated_values, ratio.index)],
        claims=claims(ok),
    )


def paper_values(ok):
    """The numbers Section VI-B's text states (:data:`QUOTES`) beside ours, each with the difference and a fidelity
    verdict (:func:`ocpkit.studies.calibration.stated`). The solve-time values are GPU times: where EMPC ran on no GPU
    ours is printed and the verdict says why it is not tested (and where the load made timings unreliable, so)."""
    robots = sorted(ok["links"].unique())
    present = set(ok["controller"])
    rows, timed, untested = [], [], {}
    if {QP, REFERENCE} <= present:
        extra = [
            100 * (np.median(paired(*(series(ok, "actual_cost", controller=c, links=n) for c in (QP, REFERENCE)))) - 1)
            for n in robots
            if n > 1
        ]
        what = f"{QP}: largest median extra cost over traditional MPC beyond one link [%]"
        rows.append((what, QUOTES["extra"], (0, 20), float(max(extra)) if extra else np.nan))

    def robot_median(controller, links):
        return ok.loc[(ok["controller"] == controller) & (ok["links"] == links), "solve_median"].median()

    for one, three in (("EMPC 1 gen", "EMPC 3 gen"), ("EMPC 1 gen (paper)", "EMPC 3 gen (paper)")):
        empc = ok[ok["controller"] == one]
        if empc.empty or REFERENCE not in present:
            continue
        faster = [robot_median(one, n) < robot_median(REFERENCE, n) for n in robots]
        first = next((float(n) for i, n in enumerate(robots) if all(faster[i:])), np.inf)
        what = f"{one}: fewest links from which it solves faster than traditional MPC (inf: not at the most links)"
        variant = [(what, QUOTES["crossover"], 10, first)]
        factor = paired(*(series(ok, "solve_median", ["links", "seed"], controller=c) for c in (three, one)))
        if factor.size:
            what = f"{three} / {one}: median optimization solve time ratio"
            variant.append((what, QUOTES["generations"], 3, float(np.median(factor))))
        rows += variant
        timed += [r[0] for r in variant]
        if not on_gpu(empc["device"]):
            devices = ", ".join(sorted(set(empc["device"])))
            untested.update(
                {r[0]: f"not tested: EMPC ran on {devices}; the paper's times are GPU times" for r in variant}
            )
    rows.append(("solve time saved by the larger GPU [ms]", QUOTES["gpus"], 3, np.nan))
    untested[rows[-1][0]] = (
        "not tested: needs two GPUs (the paper's GTX 750 Ti and GTX Titan X); ours ran on one device"
    )
    table = stated(rows)
    for what in timed:
        table.at[what, "verdict"] = timing(table.at[what, "verdict"], ok["load"])
    for what, reason in untested.items():
        table.at[what, "verdict"] = reason
    return table


def _stated_note(table, robots) -> str:
    """How many of Section VI-B's numbers were tested here, and how many of those lie within the paper's precision."""
    tested = table[~table["verdict"].str.startswith(("not tested", "not measured", "unreliable"))]
    return (
        f"Section VI-B's numbers: {int(tested['verdict'].str.startswith('within').sum())} of {len(tested)} tested here "
        f"lie within the paper's printed precision; {len(table) - len(tested)} not tested (why: in the table). The "
        f"crossover is read on the robots run: {', '.join(map(str, robots))} links."
    )


def _notes(ok, ratio, worst, final, extra, order) -> list:
    """What ran where, and how the sampling planners did (median and worst over the seeds, final errors)."""
    model = ok.groupby("links")["model_median"].median()
    sampling = ok["controller"].map(lambda c: CONTROLLERS[c][0] in SAMPLING)
    notes = [
        f"Runs: {number(ok['duration'].iloc[0])} s at 100 Hz (the paper: 10 s), horizon {HORIZON}; "
        "traditional MPC on HPIPM; "
        f"sampling planners' population {ok['population'].iloc[0]} on "
        + ", ".join(sorted(set(ok.loc[sampling, "device"])))
        + ".",
        f"Fallback steps (solver failures): {int(ok['fallbacks'].sum())} in {len(ok)} runs (by controller and "
        "cause in the last table).",
        "The MPC solve time includes the linearization, which the paper leaves out (median "
        + ", ".join(f"{links} links: {number(1e3 * v, 2)} ms" for links, v in model.items())
        + "); the sampling planners' optimization time includes their preconditioner (factor, Newton "
        "candidate) but not its QP build.",
    ]
    for c in order:
        if CONTROLLERS[c][0] in SAMPLING:
            notes.append(
                f"{c}: median cost ratio {_per_robot(ratio[c].dropna())}; worst {number(worst[c].max())}; "
                f"median final error at most {number(final[c].max(), 2)}, at most "
                f"{number(extra[c].max(), 2)} above traditional MPC's on the same start/goal."
            )
    condition = ok.groupby("links")["hessian_condition"].median()
    notes.append(
        "The landscape the planners search: median condition number of the 3-knot QP Hessian at the start, "
        + ", ".join(f"{links} links: {number(v, 2)}" for links, v in condition.items())
        + ". The paper's mutations add the same-sized noise to every input, so where the Hessian is this "
        "anisotropic (light distal links move far for a small torque) most children land far uphill; the "
        "preconditioned planners draw their noise with covariance ∝ P⁻¹ and evaluate the QP's "
        "box-constrained optimum (the Newton candidate) in every population, so with affine dynamics and "
        "the quadratic cost they cannot do worse than the QP except through the linearization both share."
    )
    return notes


def claims(ok) -> list:
    """The paper's Section VI-B claims, each decided on per-seed cost ratios (the same start and goal)."""
    out = []

    def ratios(a, b, **links):
        """Per (links, seed): cost of a / cost of b (``links=`` one robot)."""
        return paired(*(series(ok, "actual_cost", ["links", "seed"], controller=c, **links) for c in (a, b)))

    robots = sorted(ok["links"].unique())
    present = set(ok["controller"])
    if {QP, REFERENCE} <= present:
        parts = {
            links: median_claim(ratios(QP, REFERENCE, links=links), SLIGHTLY, "<") for links in robots if links > 1
        }
        out.append(
            Claim(
                f"Parameterized QP MPC costs < {number(100 * (SLIGHTLY - 1))} % more than traditional beyond one link",
                "per seed, cost ratio to traditional MPC, per robot",
                combine(v for v, _ in parts.values()),
                _by_robot(parts),
                paper="< 20 % more; below 1 for the most links (Fig. 11)",
            )
        )
    for c in ("EMPC 1 gen", "EMPC 1 gen (paper)"):
        if {c, QP} <= present:
            parts = {links: median_claim(ratios(c, QP, links=links), SLIGHTLY, "<=") for links in robots}
            wins = ok.loc[ok["controller"] == c, "child_win_rate"].median()
            out.append(
                Claim(
                    f"EMPC is slightly worse than the parameterized QP ({c})",
                    f"per seed, cost ratio to the 3-knot QP ≤ {number(SLIGHTLY)} (at most slightly worse), "
                    "per robot; "
                    f"median child win rate {number(100 * wins, 3)} %"
                    + (" (the plan is the seeds': this row measures the QP)" if wins == 0 else ""),
                    combine(v for v, _ in parts.values()),
                    _by_robot(parts),
                )
            )
    for one, three in (("EMPC 1 gen", "EMPC 3 gen"), ("EMPC 1 gen (paper)", "EMPC 3 gen (paper)")):
        if {one, three} <= present:
            r = ratios(three, one)
            v, e = median_claim(r, 1.0, "<")
            out.append(
                Claim(
                    f"More generations bring EMPC's cost down ({three} vs {one})",
                    f"per robot and seed, cost with 3 / with 1 generation < 1: lower in {int((r < 1).sum())}, "
                    f"equal in {int((r == 1).sum())}, higher in {int((r > 1).sum())} of {len(r)}",
                    v,
                    e,
                )
            )
    if {"EMPC 1 gen", REFERENCE} <= present:
        claim = "One-generation EMPC solves faster than traditional MPC from 10 links on (GPU)"
        empc = ok[ok["controller"] == "EMPC 1 gen"]
        if not on_gpu(empc["device"]):
            out.append(
                Claim(
                    claim,
                    f"EMPC ran on {', '.join(sorted(set(empc['device'])))} only",
                    NOT_TESTED,
                    "needs a GPU",
                    paper=PAPER_GPU,
                )
            )
        else:
            parts = {
                links: median_claim(
                    paired(*(series(ok, "solve_median", controller=c, links=links) for c in ("EMPC 1 gen", REFERENCE))),
                    1.0,
                    "<",
                )
                for links in robots
                if links >= 10
            }
            out.append(
                Claim(
                    claim,
                    "per seed, median solve time ratio EMPC / traditional < 1, per robot",
                    timing(combine(v for v, _ in parts.values()), ok["load"]),
                    _by_robot(parts),
                    paper=PAPER_GPU,
                )
            )
    return out


def _by_robot(parts) -> str:
    return "; ".join(f"{links} links {e}" for links, (_, e) in parts.items())


def _per_robot(series) -> str:
    return ", ".join(f"{links} links {number(v, 3)}" for links, v in series.items())
