"""How much of a turning score is the body turning.

The turning task (the paper's appendix, and the released code) rewards the mean velocity of the
robot's particles along their unit tangents about the centre of mass. A rigid rotation at rate w
scores w times the particles' mean distance from the axis, but a body that deforms also moves its
particles along those tangents without turning. For each run given, this replays its best episode
and records the robot's net rotation about up (the best-fitting rotation of its particles in the
horizontal plane, from the start to each step; positive: counter-clockwise, the task's sense)
against its score, and the score a rigid rotation at the episode's mean rate would earn.
Prints one JSON line per run:

    python benchmarks/turning_yaw.py studies/benchmark/turning_*/t000-seed* > docs/data/studies-2026-11-28-turning-yaw.jsonl
"""

from __future__ import annotations

import json
import os
import sys

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from codesign.artifacts import to_numpy  # noqa: E402
from codesign.runner import best_parts  # noqa: E402


def rotation_about_up(start: np.ndarray, now: np.ndarray) -> float:
    """Counter-clockwise angle (radians, about +y) of the rotation that best maps the start's
    particles onto now's in the x-z plane, each about its own centroid (2-D Kabsch)."""
    a = start[:, [0, 2]] - start[:, [0, 2]].mean(0)
    b = now[:, [0, 2]] - now[:, [0, 2]].mean(0)
    h = a.T @ b
    # about +y, x turns towards -z: the clockwise angle in (x, z) coordinates
    return float(np.arctan2(h[1, 0] - h[0, 1], h[0, 0] + h[1, 1]))


def measure(run: str) -> dict:
    with best_parts(run) as (parts, design, rng), torch.no_grad():
        env, controller = parts.environment, parts.controller
        observation = env.reset(design=design, seed=int(rng.integers(2**31)))
        controller.reset()
        start = env.sim.particles_state()[0][env.particles.robot].astype(np.float64)
        angles, total = [], 0.0
        for t in range(env.horizon):
            result = env.step(to_numpy(controller(observation, t)))
            observation, total = result.observation, total + float(result.reward)
            angles.append(rotation_about_up(start, env.sim.particles_state()[0][env.particles.robot]))
        mean_distance = float(np.linalg.norm(start[:, [0, 2]] - start[:, [0, 2]].mean(0), axis=1).mean())
        duration = env.horizon * env.control_dt
    return dict(run=run, per_step=total / env.horizon, yaw_degrees=round(float(np.degrees(angles[-1])), 3),
                yaw_degrees_every_5_steps=[round(float(np.degrees(a)), 3) for a in angles[4::5]],
                rigid_per_step=angles[-1] / duration * mean_distance, mean_distance=mean_distance,
                duration=duration)


if __name__ == "__main__":
    for path in sys.argv[1:]:
        print(json.dumps(measure(path)), flush=True)
