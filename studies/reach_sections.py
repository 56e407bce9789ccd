"""The reach study's report sections (:mod:`ocpkit.studies.reach`): reaching past a sphere (outcomes, costs over
IPOPT's, causes, figures and claims per robot) and the keep-out ball with a fair baseline."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ocpkit.model.task import REACH_OBSTACLE_WEIGHT
from ocpkit.sim import plots
from ocpkit.sim.plots import number
from ocpkit.sim.simulate import MOVING, STALLED, summed_tallies
from ocpkit.studies import keepout
from ocpkit.studies.evidence import NOT_TESTED, Interval, combine, decide, every, median_claim, proportion
from ocpkit.studies.reach_trials import (
    CEM,
    CONTROLLERS,
    EMPC,
    HINGE_WEIGHT,
    IPOPT,
    IPOPT_BUDGET,
    K_EMPC_HINGE,
    K_EMPC_SQUARED,
    K_IPOPT,
    K_RTI,
    KEEPOUT_CONTROLLERS,
    KNOTS,
    MARGIN,
    MPPI,
    OBSTACLE_RADIUS,
    QP,
    QP_TRAJ,
    ROBOTS,
    RTI,
)
from ocpkit.studies.report import Claim, markdown_table

GRADIENT = (IPOPT, RTI, QP, QP_TRAJ)


def ratios(ok: pd.DataFrame) -> pd.DataFrame:
    """Actual cost over IPOPT's, per robot, seed and controller, on the seeds where IPOPT succeeds."""
    rows = []
    for robot in ROBOTS:
        r = ok[ok["scenario"] == robot]
        ref = r[(r["controller"] == IPOPT) & (r["success"] == True)].set_index("seed")["actual_cost"]  # noqa: E712
        for _, row in r[r["seed"].isin(ref.index)].iterrows():
            rows.append(
                {
                    "scenario": robot,
                    "seed": row["seed"],
                    "controller": row["controller"],
                    "ratio": row["actual_cost"] / ref[row["seed"]],
                    "success": bool(row["success"]),
                }
            )
    return pd.DataFrame(rows, columns=["scenario", "seed", "controller", "ratio", "success"])


def _outcome(row) -> str:
    """success, collision, or (no collision, not reached) the loop's verdict: stalled or moving."""
    if row["success"]:
        return "success"
    if row["collision_steps"] > 0:
        return "collision"
    return row["verdict"]


def reach_section(r, out_dir, figs, tables, notes, claims):
    """The reach trials ``r`` into the report: their figures, tables, notes and claims appended to those given."""
    r = r.copy()
    r["outcome"] = r.apply(_outcome, axis=1)
    order = [c for c in CONTROLLERS if c in set(r["controller"])]
    robots = [b for b in ROBOTS if b in set(r["scenario"])]
    rat = ratios(r)
    summary = []
    for robot in robots:
        for c in order:
            g = r[(r["scenario"] == robot) & (r["controller"] == c)]
            if g.empty:
                continue
            q = rat[(rat["scenario"] == robot) & (rat["controller"] == c)]["ratio"]
            summary.append(
                {
                    "robot · controller": f"{robot} · {c}",
                    "seeds": len(g),
                    "success": f"{int(g['success'].sum())}/{len(g)}",
                    "collided": int((g["collision_steps"] > 0).sum()),
                    "stalled (no collision)": int((g["outcome"] == STALLED).sum()),
                    "moving (no collision)": int((g["outcome"] == MOVING).sum()),
                    "colliding states": int(g["collision_steps"].sum()),
                    "success while colliding": int(g["success_while_colliding"].sum()),
                    "success steps [%]": 100 * g["successes"].sum() / g["steps"].sum(),
                    "soft steps": int(g["soft_steps"].sum()),
                    "soft causes": summed_tallies(g["soft_causes"]),
                    "fallbacks": int(g["fallbacks"].sum()),
                    "cost / IPOPT median": q.median() if len(q) else np.nan,
                    "cost / IPOPT worst": q.max() if len(q) else np.nan,
                    "step median [ms]": 1e3 * g["step_median"].median(),
                    "step max [ms]": 1e3 * g["step_max"].max(),
                    "min clearance [m]": g["min_clearance"].min(),
                    "final distance median [m]": g["final_distance"].median(),
                }
            )
    table = pd.DataFrame(summary).set_index("robot · controller")
    tables[
        "Reach: per robot and controller (success: final end effector within 1 cm and true clearance ≥ 0 at "
        "every state; stalled: not reached and the distance unchanged within 1 mm over the last 0.5 s, moving: "
        "still changing at the end; colliding states: true clearance < 0; success while colliding: steps "
        "reported success whose next state collides; success steps: status 'success' only, soft steps and "
        "fallbacks apart; cost ratio to IPOPT on the seeds where IPOPT succeeds; step = the whole MPC step, "
        "wall time)"
    ] = markdown_table(table)
    # Success rates, cost ratios and step times side by side.
    labels = [f"{b}\n{c}" for b in robots for c in order if not r[(r["scenario"] == b) & (r["controller"] == c)].empty]
    rate = [
        r[(r["scenario"] == b) & (r["controller"] == c)]["success"].mean()
        for b in robots
        for c in order
        if not r[(r["scenario"] == b) & (r["controller"] == c)].empty
    ]
    figs.append(
        _bars(
            labels,
            rate,
            out_dir / "reach_success",
            ylabel="success rate (fraction of seeds)",
            title="Reach past a sphere: success (within 1 cm, no collision)",
        )
    )
    if not rat.empty:
        ratio_labels = [
            (b, c) for b in robots for c in order if len(rat[(rat["scenario"] == b) & (rat["controller"] == c)])
        ]
        figs.append(
            plots.boxes(
                [f"{b}\n{c}" for b, c in ratio_labels],
                [rat[(rat["scenario"] == b) & (rat["controller"] == c)]["ratio"].values for b, c in ratio_labels],
                out_dir / "reach_cost_ratio",
                xlabel="robot, controller",
                ylabel="actual cost / IPOPT's (ratio)",
                references=[(1.0, "1: IPOPT")],
                colours=[plots.style(c)["color"] for _, c in ratio_labels],
                title="Cost ratio to IPOPT where IPOPT succeeds",
            )
        )
    figs.append(
        plots.boxes(
            labels,
            [
                1e3 * r[(r["scenario"] == b) & (r["controller"] == c)]["step_median"].values
                for b in robots
                for c in order
                if not r[(r["scenario"] == b) & (r["controller"] == c)].empty
            ],
            out_dir / "reach_step_time",
            xlabel="robot, controller",
            ylabel="median MPC step time [ms]",
            colours=[plots.style(label.split("\n")[1])["color"] for label in labels],
            title="Per-trial median step time (wall, whole MPC step)",
        )
    )
    if "nlink:3" in robots:
        figs.append(_paths(r, out_dir))
    # Where EMPC and the gradient methods disagree.
    wide = r.pivot_table(index=["scenario", "seed"], columns="controller", values="success", aggfunc="first")
    if EMPC in wide:
        rows = []
        for g in [c for c in GRADIENT if c in wide]:
            both = wide[[EMPC, g]].dropna().astype(bool)
            e_only = both.index[both[EMPC] & ~both[g]]
            g_only = both.index[~both[EMPC] & both[g]]
            rows.append(
                {
                    "gradient method": g,
                    "seeds": len(both),
                    "EMPC succeeds, it misses": len(e_only),
                    "how it misses there": _how(r, g, e_only),
                    "it succeeds, EMPC misses": len(g_only),
                    "how EMPC misses there": _how(r, EMPC, g_only),
                }
            )
        tables[
            "EMPC vs the gradient methods, seed by seed (stalled or moving: no collision but > 1 cm from the "
            "target at the end, the loop's verdict, with the median final distance; collision: some state with "
            "true clearance < 0, with the deepest penetration)"
        ] = markdown_table(pd.DataFrame(rows).set_index("gradient method"))
    sample = ", ".join(sorted(set(r.loc[r["controller"].isin([EMPC, CEM, MPPI]), "device"])))
    notes.append(
        "Reach setup: "
        + "; ".join(
            f"{b}: {r[r['scenario'] == b]['seed'].nunique()} seeds, "
            f"{number(r[r['scenario'] == b]['duration'].iloc[0])} s at 100 Hz, "
            f"horizon {r[r['scenario'] == b]['horizon'].iloc[0]}, {KNOTS[b]} knots, obstacle radius "
            f"{number(OBSTACLE_RADIUS[b])} m, {int(r[(r['scenario'] == b)].groupby('seed')['rejected'].first().sum())}"
            f" scenario draws rejected (start or target colliding or too close)"
            for b in robots
        )
        + f". Sampling planners: population {r['population'].iloc[0]}, 1 generation, affine model re-linearized about "
        f"the plan each step (dynamics 'affine', linearization 'plan'), on {sample or '–'}. The seeds were not "
        f"tuned on: they are 0 … n−1, and the first scenario each seed draws that passes the checks is used."
    )
    notes.append(
        "How each controller holds the obstacle (ocpkit.model.task): IPOPT as a hard constraint d ≥ margin at "
        f"every predicted state, given {IPOPT_BUDGET['max_iter']} iterations a step (a step that needs more is "
        "'limited' and falls back; not in the keep-out runs); RTI and LinearMPC as QP rows linearized about the "
        "plan, hard for DAQP "
        "and softened (exact penalty) only where infeasible; EMPC, CEM and MPPI as the penalty "
        f"{REACH_OBSTACLE_WEIGHT:g}·(h + ½h²), h = max(0, margin − min clearance), in the rollout "
        "fitness: a penalty, not a constraint, so a sampled plan that cuts the sphere can still be the "
        "fittest when the target pulls hard enough. Cost ratios compare the task cost (position term, "
        "velocities, inputs) and say nothing about collisions: read them with the success column."
    )
    missed = r[~r["success"].astype(bool)]
    stalled = missed[missed["outcome"] == STALLED]
    pressed = stalled[stalled["min_clearance"] < 1.5 * MARGIN]
    moving = missed[missed["outcome"] == MOVING]
    collided = int((missed["collision_steps"] > 0).sum())
    moving_runs = ", ".join(f"{a} {b} seed {c}" for a, b, c in moving[["scenario", "controller", "seed"]].values)
    notes.append(
        f"Misses, from the data: {len(missed)} of {len(r)} runs missed; {collided} collided; "
        f"{len(stalled)} stalled short of the target without collision (the distance unchanged within 1 mm "
        f"over the last 0.5 s; {int(stalled['successes'].sum())} of their {int(stalled['steps'].sum())} "
        f"steps reported success), {len(pressed)} of them after touching the margin (min clearance < 1.5× "
        "the margin): held in front of the sphere, a local minimum of the position cost under the obstacle "
        f"constraint, not an unsuccessful solve; {len(moving)} were still moving at the end "
        f"({moving_runs or '–'}). Fallback steps in the misses: {int(missed['fallbacks'].sum())}, soft "
        f"steps {int(missed['soft_steps'].sum())}. LinearMPC's default linearization takes one model for the "
        "horizon, expanded about the current state and the input goal u_g(x_ref) — with the reach goal's "
        "x_ref the start at rest: zero torque on nlink:3, the start's set points on Baxter —; "
        "'trajectory' re-linearizes stage by stage along the plan."
    )
    claims.append(_claim_ipopt_rti(r))
    claims.append(_claim_empc_cost(rat))
    claims.append(_claim_no_success_colliding(r, order))


def _how(r, controller, index) -> str:
    if not len(index):
        return "–"
    rows = r.set_index(["scenario", "seed"])
    rows = rows[rows["controller"] == controller].loc[list(index)]
    parts = []
    hit = rows[rows["collision_steps"] > 0]
    for verdict, short in rows[rows["collision_steps"] == 0].groupby("verdict"):
        parts.append(
            f"{len(short)} {verdict} (median {number(100 * short['final_distance'].median(), 3)} cm short, "
            f"min clearance {number(100 * short['min_clearance'].min(), 3)} cm)"
        )
    if len(hit):
        parts.append(f"{len(hit)} collision (down to {number(100 * hit['min_clearance'].min(), 3)} cm)")
    return ", ".join(parts)


def _claim_ipopt_rti(r) -> Claim:
    parts, verdicts = [], []
    for c in (IPOPT, RTI):
        g = r[r["controller"] == c]
        if len(g):
            rate, low, high = proportion(int(g["success"].sum()), len(g))
            parts.append(
                f"{c} {int(g['success'].sum())}/{len(g)} = {number(100 * rate, 3)} % "
                f"[{number(100 * low, 3)}, {number(100 * high, 3)}] (95 % exact, n = {len(g)})"
            )
            verdicts.append(decide(Interval(rate, low, high, len(g), 0.95), 0.9, ">="))
    return Claim(
        "IPOPT and RTI reach ≥ 90 % of reachable targets without collision",
        "success rate per solver",
        combine(verdicts) if len(verdicts) == 2 else NOT_TESTED,
        "; ".join(parts) or "not run",
    )


def _claim_no_success_colliding(r, order) -> Claim:
    per = r.groupby("controller")["success_while_colliding"].sum()
    verdict, evidence = every(
        r["success_while_colliding"], lambda n: n == 0, "reported success on a step whose next state collides"
    )
    return Claim(
        "No controller reports success on a step whose actual next state collides (issue 43)",
        "steps reported success while the next state collides, per controller: "
        + ", ".join(f"{c} {int(per[c])}" for c in order),
        verdict,
        evidence,
    )


def _claim_empc_cost(rat) -> Claim:
    claim = "Preconditioned EMPC's median cost within 1.2× of IPOPT's where IPOPT succeeds"
    q = rat[rat["controller"] == EMPC]["ratio"]
    if not len(q):
        return Claim(claim, "no seed where both ran and IPOPT succeeded", NOT_TESTED)
    v, e = median_claim(q, 1.2, "<=")
    return Claim(
        claim,
        f"per seed, cost ratio EMPC / IPOPT (worst {number(q.max(), 3)}); EMPC succeeded on "
        f"{int(rat[rat['controller'] == EMPC]['success'].sum())} of them",
        v,
        e,
    )


def _bars(labels, values, path, *, ylabel, title):
    fig, ax = plots.figure(figsize=(max(6, 0.5 * len(labels)), 3.8))
    ax.bar(range(len(labels)), values, color=[plots.style(label.split("\n")[1])["color"] for label in labels])
    ax.set_xticks(range(len(labels)), labels, fontsize=7, rotation=60, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel(ylabel)
    plots.reference(ax, 0.9, "0.9: the claim's success rate")
    ax.grid(axis="y", alpha=0.3)
    plots.legend_outside(ax)
    plots.set_title(ax, title)
    return plots.save(fig, path)


def _paths(r, out_dir):
    """The 3-link arm's end-effector paths in its plane, first seed, every controller, with the obstacle."""
    from ocpkit.studies.comparison import row_arrays

    first = r[r["scenario"] == "nlink:3"]
    seed = first["seed"].min()
    first = first[first["seed"] == seed]
    fig, ax = plots.figure(figsize=(7, 5.0))
    arrays = None
    for row in first.index:
        arrays = row_arrays(r, row, out_dir)
        ee = arrays["ee"]
        look = plots.style(r.at[row, "controller"])
        ax.plot(
            ee[:, 0],
            ee[:, 1],
            lw=1,
            color=look["color"],
            ls=look["linestyle"],
            marker=look["marker"],
            ms=3,
            markevery=(len(ax.lines) * 3 % 20, 20),
            label=f"{r.at[row, 'controller']} ({r.at[row, 'outcome']})",
        )
    if arrays is not None:
        for cx, cy, _, rad in arrays["obstacles"]:
            ax.add_patch(plots.plt.Circle((cx, cy), rad, color="0.6", alpha=0.5))
        ax.plot(*arrays["target"][:2], "k*", ms=10, label="target")
        ax.plot(*ee[0, :2], "ko", ms=4, label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    plots.legend_outside(ax)  # outside: "best" inside still covered paths
    ax.set_title(f"3-link arm, seed {seed}: end-effector paths", fontsize=10)
    return plots.save(fig, out_dir / "reach_paths_nlink3")


def keepout_section(k, out_dir, figs, tables, notes, claims):
    """The keep-out trials ``k`` into the report: their figures, tables, notes and claims appended to those given."""
    order = [c for c in KEEPOUT_CONTROLLERS if c in set(k["controller"])]
    table = k.pivot_table(index="seed", columns="controller", values="actual_cost")[order]
    figs.append(
        plots.boxes(
            order,
            [table[c].dropna().values for c in order],
            out_dir / "reach_keepout_cost",
            xlabel="controller",
            ylabel="actual penalized cost (dimensionless)",
            colours=[plots.style(c)["color"] for c in order],
            title=f"Keep-out ball r = {number(keepout.RADIUS)} rad: same cost for all, {k['seed'].nunique()} seeds",
        )
    )
    summary = (
        k.groupby("controller")[["actual_cost", "penalty", "steps_inside", "final_error", "step_median", "step_max"]]
        .median()
        .reindex(order)
    )
    summary["step_median"] *= 1e3
    summary["step_max"] *= 1e3
    tables[
        "Keep-out, fair baseline: actual penalized cost per seed (quadratic cost + w·max(0, r − ‖q − c‖) on "
        "every state)"
    ] = markdown_table(table)
    tables[
        "Keep-out medians over the seeds (penalty part, steps inside the ball, final error max |x − x_goal|, "
        "median and max MPC step time in ms)"
    ] = markdown_table(summary)
    notes.append(
        f"Keep-out setup: as in the keep-out study ({keepout.LINKS}-link arm, horizon "
        f"{k['horizon'].iloc[0]}, {keepout.KNOTS} knots, {number(k['duration'].iloc[0])} s, w = "
        f"{number(keepout.WEIGHT)}, r = {number(keepout.RADIUS)} rad). IPOPT, RTI and '{K_EMPC_SQUARED}' "
        f"take the UserTerm {number(HINGE_WEIGHT)}·max(0, r + 0.01 − ‖q − c‖)² at every stage and the "
        f"terminal state (C¹; the 0.01 rad widens the ball so the smooth term acts before the scored "
        f"hinge does); '{K_EMPC_HINGE}' takes the scored hinge itself as its fitness. All are scored "
        f"on the same actual penalized cost. EMPC population {k['population'].iloc[0]}, fallback steps "
        f"{int(k['fallbacks'].sum())}."
    )
    if {K_IPOPT, K_EMPC_HINGE} <= set(table.columns):
        lines = []
        for ref in (K_IPOPT, K_RTI):
            if ref not in table:
                continue
            for c in (K_EMPC_HINGE, K_EMPC_SQUARED):
                if c not in table:
                    continue
                both = table[[ref, c]].dropna()
                wins = both.index[both[c] < both[ref]].tolist()
                lines.append(
                    f"{c} costs less than {ref} on {len(wins)} of {len(both)} seeds"
                    + (f" (seeds {', '.join(map(str, wins))})" if wins else "")
                    + f", median ratio {number(np.median(both[c] / both[ref]), 3)}"
                )
        med = k.groupby("controller")["step_median"].median() * 1e3
        notes.append(
            "Keep-out verdict, as measured: "
            + "; ".join(lines)
            + ". Median step times: "
            + ", ".join(f"{c} {number(med[c], 3)} ms" for c in order)
            + "."
        )
        both = table[[K_IPOPT, K_EMPC_HINGE]].dropna()
        v, e = median_claim(both[K_EMPC_HINGE] / both[K_IPOPT], 1.0, "<")
        claims.append(
            Claim(
                "EMPC's penalized fitness costs less than IPOPT given the same penalty in C¹ form "
                "(keep-out ball; not a paper claim: the keep-out study's open question)",
                f"per seed, cost ratio EMPC / IPOPT < 1: lower on "
                f"{int((both[K_EMPC_HINGE] < both[K_IPOPT]).sum())} of {len(both)} seeds",
                v,
                e,
            )
        )
