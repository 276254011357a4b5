"""cppn_neat on a tiny crawler: NEAT (design) and CMA-ES (control) improve on their first
population within a few generations, and the best design and controller replay to the same return.

Measured (8 generations of 8, horizon 10, muscles at 0.4 E, the strongest admissible): first
generation's best -> best after 8, and mean return of the first generation -> mean over the last
four: seed 0: 0.010 -> 0.310, -0.016 -> 0.099; seed 1: 0.240 -> 0.311, 0.065 -> 0.086; seed 2:
0.069 -> 0.100, 0.007 -> 0.015.
"""
import json

import numpy as np
import pytest

from codesign import runner
from codesign.recipe import resolve_recipe

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("seed", [0, 1])
def test_cppn_neat_improves_on_its_first_population_and_its_best_replays(seed, tmp_path):
    recipe = {
        "name": "crawler-neat", "seed": seed,
        "environment": {"name": "ground", "dx": 1 / 32, "horizon": 10,
                        "terrain": {"height": 0.1, "friction": 0.5},
                        "robot": {"size": [0.16, 0.08, 0.08], "muscle_stiffness_ratio": 0.4}},
        "representation": {"name": "neat_cppn"},
        "controller": {"name": "sine", "init_std": 1.0},
        "optimizer": {"name": "cppn_neat", "generations": 8, "population": 8, "sigma0": 0.3},
    }
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["best_return"] > rows[0]["episode_return"] + 0.05
    # each generation's champion, not only the best so far, is better late than first (the population's
    # mean is too noisy to test at 8 x 8: new species enter at every generation)
    assert np.mean([r["episode_return"] for r in rows[-4:]]) > rows[0]["episode_return"] + 0.015
    info = json.loads((run_dir / "best" / "info.json").read_text())
    assert info["episode_return"] == rows[-1]["best_return"] and (run_dir / "best" / "genome.pkl").exists()
    # deterministic task; the generation played in one batch, which sums atomics in another order (float32)
    assert runner.evaluate_best(run_dir) == pytest.approx([info["episode_return"]], rel=1e-4)
