"""What PPO learns on one cell of Table 1 at other budgets (issue 49): the benchmark study's PPO arm
(the sine controller, the paper's hyperparameters) written as a recipe with changed optimizer keys,
and finished runs summarised as JSON lines (each iteration's per-step return).

    python benchmarks/ppo_budget.py --recipe "Movement speed / Baby seal / Ground / PPO" \\
        total_timesteps=30000 timesteps_per_iteration=3000 > ppo-30k.yaml
    codesign run ppo-30k.yaml --run-dir runs/ppo/30k
    python benchmarks/ppo_budget.py runs/ppo/* --out records.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml
from omegaconf import OmegaConf


def recipe(label: str, changes: list[str]) -> dict:
    """The benchmark study's arm `label` at the cpu scale, one run (no sweep), optimizer keys changed."""
    from codesign.study import arm_recipe, load_study

    study = load_study("benchmark")
    arms = {arm.label: arm for arm in study.arms}
    if label not in arms:
        sys.exit(f"no arm {label!r}; the cpu scale's arms: {', '.join(arms)}")
    data = arm_recipe(study, arms[label])
    data.pop("sweep")
    for change in changes:
        key, _, value = change.partition("=")
        data["optimizer"][key] = yaml.safe_load(value)
    data["name"] = "ppo-budget"
    return data


def summarise(run_dir: Path) -> dict:
    config = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"))
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    horizon = config["environment"]["horizon"]
    optimizer = config["optimizer"]
    return {"run": run_dir.name, "seed": config["seed"], "body": config["environment"]["robot"]["body"],
            "environment": config["environment"]["name"], "task": config["environment"]["task"]["name"],
            **{k: optimizer[k] for k in ("policy", "total_timesteps", "n_steps", "batch_size", "n_epochs",
                                         "learning_rate")},
            "per_step": [r["episode_return"] / horizon for r in rows], "wall_time": rows[-1]["wall_time"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--recipe", help="print the recipe of this arm of the benchmark study, then KEY=VALUE "
                                         "changes to its optimizer as the runs")
    parser.add_argument("--out", type=Path, help="append the runs' records here (else print them)")
    args = parser.parse_args()
    if args.recipe:
        print(yaml.safe_dump(recipe(args.recipe, [str(r) for r in args.runs]), sort_keys=False), end="")
        return
    lines = "".join(json.dumps(summarise(run)) + "\n" for run in args.runs)
    if args.out:
        with open(args.out, "a", encoding="utf-8") as f:
            f.write(lines)
    else:
        print(lines, end="")


if __name__ == "__main__":
    main()
