"""Does a score depend on the number of substeps (issue 47)? Runs' best episodes replayed, the
travelling gait of docs/accuracy.md (1 s on robot_ground, stress-free or settled start), random
sine gaits of a recipe's body and an elastic ball's rebound, at the CFL number of the recipe (0.4)
and at a quarter and a sixteenth of it, for each contact and PIC setting.
Prints one JSON line per (source, setting) with the three returns (appended to --out);
docs/log/contact.md section 24 reads them.

    codesign run recipes/quickstart.yaml --run-dir runs/qs     # and cma_es, cppn_neat: the runs to replay
    python benchmarks/contact_steps.py runs/qs runs/cma --gait --out records.jsonl
    python benchmarks/contact_steps.py runs/qs --gait --settings "spring, pic_time" --terrain contact_stiffness=2e5
    python benchmarks/contact_steps.py --random-gaits 8 --recipe recipes/quickstart.yaml --dx 0.03125 0.0208333
    python benchmarks/contact_steps.py --gait --shapes --dx 0.03125 0.0208333 --settings nodes "spring, pic_time"
    python benchmarks/contact_steps.py --floating --dx 0.03125 0.0208333 --settings "nodes, pic_time"
"""
from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path
from unittest import mock

import numpy as np
from omegaconf import OmegaConf

from codesign.artifacts import play
from codesign.recipe import load_recipe
from codesign.runner import replay_best, set_up_parts
from codesign_mpm import BodySpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.reports.accuracy import Setting, gait, gait_distance, robot_env
from codesign_mpm.engine import Simulator

FACTORS = (1.0, 0.25, 0.0625)
SETTINGS = {  # label: (terrain.contact, environment.pic_time)
    "nodes": ("nodes", None),
    "nodes, pic_time": ("nodes", 0.265),
    "spring": ("spring", None),
    "spring, pic_time": ("spring", 0.265),
}


def replayed(run_dir: Path, contact: str, pic_time: float | None, terrain: dict, flip: float) -> list[float]:
    """The run's best episode's return at each CFL factor."""
    cfl = OmegaConf.load(run_dir / "config.yaml").environment.get("cfl") or 0.4
    return [replay_best(run_dir, 1, {"environment": {"cfl": cfl * f, "pic_time": pic_time, "flip": flip,
                                                     "terrain": {"contact": contact, **terrain}}})[0].episode_return
            for f in FACTORS]


def random_gait(recipe: Path, seed: int, dx: float, cfl: float, contact: str, pic_time: float | None,
                terrain: dict, flip: float) -> float:
    """The return of the recipe's environment and starting design under a sine gait drawn from
    `seed` (weights N(0, 1): up to the action bound), at `dx` and `cfl`."""
    overrides = [f"seed={seed}", "controller.name=sine", "controller.init_std=1.0", f"environment.dx={dx}",
                 f"environment.cfl={cfl}", f"environment.flip={flip}",
                 f"environment.pic_time={'null' if pic_time is None else pic_time}",
                 f"environment.terrain.contact={contact}", *(f"environment.terrain.{k}={v}" for k, v in terrain.items())]
    with set_up_parts(load_recipe(recipe, overrides)) as (parts, _):
        return play(parts.environment, parts.representation(), parts.controller, seed=0).episode_return


def rebound(cfl: float, contact: str, pic_time: float | None, terrain: dict, flip: float) -> float:
    """How high an elastic ball (radius 0.07, dropped from 0.28 above its rest) rises after its
    first bounce, above its height at rest."""
    scene = Scene(size=[1.0, 1.0, 0.5], dx=1 / 32, cfl=cfl, flip=flip, pic_time=pic_time,
                  terrain=TerrainSpec(height=0.2, friction=0.5, contact=contact, **terrain),
                  bodies=[BodySpec(shape=ShapeSpec(kind="sphere", radius=0.07), center=[0.5, 0.55, 0.25])])
    sim = Simulator(scene, build_particles(scene))
    try:
        mass = sim.particles.volume * sim.particles.density
        heights = []
        for _ in range(150):
            sim.step()
            heights.append(float(mass @ sim.particles_state()[0][:, 1] / mass.sum()))
    finally:
        sim.close()
    lowest = int(np.argmin(heights[:100]))
    return max(heights[lowest:]) - 0.27


def shape_drift(dx: float, contact: str, pic_time: float | None, terrain: dict, flip: float,
                amplitude: float = 0.3, frames: int = 125, floating: bool = False) -> dict:
    """The travelling gait on a frictionless floor (no propulsion: what moves is the body itself), or
    `floating` 0.15 above it with gravity 0 (no contact at all): how far the robot's shape (its
    particles about their centroid) moves from its start, and how far the shapes at cfl and cfl / 4,
    and at cfl / 4 and cfl / 16, lie apart (RMS over particles, mm; `*_unrotated`: after the best
    rotation of one onto the other), at frames 30, 60, 90 and 124; and the centroid's height at the end."""
    shapes, heights = [], []
    for factor in FACTORS:
        with _floating() if floating else contextlib.nullcontext():
            env = robot_env("ground", Setting(dx=dx, cfl=0.4 * factor), frames, friction=0.0, contact=contact,
                            pic_time=pic_time, flip=flip, terrain=terrain)
        try:
            env.reset()
            robot = env.particles.robot
            run = []
            for f in range(frames):
                env.step(gait(f, env.action_dim, amplitude=amplitude))
                x = env.sim.particles_state()[0][:len(robot)][robot].astype(np.float64)
                run.append(x - x.mean(0))
            shapes.append(np.array(run))
            heights.append(float(x.mean(0)[1]))
        finally:
            env.close()
    at = [30, 60, 90, frames - 1]

    def rms_mm(a: np.ndarray, b: np.ndarray, unrotate: bool = False) -> list[float]:
        return [round(1e3 * float(np.sqrt(((a[i] - (_rotated_onto(a[i], b[i]) if unrotate else b[i])) ** 2)
                                          .sum(1).mean())), 3) for i in at]

    start = np.broadcast_to(shapes[2][0], shapes[2].shape)
    return {"frames": at, "shape_motion_mm": rms_mm(shapes[2], start),
            "apart_quarter_mm": rms_mm(shapes[0], shapes[1]), "apart_sixteenth_mm": rms_mm(shapes[1], shapes[2]),
            "apart_quarter_unrotated_mm": rms_mm(shapes[0], shapes[1], True),
            "apart_sixteenth_unrotated_mm": rms_mm(shapes[1], shapes[2], True),
            "end_height_mm": [round(1e3 * h, 2) for h in heights]}


def _rotated_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Centred points b under the rotation that brings them closest to a (Kabsch)."""
    u, _, vt = np.linalg.svd(b.T @ a)
    return b @ (u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt)


@contextlib.contextmanager
def _floating():
    """Environments built inside have gravity 0 and the robot 0.15 above the terrain: the body's own
    motion without any contact (the environment has no key for either, so the scene is edited)."""
    import codesign_mpm.environment.env as env_module

    make_scene = env_module.make_scene

    def lifted(config, preset):
        scene = make_scene(config, preset)
        scene.gravity = [0.0, 0.0, 0.0]
        robot = scene.bodies[0]
        robot.rest_on_terrain = False
        robot.center = [robot.center[0], robot.center[1] + 0.15, robot.center[2]]
        return scene

    with mock.patch.object(env_module, "make_scene", lifted):
        yield


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path, help="run directories whose best episodes to replay")
    parser.add_argument("--gait", action="store_true", help="also the travelling gait, stress-free and settled, at "
                                                            "each --dx")
    parser.add_argument("--shapes", action="store_true", help="also the travelling gait's shape on a frictionless "
                                                              "floor at each --dx (shape_drift)")
    parser.add_argument("--floating", action="store_true", help="also the travelling gait's shape on a body floating "
                                                                "with gravity 0, no contact, at each --dx")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--terrain", nargs="*", default=[], metavar="KEY=VALUE",
                        help="more terrain keys for every setting, e.g. contact_stiffness=2e5 contact_damping=0.3")
    parser.add_argument("--flip", type=float, default=0.99, help="FLIP's share (per substep without pic_time)")
    parser.add_argument("--ball", action="store_true", help="also a dropped elastic ball's rebound")
    parser.add_argument("--random-gaits", type=int, default=0, metavar="N", help="also N random sine gaits")
    parser.add_argument("--recipe", type=Path, default=Path("recipes/quickstart.yaml"),
                        help="whose environment and starting design the random gaits play")
    parser.add_argument("--dx", type=float, nargs="+", default=[1 / 32], help="grids of the gaits")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    terrain = {key: float(value) for key, value in (item.split("=", 1) for item in args.terrain)}
    flip = args.flip
    sources = [(str(run), lambda c, p, run=run: replayed(run, c, p, terrain, flip)) for run in args.runs]
    if args.gait:
        sources += [(f"gait ({'settled' if settled else 'stress-free'})" + ("" if dx == 1 / 32 else f" at dx {dx:.4g}"),
                     lambda c, p, s=settled, dx=dx: [gait_distance(Setting(dx=dx, cfl=0.4 * f), contact=c, pic_time=p,
                                                                   terrain=terrain, flip=flip, settled=s)
                                                     for f in FACTORS])
                    for dx in args.dx for settled in (False, True)]
    sources += [(f"random gait {seed} at dx {dx:.4g}",
                 lambda c, p, seed=seed, dx=dx: [random_gait(args.recipe, seed, dx, 0.4 * f, c, p, terrain, flip)
                                                 for f in FACTORS])
                for dx in args.dx for seed in range(args.random_gaits)]
    if args.ball:
        sources.append(("ball rebound", lambda c, p: [rebound(0.4 * f, c, p, terrain, flip) for f in FACTORS]))
    for floating in [False] * args.shapes + [True] * args.floating:
        for dx in args.dx:
            for label in args.settings:
                emit({"source": f"shape, {'floating' if floating else 'frictionless'}, dx {dx:.4g}", "setting": label,
                      "terrain": terrain, "flip": flip, "cfl_factors": list(FACTORS),
                      **shape_drift(dx, *SETTINGS[label], terrain, flip, floating=floating)}, args.out)
    for source, measure in sources:
        for label in args.settings:
            started = time.perf_counter()
            values = measure(*SETTINGS[label])
            record = {"source": source, "setting": label, "terrain": terrain, "flip": flip, "cfl_factors": list(FACTORS),
                      "values": values,
                      "quarter": (values[1] - values[0]) / abs(values[0]),
                      "sixteenth_from_quarter": (values[2] - values[1]) / abs(values[1]),
                      "seconds": round(time.perf_counter() - started, 1)}
            emit(record, args.out)


def emit(record: dict, out: Path | None) -> None:
    print(json.dumps(record), flush=True)
    if out is not None:
        with out.open("a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
