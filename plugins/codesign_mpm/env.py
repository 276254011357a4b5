"""Locomotion environments (SoftZoo's land biomes): a box-shaped robot workspace on terrain.

The physics lives in `codesign_mpm.engine`; this module only turns a recipe config into a
`Scene`, a design into particles, and simulator state into observations and rewards.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from codesign.errors import RecipeError
from codesign.interfaces import DesignFields, DesignSpace, Environment, StepResult
from codesign_mpm.config import EnvironmentPreset, LocomotionConfig
from codesign_mpm.engine import Simulator
from codesign_mpm.sampling import Particles, build_particles
from codesign_mpm.scene import BodySpec, MaterialSpec, MuscleSpec, Scene, SceneError, ShapeSpec, TerrainSpec

OCCUPANCY_THRESHOLD = 0.5
"""Particles whose occupancy is below this are removed: near-massless particles destabilise MPM."""
UP = np.array([0.0, 1.0, 0.0])


def _problem(key: str, message: str) -> RecipeError:
    return RecipeError(f"invalid recipe: environment.{key}: {message}")


def _check_config(config: LocomotionConfig) -> None:
    """Cross-field checks the field metadata cannot express (lengths, wall band, zero vectors)."""
    for key, value, n in (("size", config.size, 3), ("robot.size", config.robot.size, 3),
                          ("robot.position", config.robot.position, 2),
                          ("robot.muscle_groups", config.robot.muscle_groups, 3),
                          ("task.direction", config.task.direction, 3)):
        if len(value) != n:
            raise _problem(key, f"expected {n} numbers, got {list(value)}")
    wall = Scene().boundary_cells * config.dx
    if config.terrain.height < wall:
        raise _problem("terrain.height", f"{config.terrain.height!r} is below the wall band; "
                       f"must be >= 3 dx = {wall:.4g}")
    if not np.linalg.norm(config.task.direction) > 0:
        raise _problem("task.direction", "must be a non-zero vector")


def make_scene(config: LocomotionConfig, preset: EnvironmentPreset) -> Scene:
    """The scene of a locomotion config: one actuated box robot resting on the terrain."""
    t, r = config.terrain, config.robot
    return Scene(
        size=list(config.size),
        dx=config.dx,
        terrain=TerrainSpec(kind=t.kind, height=t.height, amplitude=t.amplitude, frequency=t.frequency,
                            seed=t.seed, friction=preset.friction if t.friction is None else t.friction),
        bodies=[BodySpec(
            name="robot",
            shape=ShapeSpec(kind="box", size=list(r.size)),
            material=MaterialSpec(youngs_modulus=r.youngs_modulus, poisson_ratio=r.poisson_ratio,
                                  density=r.density),
            center=[r.position[0], t.height, r.position[1]],
            rest_on_terrain=True,
            particles_per_cell=r.particles_per_cell,
            muscles=MuscleSpec(groups=list(r.muscle_groups), fiber=[1.0, 0.0, 0.0]),
            robot=True,
        )],
        frame_dt=config.frame_dt,
        dtype=config.dtype,
        arch=config.arch,
    )


def _numpy(value: Any) -> np.ndarray:
    """Design fields may be torch tensors with grad; the simulator only needs their values."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


class LocomotionEnv(Environment):
    """Move fast along a direction, or turn counter-clockwise, on an environment preset.

    Observation (9): robot centre of mass (3), its velocity (3), the unit task direction (3).
    Reward per step (SoftZoo appendix), mass-weighted over robot particles:
    ``movement_speed`` = mean velocity . direction; ``turning`` = mean velocity along each
    particle's counter-clockwise tangent about the up axis through the centre of mass.

    `base_particles` is the whole workspace; each design keeps, weighs and stiffens a subset.
    """

    def __init__(self, config: LocomotionConfig, preset: EnvironmentPreset) -> None:
        _check_config(config)
        self.config = config
        self.scene = make_scene(config, preset)
        try:
            self.base_particles: Particles = build_particles(self.scene)
        except SceneError as exc:
            raise RecipeError(f"invalid recipe: environment: the robot does not fit the scene: {exc}") from exc
        k = self.base_particles.n_actuators
        self.design_space = DesignSpace(points=self.base_particles.x.copy(), n_actuators=k,
                                        default_stiffness=config.robot.youngs_modulus)
        self.action_dim = k
        self.observation_dim = 9
        self.horizon = config.horizon
        self.control_dt = config.frame_dt
        self.direction = np.asarray(config.task.direction, dtype=np.float64)
        self.direction /= np.linalg.norm(self.direction)
        self.particles: Particles = self.base_particles
        self.sim: Simulator | None = None
        self.t = 0

    def design_particles(self, design: DesignFields) -> Particles:
        """Base particles with a design applied; particles under the occupancy threshold are dropped."""
        base = self.base_particles
        occupancy = _numpy(design.occupancy).reshape(base.n)
        keep = occupancy >= OCCUPANCY_THRESHOLD
        if not keep.any():
            raise ValueError(f"the design leaves no particle with occupancy >= {OCCUPANCY_THRESHOLD}")
        subset = Particles(**{name: getattr(base, name)[keep] for name in Particles.__dataclass_fields__})
        return replace(
            subset,
            volume=subset.volume * occupancy[keep],
            youngs_modulus=_numpy(design.stiffness).reshape(base.n)[keep],
            muscle=_numpy(design.muscle).reshape(base.muscle.shape)[keep],
            fiber=_numpy(design.fiber).reshape(base.n, 3)[keep],
        )

    def reset(self, design: DesignFields | None = None, seed: int | None = None) -> np.ndarray:
        """Load ``design`` (or keep the last one); the task is deterministic, so ``seed`` is unused."""
        if design is not None:
            self.particles = self.design_particles(design)
        particles = self.particles
        # A new particle count needs a new simulator (cheap: compiled kernels of the same
        # layout are reused from the closed one); reset() re-derives the CFL step itself.
        if self.sim is None or self.sim.n != particles.n:
            self.close()
            self.sim = Simulator(self.scene, particles)
        else:
            self.sim.reset(particles)
        self.t = 0
        self._mass = particles.volume * particles.density
        return self._observe()[0]

    def step(self, action: np.ndarray) -> StepResult:
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        self.sim.step(_numpy(action))
        self.t += 1
        observation, x, v = self._observe()
        com = observation[:3]
        if self.config.task.name == "movement_speed":
            reward = float(observation[3:6] @ self.direction)
        else:
            tangent = np.cross(UP, x - com)
            length = np.linalg.norm(tangent, axis=1, keepdims=True)
            tangent = np.divide(tangent, length, out=np.zeros_like(tangent), where=length > 1e-12)
            reward = float(self._mass @ (v * tangent).sum(1) / self._mass.sum())
        return StepResult(observation, reward, self.t >= self.horizon, {"com": com.copy()})

    def _observe(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(observation, robot positions, robot velocities); the robot is the only body."""
        x, v, _, _ = self.sim.particles_state()
        x, v = x.astype(np.float64), v.astype(np.float64)
        weights = self._mass / self._mass.sum()
        return np.concatenate([weights @ x, weights @ v, self.direction]), x, v

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None
