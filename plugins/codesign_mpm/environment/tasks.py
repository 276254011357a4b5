"""Locomotion tasks (SoftZoo appendix "Locomotion Tasks"): a reward per control step, in torch.

Rewards are torch expressions of the robot's state after a control step, so one definition
serves reinforcement learning (a float per step) and gradient-based optimizers (the
differentiable loss is minus the summed reward). Mass weights are normalised: a reward is a
mass-weighted mean, so it does not grow with the robot's size.

Third-party tasks: subclass `Task` and call `register_task(name, factory)` from the plugin
module's `codesign_register` hook (or at its import); `environment.task.name` then accepts the
name and the task's own parameters go in `environment.task.params`. This is the documented
hook for tasks (a registry of their own rather than a fifth recipe section, since a task is
part of an environment's configuration).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from codesign_mpm.environment.config import TURNING_MEASURES

HEAD_TAIL_FRACTION = 0.05
"""Velocity tracking: the head and tail are this fraction of the robot's particles at either end of its heading."""
ALPHA_MAGNITUDE, ALPHA_DIRECTION = 0.1, 0.9
"""The paper's weights of velocity tracking's magnitude and direction terms."""
NORM_EPS = 1e-6


@dataclass
class RobotFrame:
    """The robot after control step `step` (1-based), at simulated time `time` (exact)."""

    step: int
    time: float
    com_x: torch.Tensor  # (3,)
    com_v: torch.Tensor  # (3,)
    mass: torch.Tensor | None = None  # (n,) per robot particle, for tasks that need particles
    x: torch.Tensor | None = None  # (n, 3)
    v: torch.Tensor | None = None  # (n, 3)
    F: torch.Tensor | None = None  # (n, 3, 3)
    com_x_before: torch.Tensor | None = None  # (3,) the centre of mass after the step before (or at the start)


@dataclass
class TaskContext:
    """What a task may know when an episode starts."""

    rest_x: np.ndarray  # (n, 3) robot particles at rest (the canonical pose)
    start_com: np.ndarray  # (3,)
    control_dt: float  # simulated seconds per control step (exact)
    horizon: int  # control steps per episode


class Task(ABC):
    """One locomotion objective. `needs_particles` False means the reward reads only the centre
    of mass, which lets open-loop controllers use the simulator's fast single-rollout path."""

    needs_particles: bool = True
    info_dim: int = 3

    def start(self, context: TaskContext) -> None:
        """Called at every reset with the design's rest pose and starting point."""
        self.context = context

    @abstractmethod
    def reward(self, frame: RobotFrame) -> torch.Tensor:
        """Scalar reward of one control step."""

    @abstractmethod
    def info(self, step: int) -> np.ndarray:
        """(info_dim,) task information observed before control step `step` (0-based)."""


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.sqrt((v * v).sum(-1, keepdim=True) + NORM_EPS ** 2)


class MovementSpeed(Task):
    """The centre of mass's mean velocity along the target direction over the control step,
    (com_x - com_x_before) . d / control_dt, so that an episode's return is its distance over
    control_dt (its mean speed times its steps); not the velocity at the step's end, which a
    stroke locked in phase to the control steps can show at its fast instants only (an ocean gait
    scored 2.8 times its distance that way)."""

    needs_particles = False

    def __init__(self, direction) -> None:
        d = np.asarray(direction, dtype=np.float64)
        self.direction = d / np.linalg.norm(d)

    def reward(self, frame: RobotFrame) -> torch.Tensor:
        if frame.com_x_before is None:
            raise ValueError("movement_speed needs the frame's com_x_before (the centre of mass a step earlier)")
        moved = frame.com_x - torch.as_tensor(frame.com_x_before, dtype=frame.com_x.dtype)
        return moved @ torch.as_tensor(self.direction, dtype=frame.com_x.dtype) / self.context.control_dt

    def info(self, step: int) -> np.ndarray:
        return self.direction


class Turning(Task):
    """Counter-clockwise turning about `up` through the centre of mass.

    `tangent` (the paper's): the mass-weighted mean velocity along each particle's unit tangent,
    sum m v . unit(up x (x - com)) / sum m. A bending body earns it too: particles near the axis
    count as much as far ones, so inner material swinging one way and outer material the other
    scores without the body turning. `angular_momentum`: the body's angular velocity about `up`,
    its angular momentum over its moment of inertia (both about the centre of mass), times the
    particles' mass-weighted mean distance from the axis, which deformation without angular
    momentum does not earn. The two agree on a rigid rotation (rate times mean distance).
    """

    def __init__(self, up, measure: str = "tangent") -> None:
        if measure not in TURNING_MEASURES:
            raise ValueError(f"turning measure {measure!r}: choose from {', '.join(TURNING_MEASURES)}")
        u = np.asarray(up, dtype=np.float64)
        self.up, self.measure = u / np.linalg.norm(u), measure

    def reward(self, frame: RobotFrame) -> torch.Tensor:
        up = torch.as_tensor(self.up, dtype=frame.x.dtype).expand_as(frame.x)
        arm = torch.cross(up, frame.x - frame.com_x, dim=1)  # |arm|: the distance from the axis
        if self.measure == "tangent":
            return (frame.mass * (frame.v * _unit(arm)).sum(1)).sum() / frame.mass.sum()
        weight = frame.mass / frame.mass.sum()
        momentum = weight @ (arm * (frame.v - frame.com_v)).sum(1)  # up . sum m (x - com) x v, per unit mass
        inertia = weight @ (arm * arm).sum(1)
        distance = weight @ torch.sqrt((arm * arm).sum(1) + NORM_EPS ** 2)
        return momentum / (inertia + NORM_EPS ** 2) * distance

    def info(self, step: int) -> np.ndarray:
        return self.up


def quintic(start, end, start_velocity, end_velocity, start_acceleration, end_acceleration,
            duration: float) -> np.ndarray:
    """(6, 3) coefficients c_k of x(t) = sum c_k t^k meeting position, velocity and acceleration
    at t = 0 and t = duration."""
    xs, xt, vs, vt, a_s, at = (np.asarray(a, dtype=np.float64) for a in
                               (start, end, start_velocity, end_velocity, start_acceleration, end_acceleration))
    T = duration
    return np.stack([
        xs, vs, a_s / 2,
        (20 * (xt - xs) - (8 * vt + 12 * vs) * T - (3 * a_s - at) * T ** 2) / (2 * T ** 3),
        (30 * (xs - xt) + (14 * vt + 16 * vs) * T + (3 * a_s - 2 * at) * T ** 2) / (2 * T ** 4),
        (12 * (xt - xs) - (6 * vt + 6 * vs) * T - (a_s - at) * T ** 2) / (2 * T ** 5),
    ])


class _PathTask(Task):
    """A quintic path from the robot's starting centre of mass to `start + offset` over the episode."""

    def __init__(self, offset, start_velocity, end_velocity, start_acceleration, end_acceleration) -> None:
        self.boundary = tuple(np.asarray(a, dtype=np.float64) for a in
                              (offset, start_velocity, end_velocity, start_acceleration, end_acceleration))

    def start(self, context: TaskContext) -> None:
        super().start(context)
        offset, vs, vt, a_s, at = self.boundary
        self.coefficients = quintic(context.start_com, context.start_com + offset, vs, vt, a_s, at,
                                    context.horizon * context.control_dt)

    def position(self, t: float) -> np.ndarray:
        return np.polynomial.polynomial.polyval(t, self.coefficients)

    def velocity(self, t: float) -> np.ndarray:
        k = np.arange(1, 6)[:, None]
        return np.polynomial.polynomial.polyval(t, k * self.coefficients[1:])


class WaypointFollowing(_PathTask):
    """Minus the squared distance of the centre of mass to the path's point at this step's time."""

    needs_particles = False

    def reward(self, frame: RobotFrame) -> torch.Tensor:
        target = torch.as_tensor(self.position(frame.time), dtype=frame.com_x.dtype)
        return -((frame.com_x - target) ** 2).sum()

    def info(self, step: int) -> np.ndarray:
        """The next waypoint (at the end of this step)."""
        return self.position((step + 1) * self.context.control_dt)


class VelocityTracking(_PathTask):
    """Track the path's velocity v*(t): 0.1 r_mag + 0.9 r_dir with r_mag = -(|v*| - |v_h|)^2 and
    r_dir = v* . unit(v_h), where v_h is the centre-of-mass velocity projected on the robot's
    heading. The heading is the rest-pose tail-to-head direction d rotated by the rotation of the
    head and tail particles' mean deformation gradient (polar decomposition)."""

    def start(self, context: TaskContext) -> None:
        super().start(context)
        rest = context.rest_x
        along = rest[:, 0]  # the canonical heading is +x
        count = max(1, int(HEAD_TAIL_FRACTION * len(rest)))
        order = np.argsort(along)
        self.tail, self.head = order[:count], order[-count:]
        d = rest[self.head].mean(0) - rest[self.tail].mean(0)
        self.rest_heading = d / np.linalg.norm(d)

    def heading(self, F: torch.Tensor) -> torch.Tensor:
        mean_F = torch.cat([F[self.head], F[self.tail]]).mean(0)
        R = mean_F
        for _ in range(8):  # Newton's polar iteration: R <- (R + R^-T) / 2, differentiable, quick near a rotation
            R = 0.5 * (R + torch.linalg.inv(R).T)
        return R @ torch.as_tensor(self.rest_heading, dtype=F.dtype)

    def reward(self, frame: RobotFrame) -> torch.Tensor:
        target = torch.as_tensor(self.velocity(frame.time), dtype=frame.com_v.dtype)
        h = self.heading(frame.F)
        projected = (frame.com_v @ h) * h
        speed = torch.sqrt((projected * projected).sum() + NORM_EPS ** 2)
        magnitude = -(target.norm() - speed) ** 2
        direction = target @ projected / speed
        return ALPHA_MAGNITUDE * magnitude + ALPHA_DIRECTION * direction

    def info(self, step: int) -> np.ndarray:
        """The target velocity at the end of this step."""
        return self.velocity((step + 1) * self.context.control_dt)


TaskFactory = Callable[..., Task]
TASKS: dict[str, TaskFactory] = {}


def register_task(name: str, factory: TaskFactory) -> None:
    """Make `environment.task.name: <name>` build `factory(config)` (config: the TaskConfig)."""
    if name in TASKS and TASKS[name] is not factory:
        raise ValueError(f"task '{name}' is registered twice")
    TASKS[name] = factory


def _path_args(config) -> tuple:
    return (config.offset, config.start_velocity, config.end_velocity, config.start_acceleration,
            config.end_acceleration)


register_task("movement_speed", lambda config: MovementSpeed(config.direction))
register_task("turning", lambda config: Turning(config.up, config.turning_measure))
register_task("velocity_tracking", lambda config: VelocityTracking(*_path_args(config)))
register_task("waypoint_following", lambda config: WaypointFollowing(*_path_args(config)))
