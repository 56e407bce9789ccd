"""Forward kinematics of named frames as symbolic CasADi expressions, and spheres that approximate a robot.

A :class:`Kinematics` reads a pinocchio ``Model`` (the trees of 1-DoF revolute and prismatic joints that
:class:`ocpkit.model.rigid_body.Chain` reads) and gives the world placement of any of its frames — a URDF link, a
joint, a link that pinocchio merged through a fixed joint, an operational frame added in code — as CasADi
expressions of q::

    ᵒM_f(q) = ᵒM_{j₁}(q₁) ⋯ ᵒM_{j}(q_j) · ʲM_f        (the joints from the base to the frame's joint j)

with the same joint transforms, axes and snapped rotations as the dynamics (``ocpkit.model.rigid_body``), so the
expressions keep no term that is zero in the true kinematics.

A robot is approximated for collision checks by :class:`RobotSphere` s, each a ball fixed in one frame:
:func:`spheres_along_links` strings them along the segments between consecutive joints (any robot),
:func:`collision_spheres` covers the URDF's ``<collision>`` primitives (spheres, cylinders, boxes), and
:func:`sphere_centers` is the CasADi Function q -> their world centres that obstacle constraints use
(``ocpkit.model.task``).
"""

from __future__ import annotations

import difflib
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ocpkit._checks import positive
from ocpkit.model.rigid_body import Chain, _snap

# Covering a box or cylinder with more spheres than this means the radius is far too small for the geometry.
MAX_SPHERES_PER_GEOMETRY = 10_000


@dataclass(frozen=True)
class _Frame:
    name: str
    kind: str  # BODY, JOINT, FIXED_JOINT, OP_FRAME, SENSOR (pinocchio's FrameType names)
    joint: int  # 0-based joint index of the Chain, -1: the fixed base
    rotation: np.ndarray  # placement in the joint's frame
    translation: np.ndarray
    depth: int  # number of frames above it in pinocchio's frame tree


class Kinematics:
    """World placements of the frames of a pinocchio Model as CasADi expressions of the joint positions q.

    ``q`` has one entry per joint (n = ``model.nv``), in pinocchio's joint order, as for
    :class:`~ocpkit.model.rigid_body.Chain` (a continuous joint is one angle here, not pinocchio's cos/sin pair).

    ``frames`` lists each frame name once, in the model's order. pinocchio may hold two frames of one name (a
    URDF link and a joint named alike); the name then means the BODY frame (the link), else the first frame
    of that name. A joint that has no frame in ``model.frames`` (a model built with ``addJoint`` alone) gets
    a JOINT frame of its name at its origin, so every joint name is a frame. ``joints`` lists the joint
    names (q's order); ``chain`` is the model's :class:`~ocpkit.model.rigid_body.Chain`, whose joint transforms
    the placements compose.
    """

    def __init__(self, pin_model):
        self.chain = Chain(pin_model)  # validates the joints; its transforms are the dynamics' own
        self.n = self.chain.n
        self.joints = list(self.chain.names)
        frames = list(pin_model.frames)
        depth = []
        for k, f in enumerate(frames):
            parent = f.parentFrame if hasattr(f, "parentFrame") else f.previousFrame  # pinocchio 3, 2
            depth.append(0 if k == 0 or parent >= k else depth[parent] + 1)
        self._frames: dict[str, _Frame] = {}
        for f, d in zip(frames, depth):
            kind = str(f.type).rsplit(".", 1)[-1]
            old = self._frames.get(f.name)
            if old is not None and (old.kind == "BODY" or kind != "BODY"):
                continue  # keep the BODY frame, else the first of the name
            joint = int(f.parentJoint if hasattr(f, "parentJoint") else f.parent) - 1
            self._frames[f.name] = _Frame(
                f.name,
                kind,
                joint,
                _snap(np.asarray(f.placement.rotation)),
                np.asarray(f.placement.translation, dtype=float).copy(),
                d,
            )
        for j, name in enumerate(self.joints):
            if name not in self._frames:
                self._frames[name] = _Frame(name, "JOINT", j, np.eye(3), np.zeros(3), 0)
        self.frames = list(self._frames)
        self._functions: dict[str, ca.Function] = {}

    def __repr__(self):
        return f"Kinematics(n={self.n}, frames={len(self.frames)})"

    # --- placements ------------------------------------------------------------------------------------

    def placement(self, q, frame: str):
        """(R, p): the frame's rotation (3×3) and origin (3×1) in the world frame at q.

        ``q`` an SX column of n entries gives SX expressions; an MX column (or numbers) goes through
        :meth:`function` and gives MX (or DM)."""
        self._frame(frame)
        if isinstance(q, ca.SX):
            return self._world(self._column(q), [frame])[0]
        p, R = self.function(frame)(self._column(q))
        return R, p

    def position(self, q, frame: str):
        """The frame's origin in the world frame at q (3×1)."""
        return self.placement(q, frame)[1]

    def function(self, frame: str) -> ca.Function:
        """``fk_<frame>``: q -> (p, R), the frame's world position and rotation (cached per frame; characters
        of the name that a CasADi Function name cannot hold become ``_``)."""
        self._frame(frame)
        if frame not in self._functions:
            q = ca.SX.sym("q", self.n)
            R, p = self._world(q, [frame])[0]
            name = "fk_" + re.sub(r"\W", "_", frame, flags=re.ASCII)
            self._functions[frame] = ca.Function(name, [q], [p, R], ["q"], ["p", "R"])
        return self._functions[frame]

    def positions(self, frame: str, q_rows) -> np.ndarray:
        """The frame's world positions (N, 3) at the configurations ``q_rows`` (N, n), one mapped call."""
        q_rows = np.atleast_2d(np.asarray(q_rows, dtype=float))
        return np.asarray(self.function(frame).map(len(q_rows))(q_rows.T)[0]).T

    def _world(self, q, frames):
        """[(R, p)] of ``frames`` at the SX column q, sharing the joints' transforms between frames."""
        chain, memo = self.chain, {}

        def joint(j):
            if j not in memo:
                R, p = chain._transform(j, q[j])
                if chain.parents[j] >= 0:
                    Rp, pp = joint(chain.parents[j])
                    R, p = ca.mtimes(Rp, R), pp + ca.mtimes(Rp, p)
                memo[j] = (R, p)
            return memo[j]

        out = []
        for name in frames:
            f = self._frames[name]
            if f.joint < 0:
                out.append((ca.SX(f.rotation), ca.SX(f.translation)))
                continue
            R, p = joint(f.joint)
            out.append((ca.mtimes(R, ca.SX(f.rotation)), p + ca.mtimes(R, ca.SX(f.translation))))
        return out

    def _column(self, q):
        if isinstance(q, (ca.SX, ca.MX, ca.DM)):
            if q.shape != (self.n, 1):
                raise ValueError(f"q must be a column of {self.n} entries, got shape {q.shape}")
            return q
        a = np.asarray(q, dtype=float)
        if a.size != self.n or a.ndim > 2:
            raise ValueError(f"q must hold {self.n} entries, got shape {a.shape}")
        return ca.DM(a.ravel())

    def _frame(self, frame) -> _Frame:
        if not isinstance(frame, str):
            raise TypeError(f"frame must be a frame name (str), got {frame!r}")
        if frame not in self._frames:
            close = difflib.get_close_matches(frame, self.frames, n=3, cutoff=0.5)
            hint = f"did you mean {', '.join(map(repr, close))}? " if close else ""
            raise ValueError(f"unknown frame {frame!r}; {hint}the model's frames: {', '.join(self.frames)}")
        return self._frames[frame]

    # --- the tree --------------------------------------------------------------------------------------

    def _children(self, j):
        return [c for c, p in enumerate(self.chain.parents) if p == j]

    def tip(self, joint: str | None = None) -> str | None:
        """The deepest frame fixed to ``joint`` (a joint name): its deepest BODY frame in pinocchio's frame tree
        (ties: the farthest from the joint), else its deepest other non-joint frame; None where it has none.

        ``joint=None``: the last joint of the first serial branch — from the first joint, down while a joint
        has exactly one child joint (an arm's wrist, not its gripper's fingers)."""
        if joint is None:
            j = 0
            while len(children := self._children(j)) == 1:
                j = children[0]
        else:
            if joint not in self.joints:
                raise ValueError(f"unknown joint {joint!r}; the model's joints: {', '.join(self.joints)}")
            j = self.joints.index(joint)
        fixed = [f for f in self._frames.values() if f.joint == j and f.kind != "JOINT"]
        candidates = [f for f in fixed if f.kind == "BODY"] or fixed
        if not candidates:
            return None
        return max(candidates, key=lambda f: (f.depth, float(np.linalg.norm(f.translation)))).name

    def segments(self) -> list[tuple[str, str]]:
        """(a, b) pairs along every branch: a joint and each of its child joints, and a joint without children
        and its :meth:`tip` frame (the last link). Parents first; the fixed base is not a segment."""
        return [(a, b) for a, b, _, _ in self._segments()]

    def _segments(self):
        """(a, b, start, end): start and end points of each segment in the frame a (constant: b is a child
        joint — its origin at q_b = 0, which a revolute joint never leaves — or a frame fixed to a's joint)."""
        out = []
        for j, name in enumerate(self.joints):
            a = self._frames[name]
            if a.joint != j:  # the name means a link of another joint (a URDF naming clash)
                continue
            ends = [(self.joints[c], np.asarray(self.chain.translations[c])) for c in self._children(j)]
            if not ends and (tip := self.tip(name)) is not None:
                ends = [(tip, self._frames[tip].translation)]
            for b, point in ends:  # the end point in joint j's frame, then in frame a
                out.append((name, b, -a.rotation.T @ a.translation, a.rotation.T @ (point - a.translation)))
        return out


@dataclass(frozen=True)
class RobotSphere:
    """A ball of ``radius`` (m) fixed in a robot frame: its centre at ``offset`` (x, y, z in that frame)."""

    frame: str
    offset: tuple
    radius: float

    def __post_init__(self):
        if not isinstance(self.frame, str) or not self.frame:
            raise ValueError(f"frame must be a frame name, got {self.frame!r}")
        offset = np.asarray(self.offset, dtype=float).ravel()
        if offset.shape != (3,) or not np.isfinite(offset).all():
            raise ValueError(f"offset must be 3 finite numbers, got {self.offset!r}")
        object.__setattr__(self, "offset", tuple(float(v) for v in offset))
        object.__setattr__(self, "radius", positive(self.radius, "radius"))


def spheres_along_links(kin: Kinematics, radius: float, spacing: float | None = None, frames=None) -> list[RobotSphere]:
    """Spheres of ``radius`` along each of ``kin.segments()``, each fixed in its segment's start frame.

    A segment of length L gets ⌈L / spacing⌉ + 1 evenly spaced centres from its start to its end, so every
    point of it lies within spacing / 2 ≤ radius of a centre (``spacing`` default = radius, at most
    2·radius). The end's sphere is left out where the next segment starts there, and a sphere that another
    segment of the same frame already placed is not repeated; zero-length segments are skipped. The end of a
    segment towards a prismatic joint is that joint's origin at q = 0. ``frames``: only the segments that
    start at these frames (joint names).
    """
    radius = positive(radius, "radius")
    spacing = radius if spacing is None else positive(spacing, "spacing")
    if spacing > 2 * radius:
        raise ValueError(f"spacing must be <= 2·radius = {2 * radius:g} (or the spheres leave gaps), got {spacing!r}")
    segments = [s for s in kin._segments() if np.linalg.norm(s[3] - s[2]) > 1e-12]
    if frames is not None:
        frames = [frames] if isinstance(frames, str) else list(frames)
        for f in frames:
            kin._frame(f)
        starts = sorted({a for a, *_ in segments})
        stray = [f for f in frames if f not in starts]
        if stray:
            raise ValueError(
                f"frame {stray[0]!r} starts no segment of non-zero length; those that do: {', '.join(starts)}"
            )
    starts = {a for a, *_ in segments if frames is None or a in frames}
    out, seen = [], set()
    for a, b, start, end in segments:
        if frames is not None and a not in frames:
            continue
        m = max(1, math.ceil(np.linalg.norm(end - start) / spacing - 1e-9))
        revolute_end = b in kin.joints and kin.chain.revolute[kin.joints.index(b)]
        last = m if not (b in starts and revolute_end) else m - 1
        for k in range(last + 1):
            sphere = RobotSphere(a, tuple(start + (end - start) * k / m), radius)
            key = (a, *np.round(sphere.offset, 12))
            if key not in seen:  # sibling segments (a hand's two fingers) share their start
                seen.add(key)
                out.append(sphere)
    return out


def sphere_centers(kin: Kinematics, spheres) -> ca.Function:
    """``sphere_centers``: q -> C, the world positions of the spheres' centres (3 × k, one column per sphere)."""
    spheres = list(spheres)
    if not spheres or not all(isinstance(s, RobotSphere) for s in spheres):
        raise ValueError("spheres must be a non-empty sequence of RobotSphere")
    names = sorted({s.frame for s in spheres})
    for name in names:
        kin._frame(name)
    q = ca.SX.sym("q", kin.n)
    world = dict(zip(names, kin._world(q, names)))
    C = ca.horzcat(*(world[s.frame][1] + ca.mtimes(world[s.frame][0], ca.DM(s.offset)) for s in spheres))
    return ca.Function("sphere_centers", [q], [C], ["q"], ["C"])


def collision_spheres(urdf_path, kin: Kinematics, radius: float | None = None) -> list[RobotSphere]:
    """Spheres covering the ``<collision>`` primitives of a URDF, each fixed in its link's BODY frame.

    A ``<sphere>`` is one sphere of its own radius. A ``<cylinder>`` (along z of its ``<origin>``) gets
    spheres on its axis of ``radius`` (> the cylinder's radius) spaced so that they cover it whole; a
    ``<box>`` a grid of spheres of ``radius`` covering it. ``radius=None`` picks one per geometry: a
    cylinder's is √(r² + (min(l, 2r)/2)²), a box's half the diagonal of its a × b × min(c, b) block
    (a ≤ b ≤ c). ``<origin xyz rpy>`` is honoured. Meshes cannot be covered this way: a ValueError says so.
    """
    path = Path(urdf_path)
    if not path.is_file():
        raise ValueError(f"URDF file not found: {str(path)!r}")
    if radius is not None:
        radius = positive(radius, "radius")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{str(path)!r} is not valid XML: {exc}") from None
    out, found = [], False
    for link in root.iter("link"):
        name = link.get("name")
        for collision in link.findall("collision"):
            found = True
            where = f"{path.name}: link {name!r}"
            frame = kin._frames.get(name)
            if frame is None or frame.kind != "BODY":
                raise ValueError(
                    f"{where} is not a link (BODY frame) of the model; its frames: {', '.join(kin.frames)}"
                )
            geometry = collision.find("geometry")
            shapes = list(geometry) if geometry is not None else []
            if len(shapes) != 1:
                raise ValueError(f"{where}: a <collision> needs one <geometry> shape, found {[s.tag for s in shapes]}")
            R, t = _origin(collision.find("origin"), where)
            for center, r in _cover(shapes[0], radius, where):
                out.append(RobotSphere(name, tuple(R @ center + t), r))
    if not found:
        raise ValueError(
            f"{path.name} has no <collision> element: nothing to make spheres of; use "
            "spheres_along_links(kin, radius) to approximate the links instead"
        )
    return out


def _numbers(text, count: int, what: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or "").split()])
    except ValueError:
        values = np.array([])
    if values.shape != (count,) or not np.isfinite(values).all():
        raise ValueError(f"{what} must be {count} finite numbers, got {text!r}")
    return values


def _origin(element, where):
    """(R, t) of an ``<origin xyz rpy>`` (identity where absent); R = Rz(yaw) Ry(pitch) Rx(roll)."""
    if element is None:
        return np.eye(3), np.zeros(3)
    t = _numbers(element.get("xyz", "0 0 0"), 3, f"{where}: <origin xyz>")
    roll, pitch, yaw = _numbers(element.get("rpy", "0 0 0"), 3, f"{where}: <origin rpy>")
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx, t


def _cover(shape, radius, where):
    """[(centre, radius)] covering one geometry shape, in its own frame."""
    tag = shape.tag
    if tag == "sphere":
        return [(np.zeros(3), positive(shape.get("radius"), f"{where}: <sphere radius>"))]
    if tag == "cylinder":
        r = positive(shape.get("radius"), f"{where}: <cylinder radius>")
        length = positive(shape.get("length"), f"{where}: <cylinder length>")
        R = math.hypot(r, min(length, 2 * r) / 2) if radius is None else radius
        if R <= r * (1 + 1e-12):  # too thin for the cross-section: cover its bounding box
            return _grid(np.array([2 * r, 2 * r, length]), R, where)
        m = max(1, math.ceil(length / (2 * math.sqrt(R * R - r * r)) - 1e-9))
        if m > MAX_SPHERES_PER_GEOMETRY:
            raise ValueError(f"{where}: radius {R:g} needs {m} spheres to cover the cylinder; choose a larger one")
        return [(np.array([0.0, 0.0, length * ((k + 0.5) / m - 0.5)]), R) for k in range(m)]
    if tag == "box":
        size = _numbers(shape.get("size"), 3, f"{where}: <box size>")
        if (size <= 0).any():
            raise ValueError(f"{where}: <box size> must be > 0, got {shape.get('size')!r}")
        a, b, c = np.sort(size)
        R = 0.5 * math.sqrt(a * a + b * b + min(c, b) ** 2) if radius is None else radius
        return _grid(size, R, where)
    if tag == "mesh":
        raise ValueError(
            f"{where}: a <mesh> collision geometry cannot be turned into spheres; use "
            "spheres_along_links(kin, radius) to approximate the links instead (or give the link "
            "<sphere>, <cylinder> or <box> collision primitives)"
        )
    raise ValueError(f"{where}: unknown collision geometry <{tag}> (expected sphere, cylinder, box or mesh)")


def _grid(size, R, where):
    """Centres of a grid of cells over a box centred at the origin, each cell's half-diagonal <= R."""
    counts = np.ones(3, dtype=int)
    while np.sum((size / counts) ** 2) > 4 * R * R * (1 + 1e-12):
        counts[np.argmax(size / counts)] += 1
        if counts.prod() > MAX_SPHERES_PER_GEOMETRY:
            raise ValueError(
                f"{where}: radius {R:g} needs over {MAX_SPHERES_PER_GEOMETRY} spheres to cover "
                f"a {size.tolist()} box; choose a larger one"
            )
    axes = [size[i] * ((np.arange(counts[i]) + 0.5) / counts[i] - 0.5) for i in range(3)]
    return [(np.array([x, y, z]), R) for x in axes[0] for y in axes[1] for z in axes[2]]
