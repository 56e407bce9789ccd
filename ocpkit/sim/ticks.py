"""Axis ticks of the figures and numbers as the reports print them: one notation per axis, log axes that keep
their 1, count axes at integers, and reference lines' values labelled."""

from __future__ import annotations

import numpy as np
from matplotlib import ticker


def number(value, digits: int = 4) -> str:
    """A number as reports print it: ``digits`` significant digits in plain decimals (scientific only below
    1e-4 or from 10^digits on), "–" for a missing value, ints as ints: 1.0037 → "1.004", 0.5 → "0.5"."""
    if value is None:
        return "–"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    v = float(value)
    if np.isnan(v):
        return "–"
    if np.isinf(v):
        return "∞" if v > 0 else "−∞"
    return format(v, f".{digits}g")


class _WithReferences(ticker.Locator):
    """An axis's own tick positions plus the reference lines' values (a dotted line at 1 whose 1 has no label
    reads as any value); the axis's ticks too near a reference to be read apart from it give way."""

    def __init__(self, base: ticker.Locator, values):
        self.base, self.values = base, sorted(set(float(v) for v in values))

    def set_axis(self, axis):
        super().set_axis(axis)
        self.base.set_axis(axis)

    def __call__(self):
        return self.tick_values(*self.axis.get_view_interval())

    def tick_values(self, vmin, vmax):
        lo, hi = sorted((vmin, vmax))
        refs = [v for v in self.values if lo <= v <= hi]
        log = self.axis.get_scale() == "log"
        where = np.log10 if log else (lambda v: v)
        span = (where(hi) - where(lo)) or 1.0
        ticks = [t for t in self.base.tick_values(lo, hi) if all(abs(where(t) - where(r)) > 0.06 * span for r in refs)]
        return np.array(sorted(ticks + refs))


def reference_ticks(ax, values, axis: str = "y") -> None:
    """Ticks labelled at the ``values`` of the axis's reference lines, beside its own (call after the scale)."""
    which = ax.yaxis if axis == "y" else ax.xaxis
    if len(values):
        which.set_major_locator(_WithReferences(which.get_major_locator(), values))


def count_axis(ax, values=None, axis: str = "x") -> None:
    """Integer ticks on an axis that counts (links, knots): at ``values`` if given and few, else integer steps."""
    which = ax.xaxis if axis == "x" else ax.yaxis
    values = None if values is None else sorted({int(v) for v in values})
    if values is not None and len(values) <= 15:
        which.set_major_locator(ticker.FixedLocator(values))
    else:
        which.set_major_locator(ticker.MaxNLocator(integer=True))
    which.set_major_formatter(ticker.FuncFormatter(lambda v, _: str(int(round(v)))))
    which.set_minor_locator(ticker.NullLocator())


class _Ticks(ticker.Formatter):
    """One notation for all ticks of an axis: plain decimals, or powers of ten when a tick needs them."""

    ticks = ()

    def set_locs(self, locs):
        self.ticks = tuple(locs)

    def __call__(self, value, pos=None):
        ticks = [abs(v) for v in self.ticks if v] or [abs(value) or 1.0]
        if max(ticks) >= 1e5 or min(ticks) < 1e-3:
            return f"{value:.0e}".replace("e+0", "e").replace("e-0", "e-").replace("e+", "e")
        return number(value, max(3, int(np.floor(np.log10(abs(value)))) + 1) if value else 3)


def log_axis(ax, axis: str = "y") -> None:
    """A log axis with readable ticks in one notation; within one decade, evenly spaced values (a log locator
    would label only 10⁰ on a ratio axis spanning 0.98–1.4), else 1, 2, 5 per decade."""
    which = ax.yaxis if axis == "y" else ax.xaxis
    which.set_major_locator(_LogTicks())
    which.set_major_formatter(_Ticks())
    which.set_minor_formatter(ticker.NullFormatter())


class _LogTicks(ticker.Locator):
    """:func:`log_axis`'s tick positions, chosen when the axis is drawn: from the final limits, which series and
    bands drawn after the call may still widen (a range chosen too early left a 0.9–12 axis without its 1)."""

    def __init__(self):
        self._linear = ticker.MaxNLocator(nbins=6)
        self._log = ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0))

    def set_axis(self, axis):
        super().set_axis(axis)
        self._linear.set_axis(axis)
        self._log.set_axis(axis)

    def __call__(self):
        return self.tick_values(*self.axis.get_view_interval())

    def tick_values(self, vmin, vmax):
        lo, hi = sorted((vmin, vmax))
        return (self._linear if lo > 0 and hi / lo < 10 else self._log).tick_values(lo, hi)


def numeric_ticks(ax, positions, logx: bool) -> None:
    """Ticks at the groups' values where they are few, else the axis's own (1, 2, 5 per decade on a log axis)."""
    values = sorted(set(positions))
    integer = all(float(v).is_integer() for v in values)
    if len(values) <= 15:
        ax.xaxis.set_major_locator(ticker.FixedLocator(values))
    elif logx:
        ax.xaxis.set_major_locator(ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    else:
        ax.xaxis.set_major_locator(ticker.MaxNLocator(integer=integer))
    ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: str(int(round(v))) if integer else number(v)))
    ax.xaxis.set_minor_locator(ticker.NullLocator())
