"""Does a gait's distance converge with resolution (issue 22)? The fixed gait of `codesign bench
accuracy`'s robot_ground problem on floors of several frictions, at several dx and CFL numbers;
the same muscled box floating free (no gravity, no terrain), whose shape should converge; and
whether random gaits rank the same at the quality presets (Spearman's rho of their distances);
the report's reference setting at finer grids (reference); and the terrain's surface moved within
one cell (offsets). `--contact surface` measures the same with the terrain's surface contact; `--start stress-free` with
the robot starting stress-free (it lands and sags in the first frames) instead of at rest.
Prints JSON lines (and appends them to --out); docs/log/contact.md reads them.

    python benchmarks/locomotion_convergence.py ground --arch cuda --out records.jsonl
    python benchmarks/locomotion_convergence.py floating
    python benchmarks/locomotion_convergence.py ranking --gaits 5
    python benchmarks/locomotion_convergence.py ranking --environment desert --presets paper --gaits 24 --arch cuda
    python benchmarks/locomotion_convergence.py reference --environment desert --resolutions 64 96 128 --arch cuda
    python benchmarks/locomotion_convergence.py offsets --resolutions 48 96 --frictions 0.5 5
    python benchmarks/locomotion_convergence.py offsets --resolutions 32 48 --frictions 0.5 --contact surface
    python benchmarks/locomotion_convergence.py offsets --environment desert --resolutions 64 --frictions 0.5 --fine
"""
from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Iterator

import numpy as np
from scipy.stats import spearmanr

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.reports.accuracy import Setting, gait, measure_robot, robot_env
from codesign_mpm.engine import Simulator

FRAMES = 125  # 1 s of 8 ms control steps
RESOLUTIONS = (32, 48, 64, 96, 128)  # 1 / dx


def fine(n: int) -> Setting:
    """The accuracy report's reference setting (27 particles per cell, CFL 0.2, float64) at dx 1/n."""
    return Setting(dx=1 / n, particles_per_cell=27, cfl=0.2, dtype="float64")


def ground(setting: Setting, friction: float, arch: str, actions=gait, terrain_height: float = 0.13,
           contact: str = "nodes", settled: bool = True, environment: str = "ground") -> dict:
    """Distance along x after 1 s (and after 0.5 s) of a gait (`actions(frame, k)`), on robot_ground's setup
    (`environment` desert: robot_desert's, the sand laid on that terrain)."""
    env = robot_env(environment, setting, FRAMES, friction=friction, arch=arch, terrain_height=terrain_height,
                    contact=contact, settled=settled)
    record = walk(env, actions)
    env.close()
    return record


def walk(env, actions) -> dict:
    """One episode of `env` (reset first) driven by `actions(frame, k)`: its distance along x."""
    com0 = env.reset()[:3]
    t0 = time.perf_counter()
    xs = [float(env.step(actions(f, env.action_dim)).info["com"][0] - com0[0]) for f in range(FRAMES)]
    return dict(distance=xs[-1], half=xs[FRAMES // 2], particles=env.sim.n, wall_s=time.perf_counter() - t0)


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


def random_gait(seed: int):
    """A sine gait at the action bound with a random frequency (2 to 6 Hz) and random phases."""
    rng = np.random.default_rng(seed)
    hz, phases = rng.uniform(2.0, 6.0), rng.uniform(0.0, 2 * math.pi, 4)
    return lambda frame, k: 0.3 * np.sin(2 * math.pi * hz * frame * 8e-3 + phases)[:k]


PRESETS = ("draft", "default", "paper")


def ranking(seeds: range, arch: str, contact: str, settled: bool, environment: str = "ground",
            presets: tuple[str, ...] = PRESETS) -> Iterator[dict]:
    """Each random gait's distance at each preset, one record per gait as it is measured (so the
    presets or the seeds can be split between machines), then Spearman's rho between the presets'
    rankings (`spearman_records`)."""
    from codesign_mpm.reports.accuracy import preset_setting
    from codesign_mpm.scene.quality import QUALITY

    distances = {}
    for name in presets:
        env = robot_env(environment, preset_setting(QUALITY[name]), FRAMES, arch=arch,
                        contact=contact, settled=settled)  # one per preset: its rest is found once
        distances[name] = []
        for seed in seeds:
            record = walk(env, random_gait(seed))
            distances[name].append(record["distance"])
            yield dict(environment=environment, preset=name, seed=seed, arch=arch, **record)
        env.close()
    yield from spearman_records(distances)


def spearman_records(distances: dict[str, list[float]]) -> list[dict]:
    """Spearman's rho between each pair of presets' distances (the same gaits, in the same order)."""
    names = list(distances)
    return [dict(spearman=f"{a}-{b}", rho=float(spearmanr(distances[a], distances[b]).statistic),
                 gaits=len(distances[a]))
            for i, a in enumerate(names) for b in names[i + 1:]]


def reference(environment: str, n: int, arch: str, seconds: float, contact: str, settled: bool) -> dict:
    """`codesign bench accuracy`'s robot problem at its reference setting (27 particles per cell,
    CFL 0.2, float64) at dx 1/n: is the report's reference converged (do the two finest agree)?"""
    t0 = time.perf_counter()
    record = measure_robot(environment, arch, contact, settled)(fine(n), dict(seconds=seconds))
    return dict(environment=environment, distance=record["value"], particles=record["particles"],
                substeps_per_frame=record["substeps_per_frame"], process_s=time.perf_counter() - t0)


def offsets(n: int, friction: float, fractions: list[float], arch: str, at_reference: bool, contact: str,
            settled: bool, environment: str = "ground") -> dict:
    """The gait's distance with the terrain's surface at (floor(0.13 n) + f) / n for each fraction f
    of a cell: how much where the surface falls between node layers moves it (docs/log/contact.md
    section 13). `at_reference`: at the accuracy report's reference setting (`fine`)."""
    setting = fine(n) if at_reference else Setting(dx=1 / n)
    distances = [ground(setting, friction, arch, terrain_height=(math.floor(0.13 * n) + f) / n,
                        contact=contact, settled=settled, environment=environment)["distance"] for f in fractions]
    mean = float(np.mean(distances))
    return dict(environment=environment, setting=setting.label(), friction=friction, fractions=fractions,
                distances=distances, mean=mean, half_range_over_mean=(max(distances) - min(distances)) / 2 / abs(mean))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", choices=["ground", "floating", "ranking", "reference", "offsets"])
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.05, 0.25, 0.5, 0.75],
                        help="offsets: where the surface falls within a cell")
    parser.add_argument("--fine", action="store_true", help="offsets: at the reference setting (27 ppc, f64)")
    parser.add_argument("--environment", default="ground", choices=["ground", "desert"],
                        help="ranking, reference, offsets: which robot problem")
    parser.add_argument("--resolutions", type=int, nargs="+", default=list(RESOLUTIONS), help="1 / dx")
    parser.add_argument("--seconds", type=float, default=1.0, help="reference: simulated time")
    parser.add_argument("--gaits", type=int, default=5, help="ranking: random gaits to rank")
    parser.add_argument("--first-seed", type=int, default=0, help="ranking: the first gait's seed")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS),
                        help="ranking: the quality presets to rank at")
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--contact", default="nodes", choices=["nodes", "surface"], help="the terrain's contact")
    parser.add_argument("--start", default="settled", choices=["settled", "stress-free"],
                        help="the robot at rest under its weight (as the accuracy report) or stress-free")
    parser.add_argument("--frictions", type=float, nargs="+", default=[0.0, 0.5, 5.0])
    parser.add_argument("--cfls", type=float, nargs="+", default=[0.4, 0.1])
    parser.add_argument("--out", default=None, help="also append the records to this file")
    args = parser.parse_args()
    settled = args.start == "settled"
    def emit(record: dict) -> None:
        line = json.dumps(dict(study=args.study, start=args.start, **record))
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")

    if args.study == "ranking":
        seeds = range(args.first_seed, args.first_seed + args.gaits)
        for record in ranking(seeds, args.arch, args.contact, settled, args.environment, tuple(args.presets)):
            emit(record)
        return
    if args.study == "reference":
        for n in args.resolutions:
            emit(dict(dx=f"1/{n}", contact=args.contact,
                      **reference(args.environment, n, args.arch, args.seconds, args.contact, settled)))
        return
    if args.study == "offsets":
        for n in args.resolutions:
            for mu in args.frictions:
                emit(dict(dx=f"1/{n}", contact=args.contact,
                          **offsets(n, mu, args.fractions, args.arch, args.fine, args.contact, settled,
                                    args.environment)))
        return
    runs = ([dict(friction=mu, cfl=cfl) for mu in args.frictions for cfl in args.cfls] if args.study == "ground"
            else [dict(cfl=cfl) for cfl in args.cfls])
    for run in runs:
        for n in args.resolutions:
            measured = (ground(Setting(dx=1 / n, cfl=run["cfl"]), run["friction"], args.arch, contact=args.contact,
                               settled=settled)
                        if args.study == "ground" else floating(1 / n, run["cfl"], args.arch))
            emit(dict(dx=f"1/{n}", contact=args.contact, **run, **measured))


if __name__ == "__main__":
    main()
