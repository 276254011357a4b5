"""Robot bodies: solids given by a signed distance, with labelled muscles (numpy only).

A :class:`Body` lives in a canonical frame: heading +x, up +y, right +z, centred on its
bounding box, longest extent 1. Every point of space gets a signed distance (negative
inside), a muscle group (-1: passive), a unit fibre direction and a relative stiffness, so one
body can be an environment's robot (sampled at that scene's particle spacing) or a design
primitive (SDF-Lerp, Wasserstein barycenters) evaluated at a representation's particles.

The library holds the four animals of the SoftZoo paper (baby seal, caterpillar, fish,
panda), built from smooth primitives because the paper's meshes are not public, and a
parametric family of fish-like bodies. Body files: an annotated ``.npz`` (``codesign
annotate``), a watertight mesh (anything trimesh loads), a point cloud (``.ply``/``.npz``)
or a voxel grid (``.npy``). trimesh and scipy are imported only when a file needs them, so
importing this module stays cheap.
"""
from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codesign.errors import CodesignError

HEADING = np.array([1.0, 0.0, 0.0])
ANIMALS = ("seal", "caterpillar", "fish", "panda")
MESH_SUFFIXES = (".obj", ".stl", ".off", ".glb", ".gltf", ".dae", ".3mf")
POINT_SUFFIXES = (".npz", ".ply", ".xyz")
VOXEL_SUFFIXES = (".npy",)
BODY_FILE_SUFFIXES = tuple(sorted(set(MESH_SUFFIXES + POINT_SUFFIXES + VOXEL_SUFFIXES)))


class BodyError(CodesignError, ValueError):
    """A body (file) that cannot be used as written; the message names the file and the problem."""


@dataclass(frozen=True)
class Labels:
    """What a body says about a set of points."""

    groups: np.ndarray
    """(N,) muscle group index, -1 for passive material."""
    fibers: np.ndarray
    """(N, 3) unit fibre directions."""
    stiffness: np.ndarray
    """(N,) Young's modulus relative to the robot's material."""


def passive_labels(n: int) -> Labels:
    """Labels of material without muscles: the default for unannotated files."""
    return Labels(np.full(n, -1), np.tile(HEADING, (n, 1)), np.ones(n))


class Body(ABC):
    """A solid with muscle labels; subclasses give the signed distance and the labels."""

    name: str
    group_names: tuple[str, ...] = ()

    @property
    def n_groups(self) -> int:
        return len(self.group_names)

    @abstractmethod
    def sdf(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distance of (N, 3) points, negative inside (approximate away from the surface)."""

    @abstractmethod
    def labels(self, points: np.ndarray) -> Labels:
        """Muscle group, fibre and relative stiffness of the material at (N, 3) points."""

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) inside test; meshes override it with an exact test."""
        return self.sdf(points) <= 0

    @functools.cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) lower and upper corner of the bounding box."""
        return self._bounds()

    @abstractmethod
    def _bounds(self) -> np.ndarray:
        """Compute `bounds` (called once)."""

    def transformed(self, scale: float, offset: Sequence[float]) -> Body:
        """This body scaled uniformly by `scale` about the origin, then moved by `offset`."""
        return Transformed(self, scale, np.asarray(offset, dtype=float))

    def fitted(self, size: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0)) -> Body:
        """Scaled uniformly to the largest size that fits in a box of extents `size`, centred at `center`."""
        lo, hi = self.bounds
        scale = float(np.min(np.asarray(size, dtype=float) / (hi - lo)))
        return self.transformed(scale, np.asarray(center, dtype=float) - scale * (lo + hi) / 2)

    def signed_distance(self, points: np.ndarray, cell: float) -> np.ndarray:
        """(N,) the true signed distance of (N, 3) points to the body (negative inside), to about a
        `cell`: a Euclidean distance transform of its occupancy on a lattice of `cell` over the
        points and the body, read off trilinearly, signed by `contains`. `sdf` is only a bound
        away from the surface (an ellipsoid's is 2 to 3 times too deep in a slender fish, a
        sampled body's at most a sample spacing deep), which biases a blend of distances toward
        whichever body's bound is deeper."""
        from scipy.ndimage import distance_transform_edt, map_coordinates

        p = np.asarray(points, dtype=float).reshape(-1, 3)
        lo = np.minimum(p.min(0), self.bounds[0]) - 2 * cell
        hi = np.maximum(p.max(0), self.bounds[1]) + 2 * cell
        counts = np.ceil((hi - lo) / cell).astype(int)
        axes = [lo[a] + (np.arange(counts[a]) + 0.5) * cell for a in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        inside = self.contains(centres).reshape(counts)
        # distance from a cell centre to the nearest centre across the surface, less half a cell
        depth = np.where(inside, distance_transform_edt(inside), distance_transform_edt(~inside)) * cell - cell / 2
        magnitude = map_coordinates(depth, ((p - lo) / cell - 0.5).T, order=1, mode="nearest")
        magnitude = np.maximum(magnitude, 1e-9 * cell)  # strictly signed, as `contains` says
        return np.where(self.contains(p), -magnitude, magnitude)

    def sample(self, spacing: float) -> np.ndarray:
        """(M, 3) points inside the body on a lattice of `spacing` (cell centres over its bounds)."""
        points = lattice(*self.bounds, spacing)
        return points[self.contains(points)]


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Cell centres of a regular lattice over [lo, hi]."""
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


class Transformed(Body):
    """A body scaled uniformly and moved; distances scale, fibres and labels do not change."""

    def __init__(self, base: Body, scale: float, offset: np.ndarray) -> None:
        if not scale > 0:
            raise BodyError(f"body {base.name!r}: scale {scale!r} must be > 0")
        self.base, self.scale, self.offset = base, scale, offset
        self.name, self.group_names = base.name, base.group_names

    def _local(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=float) - self.offset) / self.scale

    def sdf(self, points: np.ndarray) -> np.ndarray:
        return self.scale * self.base.sdf(self._local(points))

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.base.contains(self._local(points))

    def labels(self, points: np.ndarray) -> Labels:
        return self.base.labels(self._local(points))

    def _bounds(self) -> np.ndarray:
        return self.base.bounds * self.scale + self.offset

    def transformed(self, scale: float, offset: Sequence[float]) -> Body:
        return Transformed(self.base, self.scale * scale, self.offset * scale + np.asarray(offset, dtype=float))


def normalized(body: Body) -> Body:
    """`body` centred on its bounding box with its longest extent 1: the canonical frame."""
    lo, hi = body.bounds
    scale = 1.0 / float((hi - lo).max())
    return body.transformed(scale, -scale * (lo + hi) / 2)


# --- procedural bodies -------------------------------------------------------------------------

Field = Callable[[np.ndarray], np.ndarray]


def rotation(axis: str, degrees: float) -> np.ndarray:
    """Rotation matrix about the x, y or z axis."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


@dataclass(frozen=True)
class Solid:
    """A primitive's signed distance and a box that holds it (to find a body's bounds quickly)."""

    sdf: Field
    box: np.ndarray
    """(2, 3) lower and upper corner."""


def ellipsoid(center: Sequence[float], radii: Sequence[float], rot: np.ndarray | None = None) -> Solid:
    """Signed distance (Quilez's bound, exact on the surface) to an ellipsoid whose axes are `rot`'s columns."""
    c, r = np.asarray(center, dtype=float), np.asarray(radii, dtype=float)
    rt = np.eye(3) if rot is None else np.asarray(rot, dtype=float)

    def sdf(p: np.ndarray) -> np.ndarray:
        q = (p - c) @ rt  # into the ellipsoid's frame: rt^T (p - c)
        k0 = np.linalg.norm(q / r, axis=1)
        k1 = np.linalg.norm(q / r ** 2, axis=1)
        return np.where(k1 > 1e-12, k0 * (k0 - 1) / np.maximum(k1, 1e-12), -r.min())

    half = np.sqrt((rt ** 2) @ r ** 2)  # exact half extents of a rotated ellipsoid
    return Solid(sdf, np.stack([c - half, c + half]))


def capsule(a: Sequence[float], b: Sequence[float], radius: float) -> Solid:
    """Exact signed distance to the segment a-b thickened by `radius`."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ab = b - a

    def sdf(p: np.ndarray) -> np.ndarray:
        t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
        return np.linalg.norm(p - a - t[:, None] * ab, axis=1) - radius

    return Solid(sdf, np.stack([np.minimum(a, b) - radius, np.maximum(a, b) + radius]))


def smooth_union(d1: np.ndarray, d2: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: blends two solids with a fillet of size about `k`."""
    h = np.clip(0.5 + 0.5 * (d2 - d1) / k, 0.0, 1.0)
    return d2 + (d1 - d2) * h - k * h * (1 - h)


@dataclass(frozen=True)
class Part:
    """One smooth primitive of a procedural body, and the muscle labels of the material nearest it."""

    solid: Solid
    group: int | Callable[[np.ndarray], np.ndarray] = -1
    """A group index (-1 passive) or a function of the points nearest this part (e.g. to split flanks)."""
    fiber: Sequence[float] = (1.0, 0.0, 0.0)
    stiffness: float = 1.0


class PartsBody(Body):
    """A smooth union of parts; each point takes the labels of the part nearest to it."""

    def __init__(self, name: str, parts: Sequence[Part], group_names: Sequence[str], blend: float = 0.03) -> None:
        self.name, self.parts, self.group_names, self.blend = name, tuple(parts), tuple(group_names), blend

    def _distances(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.stack([part.solid.sdf(p) for part in self.parts])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        d = self._distances(points)
        out = d[0]
        for other in d[1:]:
            out = smooth_union(out, other, self.blend)
        return out

    def labels(self, points: np.ndarray) -> Labels:
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        nearest = self._distances(p).argmin(0)
        labels = passive_labels(len(p))
        for i, part in enumerate(self.parts):
            mine = nearest == i
            if not mine.any():
                continue
            group = part.group(p[mine]) if callable(part.group) else part.group
            labels.groups[mine] = group
            fiber = np.asarray(part.fiber, dtype=float)
            labels.fibers[mine] = fiber / np.linalg.norm(fiber)
            labels.stiffness[mine] = part.stiffness
        return labels

    def _bounds(self) -> np.ndarray:
        """Found on a lattice of 1/100 of the extent inside the union of the parts' boxes."""
        lo = np.min([part.solid.box[0] for part in self.parts], axis=0)
        hi = np.max([part.solid.box[1] for part in self.parts], axis=0)
        step = (hi - lo).max() / 100
        inside = (points := lattice(lo - step, hi + step, step))[self.sdf(points) <= 0]
        if not len(inside):
            raise BodyError(f"body {self.name!r} holds no solid")
        return np.stack([inside.min(0) - step / 2, inside.max(0) + step / 2])


def _split(*conditions_and_groups) -> Callable[[np.ndarray], np.ndarray]:
    """Group of each point: the group of the first condition it meets; the last entry is the default."""
    *pairs, default = conditions_and_groups

    def group(p: np.ndarray) -> np.ndarray:
        out = np.full(len(p), default)
        for condition, g in reversed(list(zip(pairs[::2], pairs[1::2]))):
            out[condition(p)] = g
        return out

    return group


@dataclass(frozen=True)
class FishShape:
    """Parameters of a fish-like body (canonical length about 1)."""

    height: float = 0.32
    """Body depth (y) as a fraction of the length."""
    thickness: float = 0.16
    """Body width (z)."""
    tail: float = 0.22
    """Length of each lobe of the caudal fin."""
    fork: float = 32.0
    """Angle (degrees) of the caudal lobes from the body axis."""
    peduncle: float = 0.16
    """Length of the narrow stalk between body and tail fin."""
    dorsal: float = 0.08
    """Height of the dorsal fin (0: none)."""


FISH_FAMILY: dict[str, FishShape] = {
    "fish_slender": FishShape(height=0.22, thickness=0.13, tail=0.2, fork=28.0, peduncle=0.2, dorsal=0.05),
    "fish_deep": FishShape(height=0.46, thickness=0.15, tail=0.2, fork=38.0, peduncle=0.1, dorsal=0.1),
    "fish_long_tail": FishShape(height=0.28, thickness=0.14, tail=0.32, fork=24.0, peduncle=0.22, dorsal=0.06),
    "fish_flat": FishShape(height=0.18, thickness=0.3, tail=0.2, fork=30.0, peduncle=0.14, dorsal=0.0),
    "fish_round": FishShape(height=0.4, thickness=0.34, tail=0.16, fork=40.0, peduncle=0.08, dorsal=0.0),
}
"""Fish-like design primitives (the SoftZoo figure of fish primitives): slender, deep, long-tailed,
flat and round; each with the fish's four flank muscles."""

FISH_GROUPS = ("left front flank", "right front flank", "left rear flank", "right rear flank")


def fish_body(name: str = "fish", shape: FishShape = FishShape()) -> Body:
    """A fish: spindle torso, narrow peduncle, forked caudal fin and an optional dorsal fin.

    Muscles are antagonistic pairs along both flanks (left z < 0, right z > 0), front and rear,
    with fibres along the body axis: alternating left and right contraction bends the body from
    side to side, the swimming gait. Fins are passive and softer than the body.
    """
    h, t = shape.height / 2, shape.thickness / 2
    stalk_end = -0.1 - shape.peduncle  # the torso spans [-0.15, 0.45], the peduncle continues behind it
    middle = (stalk_end + 0.45) / 2  # front and rear muscles meet half-way along the muscular body
    flank = _split(lambda p: (p[:, 0] > middle) & (p[:, 2] < 0), 0, lambda p: p[:, 0] > middle, 1,
                   lambda p: p[:, 2] < 0, 2, 3)
    fin = dict(group=-1, stiffness=0.6)
    parts = [
        Part(ellipsoid([0.15, 0, 0], [0.3, h, t]), group=flank),
        Part(ellipsoid([-0.1 - shape.peduncle / 2, 0, 0], [shape.peduncle / 2 + 0.05, 0.35 * h + 0.02, 0.5 * t + 0.01]),
             group=flank),
    ]
    lobe = shape.tail / 2
    for sign in (1, -1):
        turn = rotation("z", 180 - sign * shape.fork)  # the lobe's long axis points back and up (down)
        parts.append(Part(ellipsoid(np.array([stalk_end, 0, 0]) + lobe * (turn @ HEADING), [lobe, 0.035, 0.03], turn),
                          fiber=-(turn @ HEADING), **fin))
    if shape.dorsal > 0:
        parts.append(Part(ellipsoid([0.1, h * 0.8, 0], [0.12, shape.dorsal + 0.2 * h, 0.025], rotation("z", 15)),
                          **fin))
    return normalized(PartsBody(name, parts, FISH_GROUPS, blend=0.04))


def seal_body() -> Body:
    """A baby seal: a plump body and round head, fore-flippers at the sides and a tail with hind flippers.

    Groups: the left and right fore-flippers (fibres along each flipper, so they sweep and push),
    and the rear of the body split into a dorsal and a ventral muscle (fibres along the body)
    whose alternation flaps the tail and its passive hind flippers up and down, the seal's
    push-off on ice.
    """
    tail = _split(lambda p: p[:, 0] > -0.18, -1, lambda p: p[:, 1] >= 0, 2, 3)
    parts = [
        Part(ellipsoid([0, 0, 0], [0.4, 0.17, 0.19]), group=tail),
        Part(ellipsoid([0.4, 0.06, 0], [0.15, 0.13, 0.14])),
    ]
    for sign, group in ((-1, 0), (1, 1)):
        turn = rotation("y", sign * 35) @ rotation("x", sign * 25)
        parts.append(Part(ellipsoid([0.14, -0.1, sign * 0.2], [0.14, 0.03, 0.07], turn), group=group,
                          fiber=turn @ HEADING))
    for sign in (-1, 1):
        splay = rotation("y", sign * 20)
        parts.append(Part(ellipsoid([-0.45, -0.06, sign * 0.055], [0.12, 0.03, 0.07], splay),
                          fiber=splay @ HEADING, stiffness=0.8))
    names = ("left fore-flipper", "right fore-flipper", "tail dorsal", "tail ventral")
    return normalized(PartsBody("seal", parts, names, blend=0.05))


CATERPILLAR_SEGMENTS = 6


def caterpillar_body() -> Body:
    """A caterpillar: a chain of round segments with a pair of prolegs under each.

    Each segment (numbered from the tail) is two muscles, its left and its right half with the leg
    on that side, fibres along the body: a wave of contractions passing from tail to head is the
    caterpillar's crawl, and one side contracting more than the other bends it, its turn. One
    muscle per segment would be mirror-symmetric about the body's midplane and could not turn it.
    """
    parts = []
    spacing = 0.17
    for i in range(CATERPILLAR_SEGMENTS):
        x = -0.43 + i * spacing
        r = 0.1 if i < CATERPILLAR_SEGMENTS - 1 else 0.11
        left, right = 2 * i, 2 * i + 1
        parts.append(Part(ellipsoid([x, 0, 0], [0.1, r, r]), group=_split(lambda p: p[:, 2] < 0, left, right)))
        for sign, group in ((-1, left), (1, right)):
            parts.append(Part(ellipsoid([x, -0.1, sign * 0.055], [0.03, 0.04, 0.03]), group=group))
    names = tuple(f"segment {i + 1} {side}" for i in range(CATERPILLAR_SEGMENTS) for side in ("left", "right"))
    return normalized(PartsBody("caterpillar", parts, names, blend=0.04))


def panda_body() -> Body:
    """A panda: a heavy body, head with ears and snout, four legs and a short tail.

    Each leg is one muscle with fibres along it: lengthening and shortening the legs in turn
    rocks and bounds the body forward, the spring-like gallop the paper reports.
    """
    parts = [
        Part(ellipsoid([0, 0.06, 0], [0.35, 0.2, 0.21])),
        Part(ellipsoid([0.37, 0.18, 0], [0.15, 0.14, 0.15])),
        Part(ellipsoid([0.5, 0.14, 0], [0.06, 0.05, 0.06])),
        Part(ellipsoid([-0.36, 0.12, 0], [0.05, 0.05, 0.05])),
    ]
    for sign in (-1, 1):
        parts.append(Part(ellipsoid([0.36, 0.33, sign * 0.1], [0.04, 0.045, 0.025])))
    up = np.array([0.0, 1.0, 0.0])
    for group, (x, z) in enumerate(((0.2, -0.12), (0.2, 0.12), (-0.2, -0.12), (-0.2, 0.12))):
        parts.append(Part(capsule([x, -0.02, z], [x, -0.26, z], 0.075), group=group, fiber=up, stiffness=1.2))
    names = ("front left leg", "front right leg", "hind left leg", "hind right leg")
    return normalized(PartsBody("panda", parts, names, blend=0.04))


_LIBRARY: dict[str, Callable[[], Body]] = {
    "seal": seal_body,
    "caterpillar": caterpillar_body,
    "fish": fish_body,
    "panda": panda_body,
    **{name: functools.partial(fish_body, name, shape) for name, shape in FISH_FAMILY.items()},
}
LIBRARY_BODIES = tuple(_LIBRARY)
"""Names of the built-in bodies: the four animals, then the fish family."""


@functools.lru_cache(maxsize=None)
def library_body(name: str) -> Body:
    """A built-in body by name (see LIBRARY_BODIES); built once per process."""
    if name not in _LIBRARY:
        raise BodyError(f"unknown body {name!r}; the library has {', '.join(LIBRARY_BODIES)}")
    return _LIBRARY[name]()


# --- bodies from samples, voxels and meshes -----------------------------------------------------


class SampledBody(Body):
    """A solid given by points filling it (a point cloud or the annotator's samples).

    Each point stands for a cube of the sample spacing h. Samples on a lattice (the annotator's,
    whose files store h) make the body the union of those cubes: the solid they were sampled
    from, to half a sample. Other clouds make it the union of balls of radius 0.9 h around the
    points, just more than the h sqrt(3)/2 that covers the cubes of an irregular cloud (and 0.4 h
    fatter on every face: balls around lattice samples made annotated bodies 30% too large).
    Labels are the nearest sample's.
    """

    def __init__(self, name: str, points: np.ndarray, labels: Labels | None = None,
                 group_names: Sequence[str] = (), spacing: float | None = None, on_lattice: bool = False) -> None:
        from scipy.spatial import cKDTree

        self.name, self.points = name, points
        self.tree = cKDTree(points)
        if spacing is None:
            spacing = float(np.median(self.tree.query(points, k=2)[0][:, 1])) if len(points) > 1 else 1.0
        self.spacing = spacing
        self.radius = 0.9 * spacing
        self.on_lattice = on_lattice
        self.point_labels = labels or passive_labels(len(points))
        self.group_names = tuple(group_names)

    def sdf(self, points: np.ndarray) -> np.ndarray:
        return self.tree.query(np.asarray(points, dtype=float).reshape(-1, 3))[0] - self.radius

    def contains(self, points: np.ndarray) -> np.ndarray:
        if not self.on_lattice:
            return super().contains(points)
        chebyshev = self.tree.query(np.asarray(points, dtype=float).reshape(-1, 3), p=np.inf)[0]
        return chebyshev <= 0.5 * self.spacing * (1 + 1e-9)  # inside a sample's cube

    def labels(self, points: np.ndarray) -> Labels:
        nearest = self.tree.query(np.asarray(points, dtype=float).reshape(-1, 3))[1]
        own = self.point_labels
        return Labels(own.groups[nearest], own.fibers[nearest], own.stiffness[nearest])

    def _bounds(self) -> np.ndarray:
        return np.stack([self.points.min(0) - self.spacing / 2, self.points.max(0) + self.spacing / 2])


class VoxelBody(Body):
    """A solid given by a boolean voxel grid (voxel edge 1, grid centred on the origin)."""

    def __init__(self, name: str, occupancy: np.ndarray) -> None:
        from scipy.ndimage import distance_transform_edt

        self.name = name
        padded = np.pad(occupancy, 1)
        # signed distance at voxel centres, zero half-way between a full and an empty voxel
        self.grid = np.where(padded, 0.5 - distance_transform_edt(padded), distance_transform_edt(~padded) - 0.5)
        self.shape = np.asarray(occupancy.shape, dtype=float)

    def sdf(self, points: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        p = np.asarray(points, dtype=float).reshape(-1, 3)
        index = p + self.shape / 2 + 0.5  # voxel (i, j, k) of the padded grid has its centre at index i
        inner = np.clip(index, 0, np.asarray(self.grid.shape) - 1)
        return map_coordinates(self.grid, inner.T, order=1) + np.linalg.norm(index - inner, axis=1)

    def labels(self, points: np.ndarray) -> Labels:
        return passive_labels(len(np.asarray(points).reshape(-1, 3)))

    def _bounds(self) -> np.ndarray:
        return np.stack([-self.shape / 2, self.shape / 2])


class MeshBody(Body):
    """A watertight triangle mesh; inside by trimesh's ray test, distance by closest points."""

    def __init__(self, name: str, mesh) -> None:
        self.name, self.mesh = name, mesh

    def sdf(self, points: np.ndarray) -> np.ndarray:
        import trimesh

        return -trimesh.proximity.signed_distance(self.mesh, np.asarray(points, dtype=float).reshape(-1, 3))

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.mesh.contains(np.asarray(points, dtype=float).reshape(-1, 3))

    def labels(self, points: np.ndarray) -> Labels:
        return passive_labels(len(np.asarray(points).reshape(-1, 3)))

    def _bounds(self) -> np.ndarray:
        return np.asarray(self.mesh.bounds, dtype=float)


def _check_extent(path: Path, points: np.ndarray) -> None:
    extent = points.max(0) - points.min(0)
    flat = [axis for axis, e in zip("xyz", extent) if not e > 1e-9 * max(extent.max(), 1e-300)]
    if flat:
        raise BodyError(f"body file {path}: the solid has no extent along {', '.join(flat)} (it is flat)")


def _load_mesh(path: Path, mesh) -> Body:
    import trimesh

    if len(mesh.faces) == 0:
        raise BodyError(f"body file {path}: the mesh holds no triangles (an empty body)")
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise BodyError(f"body file {path}: the mesh is not watertight ({open_edges} open edges), so its inside "
                        "is undefined; close its holes (e.g. trimesh.repair.fill_holes) or voxelise it to .npy")
    if mesh.volume < 0:
        mesh.invert()
    if not mesh.volume > 0:
        raise BodyError(f"body file {path}: the mesh encloses no volume")
    _check_extent(path, mesh.vertices)
    return MeshBody(path.stem, mesh)


def _points_body(path: Path, points: np.ndarray, data: dict | None = None) -> Body:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise BodyError(f"body file {path}: points must be an (N, 3) array, got shape {points.shape}")
    if len(points) == 0:
        raise BodyError(f"body file {path}: the point cloud holds no point (an empty body)")
    if not np.isfinite(points).all():
        raise BodyError(f"body file {path}: the point cloud holds non-finite coordinates")
    _check_extent(path, points)
    data = data or {}
    n = len(points)
    labels = passive_labels(n)
    names: tuple[str, ...] = ()
    if "groups" in data:
        groups = np.asarray(data["groups"])
        if groups.shape != (n,) or not np.issubdtype(groups.dtype, np.integer) or groups.min() < -1:
            raise BodyError(f"body file {path}: 'groups' must hold one integer >= -1 per point ({n}), "
                            f"got shape {groups.shape} of {groups.dtype}")
        used = np.unique(groups[groups >= 0])
        if len(used) and not np.array_equal(used, np.arange(used.max() + 1)):
            raise BodyError(f"body file {path}: muscle groups must be numbered 0..K-1 without gaps, "
                            f"got {used.tolist()}")
        k = int(groups.max()) + 1
        names = tuple(str(s) for s in data["group_names"]) if "group_names" in data else \
            tuple(f"group {g}" for g in range(k))
        if len(names) != k:
            raise BodyError(f"body file {path}: {len(names)} group_names for {k} muscle groups")
        labels = Labels(groups.astype(int), labels.fibers, labels.stiffness)
    if "fibers" in data:
        fibers = np.asarray(data["fibers"], dtype=float)
        length = np.linalg.norm(fibers, axis=1) if fibers.ndim == 2 else np.zeros(0)
        if fibers.shape != (n, 3) or not (length > 1e-12).all():
            raise BodyError(f"body file {path}: 'fibers' must be (N, 3) non-zero directions, one per point")
        labels = Labels(labels.groups, fibers / length[:, None], labels.stiffness)
    if "stiffness" in data:
        stiffness = np.asarray(data["stiffness"], dtype=float)
        if stiffness.shape != (n,) or not (stiffness > 0).all():
            raise BodyError(f"body file {path}: 'stiffness' must hold one relative stiffness > 0 per point")
        labels = Labels(labels.groups, labels.fibers, stiffness)
    spacing = float(data["spacing"]) if "spacing" in data else None
    return SampledBody(path.stem, points, labels, names, spacing, on_lattice=spacing is not None)


def _load_voxels(path: Path) -> Body:
    occupancy = np.load(path, allow_pickle=False)
    if occupancy.ndim != 3:
        raise BodyError(f"body file {path}: a voxel body needs a 3-D array, got shape {occupancy.shape}")
    occupancy = occupancy.astype(bool)
    if not occupancy.any():
        raise BodyError(f"body file {path}: no voxel is set (an empty body)")
    return VoxelBody(path.stem, occupancy)


@functools.lru_cache(maxsize=32)
def _load(path: Path, _stamp: tuple[int, int]) -> Body:
    suffix = path.suffix.lower()
    if suffix in VOXEL_SUFFIXES:
        return normalized(_load_voxels(path))
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            contents = {key: data[key] for key in data.files}
        if "points" not in contents:
            raise BodyError(f"body file {path}: an .npz body needs a 'points' array (N, 3); "
                            f"found {', '.join(contents) or 'nothing'}")
        return normalized(_points_body(path, contents.pop("points"), contents))
    if suffix == ".xyz":
        return normalized(_points_body(path, np.loadtxt(path, ndmin=2)[:, :3]))
    import trimesh

    try:
        loaded = trimesh.load(path, force="mesh" if suffix != ".ply" else None)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise BodyError(f"body file {path}: trimesh cannot read it ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_mesh() if loaded.geometry else trimesh.Trimesh()
    if isinstance(loaded, trimesh.PointCloud):
        return normalized(_points_body(path, loaded.vertices))
    if suffix == ".ply" and len(loaded.faces) == 0:
        return normalized(_points_body(path, loaded.vertices))
    return normalized(_load_mesh(path, loaded))


def load_body(path: str | Path) -> Body:
    """A body from a file, in the canonical frame (centred, longest extent 1).

    The file's axes are kept (heading +x, up +y); annotated ``.npz`` files carry ``points``
    (N, 3) and optionally ``groups`` (N,) (-1 passive), ``fibers`` (N, 3), ``stiffness`` (N,),
    ``group_names`` and ``spacing``. Loaded bodies are cached until the file changes.
    """
    path = Path(path)
    if not path.is_file():
        raise BodyError(f"body file {path}: no such file")
    if path.suffix.lower() not in BODY_FILE_SUFFIXES:
        raise BodyError(f"body file {path}: unsupported type {path.suffix!r}; use one of "
                        f"{', '.join(BODY_FILE_SUFFIXES)}")
    stat = path.stat()
    return _load(path.resolve(), (stat.st_mtime_ns, stat.st_size))


def get_body(name_or_path: str | Path) -> Body:
    """A library body by name, otherwise a body file."""
    if isinstance(name_or_path, str) and name_or_path in _LIBRARY:
        return library_body(name_or_path)
    return load_body(name_or_path)
