"""Rigid-body dynamics of kinematic trees of revolute, continuous and prismatic joints as CasADi expressions.

The robots of the paper (Puma 560, eq. puma_dynamics; the N-link robots, eq. threelink; the Baxter arm)
and any robot read from a URDF obey the canonical form

    M(q) q̈ + C(q, q̇) q̇ + g(q) + b q̇ = τ,      h(q, q̇) = C(q, q̇) q̇ + g(q).

A :class:`Chain` reads the kinematics and inertias of a tree of 1-DoF joints (revolute about any axis,
continuous, or prismatic along any axis: a serial arm, or an arm with two gripper fingers on its hand) from
a pinocchio ``Model`` (built from a URDF or in code) and evaluates Featherstone's recursive algorithms on
CasADi symbols, in pinocchio's conventions (local joint frames, spatial vectors [linear; angular], gravity as
a base acceleration, rotor inertia as ``model.armature``):

* :meth:`Chain.aba` — the articulated-body algorithm, q̈ = M⁻¹(τ − h), O(n), no matrix inverse;
* :meth:`Chain.crba` — the composite-rigid-body algorithm, M(q) (with the armature on its diagonal);
* :meth:`Chain.rnea` — recursive Newton–Euler inverse dynamics, :meth:`Chain.bias` h = RNEA(q, q̇, 0) and
  :meth:`Chain.gravity` g(q) = RNEA(q, 0, 0), the torques that hold q at rest;
* :meth:`Chain.forward_dynamics` — q̈ with viscous damping b q̇, smoothed Coulomb friction and the paper's
  error multiplier.

:func:`load_urdf` is the route from a URDF: pinocchio parses it (fixed joints merged into their links, joint
damping, friction and effort limits read), and joints named in ``locked_joints`` are frozen at a position.
pinocchio is the numerical reference in the tests; every controller sees only these CasADi expressions.
The recursions use plain 3-vector / 3×3 block algebra so that CasADi's SX simplification drops every
structural zero of the joint axes and placements.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
# pinocchio joint kind -> (revolute?, axis in the joint frame); None: the axis is read from the joint.
_JOINTS = {
    "JointModelRX": (True, _X),
    "JointModelRY": (True, _Y),
    "JointModelRZ": (True, _Z),
    "JointModelRUBX": (True, _X),
    "JointModelRUBY": (True, _Y),
    "JointModelRUBZ": (True, _Z),
    "JointModelRevoluteUnaligned": (True, None),
    "JointModelRevoluteUnboundedUnaligned": (True, None),
    "JointModelPX": (False, _X),
    "JointModelPY": (False, _Y),
    "JointModelPZ": (False, _Z),
    "JointModelPrismaticUnaligned": (False, None),
}
# Rotation entries within this of 0 or ±1 are snapped to exact values (URDF angles such as 1.57079632679
# leave 1e-12 residues); that keeps SX expressions free of terms that are zero in the true kinematics.
_SNAP = 1e-10


class Chain:
    """A kinematic tree of n one-DoF joints (revolute or prismatic) read from a pinocchio Model.

    Joint i (1-based in pinocchio, listed parents first) has a parent joint, a constant placement (R_i, p_i)
    in its parent's frame, a unit axis a_i in its own frame — a rotation about a_i (revolute, q_i in rad) or
    a translation along it (prismatic, q_i in m) —, a rigid-body inertia (mass m_i, centre of mass c_i,
    rotational inertia about the centre of mass) and a rotor inertia (armature) added to M's diagonal.
    Continuous joints (pinocchio's unbounded revolute, two configuration entries cos/sin) are one angle here.
    """

    def __init__(self, model):
        try:
            import pinocchio as pin
        except ImportError as err:  # pragma: no cover - pin is a hard dependency
            raise ImportError("ocpkit.model.rigid_body needs pinocchio (pip install pin)") from err
        if not isinstance(model, pin.Model):
            raise TypeError(f"model must be a pinocchio.Model, got {type(model).__name__}")
        n = model.njoints - 1
        if n < 1:
            raise ValueError("model must have at least one joint")
        if model.nv != n:
            raise ValueError(f"model must hold 1-DoF joints only (revolute or prismatic): nv={model.nv}, joints={n}")
        self.n = n
        self.names = [model.names[i] for i in range(1, n + 1)]
        self.parents, self.revolute = [], []
        self.axes, self.rotations, self.translations = [], [], []
        self.masses, self.coms, self.inertias = [], [], []
        for i in range(1, n + 1):
            joint = model.joints[i]
            kind = joint.shortname()
            if kind not in _JOINTS:
                raise ValueError(
                    f"model joint {model.names[i]!r} is {kind}; only 1-DoF revolute and prismatic "
                    "joints are supported (lock the others with locked_joints=)"
                )
            if joint.idx_v != i - 1:
                raise ValueError(f"model joint {model.names[i]!r} has velocity index {joint.idx_v}, expected {i - 1}")
            revolute, axis = _JOINTS[kind]
            if axis is None:
                axis = _joint_axis(model, i, revolute)
            parent = model.parents[i] - 1  # -1: the fixed base
            if parent >= i - 1:
                raise ValueError(f"model joint {model.names[i]!r} is listed before its parent")
            placement = model.jointPlacements[i]
            body = model.inertias[i]
            self.parents.append(parent)
            self.revolute.append(revolute)
            self.axes.append(_snap(np.asarray(axis, dtype=float)))
            self.rotations.append(_snap(np.asarray(placement.rotation, dtype=float)))
            self.translations.append(np.asarray(placement.translation, dtype=float).copy())
            self.masses.append(float(body.mass))
            self.coms.append(np.asarray(body.lever, dtype=float).copy())
            self.inertias.append(np.asarray(body.inertia, dtype=float).copy())
        # Motion subspace S_i = (linear, angular): (0, a) for a revolute joint, (a, 0) for a prismatic one.
        self._S = [(_zeros(), ca.SX(a)) if rev else (ca.SX(a), _zeros()) for a, rev in zip(self.axes, self.revolute)]
        self.armature = np.asarray(model.armature, dtype=float).copy()
        self.gravity_vector = np.asarray(model.gravity.linear, dtype=float).copy()

    def __repr__(self):
        kinds = "".join("R" if r else "P" for r in self.revolute)
        return f"Chain(n={self.n}, joints={kinds}, gravity={self.gravity_vector.tolist()})"

    @property
    def serial(self) -> bool:
        """True when every joint's parent is the joint before it (an unbranched chain)."""
        return all(p == i - 1 for i, p in enumerate(self.parents))

    # --- the three recursive algorithms -------------------------------------------------------------

    def aba(self, q, qd, tau, *, gravity: bool = True):
        """Forward dynamics q̈ = M(q)⁻¹ (τ − h(q, q̇)) by the articulated-body algorithm (O(n)).

        ``gravity=False`` drops g(q), e.g. for an arm whose servo compensates gravity.
        """
        q, qd, tau = (self._vector(v, name) for v, name in ((q, "q"), (qd, "qd"), (tau, "tau")))
        n, par = self.n, self.parents
        X, Sq, v, c, IA, pA = [None] * n, [None] * n, [None] * n, [None] * n, [None] * n, [None] * n
        for i in range(n):
            X[i] = self._transform(i, q[i])
            Sq[i] = _scale(self._S[i], qd[i])  # joint velocity S q̇
            vi = (_zeros(), _zeros()) if par[i] < 0 else _motion_inv(X[i], v[par[i]])
            v[i] = (vi[0] + Sq[i][0], vi[1] + Sq[i][1])
            c[i] = _motion_cross(v[i], Sq[i])  # v × S q̇ (bias acceleration)
            IA[i] = self._body(i)
            pA[i] = _force_cross(v[i], _inertia_times(IA[i], v[i]))
        U, D, u = [None] * n, [None] * n, [None] * n
        for i in reversed(range(n)):
            U[i] = _inertia_times(IA[i], self._S[i])  # U = I^A S
            D[i] = _dot(self._S[i], U[i]) + self.armature[i]
            u[i] = tau[i] - _dot(self._S[i], pA[i])
            p = par[i]
            if p >= 0:
                A, B, C = IA[i]
                Ia = (
                    A - ca.mtimes(U[i][0], U[i][0].T) / D[i],
                    B - ca.mtimes(U[i][0], U[i][1].T) / D[i],
                    C - ca.mtimes(U[i][1], U[i][1].T) / D[i],
                )
                ff = _inertia_times(Ia, c[i])
                pa = (pA[i][0] + ff[0] + U[i][0] * (u[i] / D[i]), pA[i][1] + ff[1] + U[i][1] * (u[i] / D[i]))
                IA[p] = _add_inertia(IA[p], _inertia_act(X[i], Ia))
                fp = _force_act(X[i], pa)
                pA[p] = (pA[p][0] + fp[0], pA[p][1] + fp[1])
        qdd, acc = [None] * n, [None] * n
        base = (ca.SX(-self.gravity_vector) if gravity else _zeros(), _zeros())
        for i in range(n):
            ai = _motion_inv(X[i], base if par[i] < 0 else acc[par[i]])
            ai = (ai[0] + c[i][0], ai[1] + c[i][1])
            qdd[i] = (u[i] - ca.dot(U[i][0], ai[0]) - ca.dot(U[i][1], ai[1])) / D[i]
            acc[i] = (ai[0] + self._S[i][0] * qdd[i], ai[1] + self._S[i][1] * qdd[i])
        return ca.vertcat(*qdd)

    def crba(self, q):
        """The joint-space inertia matrix M(q) by the composite-rigid-body algorithm (armature included)."""
        q = self._vector(q, "q")
        n, par = self.n, self.parents
        X = [self._transform(i, q[i]) for i in range(n)]
        Ic = [self._body(i) for i in range(n)]
        M = ca.SX.zeros(n, n)
        for i in reversed(range(n)):
            F = _inertia_times(Ic[i], self._S[i])  # I^c S: force of a unit joint rate
            M[i, i] = _dot(self._S[i], F) + self.armature[i]
            j = i
            while par[j] >= 0:  # up the ancestors of i
                F = _force_act(X[j], F)
                j = par[j]
                M[i, j] = M[j, i] = _dot(self._S[j], F)
            if par[i] >= 0:
                Ic[par[i]] = _add_inertia(Ic[par[i]], _inertia_act(X[i], Ic[i]))
        return M

    def rnea(self, q, qd, qdd, *, gravity: bool = True):
        """Inverse dynamics τ = M(q) q̈ + h(q, q̇) by recursive Newton–Euler."""
        q, qd, qdd = (self._vector(v, name) for v, name in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
        n, par = self.n, self.parents
        X, f, v, acc = [None] * n, [None] * n, [None] * n, [None] * n
        base_v = (_zeros(), _zeros())
        base_a = (ca.SX(-self.gravity_vector) if gravity else _zeros(), _zeros())
        for i in range(n):
            X[i] = self._transform(i, q[i])
            S = self._S[i]
            Sq = _scale(S, qd[i])
            vp = _motion_inv(X[i], base_v if par[i] < 0 else v[par[i]])
            v[i] = (vp[0] + Sq[0], vp[1] + Sq[1])
            ap = _motion_inv(X[i], base_a if par[i] < 0 else acc[par[i]])
            cr = _motion_cross(v[i], Sq)
            acc[i] = (ap[0] + cr[0] + S[0] * qdd[i], ap[1] + cr[1] + S[1] * qdd[i])
            body = self._body(i)
            fi = _inertia_times(body, acc[i])
            fv = _force_cross(v[i], _inertia_times(body, v[i]))
            f[i] = (fi[0] + fv[0], fi[1] + fv[1])
        tau = [None] * n
        for i in reversed(range(n)):
            tau[i] = _dot(self._S[i], f[i]) + self.armature[i] * qdd[i]
            if par[i] >= 0:
                fp = _force_act(X[i], f[i])
                f[par[i]] = (f[par[i]][0] + fp[0], f[par[i]][1] + fp[1])
        return ca.vertcat(*tau)

    def bias(self, q, qd, *, gravity: bool = True):
        """h(q, q̇) = C(q, q̇) q̇ + g(q): RNEA with q̈ = 0."""
        return self.rnea(q, qd, ca.SX.zeros(self.n), gravity=gravity)

    def gravity(self, q):
        """g(q): the joint torques (forces on prismatic joints) that hold the robot at rest at q."""
        zero = ca.SX.zeros(self.n)
        return self.rnea(q, zero, zero)

    def forward_dynamics(
        self,
        q,
        qd,
        tau,
        *,
        damping=0.0,
        friction=0.0,
        friction_velocity: float = 0.01,
        inertia_scale: float = 1.0,
        gravity: bool = True,
    ):
        """q̈ of  e M(q) q̈ + h(q, q̇) + b q̇ + f tanh(q̇ / v_f) = τ  with the paper's error multiplier e on M(q).

        Exact and O(n) without any inverse: e M q̈ = τ' − h  ⇔  q̈ = ABA(q, q̇, τ') / e with τ' = τ − b q̇ − …,
        because the ABA returns M⁻¹(τ' − h). The same scale applies to the armature (part of M).
        ``damping`` b and ``friction`` f (Coulomb, smoothed over ``friction_velocity`` v_f so that the
        dynamics stay differentiable) are scalars or one coefficient per joint.
        """
        if isinstance(inertia_scale, bool) or not np.isfinite(inertia_scale) or inertia_scale <= 0:
            raise ValueError(f"inertia_scale must be finite and > 0, got {inertia_scale!r}")
        b = self.coefficients(damping, "damping")
        fc = self.coefficients(friction, "friction")
        if isinstance(friction_velocity, bool) or not np.isfinite(friction_velocity) or friction_velocity <= 0:
            raise ValueError(f"friction_velocity must be finite and > 0, got {friction_velocity!r}")
        qd = self._vector(qd, "qd")
        tau = self._vector(tau, "tau")
        if np.any(b):
            tau = tau - ca.DM(b) * qd
        if np.any(fc):
            tau = tau - ca.DM(fc) * ca.tanh(qd / float(friction_velocity))
        qdd = self.aba(q, qd, tau, gravity=gravity)
        return qdd if inertia_scale == 1.0 else qdd / float(inertia_scale)

    def coefficients(self, value, name: str) -> np.ndarray:
        """A scalar or one value per joint as n finite values >= 0 (a ValueError naming ``name`` otherwise)."""
        try:
            arr = np.asarray(value, dtype=float)
            out = np.broadcast_to(arr, (self.n,)).copy() if arr.ndim == 0 else arr
        except (TypeError, ValueError):
            out = None
        if out is None or out.shape != (self.n,) or not np.all(np.isfinite(out)) or np.any(out < 0):
            raise ValueError(f"{name} must be a finite scalar or {self.n} values >= 0, got {value!r}")
        return out

    # --- helpers ----------------------------------------------------------------------------------

    def _vector(self, value, name):
        v = ca.SX(value) if not isinstance(value, ca.SX) else value
        if v.shape != (self.n, 1):
            raise ValueError(f"{name} must be a column of {self.n} entries, got shape {v.shape}")
        return v

    def _transform(self, i, qi):
        """(R, p) of joint i's frame in its parent's: the constant placement times the joint's own motion
        (a rotation about a_i, or a translation along it)."""
        R0, p0 = self.rotations[i], self.translations[i]
        if self.revolute[i]:
            return ca.mtimes(ca.SX(R0), _rotation(self.axes[i], qi)), ca.SX(p0)
        return ca.SX(R0), ca.SX(p0) + ca.SX(R0 @ self.axes[i]) * qi

    def _body(self, i):
        """The rigid-body inertia of link i as blocks (A, B, C): f = A v + B ω, n = Bᵀ v + C ω (origin frame)."""
        m, c, Ic = self.masses[i], self.coms[i], self.inertias[i]
        cx = _skew_np(c)
        return ca.SX(m * np.eye(3)), ca.SX(-m * cx), ca.SX(Ic - m * cx @ cx)


def _joint_axis(model, i: int, revolute: bool) -> np.ndarray:
    """The unit axis of 1-DoF joint i in its own frame, read from its motion subspace S = [linear; angular] at its
    neutral configuration (pinocchio exposes no ``axis`` on an unbounded revolute joint)."""
    import pinocchio as pin

    joint = model.joints[i]
    data = joint.createData()
    joint.calc(data, pin.neutral(model)[joint.idx_q : joint.idx_q + joint.nq])
    S = np.asarray(data.S, dtype=float).ravel()
    axis = S[3:] if revolute else S[:3]
    return axis / np.linalg.norm(axis)


def position_limits(model) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper): each 1-DoF joint's position limits in q's order (one entry per joint, not per pinocchio
    configuration entry); −∞, +∞ for a continuous joint, whose cos/sin bounds in pinocchio are no angle limits."""
    lo, hi = np.asarray(model.lowerPositionLimit, dtype=float), np.asarray(model.upperPositionLimit, dtype=float)
    joints = [model.joints[i] for i in range(1, model.njoints)]
    return (
        np.array([lo[j.idx_q] if j.nq == 1 else -np.inf for j in joints]),
        np.array([hi[j.idx_q] if j.nq == 1 else np.inf for j in joints]),
    )


def _snap(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    for target in (0.0, 1.0, -1.0):
        a[np.abs(a - target) < _SNAP] = target
    return a


def _zeros():
    return ca.SX.zeros(3, 1)


def _scale(m, s):
    return m[0] * s, m[1] * s


def _dot(S, f):
    """Sᵀ f for a motion subspace S = (linear, angular) and a force f = (force, moment)."""
    return ca.dot(S[0], f[0]) + ca.dot(S[1], f[1])


def _motion_cross(m1, m2):
    """Spatial motion cross product m1 × m2 = (ω1 × v2 + v1 × ω2, ω1 × ω2)."""
    v1, w1 = m1
    v2, w2 = m2
    return ca.cross(w1, v2) + ca.cross(v1, w2), ca.cross(w1, w2)


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


def load_urdf(path, *, locked_joints=(), locked_positions=None):
    """The pinocchio Model of a URDF with the joints named in ``locked_joints`` frozen.

    pinocchio merges fixed joints into their links and reads each joint's ``<dynamics damping friction>``
    (``model.damping``, ``model.friction``) and ``<limit effort lower upper>``. A locked joint stays at
    ``locked_positions[name]`` (default 0, clipped into its limits); its link's inertia moves onto its parent
    (``pinocchio.buildReducedModel``); a continuous joint's position is its angle. Unknown joint names raise a
    ValueError listing the joints.
    """
    import pinocchio as pin

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"URDF file not found: {str(path)!r}")
    try:
        model = pin.buildModelFromUrdf(str(path))
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"{str(path)!r} is not a URDF pinocchio can read: {exc}") from None
    if isinstance(locked_joints, str):
        locked_joints = [locked_joints]
    locked = list(locked_joints or ())
    positions = dict(locked_positions or {})
    joints = [model.names[i] for i in range(1, model.njoints)]
    unknown = sorted((set(locked) | set(positions)) - set(joints))
    if unknown:
        raise ValueError(f"{path.name} has no joint {unknown[0]!r}; its joints: {', '.join(joints)}")
    stray = sorted(set(positions) - set(locked))
    if stray:
        raise ValueError(f"locked_positions names {stray[0]!r}, which is not in locked_joints")
    if not locked:
        return model
    q = pin.neutral(model)
    lo, hi = model.lowerPositionLimit, model.upperPositionLimit
    for name in locked:
        joint = model.joints[model.getJointId(name)]
        continuous = joint.nq == 2 and joint.nv == 1  # an unbounded revolute joint: q holds (cos θ, sin θ)
        if joint.nq != 1 and not continuous:
            if name in positions:
                raise ValueError(f"locked_positions: joint {name!r} has {joint.nq} configuration entries")
            continue
        k = joint.idx_q
        value = float(positions.get(name, np.clip(0.0, lo[k], hi[k]) if lo[k] <= hi[k] and not continuous else 0.0))
        if not np.isfinite(value):
            raise ValueError(f"locked_positions[{name!r}] must be finite, got {value!r}")
        q[k : k + joint.nq] = (np.cos(value), np.sin(value)) if continuous else value
    return pin.buildReducedModel(model, [model.getJointId(name) for name in locked], q)
