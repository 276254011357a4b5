"""How much of each library animal is muscle, and how much of it the grid carries thinly.

For each animal fitted to Table 1's size (0.3 x 0.15 x 0.15) at the `cpu` scale's dx (1/64) and the
paper's (1/128): its particles, the share in muscle groups, each group's count, and per group the
particles in parts thinner than 2 grid cells (`integrity.thinnest_cells`' measure, the thickness the
grid carries without tearing). Prints one JSON line per animal and dx; sampling only, no simulation.

    python benchmarks/body_muscles.py > docs/data/bodies-2026-11-28-muscles.jsonl
"""

from __future__ import annotations

import json
import warnings

import numpy as np

from codesign.bodies import ANIMALS
from codesign_mpm import BodySpec, Scene, build_particles
from codesign_mpm.scene.integrity import thick_enough
from codesign_mpm.scene.spec import MuscleSpec, ShapeSpec

SIZE = [0.3, 0.15, 0.15]
PARTICLES_PER_AXIS = 2  # 8 particles per cell, as every body of the studies


def measure(animal: str, dx: float) -> dict:
    scene = Scene(size=[1.0, 0.5, 0.5], dx=dx, bodies=[BodySpec(
        center=[0.5, 0.2, 0.25], shape=ShapeSpec(kind="body", body=animal, size=SIZE),
        muscles=MuscleSpec(layout="body"))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the thin-part warning: measured below instead
        particles = build_particles(scene)
    x = particles.x.astype(np.float64)
    thin = ~thick_enough(x, np.ones(len(x), dtype=bool), dx / PARTICLES_PER_AXIS, dx)
    active = particles.muscle.max(1) > 0
    group = np.where(active, particles.muscle.argmax(1), -1)
    groups = range(particles.muscle.shape[1])
    return dict(animal=animal, dx=dx, particles=len(x), muscle_share=round(float(active.mean()), 4),
                group_particles=[int((group == g).sum()) for g in groups],
                group_thin_particles=[int((thin & (group == g)).sum()) for g in groups],
                passive_particles=int((~active).sum()), passive_thin_particles=int((thin & ~active).sum()))


if __name__ == "__main__":
    for name in ANIMALS:
        for grid in (1 / 64, 1 / 128):
            print(json.dumps(measure(name, grid)), flush=True)
