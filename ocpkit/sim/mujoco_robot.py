"""The robot a :class:`~ocpkit.sim.mujoco_plant.MuJoCoPlant` simulates, as a MuJoCo spec (``MjSpec``): an MJCF
written from the problem's Chain, MuJoCo's import of its URDF, or a user's MJCF with its joints mapped to the
problem's; then the problem's gravity, damping, friction and rotor inertia, and the options' effects."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def mjcf_spec(mujoco, path):
    """A user's MJCF file as MuJoCo reads it (a ValueError naming the file when it cannot)."""
    file = Path(path)
    if not file.is_file():
        raise ValueError(f"mjcf: no such file {str(file)!r}")
    try:
        return mujoco.MjSpec.from_file(str(file))
    except ValueError as exc:
        raise ValueError(f"mjcf: {str(file)!r} is not an MJCF MuJoCo can read: {exc}") from None


def map_joints(mujoco, spec, joint_map, names: list) -> list:
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


def chain_spec(mujoco, problem):
    """The MJCF of a Chain: body i is joint i's frame at q = 0, its joint at the body's origin."""
    from ocpkit.model.rigid_body import position_limits

    chain = problem.chain
    spec = mujoco.MjSpec()
    spec.modelname = problem.name.replace(":", "_")
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.compiler.degree = False  # joint ranges in rad, as the Chain's (an MJCF's default is degrees)
    # stand-ins for the inertias MuJoCo's compiler refuses; exact_inertias puts the Chain's back
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


def exact_inertias(mujoco, model, chain) -> None:
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


def urdf_spec(mujoco, problem, meshes: bool):
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


def set_problem_dynamics(mujoco, spec, problem, joints):
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


def apply_options(mujoco, spec, joints, options):
    """The effects ocpkit's model leaves out, as :class:`~ocpkit.sim.mujoco_plant.MuJoCoPlant`'s ``options`` ask: dry
    friction and rotor inertia added to the joints', joint ranges as constraints, actuator limits, a floor."""
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
