"""`ocpkit study` and `ocpkit reproduce`: the paper's experiments (or a closed-loop study on the problems of
--problem) run into a results folder, their report sections written and printed."""

from __future__ import annotations

from pathlib import Path

from ocpkit.cli.checks import check_output_file, check_output_folder

# Studies that take --problem.
PROBLEM_STUDIES = ("knots", "horizon", "robustness")


def _study_options(args) -> dict:
    """The study runner's options from the command line, with the output paths and the scheduler checked first."""
    from ocpkit.runs.cluster import check_scheduler

    check_output_folder(args.out, "--out")
    if args.export is not None:
        check_output_file(args.export, "--export")
    if args.trial_timeout is not None and not args.trial_timeout > 0:
        raise ValueError(f"--trial-timeout must be a positive number of seconds, got {args.trial_timeout}")
    if args.scheduler is not None:
        check_scheduler(args.scheduler)
    return {"trial_timeout": args.trial_timeout, "retry_failed": args.retry_failed, "stale": args.stale}


def _export_store(args) -> None:
    if args.export is not None:
        from ocpkit.runs.store import Store

        with Store(args.out) as store:
            print(f"results database: {store.export(args.export)}")


def study_command(args):
    """`ocpkit study NAME`: one study run into --out, its report section written there and printed."""
    from ocpkit.studies.reproduce import run_study

    options = _study_options(args)
    if args.plant != "ocpkit" and args.name != "robustness":
        raise ValueError(f"--plant applies to the robustness study only, not {args.name!r}")
    if args.problem:
        section = _study_problems(args, options)
    else:
        section = run_study(
            args.name, args.size, args.out, workers=args.workers, scheduler=args.scheduler, plant=args.plant, **options
        )
    path = Path(args.out) / f"{args.name}{'' if args.plant == 'ocpkit' else '_' + args.plant}.md"
    path.write_text(section)
    print(section + f"\nreport: {path}")
    _export_store(args)
    return 0


def _study_problems(args, options) -> str:
    """A closed-loop study on the problems of --problem: its table (CSV), figures and report section."""
    from ocpkit.runs import study as study_runner
    from ocpkit.studies import get

    if args.name not in PROBLEM_STUDIES:
        raise ValueError(f"--problem applies to the studies {', '.join(PROBLEM_STUDIES)}, not {args.name!r}")
    module = get(args.name)
    out = Path(args.out)
    study = module.study(args.size, problems=args.problem, **({} if args.plant == "ocpkit" else {"plant": args.plant}))
    df = study_runner.run(study, out, workers=args.workers, scheduler=args.scheduler, **options)
    df.to_csv(out / f"{study.name}.csv", index=False)
    failed = df[df["status"] == "failed"]
    if len(failed) == len(df):
        raise ValueError(f"every trial of {args.name} failed; first error: {failed['error'].iloc[0].splitlines()[0]}")
    return module.report(df, out) + study_runner.failure_summary(df) + study_runner.cluster_summary(df)


def reproduce_command(args):
    """`ocpkit reproduce`: every study of the paper run into --out, and the report."""
    from ocpkit.studies import chosen
    from ocpkit.studies.reproduce import reproduce

    options = _study_options(args)
    names = chosen(args.only)
    report = reproduce(args.size, args.out, names=names, workers=args.workers, scheduler=args.scheduler, **options)
    print(f"report: {report}")
    _export_store(args)
    return 0
