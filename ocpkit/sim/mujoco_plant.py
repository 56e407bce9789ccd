"""MuJoCo as the plant: a controller tested in the simulator robotics people use (issue 34).

A :class:`MuJoCoPlant` stands wherever :func:`ocpkit.sim.simulate.simulate` takes a plant. Each control period dt it
sets MuJoCo's q, q̇ of the controlled joints from x = [q, q̇], holds the input u as joint torques (one motor per
joint, gear 1: forces on prismatic joints) and takes ``substeps`` MuJoCo steps of dt / substeps with the
``integrator`` chosen — "rk4" by default, the same method and sub-step as ocpkit's own plant, so the two agree to
round-off on the same robot; "implicit" or "implicitfast" (damping, and with them constraint forces, implicit in
q̇: stable at larger steps, first order) or "euler" (semi-implicit) —, then reads q, q̇ back.

Where the robot comes from:

* a problem described by a :class:`ocpkit.model.rigid_body.Chain` (``nlink:N``, ``puma560``, a user's Chain-based
  problem): an MJCF written from the Chain — one body per joint at its placement, its joint axis, mass, centre of mass
  and inertia, the rotor inertia as ``armature``, the problem's viscous damping b as joint ``damping`` (the ODE
  M q̈ + h + b q̇ = τ of :meth:`Chain.forward_dynamics`), gravity as the Chain's, the joint limits as ranges;
* a URDF problem (``urdf:…``, ``panda``): MuJoCo's own URDF import of the same file, the joints the problem
  locked removed (held at 0, load_urdf's default) and the problem's damping set on the others; its collision meshes
  left out (``meshes=True`` keeps them: most robot files name ``package://`` meshes MuJoCo cannot open, and the
  dynamics need none); a continuous joint is a hinge without range;
* a user's MJCF (``mjcf=``): ``joint_map`` says which of its joints are the problem's, in q's order; the file's
  actuators are replaced by torque motors on those joints. Its joints outside the map evolve on their own.

Every plant, a user's MJCF included, is checked against the problem's dynamics at construction (q̈ at seeded states,
before the options below, MuJoCo's constraints off): a robot that is not the problem's (a mass, an axis, a joint
type of its own) or a problem whose ``dynamics`` is not its Chain's ODE is refused rather than simulated as
something else; ``check_tolerance`` (relative to the largest |q̈|) loosens the check, None skips it.

The effects ocpkit's model leaves out are options, all off by default: ``frictionloss`` (dry joint friction, N·m, a
MuJoCo constraint) and ``armature`` (rotor inertia, kg·m²), both added to the source's own;
``ctrlrange`` (actuator limits: MuJoCo clamps u); ``floor`` (a plane at that height that the links, capsules of
the problem's ``link_radius`` between the joints, touch); ``limits`` (the joint ranges as constraints).
"""

from __future__ import annotations

import copy

import numpy as np

from ocpkit._checks import choice, integer, positive
from ocpkit.sim.mujoco_robot import (
    apply_options,
    chain_spec,
    exact_inertias,
    map_joints,
    mjcf_spec,
    set_problem_dynamics,
    urdf_spec,
)

INTEGRATORS = ("rk4", "implicit", "implicitfast", "euler")
_MJ_INTEGRATORS = {
    "rk4": "mjINT_RK4",
    "implicit": "mjINT_IMPLICIT",
    "implicitfast": "mjINT_IMPLICITFAST",
    "euler": "mjINT_EULER",
}
# MuJoCo resets its data (to qpos0) when q, q̇ or q̈ turn non-finite or huge, and zeros every input when one is, and
# counts a warning: a run must fail there instead of continuing from the reset state or without its inputs.
_DIVERGED = {"mjWARN_BADQPOS": "q", "mjWARN_BADQVEL": "q̇", "mjWARN_BADQACC": "q̈", "mjWARN_BADCTRL": "u"}
# The construction check's default tolerance (check_tolerance): q̈ of MuJoCo and of the problem's plant at seeded
# states agree to this, relative to the largest |q̈|; round-off gives ~1e-12, a different robot or ODE O(1), an MJCF
# written with rounded numbers their rounding.
CHECK_TOLERANCE = 1e-6


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise ImportError('MuJoCoPlant needs MuJoCo: pip install "ocpkit[mujoco]"') from None
    return mujoco


class MuJoCoPlant:
    """A plant simulated by MuJoCo for the problem ``problem`` (a Problem or a spec such as "nlink:3").

    ``mjcf``: a user's MJCF file instead of the robot generated from the problem; ``joint_map`` then names its
    joints: a sequence of MJCF joint names in q's order, or a dict {problem joint name: MJCF joint name} (default:
    the problem's own joint names). ``integrator``: one of :data:`INTEGRATORS` (it and the time step replace an
    MJCF's own). ``frictionloss``, ``armature``:
    scalars or one value per joint (>= 0) added to the source's own. ``ctrlrange``: (low, high), scalars or one
    value per input. ``floor``: the height (m) of a plane under the robot, or None. ``limits``: the joint ranges as
    MuJoCo constraints (None: off for a generated or URDF robot, as ocpkit's model has none; the file's own for
    an MJCF). ``meshes``: keep a URDF's collision meshes (each file must exist). ``check_tolerance``: how far MuJoCo's
    q̈ may be from the problem's, relative to the largest |q̈| (None: no check). See the module docstring for the
    sources and conventions.
    """

    def __init__(
        self,
        problem,
        *,
        mjcf=None,
        joint_map=None,
        integrator: str = "rk4",
        frictionloss=0.0,
        armature=0.0,
        ctrlrange=None,
        floor: float | None = None,
        limits: bool | None = None,
        meshes: bool = False,
        check_tolerance: float | None = CHECK_TOLERANCE,
    ):
        mujoco = _mujoco()
        from ocpkit import problems
        from ocpkit.model.dynamics import Model
        from ocpkit.model.problem import Problem

        problem = problems.make(problem)
        if not isinstance(problem, Problem):  # pragma: no cover - problems.make returns Problems only
            raise TypeError(f"problem must be an ocpkit Problem or spec, got {type(problem).__name__}")
        plant = problem.plant()
        nq = plant.second_order
        if nq is None or plant.nu != nq:
            raise ValueError(
                f"MuJoCoPlant needs a state x = [q, q̇] and one torque per joint; problem "
                f"{problem.name!r} has nx = {plant.nx}, nu = {plant.nu}"
            )
        if type(plant).rk4 is not Model.rk4:
            raise ValueError(
                f"problem {problem.name!r} has a plant of its own ({type(plant).__name__}: its inputs "
                "are not joint torques), which MuJoCoPlant does not reproduce"
            )
        self.problem, self.nx, self.nu = problem, plant.nx, plant.nu
        self.state_names, self.input_names = plant.state_names, plant.input_names
        self.integrator = choice(integrator, INTEGRATORS, "integrator")
        chain = getattr(problem, "chain", None)
        self.joint_names = list(chain.names) if chain is not None else plant.state_names[:nq]
        if mjcf is None and joint_map is not None:
            raise ValueError("joint_map names the joints of an MJCF file: give mjcf= too")
        if limits is not None and not isinstance(limits, bool):
            raise TypeError(f"limits must be True, False or None, got {limits!r}")
        if not isinstance(meshes, bool):
            raise TypeError(f"meshes must be True or False, got {meshes!r}")
        if check_tolerance is not None:
            check_tolerance = positive(check_tolerance, "check_tolerance")
        self.meshes = meshes
        self.options = {
            "frictionloss": _per_joint(frictionloss, nq, "frictionloss"),
            "armature": _per_joint(armature, nq, "armature"),
            "ctrlrange": _ctrlrange(ctrlrange, nq),
            "floor": _floor(floor),
            "limits": limits,
        }
        if mjcf is not None:
            spec, self.source = mjcf_spec(mujoco, mjcf), f"mjcf:{mjcf}"
            self.mj_joints = map_joints(mujoco, spec, joint_map, self.joint_names)
            for actuator in list(spec.actuators):  # someone else's controller: u drives the joints here
                spec.delete(actuator)
        elif getattr(problem, "urdf", None) is not None and chain is not None:
            spec, self.source = urdf_spec(mujoco, problem, meshes), f"urdf:{problem.urdf}"
            self.mj_joints = list(self.joint_names)
        elif chain is not None:
            spec, self.source = chain_spec(mujoco, problem), "chain"
            self.mj_joints = list(self.joint_names)
        else:
            raise ValueError(
                f"problem {problem.name!r} has no rigid-body description (a Chain) to write an MJCF "
                "from; MuJoCoPlant supports nlink:N, puma560, panda, urdf:… and Chain-based problems "
                "of your own, or any problem with an MJCF of yours (mjcf=…, joint_map=…)"
            )
        if meshes and not self.source.startswith("urdf:"):
            raise ValueError(
                f"meshes=True applies to a URDF robot (MuJoCo's import of a URDF problem's file), not to "
                f"the robot from {self.source}"
            )
        if mjcf is None:
            set_problem_dynamics(mujoco, spec, problem, self.mj_joints)
        for name in self.mj_joints:
            spec.add_actuator(name=f"u_{name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT).set_to_motor()
        spec.option.integrator = getattr(mujoco.mjtIntegrator, _MJ_INTEGRATORS[self.integrator])
        if check_tolerance is not None:
            self._check(mujoco, self._compile(mujoco, spec), plant, check_tolerance)
        apply_options(mujoco, spec, self.mj_joints, self.options)
        self.spec = spec
        self.model = self._compile(mujoco, spec)
        self._qpos, self._qvel = _addresses(self.model, self.mj_joints)

    def __repr__(self):
        active = [k for k, v in self.options.items() if v is not None and (not isinstance(v, np.ndarray) or v.any())]
        active += ["meshes"] if self.meshes else []
        return (
            f"MuJoCoPlant({self.problem.name!r}, source={self.source!r}, integrator={self.integrator!r}"
            + "".join(f", {k}" for k in active)
            + ")"
        )

    def xml(self) -> str:
        """The MJCF of the simulated robot (options applied), as MuJoCo writes it; a generated robot's inertias that
        MuJoCo's compiler refuses appear there as its stand-ins (see :func:`ocpkit.sim.mujoco_robot.exact_inertias`)."""
        return self.spec.to_xml()

    def stepper(self, dt: float, substeps: int = 1):
        """F(x, u) -> x⁺ over one control period ``dt``: ``substeps`` MuJoCo steps of dt / substeps with u held.

        Each call makes fresh MuJoCo data, so a run starts from the model's rest state in every joint x does not
        hold (an MJCF's extra joints) and with no contact history.
        """
        mujoco = _mujoco()
        dt, substeps = positive(dt, "dt"), integer(substeps, "substeps", 1)
        model = copy.copy(self.model)  # the time step is this stepper's own
        model.opt.timestep = dt / substeps
        data = mujoco.MjData(model)
        n = self.nx // 2
        diverged = {int(getattr(mujoco.mjtWarning, w)): what for w, what in _DIVERGED.items()}

        def step(x, u):
            x, u = np.asarray(x, dtype=float).ravel(), np.asarray(u, dtype=float).ravel()
            data.qpos[self._qpos], data.qvel[self._qvel], data.ctrl[:] = x[:n], x[n:], u
            before = {w: data.warning[w].number for w in diverged}
            mujoco.mj_step(model, data, substeps)
            bad = [what for w, what in diverged.items() if data.warning[w].number > before[w]]
            if bad:
                raise FloatingPointError(
                    f"MuJoCo found a NaN, inf or huge value in {', '.join(bad)} stepping from "
                    f"x = {x.tolist()}, u = {u.tolist()} and reset its data: the simulation "
                    "diverged (more plant_substeps or a smaller dt may help)"
                )
            return np.concatenate([data.qpos[self._qpos], data.qvel[self._qvel]])

        return step

    def _compile(self, mujoco, spec):
        try:
            model = spec.compile()
        except ValueError as exc:
            raise ValueError(f"MuJoCo cannot compile the robot from {self.source}: {exc}") from None
        if self.source == "chain":
            exact_inertias(mujoco, model, self.problem.chain)
            mujoco.mj_setConst(model, mujoco.MjData(model))  # constants derived from the inertias (constraint scales)
        return model

    def _check(self, mujoco, model, plant, tolerance: float, samples: int = 3):
        """Refuse a robot whose q̈ differs from the problem's plant's at seeded states and inputs by more than
        ``tolerance`` times the largest |q̈| (at least 1), naming the joint nearest the difference.

        Constraints are off here (joint ranges, dry friction, contacts, equalities are MuJoCo's own effects), and
        the velocities are 0 for a problem with Coulomb friction, which ocpkit smooths and MuJoCo does not."""
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        data = mujoco.MjData(model)
        n = self.nx // 2
        qpos, qvel = _addresses(model, self.mj_joints)
        rng = np.random.default_rng(0)
        moving = not np.any(getattr(self.problem, "friction", 0.0))
        gap, residual, scale, torque = np.zeros(n), np.zeros(n), 1.0, 1.0
        for seed in range(samples):
            x = self.problem.sample(seed)[0] + np.r_[np.zeros(n), rng.uniform(-1, 1, n) * moving]
            u = rng.uniform(-1, 1, n)
            data.qpos[qpos], data.qvel[qvel], data.ctrl[:] = x[:n], x[n:], u
            mujoco.mj_forward(model, data)
            expected = np.asarray(plant.f(x, u), dtype=float).ravel()[n:]
            gap = np.maximum(gap, np.abs(data.qacc[qvel] - expected))
            scale = max(scale, float(np.abs(expected).max()))
            # The torques MuJoCo needs for the problem's q̈: a wrong body shows at the joints above it only.
            data.qacc[qvel] = expected
            mujoco.mj_inverse(model, data)
            residual = np.maximum(residual, np.abs(data.qfrc_inverse[qvel] - u))
            torque = max(torque, float(np.abs(data.qfrc_inverse[qvel]).max()))
        if gap.max() <= tolerance * scale:
            return
        depth = [_depth(model, model.joint(name).bodyid[0]) for name in self.mj_joints]
        differs = [k for k in range(n) if residual[k] > tolerance * torque] or [int(np.argmax(gap))]
        joint = model.joint(self.mj_joints[max(differs, key=lambda k: depth[k])])
        hint = (
            "the generated robot follows M(q) q̈ + h(q, q̇) + b q̇ = τ of its Chain; write an MJCF (mjcf=, "
            "joint_map=) for other dynamics"
            if self.source == "chain"
            else "its masses, inertias, axes, joint types, damping or gravity are not the problem's"
        )
        raise ValueError(
            f"MuJoCo's model of {self.problem.name!r} ({self.source}) gives q̈ up to {gap.max():.3g} "
            f"away from the problem's dynamics (|q̈| up to {scale:.3g}, relative {gap.max() / scale:.3g} "
            f"> check_tolerance={tolerance:g}; the deepest joint whose torque differs: {joint.name!r}, "
            f"body {model.body(joint.bodyid[0]).name!r}): {hint}; a larger check_tolerance accepts it, "
            "check_tolerance=None skips this check"
        )


def _depth(model, body: int) -> int:
    """The number of bodies between ``body`` and the world in a compiled model."""
    depth = 0
    while body:
        body, depth = model.body_parentid[body], depth + 1
    return depth


def _addresses(model, joints):
    """The qpos and qvel indices of ``joints`` (names) in a compiled model."""
    ids = [model.joint(name).id for name in joints]
    return np.array([model.jnt_qposadr[i] for i in ids]), np.array([model.jnt_dofadr[i] for i in ids])


def _per_joint(value, n: int, name: str) -> np.ndarray:
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()
    except (TypeError, ValueError):
        arr = None
    if arr is None or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{name} must be a finite scalar or {n} values >= 0, got {value!r}")
    return arr


def _ctrlrange(value, n: int):
    if value is None:
        return None
    try:
        low, high = (np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy() for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"ctrlrange must be (low, high), scalars or {n} values each, got {value!r}") from None
    if np.isnan(low).any() or np.isnan(high).any() or not np.all(low < high):
        raise ValueError(f"ctrlrange must have low < high for every input, got {value!r}")
    return np.stack([low, high])


def _floor(value):
    if value is None:
        return None
    try:
        z = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"floor must be a height in m or None, got {value!r}") from None
    if not np.isfinite(z):
        raise ValueError(f"floor must be a finite height in m, got {value!r}")
    return z
