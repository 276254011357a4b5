"""Do a recipe's gradients point the same way at every number of substeps (issue 47, item 2)?
The quick start's design and control gradients (its differentiable episode from the starting
parameters of each seed) at the CFL number of the recipe and at a quarter and a sixteenth of it,
for each contact and PIC setting; prints one JSON line per (seed, setting) with the cosine between
the gradients at cfl and cfl / 4 and at cfl / 4 and cfl / 16, per parameter group.

    python benchmarks/contact_gradients.py --seeds 0 1 2 --out records.jsonl
    python benchmarks/contact_gradients.py --settings "spring, pic_time" --recipe recipes/ice.yaml
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from contact_steps import FACTORS, SETTINGS, emit

from codesign.recipe import load_recipe
from codesign.runner import set_up_parts
from codesign_optimizers.common import parameter_groups


def gradients(recipe: Path, seed: int, cfl: float, contact: str, pic_time: float | None) -> tuple[float, dict]:
    """The episode's return and its gradient per parameter group (flattened) at `cfl`."""
    overrides = [f"seed={seed}", f"environment.cfl={cfl}", f"environment.terrain.contact={contact}",
                 f"environment.pic_time={'null' if pic_time is None else pic_time}"]
    with set_up_parts(load_recipe(recipe, overrides)) as (parts, _):
        groups = parameter_groups("both", parts.representation, parts.controller)
        episode = parts.environment.differentiable_episode(parts.representation(), parts.controller)
        episode.loss.backward()
        flat = {name: torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).flatten()
                                 for p in params]).double().numpy() for name, params in groups.items()}
        return episode.episode_return, flat


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", type=Path, default=Path("recipes/quickstart.yaml"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--settings", nargs="+", default=["nodes", "spring, pic_time"], choices=list(SETTINGS))
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    cfl = load_recipe(args.recipe, []).sections["environment"].config.cfl or 0.4
    for seed in args.seeds:
        for label in args.settings:
            started = time.perf_counter()
            runs = [gradients(args.recipe, seed, cfl * f, *SETTINGS[label]) for f in FACTORS]
            emit({"recipe": str(args.recipe), "seed": seed, "setting": label, "cfl_factors": list(FACTORS),
                  "returns": [r for r, _ in runs],
                  "cosine_quarter": {g: cosine(runs[0][1][g], runs[1][1][g]) for g in runs[0][1]},
                  "cosine_sixteenth_from_quarter": {g: cosine(runs[1][1][g], runs[2][1][g]) for g in runs[0][1]},
                  "norms": {g: [float(np.linalg.norm(r[1][g])) for r in runs] for g in runs[0][1]},
                  "seconds": round(time.perf_counter() - started, 1)}, args.out)


if __name__ == "__main__":
    main()
