"""Turn body specs into particles: lattice sampling inside shapes, muscles, materials.

Each particle stands for the shape's volume divided by the number of particles actually
seeded, so mass and stiffness do not change with the sampling density or with how the
lattice happens to fit the shape (the old code used dx^3 for every particle).

Layers (ground cover: sand, snow, water, ...) are sampled after every other body, as in the
paper: on the terrain, up to their thickness, leaving out the grid cells that the other
bodies' particles occupy, so no two bodies overlap.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from codesign.bodies import Body, BodyError, Labels, library_body, load_body
from codesign.geometry import grid_partition
from codesign_mpm.scene.integrity import MIN_THICKNESS_CELLS, thinnest_cells
from codesign_mpm.materials import MATERIALS, load_plugin_materials, spec_params
from codesign_mpm.scene.spec import BodySpec, Scene, SceneError, ShapeSpec
from codesign_mpm.scene.terrain import height_map


@dataclass
class Particles:
    """Initial particle state and per-particle material / design fields (numpy, float64)."""

    x: np.ndarray  # (N,3)
    v: np.ndarray  # (N,3)
    volume: np.ndarray  # (N,)
    density: np.ndarray  # (N,)
    youngs_modulus: np.ndarray  # (N,)
    poisson_ratio: np.ndarray  # (N,)
    material: np.ndarray  # (N,) int model id
    muscle: np.ndarray  # (N,K) membership r_p
    fiber: np.ndarray  # (N,3) unit fibre direction f_p
    muscle_ratio: np.ndarray  # (N,) muscle stiffness s_p / E_p
    params: np.ndarray  # (N, N_PARAMS) parameters of the non-elastic models (materials.spec_params)
    body: np.ndarray  # (N,) index of the body in scene.bodies
    robot: np.ndarray  # (N,) bool

    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def n_actuators(self) -> int:
        return self.muscle.shape[1]


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Points at cell centres of a regular lattice covering [lo, hi]."""
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def fitted_lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres of a lattice that spans [lo, hi] exactly, each axis split into round(extent /
    spacing) equal cells (the same count `lattice` gives), and a cell's edge lengths. A body then has
    its shape's extents at every dx instead of snapping to the spacing: on a plain lattice a box
    0.08 high sampled 0.0833 high at dx 1/48 and 0.078 at dx 1/32 (measured), so the muscles'
    lever arms, the mass's height and the contact patch changed with the resolution."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    counts = np.maximum(1, np.round((hi - lo) / spacing)).astype(int)
    cell = (hi - lo) / counts
    axes = [a + (np.arange(c) + 0.5) * h for a, c, h in zip(lo, counts, cell)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3), cell


def _load_points(path: Path) -> np.ndarray:
    if path.suffix == ".npy":
        return np.asarray(np.load(path), dtype=np.float64).reshape(-1, 3)
    if path.suffix == ".xyz":
        return np.loadtxt(path)[:, :3]
    import trimesh

    return np.asarray(trimesh.load(path).vertices, dtype=np.float64)


def _fitted_body(key: str, shape: ShapeSpec) -> Body:
    """The solid of a `body` shape, scaled uniformly to fit in `size` and centred on the origin."""
    source, value = ("body", shape.body) if shape.body else ("file", shape.file)
    try:
        body = library_body(shape.body) if shape.body else load_body(shape.file)
    except BodyError as exc:
        raise SceneError(f"{key}.shape.{source} = {value!r} is invalid: {exc}") from exc
    return body.fitted(shape.size)


def _shape_points(key: str, shape: ShapeSpec, spacing: float) -> tuple[np.ndarray, float, float]:
    """Particle offsets from the body centre, the shape's total volume and the particles' vertical
    spacing (a lattice fitted to the shape's bounds: `fitted_lattice`)."""
    if shape.kind == "body":
        body = _fitted_body(key, shape)
        p, cell = fitted_lattice(*body.bounds, spacing)
        p = p[body.contains(p)]
        return p, len(p) * float(np.prod(cell)), cell[1]
    if shape.kind in ("box", "ellipsoid"):
        size = np.asarray(shape.size, dtype=float)
        p, cell = fitted_lattice(-size / 2, size / 2, spacing)
        if shape.kind == "box":
            return p, float(np.prod(size)), cell[1]
        return p[((2 * p / size) ** 2).sum(1) <= 1], float(np.pi / 6 * np.prod(size)), cell[1]
    if shape.kind == "sphere":
        r = shape.radius
        p, cell = fitted_lattice(np.full(3, -r), np.full(3, r), spacing)
        return p[(p ** 2).sum(1) <= r * r], 4 / 3 * np.pi * r ** 3, cell[1]
    if shape.kind == "capsule":
        r, h = shape.radius, shape.length / 2
        p, cell = fitted_lattice(np.array([-h - r, -r, -r]), np.array([h + r, r, r]), spacing)
        axial = np.clip(p[:, 0], -h, h)
        inside = (p[:, 0] - axial) ** 2 + p[:, 1] ** 2 + p[:, 2] ** 2 <= r * r
        return p[inside], np.pi * r * r * shape.length + 4 / 3 * np.pi * r ** 3, cell[1]
    path = Path(shape.file or "")
    if not path.is_file():
        raise SceneError(f"{key}.shape.file = {shape.file!r} is invalid: no such file")
    if shape.kind == "voxels":
        occ = np.load(path).astype(bool)
        if occ.ndim != 3:
            raise SceneError(f"{key}.shape.file = {shape.file!r} is invalid: need a 3-D boolean array")
        size = np.asarray(occ.shape) * shape.voxel_size
        p, cell = fitted_lattice(-size / 2, size / 2, spacing)
        idx = np.clip(((p + size / 2) / shape.voxel_size).astype(int), 0, np.asarray(occ.shape) - 1)
        return p[occ[idx[:, 0], idx[:, 1], idx[:, 2]]], float(occ.sum() * shape.voxel_size ** 3), cell[1]
    if shape.kind == "mesh":
        import trimesh

        mesh = trimesh.load(path, force="mesh")
        lo, hi = mesh.bounds
        mesh.apply_translation(-(lo + hi) / 2)
        mesh.apply_scale(shape.scale / (hi - lo).max())
        lo, hi = mesh.bounds
        p, cell = fitted_lattice(lo, hi, spacing)
        inside = mesh.contains(p)
        volume = float(mesh.volume) if mesh.is_watertight else inside.sum() * float(np.prod(cell))
        return p[inside], volume, cell[1]
    # points: used as given; each stands for the volume of the lattice cells it occupies
    pts = _load_points(path)
    lo, hi = pts.min(0), pts.max(0)
    pts = (pts - (lo + hi) / 2) * (shape.scale / (hi - lo).max())
    h = (np.prod(np.maximum(hi - lo, 1e-12)) * (shape.scale / (hi - lo).max()) ** 3 / len(pts)) ** (1 / 3)
    cells = np.unique(np.floor(pts / h).astype(np.int64), axis=0)
    return pts, len(cells) * h ** 3, spacing


def rotation_matrix(degrees: list[float]) -> np.ndarray:
    """Rotation about x, then y, then z (extrinsic), angles in degrees."""
    rx, ry, rz = np.radians(degrees)
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def build_particles(scene: Scene) -> Particles:
    """Sample every body of a (validated) scene; actuators of all bodies are numbered in order.

    Particles keep the order of `scene.bodies`; layers are sampled last (they fill the space
    the others leave) but still stored in their place in that order.
    """
    if any(body.material.kind not in MATERIALS for body in scene.bodies):
        load_plugin_materials()  # a plugin's model (validate_scene loads them too)
    by_body: dict[int, dict[str, np.ndarray]] = {}
    for i, body in enumerate(scene.bodies):
        if body.shape.kind != "layer":
            by_body[i] = _body_particles(scene, i, body)
    for i, body in enumerate(scene.bodies):
        if body.shape.kind == "layer":
            by_body[i] = _layer_particles(scene, i, body, list(by_body.values()))
    return join_particles([Particles(**by_body[i]) for i in range(len(scene.bodies))])


def join_particles(parts: list[Particles]) -> Particles:
    """The particles of every part, in order, in new arrays; each part's muscles take their own block
    of columns. The rest of the muscle matrix stays as `np.zeros` allocates it, untouched, so a
    terrain of millions of particles costs nothing for the muscles it lacks."""
    muscle = np.zeros((sum(p.n for p in parts), sum(p.n_actuators for p in parts)))
    row = column = 0
    for p in parts:
        muscle[row:row + p.n, column:column + p.n_actuators] = p.muscle
        row, column = row + p.n, column + p.n_actuators
    return Particles(muscle=muscle, **{name: np.concatenate([getattr(p, name) for p in parts])
                                       for name in Particles.__dataclass_fields__ if name != "muscle"})


def _body_particles(scene: Scene, i: int, body: BodySpec) -> dict[str, np.ndarray]:
    key = f"bodies[{i}]"
    per_axis = round(body.particles_per_cell ** (1 / 3))
    spacing = scene.dx / per_axis
    if body.shape.kind == "body":
        _check_resolved(scene, key, body.shape)
    offsets, total_volume, rise = _shape_points(key, body.shape, spacing)
    if len(offsets) == 0:
        raise SceneError(f"{key}.shape = {body.shape!r} is invalid: it holds no particle at "
                         f"dx={scene.dx}; make it larger or the grid finer")
    local = offsets
    if body.shape.kind == "body":
        _warn_thin(scene, key, body.shape, local, spacing)
    offsets = local @ rotation_matrix(body.rotation).T
    center = np.asarray(body.center, dtype=float)
    if body.rest_on_terrain:
        heights = height_map(scene)
        ij = np.clip(np.round((offsets[:, [0, 2]] + center[[0, 2]]) / scene.dx).astype(int), 0,
                     np.asarray(heights.shape) - 1)
        ground = heights[ij[:, 0], ij[:, 1]].max()
        # the lowest particles half a lattice spacing above the surface: the body's face touches it,
        # with no free grid cell beneath for a ground cover to fill
        center[1] = ground + body.rest_offset + rise / 2 - offsets[:, 1].min()
    x = offsets + center
    margin = scene.wall
    lo_ok = (x >= margin).all()
    hi_ok = (x <= np.asarray(scene.size) - margin).all()
    if not (lo_ok and hi_ok):
        raise SceneError(f"{key}.center = {center.tolist()} is invalid: the body spans "
                         f"{x.min(0).round(4).tolist()} to {x.max(0).round(4).tolist()}, outside the "
                         f"domain interior [{margin:.4g}, size - {margin:.4g}] for size {list(scene.size)}")
    n = len(x)
    labels = _body_labels(scene, key, body.shape, local) if body.shape.kind == "body" else None
    if body.muscles is not None and body.muscles.layout == "body":
        k = _fitted_body(key, body.shape).n_groups
        if k == 0:
            raise SceneError(f"{key}.muscles.layout = 'body' is invalid: the body ({_body_source(key, body.shape)}) "
                             "has no muscle groups; annotate it (codesign annotate) or use layout grid")
        muscle = np.zeros((n, k))
        active = labels.groups >= 0
        muscle[np.flatnonzero(active), labels.groups[active]] = 1.0
        fiber = labels.fibers @ rotation_matrix(body.rotation).T
        ratio = body.muscles.stiffness_ratio
    elif body.muscles is not None:
        groups = list(body.muscles.groups)
        muscle = np.eye(int(np.prod(groups)))[grid_partition(local, groups)]
        fiber = rotation_matrix(body.rotation) @ np.asarray(body.muscles.fiber, dtype=float)
        fiber = np.tile(fiber / np.linalg.norm(fiber), (n, 1))
        ratio = body.muscles.stiffness_ratio
    else:
        muscle, fiber, ratio = np.zeros((n, 0)), np.tile([1.0, 0, 0], (n, 1)), 0.0
    fields = _fields(i, body, x, total_volume / n, muscle, fiber, ratio)
    if labels is not None:
        fields["youngs_modulus"] = fields["youngs_modulus"] * labels.stiffness
    if body.muscles is not None and body.muscles.layout == "body":
        passive = labels.groups < 0
        fields["density"][passive] *= body.muscles.passive_density
        fields["youngs_modulus"][passive] *= body.muscles.passive_stiffness
    return fields


def _body_source(key: str, shape: ShapeSpec) -> str:
    return f"{key}.shape.body = {shape.body!r}" if shape.body else f"{key}.shape.file = {shape.file!r}"


def _check_resolved(scene: Scene, key: str, shape: ShapeSpec) -> None:
    """A body thinner than a grid cell along some axis cannot be simulated meaningfully: say so."""
    lo, hi = _fitted_body(key, shape).bounds
    for axis, extent in zip("xyz", hi - lo):
        if extent < scene.dx:
            raise SceneError(f"{_body_source(key, shape)} is invalid: fitted to size {list(shape.size)} the body is "
                             f"{extent:.3g} thick along {axis}, under one grid cell (dx = {scene.dx:.4g}); make it "
                             "larger or the grid finer")


def _warn_thin(scene: Scene, key: str, shape: ShapeSpec, local: np.ndarray, spacing: float) -> None:
    """Warn when a body's thinnest part (on its sampling lattice, before rotation) is under
    `integrity.MIN_THICKNESS_CELLS` grid cells: the grid carries it on one or two rows of nodes and it
    tears at small strains. (A design representation drops such parts; a scene keeps them.)"""
    cells = thinnest_cells(local, spacing, scene.dx, MIN_THICKNESS_CELLS)
    if cells < MIN_THICKNESS_CELLS:
        warnings.warn(f"{_body_source(key, shape)}: fitted to size {list(shape.size)}, its thinnest part is "
                      f"{cells:.3g} grid cells thick at dx = {scene.dx:.4g}, under the {MIN_THICKNESS_CELLS:g} cells "
                      "the grid carries without tearing; give the body a larger size or the grid a finer dx",
                      UserWarning, stacklevel=2)


def _body_labels(scene: Scene, key: str, shape: ShapeSpec, local: np.ndarray) -> Labels:
    """The body's labels at its particles; every muscle group must keep at least one particle."""
    body = _fitted_body(key, shape)
    labels = body.labels(local)
    empty = np.flatnonzero(np.bincount(labels.groups[labels.groups >= 0], minlength=body.n_groups) == 0)
    if len(empty):
        raise SceneError(f"{_body_source(key, shape)} is invalid: its muscle group {empty[0]} "
                         f"({body.group_names[empty[0]]}) holds no particle at dx = {scene.dx:.4g} and size "
                         f"{list(shape.size)}; make the body larger or the grid finer")
    return labels


def _fields(i: int, body: BodySpec, x: np.ndarray, volume: float, muscle: np.ndarray, fiber: np.ndarray,
            ratio: float) -> dict[str, np.ndarray]:
    n, mat = len(x), body.material
    params = spec_params(mat)
    # rows alike in every particle are read-only views; join_particles writes them once
    return dict(
        x=x, v=np.broadcast_to(np.asarray(body.velocity, dtype=float), (n, 3)), volume=np.full(n, volume),
        density=np.full(n, mat.density), youngs_modulus=np.full(n, mat.youngs_modulus),
        poisson_ratio=np.full(n, mat.poisson_ratio),
        material=np.full(n, MATERIALS[mat.kind].id, dtype=np.int32), muscle=muscle, fiber=fiber,
        muscle_ratio=np.full(n, ratio), params=np.broadcast_to(params, (n, len(params))),
        body=np.full(n, i, dtype=np.int32), robot=np.full(n, body.robot, dtype=bool))


def _inside(points: np.ndarray, bodies: list[dict[str, np.ndarray]]) -> np.ndarray:
    """Which points lie in the space the bodies' particles stand for: within half a particle's width
    (the cube root of its volume) of one of them along every axis. (Grid cells holding a particle
    were used before: where a cell boundary fell within the half spacing under a body's lowest row,
    a sheet of the desert's sand was sampled inside the robot and halved its distance at dx 1/64 and
    1/96: docs/log/contact.md section 21.)"""
    inside = np.zeros(len(points), dtype=bool)
    for body in bodies:
        half = 0.5 * np.cbrt(body["volume"])
        reach = half.max()
        # only points in the body's box ask the tree: a layer spans the domain, a body a corner of it
        box = np.flatnonzero(np.all((points >= body["x"].min(axis=0) - reach)
                                    & (points <= body["x"].max(axis=0) + reach), axis=1))
        distance, nearest = cKDTree(body["x"]).query(points[box], p=np.inf, distance_upper_bound=reach)
        near = np.isfinite(distance)
        inside[box[near]] |= distance[near] < half[nearest[near]]
    return inside


def layer_ground(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Where a layer starts under each point: the terrain's height (not below the wall band) at the
    node column nearest the point's (x, z)."""
    heights = np.maximum(height_map(scene), scene.wall)
    ij = np.clip(np.round(points[:, [0, 2]] / scene.dx).astype(int), 0, np.asarray(heights.shape) - 1)
    return heights[ij[:, 0], ij[:, 1]]


def _layer_particles(scene: Scene, i: int, body: BodySpec, others: list[dict[str, np.ndarray]]
                     ) -> dict[str, np.ndarray]:
    """A layer of `thickness` on the terrain, wall to wall, minus the space the `others` (the bodies
    sampled before it) fill.

    Each column of particles spans the layer exactly, from its own ground up: round(thickness /
    spacing) rows of equal height, so the layer's mass and top do not snap to the particle
    spacing (on a plain lattice the desert's 0.02 of sand was sampled 0.0234 thick at 8 particles
    per cell and 0.0208 at 27, dx 1/64, and the robot's distance in it moved by 40%: docs/log/contact.md
    section 20). The walls are the outermost `boundary_cells` nodes, so the last wall node, at
    (boundary_cells - 1) dx from the edge, is where material comes to rest against them.
    """
    spacing = scene.dx / round(body.particles_per_cell ** (1 / 3))
    margin = scene.wall
    size = np.asarray(scene.size, dtype=float)
    thickness = body.shape.thickness
    top = max(float(height_map(scene).max()), margin) + thickness
    if top > size[1] - margin:
        raise SceneError(f"bodies[{i}].shape.thickness = {thickness!r} is invalid: the layer "
                         f"reaches y = {top:.4g}, above the domain interior (size - {margin:.4g})")
    columns = lattice(np.array([margin, 0.0, margin]), np.array([size[0] - margin, spacing, size[2] - margin]),
                      spacing)  # one lattice row: the columns' (x, z)
    ground = layer_ground(scene, columns)
    rows = max(1, round(thickness / spacing))
    row_height = thickness / rows
    x = np.repeat(columns, rows, axis=0)
    x[:, 1] = (ground[:, None] + (np.arange(rows) + 0.5) * row_height).reshape(-1)
    x = x[~_inside(x, others)]
    if len(x) == 0:
        raise SceneError(f"bodies[{i}].shape = {body.shape!r} is invalid: the layer holds no particle "
                         f"(no free space above the terrain at dx={scene.dx})")
    n = len(x)
    return _fields(i, body, x, spacing ** 2 * row_height, np.zeros((n, 0)), np.broadcast_to([1.0, 0, 0], (n, 3)), 0.0)
