"""Gymnasium environments: every environment x task, with a fixed design, for reinforcement learning.

Ids are ``codesign/<Environment>-<Task>-v0``, e.g. ``codesign/Ground-MovementSpeed-v0`` or
``codesign/Ocean-WaypointFollowing-v0``. They are registered when this module is imported;
``gymnasium.make("codesign_mpm.environment.gym:codesign/Ground-MovementSpeed-v0")`` imports it for you,
and importing `codesign_mpm` registers them too when gymnasium is already imported::

    env = gymnasium.make("codesign_mpm.environment.gym:codesign/Desert-Turning-v0",
                         environment={"dx": 1 / 32, "horizon": 50}, representation={"name": "particle"})

Keyword arguments: ``environment`` (any keys of the environment's recipe section, e.g. the
robot body, cover or observation parts; validated like a recipe) and ``representation`` (a
recipe section: ``name`` plus parameters) whose initial design, drawn with ``design_seed``,
is the robot the agent controls. Episodes end by truncation at the horizon.
"""
from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS

TASK_IDS = {"movement_speed": "MovementSpeed", "turning": "Turning", "velocity_tracking": "VelocityTracking",
            "waypoint_following": "WaypointFollowing"}


def env_id(environment: str, task: str) -> str:
    return f"codesign/{environment.title().replace('_', '')}-{TASK_IDS[task]}-v0"


class CodesignEnv(gymnasium.Env):
    """A `LocomotionEnv` with a fixed design as a Gymnasium environment (float32 observations)."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, preset: str, task: str, environment: dict | None = None, representation: dict | None = None,
                 design_seed: int = 0) -> None:
        from codesign.recipe import resolve_section
        from codesign_mpm.environment.env import LocomotionEnv

        settings = dict(environment or {})
        settings["task"] = {**settings.get("task", {}), "name": task}
        config = resolve_section("environment", {"name": preset, **settings}).config
        self.env = LocomotionEnv(config, PRESETS[preset])
        rep_section = resolve_section("representation", representation or {"name": "particle"})
        from codesign.plugins import get_registry

        rep = get_registry().get("representation", rep_section.name).load_factory()(rep_section.config)
        rep.setup(self.env.design_space, np.random.default_rng(design_seed))
        self.design = rep()
        bound = self.env.scene.max_action
        self.action_space = gymnasium.spaces.Box(-bound, bound, (self.env.action_dim,), dtype=np.float32)
        self.observation_space = self.env.observation_space

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        observation = self.env.reset(self.design, seed=seed)
        return observation.astype(np.float32), {}

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict]:
        result = self.env.step(np.asarray(action, dtype=np.float64))
        return result.observation.astype(np.float32), result.reward, False, result.done, result.info

    def close(self) -> None:
        self.env.close()


def register_envs() -> None:
    """Register every environment x task id (idempotent)."""
    for preset in PRESET_CONFIGS:
        for task in TASK_IDS:
            name = env_id(preset, task)
            if name not in gymnasium.registry:
                gymnasium.register(name, entry_point=CodesignEnv, kwargs={"preset": preset, "task": task})


register_envs()
