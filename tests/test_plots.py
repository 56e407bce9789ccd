"""The one number style of reports and figures."""

import numpy as np

from ocpkit.sim import plots


def test_number_formatter():
    assert plots.number(1.0037) == "1.004"  # not "1"
    assert plots.number(1.0) == "1" and plots.number(0.5) == "0.5" and plots.number(1.1) == "1.1"
    assert plots.number(222.98) == "223" and plots.number(12.537) == "12.54"
    assert plots.number(5.3e-5) == "5.3e-05" and plots.number(12537.2) == "1.254e+04"
    assert plots.number(float("nan")) == "–" and plots.number(None) == "–" and plots.number(np.inf) == "∞"
    assert plots.number(7) == "7" and plots.number(np.int64(3)) == "3"
    assert plots.number(3.14159, 2) == "3.1"


def test_ratio_axis_is_labelled_in_plain_decimals(tmp_path):
    """A log ratio axis over 0.98–1.4 gets several plain ticks, not one "10⁰"."""
    path = plots.boxes(
        [1, 2], [np.array([0.98, 1.0, 1.02]), np.array([1.2, 1.3, 1.4])], tmp_path / "b", xlabel="knots", ylabel="ratio"
    )
    fig = plots.plt.figure()
    ax = fig.add_subplot()
    ax.set_yscale("log")
    ax.set_ylim(0.95, 1.45)
    plots.log_axis(ax)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
    plots.plt.close(fig)
    assert len(labels) >= 3 and all("10^" not in s and "times" not in s for s in labels), labels
    assert path.stat().st_size > 5000


def test_a_long_label_does_not_squeeze_the_closed_loop_panels(tmp_path, monkeypatch):
    """Issue 44, item 15: a controller's long label in a legend beside the panels squeezed them into a third of the
    image; below them, the panels keep the figure's width."""
    from ocpkit.sim.simulate import Trajectory

    t = np.linspace(0, 1, 11)
    traj = Trajectory(t=t, x=np.zeros((11, 4)), u=np.zeros((10, 2)), goal=np.ones(4), solutions=[])
    widths = []

    def measure(fig, path):
        fig.canvas.draw()
        widths.extend(ax.get_position().width for ax in fig.axes)
        return path

    monkeypatch.setattr(plots, "save", measure)
    plots.closed_loop(
        {"LinearMPC(condensed, daqp, Python step, OCP('nlink:2', dt=0.01, horizon=50, linear knots=5))": traj},
        tmp_path / "f.png",
        title="nlink:2, seed 0",
    )
    assert len(widths) == 4 and min(widths) > 0.8, widths
