"""Locomotion environments (SoftZoo's biomes): a box-shaped robot workspace on terrain.

Construction follows the paper: terrain, then the robot placed on it, then the ground cover
(sand, snow, clay, mud, water) laid on the terrain as a layer, leaving out the grid cells the
robot's particles occupy. The physics lives in `codesign_mpm.engine`; this module only turns
a recipe config into a `Scene`, a design into particles, and simulator state into
observations and rewards.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from codesign.errors import RecipeError
from codesign.interfaces import DesignFields, DesignSpace, Environment, StepResult
from codesign_mpm.config import CoverConfig, EnvironmentPreset, LocomotionConfig
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


def cover_body(cover: CoverConfig) -> BodySpec:
    """The ground-cover layer of an environment as a scene body."""
    material = MaterialSpec(**{name: getattr(cover, name) for name in MaterialSpec.__dataclass_fields__
                               if name != "kind"}, kind=cover.kind)
    return BodySpec(name=f"cover ({cover.kind})", shape=ShapeSpec(kind="layer", thickness=cover.thickness),
                    material=material, particles_per_cell=cover.particles_per_cell)


def make_scene(config: LocomotionConfig, preset: EnvironmentPreset) -> Scene:
    """The scene of a locomotion config: an actuated box robot on the terrain, then the cover."""
    t, r = config.terrain, config.robot
    cover = preset.cover if config.cover is None else config.cover
    on_cover = r.rest_on == "cover" and cover.kind != "none"
    scene = Scene(
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
            rest_offset=cover.thickness if on_cover else 0.0,
            particles_per_cell=r.particles_per_cell,
            muscles=MuscleSpec(groups=list(r.muscle_groups), fiber=[1.0, 0.0, 0.0]),
            robot=True,
        )],
        frame_dt=config.frame_dt,
        dtype=config.dtype,
        arch=config.arch,
    )
    if cover.kind != "none":
        scene.bodies.append(cover_body(cover))
    return scene


def _subset(particles: Particles, keep: np.ndarray) -> Particles:
    return Particles(**{name: getattr(particles, name)[keep] for name in Particles.__dataclass_fields__})


def _concat(first: Particles, second: Particles) -> Particles:
    """Particles of both sets, in order; the cover has no actuators, so its muscle rows are zero."""
    if second.n == 0:
        return first
    second = replace(second, muscle=np.zeros((second.n, first.n_actuators)))
    return Particles(**{name: np.concatenate([getattr(first, name), getattr(second, name)])
                        for name in Particles.__dataclass_fields__})


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

    `base_particles` is the robot's whole workspace; each design keeps, weighs and stiffens a
    subset. `cover_particles` (the ground cover, possibly none) follow the robot's in the
    simulator and are the same for every design.
    """

    def __init__(self, config: LocomotionConfig, preset: EnvironmentPreset) -> None:
        _check_config(config)
        self.config = config
        self.scene = make_scene(config, preset)
        try:
            everything = build_particles(self.scene)
        except SceneError as exc:
            raise RecipeError(f"invalid recipe: environment: the robot does not fit the scene: {exc}") from exc
        self.base_particles: Particles = _subset(everything, everything.robot)
        self.cover_particles: Particles = _subset(everything, ~everything.robot)
        k = self.base_particles.n_actuators
        self.design_space = DesignSpace(points=self.base_particles.x.copy(), n_actuators=k,
                                        default_stiffness=config.robot.youngs_modulus)
        self.action_dim = k
        self.observation_dim = 9
        self.horizon = config.horizon
        self.control_dt = config.frame_dt
        self.direction = np.asarray(config.task.direction, dtype=np.float64)
        self.direction /= np.linalg.norm(self.direction)
        self.particles: Particles = _concat(self.base_particles, self.cover_particles)
        self.sim: Simulator | None = None
        self.t = 0

    def design_particles(self, design: DesignFields) -> Particles:
        """Base particles with a design applied; particles under the occupancy threshold are dropped."""
        base = self.base_particles
        occupancy = _numpy(design.occupancy).reshape(base.n)
        keep = occupancy >= OCCUPANCY_THRESHOLD
        if not keep.any():
            raise ValueError(f"the design leaves no particle with occupancy >= {OCCUPANCY_THRESHOLD}")
        robot = replace(
            _subset(base, keep),
            volume=base.volume[keep] * occupancy[keep],
            youngs_modulus=_numpy(design.stiffness).reshape(base.n)[keep],
            muscle=_numpy(design.muscle).reshape(base.muscle.shape)[keep],
            fiber=_numpy(design.fiber).reshape(base.n, 3)[keep],
        )
        return _concat(robot, self.cover_particles)

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
        robot = particles.robot
        self._n_robot = int(robot.sum())
        self._mass = particles.volume[robot] * particles.density[robot]
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
        """(observation, robot positions, robot velocities); the robot's particles come first."""
        x, v, _, _ = self.sim.particles_state()
        x, v = x[:self._n_robot].astype(np.float64), v[:self._n_robot].astype(np.float64)
        weights = self._mass / self._mass.sum()
        return np.concatenate([weights @ x, weights @ v, self.direction]), x, v

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None
