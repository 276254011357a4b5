"""Forward speed where a substep's fixed cost shows (issue 48): `codesign bench engine`'s tiny
(1,024 particles, dx 1/32) and small (7,200, dx 1/64) scenes' forward particle-substeps/s
(medians of 9), and the median wall time of the quick start's forward episode (40 control steps,
what evaluate, CMA-ES and NEAT play per candidate). Prints one JSON line labelled with the first
argument; to compare two commits, run it alternately in a checkout of each (the same machine,
the same minutes) and compare the ratios:

    python benchmarks/forward_rates.py before     # in the older checkout
    python benchmarks/forward_rates.py after      # in the newer one; repeat both
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from codesign.artifacts import play
from codesign.recipe import load_recipe
from codesign.runner import set_up_parts
from codesign_mpm.reports.bench import Case, measure_forward


def quickstart_episode_s(repeats: int = 7) -> float:
    with set_up_parts(load_recipe("recipes/quickstart.yaml", [])) as (parts, _):
        env, design = parts.environment, parts.representation()
        play(env, design, parts.controller, seed=0)  # compiles (or loads from the offline cache)
        times = []
        for _ in range(repeats):
            started = time.perf_counter()
            play(env, design, parts.controller, seed=0)
            times.append(time.perf_counter() - started)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("variant", nargs="?", default="this checkout", help="the label of this checkout's line")
    record = {"variant": parser.parse_args().variant}
    for scale, frames in (("tiny", 40), ("small", 10)):
        record[scale] = measure_forward(Case(scale, "float32"), repeats=9, frames=frames)["particle_substeps_per_s"]
    record["quickstart_episode_s"] = quickstart_episode_s()
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
