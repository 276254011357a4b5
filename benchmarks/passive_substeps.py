"""What the released code's passive material costs Table 1 at the paper's scale: substeps a control step.

An animal's passive material a fifth as dense and 10 times as stiff as its muscles (the released
SoftZoo's annotated animals; `robot.passive_density` 0.2, `robot.passive_stiffness` 10) carries a
wave sqrt(50) times as fast, and the time step follows the fastest wave (the CFL condition). For
each animal and environment of the `benchmark` study at a scale (default `paper`): the substeps of
a control step with that material and with passive material like the muscles, and the particles.
Builds each cell's environment and its design, no simulation; one JSON line per cell.

    python benchmarks/passive_substeps.py > docs/data/studies-2026-11-28-passive-substeps.jsonl
"""

from __future__ import annotations

import copy
import json
import os
import sys
import warnings

import numpy as np

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")  # stdout holds the JSON lines alone

from codesign.recipe import resolve_recipe
from codesign.runner import build_parts
from codesign.study import arm_recipe, load_study
from codesign_mpm.engine.time_step import time_step


def substeps(recipe: dict) -> tuple[int, int]:
    """(substeps a control step, particles) of the recipe's environment with its starting design."""
    parts = build_parts(resolve_recipe(recipe))
    env = parts.environment
    try:
        parts.representation.setup(env.design_space, np.random.default_rng(0))
        particles = env.design_particles(parts.representation())
        return time_step(env.scene, particles).substeps, particles.n
    finally:
        env.close()


def main(scale: str = "paper") -> None:
    study = load_study("benchmark", scale)
    seen = set()
    for arm in study.arms:
        animal, environment = arm.label.split(" / ")[1:3]
        if (animal, environment) in seen:
            continue  # one task and method per cell: the time step depends on neither
        seen.add((animal, environment))
        recipe = arm_recipe(study, arm)
        recipe.pop("sweep", None)  # its seeds: one build is enough
        recipe["environment"]["arch"] = "cpu"  # the time step does not depend on the device
        recipe.setdefault("tracking", {})["wandb"] = False
        plain = copy.deepcopy(recipe)
        plain["environment"]["robot"].update(passive_density=1.0, passive_stiffness=1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # thin parts: measured in benchmarks/body_muscles.py
            released, n = substeps(recipe)
            like_muscle, _ = substeps(plain)
        print(json.dumps(dict(scale=scale, animal=animal, environment=environment, particles=n,
                              substeps_released=released, substeps_like_muscle=like_muscle,
                              ratio=round(released / like_muscle, 3))), flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
