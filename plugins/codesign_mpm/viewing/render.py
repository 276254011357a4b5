"""`codesign render`: headless videos and stills of MPM episodes, with numpy and matplotlib only.

Particles are drawn as shaded discs by a numpy point splatter with a z-buffer (orthographic
camera) and matplotlib (Agg) only stamps the time and the legend: it needs no display, GPU or
Vulkan, unlike Taichi's GGUI (docs: /work/shared/DESIGN.md section 5), and draws a frame of a
few thousand particles in tens of milliseconds. The terrain is static, so it is splatted once
(height-map surface plus side walls, which read as a ground band from the side) and each frame
only composites the particles over it.

Colours: ground-cover particles by material kind (sand, snow, clay, water, mud), robot particles
by muscle activation a = u . r_p (the action times the particle's membership): red for
a > 0 (contraction), blue for a < 0, grey where passive; orange (whatever the activation) where
a robot particle has torn off its body: it lies outside the body's largest piece at that frame
(by mass; by count for an export, which has no masses), pieces being the particles whose B-spline
stencils share grid nodes (`codesign_mpm.scene.integrity.pieces`; docs/integrity.md), and the frame's
label says the share of the robot's mass torn off ("torn 23.5% (orange)"). Water is drawn as a
translucent veil over what lies behind it (`VEILED`), so a robot in the ocean or in shallow water
stays in sight. Stills colour the
design by muscle group (the tab10 colours of `codesign.artifacts.PALETTE`, as in best/design.ply).

Videos are written with imageio: ``.mp4`` (H.264 through imageio-ffmpeg, which ships its own
ffmpeg binary, so nothing is needed from the system; small files that W&B and browsers play)
or ``.gif`` (Pillow; larger, but viewable anywhere and in Markdown).

Inputs are a `Recording`: from an ``.npz`` written by ``codesign simulate --export``, or from a
run directory whose best design and controller `record_run` replays for one episode.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from codesign.artifacts import PALETTE, to_numpy
from codesign.errors import CodesignError

if TYPE_CHECKING:
    from codesign.interfaces import Controller, DesignFields
    from codesign_mpm.environment.env import LocomotionEnv

CAMERAS: dict[str, tuple[float, float]] = {"side": (0.0, 0.0), "top": (0.0, 90.0), "oblique": (-35.0, 30.0)}
"""Camera name -> (azimuth about +y, elevation), degrees; `side` looks along +z at the x-y plane."""
VIDEO_SUFFIXES = (".mp4", ".gif")
SIZE = (640, 480)
"""Frame width and height in pixels (multiples of 16, as H.264 wants)."""

BACKGROUND = np.array([0.96, 0.96, 0.97])
TERRAIN = np.array([0.55, 0.50, 0.42])
PASSIVE = np.array([0.62, 0.62, 0.65])
CONTRACT = np.array([0.86, 0.10, 0.10])  # a > 0
EXTEND = np.array([0.10, 0.25, 0.90])  # a < 0
TORN = np.array([1.00, 0.50, 0.00])  # orange: a robot particle torn off its body (`Recording.torn`)
MATERIAL_COLORS: dict[str, tuple[float, float, float]] = {
    "neo_hookean": (0.45, 0.70, 0.45), "corotated": (0.45, 0.70, 0.45), "stvk": (0.45, 0.70, 0.45),
    "sand": (0.87, 0.76, 0.50), "snow": (0.93, 0.95, 1.00), "clay": (0.74, 0.46, 0.30),
    "water": (0.30, 0.60, 0.95), "mud": (0.42, 0.32, 0.22),
}
"""Colours of non-robot particles by material kind (elastic bodies share a green)."""
VEILED = ("water",)
VEIL_OPACITY = 0.25
"""Materials drawn see-through, and how much of their colour covers what lies behind them."""


@dataclass
class Recording:
    """What rendering needs: every frame's positions and actions, and per-particle labels."""

    x: np.ndarray  # (F+1, N, 3) positions, frame 0 the initial state
    actions: np.ndarray  # (F, K) action held from frame f to f+1
    material: np.ndarray  # (N,) material model id (codesign_mpm.materials)
    robot: np.ndarray  # (N,) bool
    muscle: np.ndarray  # (N, K) membership r_p (zeros off the robot)
    frame_dt: float
    dx: float
    heights: np.ndarray | None  # (nx, nz) terrain height on grid nodes; None: no terrain
    mass: np.ndarray | None = None  # (N,) particle mass (volume x density); None: unknown, pieces count particles
    body: np.ndarray | None = None  # (N,) index of the particle's body in the scene; None: one robot body
    rewards: np.ndarray | None = None  # (F,) the task's reward of each control step; None: not recorded (an export)
    target: dict[str, np.ndarray] | None = None  # the task's target (`task_target`); None: unknown

    @property
    def frames(self) -> int:
        return len(self.x) - 1

    def piece_labels(self, frame: int) -> np.ndarray:
        """(N,) which piece of its body each robot particle is in at `frame`: 0 the body's largest
        piece (by mass where `mass` is known, else by count), 1, 2, ... the pieces torn off it, by
        size; -1 off the robot. Pieces are particles whose stencils share grid nodes
        (`codesign_mpm.scene.integrity.pieces` at the recording's dx)."""
        from codesign_mpm.scene.integrity import pieces

        labels = np.full(len(self.material), -1, dtype=np.int64)
        body = self.body if self.body is not None else np.zeros(len(self.material), dtype=np.int64)
        for b in np.unique(body[self.robot]):
            members = np.flatnonzero(self.robot & (body == b))
            label = pieces(self.x[frame][members], self.dx)
            size = np.bincount(label, weights=None if self.mass is None else self.mass[members])
            rank = np.empty(len(size), dtype=np.int64)
            rank[np.argsort(-size, kind="stable")] = np.arange(len(size))
            labels[members] = rank[label]
        return labels

    def torn(self, frame: int) -> np.ndarray:
        """(N,) robot particles torn off their body at `frame`: outside the body's largest piece
        (`piece_labels`)."""
        return self.piece_labels(frame) > 0

    def torn_fraction(self, torn: np.ndarray) -> float:
        """The share of the robot's mass (of its particles, without masses) that `torn` marks."""
        weight = np.ones(len(self.material)) if self.mass is None else np.asarray(self.mass, dtype=np.float64)
        total = weight[self.robot].sum()
        return float(weight[torn & self.robot].sum() / total) if total > 0 else 0.0

    def activation(self, frame: int) -> np.ndarray:
        """a = u . r_p of every particle at `frame` (the action that moved it there; 0 at frame 0)."""
        if frame == 0 or self.actions.size == 0 or self.muscle.shape[1] == 0:
            return np.zeros(len(self.material))
        return self.muscle @ self.actions[frame - 1]


# --- inputs -----------------------------------------------------------------------------------


def load_npz(path: str | Path) -> Recording:
    """A `codesign simulate --export` file; older exports (without actions, muscles, dx or the
    height map) render too: no activation colours, spacing guessed, no terrain."""
    try:
        data = np.load(path)
    except (OSError, ValueError) as exc:
        raise CodesignError(f"cannot read {path}: {exc}") from None
    missing = [k for k in ("x", "material") if k not in data.files]
    if missing:
        raise CodesignError(f"{path} has no {', '.join(missing)}: expected an export of `codesign simulate "
                            f"--export` (keys x, material, ...), found {', '.join(data.files) or 'nothing'}")
    x = np.asarray(data["x"], np.float32)
    n = x.shape[1]
    muscle = data["muscle"] if "muscle" in data.files else np.zeros((n, 0))
    actions = data["actions"] if "actions" in data.files else np.zeros((len(x) - 1, muscle.shape[1]))
    dx = float(data["dx"]) if "dx" in data.files else float(np.prod(np.ptp(x[0], 0) + 1e-9) / n) ** (1 / 3) * 2
    return Recording(x, actions, data["material"], data["robot"].astype(bool) if "robot" in data.files
                     else np.zeros(n, bool), muscle, float(data["frame_dt"]) if "frame_dt" in data.files else 0.0,
                     dx, data["height_map"] if "height_map" in data.files else None,
                     body=data["body"] if "body" in data.files else None)


def record_episode(env: LocomotionEnv, design: DesignFields | None, controller: Controller,
                   steps: int | None = None) -> Recording:
    """Play one episode like `codesign.artifacts.play` (no gradients), keeping every frame's
    particle positions and action; ``steps=0`` records only the design at rest (no simulation)."""
    import torch

    from codesign_mpm.scene.terrain import height_map

    if not hasattr(env, "design_particles") or not hasattr(env, "scene"):
        raise CodesignError(f"rendering needs an MPM locomotion environment (codesign_mpm), "
                            f"not a {type(env).__name__}")
    steps = env.horizon if steps is None else steps
    rewards: list[float] = []
    if steps == 0:
        particles = env.design_particles(design) if design is not None else env.particles
        xs, actions = [particles.x.astype(np.float32)], []
    else:
        with torch.no_grad():
            observation = env.reset(design=design)
            controller.reset()
            particles = env.particles
            xs, actions = [env.sim.particles_state()[0].astype(np.float32)], []
            for t in range(steps):
                action = to_numpy(controller(observation, t))
                result = env.step(action)
                actions.append(action)
                rewards.append(float(result.reward))
                xs.append(env.sim.particles_state()[0].astype(np.float32))
                observation = result.observation
                if result.done:
                    break
    k = particles.muscle.shape[1]
    heights = height_map(env.scene) if env.scene.terrain.kind != "none" else None
    return Recording(np.stack(xs), np.array(actions).reshape(len(actions), k), particles.material.copy(),
                     particles.robot.copy(), particles.muscle.copy(), env.control_dt, env.scene.dx, heights,
                     mass=particles.volume * particles.density, body=particles.body.copy(),
                     rewards=np.array(rewards), target=task_target(env.task, env.control_dt, env.horizon))


def task_target(task: object, control_dt: float, horizon: int) -> dict[str, np.ndarray]:
    """What a viewer can draw of a started task (`codesign_mpm.environment.tasks`): its unit `direction` to move
    along, the `up` axis to turn about, or the path's `waypoints` at the end of each control step;
    empty for a task that has none of these."""
    if hasattr(task, "position") and hasattr(task, "coefficients"):
        return {"waypoints": np.stack([task.position((t + 1) * control_dt) for t in range(horizon)])}
    for key in ("direction", "up"):
        if hasattr(task, key):
            return {key: np.asarray(getattr(task, key), dtype=np.float64)}
    return {}


ITERATIONS = ("best", "0")
"""The episodes a run can replay: its best design and controller (best/), or those it started from
(iteration 0: the representation and controller set up from the run's seed, before any update)."""


def record_run(run_dir: str | Path, steps: int | None = None, iteration: str = "best") -> Recording:
    """Record one episode of a run's best design and controller, or (``iteration="0"``) of those it
    started from; its parts are rebuilt from config.yaml."""
    from codesign import runner

    if iteration not in ITERATIONS:
        raise CodesignError(f"iteration {iteration!r} of {run_dir} is not kept: a run keeps its start (0) and its "
                            f"best (best); choose from {', '.join(ITERATIONS)}")
    parts_of = runner.best_parts if iteration == "best" else runner.start_parts
    with parts_of(run_dir) as (parts, design, _):
        return record_episode(parts.environment, design, parts.controller, steps)  # type: ignore[arg-type]


def load_input(path: str | Path, steps: int | None = None) -> Recording:
    """A run directory (replayed) or an ``.npz`` export, chosen by what `path` is."""
    path = Path(path)
    if path.is_dir():
        return record_run(path, steps)
    if path.suffix == ".npz" and path.is_file():
        return load_npz(path)
    raise CodesignError(f"{path}: expected a run directory (with config.yaml and best/) or an .npz written "
                        "by `codesign simulate --export`")


# --- drawing ----------------------------------------------------------------------------------


@dataclass
class Camera:
    """Orthographic view fitted to a box: world points -> (column, row, depth)."""

    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    center: np.ndarray  # screen-space centre of the box
    scale: float  # pixels per scene unit
    size: tuple[int, int]

    @classmethod
    def fit(cls, name: str, lo: np.ndarray, hi: np.ndarray, size: tuple[int, int] = SIZE) -> Camera:
        if name not in CAMERAS:
            raise CodesignError(f"camera {name!r} is not known; choose from {', '.join(CAMERAS)}")
        az, el = np.radians(CAMERAS[name])
        ry = np.array([[np.cos(az), 0, np.sin(az)], [0, 1, 0], [-np.sin(az), 0, np.cos(az)]])
        right = ry @ np.array([1.0, 0, 0])
        up = ry @ np.array([0, np.cos(el), np.sin(el)])
        forward = ry @ np.array([0, -np.sin(el), np.cos(el)])
        corners = np.array([[(lo, hi)[i >> k & 1][k] for k in range(3)] for i in range(8)])
        screen = corners @ np.stack([right, up]).T
        extent = np.maximum(screen.max(0) - screen.min(0), 1e-6)
        scale = 0.92 * min(size[0] / extent[0], size[1] / extent[1])
        return cls(right, up, forward, (screen.max(0) + screen.min(0)) / 2, scale, size)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = (points @ np.stack([self.right, self.up]).T - self.center) * self.scale
        return s[:, 0] + self.size[0] / 2, self.size[1] / 2 - s[:, 1], points @ self.forward


def splat(image: np.ndarray, depth: np.ndarray, camera: Camera, points: np.ndarray, colors: np.ndarray,
          radius: float) -> None:
    """Draw `points` as shaded discs of `radius` (scene units) into `image` where they are nearer
    than `depth` (updated): the nearest disc pixel wins whatever the drawing order."""
    r_px = max(radius * camera.scale, 0.75)
    reach = int(np.ceil(r_px))
    oy, ox = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    inside = ox ** 2 + oy ** 2 <= r_px ** 2 + 0.25
    ox, oy = ox[inside], oy[inside]
    bulge = np.sqrt(np.clip(1 - (ox ** 2 + oy ** 2) / r_px ** 2, 0, 1))
    shade = 0.7 + 0.3 * bulge  # a sphere lit from the camera
    cols, rows, d = camera.project(points)
    c = (np.rint(cols)[:, None] + ox).ravel().astype(np.int64)
    r = (np.rint(rows)[:, None] + oy).ravel().astype(np.int64)
    z = (d[:, None] - bulge * radius).ravel()
    rgb = (colors[:, None, :] * shade[None, :, None]).reshape(-1, 3)
    w, h = camera.size
    ok = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    pix, z, rgb = r[ok] * w + c[ok], z[ok], rgb[ok]
    order = np.lexsort((z, pix))
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]]
    pix, z, rgb = pix[first], z[first], rgb[first]
    flat_depth, flat_image = depth.reshape(-1), image.reshape(-1, 3)
    nearer = z < flat_depth[pix]
    flat_depth[pix[nearer]] = z[nearer]
    flat_image[pix[nearer]] = rgb[nearer]


def _bilinear(heights: np.ndarray, dx: float, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    nx, nz = heights.shape
    u, w = np.clip(x / dx, 0, nx - 1.001), np.clip(z / dx, 0, nz - 1.001)
    i, k = u.astype(int), w.astype(int)
    fu, fw = u - i, w - k
    return ((heights[i, k] * (1 - fu) + heights[i + 1, k] * fu) * (1 - fw)
            + (heights[i, k + 1] * (1 - fu) + heights[i + 1, k + 1] * fu) * fw)


def terrain_layer(rec: Recording, camera: Camera, lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(image, depth) of the background and the terrain over [lo, hi] in x and z: the height-map
    surface, lit and lined every 0.1 units so motion shows, and its side walls down to lo[1]."""
    w, h = camera.size
    image, depth = np.tile(BACKGROUND, (h, w, 1)), np.full((h, w), np.inf)
    if rec.heights is None or (rec.heights < 0).all():
        return image, depth
    step = 1.2 / camera.scale  # about a pixel apart, so the discs close up
    xs = np.arange(lo[0], hi[0] + step, step)
    zs = np.arange(lo[2], hi[2] + step, step)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    gy = _bilinear(rec.heights, rec.dx, gx, gz)
    nrm = np.stack([-np.gradient(gy, step, axis=0), np.ones_like(gy), -np.gradient(gy, step, axis=1)], -1)
    light = np.array([0.3, 1.0, -0.5]) / np.linalg.norm([0.3, 1.0, -0.5])
    lit = 0.55 + 0.45 * np.clip((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)) @ light, 0, 1)
    lines = (np.abs((gx + 0.05) % 0.1 - 0.05) < step) | (np.abs((gz + 0.05) % 0.1 - 0.05) < step)
    colors = TERRAIN * (lit * np.where(lines, 0.85, 1.0))[..., None]
    points = np.stack([gx, gy, gz], -1).reshape(-1, 3)
    walls = []
    for edge_x, edge_z in ((xs, np.full_like(xs, lo[2])), (xs, np.full_like(xs, zs[-1])),
                           (np.full_like(zs, lo[0]), zs), (np.full_like(zs, xs[-1]), zs)):
        top = _bilinear(rec.heights, rec.dx, edge_x, edge_z)
        for y in np.arange(lo[1], top.max() + step, step):
            below = y <= top
            walls.append(np.stack([edge_x[below], np.full(below.sum(), y), edge_z[below]], -1))
    wall_points = np.concatenate(walls) if walls else np.zeros((0, 3))
    splat(image, depth, camera, np.concatenate([points, wall_points]),
          np.concatenate([colors.reshape(-1, 3), np.tile(TERRAIN * 0.7, (len(wall_points), 1))]), step)
    return image, depth


def view_box(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """The box every frame's particles stay in, padded, reaching a little below the terrain."""
    lo, hi = rec.x.min((0, 1)).astype(float), rec.x.max((0, 1)).astype(float)
    pad = 0.08 * (hi - lo).max() + 2 * rec.dx
    lo, hi = lo - pad, hi + pad
    if rec.heights is not None and (rec.heights >= 0).any():
        lo[1] = max(0.0, min(rec.x[..., 1].min(), rec.heights.min()) - max(0.03, rec.dx))
    return lo, hi


def material_colors(material: np.ndarray) -> np.ndarray:
    """(N, 3) each particle's colour by its material kind (`MATERIAL_COLORS`; grey for a plugin's)."""
    from codesign_mpm.materials import MATERIALS

    table = np.tile(PASSIVE, (max(m.id for m in MATERIALS.values()) + 1, 1))
    for name, color in MATERIAL_COLORS.items():
        table[MATERIALS[name].id] = color
    return table[np.clip(material, 0, len(table) - 1)]


def particle_colors(rec: Recording, frame: int, scale: float) -> np.ndarray:
    """Cover by material kind; the robot grey, turning red (a > 0) or blue (a < 0) with |a| / scale."""
    colors = material_colors(rec.material)
    a = rec.activation(frame)[rec.robot]
    t = np.clip(np.abs(a) / scale, 0, 1)[:, None] if scale > 0 else np.zeros((len(a), 1))
    colors[rec.robot] = PASSIVE * (1 - t) + np.where(a[:, None] > 0, CONTRACT, EXTEND) * t
    return colors


def episode_colors(rec: Recording, frame: int, scale: float) -> tuple[np.ndarray, float]:
    """`particle_colors` with the robot particles torn off their body (`Recording.torn`) orange, and
    the share of the robot's mass torn off (0: whole)."""
    colors = particle_colors(rec, frame, scale)
    torn = rec.torn(frame)
    if not torn.any():
        return colors, 0.0
    colors[torn] = TORN
    return colors, rec.torn_fraction(torn)


def group_colors(rec: Recording) -> np.ndarray:
    """Robot particles by their strongest muscle group (grey without one); others by material."""
    colors = particle_colors(rec, 0, 0.0)
    if rec.muscle.shape[1]:
        strength = np.abs(rec.muscle)
        active = rec.robot & (strength.max(1) > 0)
        colors[active] = PALETTE[strength[active].argmax(1) % len(PALETTE)] / 255.0
    return colors


def activation_scale(rec: Recording) -> float:
    """The largest |a| of a robot particle over the episode: `particle_colors` saturates there."""
    activations = [np.abs(rec.activation(f)[rec.robot]) for f in range(1, rec.frames + 1)]
    return float(max((a.max() for a in activations if a.size), default=0.0))


class Renderer:
    """Frames of one recording from one camera; matplotlib adds the text over each."""

    def __init__(self, rec: Recording, camera: str = "oblique", size: tuple[int, int] = SIZE) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.rec = rec
        lo, hi = view_box(rec)
        self.camera = Camera.fit(camera, lo, hi, size)
        self.background = terrain_layer(rec, self.camera, lo, hi)
        self.radius = 0.3 * rec.dx  # particles sit about dx / 2 apart (8 per cell)
        from codesign_mpm.materials import MATERIALS

        self.veiled = np.isin(rec.material, [MATERIALS[name].id for name in VEILED])
        self.scale = activation_scale(rec)
        self.figure = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
        FigureCanvasAgg(self.figure)  # Agg whatever the default backend: no display needed
        ax = self.figure.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        self.axes = ax
        self.image = ax.imshow(self.background[0], interpolation="nearest")
        self.text = ax.text(0.015, 0.975, "", transform=ax.transAxes, va="top", family="monospace", fontsize=10)

    def draw(self, colors: np.ndarray, frame: int, label: str) -> np.ndarray:
        image, depth = (a.copy() for a in self.background)
        x, veiled = self.rec.x[frame], self.veiled
        splat(image, depth, self.camera, x[~veiled], colors[~veiled], self.radius)
        if veiled.any():  # the veil's nearest disc, blended over whatever is behind it
            veil, veil_depth = image.copy(), depth.copy()
            splat(veil, veil_depth, self.camera, x[veiled], colors[veiled], self.radius)
            front = veil_depth < depth
            image[front] = (1 - VEIL_OPACITY) * image[front] + VEIL_OPACITY * veil[front]
        self.image.set_data(np.clip(image, 0, 1))
        self.text.set_text(label)
        self.figure.canvas.draw()
        return np.asarray(self.figure.canvas.buffer_rgba())[..., :3].copy()

    def frame(self, f: int) -> np.ndarray:
        colors, torn = episode_colors(self.rec, f, self.scale)
        label = f"t = {f * self.rec.frame_dt:6.3f} s  frame {f}/{self.rec.frames}"
        if torn > 0:
            label += f"  torn {100 * torn:.3g}% (orange)"
        return self.draw(colors, f, label)

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self.frame(f) for f in range(self.rec.frames + 1))


def write_video(rec: Recording, out: str | Path, camera: str = "oblique", fps: int = 25,
                progress: bool = True) -> Path:
    """Render every frame into an .mp4 or .gif; the progress bar shows only on a terminal."""
    import imageio.v2 as imageio

    from codesign.progress import progress_bar

    out = Path(out)
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise CodesignError(f"video {out}: suffix {out.suffix or '(none)'!r} is not supported; "
                            f"choose from {', '.join(VIDEO_SUFFIXES)}")
    if fps < 1:
        raise CodesignError(f"fps {fps} is invalid: must be >= 1")
    out.parent.mkdir(parents=True, exist_ok=True)
    frames = progress_bar(Renderer(rec, camera), total=rec.frames + 1, desc="render", unit="frame", show=progress)
    if out.suffix.lower() == ".gif":
        imageio.mimwrite(out, list(frames), duration=1000 / fps, loop=0)
    else:
        with imageio.get_writer(out, fps=fps, codec="libx264", quality=7, pixelformat="yuv420p",
                                macro_block_size=16, ffmpeg_log_level="error") as writer:
            for image in frames:
                writer.append_data(image)
    return out


def write_still(rec: Recording, out: str | Path, camera: str = "oblique") -> Path:
    """A PNG of the design at rest (frame 0), robot particles coloured by muscle group."""
    from matplotlib.patches import Patch

    out = Path(out)
    if out.suffix.lower() != ".png":
        raise CodesignError(f"still {out}: suffix {out.suffix or '(none)'!r} is not supported; use .png")
    out.parent.mkdir(parents=True, exist_ok=True)
    renderer = Renderer(rec, camera)
    k = rec.muscle.shape[1]
    renderer.draw(group_colors(rec), 0, f"design: {int(rec.robot.sum())} robot particles, {k} muscle groups")
    if k:
        handles = [Patch(color=PALETTE[i % len(PALETTE)] / 255.0, label=f"muscle {i}") for i in range(k)]
        renderer.axes.legend(handles=handles, loc="lower right", fontsize=8, framealpha=0.8)
    renderer.figure.savefig(out, dpi=100)
    return out


def render(source: str | Path, out: str | Path | None = None, still: str | Path | None = None,
           camera: str = "oblique", fps: int = 25, progress: bool = True) -> list[Path]:
    """`codesign render`: a video (default ``best/episode.mp4`` of a run, ``<name>.mp4`` next to an
    export) and/or a still; a still alone replays nothing. Returns the files written."""
    if camera not in CAMERAS:
        raise CodesignError(f"camera {camera!r} is not known; choose from {', '.join(CAMERAS)}")
    source = Path(source)
    if out is None and still is None:
        out = source / "best" / "episode.mp4" if source.is_dir() else source.with_suffix(".mp4")
    rec = load_input(source, steps=0 if out is None else None)
    written = []
    if out is not None:
        written.append(write_video(rec, out, camera, fps, progress))
    if still is not None:
        written.append(write_still(rec, still, camera))
    return written

