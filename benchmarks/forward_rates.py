"""Forward speed where a substep's fixed cost shows (issue 48): `codesign bench engine`'s tiny
(about 1k particles, dx 1/32) and small (about 7.7k, dx 1/64) scenes' forward particle-substeps/s
(medians of 9), and the median wall time of the quick start's forward episode (40 control steps,
what evaluate, CMA-ES and NEAT play per candidate). Prints one JSON line labelled with the first
argument; to compare two commits, run it alternately in a checkout of each (the same machine,
the same minutes) and compare the ratios:

    python benchmarks/forward_rates.py before     # in the older checkout
    python benchmarks/forward_rates.py after      # in the newer one; repeat both
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from codesign.artifacts import play
from codesign.recipe import load_recipe
from codesign.runner import build_parts
from codesign_mpm.bench import Case, measure_forward


def quickstart_episode_s(repeats: int = 7) -> float:
    parts = build_parts(load_recipe("recipes/quickstart.yaml", []))
    env = parts.environment
    rng = np.random.default_rng(0)
    parts.representation.setup(env.design_space, rng)
    parts.controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
    design = parts.representation()
    play(env, design, parts.controller, seed=0)  # compiles (or loads from the offline cache)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        play(env, design, parts.controller, seed=0)
        times.append(time.perf_counter() - started)
    env.close()
    return float(np.median(times))


def main() -> None:
    record = {"variant": sys.argv[1] if len(sys.argv) > 1 else "this checkout"}
    for scale, frames in (("tiny", 40), ("small", 10)):
        record[scale] = measure_forward(Case(scale, "float32"), repeats=9, frames=frames)["particle_substeps_per_s"]
    record["quickstart_episode_s"] = quickstart_episode_s()
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
