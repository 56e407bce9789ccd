"""Rigid-body dynamics of serial revolute chains as symbolic CasADi expressions.

The robots of the paper (Puma 560, eq. puma_dynamics; the N-link robots, eq. threelink; the Baxter arm)
obey the canonical form

    M(q) q̈ + C(q, q̇) q̇ + g(q) + b q̇ = τ,      h(q, q̇) = C(q, q̇) q̇ + g(q).

A :class:`Chain` reads the kinematics and inertias of a serial chain of revolute joints from a pinocchio
``Model`` (built from a URDF or in code) and evaluates Featherstone's recursive algorithms on CasADi
symbols, in pinocchio's conventions (local joint frames, spatial vectors [linear; angular], gravity as
a base acceleration, rotor inertia as ``model.armature``):

* :meth:`Chain.aba` — the articulated-body algorithm, q̈ = M⁻¹(τ − h), O(n), no matrix inverse;
* :meth:`Chain.crba` — the composite-rigid-body algorithm, M(q) (with the armature on its diagonal);
* :meth:`Chain.rnea` — recursive Newton–Euler inverse dynamics, and :meth:`Chain.bias` h = RNEA(q, q̇, 0);
* :meth:`Chain.forward_dynamics` — q̈ with viscous damping b q̇ and the paper's error multiplier.

pinocchio is the numerical reference in the tests; every controller sees only these CasADi expressions.
The recursions use plain 3-vector / 3×3 block algebra so that CasADi's SX simplification drops every
structural zero of the joint axes and placements.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0),
         "JointModelRUBX": (1.0, 0.0, 0.0), "JointModelRUBY": (0.0, 1.0, 0.0), "JointModelRUBZ": (0.0, 0.0, 1.0)}
_UNALIGNED = ("JointModelRevoluteUnaligned", "JointModelRevoluteUnboundedUnaligned")
# Rotation entries within this of 0 or ±1 are snapped to exact values (URDF angles such as 1.57079632679
# leave 1e-12 residues); that keeps SX expressions free of terms that are zero in the true kinematics.
_SNAP = 1e-10


class Chain:
    """A serial chain of n revolute joints read from a pinocchio Model, for symbolic dynamics.

    Joint i (1-based in pinocchio) has parent i−1, a constant placement (R_i, p_i) in its parent's frame,
    a unit axis a_i in its own frame, a rigid-body inertia (mass m_i, centre of mass c_i, rotational
    inertia about the centre of mass) and a rotor inertia (armature) added to M's diagonal.
    """

    def __init__(self, model):
        try:
            import pinocchio as pin
        except ImportError as err:  # pragma: no cover - pin is a hard dependency
            raise ImportError("ocpkit.rigid_body needs pinocchio (pip install pin)") from err
        if not isinstance(model, pin.Model):
            raise TypeError(f"model must be a pinocchio.Model, got {type(model).__name__}")
        n = model.njoints - 1
        if n < 1:
            raise ValueError("model must have at least one joint")
        if model.nq != n or model.nv != n:
            raise ValueError(f"model must be a chain of 1-DoF revolute joints: nq={model.nq}, nv={model.nv}, "
                             f"joints={n}")
        self.n = n
        self.names = [model.names[i] for i in range(1, n + 1)]
        self.axes, self.rotations, self.translations = [], [], []
        self.masses, self.coms, self.inertias = [], [], []
        for i in range(1, n + 1):
            joint = model.joints[i]
            if model.parents[i] != i - 1:
                raise ValueError(f"model must be a serial chain: joint {model.names[i]!r} has parent "
                                 f"{model.parents[i]}, expected {i - 1}")
            kind = joint.shortname()
            if kind in _AXES:
                axis = np.array(_AXES[kind])
            elif kind in _UNALIGNED:
                axis = np.asarray(joint.extract().axis, dtype=float)
                axis = axis / np.linalg.norm(axis)
            else:
                raise ValueError(f"model joint {model.names[i]!r} is {kind}; only revolute joints are supported")
            placement = model.jointPlacements[i]
            body = model.inertias[i]
            self.axes.append(_snap(axis))
            self.rotations.append(_snap(np.asarray(placement.rotation, dtype=float)))
            self.translations.append(np.asarray(placement.translation, dtype=float).copy())
            self.masses.append(float(body.mass))
            self.coms.append(np.asarray(body.lever, dtype=float).copy())
            self.inertias.append(np.asarray(body.inertia, dtype=float).copy())
        self._axes = [ca.SX(a) for a in self.axes]
        self.armature = np.asarray(model.armature, dtype=float).copy()
        self.gravity = np.asarray(model.gravity.linear, dtype=float).copy()

    def __repr__(self):
        return f"Chain(n={self.n}, gravity={self.gravity.tolist()})"

    # --- the three recursive algorithms -------------------------------------------------------------

    def aba(self, q, qd, tau, *, gravity: bool = True):
        """Forward dynamics q̈ = M(q)⁻¹ (τ − h(q, q̇)) by the articulated-body algorithm (O(n)).

        ``gravity=False`` drops g(q), e.g. for an arm whose servo compensates gravity.
        """
        q, qd, tau = (self._vector(v, name) for v, name in ((q, "q"), (qd, "qd"), (tau, "tau")))
        n = self.n
        X, S, v, c, IA, pA = [None] * n, [None] * n, [None] * n, [None] * n, [None] * n, [None] * n
        for i in range(n):
            X[i] = self._transform(i, q[i])
            S[i] = self._axes[i] * qd[i]                       # joint velocity S q̇ (angular only)
            vi = (_zeros(), _zeros()) if i == 0 else _motion_inv(X[i], v[i - 1])
            v[i] = (vi[0], vi[1] + S[i])
            c[i] = (ca.cross(v[i][0], S[i]), ca.cross(v[i][1], S[i]))   # v × S q̇ (bias acceleration)
            IA[i] = self._body(i)
            pA[i] = _force_cross(v[i], _inertia_times(IA[i], v[i]))
        U, D, u = [None] * n, [None] * n, [None] * n
        for i in reversed(range(n)):
            A, B, C = IA[i]
            a = self._axes[i]
            U[i] = (ca.mtimes(B, a), ca.mtimes(C, a))                     # U = I^A S
            D[i] = ca.dot(a, U[i][1]) + self.armature[i]
            u[i] = tau[i] - ca.dot(a, pA[i][1])
            if i > 0:
                Ia = (A - ca.mtimes(U[i][0], U[i][0].T) / D[i], B - ca.mtimes(U[i][0], U[i][1].T) / D[i],
                      C - ca.mtimes(U[i][1], U[i][1].T) / D[i])
                ff = _inertia_times(Ia, c[i])
                pa = (pA[i][0] + ff[0] + U[i][0] * (u[i] / D[i]), pA[i][1] + ff[1] + U[i][1] * (u[i] / D[i]))
                IA[i - 1] = _add_inertia(IA[i - 1], _inertia_act(X[i], Ia))
                fp = _force_act(X[i], pa)
                pA[i - 1] = (pA[i - 1][0] + fp[0], pA[i - 1][1] + fp[1])
        qdd = [None] * n
        acc = (ca.SX(-self.gravity) if gravity else _zeros(), _zeros())
        for i in range(n):
            ai = _motion_inv(X[i], acc)
            ai = (ai[0] + c[i][0], ai[1] + c[i][1])
            qdd[i] = (u[i] - ca.dot(U[i][0], ai[0]) - ca.dot(U[i][1], ai[1])) / D[i]
            acc = (ai[0], ai[1] + self._axes[i] * qdd[i])
        return ca.vertcat(*qdd)

    def crba(self, q):
        """The joint-space inertia matrix M(q) by the composite-rigid-body algorithm (armature included)."""
        q = self._vector(q, "q")
        n = self.n
        X = [self._transform(i, q[i]) for i in range(n)]
        Ic = [self._body(i) for i in range(n)]
        M = ca.SX.zeros(n, n)
        for i in reversed(range(n)):
            a = self._axes[i]
            F = (ca.mtimes(Ic[i][1], a), ca.mtimes(Ic[i][2], a))          # I^c S: force of a unit joint rate
            M[i, i] = ca.dot(a, F[1]) + self.armature[i]
            for j in reversed(range(i)):
                F = _force_act(X[j + 1], F)
                M[i, j] = M[j, i] = ca.dot(self._axes[j], F[1])
            if i > 0:
                Ic[i - 1] = _add_inertia(Ic[i - 1], _inertia_act(X[i], Ic[i]))
        return M

    def rnea(self, q, qd, qdd, *, gravity: bool = True):
        """Inverse dynamics τ = M(q) q̈ + h(q, q̇) by recursive Newton–Euler."""
        q, qd, qdd = (self._vector(v, name) for v, name in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
        n = self.n
        X, f = [None] * n, [None] * n
        v = (_zeros(), _zeros())
        acc = (ca.SX(-self.gravity) if gravity else _zeros(), _zeros())
        for i in range(n):
            X[i] = self._transform(i, q[i])
            a = self._axes[i]
            vp = _motion_inv(X[i], v)
            v = (vp[0], vp[1] + a * qd[i])
            ap = _motion_inv(X[i], acc)
            acc = (ap[0] + ca.cross(v[0], a * qd[i]), ap[1] + ca.cross(v[1], a * qd[i]) + a * qdd[i])
            body = self._body(i)
            fi = _inertia_times(body, acc)
            fv = _force_cross(v, _inertia_times(body, v))
            f[i] = (fi[0] + fv[0], fi[1] + fv[1])
        tau = [None] * n
        for i in reversed(range(n)):
            tau[i] = ca.dot(self._axes[i], f[i][1]) + self.armature[i] * qdd[i]
            if i > 0:
                fp = _force_act(X[i], f[i])
                f[i - 1] = (f[i - 1][0] + fp[0], f[i - 1][1] + fp[1])
        return ca.vertcat(*tau)

    def bias(self, q, qd, *, gravity: bool = True):
        """h(q, q̇) = C(q, q̇) q̇ + g(q): RNEA with q̈ = 0."""
        return self.rnea(q, qd, ca.SX.zeros(self.n), gravity=gravity)

    def forward_dynamics(self, q, qd, tau, *, damping=0.0, inertia_scale: float = 1.0, gravity: bool = True):
        """q̈ of  e M(q) q̈ + h(q, q̇) + b q̇ = τ  with the paper's error multiplier e on M(q) only.

        Exact and O(n) without any inverse: e M q̈ = τ − b q̇ − h  ⇔  q̈ = ABA(q, q̇, τ − b q̇) / e,
        because the ABA returns M⁻¹(τ' − h). The same scale applies to the armature (part of M).
        ``damping`` is a scalar b or one coefficient per joint.
        """
        if isinstance(inertia_scale, bool) or not np.isfinite(inertia_scale) or inertia_scale <= 0:
            raise ValueError(f"inertia_scale must be finite and > 0, got {inertia_scale!r}")
        b = np.broadcast_to(np.asarray(damping, dtype=float), (self.n,)) if np.ndim(damping) == 0 \
            else np.asarray(damping, dtype=float)
        if b.shape != (self.n,) or not np.all(np.isfinite(b)) or np.any(b < 0):
            raise ValueError(f"damping must be a finite scalar or {self.n} values >= 0, got {damping!r}")
        qd = self._vector(qd, "qd")
        tau = self._vector(tau, "tau") - ca.DM(b) * qd if np.any(b) else tau
        qdd = self.aba(q, qd, tau, gravity=gravity)
        return qdd if inertia_scale == 1.0 else qdd / float(inertia_scale)

    # --- helpers ----------------------------------------------------------------------------------

    def _vector(self, value, name):
        v = ca.SX(value) if not isinstance(value, ca.SX) else value
        if v.shape != (self.n, 1):
            raise ValueError(f"{name} must be a column of {self.n} entries, got shape {v.shape}")
        return v

    def _transform(self, i, qi):
        """(R, p) of joint i's frame in its parent's: the constant placement times the rotation about a_i."""
        return ca.mtimes(ca.SX(self.rotations[i]), _rotation(self.axes[i], qi)), ca.SX(self.translations[i])

    def _body(self, i):
        """The rigid-body inertia of link i as blocks (A, B, C): f = A v + B ω, n = Bᵀ v + C ω (origin frame)."""
        m, c, Ic = self.masses[i], self.coms[i], self.inertias[i]
        cx = _skew_np(c)
        return ca.SX(m * np.eye(3)), ca.SX(-m * cx), ca.SX(Ic - m * cx @ cx)


def _snap(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    for target in (0.0, 1.0, -1.0):
        a[np.abs(a - target) < _SNAP] = target
    return a


def _zeros():
    return ca.SX.zeros(3, 1)


def _skew_np(p):
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


def _skew(p):
    return ca.vertcat(ca.horzcat(0, -p[2], p[1]), ca.horzcat(p[2], 0, -p[0]), ca.horzcat(-p[1], p[0], 0))


def _rotation(axis: np.ndarray, angle):
    """Rodrigues' rotation about a numeric unit axis (exact zeros for coordinate axes)."""
    c, s = ca.cos(angle), ca.sin(angle)
    K = _skew_np(axis)
    return ca.SX(np.eye(3)) + s * ca.SX(K) + (1 - c) * ca.SX(K @ K)


def _motion_inv(X, m):
    """Motion vector of the parent expressed in the child frame: (Rᵀ(v − p × ω), Rᵀ ω)."""
    R, p = X
    v, w = m
    return ca.mtimes(R.T, v - ca.cross(p, w)), ca.mtimes(R.T, w)


def _force_act(X, f):
    """Force of the child expressed in the parent frame: (R f, R n + p × R f)."""
    R, p = X
    Rf = ca.mtimes(R, f[0])
    return Rf, ca.mtimes(R, f[1]) + ca.cross(p, Rf)


def _force_cross(m, f):
    """Spatial force cross product m ×* f = (ω × f, ω × n + v × f)."""
    v, w = m
    return ca.cross(w, f[0]), ca.cross(w, f[1]) + ca.cross(v, f[0])


def _inertia_times(I, m):
    A, B, C = I
    v, w = m
    return ca.mtimes(A, v) + ca.mtimes(B, w), ca.mtimes(B.T, v) + ca.mtimes(C, w)


def _inertia_act(X, I):
    """Spatial inertia of the child expressed in the parent frame: X* I X⁻¹ in block form."""
    R, p = X
    A, B, C = (ca.mtimes(ca.mtimes(R, M), R.T) for M in I)
    P = _skew(p)
    PA = ca.mtimes(P, A)
    return A, B - ca.mtimes(A, P), C - ca.mtimes(B.T, P) + ca.mtimes(P, B) - ca.mtimes(PA, P)


def _add_inertia(I, J):
    return I[0] + J[0], I[1] + J[1], I[2] + J[2]
