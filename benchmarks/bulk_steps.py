"""Is an elastic body's own motion consistent in time, with no contact and no muscle (issue 47)?
A free box (the quick start's: 0.2 x 0.08 x 0.08, E 1e4), gravity 0 and no terrain, started with a
bending velocity field, for 1 s at the CFL number 0.4 and at a quarter and a sixteenth of it; per
dx, prints one JSON line: its kinetic energy and how far its shapes at cfl and cfl / 4, and at
cfl / 4 and cfl / 16, lie apart (RMS over particles about the centroid, after the best rotation, mm).
docs/log/contact.md section 27 reads them.

    python benchmarks/bulk_steps.py --dx 0.03125 0.0208333333333 --pic-time 0.265 --out records.jsonl
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from contact_steps import FACTORS, _rotated_onto, emit

from codesign_mpm import BodySpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator
from codesign_mpm.scene.spec import MaterialSpec

FRAMES = (15, 30, 60, 124)


def free_vibration(dx: float, cfl: float, pic_time: float | None, frames: int = 125) -> tuple[np.ndarray, list[float]]:
    """(frames, N, 3) the box's particles about their centroid, and its kinetic energy per frame."""
    scene = Scene(size=[1.0, 0.5, 0.5], dx=dx, cfl=cfl, flip=0.99, pic_time=pic_time, gravity=[0.0, 0.0, 0.0],
                  terrain=TerrainSpec(kind="none"),
                  bodies=[BodySpec(shape=ShapeSpec(kind="box", size=[0.2, 0.08, 0.08]), center=[0.5, 0.25, 0.25],
                                   material=MaterialSpec(youngs_modulus=1e4, poisson_ratio=0.2, density=1000.0))])
    particles = build_particles(scene)
    sim = Simulator(scene, particles)
    try:
        v0 = np.zeros_like(particles.x)
        v0[:, 1] = 0.1 * np.cos(np.pi * (particles.x[:, 0] - 0.5) / 0.2)  # the first bending mode's shape
        v0[:, 1] -= v0[:, 1].mean()
        sim.set_initial_state(v=v0)
        mass = particles.volume * particles.density
        shapes, energy = [], []
        for _ in range(frames):
            sim.step()
            x, v = (a.astype(np.float64) for a in sim.particles_state()[:2])
            shapes.append(x - x.mean(0))
            energy.append(float(0.5 * mass @ (v ** 2).sum(1)))
        return np.array(shapes), energy
    finally:
        sim.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dx", type=float, nargs="+", default=[1 / 32])
    parser.add_argument("--pic-time", type=float, default=None, help="the PIC share as a time (default: per substep)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    for dx in args.dx:
        runs = [free_vibration(dx, 0.4 * f, args.pic_time) for f in FACTORS]

        def apart_mm(a: np.ndarray, b: np.ndarray) -> list[float]:
            return [round(1e3 * float(np.sqrt(((a[i] - _rotated_onto(a[i], b[i])) ** 2).sum(1).mean())), 3)
                    for i in FRAMES]

        emit({"source": f"free box, bending, dx {dx:.4g}", "pic_time": args.pic_time, "cfl_factors": list(FACTORS),
              "frames": list(FRAMES), "apart_quarter_mm": apart_mm(runs[0][0], runs[1][0]),
              "apart_sixteenth_mm": apart_mm(runs[1][0], runs[2][0]),
              "kinetic_energy_mJ": [[round(1e3 * r[1][i], 5) for i in FRAMES] for r in runs]}, args.out)


if __name__ == "__main__":
    main()
