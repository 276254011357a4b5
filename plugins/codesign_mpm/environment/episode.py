"""Differentiable episodes: a design and a controller in, minus the summed task reward out.

Two paths, chosen per episode:

- **open loop** (a controller with `open_loop = True`, e.g. `sine` or `trajectory`, and a
  task that reads only the centre of mass): all actions are computed first and the episode is
  one checkpointed rollout through the torch bridge (`bridge.simulate`): memory grows with
  T / S + S states;
- **closed loop** (anything else): each control step is its own autograd node
  (`bridge.step_frame`), so the action at step t may depend on the observation of the state
  at step t and gradients flow back through it. Torch keeps each step's input state (about
  200 bytes per particle per step in float64).

Design fields enter as the simulator's per-particle inputs (volume = sampled volume x
occupancy, Young's modulus, muscle membership, fibre); particles under the occupancy
threshold or in parts too thin for the grid are dropped (`LocomotionEnv.design_mask`), as in every
other episode, so they receive no gradient.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np
import torch

from codesign.interfaces import Controller, DesignFields
from codesign_mpm.environment.bridge import STATE_FIELDS, simulate, step_frame
from codesign_mpm.environment.protocols import EpisodeEnvironment
from codesign_mpm.scene.sampling import Particles
from codesign_mpm.environment.tasks import RobotFrame

DTYPE = torch.float64


@dataclass
class Episode:
    loss: torch.Tensor  # scalar: minus the episode's return
    rewards: torch.Tensor  # (T,) the task's reward per step, those a tear drops set to zero
    com: np.ndarray  # (T + 1, 3) robot centre of mass per frame
    actions: np.ndarray  # (T, K)
    penalty: float = 0.0  # what a tear costs (`LocomotionEnv.tear_outcome`), taken off the return
    metrics: dict = field(default_factory=dict)  # the body's integrity (codesign_mpm.scene.integrity)

    @property
    def episode_return(self) -> float:
        return self.rewards.sum().item() - self.penalty


def _tensor(value, shape) -> torch.Tensor:
    return torch.as_tensor(value).to(DTYPE).reshape(shape)


def design_inputs(env: EpisodeEnvironment, design: DesignFields) -> tuple[Particles, tuple[torch.Tensor, ...]]:
    """The design's particles (robot, then cover) and its differentiable per-particle inputs
    (volume, Young's modulus, muscle, fibre), the cover's (with what fills the design's empty
    workspace) as constants."""
    base = env.base_particles
    occupancy = _tensor(design.occupancy, (base.n,))
    mask = env.design_mask(occupancy.detach().numpy())
    particles = env.design_particles(design, mask)
    keep = torch.as_tensor(mask)
    robot = (
        torch.as_tensor(base.volume, dtype=DTYPE)[keep] * occupancy[keep],
        _tensor(design.stiffness, (base.n,))[keep],
        _tensor(design.muscle, base.muscle.shape)[keep],
        _tensor(design.fiber, (base.n, 3))[keep],
    )
    n = int(mask.sum())
    constant = (particles.volume[n:], particles.youngs_modulus[n:], np.zeros((particles.n - n, base.n_actuators)),
                particles.fiber[n:])
    inputs = tuple(torch.cat([r, torch.as_tensor(c, dtype=DTYPE)]) for r, c in zip(robot, constant))
    return particles, inputs


def run_episode(env: EpisodeEnvironment, design: DesignFields, controller: Controller,
                checkpoint_every: int | None = None) -> Episode:
    particles, inputs = design_inputs(env, design)
    volume, stiffness, muscle, fiber = inputs
    start = env.initial_state(particles)
    sim = env.grad_simulator(particles, start)
    watch = env._start_task(particles, start["x"]).watch
    n = len(watch.mass)
    sim.on_frame = watch.see
    controller.reset()
    dt, T = env.control_dt, env.horizon
    density = torch.as_tensor(particles.density[:n], dtype=DTYPE)
    mass = volume[:n] * density  # differentiable in the occupancy
    weights = mass / mass.sum()
    if getattr(controller, "open_loop", False) and not env.task.needs_particles:
        actions = torch.stack([torch.as_tensor(controller(None, t)).to(DTYPE) for t in range(T)])
        com_x, com_v, _, _ = simulate(sim, actions, volume=volume, youngs_modulus=stiffness, muscle=muscle,
                                      fiber=fiber, checkpoint_every=checkpoint_every)
        rewards = torch.stack([env.task.reward(RobotFrame(t, t * dt, com_x[t], com_v[t], com_x_before=com_x[t - 1]))
                               for t in range(1, T + 1)])
        com = com_x.detach().numpy()
    else:
        springs = {"u": np.zeros((len(start["x"]), 3))}  # no contact has stuck yet
        state = tuple(torch.as_tensor({**start, **springs}[key], dtype=DTYPE) for key in STATE_FIELDS)
        cover_x = None
        before = weights @ state[0][:n]  # the centre of mass a step earlier (differentiable in the design)
        rewards, coms, actions = [], [before.detach().numpy()], []
        robot_muscle = muscle[:n]
        for t in range(T):
            x, v = state[0][:n], state[1][:n]
            if env.config.observation.occupancy:
                cover_x = state[0][n:].detach().numpy()
            observation = env.observer(t, x, v, mass, robot_muscle, cover_x)
            action = torch.as_tensor(controller(observation, t)).to(DTYPE)
            actions.append(action)
            state = step_frame(sim, state, action, inputs, checkpoint_every)
            x, v, F = state[0][:n], state[1][:n], state[3][:n]
            frame = RobotFrame(t + 1, (t + 1) * dt, weights @ x, weights @ v, mass, x, v, F, com_x_before=before)
            before = frame.com_x
            rewards.append(env.task.reward(frame))
            coms.append(frame.com_x.detach().numpy())
        rewards, actions, com = torch.stack(rewards), torch.stack(actions), np.stack(coms)
    outcomes = [env.tear_outcome(watch, t) for t in range(1, T + 1)]
    kept = torch.tensor([0.0 if dropped else 1.0 for dropped, _ in outcomes], dtype=DTYPE)
    penalty = sum(p for _, p in outcomes)
    rewards = rewards * kept
    return Episode(penalty - rewards.sum(), rewards, com, actions.detach().numpy(), penalty, watch.metrics())
