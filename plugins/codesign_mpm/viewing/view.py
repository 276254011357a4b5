"""`codesign view`: interactive 3D recordings of episodes, exports and designs, for the Rerun viewer.

Why Rerun (`rerun-sdk`): a recording is one ``.rrd`` file that opens later, on this machine or
another, in Rerun's native viewer (``rerun FILE.rrd``) or in a browser (``rerun --serve-web
FILE.rrd``; the web viewer ships inside the wheel, so nothing is fetched from the internet at
view time); the viewer has timelines to scrub and play, an entity tree whose parts can be
hidden one by one, and time-series plots beside the 3D view, which is what a gait needs. It is
written headless (no display, GPU or browser), and the same file can be read back by tests.

Episodes are replayed with `codesign_mpm.viewing.render` (the code behind `codesign render`), so a view
shows the same episode as a video. Each episode gets an entity tree of its own, its root
``/<run>/<iteration>`` shifted across z into a lane of its own when there are several (robots
move along x, so lanes side by side keep them racing in view):

- ``robot/action`` (shown): the robot's particles grey, red where a muscle contracts (a > 0),
  blue where it extends; ``robot/muscle_group``, ``robot/material`` and ``robot/piece`` (hidden at
  first: tick them in the blueprint panel) colour them by their strongest muscle (matplotlib's
  tab10, as ``best/design.ply``), by material and by piece (grey: the body's largest piece;
  orange, then the other tab10 colours: pieces torn off it, `Recording.piece_labels`);
- ``cover/<material>``: sand, snow, clay, mud or water particles, each hideable on its own;
- ``terrain``: the height map as a mesh under the robot;
- ``com/path`` and ``com/now``: the robot's centre of mass so far and now;
- ``target``: the task's direction (an arrow from the start), its turning axis, or its path's
  waypoints (``target/now``: the waypoint of the current step);
- ``plots/actions/muscle_k``, ``plots/reward`` and ``plots/torn_percent``: per control step.

Timelines: ``step`` (control steps, frame 0 the start) and ``time`` (simulated seconds).
A design (``best/design.npz``, or an annotated body from `codesign annotate`) is a static
tree: ``particles/muscle_group``, ``particles/stiffness`` (viridis, low to high Young's
modulus; hidden at first) and ``fibers`` (an arrow per sampled muscle particle).
"""
from __future__ import annotations

import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

import numpy as np

from codesign.artifacts import BEST, KEEP_THRESHOLD, PALETTE
from codesign.errors import CodesignError
from codesign.hookspecs import ViewRecording
from codesign.runner import CONFIG_FILE
from codesign_mpm.viewing.render import (
    ITERATIONS,
    PASSIVE,
    TERRAIN,
    Recording,
    activation_scale,
    group_colors,
    load_npz,
    material_colors,
    particle_colors,
    record_run,
    view_box,
)

APP_ID = "codesign"
SUFFIX = ".rrd"
DEFAULT_FILE = "view.rrd"
WEB_PORT = 9090
"""The web viewer's default port with ``--serve`` (Rerun's own default)."""
PIECE_COLORS = np.roll(PALETTE, -1, axis=0) / 255.0
"""Torn-off pieces 1, 2, ...: orange first, as `codesign render` draws torn particles."""
MAX_FIBERS = 400
"""Fibre arrows drawn of a design at most (every k-th muscle particle)."""
LANE_MARGIN = 0.1
"""Gap between lanes, as a share of a lane's width."""


@dataclass
class Episode:
    """One episode to show, under the entity path `label`."""

    label: str
    rec: Recording


@dataclass
class Design:
    """One design to show, under `label`: its kept particles and their fields."""

    label: str
    points: np.ndarray  # (N, 3)
    groups: np.ndarray  # (N,) strongest muscle, -1 passive
    fibers: np.ndarray  # (N, 3) unit fibre directions
    spacing: float  # particle spacing, for sizes
    stiffness: np.ndarray | None = None  # (N,) Young's modulus; None: not in the file (an annotated body)
    group_names: list[str] = field(default_factory=list)


# --- inputs -----------------------------------------------------------------------------------


def _part(name: str) -> str:
    """An entity path part from a file or directory name."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "item"


def is_run(path: Path) -> bool:
    return (path / CONFIG_FILE).is_file()


def runs_under(directory: Path) -> list[Path]:
    """The finished runs below a sweep or study directory: those with a saved best design."""
    return sorted(p.parent for p in directory.rglob(CONFIG_FILE) if (p.parent / BEST / "design.npz").is_file())


def load_design(path: Path) -> Design:
    """A run's ``best/design.npz`` (occupancy, stiffness, muscle, fiber over the workspace points) or
    an annotated body of `codesign annotate` (points, groups, fibers, spacing, group_names)."""
    data = np.load(path)
    label = f"{_part(path.parent.parent.name)}/design" if path.parent.name == BEST else _part(path.stem)
    if "occupancy" in data.files:
        keep = data["occupancy"].reshape(-1) >= KEEP_THRESHOLD
        points, muscle = data["points"][keep], np.asarray(data["muscle"])[keep]
        strength = np.abs(muscle)
        groups = np.where(strength.max(1) > 0, strength.argmax(1), -1) if muscle.shape[1] else np.full(len(points), -1)
        spacing = _spacing(data["points"])
        return Design(label, points, groups, data["fiber"][keep], spacing, data["stiffness"].reshape(-1)[keep],
                      [f"muscle {k}" for k in range(muscle.shape[1])])
    return Design(label, data["points"], data["groups"].astype(np.int64), data["fibers"], float(data["spacing"]),
                  group_names=[str(n) for n in data["group_names"]])


def _spacing(points: np.ndarray) -> float:
    """The smallest non-zero gap between sorted coordinates: the sampling lattice's spacing."""
    gaps = [np.diff(np.unique(np.round(points[:, a], 9))) for a in range(3)]
    gaps = [g[g > 0].min() for g in gaps if (g > 0).any()]
    return float(min(gaps)) if gaps else 0.01


def load_file(path: Path) -> Episode | Design:
    """An ``.npz`` by its keys: an episode export, a design or an annotated body."""
    try:
        keys = set(np.load(path).files)
    except (OSError, ValueError) as exc:
        raise CodesignError(f"cannot read {path}: {exc}") from None
    if {"x", "material"} <= keys:
        return Episode(_part(path.stem), load_npz(path))
    if {"points", "occupancy", "muscle", "fiber"} <= keys or {"points", "groups", "fibers"} <= keys:
        return load_design(path)
    raise CodesignError(f"{path} is neither an episode export (keys x, material: `codesign simulate --export`), a "
                        "design (points, occupancy, stiffness, muscle, fiber: a run's best/design.npz) nor an "
                        "annotated body (points, groups, fibers: `codesign annotate`); "
                        f"it has {', '.join(sorted(keys))}")


def resolve(sources: list[Path], iterations: list[str]) -> list[Path | Episode | Design]:
    """Check every source before replaying anything; runs stay paths (replayed later, one at a time)."""
    for it in iterations:
        if it not in ITERATIONS:
            raise CodesignError(f"--iterations: {it!r} is not an iteration a run keeps; choose from "
                                f"{', '.join(ITERATIONS)} (0: the design and controller it started from)")
    items: list[Path | Episode | Design] = []
    for source in sources:
        if source.is_dir():
            if is_run(source):
                items.append(source)
                continue
            found = runs_under(source)
            if not found:
                raise CodesignError(f"{source} is not a run directory (no config.yaml) and holds no finished run "
                                    "(no */config.yaml with best/design.npz below it): name a run, a sweep or "
                                    "study directory, or an .npz")
            items += found
        elif source.is_file() and source.suffix == ".npz":
            if iterations != ["best"]:
                raise CodesignError(f"--iterations {','.join(iterations)}: {source} is a file, which holds one "
                                    "episode or design; --iterations picks episodes of run directories")
            items.append(load_file(source))
        else:
            raise CodesignError(f"{source}: expected a run directory, a sweep or study directory, or an .npz "
                                "(an export of `codesign simulate --export`, a best/design.npz or an annotated "
                                "body of `codesign annotate`)" + ("" if source.exists() else "; it does not exist"))
    return items


def default_out(sources: list[Path]) -> Path:
    """RUN_DIR/view.rrd for one directory, FILE.rrd beside one file, ./view.rrd for several."""
    if len(sources) == 1:
        source = sources[0]
        return source / DEFAULT_FILE if source.is_dir() else source.with_suffix(SUFFIX)
    return Path(DEFAULT_FILE)


# --- writing ----------------------------------------------------------------------------------


def rgb8(colors: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(colors) * 255), 0, 255).astype(np.uint8)


def com_path(rec: Recording) -> np.ndarray:
    """(F+1, 3) the robot's centre of mass each frame (by mass where known, else the mean)."""
    robot = rec.robot if rec.robot.any() else np.ones(len(rec.material), bool)
    weight = np.ones(int(robot.sum())) if rec.mass is None else np.asarray(rec.mass, np.float64)[robot]
    return np.einsum("fnd,n->fd", rec.x[:, robot].astype(np.float64), weight / weight.sum())


def terrain_mesh(rec: Recording, lo: np.ndarray, hi: np.ndarray):
    """The height map's nodes over [lo, hi] in x and z as a lit mesh (None: no terrain)."""
    import rerun as rr

    if rec.heights is None or (rec.heights < 0).all():
        return None
    nx, nz = rec.heights.shape
    i = np.arange(max(0, int(lo[0] / rec.dx)), min(nx, int(np.ceil(hi[0] / rec.dx)) + 1))
    k = np.arange(max(0, int(lo[2] / rec.dx)), min(nz, int(np.ceil(hi[2] / rec.dx)) + 1))
    if len(i) < 2 or len(k) < 2:
        return None
    h = rec.heights[np.ix_(i, k)].astype(np.float64)
    gx, gz = np.meshgrid(i * rec.dx, k * rec.dx, indexing="ij")
    vertices = np.stack([gx, h, gz], -1).reshape(-1, 3)
    normals = np.stack([-np.gradient(h, rec.dx, axis=0), np.ones_like(h), -np.gradient(h, rec.dx, axis=1)], -1)
    normals = (normals / np.linalg.norm(normals, axis=-1, keepdims=True)).reshape(-1, 3)
    a = (np.arange(len(i) - 1)[:, None] * len(k) + np.arange(len(k) - 1)[None, :]).ravel()
    triangles = np.concatenate([np.stack([a, a + 1, a + len(k)], 1), np.stack([a + 1, a + len(k) + 1, a + len(k)], 1)])
    return rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles, vertex_normals=normals,
                     albedo_factor=rgb8(TERRAIN).tolist() + [255])


def lane_width(item: Episode | Design) -> float:
    if isinstance(item, Episode):
        lo, hi = view_box(item.rec)
        return float(hi[2] - lo[2])
    return float(np.ptp(item.points[:, 2]) + 4 * item.spacing) if len(item.points) else 0.0


def log_episode(stream, root: str, rec: Recording, named: bool = False) -> list[str]:
    """Log one episode under `root` (`named`: its plots' series named after it, to tell episodes
    apart in shared plots); returns the entities a 3D view should hide at first."""
    import rerun as rr

    from codesign_mpm.materials import MATERIALS

    radius = 0.3 * rec.dx
    robot = np.flatnonzero(rec.robot)
    names = {m.id: name for name, m in MATERIALS.items()}
    covers = {names.get(int(m), f"material_{int(m)}"): np.flatnonzero((rec.material == m) & ~rec.robot)
              for m in np.unique(rec.material[~rec.robot])}
    lo, hi = view_box(rec)
    mesh = terrain_mesh(rec, lo, hi)
    if mesh is not None:
        stream.log(f"{root}/terrain", mesh, static=True)
    if len(robot):  # colours that do not change: logged once, positions every frame
        stream.log(f"{root}/robot/muscle_group", rr.Points3D.from_fields(colors=rgb8(group_colors(rec)[robot]),
                                                                         radii=radius), static=True)
        stream.log(f"{root}/robot/material", rr.Points3D.from_fields(colors=rgb8(material_colors(rec.material[robot])),
                                                                     radii=radius), static=True)
        stream.log(f"{root}/robot/action", rr.Points3D.from_fields(radii=radius), static=True)
        stream.log(f"{root}/robot/piece", rr.Points3D.from_fields(radii=radius), static=True)
    for name, members in covers.items():
        stream.log(f"{root}/cover/{name}", rr.Points3D.from_fields(colors=rgb8(material_colors(rec.material[members])),
                                                                   radii=radius), static=True)
    com = com_path(rec)
    target = rec.target or {}
    length = max(float(np.ptp(rec.x[0][robot, 0])) if len(robot) else 0.0, 10 * rec.dx)
    for key, label in (("direction", "target direction"), ("up", "turn counter-clockwise about")):
        if key in target:
            stream.log(f"{root}/target/{key}", rr.Arrows3D(origins=[com[0]], vectors=[target[key] * length],
                                                           colors=[[20, 20, 20]], labels=[label], radii=rec.dx / 8),
                       static=True)
    if "waypoints" in target:
        stream.log(f"{root}/target/path", rr.LineStrips3D([np.vstack([com[0], target["waypoints"]])],
                                                          colors=[[20, 20, 20]], radii=rec.dx / 6), static=True)
    k = rec.actions.shape[1]
    for j in range(k):
        stream.log(f"{root}/plots/actions/muscle_{j}",
                   rr.SeriesLines(colors=[PALETTE[j % len(PALETTE)].tolist()],
                                  names=[f"{root}: muscle {j}" if named else f"muscle {j}"]), static=True)
    scale = activation_scale(rec)
    for f in range(rec.frames + 1):
        stream.set_time("step", sequence=f)
        stream.set_time("time", duration=f * rec.frame_dt)
        x = rec.x[f]
        if len(robot):
            stream.log(f"{root}/robot/muscle_group", rr.Points3D.from_fields(positions=x[robot]))
            stream.log(f"{root}/robot/material", rr.Points3D.from_fields(positions=x[robot]))
            stream.log(f"{root}/robot/action", rr.Points3D.from_fields(
                positions=x[robot], colors=rgb8(particle_colors(rec, f, scale)[robot])))
            pieces = rec.piece_labels(f)  # -1 off the robot, 0 its body, 1, 2, ... pieces torn off
            labels = pieces[robot]
            colors = np.where(labels[:, None] > 0, PIECE_COLORS[(labels - 1) % len(PIECE_COLORS)], PASSIVE)
            stream.log(f"{root}/robot/piece", rr.Points3D.from_fields(positions=x[robot], colors=rgb8(colors)))
            stream.log(f"{root}/plots/torn_percent", rr.Scalars(100 * rec.torn_fraction(pieces > 0)))
        for name, members in covers.items():
            stream.log(f"{root}/cover/{name}", rr.Points3D.from_fields(positions=x[members]))
        stream.log(f"{root}/com/path", rr.LineStrips3D([com[:f + 1]], colors=[[0, 0, 0]], radii=rec.dx / 5))
        stream.log(f"{root}/com/now", rr.Points3D([com[f]], colors=[[0, 0, 0]], radii=rec.dx))
        if "waypoints" in target and f > 0:
            stream.log(f"{root}/target/now", rr.Points3D([target["waypoints"][f - 1]], colors=[[20, 20, 20]],
                                                          radii=rec.dx))
        if f > 0:
            for j in range(k):
                stream.log(f"{root}/plots/actions/muscle_{j}", rr.Scalars(float(rec.actions[f - 1, j])))
            if rec.rewards is not None and len(rec.rewards) >= f:
                stream.log(f"{root}/plots/reward", rr.Scalars(float(rec.rewards[f - 1])))
    stream.reset_time()
    return [f"{root}/robot/{name}" for name in ("muscle_group", "material", "piece")]


def log_design(stream, root: str, design: Design) -> list[str]:
    """Log one design under `root` (static); returns the entities a 3D view should hide at first."""
    import rerun as rr
    from matplotlib import colormaps

    radius = 0.3 * design.spacing
    colors = np.tile(PASSIVE, (len(design.points), 1))
    muscle = design.groups >= 0
    colors[muscle] = PALETTE[design.groups[muscle] % len(PALETTE)] / 255.0
    stream.log(f"{root}/particles/muscle_group", rr.Points3D(design.points, colors=rgb8(colors), radii=radius),
               static=True)
    if design.stiffness is not None and len(design.points):
        low, high = float(design.stiffness.min()), float(design.stiffness.max())
        t = (design.stiffness - low) / (high - low) if high > low else np.full(len(design.points), 0.5)
        viridis = rgb8(colormaps["viridis"](t)[:, :3])
        stream.log(f"{root}/particles/stiffness", rr.Points3D(design.points, colors=viridis, radii=radius), static=True)
        stream.log(f"{root}/stiffness_range", rr.TextDocument(
            f"Young's modulus from {low:.4g} (dark purple) to {high:.4g} (yellow), viridis"), static=True)
    sampled = np.flatnonzero(muscle)[::max(1, int(np.ceil(muscle.sum() / MAX_FIBERS)))]
    if len(sampled):
        stream.log(f"{root}/fibers", rr.Arrows3D(origins=design.points[sampled],
                                                 vectors=design.fibers[sampled] * 2 * design.spacing,
                                                 colors=rgb8(colors[sampled] * 0.6), radii=design.spacing / 8),
                   static=True)
    if design.group_names:
        legend = "\n".join(f"- muscle group {g}: {name}, tab10 colour {g % len(PALETTE)}"
                           for g, name in enumerate(design.group_names))
        stream.log(f"{root}/muscle_groups", rr.TextDocument(legend + "\n- grey: passive", media_type="text/markdown"),
                   static=True)
    return [f"{root}/particles/stiffness"]


def blueprint(roots: list[str], hidden: list[str], episodes: bool):
    """A 3D view of everything but the plots, with the actions and rewards plotted beside it."""
    import rerun.blueprint as rrb

    scene = rrb.Spatial3DView(name="scene", origin="/", contents=["+ /**", "- /**/plots/**"],
                              overrides={path: rrb.EntityBehavior(visible=False) for path in hidden})
    panels = (rrb.SelectionPanel(state="collapsed"),)
    if not episodes:
        return rrb.Blueprint(scene, *panels)
    plots = rrb.Vertical(
        rrb.TimeSeriesView(name="actions", contents=[f"+ /{r}/plots/actions/**" for r in roots]),
        rrb.TimeSeriesView(name="reward per step", contents=[f"+ /{r}/plots/reward" for r in roots]),
        rrb.TimeSeriesView(name="torn off (% of the robot's mass)",
                           contents=[f"+ /{r}/plots/torn_percent" for r in roots]),
    )
    return rrb.Blueprint(rrb.Horizontal(scene, plots, column_shares=[2, 1]), rrb.TimePanel(timeline="step"), *panels)


def write(items: list[Path | Episode | Design], iterations: list[str], out: Path) -> Path:
    """Log every episode and design into one .rrd at `out`, each in a lane of its own when there are
    several; runs are replayed one at a time, and each recording is dropped once logged."""
    import rerun as rr

    if out.suffix != SUFFIX:
        raise CodesignError(f"--out {out}: a recording is a {SUFFIX} file (Rerun's format); name it FILE{SUFFIX}")
    out.parent.mkdir(parents=True, exist_ok=True)
    stream = rr.RecordingStream(APP_ID)
    stream.save(out)
    try:
        stream.log("/", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        count = sum(len(iterations) if isinstance(item, Path) else 1 for item in items)
        roots: list[str] = []
        hidden: list[str] = []
        offset, episodes = 0.0, False
        for item in items:
            for shown in _expand(item, iterations):
                root = _unique(shown.label, roots)
                roots.append(root)
                if count > 1:
                    stream.log(root, rr.Transform3D(translation=[0.0, 0.0, offset]), static=True)
                    offset += lane_width(shown) * (1 + LANE_MARGIN)
                if isinstance(shown, Episode):
                    hidden += log_episode(stream, root, shown.rec, named=count > 1)
                    episodes = True
                else:
                    hidden += log_design(stream, root, shown)
        stream.send_blueprint(blueprint(roots, hidden, episodes))
    except BaseException:
        stream.disconnect()
        out.unlink(missing_ok=True)  # no half recording left behind
        raise
    stream.disconnect()  # flushes and writes the file's footer
    return out


def _expand(item: Path | Episode | Design, iterations: list[str]) -> Iterator[Episode | Design]:
    """A run's episodes at `iterations`, replayed as they are asked for; anything else as it is."""
    if not isinstance(item, Path):
        yield item
        return
    for it in iterations:
        yield Episode(f"{_part(item.name)}/{'best' if it == 'best' else 'iteration_' + it}",
                      record_run(item, iteration=it))


def _unique(label: str, taken: list[str]) -> str:
    """`label`, or label_2, label_3, ... when taken (two runs of the same name in a comparison)."""
    root, n = label, 1
    while root in taken:
        n += 1
        root = f"{label}_{n}"
    return root


# --- opening ----------------------------------------------------------------------------------


def how_to_open(path: Path) -> str:
    return (f"open it with Rerun's viewer (pip install rerun-sdk, on this machine or another):\n"
            f"  rerun {path}                 # native viewer\n"
            f"  rerun --serve-web {path}     # web viewer at http://localhost:{WEB_PORT}\n"
            f"or serve it from here: codesign view ... --serve [--port {WEB_PORT}]")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve_command(path: Path, port: int, data_port: int) -> tuple[list[str], str]:
    """The `rerun` command that serves `path` to browsers on `port` (its data on `data_port`), and the
    address that opens it."""
    url = f"http://localhost:{port}/?url=" + quote(f"rerun+http://localhost:{data_port}/proxy", safe="")
    return ([sys.executable, "-m", "rerun", "--serve-web", "--web-viewer-port", str(port), "--port", str(data_port),
             str(path)], url)


def serve(path: Path, port: int) -> None:
    """Serve the recording to web browsers on `port` (Rerun's bundled web viewer) until Ctrl-C."""
    command, url = serve_command(path, port, _free_port())
    print(f"serving {path}: open {url} (Ctrl-C stops)", file=sys.stderr, flush=True)
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
    try:
        code = process.wait()
    except KeyboardInterrupt:
        process.terminate()
        process.wait()
        return
    if code != 0:
        raise CodesignError(f"the viewer's server stopped (exit {code}): is port {port} in use? choose another "
                            "with --port")


def view(sources: list[Path], iterations: list[str], out: Path | None = None) -> ViewRecording:
    """`codesign view`: check the sources, replay and log them, and say how to open the recording."""
    try:
        import rerun  # noqa: F401  (an optional dependency: half a gigabyte installed)
    except ImportError as exc:
        raise CodesignError('codesign view needs the Rerun SDK: pip install "codesign[view]" '
                            '(or pip install "rerun-sdk>=0.41,<0.42")') from exc
    items = resolve(sources, iterations)
    path = write(items, iterations, Path(out) if out is not None else default_out(sources))
    return ViewRecording(path, how_to_open(path), lambda port: serve(path, port))
