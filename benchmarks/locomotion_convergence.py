"""Why a gait's distance does not converge with resolution (issue 22): the fixed sine gait of
`codesign bench accuracy`'s robot_ground problem on floors of several frictions, at several dx and
CFL numbers, and the same muscled box floating free (no gravity, no terrain), whose shape should
converge. Prints JSON lines (and appends them to --out); docs/contact.md reads them.

    python benchmarks/locomotion_convergence.py ground --arch cuda --out records.jsonl
    python benchmarks/locomotion_convergence.py floating
"""
from __future__ import annotations

import argparse
import json
import time

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.accuracy import gait
from codesign_mpm.config import PRESET_CONFIGS, PRESETS, RobotConfig, TerrainConfig
from codesign_mpm.engine import Simulator
from codesign_mpm.env import LocomotionEnv

FRAMES = 125  # 1 s of 8 ms control steps
RESOLUTIONS = (32, 48, 64, 96, 128)  # 1 / dx


def ground(dx: float, cfl: float, friction: float, arch: str) -> dict:
    """Distance along x after 1 s (and after 0.5 s) of the gait, on robot_ground's setup."""
    preset = PRESETS["ground"]
    config = PRESET_CONFIGS["ground"](
        dx=dx, cfl=cfl, horizon=FRAMES, arch=arch, terrain=TerrainConfig(height=0.13, friction=friction),
        robot=RobotConfig(youngs_modulus=preset.robot_youngs_modulus, position=[0.35, 0.25]))
    env = LocomotionEnv(config, preset)
    com0 = env.reset()[:3]
    t0 = time.perf_counter()
    xs = [float(env.step(gait(f, env.action_dim)).info["com"][0] - com0[0]) for f in range(FRAMES)]
    particles = env.sim.n
    env.close()
    return dict(distance=xs[-1], half=xs[FRAMES // 2], particles=particles, wall_s=time.perf_counter() - t0)


def floating(dx: float, cfl: float, arch: str) -> dict:
    """The box's spread (standard deviation of its particles along x and y) every 25 frames."""
    scene = Scene(size=[1.0, 0.5, 0.5], dx=dx, cfl=cfl, gravity=[0.0, 0.0, 0.0], arch=arch,
                  terrain=TerrainSpec(kind="none"),
                  bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.2, 0.08, 0.08]),
                                   center=[0.5, 0.25, 0.25], material=MaterialSpec(youngs_modulus=1e4),
                                   muscles=MuscleSpec(groups=[2, 2, 1]))])
    sim = Simulator(scene, build_particles(scene))
    spread = []
    for f in range(FRAMES):
        sim.step(gait(f, sim.n_actuators))
        if f % 25 == 0 or f == FRAMES - 1:
            x = sim.particles_state()[0]
            spread.append((float(x[:, 0].std()), float(x[:, 1].std())))
    sim.close()
    return dict(std_x=[s[0] for s in spread], std_y=[s[1] for s in spread])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", choices=["ground", "floating"])
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--frictions", type=float, nargs="+", default=[0.0, 0.5, 5.0])
    parser.add_argument("--cfls", type=float, nargs="+", default=[0.4, 0.1])
    parser.add_argument("--out", default=None, help="also append the records to this file")
    args = parser.parse_args()
    runs = ([dict(friction=mu, cfl=cfl) for mu in args.frictions for cfl in args.cfls] if args.study == "ground"
            else [dict(cfl=cfl) for cfl in args.cfls])
    for run in runs:
        for n in RESOLUTIONS:
            measured = (ground(1 / n, run["cfl"], run["friction"], args.arch) if args.study == "ground"
                        else floating(1 / n, run["cfl"], args.arch))
            record = json.dumps(dict(study=args.study, dx=f"1/{n}", **run, **measured))
            print(record, flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(record + "\n")


if __name__ == "__main__":
    main()
