"""The evolutionary recipes' runs in a few numbers (issue 44): one JSON line per run directory
(appended to --out), and the table docs/optimizers.md shows, by label and recipe over seeds.

    # the runs (cma_es, cppn_neat and hyperneat, seeds 0-2; about 6 minutes on 2 cores)
    for r in cma_es cppn_neat hyperneat; do for s in 0 1 2; do
        codesign run recipes/$r.yaml seed=$s --run-dir runs/evolution/$r-s$s; done; done
    python benchmarks/evolution_runs.py runs/evolution/* --label after --out records.jsonl
    # the code before issue 44, for comparison: git worktree add /tmp/before 50ba95b, the same runs there
    python benchmarks/evolution_runs.py --table records.jsonl
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf


def summarise(run_dir: Path, label: str) -> dict:
    """A run's recipe, budget and results: first generation's best, best, validity, time."""
    config = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"))
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    info = json.loads((run_dir / "best" / "info.json").read_text())
    horizon = config["environment"]["horizon"]
    record = {
        "label": label, "run": run_dir.name, "recipe": config["name"], "seed": config["seed"],
        "representation": config["representation"]["name"], "controller": config["controller"]["name"],
        "bias": config["controller"].get("bias"), "population": config["optimizer"].get("population"),
        "generations": len(rows), "episodes": int(sum(r["simulated_steps"] for r in rows) / horizon),
        "first_best": rows[0]["episode_return"], "best_return": info["episode_return"],
        "best_generation": info["iteration"], "torn_fraction": info.get("torn_fraction"),
        "thinnest_cells": info.get("thinnest_cells"), "wall_time": rows[-1]["wall_time"],
    }
    for key in ("valid_fraction", "full_bodies", "body_fraction"):
        if key in rows[0]:
            record[key] = float(np.mean([r[key] for r in rows]))
    return record


def table(records: list[dict]) -> str:
    """Markdown: mean +- std over seeds per (recipe, label, controller and its bias, population)."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        controller = f"sine, {r['bias'] or 'per_basis'}" if r["controller"] == "sine" else r["controller"]
        groups[(r["recipe"], r["label"], controller, r["population"])].append(r)

    def stat(rows: list[dict], key: str, fmt: str = "{:.2f}") -> str:
        values = [r[key] for r in rows if r.get(key) is not None]
        if not values:
            return "-"
        return fmt.format(np.mean(values)) + (f" +- {fmt.format(np.std(values))}" if len(values) > 1 else "")

    lines = ["| recipe | code | controller | population | seeds | episodes | first generation's best | best return | "
             "valid bodies | whole-workspace bodies | torn off | wall (s) |", "| --- " * 12 + "|"]
    for (recipe, label, controller, population), rows in sorted(groups.items(), key=lambda kv: kv[0][:2]):
        lines.append(f"| {recipe} | {label} | {controller} | {population or 'pycma'} | {len(rows)} | "
                     f"{stat(rows, 'episodes', '{:.0f}')} | {stat(rows, 'first_best')} | {stat(rows, 'best_return')} | "
                     f"{stat(rows, 'valid_fraction', '{:.0%}')} | {stat(rows, 'full_bodies', '{:.0%}')} | "
                     f"{max(r['torn_fraction'] or 0.0 for r in rows):.0%} | {stat(rows, 'wall_time', '{:.0f}')} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path, help="run directories to summarise")
    parser.add_argument("--label", default="after", help="what code made the runs (e.g. before, after)")
    parser.add_argument("--out", type=Path, help="append the records to this JSON-lines file")
    parser.add_argument("--table", type=Path, help="print the table of this JSON-lines file")
    args = parser.parse_args()
    records = [summarise(run, args.label) for run in args.runs]
    for record in records:
        print(json.dumps(record))
    if args.out is not None and records:
        with args.out.open("a", encoding="utf-8") as f:
            f.writelines(json.dumps(record) + "\n" for record in records)
    if args.table is not None:
        print(table([json.loads(line) for line in args.table.read_text().splitlines()]))


if __name__ == "__main__":
    main()
