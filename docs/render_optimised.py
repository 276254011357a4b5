"""Optimise each representation's design with the quick start's co-design and draw the best one.

Run from the repository root: ``python docs/render_optimised.py [NAME ...]`` (about a minute
and a half per representation on 2 cores; default: all). For each gradient-based representation it runs the quick start's
recipe (ground, 40 control steps, design and gait by Adam) at dx 1/48 (the quick start's 1/32
leaves the 0.08-high workspace 2.6 cells thick: some first designs hold no part 2 cells thick)
for 12 iterations, with that representation in its default configuration (the primitive blends
in a 0.3 x 0.15 x 0.15 workspace: their slender fish are under 2 cells thick in the quick
start's 0.2 x 0.08 x 0.08), and for `neat_cppn`
the `cppn_neat` recipe; then `codesign render --still` draws each run's best design to
docs/images/designs/optimised_NAME.png, each run's best episode and returns go to
docs/data/designs-optimised.jsonl, and the table of best returns, torn-off mass and thinnest part
is printed for docs/designs.md (a run that fails is listed with its error). ``--runs DIR`` keeps
the runs, to replay and render them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

from codesign.runner import read_metrics

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "images" / "designs"
DATA = ROOT / "docs" / "data" / "designs-optimised.jsonl"  # each run's best episode and its returns
GRADIENT_BASED = ["particle", "voxel", "implicit", "diff_cppn", "sdf_lerp", "wasserstein"]
PRIMITIVE_BLENDS = ("sdf_lerp", "wasserstein")
CODESIGN = str(Path(sys.executable).parent / "codesign")  # the command of this environment


def recipe_for(name: str) -> dict:
    recipe = yaml.safe_load((ROOT / "recipes" / "quickstart.yaml").read_text())
    recipe["name"] = f"optimised_{name}"
    recipe["representation"] = {"name": name}
    recipe["environment"]["dx"] = 1 / 48
    if name in PRIMITIVE_BLENDS:
        recipe["environment"]["robot"]["size"] = [0.3, 0.15, 0.15]
    recipe["optimizer"]["iterations"] = 12
    return recipe


def run(recipe: Path, run_dir: Path) -> dict | str:
    """The run's best/info.json, or the error it stopped with; a completed run in `run_dir` is kept."""
    summary = run_dir / "summary.json"
    if summary.exists() and json.loads(summary.read_text())["status"] == "completed":
        return json.loads((run_dir / "best" / "info.json").read_text())
    done = subprocess.run([CODESIGN, "run", str(recipe), "--run-dir", str(run_dir), "--no-progress"],
                          capture_output=True, text=True)
    if done.returncode:
        return done.stderr.strip().splitlines()[-1]
    return json.loads((run_dir / "best" / "info.json").read_text())


def main(names: list[str], runs: Path | None = None) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = runs or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        jobs = []
        for name in GRADIENT_BASED:
            path = Path(tmp) / f"{name}.yaml"
            path.write_text(yaml.safe_dump(recipe_for(name)))
            jobs.append((name, path))
        jobs.append(("neat_cppn", ROOT / "recipes" / "cppn_neat.yaml"))
        jobs = [(name, path) for name, path in jobs if not names or name in names]
        for name, recipe in jobs:
            run_dir = root / f"run_{name}"
            info = run(recipe, run_dir)
            if isinstance(info, dict):
                subprocess.run([CODESIGN, "render", str(run_dir), "--still", str(OUT / f"optimised_{name}.png"),
                                "--camera", "oblique", "--no-progress"], check=True)
                metrics = read_metrics(run_dir / "metrics.jsonl")
                info = dict(info, returns=[row.get("episode_return") for row in metrics],  # None: not played
                            wall_s=round(metrics[-1]["wall_time"], 1))
            rows.append((name, info))
    records = {}  # the representations not run this time keep their records
    if DATA.exists():
        records = {row["representation"]: row for row in map(json.loads, DATA.read_text().splitlines())}
    for name, info in rows:
        records[name] = {"representation": name, **(info if isinstance(info, dict) else {"error": info})}
    DATA.write_text("".join(json.dumps(records[name]) + "\n" for name in [*GRADIENT_BASED, "neat_cppn"]
                            if name in records))
    print("| representation | best return | torn off | thinnest part (cells) |\n| --- | --- | --- | --- |")
    for name, info in rows:
        if isinstance(info, str):
            print(f"| {name} | failed: {info} | | |")
        else:
            print(f"| {name} | {info['episode_return']:.3g} | {info['torn_fraction']:.0%} | {info['thinnest_cells']:g} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="representations (default: all)")
    parser.add_argument("--runs", type=Path, help="keep the runs here (default: a temporary folder)")
    arguments = parser.parse_args()
    main(arguments.names, arguments.runs)
