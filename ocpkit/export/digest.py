"""The OCP an export was made for, field by field: written into the library (``<name>_ocp_digest``) and compared by
:class:`~ocpkit.export.ExportedMPC` with the OCP it is loaded with, so a library exported for other weights, bounds,
dynamics or task is refused by name instead of solving with its own data.

The digest is a list of ``field value`` entries: sizes and settings as their values (``knots 5``), arrays as a
hash of their float64 bytes, CasADi expressions (the model, a goal input, the task's residuals and robot spheres)
as a hash of their serialization — which depends on CasADi's version, recorded as the entry ``casadi``."""

from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from ocpkit.model.ocp import OCP

FORMAT = "ocpkit-ocp-digest 1"  # the first entry: the digest's own format
_SERIALIZED = ("model", "goal_input", "task_terms", "robot_spheres")  # hashes of CasADi's serialization
_VALUES = ("nx", "nu", "knots", "horizon", "dt", "substeps", "integrator", "targets", "margin")  # as they are


def _hash(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def _arrays(*values) -> str:
    """The hash of arrays' shapes and float64 bytes (-0.0 counted as 0.0)."""
    parts = [np.asarray(v, dtype=float) + 0.0 for v in values]
    return _hash(b"".join(repr(p.shape).encode() + np.ascontiguousarray(p).tobytes() for p in parts))


def _functions(*functions) -> str:
    return _hash("".join(f.serialize() for f in functions).encode())


def ocp_entries(ocp: OCP) -> list[str]:
    """The digest of ``ocp`` as its ``field value`` entries, :data:`FORMAT` first."""
    model, tf = ocp.model, ocp.task_functions
    goal_input = getattr(ocp, "goal_input", None)
    fields = {
        "nx": ocp.nx,
        "nu": ocp.nu,
        "knots": ocp.knots,
        "horizon": ocp.horizon,
        "dt": repr(ocp.dt),
        "substeps": ocp.substeps,
        "integrator": ocp.integrator,
        "casadi": ca.__version__,
        "model": _functions(ca.Function("f", [model.x, model.u], [model.xdot])),
        "goal_input": "none" if goal_input is None else _functions(goal_input),
        "Q": _arrays(ocp.Q),
        "R": _arrays(ocp.R),
        "Q_terminal": _arrays(ocp.Q_terminal),
        "u_goal": _arrays(ocp.u_goal),
        "u_goal_gain": _arrays(ocp.u_goal_gain),
        "u_min": _arrays(ocp.u_min),
        "u_max": _arrays(ocp.u_max),
        "x_min": _arrays(ocp.x_min),
        "x_max": _arrays(ocp.x_max),
        "parameterization": ocp.parameterization.kind + ":" + _arrays(ocp.parameterization.basis),
        "targets": ocp.ng - ocp.nx,
    }
    if tf is None:
        fields.update(task_terms="none", task_weights="none", obstacles="none", robot_spheres="none", margin="none")
    else:
        fields.update(
            task_terms=_functions(tf.stage_residual, tf.terminal_residual),
            task_weights=_arrays(tf.stage_weight, tf.terminal_weight),
            obstacles=_arrays(tf.table),
            robot_spheres=_functions(tf.spheres) if tf.pairs else "none",
            margin=repr(ocp.task.margin),
        )
    return [FORMAT] + [f"{key} {value}" for key, value in fields.items()]


def _parse(text: str) -> dict[str, str]:
    return dict(entry.partition(" ")[::2] for entry in text.split("; "))


def differences(stored: str, ocp: OCP) -> str:
    """What differs between a library's digest ``stored`` and ``ocp`` ("" for nothing), in words: "Q differs",
    "knots 5 vs 7" (the library's value first)."""
    have, want = _parse(stored), _parse("; ".join(ocp_entries(ocp)))
    kind = FORMAT.split()[0]
    if have.get(kind) != want[kind]:  # another format's entries are not comparable
        return f"digest format {have.get(kind, 'unknown')} vs {want[kind]}"
    words = []
    for key, value in want.items():
        if key in (kind, "casadi") or have.get(key) == value:
            continue
        words.append(f"{key} {have.get(key, 'absent')} vs {value}" if key in _VALUES else f"{key} differs")
    text = ", ".join(words)
    if have.get("casadi") != want["casadi"] and any(w.split()[0] in _SERIALIZED for w in words):
        text += (
            f" (exported with CasADi {have.get('casadi')}, running {want['casadi']}: its serialization may differ too)"
        )
    return text
