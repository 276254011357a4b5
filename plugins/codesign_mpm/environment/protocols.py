"""What a differentiable episode needs of its environment, as a protocol.

`codesign_mpm.environment.episode` runs an episode against this interface rather than against
`LocomotionEnv` itself, so the environment module can offer `differentiable_episode` by
importing `episode` while `episode` imports nothing of `env` (no import cycle).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from codesign.interfaces import DesignFields
    from codesign_mpm.engine import Simulator
    from codesign_mpm.scene.integrity import IntegrityWatch
    from codesign_mpm.environment.observations import Observer
    from codesign_mpm.scene.sampling import Particles
    from codesign_mpm.environment.tasks import Task


class TaskStart(Protocol):
    watch: IntegrityWatch


class EpisodeEnvironment(Protocol):
    """The parts of `codesign_mpm.environment.env.LocomotionEnv` that `codesign_mpm.environment.episode.run_episode` uses."""

    base_particles: Particles
    config: Any  # LocomotionConfig: reads observation.occupancy
    observer: Observer
    task: Task
    control_dt: float
    horizon: int

    def design_mask(self, occupancy: np.ndarray) -> np.ndarray: ...

    def design_particles(self, design: DesignFields, mask: np.ndarray) -> Particles: ...

    def grad_simulator(self, particles: Particles, start: dict[str, np.ndarray] | None = None) -> Simulator: ...

    def _start_task(self, particles: Particles, x: np.ndarray) -> TaskStart: ...

    def initial_state(self, particles: Particles) -> dict[str, np.ndarray]: ...

    def tear_outcome(self, watch: IntegrityWatch, t: int) -> tuple[bool, float]: ...
