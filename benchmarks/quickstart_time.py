"""The quick start's wall time, checkout against checkout, alternated.

Runs the README's main job (`codesign run recipes/quickstart.yaml`, 20 diff-physics iterations) in
each checkout given as NAME=PATH, round after round, alternating, so that two variants share the
machine's state; each run is a fresh process (imports, loading the compiled kernels, the first
episode: what a user waits for). Run each checkout once beforehand so that Taichi's kernel cache
holds its kernels. Prints one JSON line per run:

    python benchmarks/quickstart_time.py --rounds 3 before=/tmp/before after=. > runs.jsonl

The command's wall time, the first iteration's (loading the kernels, the first episode) and the
median of the others come from the run's own metrics.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def one_run(checkout: Path) -> dict:
    """Run the quick start from `checkout`'s code (its package and plugins first on the path)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), str(checkout / "plugins")]),
           "ENABLE_TAICHI_HEADER_PRINT": "0"}
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "codesign", "run", str(checkout / "recipes" / "quickstart.yaml"),
                        "--run-dir", str(run_dir), "--no-progress"], env=env, check=True, cwd=tmp,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
        summary = json.loads((run_dir / "summary.json").read_text())
    ends = [row["wall_time"] for row in rows]
    return {"wall_s": round(wall, 2), "best_return": summary["best"]["episode_return"],
            "first_iteration_s": round(ends[0], 2),
            "per_iteration_s": round(statistics.median(b - a for a, b in zip(ends, ends[1:])), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkouts", nargs="+", help="NAME=PATH of a checkout of this repository")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    variants = [(name, Path(path).resolve()) for name, _, path in (c.partition("=") for c in args.checkouts)]
    commits = {name: subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], text=True,
                                    capture_output=True, check=True).stdout.strip() for name, checkout in variants}
    for repeat in range(1, args.rounds + 1):
        for name, checkout in variants:
            print(json.dumps({"variant": name, "repeat": repeat, **one_run(checkout), "commit": commits[name]}),
                  flush=True)


if __name__ == "__main__":
    main()
