"""One cell of Table 1 (`codesign study benchmark`) at a scale, timed on a fraction of its budget
(issue 48 item 4): the arm's own recipe with diff-physics cut to a few iterations and PPO to a few
rollouts, each run once; prints one JSON line per arm with the seconds per iteration or per
environment step after the first (which compiles) and the arm's whole budget extrapolated from it:

    python benchmarks/paper_cell.py --scale paper                        # on a GPU (the paper scale sets arch: cuda)
    python benchmarks/paper_cell.py --scale cpu --env Ground --task "Movement speed"

Needs the project's dependencies except wandb (runs are tracked to their metrics.jsonl only).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from codesign.recipe import resolve_recipe
from codesign.runner import run
from codesign.study import arm_recipe, arm_seeds, load_study


def timed_run(recipe: dict, directory: Path) -> list[float]:
    """Run `recipe` in `directory`: its whole wall time, then the wall time at which each
    iteration ended (metrics.jsonl)."""
    started = time.perf_counter()
    run(resolve_recipe({**recipe, "tracking": {**recipe.get("tracking", {}), "wandb": False}}),
        run_dir=directory, progress=False)
    ends = [json.loads(line)["wall_time"] for line in (directory / "metrics.jsonl").read_text().splitlines()]
    return [time.perf_counter() - started, *ends]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", default="paper")
    parser.add_argument("--task", default="Movement speed")
    parser.add_argument("--animal", default="Baby seal")
    parser.add_argument("--env", default="Ground")
    parser.add_argument("--iterations", type=int, default=3, help="diff-physics iterations run (the first compiles)")
    parser.add_argument("--rollouts", type=int, default=3, help="PPO rollouts run (the first compiles)")
    args = parser.parse_args()
    study = load_study("benchmark", args.scale)
    cell = f"{args.task} / {args.animal} / {args.env} / "
    arms = [arm for arm in study.arms if arm.label.startswith(cell)]
    if not arms:
        raise SystemExit(f"no arm {cell}...: the arms at scale {args.scale} are {[a.label for a in study.arms]}")
    with tempfile.TemporaryDirectory() as scratch:
        for arm in arms:
            recipe = arm_recipe(study, arm, Path(scratch))
            recipe.pop("sweep")
            recipe = resolve_recipe(recipe).data  # the optimizer's defaults filled in
            optimizer = dict(recipe["optimizer"])
            if optimizer["name"] == "diff_physics":
                budget, unit = optimizer["iterations"], "iteration"
                optimizer["iterations"] = args.iterations
            else:
                steps = optimizer["timesteps_per_iteration"]
                budget, unit = optimizer["total_timesteps"], "environment step"
                optimizer["total_timesteps"] = args.rollouts * steps
            wall, *ends = timed_run({**recipe, "optimizer": optimizer, "seed": arm_seeds(study, arm)[0]},
                                    Path(scratch) / arm.slug)
            per_iteration = (ends[-1] - ends[0]) / max(len(ends) - 1, 1)
            per_unit = per_iteration if unit == "iteration" else per_iteration / steps
            seeds = len(arm_seeds(study, arm))
            print(json.dumps({
                "arm": arm.label, "scale": args.scale, "arch": recipe["environment"].get("arch", "cpu"),
                "horizon": recipe["environment"]["horizon"], "unit": unit, "seconds_per_unit": per_unit,
                "first_iteration_s": ends[0], "run_wall_s": wall, "budget_units": budget, "seeds": seeds,
                "arm_hours": per_unit * budget * seeds / 3600}), flush=True)


if __name__ == "__main__":
    main()
