"""Scenes as data: domain, terrain, bodies and time stepping.

Everything here is a plain dataclass, so a scene round-trips through YAML (omegaconf) and
can be validated before Taichi is even imported. `validate_scene` turns bad input into a
`SceneError` that names the key, the bad value and what is allowed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional

from codesign.bodies import LIBRARY_BODIES
from codesign_mpm import materials
from codesign_mpm.materials import MATERIALS, MUSCLE_MODELS, material_names

SHAPE_KINDS = ("box", "sphere", "ellipsoid", "capsule", "mesh", "points", "voxels", "body", "layer")
MUSCLE_LAYOUTS = ("grid", "body")
TERRAIN_KINDS = ("none", "flat", "incline", "perlin")
DTYPES = ("float32", "float64")
ARCHS = ("cpu", "cuda", "gpu", "vulkan", "metal")
GRID_REGIONS = ("bbox", "full")
TERRAIN_CONTACTS = ("nodes", "surface", "spring")


class SceneError(ValueError):
    """A scene that cannot be simulated as written; the message names key, value and remedy."""


@dataclass
class ShapeSpec:
    """Where material is. Which fields matter depends on `kind`."""

    kind: str = "box"
    size: List[float] = field(default_factory=lambda: [0.1, 0.1, 0.1])  # box, ellipsoid diameters; body: box to fit in
    radius: float = 0.05  # sphere, capsule
    length: float = 0.1  # capsule: length of the axis segment (along x)
    file: Optional[str] = None  # mesh (anything trimesh loads), points (.npy/.ply/.xyz), voxels (.npy bool)
    scale: float = 1.0  # mesh / points: the file's longest extent becomes `scale` scene units
    voxel_size: float = 0.01  # voxels: edge of one voxel in scene units
    thickness: float = 0.05  # layer: depth of material laid on the terrain (the body's centre is unused)
    body: Optional[str] = None  # body: a library body (codesign.bodies.LIBRARY_BODIES), or null and a body `file`


@dataclass
class MaterialSpec:
    """A constitutive model by name with its parameters (scene units).

    E and nu set the elastic response of every model except water (which uses
    `bulk_modulus`); the other fields matter only to the models named in their comment. A
    plugin's model (docs/plugins.md) takes its own parameters from `parameters`. Each model's
    module in `codesign_mpm.materials` defines its parameters' defaults and valid ranges.
    """

    kind: str = "neo_hookean"
    youngs_modulus: float = 1.0e4
    poisson_ratio: float = 0.2
    density: float = 1.0e3
    friction_angle: float = 30.0  # sand: Drucker-Prager friction angle, degrees
    cohesion: float = 0.0  # sand: tensile strength (mean Kirchhoff stress at the cone apex)
    yield_stress: float = 200.0  # clay, mud: von Mises yield stress (mud: undrained shear strength)
    critical_compression: float = 2.5e-2  # snow: theta_c, principal stretches stay >= 1 - theta_c
    critical_stretch: float = 7.5e-3  # snow: theta_s, principal stretches stay <= 1 + theta_s
    hardening: float = 10.0  # snow: xi, stiffness grows as exp(xi (1 - J_p)) with compaction
    max_hardening: float = 10.0  # snow: bound on that factor (keeps the step and gradients bounded)
    bulk_modulus: float = 1.0e5  # water: K, pressure K (1 - J); sound speed sqrt(K / rho)
    viscosity: float = 0.0  # water, mud: dynamic viscosity
    parameters: Dict[str, float] = field(default_factory=dict)  # a plugin model's own parameters, by name


@dataclass
class MuscleSpec:
    """Muscle groups laid out as a grid over the body's bounding box, all fibres along `fiber`,
    or (`layout: body`, for `body` shapes) the body's own labelled groups and fibres.

    `groups: [2, 2, 1]` gives four actuators (front/back x bottom/top). Particle p's actuation
    is a = u . r_p and its muscle stiffness s = stiffness_ratio * E_p; how they make a stress
    is the scene's `muscle_model` (see `codesign_mpm.materials.MUSCLE_MODELS`).
    """

    groups: List[int] = field(default_factory=lambda: [2, 2, 1])
    fiber: List[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])
    stiffness_ratio: float = 0.3  # at most materials.max_stiffness_ratio(max_action, nu): 0.417 at 0.3 and nu 0.2
    layout: str = "grid"  # grid: `groups` and `fiber` as above; body: the body's muscle groups and fibres
    # layout body: the body's passive material (no muscle group) relative to the body's material. The
    # SoftZoo release's animals: a fifth of the density, 10 times the stiffness (light, stiff bones)
    passive_density: float = 1.0
    passive_stiffness: float = 1.0


@dataclass
class BodySpec:
    name: str = "body"
    shape: ShapeSpec = field(default_factory=ShapeSpec)
    material: MaterialSpec = field(default_factory=MaterialSpec)
    center: List[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    rotation: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # degrees about x, then y, then z
    rest_on_terrain: bool = False  # move the body down/up so its lowest face touches the terrain
    rest_offset: float = 0.0  # with rest_on_terrain: extra height (e.g. the thickness of a layer to rest on)
    velocity: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    particles_per_cell: int = 8  # a cube number: 1, 8, 27 or 64 particles on a regular lattice
    muscles: Optional[MuscleSpec] = None
    robot: bool = False  # the body whose centre of mass the tasks track


@dataclass
class TerrainSpec:
    """A height map y = h(x, z) acting as a frictional boundary on the grid."""

    kind: str = "flat"
    height: float = 0.05  # base height
    friction: float = 0.5  # Coulomb coefficient mu (ground 0.5, ice 0.05)
    slope_deg: float = 0.0  # incline: the surface rises along +x at this angle
    amplitude: float = 0.02  # perlin: peak-to-peak height range
    roughness: float = 0.5  # perlin: amplitude ratio between octaves (0..1)
    frequency: float = 4.0  # perlin: features per unit length of the first octave
    octaves: int = 3
    seed: int = 0
    # nodes: the nodes below the surface are held (fast; where the surface falls within a cell moves a
    # gait's distance by up to a third); surface: contact at the exact surface (docs/log/contact.md section 15);
    # spring: at the exact surface, a spring-damper of physical stiffness whose friction remembers
    # (engine/contact.py)
    contact: str = "nodes"
    contact_stiffness: float = 2.0e6  # spring: normal stiffness per unit contact area, Pa/m (= N/m^3)
    contact_damping: float = 1.0  # spring: damping ratio of a particle's contact (1: critical)


@dataclass
class Scene:
    """A complete simulation setup in scene units (the paper: unit cube, gravity 3.8)."""

    size: List[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    dx: float = 1.0 / 64
    gravity: List[float] = field(default_factory=lambda: [0.0, -3.8, 0.0])
    terrain: TerrainSpec = field(default_factory=TerrainSpec)
    bodies: List[BodySpec] = field(default_factory=list)
    frame_dt: float = 8e-3  # one control step; actions are held over its substeps
    cfl: float = 0.4  # dt <= cfl * dx / (wave speed + speed)
    # FLIP's share in the elastic bodies' velocity update; 0, APIC alone, conserves angular momentum
    # exactly. The locomotion environment's default is config.FLIP_DEFAULT (docs/log/contact.md sections 10-11)
    flip: float = 0.0
    # the PIC share as a time: each substep keeps exp(-dt / pic_time) of FLIP (None: `flip` per substep)
    pic_time: Optional[float] = None
    dt: Optional[float] = None  # force a (smaller) substep
    allow_unstable_dt: bool = False  # accept a dt above the CFL bound (you were warned)
    adaptive_dt: bool = True  # each frame takes as many substeps as its state needs (speeds, stretch); never fewer than at rest
    dtype: str = "float32"
    arch: str = "cpu"
    grid_region: str = "bbox"  # bbox: clear and update only the nodes particles touch; full: the whole grid
    boundary_cells: int = 3  # walls: nodes this close to the domain edge block outward motion
    muscle_model: str = "active"  # active: tau += s a (Ff)(Ff)^T; energy: s (|Ff|^2 - 1 + a)^2 (materials.MUSCLE_MODELS)
    max_action: float = 0.3  # largest |action| (the paper's bound): sizes the time step, bounds compression; larger actions are refused

    @property
    def wall(self) -> float:
        """Where material may start: the last wall node, (boundary_cells - 1) dx from each edge.

        Nodes closer to an edge than boundary_cells cannot move outwards, so material comes to
        rest against this plane; a body placed with its face on it is flush with the wall.
        """
        return self.dx * (self.boundary_cells - 1)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        return tuple(int(round(s / self.dx)) + 1 for s in self.size)  # type: ignore[return-value]


def _fail(key: str, value, allowed: str) -> None:
    raise SceneError(f"{key} = {value!r} is invalid: {allowed}")


def _check_vec(key: str, value, n: int = 3) -> None:
    if len(value) != n or not all(math.isfinite(float(v)) for v in value):
        _fail(key, list(value), f"expected {n} finite numbers")


def validate_scene(scene: Scene) -> None:
    """Check everything that does not need particles; raise SceneError on the first problem."""
    _check_vec("size", scene.size)
    if min(scene.size) <= 0:
        _fail("size", list(scene.size), "every extent must be > 0")
    if not scene.dx > 0:
        _fail("dx", scene.dx, "must be > 0")
    if min(scene.grid_shape) < 2 * scene.boundary_cells + 4:
        _fail("dx", scene.dx, f"too coarse for size {list(scene.size)}: need at least "
              f"{2 * scene.boundary_cells + 4} cells along every axis")
    _check_vec("gravity", scene.gravity)
    if not (scene.max_action > 0 and math.isfinite(scene.max_action)):
        _fail("max_action", scene.max_action, "must be a finite number > 0")
    if not scene.frame_dt > 0:
        _fail("frame_dt", scene.frame_dt, "must be > 0")
    if not 0 < scene.cfl <= 1:
        _fail("cfl", scene.cfl, "must be in (0, 1]; 0.3 to 0.5 is typical")
    if not 0 <= scene.flip < 1:
        _fail("flip", scene.flip, "must be in [0, 1): 0 is APIC alone, 0.99 converges in time")
    if scene.pic_time is not None and not scene.pic_time > 0:
        _fail("pic_time", scene.pic_time, "must be > 0 seconds (or null for flip's share per substep)")
    if scene.dt is not None and not scene.dt > 0:
        _fail("dt", scene.dt, "must be > 0 (or null to derive it from the CFL condition)")
    for key, value, allowed in (("dtype", scene.dtype, DTYPES), ("arch", scene.arch, ARCHS),
                                ("grid_region", scene.grid_region, GRID_REGIONS),
                                ("terrain.kind", scene.terrain.kind, TERRAIN_KINDS),
                                ("terrain.contact", scene.terrain.contact, TERRAIN_CONTACTS),
                                ("muscle_model", scene.muscle_model, MUSCLE_MODELS)):
        if value not in allowed:
            _fail(key, value, f"one of {', '.join(allowed)}")
    t = scene.terrain
    if t.friction < 0:
        _fail("terrain.friction", t.friction, "must be >= 0")
    if not t.contact_stiffness > 0:
        _fail("terrain.contact_stiffness", t.contact_stiffness, "must be > 0 (Pa/m: pressure per metre of depth)")
    if not t.contact_damping >= 0:
        _fail("terrain.contact_damping", t.contact_damping, "must be >= 0 (a damping ratio; 1 is critical)")
    if t.kind != "none" and not 0 <= t.height < scene.size[1]:
        _fail("terrain.height", t.height, f"must be in [0, {scene.size[1]})")
    if not -60 <= t.slope_deg <= 60:
        _fail("terrain.slope_deg", t.slope_deg, "must be in [-60, 60] degrees")
    if not scene.bodies:
        _fail("bodies", [], "a scene needs at least one body")
    if any(body.material.kind not in MATERIALS for body in scene.bodies):
        materials.load_plugin_materials()  # a plugin's model: the registry is asked only for those
    robots = [b.name for b in scene.bodies if b.robot]
    if len(robots) > 1:
        _fail("bodies", robots, "at most one body may be the robot")
    for i, body in enumerate(scene.bodies):
        _validate_body(f"bodies[{i}]", body)


def _validate_body(key: str, body: BodySpec) -> None:
    shape, mat = body.shape, body.material
    if shape.kind not in SHAPE_KINDS:
        _fail(f"{key}.shape.kind", shape.kind, f"one of {', '.join(SHAPE_KINDS)}")
    if shape.kind in ("box", "ellipsoid"):
        _check_vec(f"{key}.shape.size", shape.size)
        if min(shape.size) <= 0:
            _fail(f"{key}.shape.size", list(shape.size), "every extent must be > 0")
    if shape.kind in ("sphere", "capsule") and not shape.radius > 0:
        _fail(f"{key}.shape.radius", shape.radius, "must be > 0")
    if shape.kind == "capsule" and not shape.length >= 0:
        _fail(f"{key}.shape.length", shape.length, "must be >= 0")
    if shape.kind == "layer" and not shape.thickness > 0:
        _fail(f"{key}.shape.thickness", shape.thickness, "must be > 0")
    if shape.kind == "layer" and body.muscles is not None:
        _fail(f"{key}.muscles", body.muscles, "a layer cannot have muscles (null)")
    if shape.kind in ("mesh", "points", "voxels") and not shape.file:
        _fail(f"{key}.shape.file", shape.file, f"a {shape.kind} shape needs a file path")
    if shape.kind == "body":
        _check_vec(f"{key}.shape.size", shape.size)
        if min(shape.size) <= 0:
            _fail(f"{key}.shape.size", list(shape.size), "every extent of the box the body fits in must be > 0")
        if shape.body is None and not shape.file:
            _fail(f"{key}.shape.body", shape.body, "a body shape needs a library body or a body file (shape.file)")
        if shape.body is not None and shape.file:
            _fail(f"{key}.shape.body", shape.body, f"give a library body or a body file ({shape.file!r}), not both")
        if shape.body is not None and shape.body not in LIBRARY_BODIES:
            _fail(f"{key}.shape.body", shape.body, f"one of {', '.join(LIBRARY_BODIES)}")
    if not shape.scale > 0 or not shape.voxel_size > 0:
        _fail(f"{key}.shape.scale", shape.scale, "scale and voxel_size must be > 0")
    if mat.kind not in MATERIALS:
        _fail(f"{key}.material.kind", mat.kind, f"one of {', '.join(material_names())}")
    if not mat.youngs_modulus > 0:
        _fail(f"{key}.material.youngs_modulus", mat.youngs_modulus, "must be > 0")
    if not -1 < mat.poisson_ratio < 0.5:
        _fail(f"{key}.material.poisson_ratio", mat.poisson_ratio, "must be in (-1, 0.5)")
    if not mat.density > 0:
        _fail(f"{key}.material.density", mat.density, "must be > 0")
    _validate_plasticity(f"{key}.material", mat)
    _check_vec(f"{key}.center", body.center)
    _check_vec(f"{key}.velocity", body.velocity)
    _check_vec(f"{key}.rotation", body.rotation)
    root = round(body.particles_per_cell ** (1 / 3))
    if body.particles_per_cell < 1 or root ** 3 != body.particles_per_cell:
        _fail(f"{key}.particles_per_cell", body.particles_per_cell, "a cube number: 1, 8, 27 or 64")
    if body.muscles is not None:
        m = body.muscles
        if len(m.groups) != 3 or min(m.groups) < 1:
            _fail(f"{key}.muscles.groups", list(m.groups), "three positive integers")
        _check_vec(f"{key}.muscles.fiber", m.fiber)
        if math.hypot(*m.fiber) == 0:
            _fail(f"{key}.muscles.fiber", list(m.fiber), "a non-zero direction")
        if m.stiffness_ratio < 0:
            _fail(f"{key}.muscles.stiffness_ratio", m.stiffness_ratio, "must be >= 0")
        for name in ("passive_density", "passive_stiffness"):
            if not getattr(m, name) > 0:
                _fail(f"{key}.muscles.{name}", getattr(m, name), "must be > 0")
        if m.layout not in MUSCLE_LAYOUTS:
            _fail(f"{key}.muscles.layout", m.layout, f"one of {', '.join(MUSCLE_LAYOUTS)}")
        if m.layout == "body" and shape.kind != "body":
            _fail(f"{key}.muscles.layout", m.layout, f"only a body shape has its own muscles, not a {shape.kind}; "
                  "use grid")


def _validate_plasticity(key: str, mat: MaterialSpec) -> None:
    """Ranges of the models' parameters (each model's module defines its own): the fields of
    MaterialSpec whatever the kind, so typos surface early; `parameters` against the kind's own."""
    for name, parameter in materials.parameters().items():
        if hasattr(mat, name):
            value = getattr(mat, name)
            if not (parameter.check(value) and math.isfinite(value)):
                _fail(f"{key}.{name}", value, parameter.allowed)
    own = {p.name: p for p in MATERIALS[mat.kind].parameters if not hasattr(mat, p.name)}
    for name, value in (mat.parameters or {}).items():
        if name not in own:
            _fail(f"{key}.parameters.{name}", value, f"{mat.kind} takes {', '.join(sorted(own)) or 'no parameters here'}")
        if not (isinstance(value, (int, float)) and math.isfinite(value) and own[name].check(value)):
            _fail(f"{key}.parameters.{name}", value, own[name].allowed)
