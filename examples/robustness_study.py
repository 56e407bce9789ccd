"""Tutorial "A robustness study": the paper's robustness experiment (Figs. 5-6) on the cart-pole of ``cartpole.py``
at the quick size (3 error multipliers × 2 seeds), as ``ocpkit study robustness --problem ./cartpole.py:CartPole``
runs it. Run it as ``python robustness_study.py [OUT_DIR]``; a second run resumes from the stored trials."""

import sys
from pathlib import Path

from ocpkit import studies
from ocpkit.runs.study import run

if __name__ == "__main__":  # the study's worker processes import this file: only the main process runs the study
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "results/cartpole")
    spec = f"{Path(__file__).with_name('cartpole.py')}:CartPole"  # a problem by spec, as the command line names it
    robustness = studies.get("robustness")
    df = run(robustness.study("quick", problems=[spec]), out, workers=2, progress=False)
    costs = df.pivot_table(index="knots", columns="error_multiplier", values="actual_cost", dropna=False)
    print(costs.rename(index=lambda k: "traditional" if k != k else f"{k:.0f} knots"))  # knots NaN: p = T
    (out / "robustness.md").write_text(robustness.report(df, out))  # the report's section and its figure
    print(sorted(p.name for p in out.iterdir() if p.suffix in (".md", ".csv", ".png")))
