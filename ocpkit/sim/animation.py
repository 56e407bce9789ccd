"""Pictures of motion: a closed-loop :class:`~ocpkit.sim.simulate.Trajectory` as an animated GIF of the robot.

The robot is a stick figure drawn from the problem's forward kinematics (:mod:`ocpkit.model.kinematics`): one line per
segment of :meth:`~ocpkit.model.kinematics.Kinematics.segments` (joint to child joint, last joint to its tip frame),
the end effector's path as a trail. A robot whose every drawn point stays in one plane z = const (the planar
N-link chains) is drawn in that plane, any other in 3-D; the pendulum (no kinematics) as its rod, pivot at the
origin, q = 0 hanging down. The goal is drawn where the run has one: a task-space ``target`` point (``reach``; a moving
reference's target where it is at each frame), or else the joint goal's pose as a faint ghost; obstacles
(:class:`ocpkit.model.task.Sphere`) as wireframe spheres (in the plane: the circle where they cut it), where the run
moved them (:attr:`~ocpkit.sim.simulate.Trajectory.obstacles`) where they are at each frame. Every frame shows the
simulated time.

Frames play in real time, evenly spaced over the run (at most ``max_frames``), the last held a second; Pillow
(matplotlib's own dependency) writes them at a small size, so a run of a few seconds takes a few hundred kB. MuJoCo's
offscreen renderer is not used: it needs an OpenGL context (EGL or OSMesa) that a CI machine need not have, and
geometry to show that the problems do not describe (their URDFs ship without meshes).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ocpkit.sim import plots  # before pyplot: it selects the Agg backend
from ocpkit._checks import integer, positive

import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

SUFFIXES = (".gif",)
BASE = "(world origin)"  # the start of the base segments: not a frame name (frame names hold no spaces or brackets)
HOLD = 1.0  # seconds the last frame stays before the GIF loops
PLANAR_TOL = 1e-9  # m: drawn points whose z spread stays below this are a planar robot
GHOST = {"color": "0.6", "alpha": 0.5, "lw": 2, "ls": "--"}
ROBOT = {"color": "C0", "lw": 3, "marker": "o", "ms": 4, "mfc": "k", "mec": "k"}


def check_path(path, name: str = "path") -> Path:
    """``path`` as a Path ending in .gif (the only format written: Pillow ships with matplotlib; an MP4 needs
    ffmpeg); a ValueError naming ``name`` otherwise."""
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        got = f"not {p.suffix}" if p.suffix else "it has no suffix"
        raise ValueError(f"{name} {path}: an animation is written as a GIF; give a path ending in .gif ({got})")
    return p


class Skeleton:
    """The drawn robot of a problem: world points of its segments at configurations q (rows), and of its end point.

    ``segments(q_rows)`` -> (N, S, 2, 3) start and end of each segment; ``end(q_rows)`` -> (N, 3) the point whose path
    is drawn (``frame``: default the problem's end effector; the pendulum's bob)."""

    def __init__(self, problem, frame: str | None = None):
        self.kinematics = getattr(problem, "kinematics", None)
        if self.kinematics is not None:
            self.n = self.kinematics.n
            chain = self.kinematics.chain
            # the fixed base: from the world origin to each root joint away from it (a Panda's link 0, Baxter's torso)
            roots = [
                (BASE, name)
                for name, parent, offset in zip(self.kinematics.joints, chain.parents, chain.translations)
                if parent < 0 and np.linalg.norm(offset) > 0
            ]
            self.pairs = roots + self.kinematics.segments()
            self.frame = frame or getattr(problem, "end_effector", None) or self.pairs[-1][1]
            self.kinematics.function(self.frame)  # an unknown frame fails here, with the model's frames
            self.length = None
        elif _is_pendulum(problem):
            if frame is not None:
                raise ValueError(f"frame {frame!r}: the pendulum has no frames; it is drawn as its rod")
            self.n, self.pairs, self.frame, self.length = 1, [("pivot", "bob")], "bob", float(problem.l)
        else:
            raise ValueError(
                f"problem {getattr(problem, 'name', problem)!r} has no kinematics to draw; an "
                "animation needs a robot with frames (nlink:N, puma560, panda, baxter, urdf:FILE) or "
                "the pendulum"
            )

    def segments(self, q_rows) -> np.ndarray:
        q_rows = np.atleast_2d(np.asarray(q_rows, dtype=float))[:, : self.n]
        if self.length is not None:
            bob = self.length * np.stack([np.sin(q_rows[:, 0]), -np.cos(q_rows[:, 0]), 0 * q_rows[:, 0]], axis=1)
            return np.stack([np.zeros_like(bob), bob], axis=1)[:, None]
        names = sorted({f for pair in self.pairs for f in pair} - {BASE})
        where = {f: self.kinematics.positions(f, q_rows) for f in names}
        where[BASE] = np.zeros((len(q_rows), 3))
        return np.stack([np.stack([where[a], where[b]], axis=1) for a, b in self.pairs], axis=1)

    def end(self, q_rows) -> np.ndarray:
        if self.length is not None:
            return self.segments(q_rows)[:, 0, 1]
        q_rows = np.atleast_2d(np.asarray(q_rows, dtype=float))[:, : self.n]
        return self.kinematics.positions(self.frame, q_rows)

    def polyline(self, segments: np.ndarray) -> np.ndarray:
        """One configuration's segments (S, 2, 3) as one line (P, 3): a segment that starts where the previous one
        ended continues it, any other starts after a NaN row (a break in the line)."""
        rows, last = [], None
        for (a, b), (p, q) in zip(self.pairs, segments):
            if last != a:
                if rows:
                    rows.append(np.full(3, np.nan))
                rows.append(p)
            rows.append(q)
            last = b
        return np.array(rows)


def _is_pendulum(problem) -> bool:
    from ocpkit.problems.pendulum import Pendulum  # the one shipped robot without frames; imported only to draw it

    return isinstance(problem, Pendulum)


class MotionPicture:
    """The frames of one closed-loop run: a figure whose artists :meth:`draw` sets to the run's k-th frame.

    ``robot`` (the stick figure, a line through the joints), ``tip`` (the end point: a marker), ``trail`` (the end
    point's path so far), ``clock`` (the time) change per frame; ``ghost`` stays; ``target_artist`` and
    ``obstacle_artists`` (per obstacle: its circle in the plane, its wireframe and shadow in 3-D) move where the
    target (``target`` (H+1, 3), a moving reference's) and the obstacles (the trajectory's ``obstacles``) moved.
    ``indices``: the trajectory's states drawn, in order."""

    def __init__(
        self,
        trajectory,
        problem,
        *,
        target=None,
        obstacles=(),
        frame: str | None = None,
        fps: float = 20.0,
        max_frames: int = 120,
        size: float = 4.0,
        dpi: int = 75,
        title: str | None = None,
    ):
        self.trajectory, self.skeleton = trajectory, Skeleton(problem, frame)
        fps, max_frames = positive(fps, "fps"), integer(max_frames, "max_frames", 2)
        t = np.asarray(trajectory.t, dtype=float)
        self.target = None if target is None else np.asarray(target, dtype=float)
        if self.target is not None and (
            self.target.shape not in ((3,), (len(t), 3)) or not np.isfinite(self.target).all()
        ):
            raise ValueError(
                f"target must be 3 finite numbers (x, y, z in m), or one such row per recorded time ({len(t)}, 3), "
                f"got {np.asarray(target).tolist()}"
            )
        # the obstacles at every recorded time (H+1, N, 4): where the run moved them, else as given, held
        moved = getattr(trajectory, "obstacles", None)
        held = np.array([[*o.center, o.radius] for o in obstacles], dtype=float).reshape(-1, 4)
        self.spheres = np.broadcast_to(held, (len(t), *held.shape)) if moved is None else np.asarray(moved, float)
        q = np.asarray(trajectory.x, dtype=float)[:, : self.skeleton.n]
        # real time: frames evenly spaced over the run, fewer per second where the run is long
        count = int(min(max_frames, max(2, math.floor((t[-1] - t[0]) * fps) + 1)))
        shown = np.unique(np.round(np.linspace(0, len(t) - 1, count)).astype(int))
        self.indices = shown
        self.segments = dict(zip(shown, self.skeleton.segments(q[shown])))
        self.ends = dict(zip(shown, self.skeleton.end(q[shown])))
        # the joint goal's pose, unless the goal is a task-space target or carries a task's targets: a reach task's
        # x_goal holds the start's angles, unweighted
        plain = self.target is None and len(trajectory.goal) == np.shape(trajectory.x)[1]
        goal_pose = self.skeleton.segments(trajectory.goal[None, : self.skeleton.n])[0] if plain else None
        points = [s.reshape(-1, 3) for s in self.segments.values()]
        points += [goal_pose.reshape(-1, 3)] if goal_pose is not None else []
        self.planar = np.ptp(np.concatenate(points)[:, 2]) < PLANAR_TOL
        self.figure = plt.figure(figsize=(size, size), dpi=dpi, layout="constrained")
        ax = self.axes = self.figure.add_subplot(projection=None if self.planar else "3d")
        plots.set_title(ax, title or getattr(problem, "name", ""), fontsize=9)
        self._limits(points)
        z = () if self.planar else ([],)  # an empty line's z, in 3-D
        self.ghost = self.target_artist = self.drop = None
        if goal_pose is not None:
            self.ghost = ax.plot(*self._xyz(self.skeleton.polyline(goal_pose)), **GHOST, label="goal pose")[0]
        if self.target is not None:
            self.target_artist = ax.plot([], [], *z, "*", color="k", ms=12, label="target")[0]
            # 3-D: a drop line to the floor places the point in depth
            self.drop = None if self.planar else ax.plot([], [], [], ":", color="k", lw=0.8)[0]
        self.obstacle_artists = [self._obstacle() for _ in range(self.spheres.shape[1])]
        self._place(0)
        self.trail = ax.plot([], [], *z, color="C1", lw=1.2, alpha=0.8)[0]
        # the robot's shadow on the floor of the box (straight down): depth that one 3-D view cannot show
        self.shadow = None if self.planar else ax.plot([], [], [], color="0.2", lw=3, alpha=0.2)[0]
        self.robot = ax.plot([], [], *z, **ROBOT)[0]
        self.tip = ax.plot([], [], *z, "o", color="C3", ms=6, label=self.skeleton.frame)[0]
        where = {"transform": ax.transAxes, "fontsize": 8, "va": "top"}
        self.clock = (ax.text if self.planar else ax.text2D)(0.02, 0.98, "", **where)
        self.figure.legend(loc="outside lower center", ncols=2, fontsize=7, frameon=False)

    def _xyz(self, points):
        """Columns of (P, 3) points as the axes take them: x, y in the plane, x, y, z in 3-D."""
        points = np.atleast_2d(points)
        return (points[:, 0], points[:, 1]) if self.planar else (points[:, 0], points[:, 1], points[:, 2])

    @property
    def moving(self) -> list:
        """The artists that move with the target and obstacles (each frame places them; none where nothing moved)."""
        target = [] if self.target is None or self.target.ndim == 1 else [self.target_artist, self.drop]
        obstacles = [] if getattr(self.trajectory, "obstacles", None) is None else self.obstacle_artists
        return [a for a in target + [a for artists in obstacles for a in artists] if a is not None]

    def _limits(self, points):
        """Fixed equal-scale limits around every drawn point, target and obstacle (wherever they move), with a
        margin."""
        pts = np.concatenate(points + ([self.target.reshape(-1, 3)] if self.target is not None else []))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if self.spheres.shape[1]:
            spheres = self.spheres[self.indices].reshape(-1, 4)
            lo = np.minimum(lo, (spheres[:, :3] - spheres[:, 3:]).min(axis=0))
            hi = np.maximum(hi, (spheres[:, :3] + spheres[:, 3:]).max(axis=0))
        dims = 2 if self.planar else 3
        centre, half = (lo + hi)[:dims] / 2, 0.55 * max(float(np.max(hi - lo)), 0.1)
        setters = (self.axes.set_xlim, self.axes.set_ylim, getattr(self.axes, "set_zlim", None))
        for k in range(dims):
            setters[k](centre[k] - half, centre[k] + half)
        self.floor = float(centre[-1] - half)  # 3-D: the bottom of the box, where shadows fall
        labels = ("x [m]", "y [m]", "z [m]")
        self.axes.set_xlabel(labels[0], fontsize=8)
        self.axes.set_ylabel(labels[1], fontsize=8)
        if self.planar:
            self.axes.set_aspect("equal")
            self.axes.grid(alpha=0.3)
        else:
            self.axes.set_zlabel(labels[2], fontsize=8)
            self.axes.set_box_aspect((1, 1, 1))
        self.axes.tick_params(labelsize=6)

    def _obstacle(self) -> tuple:
        """An obstacle's artists, placed by :meth:`_place`: in the plane the circle where the sphere cuts the robot's
        plane (its outline, dashed, where it misses the plane); in 3-D a wireframe (matplotlib sorts 3-D artists
        whole, not per pixel, so a surface would hide the arm behind it) and its shadow on the floor."""
        if self.planar:
            return (self.axes.add_patch(Circle((0.0, 0.0), 1.0, color="C3", label="obstacle")),)
        wire = self.axes.plot([], [], [], color="C3", alpha=0.6, lw=0.7, label="obstacle")[0]
        return wire, self.axes.plot([], [], [], color="C3", alpha=0.3, lw=1)[0]

    def _place(self, i: int):
        """Put the target and the obstacles where they are at recorded time ``i``."""
        if self.target is not None:
            point = self.target if self.target.ndim == 1 else self.target[i]
            self.target_artist.set_data(*self._xyz(point[None])[:2])
            if not self.planar:
                self.target_artist.set_3d_properties([point[2]])
                self.drop.set_data([point[0]] * 2, [point[1]] * 2)
                self.drop.set_3d_properties([self.floor, point[2]])
        for artists, (*c, r) in zip(self.obstacle_artists, self.spheres[i]):
            c = np.asarray(c)
            if self.planar:
                plane = float(next(iter(self.segments.values()))[0, 0, 2])
                cut = r * r - (c[2] - plane) ** 2
                (circle,) = artists
                circle.set_center(c[:2])
                circle.set_radius(math.sqrt(cut) if cut > 0 else r)
                circle.set_alpha(0.35 if cut > 0 else 0.15)
                circle.set_linestyle("-" if cut > 0 else "--")
                continue
            wire, shadow = artists
            u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 17), np.linspace(0, np.pi, 9))
            grid = c[:, None, None] + r * np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
            # the wireframe's parallels, then its meridians, as one line broken by NaN rows
            lines = [grid[:, j] for j in range(grid.shape[1])] + [grid[:, :, j] for j in range(grid.shape[2])]
            points = np.concatenate([np.c_[line, np.full((3, 1), np.nan)] for line in lines], axis=1)
            wire.set_data(points[0], points[1])
            wire.set_3d_properties(points[2])
            shadow.set_data(c[0] + r * np.cos(u[0]), c[1] + r * np.sin(u[0]))
            shadow.set_3d_properties(np.full(u.shape[1], self.floor))

    def draw(self, k: int):
        """Set the artists to frame ``k`` (an index into :attr:`indices`); the changed artists."""
        i = int(self.indices[k])
        robot = self.skeleton.polyline(self.segments[i])
        trail = np.array([self.ends[j] for j in self.indices[: k + 1]])
        self.robot.set_data(*self._xyz(robot)[:2])
        self.trail.set_data(*self._xyz(trail)[:2])
        self.tip.set_data(*self._xyz(self.ends[i][None])[:2])
        if not self.planar:
            self.shadow.set_data(*self._xyz(robot)[:2])
            self.shadow.set_3d_properties(np.where(np.isnan(robot[:, 2]), np.nan, self.floor))
            self.robot.set_3d_properties(robot[:, 2])
            self.trail.set_3d_properties(trail[:, 2])
            self.tip.set_3d_properties(self.ends[i][None, 2])
        self.clock.set_text(f"t = {self.trajectory.t[i]:.2f} s")
        self._place(i)
        return [a for a in (self.robot, self.shadow, self.trail, self.tip, self.clock) if a is not None] + self.moving

    def drawn(self, artist) -> np.ndarray:
        """The points (P, 3) an artist holds now (z = 0 in the plane): what a frame shows, for checks."""
        if self.planar:
            x, y = artist.get_data()
            return np.column_stack([x, y, np.zeros(len(x))])
        return np.column_stack(artist.get_data_3d())

    def save(self, path) -> Path:
        """Write the frames as a GIF at ``path`` (its folder created): each shown for the simulated time until the
        next (to the GIF's 10 ms), the last for ``HOLD`` seconds."""
        path = check_path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        images = list(self.images())
        ticks = np.round(100 * np.asarray(self.trajectory.t)[self.indices]).astype(int)  # centiseconds, unsummed
        durations = [10 * int(d) for d in np.diff(ticks)] + [int(1000 * HOLD)]
        images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0)
        return path

    def images(self):
        """The frames as Pillow images. The figure is laid out and drawn once without the moving artists; each frame
        restores that background and draws them alone (a full redraw per frame, constrained layout included, is far
        slower)."""
        from PIL import Image

        moving = self.draw(len(self.indices) - 1)  # the layout fits the last frame: the trail at its longest
        for artist in moving:
            artist.set_animated(True)
        canvas = self.figure.canvas
        canvas.draw()
        self.figure.set_layout_engine("none")
        background = canvas.copy_from_bbox(self.figure.bbox)
        for k in range(len(self.indices)):
            canvas.restore_region(background)
            for artist in self.draw(k):
                self.figure.draw_artist(artist)
            yield Image.frombuffer("RGBA", canvas.get_width_height(), canvas.buffer_rgba()).convert("RGB")

    def close(self):
        plt.close(self.figure)


def animate(
    trajectory,
    path,
    problem,
    *,
    target=None,
    obstacles=(),
    frame: str | None = None,
    fps: float = 20.0,
    max_frames: int = 120,
    size: float = 4.0,
    dpi: int = 75,
    title: str | None = None,
) -> Path:
    """Write the closed-loop ``trajectory`` of ``problem``'s robot as an animated GIF at ``path``; its Path.

    ``target``: a task-space target point (x, y, z; drawn as a star), else the trajectory's joint goal is drawn as a
    ghost pose (where the goal is a plain state, without a task's targets); ``obstacles``: spheres
    (:class:`ocpkit.model.task.Sphere`); ``frame``: the frame whose path is drawn (default the problem's end
    effector). Real-time playback at ``fps`` (fewer frames per second where the run would need more than
    ``max_frames``); ``size`` inches square at ``dpi``."""
    path = check_path(path)
    picture = MotionPicture(
        trajectory,
        problem,
        target=target,
        obstacles=obstacles,
        frame=frame,
        fps=fps,
        max_frames=max_frames,
        size=size,
        dpi=dpi,
        title=title,
    )
    try:
        return picture.save(path)
    finally:
        picture.close()
