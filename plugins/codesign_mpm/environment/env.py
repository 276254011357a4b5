"""Locomotion environments (SoftZoo's biomes): a robot workspace (box, ellipsoid, animal or body
file) on terrain.

Construction follows the paper: terrain, then the robot placed on it, then the ground cover
(sand, snow, clay, mud, water) laid on the terrain as a layer, leaving out the grid cells the
robot's particles occupy. The physics lives in `codesign_mpm.engine`; this module only turns
a recipe config into a `Scene`, a design into particles, and simulator state into
observations and rewards.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from codesign.artifacts import EPISODE_METRICS
from codesign.bodies import BODY_FILE_SUFFIXES, BodyError, load_body
import torch

from codesign.errors import DesignError, RecipeError
from codesign.interfaces import Controller, DesignFields, DesignSpace, Environment, StepResult
from codesign.registry import suggest
from codesign_mpm.engine.batch import BatchSimulator
from codesign_mpm.environment.config import (CoverConfig, EnvironmentPreset, LocomotionConfig, RobotConfig, TaskConfig,
                                 check_config, environment_error)
from codesign_mpm.engine import Simulator
from codesign_mpm.environment.episode import Episode, run_episode
from codesign_mpm.scene.integrity import MIN_THICKNESS_CELLS, IntegrityWatch, resolved_body, thinnest_cells
from codesign_mpm.environment.observations import Observer
from codesign_mpm.scene.sampling import Particles, build_particles, join_particles, layer_ground
from codesign_mpm.scene.spec import BodySpec, MaterialSpec, MuscleSpec, Scene, SceneError, ShapeSpec, TerrainSpec
from codesign_mpm.environment.settle import REST_SPEED, ROBOT_REST_SPEED, Relaxed, relax_scene, settled_state
from codesign_mpm.environment.tasks import TASKS, RobotFrame, Task, TaskContext
from codesign_mpm.scene.terrain import height_map

OCCUPANCY_THRESHOLD = 0.5
"""Particles whose occupancy is below this are removed: near-massless particles destabilise MPM."""
WATER_WALL_CLEARANCE = 0.1
"""Metres of water a robot's workspace should keep from the domain's walls (docs/studies.md): a 0.3 m box
that extends its muscles and holds still moved 12.5, 5.9, 0.5 and -1.1 mm in 0.48 s with its back 0.006,
0.056, 0.106 and 0.206 m from the wall band (dx 1/32): it pushes the water against the wall."""


def _warn_wall_push(config: LocomotionConfig, preset: EnvironmentPreset) -> None:
    """Warn when a robot in water starts closer than WATER_WALL_CLEARANCE to the walls at either end
    of the domain along x: pushing the water against a wall moves it, which an optimizer ranks as
    swimming."""
    if config.resolved_cover(preset).kind != "water":
        return
    wall = Scene().boundary_cells * config.dx
    back = config.robot.position[0] - config.robot.size[0] / 2 - wall
    front = config.size[0] - wall - (config.robot.position[0] + config.robot.size[0] / 2)
    if min(back, front) < WATER_WALL_CLEARANCE:
        warnings.warn(f"environment.robot.position: the robot's workspace is {min(back, front):.3g} m from the wall "
                      f"band along x in water; pushing the water against the wall moves it (a body that extends "
                      f"and holds still, 12.5 mm in 0.48 s at 6 mm): keep at least {WATER_WALL_CLEARANCE} m",
                      UserWarning, stacklevel=3)


def make_task(config: TaskConfig) -> Task:
    if config.name not in TASKS:
        raise environment_error("task.name", f"{config.name!r} is not a task; {suggest(config.name, TASKS)}"
                                             f"allowed: {', '.join(sorted(TASKS))} (or a task registered with "
                                             "codesign_mpm.environment.tasks.register_task)")
    return TASKS[config.name](config)


def cover_body(cover: CoverConfig) -> BodySpec:
    """The ground-cover layer of an environment as a scene body."""
    material = MaterialSpec(**{name: getattr(cover, name) for name in MaterialSpec.__dataclass_fields__
                               if name != "kind" and hasattr(cover, name)}, kind=cover.kind)
    return BodySpec(name=f"cover ({cover.kind})", shape=ShapeSpec(kind="layer", thickness=cover.thickness),
                    material=material, particles_per_cell=cover.particles_per_cell)


def robot_shape(robot: RobotConfig) -> tuple[ShapeSpec, MuscleSpec]:
    """The robot's base shape and muscles: a grid of muscles in a box or ellipsoid, a library body's
    own muscles, or a body file's (its annotated groups, else the grid)."""
    if robot.body_file is not None and robot.body != "file":
        raise environment_error("robot.body_file", f"{robot.body_file!r} is set but robot.body is {robot.body!r}; "
                                                   "set robot.body: file (or body_file: null)")
    grid = MuscleSpec(groups=list(robot.muscle_groups), fiber=[1.0, 0.0, 0.0],
                      stiffness_ratio=robot.muscle_stiffness_ratio, passive_density=robot.passive_density,
                      passive_stiffness=robot.passive_stiffness)
    if robot.body in ("box", "ellipsoid"):
        return ShapeSpec(kind=robot.body, size=list(robot.size)), _without_passive(robot, grid)
    if robot.body != "file":
        return ShapeSpec(kind="body", body=robot.body, size=list(robot.size)), replace(grid, layout="body")
    if not robot.body_file:
        raise environment_error("robot.body_file", f"{robot.body_file!r}: robot.body: file needs the path of a "
                                                   f"body file ({', '.join(BODY_FILE_SUFFIXES)})")
    try:
        body = load_body(robot.body_file)
    except BodyError as exc:
        raise environment_error("robot.body_file", str(exc)) from exc
    shape = ShapeSpec(kind="body", file=robot.body_file, size=list(robot.size))
    return shape, replace(grid, layout="body") if body.n_groups else _without_passive(robot, grid)


def _without_passive(robot: RobotConfig, grid: MuscleSpec) -> MuscleSpec:
    """A grid of muscles covers the whole body: passive material's settings would do nothing, so say so."""
    for name in ("passive_density", "passive_stiffness"):
        if getattr(robot, name) != 1.0:
            raise environment_error(f"robot.{name}", (
                f"{getattr(robot, name)!r} would do nothing: robot.body {robot.body!r} has no passive material (its "
                "grid of robot.muscle_groups covers it); only a library body or an annotated file has; leave it 1"))
    return grid


def make_scene(config: LocomotionConfig, preset: EnvironmentPreset) -> Scene:
    """The scene of a locomotion config: the actuated robot resting on the terrain, then the cover."""
    t, r = config.terrain, config.robot
    shape, muscles = robot_shape(r)
    cover = config.resolved_cover(preset)
    on_cover = r.rest_on == "cover" and cover.kind != "none"
    scene = Scene(
        size=list(config.size),
        dx=config.dx,
        terrain=TerrainSpec(kind=t.kind, height=t.height, amplitude=t.amplitude, frequency=t.frequency,
                            seed=t.seed, friction=preset.friction if t.friction is None else t.friction,
                            contact=t.contact, contact_stiffness=t.contact_stiffness,
                            contact_damping=t.contact_damping),
        bodies=[BodySpec(
            name="robot",
            shape=shape,
            material=MaterialSpec(youngs_modulus=r.youngs_modulus, poisson_ratio=r.poisson_ratio,
                                  density=r.density),
            center=[r.position[0], t.height, r.position[1]],
            rest_on_terrain=True,
            rest_offset=cover.thickness if on_cover else 0.0,
            particles_per_cell=r.particles_per_cell,
            muscles=muscles,
            robot=True,
        )],
        frame_dt=config.frame_dt,
        cfl=config.cfl,
        flip=config.flip,
        pic_time=config.pic_time,
        adaptive_dt=config.adaptive_dt,
        dtype=config.dtype,
        arch=config.arch,
    )
    if cover.kind != "none":
        scene.bodies.append(cover_body(cover))
    return scene


def _subset(particles: Particles, keep: np.ndarray | slice) -> Particles:
    return Particles(**{name: getattr(particles, name)[keep] for name in Particles.__dataclass_fields__})


def _concat(first: Particles, second: Particles) -> Particles:
    """Particles of both sets, in order; the second (the cover) has no muscle columns."""
    return first if second.n == 0 else join_particles([first, second])


def _without_muscles(particles: Particles) -> Particles:
    """The cover's particles carry no muscle columns: no copy of rows that are all zero."""
    return replace(particles, muscle=np.zeros((particles.n, 0)))


def _numpy(value: Any) -> np.ndarray:
    """Design fields may be torch tensors with grad; the simulator only needs their values."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


@dataclass
class EpisodeState:
    """What one running episode's observations and rewards need besides the particles."""

    task: Task
    observer: Observer
    n_robot: int  # the design's robot particles come first
    mass: torch.Tensor  # (n_robot,)
    muscle: torch.Tensor  # (n_robot, K)
    watch: IntegrityWatch  # whether the body holds together, frame by frame
    com: torch.Tensor | None = None  # the robot's centre of mass at the last frame observed


class LocomotionEnv(Environment):
    """A robot and a task (codesign_mpm.environment.tasks) on an environment preset.

    The observation is made of the parts switched on in `config.observation`
    (codesign_mpm.environment.observations; by default 9: centre of mass, its velocity, task information).
    The reward of each control step is the task's. `differentiable_episode` runs a whole
    episode of a design and a controller as a torch loss (minus the summed reward).

    `base_particles` is the robot's whole workspace; each design keeps, weighs and stiffens a
    subset. `cover_particles` (the ground cover, possibly none) follow the robot's in the
    simulator and are the same for every design.

    A population of episodes (`reset_population`, `step_population`) is simulated in one
    `BatchSimulator`, each episode with its own task state.
    """

    batched = True

    def __init__(self, config: LocomotionConfig, preset: EnvironmentPreset) -> None:
        check_config(config)  # again: a config changed after it was read
        _warn_wall_push(config, preset)
        self.config = config
        self.scene = make_scene(config, preset)
        try:
            everything = build_particles(self.scene)
        except SceneError as exc:
            raise RecipeError(f"invalid recipe: environment: the robot does not fit the scene: {exc}") from exc
        # the robot is the scene's first body, so its particles come first: both parts are views, not
        # copies of a terrain that may hold millions of particles
        n_robot = int(everything.robot.sum())
        assert everything.robot[:n_robot].all(), "make_scene puts the robot first"
        self.base_particles: Particles = _subset(everything, slice(0, n_robot))
        self.cover_particles: Particles = _subset(_without_muscles(everything), slice(n_robot, None))
        k = self.base_particles.n_actuators
        self.spacing = config.dx / round(config.robot.particles_per_cell ** (1 / 3))  # the robot's sampling lattice
        base = self.base_particles
        self.design_space = DesignSpace(points=base.x.copy(), n_actuators=k, default_stiffness=config.robot.youngs_modulus,
                                        stiffness=base.youngs_modulus.copy(),
                                        bounds=np.stack([base.x.min(0) - self.spacing / 2, base.x.max(0) + self.spacing / 2]),
                                        muscle=base.muscle.copy(), fiber=base.fiber.copy(), keep=self.resolved)
        self.action_dim = k
        self.horizon = config.horizon
        self.control_dt = config.frame_dt
        self.task = make_task(config.task)
        self.observer = Observer(config.observation, self.task, k, config.horizon, config.dx, height_map(self.scene))
        self.observation_dim = self.observer.dim
        self.particles: Particles = everything  # the robot, then the cover, as design_particles gives them
        cover = config.resolved_cover(preset)
        self._settled = cover.settled
        self._relaxed: tuple[tuple, Relaxed] | None = None  # (the body it is for, the relaxed start)
        self._fillable = self._under_cover(cover)
        self.sim: Simulator | None = None
        self._grad_sim: Simulator | None = None
        self._grad_segment: int | None = None  # the first design's default segment, kept for the next ones
        self._batch: BatchSimulator | None = None
        self._episode: EpisodeState | None = None
        self._population: list[EpisodeState] = []
        self.t = 0
        self.population_t = 0

    @property
    def observation_space(self):
        """The observation as a `gymnasium.spaces.Box`."""
        return self.observer.space()

    def resolved(self, occupied: np.ndarray) -> np.ndarray:
        """What of an occupied set of workspace particles this environment simulates: the parts at
        least `integrity.MIN_THICKNESS_CELLS` grid cells thick, in one connected body (thinner parts
        tear under actuation; `codesign_mpm.scene.integrity.resolved_body`)."""
        return resolved_body(self.base_particles.x, occupied, self.spacing, self.config.dx)

    def design_mask(self, occupancy: np.ndarray) -> np.ndarray:
        """(N,) the workspace particles a design keeps: occupancy >= OCCUPANCY_THRESHOLD, then `resolved`.
        A `DesignError` if nothing is left."""
        occupied = np.asarray(occupancy).reshape(self.base_particles.n) >= OCCUPANCY_THRESHOLD
        keep = self.resolved(occupied)
        if not keep.any():
            raise DesignError(
                f"the design leaves no part at least {MIN_THICKNESS_CELLS:g} grid cells thick (dx = {self.config.dx:.4g}; "
                f"{int(occupied.sum())} of {len(occupied)} particles have occupancy >= {OCCUPANCY_THRESHOLD})")
        return keep

    def design_particles(self, design: DesignFields, keep: np.ndarray | None = None) -> Particles:
        """Base particles with a design applied: those `design_mask` keeps (or `keep`, its result),
        weighed by their occupancy."""
        base = self.base_particles
        occupancy = _numpy(design.occupancy).reshape(base.n)
        keep = self.design_mask(occupancy) if keep is None else keep
        robot = replace(
            _subset(base, keep),
            volume=base.volume[keep] * occupancy[keep],
            youngs_modulus=_numpy(design.stiffness).reshape(base.n)[keep],
            muscle=_numpy(design.muscle).reshape(base.muscle.shape)[keep],
            fiber=_numpy(design.fiber).reshape(base.n, 3)[keep],
        )
        return _concat(robot, self._cover_with_fill(self._fillable & ~keep))

    def _under_cover(self, cover: CoverConfig) -> np.ndarray:
        """(N,) the workspace particles inside the cover layer's extent (above the terrain, below its
        top): where the cover would be if the workspace were not there; none without a cover."""
        x = self.base_particles.x
        if cover.kind == "none" or self.cover_particles.n == 0:
            return np.zeros(len(x), dtype=bool)
        ground = layer_ground(self.scene, x)
        return (x[:, 1] > ground) & (x[:, 1] < ground + cover.thickness)

    def _cover_with_fill(self, fill: np.ndarray) -> Particles:
        """The cover, plus cover material at the workspace particles `fill`: the part of the layer a
        design leaves empty. Without it a design smaller than its workspace would sit in a hole in
        the water (or sand), which collapses at the start and carries the body with it."""
        if not fill.any():
            return self.cover_particles
        cover, base = self.cover_particles, self.base_particles
        n = int(fill.sum())
        like = {name: np.repeat(getattr(cover, name)[:1], n, axis=0)
                for name in ("density", "youngs_modulus", "poisson_ratio", "material", "muscle_ratio", "params", "body",
                             "robot", "fiber")}
        filled = Particles(x=base.x[fill], v=base.v[fill], volume=base.volume[fill],
                           muscle=np.zeros((n, cover.muscle.shape[1])), **like)
        return _concat(filled, cover)

    def reset(self, design: DesignFields | None = None, seed: int | None = None) -> np.ndarray:
        """Load ``design`` (or keep the last one); the tasks are deterministic, so ``seed`` is unused."""
        if design is not None:
            self.particles = self.design_particles(design)
        particles = self.particles
        # A new particle count needs a new simulator (cheap: compiled kernels of the same
        # layout are reused from the closed one), and so does a Taichi program of another
        # environment's precision built since; reset() re-derives the CFL step itself.
        if self.sim is None or not self.sim.alive or self.sim.n != particles.n:
            if self.sim is not None:
                self.sim.close()
            self.sim = Simulator(self.scene, particles, capacity=self.capacity)
        else:
            self.sim.reset(particles)
        start = self.initial_state(particles)
        self.sim.set_initial_state(**start)
        self.t = 0
        self._episode = self._start_task(particles, start["x"])
        self.sim.on_frame = self._episode.watch.see
        return self._observe(self._episode, 0, self.sim.particles_state())[0]

    def reset_population(self, designs: list[DesignFields | None],
                         seed: int | list[int] | None = None) -> list[np.ndarray]:
        """Start one episode per design (None: the current design), all in one batched simulator.
        The tasks are deterministic, so ``seed`` (one per design, or one for all) changes nothing."""
        members = [self.particles if design is None else self.design_particles(design) for design in designs]
        if self._batch is None or not self._batch.alive or self._batch.counts != [m.n for m in members]:
            if self._batch is not None:
                self._batch.close()
            self._batch = BatchSimulator(self.scene, members, capacity=self.capacity)
        else:
            self._batch.reset_members(members)
        starts = [self.initial_state(m) for m in members]
        self._batch.set_initial_state(**{key: np.concatenate([s[key] for s in starts]) for key in starts[0]})
        self.population_t = 0
        self._population = []
        for member, start in zip(members, starts):
            task = make_task(self.config.task)
            self._population.append(self._start_task(member, start["x"], task, replace(self.observer, task=task)))
        self._batch.on_frame = self._see_population
        return [self._observe(episode, 0, state)[0] for episode, state in zip(self._population, self._member_states())]

    def step_population(self, actions: np.ndarray) -> list[StepResult]:
        if self._batch is None:
            raise RuntimeError("call reset_population() before step_population()")
        self._batch.step(_numpy(actions))
        self.population_t += 1
        return [self._result(episode, self.population_t, state)
                for episode, state in zip(self._population, self._member_states())]

    def _see_population(self, x: np.ndarray) -> None:
        for episode, member_x in zip(self._population, self._batch.split(x)):
            episode.watch.see(member_x)

    def _member_states(self) -> list[tuple[np.ndarray, ...]]:
        """(x, v, C, F) of each member of the batch."""
        return list(zip(*(self._batch.split(a) for a in self._batch.particles_state())))

    @property
    def capacity(self) -> int:
        """Particles of the full workspace plus the cover: every design's simulators share one layout."""
        return self.base_particles.n + self.cover_particles.n

    def initial_state(self, particles: Particles) -> dict[str, np.ndarray]:
        """The state a design's particles start from (`Simulator.set_initial_state` keywords x, v, C,
        F, Jp): the robot stress-free and at rest, the cover loaded by its own weight; with
        `robot.settled`, the scene relaxed to rest (`settle.relax_scene`: once per body, kept on disk)."""
        F, jp = np.tile(np.eye(3), (particles.n, 1, 1)), np.ones(particles.n)
        if self._settled and self.cover_particles.n:
            rest = ~particles.robot
            F[rest], jp[rest] = settled_state(self.scene, _subset(particles, rest))
        start = {"x": particles.x, "v": particles.v, "C": np.zeros((particles.n, 3, 3)), "F": F, "Jp": jp}
        return self._relaxed_start(particles, start) if self.config.robot.settled else start

    def _relaxed_start(self, particles: Particles, start: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`start` relaxed to rest (`settle.relax_scene`), found for the first body and reused: the same
        body needs no action to settle, whatever its muscles; a body of another shape or stiffness
        would need its own, which no gradient could reach (the relaxation is forward only)."""
        body = (particles.n, particles.volume.tobytes(), particles.density.tobytes(), particles.youngs_modulus.tobytes())
        if self._relaxed is None:
            relaxed = relax_scene(self.scene, particles, start, capacity=self.capacity)
            if not relaxed.at_rest:
                warnings.warn(f"environment.robot.settled: the scene is not at rest after {relaxed.frames} frames "
                              f"(RMS speed {relaxed.speed:.1e} m/s, the robot's {relaxed.robot_speed:.1e}; at rest "
                              f"under {REST_SPEED:g} and {ROBOT_REST_SPEED:g}; in water a body rises or sinks "
                              "unless it is as dense as the water); it starts from there", stacklevel=2)
            self._relaxed = (body, relaxed)
        elif self._relaxed[0] != body:
            raise RecipeError("invalid recipe: environment.robot.settled: true starts a fixed body at rest (relaxed "
                              "once), but this design changes the body's shape, mass or stiffness: set it false to "
                              "optimise those (a design that moves only the muscles may keep it)")
        return self._relaxed[1].state

    def _start_task(self, particles: Particles, x: np.ndarray, task: Task | None = None,
                    observer: Observer | None = None) -> EpisodeState:
        """Start `task` (default: the environment's own, observed by its observer) for a design's particles
        starting at positions `x` (initial_state's)."""
        task, observer = task or self.task, observer or self.observer
        robot = particles.robot
        mass = torch.as_tensor(particles.volume[robot] * particles.density[robot])
        rest = x[robot]
        com = (mass.numpy() @ rest) / mass.sum().item()
        task.start(TaskContext(rest_x=rest, start_com=com, control_dt=self.control_dt, horizon=self.horizon))
        watch = IntegrityWatch(mass.numpy(), self.config.dx, self.config.integrity.tolerance,
                               thinnest_cells(rest, self.spacing, self.config.dx))
        return EpisodeState(task, observer, int(robot.sum()), mass, torch.as_tensor(particles.muscle[robot]), watch)

    def tear_outcome(self, watch: IntegrityWatch, t: int) -> tuple[bool, float]:
        """(whether step t's reward is dropped, the penalty taken off at step t) for a robot that tore
        (`config.integrity`): terminate drops the rewards from the frame it tore on; penalize takes
        penalty x horizon x (torn fraction - tolerance) off the last step."""
        rule = self.config.integrity
        dropped = rule.on_tear == "terminate" and watch.torn_at is not None and t >= watch.torn_at
        penalty = 0.0
        if rule.on_tear == "penalize" and t == self.horizon:
            penalty = rule.penalty * self.horizon * max(0.0, watch.torn - rule.tolerance)
        return dropped, penalty

    def step(self, action: np.ndarray) -> StepResult:
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        self.sim.step(_numpy(action))
        self.t += 1
        return self._result(self._episode, self.t, self.sim.particles_state())

    def _result(self, episode: EpisodeState, t: int, state: tuple[np.ndarray, ...]) -> StepResult:
        observation, frame = self._observe(episode, t, state)
        reward = float(episode.task.reward(frame))
        dropped, penalty = self.tear_outcome(episode.watch, t)
        info = {"com": frame.com_x.numpy().copy(), EPISODE_METRICS: episode.watch.metrics()}
        return StepResult(observation, (0.0 if dropped else reward) - penalty, t >= self.horizon or dropped, info)

    def _observe(self, episode: EpisodeState, t: int, state: tuple[np.ndarray, ...]) -> tuple[np.ndarray, RobotFrame]:
        """(observation before step t + 1, the robot's frame after step t) from the particles'
        (x, v, C, F); robot particles come first."""
        n = episode.n_robot
        x, v, F = (torch.as_tensor(state[i][:n], dtype=torch.float64) for i in (0, 1, 3))
        cover_x = state[0][n:] if self.config.observation.occupancy else None
        observation = episode.observer(t, x, v, episode.mass, episode.muscle, cover_x)
        w = episode.mass / episode.mass.sum()
        frame = RobotFrame(t, t * self.control_dt, w @ x, w @ v, episode.mass, x, v, F, com_x_before=episode.com)
        episode.com = frame.com_x
        return observation.numpy().astype(np.float64), frame

    def differentiable_episode(self, design: DesignFields, controller: Controller,
                               checkpoint_every: int | None = None) -> Episode:
        """Run an episode of `design` and `controller` as a torch loss (minus the summed reward)
        whose `backward()` reaches the torch parameters behind both (codesign_mpm.environment.episode)."""
        return run_episode(self, design, controller, checkpoint_every)

    def grad_simulator(self, particles: Particles, start: dict[str, np.ndarray] | None = None) -> Simulator:
        """A differentiable simulator for `particles` (one per particle count, sharing one layout: the
        capacity and the segment are the first design's, which a stiffer one's time step would change) at
        `start` (default: `initial_state(particles)`)."""
        if self._grad_sim is None or not self._grad_sim.alive or self._grad_sim.n != particles.n:
            if self._grad_sim is not None:
                self._grad_sim.close()
            self._grad_sim = Simulator(self.scene, particles, requires_grad=True, max_frames=self.horizon,
                                       checkpoint_every=self.config.checkpoint_every or self._grad_segment,
                                       capacity=self.capacity)
            self._grad_segment = self._grad_sim.segment
        else:
            self._grad_sim.reset(particles)
        self._grad_sim.set_initial_state(**(self.initial_state(particles) if start is None else start))
        return self._grad_sim

    def close(self) -> None:
        for sim in (self.sim, self._grad_sim, self._batch):
            if sim is not None:
                sim.close()
        self.sim = self._grad_sim = self._batch = None
