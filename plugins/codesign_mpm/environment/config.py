"""Recipe schemas and environment presets, kept light so validating a recipe never imports Taichi.

An environment name (``ground``, ``desert``, ``ocean``, ...) is a preset: the same locomotion
setup with preset-specific terrain friction, ground cover (a layer of sand, snow, clay, mud
or water laid on the terrain around the robot) and robot stiffness. Each preset registers
its own config class (`PRESET_CONFIGS`) whose defaults are the preset's values, so
``codesign show`` prints every material parameter an environment uses.
"""

import copy
from dataclasses import dataclass, field, make_dataclass
from typing import Any, Optional

import numpy as np

from codesign.bodies import BODY_FILE_SUFFIXES, LIBRARY_BODIES
from codesign.errors import RecipeError
from codesign_mpm.materials.admissible import MAX_ACTIVE_STRESS_RATIO, active_stress_ratio, max_stiffness_ratio
from codesign_mpm.scene.quality import QUALITY_NAMES, quality

ROBOT_BODIES = ("box", "ellipsoid", *LIBRARY_BODIES, "file")
COVER_KINDS = ("none", "sand", "snow", "clay", "mud", "water")
# FLIP's share in a robot's velocity update: a gait's distance then holds within 5% from cfl 0.4 to
# 0.025 at dx 1/32, where APIC alone (0) loses it all (docs/log/contact.md sections 10-11)
FLIP_DEFAULT = 0.99


@dataclass
class CoverConfig:
    """Ground cover laid on the terrain, leaving out the cells the robot occupies.

    The material fields are those of `codesign_mpm.scene.spec.MaterialSpec`; each matters only
    to the kinds named in its help.
    """

    kind: str = field(default="none", metadata={"choices": list(COVER_KINDS)})
    thickness: float = field(default=0.05, metadata={"gt": 0, "help": "depth of the layer above the terrain"})
    youngs_modulus: float = field(default=1.0e5, metadata={"gt": 0, "help": "all but water"})
    poisson_ratio: float = field(default=0.2, metadata={"gt": -1, "lt": 0.5})
    density: float = field(default=1.0e3, metadata={"gt": 0})
    friction_angle: float = field(default=45.0, metadata={"ge": 0, "le": 80, "help": "sand: degrees"})
    cohesion: float = field(default=0.0, metadata={"ge": 0, "help": "sand: tensile strength"})
    yield_stress: float = field(default=200.0, metadata={"gt": 0, "help": "clay, mud: von Mises yield stress"})
    critical_compression: float = field(default=2.5e-2, metadata={"gt": 0, "lt": 1, "help": "snow: theta_c"})
    critical_stretch: float = field(default=7.5e-3, metadata={"gt": 0, "help": "snow: theta_s"})
    hardening: float = field(default=10.0, metadata={"ge": 0, "help": "snow: xi"})
    max_hardening: float = field(default=10.0, metadata={"ge": 1, "le": 100, "help": "snow: bound on exp(xi (1-Jp))"})
    bulk_modulus: float = field(default=1.0e5, metadata={"gt": 0, "help": "water: K (sound speed sqrt(K/rho))"})
    viscosity: float = field(default=0.0, metadata={"ge": 0, "help": "water, mud: dynamic viscosity"})
    particles_per_cell: Optional[int] = field(default=None, metadata={
        "choices": [1, 8, 27, 64], "help": "null = the environment's quality preset's"})
    settled: bool = field(default=True, metadata={
        "help": "start loaded by its own weight (geostatic F, codesign_mpm.environment.settle); false: stress-free, it "
                "settles during the first frames"})


@dataclass(frozen=True)
class EnvironmentPreset:
    """What distinguishes one named environment from another."""

    description: str
    friction: float
    """Coulomb coefficient of the terrain surface."""
    cover: CoverConfig = field(default_factory=CoverConfig)
    robot_youngs_modulus: float = 1.0e4


PRESETS: dict[str, EnvironmentPreset] = {
    "ground": EnvironmentPreset("Robot on firm ground (friction 0.5); flat or Perlin terrain.", friction=0.5),
    "ice": EnvironmentPreset("Robot on slippery ice (friction 0.05); flat or Perlin terrain.", friction=0.05),
    "desert": EnvironmentPreset(
        "A layer of sand (Drucker-Prager, friction angle 45 deg) on the terrain.", friction=0.5,
        cover=CoverConfig(kind="sand", thickness=0.02, friction_angle=45.0)),
    "snow": EnvironmentPreset(
        "A layer of light snow (Stomakhin 2013) that compacts and hardens under the robot.", friction=0.5,
        cover=CoverConfig(kind="snow", thickness=0.05, youngs_modulus=1.0e4, density=400.0)),
    "clay": EnvironmentPreset(
        "A layer of clay (von Mises, yield stress 200) that keeps the robot's footprints.", friction=0.5,
        cover=CoverConfig(kind="clay", thickness=0.05, yield_stress=200.0)),
    "wetland": EnvironmentPreset(
        "A layer of mud: saturated, nearly incompressible soil with a low yield stress and viscosity.",
        friction=0.5, cover=CoverConfig(kind="mud", thickness=0.05, youngs_modulus=2.0e4, poisson_ratio=0.45,
                                        density=1.3e3, yield_stress=30.0, viscosity=1.0)),
    "shallow_water": EnvironmentPreset(
        "Shallow water (weakly compressible, bulk modulus 1e5) over the terrain.", friction=0.5,
        cover=CoverConfig(kind="water", thickness=0.05, bulk_modulus=1.0e5)),
    "ocean": EnvironmentPreset(
        "Water deep enough to cover the robot over a frictionless floor; a stiffer robot (E 1e5).",
        friction=0.0, cover=CoverConfig(kind="water", thickness=0.15, bulk_modulus=1.0e5),
        robot_youngs_modulus=1.0e5),
}


@dataclass
class RobotConfig:
    body: str = field(default="box", metadata={
        "choices": list(ROBOT_BODIES),
        "help": "the base workspace a design shapes: a box or ellipsoid filling `size`, a library body (the "
                "animals seal, caterpillar, fish, panda; the fish_* primitives) or `file` (body_file), scaled "
                "uniformly to fit in `size`"})
    body_file: Optional[str] = field(default=None, metadata={
        "help": f"body: file: an annotated .npz (codesign annotate), a watertight mesh, a point cloud or voxels "
                f"({', '.join(BODY_FILE_SUFFIXES)}); heading +x, up +y; relative to the working directory"})
    size: list[float] = field(
        default_factory=lambda: [0.2, 0.08, 0.08],
        metadata={"gt": 0, "min_len": 3, "help": "extents (x, y, z) of the box workspace the design shapes "
                                                "(other bodies: the box they fit in)"},
    )
    position: list[float] = field(
        default_factory=lambda: [0.25, 0.25],
        metadata={"min_len": 2, "help": "(x, z) of the box centre; the box rests on the terrain"},
    )
    youngs_modulus: float = field(default=1.0e4, metadata={"gt": 0, "help": "default stiffness E"})
    poisson_ratio: float = field(default=0.2, metadata={"gt": -1, "lt": 0.5})
    density: float = field(default=1.0e3, metadata={"gt": 0})
    muscle_groups: list[int] = field(
        default_factory=lambda: [2, 2, 1],
        metadata={"ge": 1, "min_len": 3, "help": "grid of muscle blocks along x, y, z; K = their product (box, "
                                                "ellipsoid, unannotated files; other bodies bring their own muscles)"},
    )
    muscle_stiffness_ratio: float = field(default=0.3, metadata={
        "ge": 0, "help": "muscle stiffness s / E: the active stress is s a (F f)(F f)^T; admissible while s 0.3 <= "
                         "0.3 x the shear modulus: <= 0.417 at Poisson's ratio 0.2 (codesign_mpm.materials)"})
    passive_density: float = field(default=1.0, metadata={
        "gt": 0, "help": "a library body's or annotated file's passive material (no muscle group): density relative "
                         "to `density` (the SoftZoo release's animals: 0.2)"})
    passive_stiffness: float = field(default=1.0, metadata={
        "gt": 0, "help": "the same material's Young's modulus relative to the body's (the SoftZoo release's animals: "
                         "10); a stiffer, lighter material has a faster wave, so more substeps"})
    particles_per_cell: Optional[int] = field(default=None, metadata={
        "choices": [1, 8, 27, 64], "help": "null = the environment's quality preset's"})
    rest_on: str = field(default="terrain", metadata={
        "choices": ["terrain", "cover"], "help": "terrain: stand on the terrain inside the cover (the paper); "
                                                "cover: start on top of the cover layer"})
    settled: bool = field(default=False, metadata={
        "help": "start at rest under its own weight (found by dynamic relaxation, codesign_mpm.environment.settle.relax) "
                "instead of stress-free, so a no-action episode stays where it is; a fixed body only (a design "
                "that changes its shape or stiffness is an error)"})


@dataclass
class TerrainConfig:
    kind: str = field(default="flat", metadata={"choices": ["flat", "perlin"]})
    height: float = field(
        default=0.08, metadata={"ge": 0, "help": "base height; must be >= 3 dx (above the wall band)"}
    )
    amplitude: float = field(default=0.02, metadata={"ge": 0, "help": "perlin: peak-to-peak height range"})
    frequency: float = field(default=4.0, metadata={"gt": 0, "help": "perlin: features per unit length"})
    seed: int = field(default=0, metadata={"ge": 0, "help": "perlin: noise seed"})
    friction: Optional[float] = field(
        default=None, metadata={"ge": 0, "help": "Coulomb coefficient; null = the environment's own"}
    )
    contact: str = field(default="nodes", metadata={
        "choices": ["nodes", "surface", "spring"],
        "help": "nodes: hold the grid nodes below the surface; surface: contact at the exact surface, "
                "whatever its height within a cell (docs/log/contact.md section 15); spring: at the exact "
                "surface, a spring-damper of physical stiffness with friction that remembers (a tangential "
                "spring per particle, capped by Coulomb)"})
    contact_stiffness: float = field(default=2.0e6, metadata={
        "gt": 0, "help": "spring: normal stiffness per unit contact area, Pa/m; a body of weight W on area A "
                         "sinks W / (A stiffness); the tangential spring is as stiff"})
    contact_damping: float = field(default=1.0, metadata={
        "ge": 0, "help": "spring: damping ratio of each particle's contact, normal and tangential (1: critical)"})


TURNING_MEASURES = ("tangent", "angular_momentum")
"""How the turning task scores a step (codesign_mpm.environment.tasks.Turning)."""


def _vector(default: list[float], help: str) -> Any:
    return field(default_factory=lambda: list(default), metadata={"min_len": 3, "help": help})


@dataclass
class TaskConfig:
    """The task; each parameter matters to the tasks named in its help (codesign_mpm.environment.tasks)."""

    name: str = field(default="movement_speed", metadata={
        "help": "movement_speed | turning | velocity_tracking | waypoint_following, or a registered task"})
    direction: list[float] = _vector([1.0, 0.0, 0.0], "movement_speed: target heading (normalised)")
    up: list[float] = _vector([0.0, 1.0, 0.0], "turning: counter-clockwise about this axis")
    turning_measure: str = field(default="tangent", metadata={
        "choices": list(TURNING_MEASURES),
        "help": "turning: tangent, the particles' mean velocity along their tangents about the centre of mass "
                "(the paper's; a bending body earns it too), or angular_momentum, the body's angular velocity "
                "(angular momentum over moment of inertia) times their mean distance from the axis; the two "
                "agree on a rigid rotation"})
    offset: list[float] = _vector([0.3, 0.0, 0.0], "path tasks: end point minus the start centre of mass")
    start_velocity: list[float] = _vector([0.0, 0.0, 0.0], "path tasks: velocity at the start of the path")
    end_velocity: list[float] = _vector([0.0, 0.0, 0.0], "path tasks: velocity at the end")
    start_acceleration: list[float] = _vector([0.0, 0.0, 0.0], "path tasks: acceleration at the start")
    end_acceleration: list[float] = _vector([0.0, 0.0, 0.0], "path tasks: acceleration at the end")
    params: dict[str, Any] = field(default_factory=dict, metadata={"help": "parameters of a third-party task"})


@dataclass
class ObservationConfig:
    """Parts of the observation, in this order when switched on (codesign_mpm.environment.observations)."""

    com: bool = field(default=True, metadata={"help": "robot centre of mass (3)"})
    velocity: bool = field(default=True, metadata={"help": "robot centre-of-mass velocity (3)"})
    muscle_centroids: bool = field(default=False, metadata={
        "help": "position and velocity of each muscle's membership-weighted centroid (6 K)"})
    occupancy: bool = field(default=False, metadata={
        "help": "semantic occupancy around the robot from the MPM grid: terrain, cover, robot (3 x cells)"})
    occupancy_cells: list[int] = field(default_factory=lambda: [8, 4, 8], metadata={
        "ge": 1, "min_len": 3, "help": "occupancy map size in grid cells (x, y, z), centred on the robot"})
    task: bool = field(default=True, metadata={"help": "task information (3): direction, next waypoint, ..."})
    time: bool = field(default=False, metadata={"help": "control step / horizon (1)"})


@dataclass
class IntegrityConfig:
    """What an episode in which the robot tears apart (numerical fracture, codesign_mpm.scene.integrity)
    gets. Torn: more than `tolerance` of its mass outside its largest connected piece."""

    on_tear: str = field(default="penalize", metadata={
        "choices": ["penalize", "terminate", "off"],
        "help": "penalize: the return loses penalty x horizon x (torn fraction - tolerance); terminate: the "
                "episode's reward stops at the frame it tore; off: measured and logged only"})
    tolerance: float = field(default=0.01, metadata={
        "ge": 0, "lt": 1, "help": "torn mass fraction that still counts as whole"})
    penalty: float = field(default=100.0, metadata={
        "ge": 0, "help": "penalize: return lost per control step and unit of torn mass fraction (100: a 1% tear "
                        "costs as much as moving 1 unit/s slower, faster than any gait here)"})


@dataclass
class LocomotionConfig:
    """A locomotion environment. `quality` sets dx, cfl, dtype, checkpoint_every and the robot's
    and cover's particles_per_cell (codesign_mpm.scene.quality); each of them written explicitly wins."""

    quality: str = field(default="default", metadata={
        "choices": list(QUALITY_NAMES), "help": "numerical settings preset (docs/accuracy.md); explicit "
                                                "dx, cfl, dtype, checkpoint_every, particles_per_cell override it"})
    dx: Optional[float] = field(default=None, metadata={
        "gt": 0, "le": 0.1, "help": "grid spacing; null = the quality preset's"})
    cfl: Optional[float] = field(default=None, metadata={
        "gt": 0, "le": 1, "help": "dt <= cfl dx / wave speed; null = the quality preset's"})
    flip: float = field(default=FLIP_DEFAULT, metadata={
        "ge": 0, "lt": 1, "help": "FLIP's share in the robot's velocity update: a particle keeps its own velocity plus "
                                  "the grid's change, so a gait converges as the step shrinks; 0 is APIC alone, which "
                                  "damps once per substep (docs/log/contact.md sections 10-11)"})
    pic_time: Optional[float] = field(default=None, metadata={
        "gt": 0, "help": "the PIC share as a time constant, s: each substep keeps FLIP's share exp(-dt / pic_time), "
                         "so the damping per second does not grow with the number of substeps (0.265 is flip 0.99 at "
                         "the quick start's 2.7 ms step); null: flip per substep"})
    adaptive_dt: bool = field(default=True, metadata={
        "help": "each frame takes as many substeps as its state needs (speeds, stretch-stiffened materials), never "
                "fewer than at rest; false: the step at rest throughout"})
    checkpoint_every: Optional[int] = field(default=None, metadata={
        "ge": 1, "help": "substeps between stored states of a differentiable episode; null = the quality "
                         "preset's (when it has none: the whole episode where its states fit in 256 MB, "
                         "else as many as fit, at least the memory-optimal sqrt(T/2))"})
    size: list[float] = field(
        default_factory=lambda: [1.0, 0.5, 0.5], metadata={"gt": 0, "min_len": 3, "help": "domain extents"}
    )
    horizon: int = field(default=100, metadata={"ge": 1, "help": "control steps per episode"})
    frame_dt: float = field(default=8e-3, metadata={"gt": 0, "help": "simulated seconds per control step"})
    dtype: Optional[str] = field(default=None, metadata={
        "choices": ["float32", "float64"], "help": "null = the quality preset's"})
    arch: str = field(default="cpu", metadata={"choices": ["cpu", "cuda", "gpu"]})
    robot: RobotConfig = field(default_factory=RobotConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    cover: Optional[CoverConfig] = field(
        default=None, metadata={"help": "ground cover layer; null = the environment's own"})
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)

    def __post_init__(self) -> None:
        """Fill the settings left null from the quality preset (an unknown name: RecipeError)."""
        q = quality(self.quality)
        for key in ("dx", "cfl", "dtype", "checkpoint_every"):
            if getattr(self, key) is None:
                setattr(self, key, getattr(q, key))
        if self.robot.particles_per_cell is None:
            self.robot.particles_per_cell = q.particles_per_cell
        if self.cover is not None and self.cover.particles_per_cell is None:
            self.cover.particles_per_cell = q.cover_particles_per_cell
        check_config(self)

    def resolved_cover(self, preset: EnvironmentPreset) -> CoverConfig:
        """The cover to lay: this config's, else the preset's, with particles per cell resolved."""
        cover = copy.copy(preset.cover if self.cover is None else self.cover)
        if cover.particles_per_cell is None:
            cover.particles_per_cell = quality(self.quality).cover_particles_per_cell
        return cover


def preset_config(name: str, preset: EnvironmentPreset) -> type:
    """LocomotionConfig with the preset's friction, cover and robot stiffness as defaults (the
    config class of the environment `name`; `codesign_mpm.plugin.register_environment` uses it)."""
    return make_dataclass(
        f"{name.title().replace('_', '')}Config",
        [("terrain", TerrainConfig, field(default_factory=lambda: TerrainConfig(friction=preset.friction))),
         ("robot", RobotConfig, field(default_factory=lambda: RobotConfig(youngs_modulus=preset.robot_youngs_modulus))),
         ("cover", Optional[CoverConfig], field(default_factory=lambda: copy.copy(preset.cover)))],
        bases=(LocomotionConfig,),
        namespace={"__module__": __name__, "__doc__": f"Locomotion in the '{name}' environment: {preset.description}"})


PRESET_CONFIGS: dict[str, type] = {name: preset_config(name, preset) for name, preset in PRESETS.items()}


def environment_error(key: str, message: str) -> RecipeError:
    return RecipeError(f"invalid recipe: environment.{key}: {message}")


def check_config(config: LocomotionConfig) -> None:
    """Cross-field checks the field metadata cannot express (lengths, the wall band at the preset's
    dx, the muscles' strength, zero vectors): run when a recipe is read, so nothing is built first."""
    for key, value, n in (("size", config.size, 3), ("robot.size", config.robot.size, 3),
                          ("robot.position", config.robot.position, 2),
                          ("robot.muscle_groups", config.robot.muscle_groups, 3),
                          ("task.direction", config.task.direction, 3), ("task.up", config.task.up, 3),
                          ("task.offset", config.task.offset, 3)):
        if len(value) != n:
            raise environment_error(key, f"expected {n} numbers, got {list(value)}")
    from codesign_mpm.scene.spec import Scene  # the scene's wall band and action bound; it imports the materials

    wall = Scene().boundary_cells * config.dx
    if config.terrain.height < wall:
        raise environment_error("terrain.height", f"{config.terrain.height!r} is below the wall band; "
                                f"must be >= 3 dx = {wall:.4g}")
    robot, max_action = config.robot, Scene().max_action
    if active_stress_ratio(robot.muscle_stiffness_ratio, max_action, robot.poisson_ratio) > MAX_ACTIVE_STRESS_RATIO:
        raise environment_error("robot.muscle_stiffness_ratio", (
            f"{robot.muscle_stiffness_ratio!r} is too strong for the body: at the action bound {max_action} its "
            f"stress would exceed {MAX_ACTIVE_STRESS_RATIO} x the shear modulus (numerical fracture); must be <= "
            f"{max_stiffness_ratio(max_action, robot.poisson_ratio):.4g} at poisson_ratio {robot.poisson_ratio}"))
    for key in ("direction", "up"):
        if not np.linalg.norm(getattr(config.task, key)) > 0:
            raise environment_error(f"task.{key}", "must be a non-zero vector")
