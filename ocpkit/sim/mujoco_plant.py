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
from pathlib import Path

import numpy as np

from ocpkit._checks import choice, integer, positive

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
            spec, self.source = _mjcf_spec(mujoco, mjcf), f"mjcf:{mjcf}"
            self.mj_joints = _map_joints(mujoco, spec, joint_map, self.joint_names)
            for actuator in list(spec.actuators):  # someone else's controller: u drives the joints here
                spec.delete(actuator)
        elif getattr(problem, "urdf", None) is not None and chain is not None:
            spec, self.source = _urdf_spec(mujoco, problem, meshes), f"urdf:{problem.urdf}"
            self.mj_joints = list(self.joint_names)
        elif chain is not None:
            spec, self.source = _chain_spec(mujoco, problem), "chain"
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
            _set_problem_dynamics(mujoco, spec, problem, self.mj_joints)
        for name in self.mj_joints:
            spec.add_actuator(name=f"u_{name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT).set_to_motor()
        spec.option.integrator = getattr(mujoco.mjtIntegrator, _MJ_INTEGRATORS[self.integrator])
        if check_tolerance is not None:
            self._check(mujoco, self._compile(mujoco, spec), plant, check_tolerance)
        _apply_options(mujoco, spec, self.mj_joints, self.options)
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
        MuJoCo's compiler refuses appear there as its stand-ins (see :func:`_exact_inertias`)."""
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
            _exact_inertias(mujoco, model, self.problem.chain)
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


def _mjcf_spec(mujoco, path):
    file = Path(path)
    if not file.is_file():
        raise ValueError(f"mjcf: no such file {str(file)!r}")
    try:
        return mujoco.MjSpec.from_file(str(file))
    except ValueError as exc:
        raise ValueError(f"mjcf: {str(file)!r} is not an MJCF MuJoCo can read: {exc}") from None


def _map_joints(mujoco, spec, joint_map, names: list) -> list:
    """The MJCF joint of each of the problem's joints, in q's order (a ValueError naming the first bad entry)."""
    if joint_map is None:
        mapped = list(names)
    elif isinstance(joint_map, dict):
        stray = [k for k in joint_map if k not in names]
        if stray:
            raise ValueError(
                f"joint_map names {stray[0]!r}, not a joint of the problem; its joints: {', '.join(names)}"
            )
        missing = [k for k in names if k not in joint_map]
        if missing:
            raise ValueError(f"joint_map has no MJCF joint for the problem's joint {missing[0]!r}")
        mapped = [joint_map[k] for k in names]
    elif isinstance(joint_map, str) or len(joint_map) != len(names):
        raise ValueError(f"joint_map must be {len(names)} MJCF joint names (q's order) or a dict, got {joint_map!r}")
    else:
        mapped = list(joint_map)
    joints = {j.name: j for j in spec.joints}
    for name in mapped:
        if name not in joints:
            raise ValueError(f"joint_map: the MJCF has no joint {name!r}; its joints: {', '.join(joints) or 'none'}")
    if len(set(mapped)) != len(mapped):
        raise ValueError(f"joint_map names an MJCF joint twice: {mapped}")
    for name in mapped:
        if joints[name].type not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            raise ValueError(f"joint_map: MJCF joint {name!r} is not a hinge or slide joint (one q each)")
    return mapped


def _chain_spec(mujoco, problem):
    """The MJCF of a Chain: body i is joint i's frame at q = 0, its joint at the body's origin."""
    from ocpkit.model.rigid_body import position_limits

    chain = problem.chain
    spec = mujoco.MjSpec()
    spec.modelname = problem.name.replace(":", "_")
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.compiler.degree = False  # joint ranges in rad, as the Chain's (an MJCF's default is degrees)
    # stand-ins for the inertias MuJoCo's compiler refuses; _exact_inertias puts the Chain's back
    spec.compiler.balanceinertia, spec.compiler.boundmass, spec.compiler.boundinertia = True, 1e-6, 1e-9
    bodies = []
    for i in range(chain.n):
        parent = spec.worldbody if chain.parents[i] < 0 else bodies[chain.parents[i]]
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.asarray(chain.rotations[i], dtype=float).ravel())
        body = parent.add_body(name=chain.names[i], pos=chain.translations[i], quat=quat)
        inertia = chain.inertias[i]
        body.explicitinertial, body.mass, body.ipos = True, chain.masses[i], chain.coms[i]
        body.fullinertia = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
        kind = mujoco.mjtJoint.mjJNT_HINGE if chain.revolute[i] else mujoco.mjtJoint.mjJNT_SLIDE
        body.add_joint(name=chain.names[i], type=kind, axis=chain.axes[i])
        bodies.append(body)
    lo, hi = position_limits(problem.pin_model)
    for i, joint in enumerate(spec.joints):
        if max(abs(lo[i]), abs(hi[i])) < 1e10 and lo[i] < hi[i]:  # pinocchio's 'no limit' is ±1.8e308
            joint.range = [lo[i], hi[i]]
        joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE  # ocpkit's model has no limits: the option sets them
    return spec


def _exact_inertias(mujoco, model, chain) -> None:
    """Set each link's mass, centre of mass and inertia to the Chain's exactly, after compiling.

    MuJoCo's compiler requires positive principal moments with A + B >= C, and mass > 0. The N-link robots' thin
    rods have no moment about their own axis, the Puma 560's first link a mass of 0 and its third link moments
    (0.066, 0.086, 0.0125 kg·m²) that break A + B >= C: the published parameters are a model, not a body. The spec
    holds compile-able stand-ins (``balanceinertia``, ``boundmass``, ``boundinertia``); the simulated model holds
    the Chain's values, which MuJoCo's dynamics take as they are (its runtime checks none of this)."""
    for i, name in enumerate(chain.names):
        body = model.body(name).id
        moments, frame = np.linalg.eigh(np.asarray(chain.inertias[i], dtype=float))
        if np.linalg.det(frame) < 0:
            frame[:, 0] = -frame[:, 0]
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, frame.ravel())
        model.body_mass[body], model.body_ipos[body] = chain.masses[i], chain.coms[i]
        model.body_inertia[body], model.body_iquat[body] = np.maximum(moments, 0.0), quat
        model.body_sameframe[body] = 0  # the compiler's "inertia frame = body frame" shortcut no longer holds
    model.body_subtreemass[:] = model.body_mass
    for body in range(model.nbody - 1, 0, -1):
        model.body_subtreemass[model.body_parentid[body]] += model.body_subtreemass[body]


def _urdf_spec(mujoco, problem, meshes: bool):
    """MuJoCo's import of the problem's URDF with the joints the problem locked removed (held at 0), without its
    collision meshes unless ``meshes`` (MuJoCo's import discards the visual ones)."""
    from ocpkit.model.rigid_body import load_urdf

    try:
        spec = mujoco.MjSpec.from_file(problem.urdf)
    except ValueError as exc:
        raise ValueError(f"MuJoCo cannot read the URDF {problem.urdf!r}: {exc}") from None
    _urdf_meshes(mujoco, spec, problem.urdf, meshes)
    keep = set(problem.chain.names)
    locked = [j.name for j in spec.joints if j.name not in keep]
    # The problem's Chain must be load_urdf's default locking (0 clipped into the limits), and that 0:
    # removing a joint in MuJoCo freezes its child where q = 0 puts it.
    default = load_urdf(problem.urdf, locked_joints=locked)
    same = len(default.inertias) == len(problem.pin_model.inertias) and all(
        np.allclose(a.toDynamicParameters(), b.toDynamicParameters(), rtol=0, atol=1e-12)
        for a, b in zip(default.inertias, problem.pin_model.inertias)
    )
    for name in locked:
        joint = spec.joint(name)
        low, high = joint.range
        if not same or (joint.limited != mujoco.mjtLimited.mjLIMITED_FALSE and low < high and not low <= 0 <= high):
            raise ValueError(
                f"{problem.name}: joint {name!r} is locked away from 0, which the URDF import cannot "
                "hold; use an MJCF of yours (mjcf=, joint_map=)"
            )
    for eq in list(spec.equalities):  # mimic joints (the Panda's fingers) tie locked joints together
        if {eq.name1, eq.name2} & set(locked):
            spec.delete(eq)
    for name in locked:
        spec.delete(spec.joint(name))
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    for joint in spec.joints:
        joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE
    return spec


def _urdf_meshes(mujoco, spec, urdf: str, keep: bool) -> None:
    """Remove the mesh geometries of a URDF's import, or (``keep``) check that MuJoCo finds each mesh file.

    Robot files name their meshes as ``package://…`` URIs that only a ROS workspace resolves: MuJoCo fails on them,
    and the dynamics (masses from the URDF's <inertial>) need none of them."""
    if not keep:
        for geom in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]:
            spec.delete(geom)
        for mesh in list(spec.meshes):
            spec.delete(mesh)
        return
    folder = Path(spec.modelfiledir) / spec.meshdir
    for mesh in spec.meshes:
        if not (folder / mesh.file).is_file():  # an absolute file name replaces the folder
            raise ValueError(
                f"meshes=True: MuJoCo cannot open the mesh {mesh.file!r} of {urdf!r} (not a file "
                f"under {str(folder)!r}); leave meshes=False to simulate without the URDF's meshes"
            )


def _set_problem_dynamics(mujoco, spec, problem, joints):
    """Gravity, damping, Coulomb friction and rotor inertia of a robot generated from ``problem``; capsules along
    its links (for contacts with a floor and for pictures)."""
    chain = problem.chain
    gravity = getattr(problem, "gravity", True)  # URDFRobot(gravity=False) simulates none
    spec.option.gravity = chain.gravity_vector if gravity is not False else np.zeros(3)
    damping = chain.coefficients(getattr(problem, "damping", 0.0), "damping")
    friction = chain.coefficients(getattr(problem, "friction", 0.0), "friction")
    for i, name in enumerate(joints):
        joint = spec.joint(name)
        joint.damping = [damping[i], 0.0, 0.0] if np.ndim(joint.damping) else damping[i]  # MuJoCo 4: 3 terms
        # ocpkit smooths Coulomb friction as f tanh(q̇ / 0.01); MuJoCo's dry friction is its unsmoothed limit
        joint.frictionloss, joint.armature = friction[i], chain.armature[i]
    kin = problem.kinematics
    radius = float(getattr(problem, "link_radius", 0.05))
    zero = np.zeros(chain.n)
    for a, b in kin.segments():
        R, p = (np.asarray(v, dtype=float) for v in kin.placement(zero, a))
        end = R.T @ (np.asarray(kin.position(zero, b), dtype=float).ravel() - p.ravel())
        if np.linalg.norm(end) > 1e-9:
            body = spec.joint(a).parent
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                fromto=np.r_[np.zeros(3), end],
                size=[radius, 0, 0],
                contype=0,
                conaffinity=1,
                rgba=[0.4, 0.5, 0.7, 1.0],
            )


def _apply_options(mujoco, spec, joints, options):
    for i, name in enumerate(joints):
        joint = spec.joint(name)
        joint.frictionloss += options["frictionloss"][i]
        joint.armature += options["armature"][i]
        if options["limits"] is not None:
            bounded = options["limits"] and joint.range[0] < joint.range[1]
            joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE if bounded else mujoco.mjtLimited.mjLIMITED_FALSE
    if options["ctrlrange"] is not None:
        for i, actuator in enumerate(spec.actuators):
            actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
            actuator.ctrlrange = options["ctrlrange"][:, i]
    if options["floor"] is not None:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            pos=[0, 0, options["floor"]],
            size=[0, 0, 1],
            contype=1,
            conaffinity=1,
        )
