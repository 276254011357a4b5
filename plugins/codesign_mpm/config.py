"""Recipe schemas and environment presets, kept light so validating a recipe never imports Taichi.

An environment name (``ground``, ``ice``) is a preset: the same locomotion setup with
preset-specific terrain physics. Later biomes (desert, snow, ...) add a row to `PRESETS`
once the engine has their materials.
"""

from dataclasses import dataclass, field
from typing import Optional


@dataclass(frozen=True)
class EnvironmentPreset:
    """What distinguishes one named environment from another."""

    description: str
    friction: float
    """Coulomb coefficient of the terrain surface."""


PRESETS: dict[str, EnvironmentPreset] = {
    "ground": EnvironmentPreset("Robot on firm ground (friction 0.5); flat or Perlin terrain.", friction=0.5),
    "ice": EnvironmentPreset("Robot on slippery ice (friction 0.05); flat or Perlin terrain.", friction=0.05),
}


@dataclass
class RobotConfig:
    size: list[float] = field(
        default_factory=lambda: [0.2, 0.08, 0.08],
        metadata={"gt": 0, "min_len": 3, "help": "extents (x, y, z) of the box workspace the design shapes"},
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
        metadata={"ge": 1, "min_len": 3, "help": "grid of muscle blocks along x, y, z; K = their product"},
    )
    particles_per_cell: int = field(default=8, metadata={"choices": [1, 8, 27, 64]})


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


@dataclass
class TaskConfig:
    name: str = field(default="movement_speed", metadata={"choices": ["movement_speed", "turning"]})
    direction: list[float] = field(
        default_factory=lambda: [1.0, 0.0, 0.0],
        metadata={"min_len": 3, "help": "movement_speed: target heading (normalised); also observed"},
    )


@dataclass
class LocomotionConfig:
    dx: float = field(default=1.0 / 48, metadata={"gt": 0, "le": 0.1, "help": "grid spacing"})
    size: list[float] = field(
        default_factory=lambda: [1.0, 0.5, 0.5], metadata={"gt": 0, "min_len": 3, "help": "domain extents"}
    )
    horizon: int = field(default=100, metadata={"ge": 1, "help": "control steps per episode"})
    frame_dt: float = field(default=8e-3, metadata={"gt": 0, "help": "simulated seconds per control step"})
    dtype: str = field(default="float32", metadata={"choices": ["float32", "float64"]})
    arch: str = field(default="cpu", metadata={"choices": ["cpu", "cuda", "gpu"]})
    robot: RobotConfig = field(default_factory=RobotConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
