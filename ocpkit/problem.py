"""A robot or system the paper controls: its true plant, the controller's model, defaults and sampling."""
from __future__ import annotations

from functools import cached_property

import numpy as np

from ocpkit._checks import positive
from ocpkit.model import Model
from ocpkit.ocp import OCP
from ocpkit.parameterization import Parameterization


class Problem:
    """Base class. Subclasses implement ``_model(error)``, ``defaults()`` and ``sample(seed)``.

    ``model(error)`` is the controller's model with the paper's error multiplier applied; ``plant()`` is
    always the true model (error = 1): model error belongs to the controller, never to the plant.
    """

    name = "problem"
    dt = 0.01
    horizon = 50
    duration = 1.0  # seconds of closed loop in the paper's experiments

    def model(self, error: float = 1.0) -> Model:
        """The controller's model with every modelled mass/inertia scaled by ``error``."""
        error = positive(error, "error")
        if error not in self._models:
            self._models[error] = self._model(error)
        return self._models[error]

    def plant(self) -> Model:
        """The true system (error multiplier 1)."""
        return self.model(1.0)

    def defaults(self) -> dict:
        """OCP keyword arguments: Q, R and bounds (and optionally Q_terminal, u_goal, x_min, x_max)."""
        raise NotImplementedError

    def sample(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Seeded random start and goal states."""
        raise NotImplementedError

    def _model(self, error: float) -> Model:
        raise NotImplementedError

    @cached_property
    def _models(self) -> dict:
        return {}

    def ocp(self, *, knots: int | None = None, horizon: int | None = None, error: float = 1.0,
            parameterization: str = "linear", dt: float | None = None, **overrides) -> OCP:
        """The MPC problem: ``knots`` None means traditional MPC (p = T); other keywords override defaults."""
        T = self.horizon if horizon is None else horizon
        kwargs = {**self.defaults(), **overrides}
        return OCP(self.model(error), self.dt if dt is None else dt, T,
                   parameterization=Parameterization.make(parameterization, T, knots), **kwargs)

    def __repr__(self):
        return f"{type(self).__name__}({self.name!r})"
