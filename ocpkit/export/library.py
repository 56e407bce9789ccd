"""The built library loaded back into Python: the exported C step as a :class:`~ocpkit.controller.Controller`."""

from __future__ import annotations

import ctypes
import time
from pathlib import Path

import numpy as np

from ocpkit._checks import array
from ocpkit.codegen.cache import check_trusted
from ocpkit.qp.certificate import TESTS, Certificate
from ocpkit.qp.certificate import TOL as CERT_TOL
from ocpkit.controller import Controller
from ocpkit.status import REASONS, STATUSES, SUCCESS, Reason, Solution
from ocpkit.export.constants import CERT_CODE, ILL_CONDITIONED
from ocpkit.export.digest import differences
from ocpkit.export.generate import general_rows
from ocpkit.model.ocp import OCP
from ocpkit.qp.daqp import DAQP_EXIT, daqp_exit_name
from ocpkit.qp.quadratic_program import ROUNDING_MARGIN


class ExportedMPC(Controller):
    """The compiled exported step (``lib<name>.so`` in ``out_dir``) as a Controller, through ctypes.

    The library must have been exported for ``ocp``: its digest (``<name>_ocp_digest``, :mod:`ocpkit.export.digest`)
    is compared with ``ocp``'s on load, and a library for other sizes, weights, bounds, model or task is refused
    (ValueError naming what differs). Statuses map one to one onto ocpkit's, and so do the reasons the library gives
    (``<name>_last_reason``) onto ``Solution.reason``; on failure the library returns its own
    fallback (the previous plan shifted, which a C caller gets), and this class answers with
    :meth:`Controller.fallback` instead: the shifted plan only while its prediction is safe, else the brake (a
    library with obstacles then follows that plan, :meth:`set_plan`; another keeps its own). Called by another
    controller (``_solve``: LinearMPC's C step, which answers a refused step itself) it passes the library's
    fallback on, ``path`` "fallback (C plan)". ``times`` splits the C step as the DESIGN
    does, measured in C:
    ``model`` (RK4 and its sensitivities), ``build`` (the condensing), ``solve`` (the QP solver);
    :attr:`step_seconds` is the last whole C step seen from Python (ctypes call included). Each instance owns
    its C memory (several may step in one process, up to the library's ``MAX_INSTANCES``); :meth:`close`, or
    leaving a ``with`` block, gives its QP-solver slot back.
    """

    def __init__(self, ocp: OCP, out_dir, *, name: str = "mpc", raise_on_fail: bool = False):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        lib_path = Path(out_dir) / f"lib{name}.so"
        if not lib_path.is_file():
            raise ValueError(f"out_dir {str(out_dir)!r} has no lib{name}.so; run export() and build() first")
        lib = ctypes.CDLL(str(check_trusted(lib_path)))
        _check_digest(lib, name, lib_path, ocp)
        dbl = np.ctypeslib.ndpointer(dtype=np.float64, flags="C_CONTIGUOUS")
        size = getattr(lib, f"{name}_memory_size")
        size.restype = ctypes.c_size_t
        self._mem = ctypes.create_string_buffer(size())
        self._step = getattr(lib, f"{name}_step_timed")
        self._step.argtypes = [ctypes.c_void_p] * 6
        self._step.restype = ctypes.c_int
        self._knots = getattr(lib, f"{name}_knots")
        self._knots.argtypes = [ctypes.c_void_p] * 2
        self._model = getattr(lib, f"{name}_model_step")
        self._model.argtypes = [ctypes.c_void_p, dbl, dbl, dbl]
        self._rc = getattr(lib, f"{name}_solver_return")
        self._reason = getattr(lib, f"{name}_last_reason")
        self._reason.argtypes = [ctypes.c_void_p]
        self._certificate = getattr(lib, f"{name}_certificate")
        self._certificate.argtypes = [ctypes.c_void_p] * 2
        solver_name = getattr(lib, f"{name}_qp_solver")
        solver_name.restype = ctypes.c_char_p
        self.qp = solver_name().decode()
        self._solve_qp = getattr(lib, f"{name}_solve_qp")
        self._solve_qp.argtypes = [ctypes.c_void_p] + [dbl] * 8 + [ctypes.c_void_p]
        self._lib, self.name, self.out_dir = lib, name, Path(out_dir)
        self._free = getattr(lib, f"{name}_free")
        try:  # a "trajectory" step's predicted states
            self._states = getattr(lib, f"{name}_states")
            self._states.argtypes = [ctypes.c_void_p, dbl]
        except AttributeError:
            self._states = None
        try:  # a step with obstacles: the plan it linearizes about can be set
            self._set_plan = getattr(lib, f"{name}_set_plan")
            self._set_plan.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        except AttributeError:
            self._set_plan = None
        self._step_window = getattr(lib, f"{name}_step_window_timed")  # with obstacles it takes them too
        self._step_window.argtypes = [ctypes.c_void_p] * (6 if self._set_plan is None else 7)
        self._step_window.restype = ctypes.c_int
        self._open = False
        if getattr(lib, f"{name}_init")(self._mem):
            raise RuntimeError(
                f"{name}_init failed: all QP solver memory slots of {lib_path} are in use "
                f"(close() other instances, or rebuild with make MAX_INSTANCES=N)"
            )
        self._open = True
        self._status = ctypes.c_int()
        self._status_ptr = ctypes.addressof(self._status)
        # A step's arrays in and out, where the C code reads and writes them (an array's .ctypes costs 1.4 us, an
        # ndpointer check 3 us: a fifth of the Python around a 0.15 ms C step); returned arrays are copies
        sizes = {"x": ocp.nx, "goal": ocp.ng, "u": ocp.nu, "knots": ocp.knots * ocp.nu, "split": 3, "certificate": 4}
        self._io = {k: np.zeros(n) for k, n in sizes.items()}
        self._at = {k: v.ctypes.data for k, v in self._io.items()}
        self.step_seconds = float("nan")
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    path = "C step"
    TAKES = frozenset({"goal window", "obstacles"})

    def __repr__(self):
        return f"ExportedMPC({str(self.out_dir / ('lib' + self.name + '.so'))!r}, {self.ocp!r})"

    def close(self) -> None:
        """Give the instance's C memory back (its QP-solver slot); further steps raise. Safe to call twice."""
        if getattr(self, "_open", False):
            self._free(self._mem)
            self._open = False

    @property
    def closed(self) -> bool:
        return not self._open

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may already be gone
            pass

    def _check_open(self):
        if not self._open:
            raise RuntimeError(f"{self!r} is closed")

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """True at once: the step is the compiled library (nothing of it compiles in the background)."""
        return True

    def reset(self) -> None:
        super().reset()
        if getattr(self, "_open", False):
            getattr(self._lib, f"{self.name}_reset")(self._mem)

    def model_step(self, x, u) -> np.ndarray:
        """x⁺ from the library's generated discrete model (the model the controller predicts with)."""
        x = self.ocp.check_state(x, "x")
        u = array(u, "u", (self.ocp.nu,))
        self._check_open()
        out = np.empty(self.ocp.nx)
        if self._model(self._mem, x, u, out):
            raise RuntimeError("generated discrete model failed")
        return out

    @property
    def sets_plan(self) -> bool:
        """Whether :meth:`set_plan` can set the plan the library linearizes about (an export with obstacles)."""
        return self._set_plan is not None

    def set_plan(self, knots) -> None:
        """Make ``knots`` (p, m) the plan the library's next step linearizes about, shifted a step (None: none, the
        input goal as at a cold start): after a step answered elsewhere — with obstacles the hard QP can be
        infeasible, and LinearMPC answers with its softened QP in Python; a refused step's brake."""
        self._check_open()
        if self._set_plan is None:
            raise RuntimeError(
                f"{self!r} keeps its own plan: its library has no {self.name}_set_plan (an export with obstacles has)"
            )
        if knots is None:
            self._set_plan(self._mem, None)
            return
        knots = np.ascontiguousarray(array(knots, "knots", (self.ocp.knots, self.ocp.nu)))
        self._set_plan(self._mem, knots.ctypes.data)

    def solve(self, x, goal, **step) -> Solution:
        """:meth:`Controller.solve`; where the step was refused and the library can take it, the library follows
        the plan this controller answered with (the shifted plan or the brake, :meth:`Controller.fallback`)."""
        sol = super().solve(x, goal, **step)
        if sol.fallback and self._set_plan is not None:
            self.set_plan(sol.knots)
        return sol

    def certificate(self) -> Certificate:
        """The KKT certificate the C code computed for its last QP solve (:mod:`ocpkit.qp.certificate`)."""
        self._check_open()
        self._certificate(self._mem, self._at["certificate"])
        return Certificate(*self._io["certificate"])

    def solve_qp(self, qp) -> tuple[str, np.ndarray]:
        """(status, z) of the C step's QP solve and certificate on ``qp``, a condensed knot QP of this library's size
        (an :class:`ocpkit.qp.transcription.QP` with the knot bounds as its box and state-bound rows after them, then
        with obstacles up to the library's room for obstacle rows; the rest is filled with zero rows, unbounded) — to
        test the solver and the certificate in C on QPs of one's own. The next step starts cold."""
        self._check_open()
        nz = self.ocp.knots * self.ocp.nu
        k = 0 if qp.box is None else len(qp.box)
        if qp.n != nz or qp.b.size:
            raise ValueError(f"qp must have {nz} variables and no equality rows, got {qp.n} and {qp.b.size}")
        lbx, ubx = np.full(nz, -np.inf), np.full(nz, np.inf)
        lbx[qp.box], ubx[qp.box] = qp.l[:k], qp.u[:k]
        C = np.asarray(qp.C.toarray() if hasattr(qp.C, "toarray") else qp.C, dtype=float)[k:]
        rows = general_rows(self.ocp)
        if C.shape[0] > rows:
            raise ValueError(f"qp has {C.shape[0]} general rows, this library's QP {rows}")
        pad = rows - C.shape[0]
        C = np.vstack([C, np.zeros((pad, nz))])
        lo, hi = np.r_[qp.l[k:], np.full(pad, -np.inf)], np.r_[qp.u[k:], np.full(pad, np.inf)]

        def col(v):
            return np.ascontiguousarray(v, dtype=float)

        z, status = np.empty(nz), ctypes.c_int()
        self._solve_qp(
            self._mem,
            col(np.asarray(qp.P, dtype=float).T),
            col(qp.q),
            col(C.T),
            col(lo),
            col(hi),
            col(lbx),
            col(ubx),
            z,
            ctypes.addressof(status),
        )
        return STATUSES[status.value], z

    def _solve(self, x: np.ndarray, goal: np.ndarray, *, window=None, obstacles=None) -> Solution:
        """The C step from ``x``; ``goal``: x_goal, or the whole goal vector [x_goal; targets]. With a task the
        step takes the whole vector: ``goal`` where it is one; from :meth:`solve` (x_goal, its own slice) the
        :attr:`task_goal` it was given. Another caller with a task (LinearMPC) passes the whole vector.

        ``window`` (T+1, ng) and ``obstacles`` (T+1, N, 4), as :meth:`Controller.solve` sets ``goal_window`` and
        ``obstacle_window``, make it the window step (``<name>_step_window``); None: a held goal, the task's
        obstacles (``<name>_step``). From :meth:`solve` they are this step's own, where the goal or obstacles
        move; another caller (LinearMPC's C step) passes its own."""
        self._check_open()
        if self._step_start is not None:  # this controller's own step
            window = self.goal_window if self.moving else None
            obstacles = self._moved_obstacles()
        if self.ocp.task_functions is not None and np.size(goal) != self.ocp.ng:
            if goal is not self._goal:
                raise ValueError(
                    f"this C step has a task: it needs the whole goal vector of {self.ocp.ng} entries "
                    f"[x_goal; targets] (ocp.goal(...)), got {np.size(goal)}"
                )
            goal = self.task_goal
        io, at = self._io, self._at
        io["x"][:] = x
        if window is None and obstacles is None:
            io["goal"][:] = goal
            step = self._step
            args = (self._mem, at["x"], at["goal"])
        else:  # row 0 is the goal the step starts from
            T, ng = self.ocp.horizon + 1, np.size(goal)
            step = self._step_window
            window = np.ascontiguousarray(np.broadcast_to(goal, (T, ng)) if window is None else window, dtype=float)
            args = (self._mem, at["x"], window.ctypes.data)
            if self._set_plan is not None:  # a library with obstacles takes them (NULL: its own)
                moved = None if obstacles is None else np.ascontiguousarray(obstacles, dtype=float)
                args += (None if moved is None else moved.ctypes.data,)
        t0 = time.perf_counter()
        step(*args, at["u"], self._status_ptr, at["split"])
        self.step_seconds = time.perf_counter() - t0
        self._knots(self._mem, at["knots"])
        u, knots = io["u"].copy(), io["knots"].copy()
        status = STATUSES[self._status.value]
        rc = self._rc(self._mem)
        certificate = self.certificate() if status == SUCCESS or rc >= CERT_CODE else None  # a QP solved
        reason = c_reason(self._reason(self._mem))
        raw = (
            f"{self.name}_step: {reason}"
            if status != SUCCESS and rc == 0 and reason is not None
            else _explain_rc(self.name, self.qp, rc, certificate.residuals if certificate else ())
        )
        model, build_s, solve = (float(t) for t in io["split"])
        x_pred = None
        if self._states is not None and status == SUCCESS:
            x_pred = np.empty((self.ocp.horizon + 1, self.ocp.nx))
            if self._states(self._mem, x_pred):
                x_pred = None
        times = {"model": model, "build": build_s, "solve": solve}
        knots = knots.reshape(self.ocp.knots, self.ocp.nu)
        if status != SUCCESS and self._step_start is not None:  # this controller's own step (solve)
            return self.fallback(status, raw, times, reason=reason)
        # A refused step of another controller's (LinearMPC's C step), which answers it itself: the library's own
        # fallback, without Controller.fallback's rollout and plan check (on the Panda with 10 obstacles they took
        # 11-19 ms of each refused step, beside a C step of 1.2 ms)
        refused = status != SUCCESS
        return Solution(
            u=u,
            knots=knots,
            status=status,
            raw_status=raw,
            times=times,
            certificate=certificate,
            x_pred=x_pred,
            fallback=refused,
            path="fallback (C plan)" if refused else "",
            reason=None if status == SUCCESS else reason,
        )


def _check_digest(lib, name: str, lib_path: Path, ocp: OCP) -> None:
    """A ValueError, in one line, where ``lib`` was exported for another OCP than ``ocp`` (:mod:`ocpkit.export.digest`:
    its sizes, weights, bounds, model or task) or carries no digest (exported before ocpkit wrote one)."""
    try:
        stored = getattr(lib, f"{name}_ocp_digest")
    except AttributeError:
        raise ValueError(
            f"library {lib_path} has no {name}_ocp_digest (exported by an older ocpkit): its OCP cannot "
            "be checked; export and build it again"
        ) from None
    stored.restype = ctypes.c_char_p
    differs = differences(stored().decode(), ocp)
    if differs:
        order = " (library vs ocp)" if " vs " in differs else ""
        raise ValueError(
            f"library {lib_path} was exported for another OCP: {differs}{order}; export and build it again for this OCP"
        )


def c_reason(code: int) -> Reason | None:
    """The :class:`Reason` of the library's reason code (``<name>_last_reason``: 1 + its index in REASONS; 0 none)."""
    return REASONS[code - 1] if 0 < code <= len(REASONS) else None


def _explain_rc(name: str, qp: str, rc: int, residuals) -> str:
    """The raw status of a C step whose solver (``qp``) returned ``rc`` (``residuals``: its certificate)."""
    if CERT_CODE <= rc < CERT_CODE + len(TESTS):
        test = TESTS[rc - CERT_CODE]
        return (
            f"{name}_qp_solve returned 0 but certificate failed: {test} residual "
            f"{residuals[rc - CERT_CODE]:.3g} > {CERT_TOL:.0e}"
        )
    if rc == ILL_CONDITIONED:
        return (
            f"{name}: Hessian ill-conditioned (rounding beyond {ROUNDING_MARGIN:g} x the input weight's "
            f"curvature): the prediction model diverges over the horizon"
        )
    if qp == "daqp" and rc in DAQP_EXIT:
        return f"{name}_qp_solve returned {rc}: {daqp_exit_name(rc)}"
    return f"{name}_qp_solve returned {rc}"
