"""Table 2's starting designs under a held-out gait, and the recipe of a gait trained on another fish.

Tables 2 and 3 fix a sine gait trained on the library fish (the `representations` study's
preparatory run, with the particle representation, so the fish's passive fins move with the mean
of its four actions). Whether that choice decides the tables shows in where each arm starts: this
plays every arm's starting design (iteration 0, each of its seeds) under a given gait and prints
one JSON line per start.

    python benchmarks/fish_gait_starts.py recipe fixed > fish_fixed.yaml   # the preparatory recipe, representation fixed
    codesign run fish_fixed.yaml --run-dir runs/fish-gait-fixed
    python benchmarks/fish_gait_starts.py starts runs/fish-gait-fixed
    python benchmarks/fish_gait_starts.py starts studies/representations/prepare
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

import yaml  # noqa: E402

from codesign.artifacts import load_controller, play  # noqa: E402
from codesign.recipe import merge_recipes, resolve_recipe  # noqa: E402
from codesign.runner import set_up_parts  # noqa: E402
from codesign.study import arm_recipe, arm_seeds, load_study, prepare_recipe  # noqa: E402

STUDY = "representations"


def gait_recipe(representation: str) -> dict:
    """The study's preparatory run with its representation replaced (e.g. fixed: the fish as labelled)."""
    return merge_recipes(prepare_recipe(load_study(STUDY)), {
        "representation": {"name": representation}, "name": f"{STUDY}-prepare-{representation}",
        "tracking": {"wandb": False}})


def starts(gait: Path) -> None:
    study = load_study(STUDY)
    for arm in study.arms:
        for seed in arm_seeds(study, arm):
            data = {**arm_recipe(study, arm), "seed": seed, "tracking": {"wandb": False}}
            data.pop("sweep")
            data.pop("init_controller", None)
            with set_up_parts(resolve_recipe(data)) as (parts, _):
                load_controller(gait, parts.controller)
                record = play(parts.environment, parts.representation(), parts.controller, seed=0)
            print(json.dumps({"gait": str(gait), "arm": arm.label, "seed": seed,
                              "per_step": record.episode_return / record.length,
                              "torn": record.metrics.get("torn_fraction")}), flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("recipe", "starts"):
        sys.exit(__doc__)
    if sys.argv[1] == "recipe":
        print(yaml.safe_dump(gait_recipe(sys.argv[2]), sort_keys=False))
    else:
        starts(Path(sys.argv[2]))
