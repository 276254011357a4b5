"""The table of docs/integrity.md: each run's best episode replayed at its own settings and with
the CFL number divided by 4, with the body's integrity.

Run from the repository root after running the recipes, e.g.
``codesign run recipes/quickstart.yaml --run-dir runs/check/quickstart`` (and the others), then
``python docs/check_recipes.py runs/check/*``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from codesign.runner import load_run_data, replay_best


def replay(run_dir: Path, cfl_factor: float = 1.0):
    """The best design and controller of `run_dir` for one episode, with cfl x `cfl_factor` (what
    `codesign eval RUN_DIR environment.cfl=...` prints)."""
    _, recipe = load_run_data(run_dir)
    cfl = recipe.sections["environment"].config.cfl * cfl_factor
    return replay_best(run_dir, 1, {"environment": {"cfl": cfl}})[0]


def main(run_dirs: list[str]) -> None:
    print("| recipe | best return | torn-off mass | thinnest part (cells) | return at cfl / 4 |")
    print("| --- | --- | --- | --- | --- |")
    for run_dir in map(Path, run_dirs):
        at, quarter = replay(run_dir), replay(run_dir, 0.25)
        torn = max(at.metrics["torn_fraction"], quarter.metrics["torn_fraction"])
        change = 100 * (quarter.episode_return - at.episode_return) / abs(at.episode_return)
        print(f"| `{run_dir.name}` | {at.episode_return:.3g} | {100 * torn:.2g}% | "
              f"{at.metrics['thinnest_cells']:.3g} | {quarter.episode_return:.3g} ({change:+.0f}%) |")


if __name__ == "__main__":
    main(sys.argv[1:])
